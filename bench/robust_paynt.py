"""The PAYNT master against the gradient master on the paper's grid (issue 54, docs/robust.md).

    python bench/robust_paynt.py [--out bench/results] [--budgets 1,2,3,4] [--runs floor,plain]
        [--time-limit 240] [--no-exact-seed] [--quick]

For each budget B, ``robust_controller(paper_grid(), B, memory=2, master="paynt",
objective="decoy", min_goal=0.9)`` (``floor``) and without the floor (``plain``), with the
baselines of ``bench/robust.py``'s randomized runs (given, blind), the same seeds (given,
blind, exact one-node; ``--no-exact-seed`` leaves the last out) and the same time limit (240 s).
Per run: the certified worst-case Pr(decoy) of the controller returned, its nominal Pr(goal),
the best certified worst case among the PAYNT master's own rounds (its syntheses, the seeds
left out), the rounds and the time, next to the gradient master's row of
``bench/results/robust.json`` (same problem, budget, floor, seeds and time limit) and the
paper's controller (0.719924 / 0.860130 / 0.862442 / 0.863622).

Writes robust_paynt.json, .csv and .md under --out. ``--quick``: budget 1, plain, 30 s.
"""

from __future__ import annotations

import argparse
import csv
import json
import platform
import time
from pathlib import Path

PAPER = {1: 0.719924, 2: 0.860130, 3: 0.862442, 4: 0.863622}  # the paper's controller
FLOOR = 0.9
TIME_LIMIT = 240.0
MEMORY = 2
CLOSE = 1e-9  # two worst cases this close are equal


def run(budget: int, floor: float | None, time_limit: float, exact_seed: bool) -> dict:
    import misdirect
    from misdirect.scenarios import paper_grid

    began = time.perf_counter()
    cpu = time.process_time()
    result = misdirect.robust_controller(
        paper_grid(),
        budget,
        memory=MEMORY,
        objective="decoy",
        master="paynt",
        min_goal=floor,
        time_limit=time_limit,
        baselines=("given", "blind"),
        exact_seed=exact_seed,
    )
    seconds = time.perf_counter() - began
    base = {b.kind: b for b in result.baselines}
    own = [r.worst_case for r in result.rounds if r.certified]
    seeds = [s.worst_case for s in result.seeds if s.certified]
    from_round = bool(own) and min(own) <= result.worst_case + CLOSE
    return {
        "run": "plain" if floor is None else f"floor {floor:g}",
        "budget": budget,
        "worst_case": result.worst_case,
        "certified": result.certified,
        "attack": result.alteration,
        "nominal_goal": result.nominal_goal,
        "meets_floor": floor is None or (result.nominal_goal or 0.0) >= floor - CLOSE,
        "best_round": min(own) if own else None,
        "answer_from": "a PAYNT round" if from_round else "a seed",
        "best_seed": min(seeds) if seeds else None,
        "paper": PAPER[budget],
        "given": base["given"].worst_case,
        "blind": base["blind"].worst_case,
        "blind_goal": base["blind"].nominal_goal,
        "rounds": len(result.rounds),
        "syntheses": sum(r.candidates for r in result.rounds),
        "stop_reason": result.stop_reason,
        "notes": list(result.notes),
        "seconds": round(seconds, 2),
        "cpu_seconds": round(time.process_time() - cpu, 2),
        "per_round": [r.to_dict() for r in result.rounds],
        "seeds": [s.to_dict() for s in result.seeds],
    }


def gradient_rows(path: Path) -> dict[tuple[str, int], dict]:
    """The gradient master's rows of bench/robust.py (same grid, budgets, floor, seeds and
    time limit), by (run, budget)."""
    if not path.exists():
        return {}
    rows = json.loads(path.read_text())["rows"]
    return {(r["run"], int(r["budget"])): r for r in rows}


def number(value: float | None) -> str:
    return "–" if value is None else f"{value:.6f}"


def write(rows: list[dict], gradient: dict, out: Path, meta: dict) -> None:
    out.mkdir(parents=True, exist_ok=True)
    (out / "robust_paynt.json").write_text(json.dumps({**meta, "rows": rows}, indent=1) + "\n")
    columns = [
        "run", "budget", "worst_case", "certified", "nominal_goal", "best_round",
        "answer_from", "paper", "given", "blind", "rounds", "syntheses", "seconds",
        "cpu_seconds", "stop_reason",
    ]  # fmt: skip
    with (out / "robust_paynt.csv").open("w", newline="") as handle:
        writer = csv.DictWriter(handle, columns, extrasaction="ignore")
        writer.writeheader()
        writer.writerows(rows)
    lines = [
        "# The PAYNT master on the paper's grid (2 nodes)",
        "",
        f"`{meta['command']}` on {meta['machine']}, {meta['date']}.",
        "",
        "Certified worst-case Pr(decoy), nominal Pr(goal) in brackets; gradient: "
        "bench/results/robust.json (bench/robust.py, same seeds and time limit).",
        "",
        "| run | B | PAYNT master | its best round | answer from | gradient master "
        "| paper's controller | blind | rounds (syntheses) | s (CPU s) |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        g = gradient.get((r["run"], r["budget"]))
        grad = "–" if g is None else f"{g['worst_case']:.6f} ({g['nominal_goal']:.4f})"
        lines.append(
            f"| {r['run']} | {r['budget']} | {r['worst_case']:.6f} ({r['nominal_goal']:.4f}) "
            f"| {number(r['best_round'])} | {r['answer_from']} | {grad} | {r['paper']:.6f} "
            f"| {r['blind']:.6f} ({r['blind_goal']:.4f}) | {r['rounds']} ({r['syntheses']}) "
            f"| {r['seconds']:.1f} ({r['cpu_seconds']:.1f}) |"
        )
    (out / "robust_paynt.md").write_text("\n".join(lines) + "\n")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("bench/results"))
    parser.add_argument("--budgets", default="1,2,3,4")
    parser.add_argument("--runs", default="floor,plain")
    parser.add_argument("--time-limit", type=float, default=TIME_LIMIT)
    parser.add_argument("--no-exact-seed", action="store_true")
    parser.add_argument("--quick", action="store_true", help="budget 1, plain, 30 s")
    args = parser.parse_args()
    budgets = [int(b) for b in args.budgets.split(",") if b.strip()]
    runs = [r.strip() for r in args.runs.split(",") if r.strip()]
    limit = args.time_limit
    if args.quick:
        budgets, runs, limit = [1], ["plain"], 30.0
    rows = []
    for name in runs:
        for budget in budgets:
            row = run(budget, FLOOR if name == "floor" else None, limit, not args.no_exact_seed)
            print(
                f"{row['run']} B={budget}: {row['worst_case']:.6f} "
                f"(goal {row['nominal_goal']:.4f}), best round {number(row['best_round'])}, "
                f"{row['rounds']} rounds, {row['seconds']:.1f} s",
                flush=True,
            )
            rows.append(row)
    meta = {
        "command": "python bench/robust_paynt.py "
        + (
            "--quick"
            if args.quick
            else " ".join(
                [f"--budgets {args.budgets}", f"--runs {args.runs}", f"--time-limit {limit:g}"]
                + (["--no-exact-seed"] if args.no_exact_seed else [])
            )
        ),
        "machine": f"{platform.machine()}, {platform.python_version()}",
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "time_limit": limit,
        "exact_seed": not args.no_exact_seed,
    }
    write(rows, gradient_rows(Path("bench/results/robust.json")), args.out, meta)


if __name__ == "__main__":
    main()
