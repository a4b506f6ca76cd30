"""Stealth speed (issue 52): certified curves with a monitor against the same without one.

    python bench/stealth_speed.py [--out bench/results] [--quick]

    T1  the paper's 5x5 grid, consistency monitor, budgets 0..4 (auto)       under 5 s
    T2  the same with branch-and-bound alone                                (no target: ratio)
    T3  sensor_grid(8, 6), consistency monitor, budgets 0..3 (auto)         within 2x unmonitored
    T4  sensor_grid(40, 128), consistency monitor, budgets 0..3             within 2x unmonitored
    T5  sensor_grid(10, 8), consistency monitor, budgets 0..3               (T4's target, a
        network whose full monitor has 54,707 supports: 258 along the controller's runs)

Each case solves the curve without the monitor, then with it, in this process, one after
the other; the monitored time includes building the monitor and folding it in (the product
controller, its bisimilar nodes merged). Wall and CPU seconds are both recorded (the CPU time
says what the case costs when the machine is shared); the ratio is monitored / unmonitored
wall time. The sensor grids have a time limit (``limit_s``), the paper grid none; a monitor
that does not fit its cap (the consistency monitor's belief supports) is recorded as such,
with the time it took to find out. Writes stealth_speed.json, .csv and .md under --out.
"""

from __future__ import annotations

import argparse
import csv
import json
import platform
import time
from pathlib import Path

FULL = {
    "T1": {"scenario": ("paper_grid", 5), "budgets": 4, "method": "auto", "target_s": 5.0},
    "T2": {"scenario": ("paper_grid", 5), "budgets": 4, "method": "branch-and-bound"},
    "T3": {"scenario": ("sensor_grid", 8, 6), "budgets": 3, "method": "auto", "ratio": 2.0},
    "T4": {"scenario": ("sensor_grid", 40, 128), "budgets": 3, "method": "auto", "ratio": 2.0},
    "T5": {"scenario": ("sensor_grid", 10, 8), "budgets": 3, "method": "auto", "ratio": 2.0},
}
QUICK = {
    "T1": {"scenario": ("paper_grid", 5), "budgets": 1, "method": "auto", "target_s": 5.0},
    "T3": {"scenario": ("sensor_grid", 5, 2), "budgets": 2, "method": "auto", "ratio": 2.0},
}
# each solve's time limit: none on the paper grid, where a limit changes the schedule (with one,
# branch-and-bound gives the per-state search 5 % of a budget's share and the segment search
# the rest; without one, the per-state search has 5 s first)
LIMIT_S: dict[str, float | None] = {"paper_grid": None, "sensor_grid": 300.0}


def build(scenario: tuple):
    from misdirect.scenarios import paper_grid, sensor_grid

    if scenario[0] == "paper_grid":
        return paper_grid(scenario[1])
    _, n, sensors = scenario
    return sensor_grid(n, sensors)


def timed(work):
    """``work()``, its wall and CPU seconds."""
    wall, cpu = time.perf_counter(), time.process_time()
    value = work()
    return value, time.perf_counter() - wall, time.process_time() - cpu


def curve(problem, budgets: int, method: str, limit: float | None) -> dict:
    import misdirect

    result, wall, cpu = timed(
        lambda: misdirect.solve(
            problem, budgets=list(range(budgets + 1)), method=method, time_limit=limit
        )
    )
    return {
        "wall_s": round(wall, 3),
        "cpu_s": round(cpu, 3),
        "certified": all(str(p.status) == "optimal" for p in result.curve),
        "values": [p.probability for p in result.curve],
        "statuses": [str(p.status) for p in result.curve],
        "certified_by": getattr(result, "certified_by", method),
    }


def run_case(goal: str, case: dict) -> dict:
    import misdirect
    from misdirect.core.monitor import consistency_monitor, with_monitor
    from misdirect.errors import ProblemError

    problem = build(case["scenario"])
    row: dict = {"goal": goal, "instance": problem.name, "budgets": case["budgets"]}
    row["method"] = case["method"]
    row["target_s"] = case.get("target_s")
    row["target_ratio"] = case.get("ratio")
    limit = LIMIT_S[case["scenario"][0]]
    row["limit_s"] = limit
    row["plain"] = curve(problem, case["budgets"], case["method"], limit)
    try:
        monitor, build_s, build_cpu = timed(lambda: consistency_monitor(problem))
    except ProblemError as error:
        row["monitor_error"] = str(error)
        row["pass"] = False
        return row
    watched, fold_s, fold_cpu = timed(lambda: with_monitor(problem, monitor))
    row["monitor_states"] = monitor.n_states
    row["product_nodes"] = watched.controller.n_nodes
    row["chain_states"] = misdirect.evaluate(watched).product_states
    row["plain_chain_states"] = misdirect.evaluate(problem).product_states
    row["build_s"] = round(build_s + fold_s, 3)
    watched_curve = curve(watched, case["budgets"], case["method"], limit)
    watched_curve["wall_s"] = round(watched_curve["wall_s"] + build_s + fold_s, 3)
    watched_curve["cpu_s"] = round(watched_curve["cpu_s"] + build_cpu + fold_cpu, 3)
    row["watched"] = watched_curve
    row["ratio"] = round(watched_curve["wall_s"] / max(row["plain"]["wall_s"], 1e-3), 2)
    ok = watched_curve["certified"]
    if row["target_s"] is not None:
        ok = ok and watched_curve["wall_s"] <= row["target_s"]
    if row["target_ratio"] is not None:
        ok = ok and row["ratio"] <= row["target_ratio"]
    row["pass"] = bool(ok)
    return row


