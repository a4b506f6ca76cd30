"""misdirect reproduce: the paper's experiments, ours beside its numbers."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer
from rich.markup import escape
from rich.table import Table

from misdirect.cli.common import ProgressBars, check_seconds, out, print_json
from misdirect.cli.options import MAX_GRID_SIZE, JsonOption
from misdirect.errors import ProblemError
from misdirect.io.files import prepare_output_dir
from misdirect.report import json_output
from misdirect.solvers.milp.backends import BACKENDS

if TYPE_CHECKING:
    from misdirect.report.reproduce import ReproduceReport


def reproduce(
    out_dir: Annotated[
        Path,
        typer.Option("--output", "--out", "-o", help="Folder for tables, figures and report.md."),
    ] = Path("results"),
    quick: Annotated[
        bool,
        typer.Option(
            "--quick/--full",
            help="Quick: grids 5, 15, 25 and 60 s limits; full: up to 45 and 10 min.",
        ),
    ] = True,
    solver: Annotated[str, typer.Option(help=f"MILP backend: {', '.join(BACKENDS)}.")] = "highs",
    time_limit: Annotated[
        float | None, typer.Option(help="Seconds per MILP solve (default 60 quick, 600 full).")
    ] = None,
    sizes: Annotated[
        str | None, typer.Option(help="Grid sizes of the scalability study, e.g. 5,15,25.")
    ] = None,
    as_json: JsonOption = False,
) -> None:
    """Run the paper's experiments (Section VII) and write its tables and figures beside ours."""
    from misdirect.report.reproduce import reproduce as run_reproduce

    size_list = _parse_sizes(sizes)
    check_seconds(time_limit)
    prepare_output_dir(out_dir, field="--out")
    with ProgressBars(enabled=not as_json) as bars:
        progress = bars.track if bars else None
        report = run_reproduce(
            out_dir,
            quick=quick,
            solver=solver,
            time_limit=time_limit,
            sizes=size_list,
            progress=progress,
        )
    if as_json:
        print_json(_report_payload(report))
    else:
        _print_report(report)


def _parse_sizes(sizes: str | None) -> list[int] | None:
    """``--sizes 5,15,25``: grid sizes between 5 and the largest grid."""
    if sizes is None:
        return None
    try:
        size_list = [int(part) for part in sizes.split(",") if part.strip()]
    except ValueError:
        raise ProblemError(f"expected sizes like 5,15,25, got {sizes!r}", field="--sizes") from None
    if not size_list or min(size_list) < 5:
        raise ProblemError("grid sizes must be at least 5", field="--sizes")
    if max(size_list) > MAX_GRID_SIZE:
        raise ProblemError(f"grid sizes must be at most {MAX_GRID_SIZE:,}", field="--sizes")
    return size_list


def _report_payload(report: ReproduceReport) -> dict[str, object]:
    """The tables and figures by name (relative to ``out``), and every file written."""
    names = [f"{name}{suffix}" for name in report.tables for suffix in (".csv", ".md")]
    names += [p.name for paths in report.figures.values() for p in paths]
    written = [report.out / name for name in names if (report.out / name).exists()]
    if (report.out / "report.md").exists():
        written.append(report.out / "report.md")
    return json_output.document(
        "reproduce",
        out=str(report.out),
        mode=report.mode,
        time_s=report.time_s,
        summary=report.summary,
        tables={name: f"{name}.csv" for name in report.tables},
        figures={name: [p.name for p in paths] for name, paths in report.figures.items()},
        written=written,
    )


def _print_report(report: ReproduceReport) -> None:
    out.print(escape(f"misdirect reproduce ({report.mode}): ours beside the paper"), style="bold")
    table = Table.grid(padding=(0, 1))
    table.add_column(style="dim", no_wrap=True)
    table.add_column(overflow="fold")
    for row in report.summary:
        agrees = row["agrees"]
        colour = "green" if agrees == "yes" else ("red" if agrees == "NO" else "yellow")
        table.add_row("", "")
        table.add_row(
            f"[bold]{escape(row['experiment'])}[/]", f"agrees: [{colour}]{escape(agrees)}[/]"
        )
        table.add_row("  ours", escape(row["ours"]))
        table.add_row("  paper", escape(row["paper"]))
        for note in row.get("notes", []):
            flagged = note.startswith(("UNVERIFIED", "timed out"))
            table.add_row("  note", f"[bold red]{escape(note)}[/]" if flagged else escape(note))
    out.print(table)
    out.print(
        escape(f"{report.time_s:.1f} s; tables, figures and report.md in {report.out}/"),
        highlight=False,
    )
