"""Robust controllers (issue 54) beyond the paper's grid: a drone model and a turn-back grid.

    python bench/robust_large.py [--out bench/results] [--quick] [--time-limit 600]

Per case, ``robust_controller(problem, B, memory=k, randomized=True, objective="decoy",
min_goal=q, baselines=("given", "blind"))`` (4 starts a round, seed 0): the certified
worst-case Pr(decoy) of the controller found (the oracle's, for that very controller) against
the nominal (given) controller's and the best observation-blind one's, with the nominal
Pr(goal) of each. The floor ``q`` keeps the question from being trivial (without it a
controller that goes nowhere never reaches the decoy).

* **drone**: ``drone(6, agents=2, rows=1)`` (``misdirect scenario drone --size 6 --agents 2
  --rows 1``; 1,151 states, 561 readings) with every failure counted as the "decoy": the
  landing pad and every crash (the attacker wants the mission to fail; the goal is the goal
  cell alone). Budget 1, one node, floor 0.95 on Pr(goal): the best observation-blind
  controller ("always N", Pr(goal) 0.917) falls short of it, so the answer must read its
  sensors. (With the pad alone as the decoy the question is trivial: a blind controller never
  lands on the pad, and a crash counts as a goal.)
* **turn-back**: ``sensor_grid(8, 8, goal="inside")`` (the robot may turn back; its given
  controller has 4 nodes), budget 1, 4 nodes, floor 0.7.

Target (issue 54): a certified worst case within 30 minutes, below the nominal controller's
(each run gets 600 s by default).
``--quick`` (the smoke test, a few seconds): smaller instances, one start, one round. Writes
robust_large.json, .csv and .md under --out; wall and CPU seconds (the machine may be shared).
"""

from __future__ import annotations

import argparse
import csv
import json
import platform
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

TIME_LIMIT = 600.0  # each run's limit (the results committed: this)
TARGET = 1800.0  # issue 54: a certified worst case within 30 minutes


def failing(problem: Any) -> Any:
    """The drone with every failure as the decoy: the landing pad and each crash state."""
    import numpy as np

    bad = np.array([s == "pad" or s.startswith("crash") for s in problem.pomdp.states])
    return replace(problem, decoy=bad, decoy_sets=())


def cases(quick: bool) -> list[tuple[str, str, Callable[[], Any], float, int, float]]:
    """(name, what to type, the problem, budget, memory, floor)."""
    from misdirect.scenarios import drone, sensor_grid

    # (drone size, floor), (grid size, sensors, nodes, floor): quick, then full
    (d, d_floor), (g, k, nodes, g_floor) = (
        ((5, 0.5), (6, 4, 2, 0.5)) if quick else ((6, 0.95), (8, 8, 4, 0.7))
    )
    return [
        (
            "drone",
            f"drone({d}, agents=2, rows=1), decoy = pad and crashes",
            lambda: failing(drone(d, agents=2, rows=1)),
            1.0,
            1,
            d_floor,
        ),
        (
            "turn-back",
            f'sensor_grid({g}, {k}, goal="inside")',
            lambda: sensor_grid(g, k, goal="inside"),
            1.0,
            nodes,
            g_floor,
        ),
    ]


def run(
    name: str,
    what: str,
    make: Callable[[], Any],
    budget: float,
    memory: int,
    floor: float,
    quick: bool,
    time_limit: float,
) -> dict:
    import misdirect

    problem = make()
    began, cpu = time.perf_counter(), time.process_time()
    result = misdirect.robust_controller(
        problem,
        budget,
        memory=memory,
        objective="decoy",
        randomized=True,
        restarts=1 if quick else 4,
        seed=0,
        min_goal=floor,
        time_limit=time_limit,
        max_rounds=1 if quick else None,
        baselines=("given", "blind"),
    )
    seconds, cpu_seconds = time.perf_counter() - began, time.process_time() - cpu
    base = {b.kind: b for b in result.baselines}
    given, blind = base["given"], base["blind"]
    meets = result.nominal_goal is not None and result.nominal_goal >= floor - 1e-9
    below = result.certified and given.certified and result.worst_case < given.bound
    return {
        "case": name,
        "problem": what,
        "states": problem.pomdp.n_states,
        "readings": problem.pomdp.n_observations,
        "budget": budget,
        "memory": memory,
        "min_goal": floor,
        "worst_case": result.worst_case,
        "certified": result.certified,
        "nominal_goal": result.nominal_goal,
        "meets_floor": meets,
        "given": given.worst_case,
        "given_goal": given.nominal_goal,
        "blind": blind.worst_case,
        "blind_goal": blind.nominal_goal,
        "below_given": below,
        "pass": bool(below and meets and seconds <= TARGET),
        "rounds": len(result.rounds),
        "k_size": result.k_size,
        "stop_reason": result.stop_reason,
        "seconds": seconds,
        "cpu_seconds": cpu_seconds,
        "seeds": [s.to_dict() for s in result.seeds],
        "values_per_round": [r.worst_case for r in result.rounds],
    }


