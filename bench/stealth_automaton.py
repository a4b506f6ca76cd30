"""Stealth against a user's automaton on turn-back grids (issue 52): the curves with the
monitor certified as far as the unmonitored ones are.

    python bench/stealth_automaton.py --out DIR [--quick] [--time-limit 300]

The automaton ("implausible twice") remembers the last reading and action and raises the
alarm on the second reading in a row that they make impossible: no world state emitting the
last reading moves, under the last action, into one emitting the new reading (a heading the
robot knows it took cannot land it there). It is written as a user would, as transitions
(:meth:`misdirect.core.monitor.Monitor.from_transitions`, checked deterministic and complete);
its size is (readings x actions x 2) + 2 states, so it suits models with few readings (the
drone's 1,047 readings and 5 actions would make a table of 10,470 x 1,047 x 5).

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
from misdirect.scenarios import sensor_grid

# (name, sensor_grid arguments, top budget)
FULL = [("turn-back 8x8, 8 sensors", (8, 8), 2), ("turn-back 12x12, 16 sensors", (12, 16), 2)]
QUICK = [("turn-back 8x8, 8 sensors", (8, 8), 1)]


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


def rows(case: str, monitored: bool, result: misdirect.SolveResult, wall: float) -> list[dict]:
    return [
        {
            "case": case,
            "monitor": "implausible-twice" if monitored else "",
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
    for name, (n, sensors), top in QUICK if args.quick else FULL:
        problem = sensor_grid(n, sensors, goal="inside")
        began = time.perf_counter()
        monitor = implausible_twice(problem)
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
            found = rows(name, key == "watched", result, wall)
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
