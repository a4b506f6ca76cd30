"""``misdirect sweep``, and the options that put a command's work on a Dask cluster
(``--cluster ADDRESS``, ``--workers N``), declared once for sweep, solve, audit and harden."""

from __future__ import annotations

import signal
from pathlib import Path
from typing import Annotated, Any

import typer

from misdirect.cli.common import (
    INTERRUPTED,
    TERMINATED,
    ProgressBars,
    check_range,
    note,
    print_json,
    stop_gracefully,
    wrote,
)
from misdirect.cli.options import JsonOption
from misdirect.report import json_output

ClusterOption = Annotated[
    str | None,
    typer.Option(
        "--cluster",
        help="Run on the Dask scheduler at this address (tcp://host:8786); needs "
        "misdirect[cluster].",
        show_default=False,
    ),
]
WorkersOption = Annotated[
    int | None,
    typer.Option(
        "--workers",
        help="Run on a local Dask cluster of this many worker processes; needs misdirect[cluster].",
        show_default=False,
    ),
]
MAX_WORKERS = 1024


def check_workers(workers: int | None) -> None:
    if workers is not None:
        check_range("--workers", workers, 1, MAX_WORKERS)


def sweep(
    spec: Annotated[
        Path, typer.Argument(help="Sweep file (misdirect-sweep/v1, YAML).", show_default=False)
    ],
    out: Annotated[
        Path,
        typer.Option(
            "--output",
            "--out",
            "-o",
            help="Folder of the results table (results.csv, results.parquet).",
        ),
    ] = Path("sweep-results"),
    cluster: ClusterOption = None,
    workers: WorkersOption = None,
    as_json: JsonOption = False,
) -> None:
    """Many problems or generated scenarios × budgets × methods, one results table. Resumable:
    rows already in the table are skipped; each row says where it was computed."""
    from misdirect.distributed import connect, load_sweep, run_sweep

    check_workers(workers)
    loaded, folder = load_sweep(spec)
    with (
        ProgressBars(enabled=not as_json) as bars,
        connect(cluster, workers) as pool,
        stop_gracefully() as stop,
    ):

        def on_row(row: dict[str, Any], done: int, total: int) -> None:
            if bars is not None:
                detail = f"{row['instance']} b={row['budget']:g} {row['method']}: {row['status']}"
                bars.track("sweep", done, total, detail=detail)

        report = run_sweep(loaded, folder, out, pool=pool, on_row=on_row, cancel=stop.token)
    if as_json:
        written = [report.csv] + ([] if report.parquet is None else [report.parquet])
        print_json(
            json_output.document(
                "sweep",
                rows=len(report.rows),
                computed=report.computed,
                skipped=report.skipped,
                failed=report.failed,
                written=written,
                notes=report.notes,
            )
        )
    else:
        wrote(
            f"{report.computed} rows computed, {report.skipped} skipped (already done), "
            f"{report.failed} failed; wrote {report.csv}"
            + ("" if report.parquet is None else f" and {report.parquet}")
        )
        for text in report.notes:
            note(f"note: {text}")
    if stop.received:  # 130 after Ctrl-C, 143 after SIGTERM, as every other command
        raise typer.Exit(TERMINATED if stop.received[0] == signal.SIGTERM else INTERRUPTED)
    if report.failed:
        raise typer.Exit(1)