def write(rows: list[dict], out: Path, quick: bool, load: str) -> None:
    out.mkdir(parents=True, exist_ok=True)
    machine = f"{platform.machine()}, Python {platform.python_version()}, {platform.system()}"
    mode = "quick" if quick else "full"
    (out / "robust_large.json").write_text(
        json.dumps({"mode": mode, "machine": machine, "load": load, "rows": rows}, indent=1) + "\n"
    )
    fields = [
        "case", "problem", "states", "readings", "budget", "memory", "min_goal", "worst_case",
        "certified", "nominal_goal", "meets_floor", "given", "given_goal", "blind",
        "blind_goal", "below_given", "pass", "rounds", "k_size", "seconds", "cpu_seconds",
    ]  # fmt: skip
    with (out / "robust_large.csv").open("w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=fields, extrasaction="ignore")
        writer.writeheader()
        writer.writerows(rows)
    lines = [
        f"# Robust controllers beyond the paper's grid, randomized ({mode} mode)",
        "",
        f"Machine: {machine}; load average at the start {load} (2 cores, shared: wall times "
        "move with the load, CPU seconds less). Worst-case Pr(decoy), each certified by "
        "misdirect.solve for the controller it belongs to; nominal Pr(goal) in brackets.",
        "",
        "| case | problem | B | nodes | floor | robust | given (nominal) | blind | below given | "
        "rounds | wall s | CPU s |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['case']} | `{r['problem']}` | {r['budget']:g} | {r['memory']} | "
            f"{r['min_goal']:g} | {r['worst_case']:.6f} ({r['nominal_goal']:.4f}) | "
            f"{r['given']:.6f} ({r['given_goal']:.4f}) | {r['blind']:.6f} "
            f"({r['blind_goal']:.4f}) | {'yes' if r['below_given'] else '**no**'} | "
            f"{r['rounds']} | {r['seconds']:.1f} | {r['cpu_seconds']:.1f} |"
        )
    (out / "robust_large.md").write_text("\n".join(lines) + "\n")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("bench/results"))
    parser.add_argument("--quick", action="store_true", help="a few seconds (smoke test)")
    parser.add_argument("--time-limit", type=float, default=TIME_LIMIT)
    parser.add_argument("--cases", default="drone,turn-back")
    args = parser.parse_args()
    wanted = {c.strip() for c in args.cases.split(",") if c.strip()}
    try:
        load = open("/proc/loadavg").read().split()[0]  # noqa: SIM115
    except OSError:
        load = "unknown"
    rows = []
    for name, what, make, budget, memory, floor in cases(args.quick):
        if name not in wanted:
            continue
        row = run(name, what, make, budget, memory, floor, args.quick, args.time_limit)
        print(
            f"{name} B={budget:g}: worst {row['worst_case']:.6f} (given {row['given']:.6f}, "
            f"blind {row['blind']:.6f}), goal {row['nominal_goal']:.4f}, {row['rounds']} rounds, "
            f"{row['seconds']:.1f} s wall, {row['cpu_seconds']:.1f} s CPU, pass {row['pass']}",
            flush=True,
        )
        rows.append(row)
    write(rows, args.out, args.quick, load)


if __name__ == "__main__":
    main()
