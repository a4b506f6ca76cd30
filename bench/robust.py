"""Robust controllers (issue 54) on the paper's grid: the exact master, the randomized master,
and the trade-off figure.

    python bench/robust.py [--out bench/results] [--quick] [--budgets 1,2,3,4]
        [--exact-budgets 0,1,2,3,4] [--parts exact,randomized] [--figure docs/robust-tradeoff.png]
    python bench/robust.py --replot bench/results/robust.json [--figure docs/robust-tradeoff.png]

**exact** (one memory node, deterministic, the exact master; the target of issue 54: the
min–max proven, lower = upper bound, for budgets 0..4 within 10 minutes in all), per budget B:

    goal   max-min Pr(goal): ``robust_controller(paper_grid(), B, objective="goal")``
    floor  min-max Pr(decoy) over the controllers with nominal Pr(goal) >= 0.9
           (``min_goal=0.9``), with every baseline (given, blind, harden, PAYNT nominal)

**randomized** (2 nodes, the gradient master), for each budget of ``--budgets``, two runs of
``robust_controller(paper_grid(), B, memory=2, randomized=True, objective="decoy")`` (4 starts
per round, seed 0, 240 s each):

    plain  minimise the worst-case Pr(decoy), nothing else asked
    floor  the same with a floor of 0.9 on the nominal Pr(goal) (--min-goal 0.9)

and, per run, the certified worst-case Pr(decoy) of the controller found (the oracle's, for
that very controller) against the paper's controller's (0.719924 / 0.860130 / 0.862442 /
0.863622 at B = 1..4) and the baselines' (the given controller, the best observation-blind one
-- under the floor, the best blind one meeting it), with the nominal Pr(goal) of each.
Target (issue 54): strictly below the paper's controller at every budget, and no worse than
every baseline.

**The trade-off figure** (robust_tradeoff.png under --out, and at --figure): nominal Pr(goal)
against certified worst-case Pr(decoy), one panel per budget, for every controller above.

``--quick`` (the smoke test, a few seconds): the exact floor run at budget 0 without the PAYNT
baseline, randomized plain at budget 1 with one start and one round. Writes robust.json, .csv,
.md and robust_exact.csv under --out.
"""

from __future__ import annotations

import argparse
import csv
import json
import platform
import time
from pathlib import Path

PAPER = {1: 0.719924, 2: 0.860130, 3: 0.862442, 4: 0.863622}  # the paper's controller, SPEC §3
FLOOR = 0.9
TIME_LIMIT = 240.0
MEMORY = 2


def run(
    budget: int,
    floor: float | None,
    restarts: int,
    max_rounds: int | None = None,
    exact_seed: bool = True,
) -> dict:
    import misdirect
    from misdirect.scenarios import paper_grid

    problem = paper_grid()
    began = time.perf_counter()
    result = misdirect.robust_controller(
        problem,
        budget,
        memory=MEMORY,
        objective="decoy",
        randomized=True,
        restarts=restarts,
        seed=0,
        min_goal=floor,
        time_limit=TIME_LIMIT,
        max_rounds=max_rounds,
        baselines=("given", "blind"),
        exact_seed=exact_seed,
    )
    seconds = time.perf_counter() - began
    baselines = {
        b.name: {
            "worst_case": b.worst_case,
            "certified": b.certified,
            "nominal": b.nominal,
            "nominal_goal": b.nominal_goal,
        }
        for b in result.baselines
    }
    certified = bool(result.rounds) and all(r.certified for r in result.rounds)
    best_baseline = min(b["worst_case"] for b in baselines.values())
    below_paper = result.worst_case < PAPER[budget] - 1e-9
    no_worse = result.worst_case <= best_baseline + 1e-9
    return {
        "run": "plain" if floor is None else f"floor {floor:g}",
        "budget": budget,
        "worst_case": result.worst_case,
        "worst_case_bound": result.worst_case_bound,
        "certified": certified,
        "attack": result.alteration,
        "nominal_decoy": result.nominal,
        "nominal_goal": result.nominal_goal,
        "meets_floor": floor is None or result.nominal_goal >= floor - 1e-9,
        "paper": PAPER[budget],
        "given": baselines["given controller"]["worst_case"],
        "given_goal": baselines["given controller"]["nominal_goal"],
        "blind": baselines["observation-blind"]["worst_case"],
        "blind_goal": baselines["observation-blind"]["nominal_goal"],
        "below_paper": below_paper,
        "no_worse_than_baselines": no_worse,
        "pass": bool(certified and below_paper and no_worse),
        "rounds": len(result.rounds),
        "k_size": result.k_size,
        "iterations": sum(r.iterations for r in result.rounds),
        "stop_reason": result.stop_reason,
        "deterministic": result.controller.is_deterministic,
        "seconds": round(seconds, 2),
        "per_round": [r.to_dict() for r in result.rounds],
    }


