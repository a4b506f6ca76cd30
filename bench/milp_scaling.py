"""MILP benchmark on the paper's scaled grid: both formulations, sizes, build and solve times.

    python bench/milp_scaling.py [--sizes 5,15,25,35,45] [--budgets 0..7]
                                      [--paper-sizes 5,15,25,35,45] [--paper-solve-sizes 5,15]
                                      [--time-limit 60] [--out bench/results]

For every size: the compact formulation is built and solved for every budget (one model,
warm-started along the curve); the paper's formulation is built (its size and build time are
the paper's Fig. 4 panels) and, for the sizes in --paper-solve-sizes, solved too, under the
same per-budget time limit. Every row also carries the time of one exact evaluation of the
unaltered chain, measured in the same process, so times can be read as ratios to it.

Writes milp_scaling.json, milp_scaling.csv and milp_scaling.png under --out.
"""

from __future__ import annotations

import argparse
import csv
import json
import platform
from collections import Counter
from pathlib import Path

from misdirect import solve
from misdirect.core.evaluate import evaluation_time
from misdirect.scenarios import paper_grid
from misdirect.solvers.milp.solver import build_formulation


def _ints(text: str) -> list[int]:
    if ".." in text:
        low, high = (int(p) for p in text.split(".."))
        return list(range(low, high + 1))
    return [int(p) for p in text.split(",") if p]


def run(args: argparse.Namespace) -> list[dict]:
    """Every (size, formulation); results are rewritten after each, so a crash keeps the rest."""
    rows: list[dict] = []
    budgets = _ints(args.budgets)
    sizes = sorted(set(_ints(args.sizes)) | set(_ints(args.paper_sizes)))
    for n in sizes:
        problem = paper_grid(n, budget=max(budgets))
        floor = evaluation_time(problem)
        plans = []
        if n in _ints(args.sizes):
            plans.append(("compact", True))
        if n in _ints(args.paper_sizes):
            plans.append(("paper", n in _ints(args.paper_solve_sizes)))
        for formulation, solve_it in plans:
            model = build_formulation(problem, formulation, max(budgets))
            base = {
                "n": n,
                "formulation": formulation,
                "variables": model.n_columns,
                "binaries": int(model.integer.sum()),
                "rows": model.n_rows,
                "nonzeros": int(model.matrix.nnz),
                "build_time_s": model.build_time_s,
                "evaluation_time_s": floor,
            }
            del model
            if not solve_it:
                rows.append({**base, "budget": None, "status": "not_solved"})
                write(rows, args.out, args)
                print(
                    f"n={n:3d} {formulation:8s} built: {base['variables']:,} vars, "
                    f"{base['rows']:,} rows in {base['build_time_s']:.2f} s",
                    flush=True,
                )
                continue
            result = solve(
                problem,
                method="milp",
                budgets=budgets,
                formulation=formulation,
                # --time-limit is per budget, as in the paper's runs: the curve gets the sum
                # (solve's time_limit bounds the whole call, shared out among its budgets)
                time_limit=args.time_limit * len(budgets),
            )
            for point in result.curve:
                rows.append(
                    {
                        **base,
                        "budget": point.budget,
                        "status": point.status,
                        "solver_status": point.stats["status"],
                        "probability": point.probability,
                        "solver_probability": point.solver_probability,
                        "upper_bound": point.upper_bound,
                        "solve_time_s": point.stats["solve_time_s"],
                        "nodes": point.stats["nodes"],
                        "highs_crashes": point.stats.get("highs_crashes", 0),
                        "alteration": point.alteration,
                    }
                )
                print(
                    f"n={n:3d} {formulation:8s} B={point.budget:g}: {point.probability:.6f} "
                    f"({point.status}, claimed {point.solver_probability}) "
                    f"in {point.stats['solve_time_s']:.2f} s",
                    flush=True,
                )
            write(rows, args.out, args)
    return rows


