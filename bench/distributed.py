"""Past one machine: the speedup of a sweep and of a distributed solve against Dask workers
on this machine (1 and 2), each task's cost and its communication, and from those figures a
projection to 8, 32 and 128 workers (docs/distributed.md reads it).

    python bench/distributed.py [--out bench/results] [--quick]

Sweep: rows of sensor grids × budgets (``--quick``: random 10-state problems), branch-and-bound,
in this process, then on
a LocalCluster of 1 and of 2 worker processes. Per task: its compute time (the row's
``time_s``, measured on the worker) and its overhead (wall time of the 1-worker run less the
sum of compute times, per task: scheduling, pickling, the round trip). Solve: the segment
search of one sensor grid split into subtrees (enumeration off, so that the tree is the work),
locally and on 1 and 2 workers, with each task's seconds and the size of what it sent back.

Projection (per kind of work): with ``N`` tasks of mean cost ``c``, overhead ``o`` each
(serialised at the scheduler), a serial part ``s`` (the coordinator's, e.g. the frontier) and
the longest task ``m``, ``T(P) = s + max(N c / P, N o, m)``; speedup ``T(1) / T(P)``.
"""

from __future__ import annotations

import argparse
import json
import os
import pickle
import platform
import statistics
import sys
import tempfile
import textwrap
import time
from pathlib import Path

# this file's folder first on the path would make it the package ``distributed``
HERE = Path(__file__).resolve().parent
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != HERE]
sys.path.insert(0, str(HERE.parent / "src"))

SPEC = """
scenarios:
  - scenario: random
    parameters: {{states: 10, observations: 6}}
    seeds: {seeds}
budgets: [1, 2, 3]
methods: [branch-and-bound]
"""
# rows of seconds, not milliseconds: the kind of row a sweep is for
SPEC_FULL = """
scenarios:
  - scenario: sensor-grid
    parameters: {{n: 20, sensors: 16}}
    seeds: {seeds}
budgets: [3, 4]
methods: [branch-and-bound]
"""


def _cluster(workers: int):
    import distributed

    cluster = distributed.LocalCluster(
        n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=":0"
    )
    return cluster, distributed.Client(cluster)


def bench_sweep(seeds: int, spec: str = SPEC) -> dict:
    from misdirect.distributed import DaskPool, load_sweep, run_sweep

    folder = Path(tempfile.mkdtemp())
    (folder / "s.yaml").write_text(textwrap.dedent(spec.format(seeds=list(range(seeds)))))
    spec, where = load_sweep(folder / "s.yaml")
    runs = {}
    began = time.perf_counter()
    local = run_sweep(spec, where, folder / "local")
    runs["local"] = time.perf_counter() - began
    compute = [r["time_s"] for r in local.rows]
    for workers in (1, 2):
        cluster, client = _cluster(workers)
        with cluster, client:
            pool = DaskPool(client)
            client.run(lambda: __import__("misdirect.solvers.run"))  # imports paid before
            began = time.perf_counter()
            report = run_sweep(spec, where, folder / f"w{workers}", pool=pool)
            runs[f"workers_{workers}"] = time.perf_counter() - began
            if workers == 1:
                compute_remote = [r["time_s"] for r in report.rows]
    n = len(compute)
    overhead = max(runs["workers_1"] - sum(compute_remote), 0.0) / n
    return {
        "tasks": n,
        "wall_s": runs,
        "task_s_mean": statistics.mean(compute_remote),
        "task_s_max": max(compute_remote),
        "task_s_local_mean": statistics.mean(compute),
        "overhead_s_per_task": overhead,
        "serial_s": 0.0,
        "speedup_2": runs["workers_1"] / runs["workers_2"],
    }


