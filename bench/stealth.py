"""Stealth on the paper's grid (issue 52): budgets 0..4 certified under the consistency
monitor, for ``--stealth`` and for each δ of ``--max-alarm 0,0.01,0.05,0.1,1``.

    python bench/stealth.py --out DIR [--top 4] [--time-limit 300] [--method auto]

The issue's target is all of it in under 5 s (2 cores). Reported per case (``plain``: no
monitor; ``stealth``; ``delta``: one solve of :func:`misdirect.solve_tradeoff` per δ, which
share what δ does not change) and per budget: status, exact value, Pr(alarm), proven bound,
and the case's wall time. Writes stealth.json and stealth.csv under --out, and
stealth_tradeoff.png (value against δ, one line per budget) when matplotlib is installed.
"""

from __future__ import annotations

import argparse
import csv
import json
import platform
import time
from pathlib import Path
from typing import Any

import misdirect
from misdirect.core.model import format_alteration
from misdirect.core.monitor import consistency_monitor, with_monitor
from misdirect.scenarios import paper_grid

DELTAS = (0.0, 0.01, 0.05, 0.1, 1.0)


def rows(case: str, delta: float | None, result: misdirect.SolveResult) -> list[dict[str, Any]]:
    """One row per budget of ``result``."""
    return [
        {
            "case": case,
            "max_alarm": delta,
            "budget": p.budget,
            "status": str(p.status),
            "value": p.probability,
            "alarm": p.alarm,
            "upper_bound": p.upper_bound,
            "alteration": format_alteration(p.alteration),
            "time_s": result.time_s,
        }
        for p in result.curve
    ]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--top", type=int, default=4, help="largest budget (default 4)")
    parser.add_argument("--time-limit", type=float, default=300.0, help="seconds per solve")
    parser.add_argument("--method", default="auto")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    grid = paper_grid(5)
    watched = with_monitor(grid, consistency_monitor(grid))
    budgets = list(range(args.top + 1))
    options = {"budgets": budgets, "method": args.method, "time_limit": args.time_limit}
    table: list[dict[str, Any]] = []
    walls: dict[str, float] = {}

    began = time.perf_counter()
    table += rows("plain", None, misdirect.solve(grid, **options))
    walls["plain"] = time.perf_counter() - began
    began = time.perf_counter()
    table += rows("stealth", None, misdirect.solve(watched, **options))
    walls["stealth"] = time.perf_counter() - began
    began = time.perf_counter()
    curves = misdirect.solve_tradeoff(watched, DELTAS, **options)
    walls["tradeoff"] = time.perf_counter() - began
    for delta, result in zip(DELTAS, curves, strict=True):
        table += rows("delta", delta, result)
        walls[f"delta={delta:g}"] = result.time_s

    summary = {
        "machine": platform.platform(),
        "method": args.method,
        "time_limit_s": args.time_limit,
        "budgets": budgets,
        "deltas": list(DELTAS),
        "wall_s": walls,
        "stealth_and_every_delta_s": walls["stealth"] + walls["tradeoff"],
        "target_s": 5.0,
        "all_optimal": all(r["status"] in ("optimal", "infeasible") for r in table),
        "rows": table,
    }
    (args.out / "stealth.json").write_text(json.dumps(summary, indent=2) + "\n")
    with (args.out / "stealth.csv").open("w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(table[0]))
        writer.writeheader()
        writer.writerows(table)
    try:
        from misdirect.report.figures import tradeoff_figure
    except ImportError:  # matplotlib is optional
        pass
    else:
        tradeoff_figure(curves, args.out / "stealth_tradeoff.png", title="paper grid 5x5")
    print(json.dumps({k: v for k, v in summary.items() if k != "rows"}, indent=2))


if __name__ == "__main__":
    main()