EXACT_FLOOR = 0.9
RANDOMIZED_LABEL = f"robust randomized (2 nodes), Pr(goal) ≥ {FLOOR:g}"
FLOOR_LABEL = f"robust, min-max Pr(decoy), Pr(goal) ≥ {EXACT_FLOOR:g}"
GOAL_LABEL = "robust, max-min Pr(goal)"


def exact(
    budget: int, kinds: tuple[str, ...], runs: tuple[str, ...] = ("goal", "floor")
) -> tuple[list[dict], list[dict]]:
    """The exact master (one node, deterministic) at ``budget``: max-min Pr(goal), and
    min-max Pr(decoy) under the floor with the baselines ``kinds``. Returns the rows and the
    trade-off points (nominal Pr(goal), certified worst-case Pr(decoy))."""
    import misdirect
    from misdirect.defence.robust_oracle import oracle
    from misdirect.scenarios import paper_grid

    problem = paper_grid()
    rows, points = [], []
    for run_name, objective, floor in (("goal", "goal", None), ("floor", "decoy", EXACT_FLOOR)):
        if run_name not in runs:
            continue
        began, cpu = time.perf_counter(), time.process_time()
        result = misdirect.robust_controller(
            problem, budget, objective=objective, min_goal=floor, baselines=kinds if floor else ()
        )
        seconds, cpu = time.perf_counter() - began, time.process_time() - cpu
        # the controller's worst-case Pr(decoy) (the goal run proved its worst Pr(goal))
        decoy = (
            oracle(problem, result.controller, "decoy", budget, None)
            if objective == "goal"
            else None
        )
        worst_decoy = result.worst_case if decoy is None else decoy.value
        decoy_certified = result.certified if decoy is None else decoy.certified
        rows.append(
            {
                "run": run_name,
                "budget": budget,
                "objective": objective,
                "min_goal": floor,
                "worst_case": result.worst_case,
                "lower_bound": result.lower,
                "upper_bound": result.upper,
                "optimal": result.optimal,
                "nominal_goal": result.nominal_goal,
                "worst_decoy": worst_decoy,
                "rounds": len(result.rounds),
                "k_size": result.k_size,
                "candidates": sum(r.candidates for r in result.rounds),
                "stop_reason": result.stop_reason,
                "seconds": round(seconds, 2),
                "cpu_seconds": round(cpu, 2),  # this process's CPU time (the machine is shared)
                "master_seconds": round(sum(r.time_s for r in result.rounds), 2),
                "attack": result.alteration,
                "baselines": [b.to_dict() for b in result.baselines],
                "skipped_baselines": [b.to_dict() for b in result.skipped_baselines],
            }
        )
        points.append(
            {
                "budget": budget,
                "label": GOAL_LABEL if objective == "goal" else FLOOR_LABEL,
                "nominal_goal": result.nominal_goal,
                "worst_decoy": worst_decoy,
                "certified": decoy_certified,
            }
        )
        for b in result.baselines:
            points.append(
                {
                    "budget": budget,
                    "label": "harden" if b.kind == "harden" else b.name,
                    "nominal_goal": b.nominal_goal,
                    "worst_decoy": b.worst_case,
                    "certified": b.certified,
                }
            )
    return rows, points