def bench_solve(n: int, sensors: int, budget: float) -> dict:
    from misdirect import scenarios
    from misdirect.core.attack import prepare
    from misdirect.distributed import DaskPool
    from misdirect.solvers.engines.per_state import PerStateRelaxation
    from misdirect.solvers.engines.segment_relaxation import SegmentRelaxation
    from misdirect.solvers.engines.segment_search import SegmentSearch
    from misdirect.solvers.engines.subtrees import DistributedSegmentSearch

    problem = scenarios.sensor_grid(n, sensors, seed=0, budget=budget)

    def relaxation():
        instance = prepare(problem, budget)
        relax = PerStateRelaxation(problem, instance.space, instance.chain)
        return SegmentRelaxation(instance, relax, threads=1)

    began = time.perf_counter()
    local = SegmentSearch(relaxation(), budget)
    status = local.run()
    runs = {"local": time.perf_counter() - began}
    out = {"instance": f"sensor_grid({n}, {sensors}, seed=0), budget {budget:g}"}
    out["local"] = {"status": str(status), "value": local.best_value, "nodes": local.nodes}
    for workers in (1, 2):
        cluster, client = _cluster(workers)
        with cluster, client:
            pool = DaskPool(client)
            began = time.perf_counter()
            seg = relaxation()
            search = DistributedSegmentSearch(
                seg, budget, pool, problem=pool.share(problem), max_budget=budget
            )
            status = search.run()
            runs[f"workers_{workers}"] = time.perf_counter() - began
            tasks = search.tasks
            out[f"workers_{workers}"] = {
                "status": str(status),
                "value": search.best_value,
                "bound": search.open_bound(),
                "tasks": len(tasks),
                "nodes": search.nodes,
                "coordinator_nodes": search.local.nodes,
            }
            if workers == 1:
                seconds = [t.seconds for t in tasks]
                sent = [len(pickle.dumps(t)) for t in tasks]
                busy = sum(seconds)
                first = {
                    "task_s_mean": statistics.mean(seconds) if seconds else 0.0,
                    "task_s_max": max(seconds, default=0.0),
                    "result_bytes_mean": statistics.mean(sent) if sent else 0.0,
                    "problem_bytes": len(pickle.dumps(problem)),
                    "tasks": len(tasks),
                    "wall_1": runs["workers_1"],
                    "busy_1": busy,
                }
    serial = first["wall_1"] - first["busy_1"]  # the coordinator's, and the round trips
    out.update(
        wall_s=runs,
        tasks=first["tasks"],
        task_s_mean=first["task_s_mean"],
        task_s_max=first["task_s_max"],
        result_bytes_mean=first["result_bytes_mean"],
        problem_bytes=first["problem_bytes"],
        serial_s=max(serial, 0.0),
        overhead_s_per_task=0.0,
        speedup_2=runs["workers_1"] / runs["workers_2"],
    )
    return out


def project(figures: dict, workers: int) -> float:
    """Speedup at ``workers`` from the measured figures (module docstring)."""
    n, c, o = figures["tasks"], figures["task_s_mean"], figures["overhead_s_per_task"]
    s, m = figures["serial_s"], figures["task_s_max"]

    def wall(p: int) -> float:
        return s + max(n * c / p, n * o, m)

    return wall(1) / wall(workers)


def tables(result: dict) -> list[str]:
    """The markdown of ``distributed.md``: the figures, then the search's work per run (a
    split search that visits more nodes than the local one gains less than its workers)."""
    sweep, solve = result["sweep"], result["solve"]
    lines = ["# Distributed: measured on this machine, projected beyond it", ""]
    lines += [
        "| work | tasks | mean task s | overhead/task s | serial s | local s | 1 worker s "
        "| 2 workers s | speedup 2 | proj. 8 | proj. 32 | proj. 128 |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for name, f in (("sweep", sweep), ("solve", solve)):
        w, p = f["wall_s"], {int(k): v for k, v in f["projected_speedup"].items()}
        lines.append(
            f"| {name} | {f['tasks']} | {f['task_s_mean']:.3f} | {f['overhead_s_per_task']:.4f} "
            f"| {f['serial_s']:.2f} | {w['local']:.2f} | {w['workers_1']:.2f} "
            f"| {w['workers_2']:.2f} | {f['speedup_2']:.2f} | {p[8]:.1f} | {p[32]:.1f} "
            f"| {p[128]:.1f} |"
        )
    lines += ["", f"Search: {solve['instance']}", ""]
    lines += [
        "| run | status | nodes | tasks | wall s | against local |",
        "|---|---|---|---|---|---|",
    ]
    local, local_s = solve["local"], solve["wall_s"]["local"]
    lines.append(f"| local | {local['status']} | {local['nodes']} | - | {local_s:.2f} | 1.00 |")
    for workers in (1, 2):
        run = solve[f"workers_{workers}"]
        wall = solve["wall_s"][f"workers_{workers}"]
        lines.append(
            f"| {workers} worker{'s' if workers > 1 else ''} | {run['status']} | {run['nodes']} "
            f"| {run['tasks']} | {wall:.2f} | {solve['wall_s']['local'] / wall:.2f} |"
        )
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("bench/results"))
    parser.add_argument("--quick", action="store_true")
    args = parser.parse_args()
    sweep = bench_sweep(4) if args.quick else bench_sweep(4, SPEC_FULL)
    solve = bench_solve(8, 6, 3) if args.quick else bench_solve(20, 16, 6)
    for figures in (sweep, solve):
        figures["projected_speedup"] = {p: project(figures, p) for p in (1, 2, 8, 32, 128)}
    result = {
        "machine": {"cpus": os.cpu_count(), "python": platform.python_version()},
        "sweep": sweep,
        "solve": solve,
    }
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "distributed.json").write_text(json.dumps(result, indent=2) + "\n")
    lines = tables(result)
    (args.out / "distributed.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
