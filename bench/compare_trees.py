"""Before/after a refactoring: the same cases on two source trees, alternating, in one command.

    python bench/compare_trees.py --before /path/to/old/src --after src [--out DIR] [--quick]

Every case runs in a fresh process with ``PYTHONPATH`` set to one tree's ``src``; the two
trees alternate case by case (and swap who goes first every other case), so a drift in the
machine's load hits both alike. Reported per case: both wall times, their ratio, and whether
every budget's status and exact value (to 1e-9) agree. Cases:

* the hard instances' ``auto`` runs (``bench/hard_instances.py``: sensor networks with 16–128
  sensors, with 60 s, 10 s and no time limit);
* G1 and G2 of ``bench/speed.py`` (the paper's grid, ``auto``), timed three ways against one
  exact evaluation in the same process: the first solve of the process (what a command pays),
  the best of three repeats on the same problem object, and a solve of a new problem object.

* the enumeration with low-rank updates alone (``method="incremental"``, no time limit) on
  chains with cycles: the 64-sensor turn-back grid's budgets 0..3 (2.7 million alterations)
  and the 7x7 drone with 2 agents' budgets 0..2: what its kernel costs.

* the C2 drones (``bench/hard_instances.py``'s chains with cycles) under ``auto`` at 60 s.

``--only hard,grid,enumeration,drones`` picks kinds. Writes compare_trees.json and compare_trees.md
under --out.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

import hard_instances  # beside this file: the same cases as the benchmarks, listed once
import speed


def hard_cases(plan: dict, limit: float, short_limit: float) -> list[tuple]:
    """(n, sensors, top budget, seed, time limit) of every auto run of the hard instances."""
    cases = [(*case, limit) for case in plan["set"]]
    cases += [(*case, short_limit) for case in (plan["h1"], plan["h2"])]
    return cases + [(*case, None) for case in plan["unlimited"]]


HARD_CASE = r"""
import json, sys, time
import misdirect
from misdirect.scenarios import sensor_grid
n, k, top, seed, limit = json.loads(sys.argv[1])
problem = sensor_grid(n, k, seed=seed)
began = time.perf_counter()
result = misdirect.solve(problem, budgets=range(top + 1), time_limit=limit)
wall = time.perf_counter() - began
points = [[p.status, p.probability, p.upper_bound] for p in result.curve]
print(json.dumps({"wall_s": wall, "points": points}))
"""

GRID_CASE = r"""
import json, sys, time
from misdirect import solve
from misdirect.core.evaluate import decoy_probability
from misdirect.scenarios import paper_grid
n, top = json.loads(sys.argv[1])
budgets = list(range(top + 1))
problem = paper_grid(n, budget=top)
identity = problem.identity()

def timed(run):
    began = time.perf_counter()
    value = run()
    return time.perf_counter() - began, value

floor = min(timed(lambda: decoy_probability(problem, identity))[0] for _ in range(3))
first, result = timed(lambda: solve(problem, budgets=budgets))
warm = min(timed(lambda: solve(problem, budgets=budgets))[0] for _ in range(3))
fresh, _ = timed(lambda: solve(paper_grid(n, budget=top), budgets=budgets))
points = [[p.status, p.probability, p.upper_bound] for p in result.curve]
print(json.dumps({"evaluation_s": floor, "first": first / floor, "warm": warm / floor,
                  "new_object": fresh / floor, "points": points}))
