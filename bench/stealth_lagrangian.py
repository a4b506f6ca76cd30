"""Does the Lagrangian node bound pay on the monitored paper grid? (issue 52)

    python bench/stealth_lagrangian.py --out DIR [--lambdas 100] [--rounds 2] [--top 4]

branch-and-bound alone, budgets 0..4 (``--top``) under the consistency monitor, for each δ of
``--max-alarm 0,0.01,0.05,0.1``, without and with the Lagrangian node bound
(:mod:`misdirect.solvers.engines.lagrangian`, λ from ``--lambdas``), alternating in one
process, ``rounds`` times: nodes per budget (the same search but for the extra pruning),
Lagrangian bounds asked for, wall and CPU seconds, and whether every point is certified at
the same value. Also the root: the relaxation's bound per budget against the smallest
Lagrangian root bound over a grid of λ, and the λ that attains it. Writes
stealth_lagrangian.json and .md under --out.
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path
from typing import Any

import numpy as np

import misdirect
from misdirect.core.attack import prepare
from misdirect.core.monitor import consistency_monitor, with_monitor
from misdirect.scenarios import paper_grid
from misdirect.solvers import branch_and_bound
from misdirect.solvers.engines import lagrangian
from misdirect.solvers.engines.alarm import alarm_constraint
from misdirect.solvers.engines.per_state import PerStateRelaxation

DELTAS = (0.0, 0.01, 0.05, 0.1)
BUDGETS = [0, 1, 2, 3, 4]  # --top sets the largest
ROOT_GRID = (0.0, 0.1, 0.3, 1.0, 3.0, 10.0, 30.0, 100.0)


def curve(watched: misdirect.Problem, delta: float, lambdas: tuple[float, ...]) -> dict[str, Any]:
    """One δ's curve by branch-and-bound with ``lambdas`` (empty: no Lagrangian bound)."""
    branch_and_bound.LAGRANGE_MULTIPLIERS = lambdas
    asked = []
    original = lagrangian.LagrangianBound.bound

    def counted(self: lagrangian.LagrangianBound, *args: Any, **kwargs: Any) -> float:
        asked.append(1)
        return original(self, *args, **kwargs)

    lagrangian.LagrangianBound.bound = counted  # type: ignore[method-assign]
    try:
        wall, cpu = time.perf_counter(), time.process_time()
        result = misdirect.solve(
            watched, budgets=BUDGETS, method="branch-and-bound", max_alarm=delta, time_limit=300
        )
        wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
    finally:
        lagrangian.LagrangianBound.bound = original  # type: ignore[method-assign]
        branch_and_bound.LAGRANGE_MULTIPLIERS = ()
    return {
        "delta": delta,
        "lambdas": list(lambdas),
        "wall_s": round(wall, 3),
        "cpu_s": round(cpu, 3),
        "nodes": [getattr(p.stats, "nodes", None) for p in result.curve],
        "lagrangian_bounds": len(asked),
        "values": [p.probability for p in result.curve],
        "certified": all(str(p.status) == "optimal" for p in result.curve),
    }


def roots(watched: misdirect.Problem) -> list[dict[str, Any]]:
    """Per budget and δ: the relaxation's root bound and the best Lagrangian root bound."""
    constraint = alarm_constraint(watched, 0.0)
    problem = constraint.decoy_problem
    instance = prepare(problem, max(BUDGETS))
    relax = PerStateRelaxation(problem, instance.space, instance.chain, instance.cycling)
    start = relax.best_groups(relax.live_groups.astype(np.float64))[0]
    rows = []
    for budget in BUDGETS:
        cap = instance.space.scale.cap(budget)
        allowed = relax.allowed_groups(relax.allowed_options((), cap))
        own, _, policy = relax.optimise(allowed, start.copy())
        for delta in DELTAS:
            found = []
            for lam in ROOT_GRID:
                bound = lagrangian.lagrangian_bound(relax, instance.cycling, delta, (lam,))
                assert bound is not None, "the grid's chain has no end components"
                found.append(bound.bound(allowed, policy))
            best = int(np.argmin(found))
            rows.append(
                {
                    "budget": budget,
                    "delta": delta,
                    "relaxation": own,
                    "lagrangian": found[best],
                    "lambda": ROOT_GRID[best],
                }
            )
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--lambdas", type=float, nargs="+", default=[100.0])
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--top", type=int, default=4, help="largest budget (default 4)")
    args = parser.parse_args()
    BUDGETS[:] = range(args.top + 1)
    args.out.mkdir(parents=True, exist_ok=True)
    grid = paper_grid(5)
    watched = with_monitor(grid, consistency_monitor(grid))
    misdirect.solve(grid, budgets=[0, 1], method="branch-and-bound")  # warm the process
    runs = []
    for _ in range(args.rounds):
        for delta in DELTAS:
            for lambdas in ((), tuple(args.lambdas)):
                row = curve(watched, delta, lambdas)
                print(json.dumps(row), flush=True)
                runs.append(row)
    root = roots(watched)
    document = {"machine": platform.platform(), "runs": runs, "roots": root}
    (args.out / "stealth_lagrangian.json").write_text(json.dumps(document, indent=1) + "\n")
    lines = [
        "# Lagrangian node bound on the monitored paper grid",
        "",
        f"Machine: {platform.platform()}. branch-and-bound, budgets 0..{args.top}; λ = "
        f"{', '.join(f'{lam:g}' for lam in args.lambdas)}.",
        "",
        "| δ | Lagrangian | nodes per budget | nodes | bounds | wall s | CPU s | certified |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for row in runs:
        nodes = row["nodes"]
        lines.append(
            f"| {row['delta']:g} | {'on' if row['lambdas'] else 'off'} | "
            f"{', '.join(str(n) for n in nodes)} | {sum(n or 0 for n in nodes)} | "
            f"{row['lagrangian_bounds']} | {row['wall_s']:.2f} | {row['cpu_s']:.2f} | "
            f"{'yes' if row['certified'] else 'no'} |"
        )
    lines += ["", "| budget | δ | relaxation's root bound | best Lagrangian root bound | λ |"]
    lines += ["|---|---|---|---|---|"]
    for row in root:
        lines.append(
            f"| {row['budget']} | {row['delta']:g} | {row['relaxation']:.4f} | "
            f"{row['lagrangian']:.4f} | {row['lambda']:g} |"
        )
    (args.out / "stealth_lagrangian.md").write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