def write(rows: list[dict], out: Path, args: argparse.Namespace) -> None:
    out.mkdir(parents=True, exist_ok=True)
    meta = {
        "command": "python bench/milp_scaling.py "
        + " ".join(f"--{k.replace('_', '-')} {v}" for k, v in vars(args).items() if k != "out"),
        "machine": platform.platform(),
        "python": platform.python_version(),
    }
    (out / "milp_scaling.json").write_text(json.dumps({"meta": meta, "rows": rows}, indent=2))
    fields = [
        "n",
        "formulation",
        "budget",
        "status",
        "probability",
        "solver_probability",
        "upper_bound",
        "variables",
        "binaries",
        "rows",
        "nonzeros",
        "build_time_s",
        "solve_time_s",
        "nodes",
        "evaluation_time_s",
    ]
    with (out / "milp_scaling.csv").open("w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=fields, extrasaction="ignore")
        writer.writeheader()
        writer.writerows(rows)
    plot(rows, out / "milp_scaling.png")
    (out / "milp_scaling.md").write_text(summary_table(rows), encoding="utf-8")


def summary_table(rows: list[dict]) -> str:
    """Two tables: per (n, formulation) the sizes and times, then the value at every budget."""
    lines = [
        "| n | formulation | variables | binaries | rows | build (s) | solve, all budgets (s) "
        "| statuses | solve ÷ one evaluation |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    keys = sorted({(r["n"], r["formulation"]) for r in rows})
    budgets = sorted({r["budget"] for r in rows if r.get("budget") is not None})
    values = [
        "| n | formulation | " + " | ".join(f"B={b:g}" for b in budgets) + " |",
        "|---|---|" + "---|" * len(budgets),
    ]
    for n, formulation in keys:
        mine = [r for r in rows if r["n"] == n and r["formulation"] == formulation]
        first = mine[0]
        solved = [r for r in mine if r.get("solve_time_s") is not None]
        if solved:
            total = sum(r["solve_time_s"] for r in solved)
            statuses = Counter(r["status"] for r in solved)
            cells = [
                f"{total:.1f}",
                ", ".join(f"{k} {v}" for k, v in sorted(statuses.items())),
                f"{total / first['evaluation_time_s']:,.0f}",
            ]
            by_budget = {r["budget"]: r for r in solved}
            values.append(
                f"| {n} | {formulation} | "
                + " | ".join(_value_cell(by_budget.get(b)) for b in budgets)
                + " |"
            )
        else:
            cells = ["not solved", "—", "—"]
        lines.append(
            f"| {n} | {formulation} | {first['variables']:,} | {first['binaries']:,} | "
            f"{first['rows']:,} | {first['build_time_s']:.2f} | " + " | ".join(cells) + " |"
        )
    notes = (
        "Each value is the exact Pr(reach decoy) of the alteration the solver returned. "
        "* = stopped at the time limit (the value of its incumbent); "
        "(claims x) = the solver's own objective, where it differs from the exact value by "
        "more than 1e-6."
    )
    return "\n".join(lines) + "\n\n" + "\n".join(values) + "\n\n" + notes + "\n"


def _value_cell(row: dict | None) -> str:
    if row is None:
        return "—"
    value = row["probability"]
    cell = f"{value:.8f}" if value >= 1e-3 else f"{value:.2e}"
    if row["status"] == "time_limit":
        cell += "*"
    claimed = row.get("solver_probability")
    if claimed is not None and abs(claimed - row["probability"]) > 1e-6:
        cell += f" (claims {claimed:.3f})"
    return cell


def plot(rows: list[dict], path: Path) -> None:
    """The reproduce command's scalability panels, with solve time summed over the budgets."""
    from misdirect.report.figures import scalability_panels

    totals = []
    for n, formulation in sorted({(r["n"], r["formulation"]) for r in rows}):
        mine = [r for r in rows if r["n"] == n and r["formulation"] == formulation]
        solved = [r for r in mine if r.get("solve_time_s") is not None]
        totals.append(
            {
                **mine[0],
                "solve_time_s": sum(r["solve_time_s"] for r in solved) if solved else None,
                "solver_status": "time_limit"
                if any(r.get("solver_status") == "time_limit" for r in solved)
                else "optimal",
            }
        )
    scalability_panels(totals, path.with_suffix(""), formats=(path.suffix,))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--sizes", default="5,15,25,35,45")
    parser.add_argument("--paper-sizes", default="5,15,25,35,45")
    parser.add_argument("--paper-solve-sizes", default="5,15")
    parser.add_argument("--budgets", default="0..7")
    parser.add_argument("--time-limit", type=float, default=60.0)
    parser.add_argument("--out", type=Path, default=Path("bench/results"))
    args = parser.parse_args()
    run(args)


if __name__ == "__main__":
    main()