"""


DRONE_CASE = r"""
import json, sys, time
import misdirect
from misdirect.scenarios import drone
label, scenario, parameters, top = json.loads(sys.argv[1])
problem = drone(**parameters)
began = time.perf_counter()
result = misdirect.solve(problem, budgets=range(top + 1), time_limit=60.0)
wall = time.perf_counter() - began
points = [[p.status, p.probability, p.upper_bound] for p in result.curve]
print(json.dumps({"wall_s": wall, "points": points}))
"""
ENUMERATION_CASE = r"""
import json, sys, time
import misdirect
from misdirect.scenarios import drone, sensor_grid
scenario, parameters, top = json.loads(sys.argv[1])
problem = {"sensor-grid": sensor_grid, "drone": drone}[scenario](**parameters)
began = time.perf_counter()
result = misdirect.solve(problem, budgets=range(top + 1), method="incremental")
wall = time.perf_counter() - began
points = [[p.status, p.probability, p.upper_bound] for p in result.curve]
print(json.dumps({"wall_s": wall, "points": points}))
"""
ENUMERATION_CASES = [
    ["sensor-grid", {"n": 40, "sensors": 64, "goal": "inside"}, 3],
    ["drone", {"n": 7, "agents": 2, "rows": 1}, 2],
]
QUICK_ENUMERATION = [["sensor-grid", {"n": 8, "sensors": 6, "goal": "inside"}, 2]]
KINDS = ("hard", "grid", "enumeration", "drones")


def _run(code: str, case: list, src: Path) -> dict:
    env = {**os.environ, "PYTHONPATH": str(src.resolve())}
    done = subprocess.run(
        [sys.executable, "-c", code, json.dumps(case)], capture_output=True, text=True, env=env
    )
    if done.returncode != 0:
        return {"error": done.stderr.strip().splitlines()[-1] if done.stderr else "failed"}
    return json.loads(done.stdout.strip().splitlines()[-1])


def _same(a: dict, b: dict) -> bool:
    if "points" not in a or "points" not in b:
        return False
    ours = [(s, round(v, 9)) for s, v, _ in a["points"]]
    theirs = [(s, round(v, 9)) for s, v, _ in b["points"]]
    return ours == theirs


def compare(before: Path, after: Path, quick: bool, kinds: tuple[str, ...] = KINDS) -> list[dict]:
    rows = []
    plan = hard_instances.QUICK if quick else hard_instances.FULL
    hard = hard_cases(plan, 60.0, 10.0)[:1] if quick else hard_cases(plan, 60.0, 10.0)
    grids = [speed.QUICK["g1"]] if quick else [speed.FULL["g1"], speed.FULL["g2"]]
    enumerations = QUICK_ENUMERATION if quick else ENUMERATION_CASES
    cases = [("hard", HARD_CASE, list(c)) for c in hard]
    cases += [("grid", GRID_CASE, list(c)) for c in grids]
    cases += [("enumeration", ENUMERATION_CASE, c) for c in enumerations]
    cases += [("drones", DRONE_CASE, list(c)) for c in plan["c2"]]
    cases = [case for case in cases if case[0] in kinds]
    for index, (kind, code, case) in enumerate(cases):
        order = [("before", before), ("after", after)]
        if index % 2:
            order.reverse()
        measured = {name: _run(code, case, src) for name, src in order}
        row = {"kind": kind, "case": case, **measured}
        row["same_answers"] = _same(measured["before"], measured["after"])
        rows.append(row)
        print(json.dumps({k: v for k, v in row.items() if k not in ("before", "after")}))
    return rows


def markdown(rows: list[dict]) -> str:
    lines = ["| case | before | after | after / before | same statuses and values |"]
    lines.append("|---|---|---|---|---|")
    for row in rows:
        a, b = row["before"], row["after"]
        if row["kind"] != "grid":
            if row["kind"] == "drones":
                label, scenario, parameters, top = row["case"]
                name = f"auto, 60 s, {label} B0..{top}"
            elif row["kind"] == "enumeration":
                scenario, parameters, top = row["case"]
                shown = ", ".join(f"{key}={value}" for key, value in parameters.items())
                name = f"incremental, {scenario}({shown}) B0..{top}"
            else:
                n, k, top, seed, limit = row["case"]
                name = f"sensor_grid({n}, {k}, seed={seed}) B0..{top}, limit {limit or 'none'}"
            if "wall_s" in a and "wall_s" in b:
                cells = [f"{a['wall_s']:.1f} s", f"{b['wall_s']:.1f} s"]
                cells.append(f"{b['wall_s'] / a['wall_s']:.2f}")
            else:
                cells = [str(a.get("error", "")), str(b.get("error", "")), ""]
        else:
            n, top = row["case"]
            name = f"paper_grid({n}) B0..{top}: first / warm / new object, x one evaluation"
            if "first" in a and "first" in b:
                cells = [
                    " / ".join(f"{a[key]:.1f}" for key in ("first", "warm", "new_object")),
                    " / ".join(f"{b[key]:.1f}" for key in ("first", "warm", "new_object")),
                    "",
                ]
            else:
                cells = [str(a.get("error", "")), str(b.get("error", "")), ""]
        lines.append(f"| {name} | {' | '.join(cells)} | {'yes' if row['same_answers'] else 'NO'} |")
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--before", type=Path, required=True, help="the old tree's src/")
    parser.add_argument("--after", type=Path, default=Path("src"), help="the new tree's src/")
    parser.add_argument("--out", type=Path, default=Path("bench/results"))
    parser.add_argument("--quick", action="store_true", help="one small case of each kind")
    parser.add_argument(
        "--only", default=",".join(KINDS), help=f"kinds of case, of {', '.join(KINDS)}"
    )
    args = parser.parse_args()
    kinds = tuple(kind.strip() for kind in args.only.split(","))
    unknown = sorted(set(kinds) - set(KINDS))
    if unknown:
        parser.error(f"--only: unknown kind {', '.join(unknown)} (of {', '.join(KINDS)})")
    rows = compare(args.before, args.after, args.quick, kinds)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "compare_trees.json").write_text(json.dumps(rows, indent=2) + "\n")
    (args.out / "compare_trees.md").write_text(markdown(rows))
    print(markdown(rows))


if __name__ == "__main__":
    main()
