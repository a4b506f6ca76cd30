"""The enumeration's kernel against the machine's peak (issue 50).

The low-rank enumeration values each alteration by bordering its parent's Woodbury system
(``solvers.engines.lowrank_updates.add_corrections``): per batch of parents one stack of
products ``A⁻¹ D W(P, ·)`` (BLAS), then per child a Schur complement as wide as its last
sensor's rows (a compiled loop). This runs the 64-sensor turn-back grid's budgets 0..3 by
``method="incremental"`` (2.7 million alterations) and reports, in the same process:

* the kernel's wall time (every ``add_corrections`` call), the alterations it valued, and the
  time per alteration per core;
* its arithmetic, counted from the shapes it was given (the parents' products, each child's
  Schur complement, its elimination), as a rate against the peak of one core (a 2048x2048
  matrix product on one BLAS thread, the best of three);
* the whole solve's wall time.

    .venv/bin/python bench/enumeration_kernel.py --out results/bench [--quick]

The before/after ratio of the same solve on two source trees is ``bench/compare_trees.py
--only enumeration``. Writes enumeration_kernel.json and .md under --out.
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import numpy as np

import misdirect
from misdirect.core.blas import one_blas_thread
from misdirect.scenarios.sensor_grid import sensor_grid
from misdirect.solvers.engines import lowrank, lowrank_updates

CASE = ("turn-back n=40 k=64", {"n": 40, "sensors": 64, "goal": "inside"}, 3)
QUICK = ("turn-back n=10 k=8", {"n": 10, "sensors": 8, "goal": "inside"}, 2)


def peak_gflops(size: int = 2048) -> float:
    """One core's double-precision rate on a large matrix product (best of three)."""
    rng = np.random.default_rng(0)
    a, b = rng.random((size, size)), rng.random((size, size))
    best = np.inf
    with one_blas_thread():
        for _ in range(3):
            began = time.perf_counter()
            a @ b
            best = min(best, time.perf_counter() - began)
    return 2 * size**3 / best / 1e9


def run(case: tuple) -> dict:
    label, parameters, top = case
    problem = sensor_grid(**parameters)
    counted = {"kernel_s": 0.0, "alterations": 0, "flops": 0.0, "calls": 0}
    add_corrections, children_of = lowrank.add_corrections, lowrank_updates._children_of

    def timed_add(found, altered, *args, **kwargs):
        began = time.perf_counter()
        try:
            return add_corrections(found, altered, *args, **kwargs)
        finally:
            counted["kernel_s"] += time.perf_counter() - began
            counted["alterations"] += int(altered.costs.size)
            counted["calls"] += 1

    def counted_children(parents, kids, local, tree, deltas, weight, compiled=True):
        wp = tree.width[parents].astype(float)  # each parent's system, before padding
        last = tree.first_entry[kids] + tree.depth[kids] - 1
        w = tree.entry_width[last].astype(float)  # each child's last entry
        later = float(deltas.d_w.shape[1])  # at most this many columns per parent
        flops = 2 * (wp**3 + wp**2 * later).sum()  # the inverse and the products
        flops += (2 * w**2 * wp[local] + 4 * w * wp[local] + 2 * w**3 / 3).sum()
        counted["flops"] += float(flops)
        return children_of(parents, kids, local, tree, deltas, weight, compiled)

    lowrank.add_corrections = timed_add
    lowrank_updates._children_of = counted_children
    try:
        began = time.perf_counter()
        result = misdirect.solve(problem, budgets=range(top + 1), method="incremental")
        wall = time.perf_counter() - began
    finally:
        lowrank.add_corrections = add_corrections
        lowrank_updates._children_of = children_of
    threads = lowrank.DEFAULT_THREADS
    return {
        "label": label,
        "top_budget": top,
        "status": str(result.status),
        "value": result.probability,
        "solve_s": wall,
        "kernel_s": counted["kernel_s"],
        "alterations": counted["alterations"],
        "threads": threads,
        "us_per_alteration_core": 1e6
        * counted["kernel_s"]
        * threads
        / max(counted["alterations"], 1),
        "kernel_gflops": counted["flops"] / max(counted["kernel_s"], 1e-9) / 1e9,
    }


def markdown(row: dict, peak: float) -> str:
    share = row["kernel_gflops"] / (peak * row["threads"])
    return (
        "| case | solve | kernel | alterations | per alteration and core | kernel rate | "
        "peak (cores) | share of peak |\n|---|---|---|---|---|---|---|---|\n"
        f"| {row['label']} B0..{row['top_budget']} | {row['solve_s']:.1f} s | "
        f"{row['kernel_s']:.1f} s | {row['alterations']:,} | "
        f"{row['us_per_alteration_core']:.2f} µs | {row['kernel_gflops']:.2f} GFlop/s | "
        f"{peak:.1f} GFlop/s x {row['threads']} | {100 * share:.1f} % |\n"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("results/bench"))
    parser.add_argument("--quick", action="store_true", help="a small grid (the test suite)")
    args = parser.parse_args()
    peak = peak_gflops(512 if args.quick else 2048)
    row = run(QUICK if args.quick else CASE)
    document = {"machine": platform.processor() or platform.machine(), "peak_gflops": peak}
    document.update(row)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "enumeration_kernel.json").write_text(json.dumps(document, indent=2) + "\n")
    table = markdown(row, peak)
    (args.out / "enumeration_kernel.md").write_text(table)
    print(table)


if __name__ == "__main__":
    main()
