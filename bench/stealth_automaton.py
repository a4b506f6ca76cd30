"""Stealth against a user's automaton on turn-back grids and a drone (issue 52): the curves
with the monitor certified as far as the unmonitored ones are.

    python bench/stealth_automaton.py --out DIR [--quick] [--time-limit 300]

The automaton ("implausible twice") remembers the last reading and action and raises the
alarm on the second reading in a row that they make impossible: no world state emitting the
last reading moves, under the last action, into one emitting the new reading (a heading the
robot knows it took cannot land it there). It is written as a user would, as transitions
(:meth:`misdirect.core.monitor.Monitor.from_transitions`, checked deterministic and complete);
its size is (readings x actions x 2) + 2 states, so it suits models with few readings (the
drone's 1,047 readings and 5 actions would make a table of 10,470 x 1,047 x 5).

The drone gets "cell jump" instead, the check a GPS-spoofing detector makes: every reading
names the drone's cell, and the alarm is raised when it names a cell more than one step (in
either coordinate) from the cell the previous reading named. One state per cell, written
with lists of readings as guards and a catch-all to the alarm.

Per case: each budget's status, value, Pr(alarm) and the wall time of each curve (one
process, the unmonitored curve first). Writes stealth_automaton.json and .csv under --out.
"""

from __future__ import annotations

import argparse
import csv
import json
import platform
import time
from pathlib import Path
from typing import Any

import numpy as np

import misdirect
from misdirect.core.model import Problem
from misdirect.core.monitor import Monitor, Transition, with_monitor
from misdirect.scenarios import drone, sensor_grid


def implausible_twice_on(n: int, sensors: int) -> tuple[Problem, Monitor]:
    problem = sensor_grid(n, sensors, goal="inside")
    return problem, implausible_twice(problem)


def cell_jump_on(n: int, agents: int, rows: int) -> tuple[Problem, Monitor]:
    problem = drone(n, agents=agents, rows=rows)
    return problem, cell_jump(problem)


# (name, the problem and its monitor, top budget)
TURN_BACK_8 = ("turn-back 8x8, 8 sensors", lambda: implausible_twice_on(8, 8))
FULL = [
    (*TURN_BACK_8, 2),
    ("turn-back 12x12, 16 sensors", lambda: implausible_twice_on(12, 16), 2),
    ("drone 7x7, 2 agents, 1 row", lambda: cell_jump_on(7, 2, 1), 3),
]
QUICK = [(*TURN_BACK_8, 1)]


def implausible_twice(problem: Problem) -> Monitor:
    """The automaton of the module docstring, over ``problem``'s readings and actions."""
    pomdp = problem.pomdp
    observations, actions = pomdp.observations, pomdp.actions
    coo = pomdp.transitions.tocoo()
    action, source = np.divmod(coo.row, pomdp.n_states)
    seen = pomdp.observation_of
    possible = set(zip(seen[source].tolist(), action.tolist(), seen[coo.col].tolist(), strict=True))

    def state(o: str, a: str, strikes: int) -> str:
        return f"{o}|{a}|{strikes}"

    transitions = [
        Transition(state="start", reading=o, action=a, next=state(o, a, 0))
        for o in observations
        for a in actions
    ]
    for i, last in enumerate(observations):
        for j, played in enumerate(actions):
            for strikes in (0, 1):
                for r, reading in enumerate(observations):
                    plausible = (i, j, r) in possible
                    for a in actions:
                        if plausible:
                            after = state(reading, a, 0)
                        else:
                            after = "caught" if strikes else state(reading, a, 1)
                        transitions.append(
                            Transition(
                                state=state(last, played, strikes),
                                reading=reading,
                                action=a,
                                next=after,
                            )
                        )
    states = ["start", "caught"]
    states += [state(o, a, k) for o in observations for a in actions for k in (0, 1)]
    return Monitor.from_transitions(
        states=states,
        initial="start",
        alarm=["caught"],
        transitions=transitions,
        observations=observations,
        actions=actions,
        name="implausible-twice",
    )


def cell_jump(problem: Problem) -> Monitor:
    """The drone's automaton of the module docstring: a state per cell the readings name."""
    observations = problem.pomdp.observations
    cell_of = {o: o.split(":")[0] for o in observations if ":" in o}  # "(x,y):reading"
    cells = sorted(set(cell_of.values()))
    named = {c: [o for o, at in cell_of.items() if at == c] for c in cells}

    def xy(cell: str) -> tuple[int, int]:
        x, y = cell.strip("()").split(",")
        return int(x), int(y)

    def near(a: str, b: str) -> bool:
        (ax, ay), (bx, by) = xy(a), xy(b)
        return max(abs(ax - bx), abs(ay - by)) <= 1

    transitions = [Transition(state="start", reading=named[c], next=c) for c in cells]
    transitions.append(Transition(state="start", reading="*", next="start"))  # goal, pad, crash
    for c in cells:
        transitions += [Transition(state=c, reading=named[d], next=d) for d in cells if near(c, d)]
        transitions.append(Transition(state=c, reading="*", next="caught"))
    return Monitor.from_transitions(
        states=["start", "caught", *cells],
        initial="start",
        alarm=["caught"],
        transitions=transitions,
        observations=observations,
        actions=problem.pomdp.actions,
        name="cell-jump",
    )


def rows(
    case: str, monitor: str, monitored: bool, result: misdirect.SolveResult, wall: float
) -> list[dict]:
    return [
        {
            "case": case,
            "monitor": monitor if monitored else "",
            "budget": p.budget,
            "status": str(p.status),
            "value": p.probability,
            "alarm": p.alarm,
            "upper_bound": p.upper_bound,
            "curve_wall_s": round(wall, 3),
        }
        for p in result.curve
    ]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--quick", action="store_true", help="the small case (smoke test)")
    parser.add_argument("--time-limit", type=float, default=300.0, help="seconds per curve")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    table: list[dict[str, Any]] = []
    cases = []
    for name, build, top in QUICK if args.quick else FULL:
        began = time.perf_counter()
        problem, monitor = build()
        watched = with_monitor(problem, monitor)
        build_s = time.perf_counter() - began
        budgets = list(range(top + 1))
        summary: dict[str, Any] = {
            "case": name,
            "monitor_states": monitor.n_states,
            "product_nodes": watched.controller.n_nodes,
            "build_s": round(build_s, 3),
        }
        for key, subject in (("plain", problem), ("watched", watched)):
            began = time.perf_counter()
            result = misdirect.solve(subject, budgets=budgets, time_limit=args.time_limit)
            wall = time.perf_counter() - began
            found = rows(name, monitor.name, key == "watched", result, wall)
            table += found
            summary[f"{key}_wall_s"] = round(wall, 3)
            summary[f"{key}_certified_to"] = max(
                (r["budget"] for r in found if r["status"] == "optimal"), default=None
            )
        cases.append(summary)
        print(json.dumps(summary), flush=True)
    document = {"machine": platform.platform(), "time_limit_s": args.time_limit}
    document |= {"cases": cases, "rows": table}
    (args.out / "stealth_automaton.json").write_text(json.dumps(document, indent=1) + "\n")
    with (args.out / "stealth_automaton.csv").open("w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(table[0]))
        writer.writeheader()
        writer.writerows(table)


if __name__ == "__main__":
    main()
