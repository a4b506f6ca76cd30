"""The defender's view (issue 14): audit and hardening against their time targets.

    python bench/defence.py [--out bench/results] [--quick]

    D1  audit of the paper's 5x5 grid, budgets 0..4                          under 5 s
    D2  audit of sensor_grid(20, 32, seed=0), budget 3, certified            under 60 s
    D3  hardening of the 5x5 grid (attacker budget 4), D = 0..3, certified   under 10 s

Each case runs in this process, one after the other, with a whole-case time limit of twice
its target (so a case that cannot make it reports how far it got: certified or not, and the
time it took). ``--quick`` (the test suite's smoke test) runs small cases and has no targets
worth reading. Writes defence.json, .csv and .md under --out.
"""

from __future__ import annotations

import argparse
import csv
import json
import platform
import time
from pathlib import Path

FULL = {
    "D1": {"kind": "audit", "scenario": ("paper_grid", 5), "budget": 4, "target_s": 5.0},
    "D2": {"kind": "audit", "scenario": ("sensor_grid", 20, 32, 0), "budget": 3, "target_s": 60.0},
    "D3": {
        "kind": "harden",
        "scenario": ("paper_grid", 5),
        "budget": 4,
        "protect_budget": 3,
        "target_s": 10.0,
    },
}
QUICK = {
    "D1": {"kind": "audit", "scenario": ("paper_grid", 5), "budget": 2, "target_s": 5.0},
    "D2": {"kind": "audit", "scenario": ("sensor_grid", 8, 6, 0), "budget": 2, "target_s": 60.0},
    "D3": {
        "kind": "harden",
        "scenario": ("paper_grid", 5),
        "budget": 4,
        "protect_budget": 1,
        "target_s": 10.0,
    },
}


def build(scenario: tuple):
    from misdirect.scenarios import paper_grid, sensor_grid

    if scenario[0] == "paper_grid":
        return paper_grid(scenario[1])
    _, n, sensors, seed = scenario
    return sensor_grid(n, sensors, seed=seed)


def run_case(goal: str, case: dict) -> dict:
    import misdirect

    problem = build(case["scenario"])
    limit = 2 * case["target_s"]
    began = time.perf_counter()
    if case["kind"] == "audit":
        result = misdirect.audit(problem, budget=case["budget"], time_limit=limit)
        elapsed = time.perf_counter() - began
        certified = result.certified
        detail = {
            "curve": [
                {"budget": p.budget, "probability": p.probability, "status": p.status}
                for p in result.curve
            ],
            "sensors": len(result.sensors),
            "re_solved": sum(s.in_optimal_attack for s in result.sensors),
            "online_unlimited": result.online.unlimited_probability,
            "online_budgeted": result.online.budgeted_probability,
        }
        value = result.probability
    else:
        result = misdirect.harden(
            problem,
            protect_budget=case["protect_budget"],
            budget=case["budget"],
            time_limit=limit,
        )
        elapsed = time.perf_counter() - began
        certified = result.status == "optimal" and all(p.status == "optimal" for p in result.curve)
        detail = {
            "curve": [
                {
                    "protect_budget": p.protect_budget,
                    "protection": p.protection,
                    "probability": p.probability,
                    "lower_bound": p.lower_bound,
                    "status": p.status,
                }
                for p in result.curve
            ],
            "solves": result.solves,
            "nodes": result.nodes,
        }
        value = result.value_after
    return {
        "goal": goal,
        "kind": case["kind"],
        "instance": problem.name,
        "budget": case["budget"],
        "protect_budget": case.get("protect_budget"),
        "seconds": round(elapsed, 3),
        "target_s": case["target_s"],
        "certified": certified,
        "value": value,
        "pass": bool(certified and elapsed <= case["target_s"]),
        "detail": detail,
    }


def write(rows: list[dict], out: Path, quick: bool) -> None:
    out.mkdir(parents=True, exist_ok=True)
    machine = f"{platform.machine()}, Python {platform.python_version()}, {platform.system()}"
    (out / "defence.json").write_text(
        json.dumps(
            {"mode": "quick" if quick else "full", "machine": machine, "rows": rows}, indent=1
        )
        + "\n"
    )
    fields = ["goal", "kind", "instance", "budget", "protect_budget", "seconds", "target_s"]
    fields += ["certified", "value", "pass"]
    with (out / "defence.csv").open("w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=fields, extrasaction="ignore")
        writer.writeheader()
        writer.writerows(rows)
    lines = [
        f"# The defender's view: time targets ({'quick' if quick else 'full'} mode)",
        "",
        f"Machine: {machine}. Each case has a time limit of twice its target.",
        "",
        "| goal | case | measured (s) | target (s) | certified | value | pass |",
        "|---|---|---|---|---|---|---|",
    ]
    for row in rows:
        what = (
            f"audit, {row['instance']}, budgets 0..{row['budget']:g}"
            if row["kind"] == "audit"
            else f"harden, {row['instance']}, B = {row['budget']:g}, "
            f"D = 0..{row['protect_budget']:g}"
        )
        lines.append(
            f"| {row['goal']} | {what} | {row['seconds']:.2f} | {row['target_s']:g} | "
            f"{'yes' if row['certified'] else '**no**'} | {row['value']:.9f} | "
            f"{'yes' if row['pass'] else '**no**'} |"
        )
    for row in rows:
        if row["kind"] == "audit":
            statuses = ", ".join(
                f"B={p['budget']:g}: {p['probability']:.6f} {p['status']}"
                for p in row["detail"]["curve"]
            )
            lines += ["", f"{row['goal']}: {statuses}; {row['detail']['re_solved']} re-solves."]
        else:
            curve = "; ".join(
                f"D={p['protect_budget']:g}: protect {', '.join(p['protection']) or 'nothing'} "
                f"→ {p['probability']:.6f} ({p['status']})"
                for p in row["detail"]["curve"]
            )
            lines += ["", f"{row['goal']}: {curve}; {row['detail']['solves']} attacker solves."]
    (out / "defence.md").write_text("\n".join(lines) + "\n")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("bench/results"))
    parser.add_argument("--quick", action="store_true", help="small cases (the smoke test)")
    args = parser.parse_args()
    plan = QUICK if args.quick else FULL
    rows = []
    for goal, case in plan.items():
        row = run_case(goal, case)
        print(
            f"{goal}: {row['seconds']:.2f} s (target {row['target_s']:g}), certified "
            f"{row['certified']}, pass {row['pass']}",
            flush=True,
        )
        rows.append(row)
    write(rows, args.out, args.quick)


if __name__ == "__main__":
    main()
