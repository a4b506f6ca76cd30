"""The covering bound at the root of a turn-back grid (issue 50): a bound below 1.0 where the
relaxation with every sensor free reads 1.0.

Sensors are dealt into stratified groups by their single-alteration strength (the best exact
value of altering that sensor alone), and the root's covering bound at each budget is the
largest of the unions' relaxations (:mod:`misdirect.solvers.engines.covering`); a union above
the optimum is refined once (its groups split in halves).

Then the search: branch-and-bound on smaller turn-back grids with the covers of its nodes
(:class:`~misdirect.solvers.engines.covering.CoverRule`) and without, in the same process, to
the same time limit: status, bound and seconds of each.

    .venv/bin/python bench/covering_bound.py --out results/bench [--quick] [--refine-depth 2]
        [--budgets 3] [--no-search]

A union whose proof still fails after its splits is valued alteration by alteration where it
is small (``covering.MAX_ENUMERATED``).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from misdirect import decoy_probability
from misdirect.core.attack import prepare
from misdirect.scenarios.sensor_grid import sensor_grid
from misdirect.solvers.engines.covering import covering_bound, stratified_groups
from misdirect.solvers.engines.per_state import PerStateRelaxation, relaxation_bound

# (label, grid, budgets, groups, the optimum at each budget where known: bench/results/cycles)
# (budget 1's optimum is the strongest single alteration: with unit costs each fits it)
CASES = [("turn-back n=40 k=64", (40, 64), [1, 2, 3], 16, {2: 0.682159, 3: 0.792177})]
QUICK = [("turn-back n=12 k=16", (12, 16), [1, 2], 4, {})]
# (label, grid, budget, groups): a root cover in one process and in two
WORKERS = [("turn-back n=40 k=64", (40, 64), 2, 16)]
QUICK_WORKERS = [("turn-back n=12 k=16", (12, 16), 2, 12)]
# (label, grid, budget, time limit): branch-and-bound with covers and without
SEARCHES = [
    ("turn-back n=10 k=12", (10, 12), 2, 60.0),
    ("turn-back n=12 k=16", (12, 16), 2, 60.0),
    ("turn-back n=12 k=16", (12, 16), 3, 120.0),
]
QUICK_SEARCHES = [("turn-back n=8 k=8", (8, 8), 1, 20.0)]


def strengths(problem, space) -> np.ndarray:
    """Per choice: the best exact value of altering it alone (its strongest option)."""
    best = np.zeros(len(space.choices))
    for i, choice in enumerate(space.choices):
        for k in range(1, choice.size):
            picked = np.zeros(len(space.choices), dtype=np.int64)
            picked[i] = k
            best[i] = max(best[i], decoy_probability(problem, space.alteration(problem, picked)))
    return best


def run_case(
    label, grid, budgets, n_groups, optimum, depth: int = 1, only: list[int] | None = None
) -> list[dict]:
    problem = sensor_grid(*grid, goal="inside")
    top = max(budgets)
    instance = prepare(problem, top)
    relax = PerStateRelaxation(problem, instance.space, instance.chain, instance.cycling)
    began = time.perf_counter()
    strength = strengths(problem, instance.space)
    strength_s = time.perf_counter() - began
    groups = stratified_groups(range(len(instance.space.choices)), n_groups, strength)
    optimum = {1: float(strength.max()), **optimum}
    rows = []
    for budget in budgets if only is None else [b for b in budgets if b in only]:
        began = time.perf_counter()
        all_free = relaxation_bound(problem, budget)
        all_free_s = time.perf_counter() - began
        began = time.perf_counter()
        # unions above the optimum split into halves (the bound holds for any threshold)
        threshold = optimum.get(budget, np.inf)
        found = covering_bound(
            relax,
            groups,
            instance.space.scale.cap(budget),
            refine_above=threshold,
            refine_depth=depth,
        )
        assert found is not None
        rows.append(
            {
                "label": label,
                "budget": budget,
                "groups": n_groups,
                "unions": len(found.unions),
                "covering_bound": found.bound,
                "all_free_bound": all_free,
                "optimum": optimum.get(budget),
                "unions_above_optimum": sum(
                    b > optimum.get(budget, np.inf) for _, b in found.unions
                ),
                "unions_refined": found.refined,
                "refine_depth": depth,
                "unions_enumerated": found.enumerated,
                "covering_s": time.perf_counter() - began,
                "all_free_s": all_free_s,
                "strengths_s": strength_s,
            }
        )
    return rows


def worker_rows(label, grid, budget, n_groups, repeats: int = 2) -> list[dict]:
    """The root cover of one budget with its unions in one process and shared among two
    forked ones (``workers``), alternated ``repeats`` times in this process: wall and CPU
    seconds (the children's CPU counted once they are reaped)."""
    problem = sensor_grid(*grid, goal="inside")
    instance = prepare(problem, budget)
    relax = PerStateRelaxation(problem, instance.space, instance.chain, instance.cycling)
    strength = strengths(problem, instance.space)
    groups = stratified_groups(range(len(instance.space.choices)), n_groups, strength)
    cap = instance.space.scale.cap(budget)
    rows = []
    for _ in range(repeats):
        for workers in (1, 2):
            began, cpu = time.perf_counter(), _cpu()
            found = covering_bound(relax, groups, cap, refine_depth=0, workers=workers)
            wall = time.perf_counter() - began
            time.sleep(0.5)  # the children reaped, so that their CPU is counted
            assert found is not None
            rows.append(
                {
                    "label": label,
                    "budget": budget,
                    "groups": n_groups,
                    "workers": workers,
                    "unions": len(found.unions),
                    "bound": found.bound,
                    "wall_s": wall,
                    "cpu_s": _cpu() - cpu,
                }
            )
    return rows


def _cpu() -> float:
    """CPU seconds of this process and of its reaped children."""
    import resource

    own, children = (
        resource.getrusage(who) for who in (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN)
    )
    return own.ru_utime + own.ru_stime + children.ru_utime + children.ru_stime


def worker_markdown(rows: list[dict]) -> str:
    lines = [
        "",
        "## A cover's unions in one process and in two (same process, alternated)",
        "",
        "| chain | budget | groups | unions | workers | bound | wall (s) | CPU (s) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['label']} | {r['budget']} | {r['groups']} | {r['unions']} | {r['workers']} "
            f"| {r['bound']:.6f} | {r['wall_s']:.1f} | {r['cpu_s']:.1f} |"
        )
    return "\n".join(lines) + "\n"


def search_rows(label, grid, budget, limit) -> list[dict]:
    """Branch-and-bound on one budget, covers on (as the rule says) and off."""
    from misdirect.solvers.branch_and_bound import BranchAndBoundSolver
    from misdirect.solvers.engines.covering import CoverRule
    from misdirect.solvers.options import SolveOptions

    problem = sensor_grid(*grid, goal="inside")
    rows = []
    applies = CoverRule.applies
    for covers in (True, False):
        CoverRule.applies = staticmethod(lambda cycling, on=covers: on and applies(cycling))
        try:
            began = time.perf_counter()
            solver = BranchAndBoundSolver(SolveOptions(time_limit=limit))
            answer = solver.solve(problem, [budget])[0]
            seconds = time.perf_counter() - began
        finally:
            CoverRule.applies = staticmethod(applies)
        stats = answer.stats
        rows.append(
            {
                "label": label,
                "budget": budget,
                "covers": covers,
                "limit_s": limit,
                "status": str(answer.status),
                "value": answer.solver_probability,
                "bound": answer.upper_bound,
                "nodes": stats.nodes,
                "covered_nodes": stats.covers,
                "cover_unions": stats.cover_unions,
                "cover_pruned": stats.cover_pruned,
                "seconds": seconds,
            }
        )
    return rows


def search_markdown(rows: list[dict]) -> str:
    lines = [
        "",
        "## Branch-and-bound with covers and without (same process, same limit)",
        "",
        "| chain | budget | covers | status | value | bound | nodes | covered | unions "
        "| pruned by a cover | seconds |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['label']} | {r['budget']} | {'on' if r['covers'] else 'off'} | {r['status']} "
            f"| {r['value']:.6f} | {r['bound']:.6f} | {r['nodes']} | {r['covered_nodes']} "
            f"| {r['cover_unions']} | {r['cover_pruned']} | {r['seconds']:.1f} |"
        )
    return "\n".join(lines) + "\n"


def markdown(rows: list[dict]) -> str:
    lines = [
        "# The covering bound at the root (issue 50)",
        "",
        "| chain | budget | groups | unions | covering bound | every sensor free | optimum "
        "| unions above it (refined, depth) | enumerated | seconds |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        optimum = "" if r["optimum"] is None else f"{r['optimum']:.6f}"
        lines.append(
            f"| {r['label']} | {r['budget']} | {r['groups']} | {r['unions']} "
            f"| {r['covering_bound']:.6f} | {r['all_free_bound']:.6f} | {optimum} "
            f"| {r['unions_above_optimum']} ({r['unions_refined']}, {r['refine_depth']}) "
            f"| {r['unions_enumerated']} | {r['covering_s']:.1f} |"
        )
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("results/bench"))
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--refine-depth", type=int, default=1, help="splits of a union above")
    parser.add_argument("--budgets", type=int, nargs="*", help="only these budgets of the root")
    parser.add_argument("--no-search", action="store_true", help="the root's covers only")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    cases = QUICK if args.quick else CASES
    rows = [r for case in cases for r in run_case(*case, args.refine_depth, args.budgets)]
    searches = [] if args.no_search else QUICK_SEARCHES if args.quick else SEARCHES
    found = [r for case in searches for r in search_rows(*case)]
    shared = [r for case in (QUICK_WORKERS if args.quick else WORKERS) for r in worker_rows(*case)]
    (args.out / "covering_bound.json").write_text(
        json.dumps({"root": rows, "search": found, "workers": shared}, indent=1)
    )
    text = markdown(rows) + search_markdown(found) + worker_markdown(shared)
    (args.out / "covering_bound.md").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