def write(rows: list[dict], out: Path, quick: bool) -> None:
    out.mkdir(parents=True, exist_ok=True)
    machine = f"{platform.machine()}, Python {platform.python_version()}, {platform.system()}"
    document = {"mode": "quick" if quick else "full", "machine": machine, "rows": rows}
    (out / "stealth_speed.json").write_text(json.dumps(document, indent=1) + "\n")
    fields = ["goal", "instance", "budgets", "method", "plain_wall_s", "plain_cpu_s"]
    fields += ["watched_wall_s", "watched_cpu_s", "ratio", "certified", "pass", "note"]
    with (out / "stealth_speed.csv").open("w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=fields)
        writer.writeheader()
        for row in rows:
            watched = row.get("watched", {})
            writer.writerow(
                {
                    "goal": row["goal"],
                    "instance": row["instance"],
                    "budgets": f"0..{row['budgets']}",
                    "method": row["method"],
                    "plain_wall_s": row["plain"]["wall_s"],
                    "plain_cpu_s": row["plain"]["cpu_s"],
                    "watched_wall_s": watched.get("wall_s"),
                    "watched_cpu_s": watched.get("cpu_s"),
                    "ratio": row.get("ratio"),
                    "certified": watched.get("certified"),
                    "pass": row["pass"],
                    "note": row.get("monitor_error", ""),
                }
            )
    lines = [
        f"# Stealth speed ({'quick' if quick else 'full'} mode)",
        "",
        f"Machine: {machine}. Times in seconds, wall (CPU); the monitored time includes "
        "building the monitor and folding it in.",
        "",
        "| goal | case | without monitor | with consistency | ratio | target | certified | pass |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for row in rows:
        plain = row["plain"]
        watched = row.get("watched")
        target = (
            f"under {row['target_s']:g} s"
            if row["target_s"] is not None
            else (f"{row['target_ratio']:g}x" if row["target_ratio"] is not None else "—")
        )
        shown = (
            f"{watched['wall_s']:.2f} ({watched['cpu_s']:.2f})"
            if watched
            else "monitor over its cap"
        )
        lines.append(
            f"| {row['goal']} | {row['instance']}, budgets 0..{row['budgets']}, "
            f"{row['method']} | {plain['wall_s']:.2f} ({plain['cpu_s']:.2f}) | {shown} | "
            f"{row.get('ratio', '—')} | {target} | "
            f"{'yes' if watched and watched['certified'] else 'no'} | "
            f"{'yes' if row['pass'] else '**no**'} |"
        )
    for row in rows:
        if "monitor_error" in row:
            lines += ["", f"{row['goal']}: {row['monitor_error']}"]
        else:
            lines += [
                "",
                f"{row['goal']}: monitor {row['monitor_states']:,} states; product controller "
                f"{row['product_nodes']:,} nodes; chain {row['chain_states']:,} states "
                f"(without the monitor {row['plain_chain_states']:,}); values "
                + ", ".join(f"{v:.6f}" for v in row["watched"]["values"]),
            ]
    (out / "stealth_speed.md").write_text("\n".join(lines) + "\n")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("bench/results"))
    parser.add_argument("--quick", action="store_true", help="small cases (the smoke test)")
    parser.add_argument("--only", nargs="*", help="run these goals only (T1 ...)")
    args = parser.parse_args()
    plan = QUICK if args.quick else FULL
    rows = []
    for goal, case in plan.items():
        if args.only and goal not in args.only:
            continue
        row = run_case(goal, case)
        watched = row.get("watched", {})
        print(
            f"{goal}: plain {row['plain']['wall_s']:.2f} s, watched "
            f"{watched.get('wall_s', '—')} s, ratio {row.get('ratio', '—')}, pass {row['pass']}",
            flush=True,
        )
        rows.append(row)
    write(rows, args.out, args.quick)


if __name__ == "__main__":
    main()