def write_exact(rows: list[dict], out: Path) -> list[str]:
    """robust_exact.csv, and the markdown lines of the exact table."""
    fields = [
        "run", "budget", "objective", "min_goal", "worst_case", "lower_bound", "upper_bound",
        "optimal", "nominal_goal", "worst_decoy", "rounds", "k_size", "candidates", "seconds",
        "cpu_seconds", "master_seconds",
    ]  # fmt: skip
    with (out / "robust_exact.csv").open("w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=fields, extrasaction="ignore")
        writer.writeheader()
        writer.writerows(rows)
    lines = [
        "",
        "## Exact master: one node, deterministic",
        "",
        "| run | B | worst case | lower = upper | nominal Pr(goal) | worst Pr(decoy) | rounds | "
        "candidates | s | CPU s |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['run']} | {r['budget']} | {r['worst_case']:.6f} | "
            f"{'yes' if r['optimal'] else '**no**'} | {r['nominal_goal']:.4f} | "
            f"{r['worst_decoy']:.6f} | {r['rounds']} | {r['candidates']:,} | {r['seconds']:.1f} | "
            f"{r['cpu_seconds']:.1f} |"
        )
    for run_name in ("goal", "floor"):
        mine = [r for r in rows if r["run"] == run_name]
        if mine:
            total = sum(r["seconds"] for r in mine)
            cpu = sum(r["cpu_seconds"] for r in mine)
            proven = all(r["optimal"] for r in mine)
            lines.append(
                f"\n{run_name}: budgets {', '.join(str(r['budget']) for r in mine)} in "
                f"{total:.1f} s in all ({cpu:.1f} s of this process's CPU; baselines included), "
                f"all proven: {proven}"
            )
    baseline_lines = ["", "## Baselines (floor runs), certified worst-case Pr(decoy)", ""]
    baseline_lines += [
        "| B | baseline | nominal Pr(goal) | worst case | note |",
        "|---|---|---|---|---|",
    ]
    for r in rows:
        for b in r["baselines"]:
            baseline_lines.append(
                f"| {r['budget']} | {b['name']} | {b['nominal_goal']:.4f} | {b['worst_case']:.6f} "
                f"| {b['note'] or ''} |"
            )
        for b in r["skipped_baselines"]:
            baseline_lines.append(f"| {r['budget']} | {b['kind']} (skipped) | | | {b['reason']} |")
    return lines + baseline_lines


def plot(points: list[dict], path: Path, figure: Path | None) -> None:
    """The trade-off figure at ``path`` (and at ``figure``, for the docs)."""
    from misdirect.report.figures import robust_tradeoff_figure

    title = "the paper's grid, 5x5: robustness against nominal performance"
    for target in (path, figure):
        if target is not None:
            robust_tradeoff_figure(points, target, title=title)


def write(
    rows: list[dict],
    out: Path,
    quick: bool,
    exact_rows: list[dict],
    points: list[dict],
    figure: Path | None,
) -> None:
    out.mkdir(parents=True, exist_ok=True)
    machine = f"{platform.machine()}, Python {platform.python_version()}, {platform.system()}"
    (out / "robust.json").write_text(
        json.dumps(
            {
                "mode": "quick" if quick else "full",
                "machine": machine,
                "rows": rows,
                "exact": exact_rows,
                "points": points,
            },
            indent=1,
        )
        + "\n"
    )
    if points:
        plot(points, out / "robust_tradeoff.png", figure)
    fields = [
        "run", "budget", "worst_case", "certified", "nominal_goal", "meets_floor", "paper",
        "given", "blind", "blind_goal", "below_paper", "no_worse_than_baselines", "pass",
        "rounds", "k_size", "iterations", "deterministic", "seconds",
    ]  # fmt: skip
    with (out / "robust.csv").open("w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=fields, extrasaction="ignore")
        writer.writeheader()
        writer.writerows(rows)
    lines = [
        f"# Robust controllers: the paper's grid, {MEMORY} nodes, randomized "
        f"({'quick' if quick else 'full'} mode)",
        "",
        f"Machine: {machine}. Worst-case Pr(decoy), each certified by misdirect.solve for the "
        "controller it belongs to; nominal Pr(goal) in brackets.",
        "",
        "| run | B | robust | paper's controller | blind baseline | below paper | "
        "no worse than baselines | rounds | s |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['run']} | {r['budget']} | {r['worst_case']:.6f} ({r['nominal_goal']:.4f}) | "
            f"{r['given']:.6f} ({r['given_goal']:.4f}) | {r['blind']:.6f} "
            f"({r['blind_goal']:.4f}) | {'yes' if r['below_paper'] else '**no**'} | "
            f"{'yes' if r['no_worse_than_baselines'] else '**no**'} | {r['rounds']} | "
            f"{r['seconds']:.1f} |"
        )
    if exact_rows:
        lines += write_exact(exact_rows, out)
    (out / "robust.md").write_text("\n".join(lines) + "\n")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("bench/results"))
    parser.add_argument("--quick", action="store_true", help="a few seconds (smoke test)")
    parser.add_argument("--budgets", default="1,2,3,4", help="of the randomized runs")
    parser.add_argument("--exact-budgets", default="0,1,2,3,4", help="of the exact runs")
    parser.add_argument("--parts", default="exact,randomized")
    parser.add_argument("--figure", type=Path, default=None, help="also write the figure here")
    parser.add_argument(
        "--replot", type=Path, default=None, help="draw the figure from this robust.json only"
    )
    args = parser.parse_args()
    if args.replot is not None:
        points = json.loads(args.replot.read_text())["points"]
        plot(points, args.out / "robust_tradeoff.png", args.figure)
        return
    parts = {p.strip() for p in args.parts.split(",") if p.strip()}
    exact_budgets = [0] if args.quick else [int(b) for b in args.exact_budgets.split(",") if b]
    kinds = ("given", "blind", "harden") if args.quick else ("given", "blind", "harden", "paynt")
    exact_rows: list[dict] = []
    points: list[dict] = []
    if "exact" in parts:
        for budget in exact_budgets:
            got, more = exact(budget, kinds, ("floor",) if args.quick else ("goal", "floor"))
            for r in got:
                print(
                    f"exact {r['run']} B={budget}: {r['worst_case']:.6f} proven {r['optimal']}, "
                    f"goal {r['nominal_goal']:.4f}, decoy {r['worst_decoy']:.6f}, "
                    f"{r['rounds']} rounds, {r['seconds']:.1f} s",
                    flush=True,
                )
            exact_rows += got
            points += more
    rows = []
    if "randomized" in parts:
        budgets = [1] if args.quick else [int(b) for b in args.budgets.split(",") if b]
        restarts = 1 if args.quick else 4
        for floor in (None,) if args.quick else (None, FLOOR):
            for budget in budgets:
                row = run(
                    budget,
                    floor,
                    restarts,
                    max_rounds=1 if args.quick else None,
                    exact_seed=not args.quick,  # the one-node class: 40 s
                )
                print(
                    f"{row['run']} B={budget}: worst {row['worst_case']:.6f} (paper "
                    f"{row['paper']:.6f}, blind {row['blind']:.6f}), goal "
                    f"{row['nominal_goal']:.4f}, {row['rounds']} rounds, {row['seconds']:.1f} s, "
                    f"pass {row['pass']}",
                    flush=True,
                )
                rows.append(row)
                if floor is not None:
                    points.append(
                        {
                            "budget": budget,
                            "label": RANDOMIZED_LABEL,
                            "nominal_goal": row["nominal_goal"],
                            "worst_decoy": row["worst_case"],
                            "certified": row["certified"],
                        }
                    )
    write(rows, args.out, args.quick, exact_rows, points, args.figure)


if __name__ == "__main__":
    main()
