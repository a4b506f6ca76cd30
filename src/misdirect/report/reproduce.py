"""``misdirect reproduce``: the paper's Section VII end to end, its numbers beside ours.

Four experiments, each written as Markdown + CSV tables and PNG + SVG figures under one folder,
tied together by ``report.md``:

1. the knapsack reduction example (SPEC §4) with the sizes of both MILP formulations;
2. the 5x5 grid case study, budgets 0..7 (SPEC §3), with the paper's printed values;
3. the scalability study on the scaled grid, compact vs the paper's formulation (its Fig. 4);
4. pictures of the optimal attacks on the 5x5 grid (expected visits per cell).
"""

from __future__ import annotations

import csv
import io
import platform
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from misdirect.core import tolerance
from misdirect.core.evaluate import decoy_probability, evaluate, evaluation_time
from misdirect.core.model import format_alteration
from misdirect.io.files import write_output
from misdirect.report import figures
from misdirect.scenarios import knapsack, paper_grid
from misdirect.scenarios.grid import OBSERVATIONS, hazard_cell, sensor_cells
from misdirect.solvers.run import SolveResult, solve
from misdirect.solvers.stats import MilpStats

# What the paper prints (Section VII). Budgets above 4 "remained the same".
PAPER_GRID = {0: 0.085, 1: 0.720, 2: 0.861, 3: 0.862, 4: 0.864, 5: 0.864, 6: 0.864, 7: 0.864}
PAPER_GRID_ALTERATIONS = {
    0: "none",
    1: "o1 → o3",
    2: "o1 → o5, o2 → o0",
    3: "o1 → o5, o2 → o0, o6 → o2",
    4: "o2 → o6, o5 → o1, o1 → o2, o6 → o3",
}
PAPER_REDUCTION = {"variables": 59_373, "rows": 236_477, "solve_time_s": 0.099}
KNAPSACK: dict[str, Any] = {
    "weights": [1, 2, 3, 4, 5],
    "values": [20, 30, 40, 50, 60],
    "capacity": 7,
}
QUICK_SIZES, FULL_SIZES = [5, 15, 25], [5, 15, 25, 35, 45]
SCALABILITY_BUDGET = 1  # the paper does not say which budget its Fig. 4 used
ATTACK_BUDGETS = [0, 1, 2, 4]
GRID_BUDGETS = list(range(8))
SHOWN_FIXED = 1e-6  # a value at least this is shown with six decimals, a smaller one in 3 figures
EXPERIMENTS = ("reduction example", "grid case study", "scalability study", "attack figures")
CONTROLLER_NOTE = (
    "The robot heads East after reading o0, o1, o4 or o6 and North after o2, o3 or o5, and keeps "
    "its heading on blank cells (b).\nAn altered sensor o1→o2 reports o2 instead of o1, so the "
    "robot reacts there as if it were at an o2 sensor."
)

Progress = Callable[[str, int, int], None]  # (experiment, done, total)


@dataclass
class Table:
    """One result table: written as CSV (numbers) and Markdown (for people)."""

    name: str
    title: str
    columns: list[str]
    rows: list[dict[str, Any]]
    note: str = ""

    def write(self, folder: Path) -> list[Path]:
        csv_path, md_path = folder / f"{self.name}.csv", folder / f"{self.name}.md"
        buffer = io.StringIO(newline="")
        writer = csv.DictWriter(buffer, fieldnames=self.columns, extrasaction="ignore")
        writer.writeheader()
        writer.writerows(self.rows)
        # atomic: a full disk leaves an earlier run's file as it was
        write_output(csv_path, buffer.getvalue(), field="out")
        write_output(md_path, self.markdown(), field="out")
        return [csv_path, md_path]

    def markdown(self) -> str:
        lines = [
            f"### {self.title}",
            "",
            "| " + " | ".join(self.columns) + " |",
            "|" + "---|" * len(self.columns),
        ]
        for row in self.rows:
            lines.append("| " + " | ".join(_cell(row.get(c)) for c in self.columns) + " |")
        if self.note:
            lines += ["", self.note]
        return "\n".join(lines) + "\n"


def _cell(value: Any) -> str:
    if value is None:
        return "—"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, float) and value.is_integer() and abs(value) < 1e6:
        return f"{int(value):,}"
    if isinstance(value, float):
        if 1e-3 <= abs(value) < 1:
            return f"{value:.6f}"
        if 1 <= abs(value) < 1e6:
            return f"{value:,.3f}"
        return f"{value:.3g}"
    if isinstance(value, int):
        return f"{value:,}"
    return str(value)


@dataclass
class ReproduceReport:
    out: Path
    mode: str
    tables: dict[str, Table] = field(default_factory=dict)
    figures: dict[str, list[Path]] = field(default_factory=dict)
    summary: list[dict[str, Any]] = field(default_factory=list)  # notes: a list of lines
    time_s: float = 0.0


def reproduce(
    out: Path,
    *,
    quick: bool = True,
    solver: str = "highs",
    time_limit: float | None = None,
    sizes: Sequence[int] | None = None,
    progress: Progress | None = None,
) -> ReproduceReport:
    """Run every experiment and write the report under ``out``."""
    began = time.perf_counter()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    limit = time_limit if time_limit is not None else (60.0 if quick else 600.0)
    sizes = list(sizes) if sizes is not None else (QUICK_SIZES if quick else FULL_SIZES)
    report = ReproduceReport(out=out, mode="quick" if quick else "full")
    tick = progress or (lambda name, done, total: None)

    # every bar appears at 0/total before the first experiment starts its work
    totals = dict(zip(EXPERIMENTS, (2, len(GRID_BUDGETS), 2 * len(sizes), 1), strict=True))
    for name, total in totals.items():
        tick(name, 0, total)
    _reduction(report, solver, limit, tick)
    grid_rows = _grid(report, solver, tick)
    _scalability(report, sizes, solver, limit, tick)
    _attacks(report, grid_rows, tick)
    for table in report.tables.values():
        table.write(out)
    report.time_s = time.perf_counter() - began
    _write_report(report, solver, limit, sizes)
    return report


# -- 1. the reduction example ----------------------------------------------------------------


def _milp_stats(result: SolveResult) -> MilpStats:
    """The record of a solve by method milp: its model's size and how the backend stopped."""
    stats = result.final.stats
    if not isinstance(stats, MilpStats):
        raise TypeError(f"expected a MILP's stats, got {type(stats).__name__}")
    return stats


def _reduction(report: ReproduceReport, solver: str, limit: float, tick: Progress) -> None:
    problem = knapsack(**KNAPSACK)
    rows = []
    for done, formulation in enumerate(("compact", "paper"), start=1):
        result = solve(
            problem, method="milp", solver=solver, formulation=formulation, time_limit=limit
        )
        stats = _milp_stats(result)
        rows.append(
            {
                "formulation": formulation,
                "variables": stats.variables,
                "rows": stats.rows,
                "build_time_s": stats.build_time_s,
                "solve_time_s": stats.solve_time_s,
                "solver_status": stats.status,
                "status": result.status,
                "probability": result.probability,
                "solver_probability": result.curve[-1].solver_probability,
                "alteration": format_alteration(result.alteration),
            }
        )
        tick("reduction example", done, 2)
    rows.append(
        {
            "formulation": "paper (as printed)",
            **PAPER_REDUCTION,
            "probability": 0.25,
            "status": "optimal",
            "alteration": "o4, o2, o1 → o♣",
        }
    )
    report.tables["reduction"] = Table(
        "reduction",
        "Reduction example (paper Sec. V, Fig. 3): knapsack weights 1..5, values 20..60, "
        "capacity 7",
        [
            "formulation",
            "variables",
            "rows",
            "build_time_s",
            "solve_time_s",
            "solver_status",
            "status",
            "probability",
            "solver_probability",
            "alteration",
        ],
        rows,
        note=_flags(rows[:2], "").strip()
        + "\n\nSizes: our `paper` row builds the paper's formulation with the successor filter "
        "(l[s,o,s',n',o'] only for s' a successor of s), as docs/milp.md describes and as "
        "the paper's grid experiment does. The paper's printed 59,373 variables / 236,477 rows "
        "for this "
        "example were built without that filter: l over every pair of (s, n, o), i.e. "
        "(9·3·9)² + 81 + 243 = 59,373 variables. We do not rebuild that unfiltered model; the "
        "`paper (as printed)` row quotes the paper. Optimum: (20+30+50)/(2·200) = 0.25.",
    )
    compact, paper = rows[0], rows[1]
    report.summary.append(
        {
            "experiment": "reduction example",
            "ours": f"{compact['probability']:.6f} with {compact['alteration']}",
            "paper": "0.25 with o4, o2, o1 → o♣",
            "agrees": _yes(abs(compact["probability"] - 0.25) < tolerance.CERTIFY),
            "notes": [
                f"MILP sizes: compact {compact['variables']:,} vars / {compact['rows']:,} rows; "
                f"paper {paper['variables']:,} / {paper['rows']:,} (successor filter); "
                f"paper prints {PAPER_REDUCTION['variables']:,} / {PAPER_REDUCTION['rows']:,} "
                "(no successor filter)",
                *_flag_lines(rows[:2]),
            ],
        }
    )


# -- 2. the grid case study ------------------------------------------------------------------


def _grid(report: ReproduceReport, solver: str, tick: Progress) -> list[dict[str, Any]]:
    problem = paper_grid(5, budget=7)
    goal = problem.pomdp.states.index("(4,4)")
    budgets = GRID_BUDGETS
    result = solve(
        problem,
        method="milp",
        solver=solver,
        budgets=budgets,
        # the budgets' bar: a phase without a count (total 0) is no step of it
        progress=lambda done, total, **_: (
            tick("grid case study", done, total) if total > 0 else None
        ),
    )
    rows: list[dict[str, Any]] = []
    for point in result.curve:
        b = int(point.budget)
        alpha = problem.alteration(point.alteration)
        outcome = evaluate(problem, alpha)
        printed = PAPER_GRID[b]
        paper_alteration = PAPER_GRID_ALTERATIONS.get(min(b, 4))
        paper_value = (
            decoy_probability(problem, problem.alteration(_parse(paper_alteration)))
            if paper_alteration
            else None
        )
        rows.append(
            {
                "budget": b,
                "probability": point.probability,
                "paper_printed": f"{printed:.3f}",
                "rounding_agrees": round(point.probability, 3) == printed,
                "status": point.status,
                "alteration": format_alteration(point.alteration),
                "paper_alteration": paper_alteration,
                "paper_alteration_value": paper_value,
                "goal_probability": float(outcome.outcomes.get(problem.pomdp.states[goal], 0.0)),
                "cost": point.cost,
                "_alteration": point.alteration,
                "_visits": outcome.expected_visits,
            }
        )
    report.tables["grid"] = Table(
        "grid",
        "Grid case study (paper Sec. VII-B): 5x5 grid, budgets 0..7",
        [
            "budget",
            "probability",
            "paper_printed",
            "rounding_agrees",
            "alteration",
            "paper_alteration",
            "paper_alteration_value",
            "goal_probability",
            "cost",
            "status",
        ],
        rows,
        note="`probability` is exact for the alteration found; `paper_alteration_value` is the "
        "exact value of the alteration the paper prints. At budget 2 the paper prints 0.861; "
        "the optimum is 0.860130 (a rounding slip in the paper). Our `o1 → o2` and the paper's "
        "`o1 → o3` are the same attack: the controller reacts to o2 and o3 identically.",
    )
    mismatched = [r["budget"] for r in rows if not r["rounding_agrees"]]
    report.summary.append(
        {
            "experiment": "grid case study",
            "ours": ", ".join(f"{r['probability']:.6f}" for r in rows[:5]) + " (budgets 0..4)",
            "paper": ", ".join(f"{PAPER_GRID[b]:.3f}" for b in range(5)),
            "agrees": "yes"
            if not mismatched
            else f"to 3 decimals except budget {_join(mismatched)} (paper's rounding)",
            "notes": [
                f"budget {b}: paper prints {PAPER_GRID[b]:.3f}, exact optimum "
                f"{rows[b]['probability']:.6f}"
                for b in mismatched
            ],
        }
    )
    return rows


# -- 3. scalability --------------------------------------------------------------------------


def _scalability(
    report: ReproduceReport, sizes: list[int], solver: str, limit: float, tick: Progress
) -> None:
    rows = []
    total = 2 * len(sizes)
    for i, n in enumerate(sizes):
        problem = paper_grid(n, budget=SCALABILITY_BUDGET)
        floor = evaluation_time(problem)
        for j, formulation in enumerate(("compact", "paper")):
            result = solve(
                problem,
                method="milp",
                solver=solver,
                formulation=formulation,
                budgets=[SCALABILITY_BUDGET],
                time_limit=limit,
            )
            stats = _milp_stats(result)
            rows.append(
                {
                    "n": n,
                    "formulation": formulation,
                    "variables": stats.variables,
                    "rows": stats.rows,
                    "nonzeros": stats.nonzeros,
                    "build_time_s": stats.build_time_s,
                    "solve_time_s": stats.solve_time_s,
                    "status": result.status,
                    "solver_status": stats.status,
                    "probability": result.probability,
                    "solver_probability": result.curve[-1].solver_probability,
                    "evaluation_time_s": floor,
                }
            )
            tick("scalability study", 2 * i + j + 1, total)
    report.tables["scalability"] = Table(
        "scalability",
        f"Scalability on the scaled grid (budget {SCALABILITY_BUDGET}, time limit {limit:g} s "
        "per solve)",
        [
            "n",
            "formulation",
            "variables",
            "rows",
            "nonzeros",
            "build_time_s",
            "solve_time_s",
            "solver_status",
            "status",
            "probability",
            "solver_probability",
            "evaluation_time_s",
        ],
        rows,
        note=_flags(rows, f" (time limit {limit:g} s per solve)")
        + "`solver_status` is how the MILP solver stopped (`time_limit`: at the limit, with "
        "its incumbent); `status` is ours: `unverified` when the solver's own value differs from "
        "the exact value of its alteration. The paper reports, for n = 45, more than 1.6 "
        "million variables and more than 6.2 million constraints for its formulation. "
        "`probability` is always the exact value of "
        "the alteration returned; `solver_probability` is what the MILP itself believed (the "
        "paper's formulation can claim 1 on a trap). `evaluation_time_s`: one exact "
        "evaluation of the unaltered chain, the floor of any method.",
    )
    report.figures["scalability"] = figures.scalability_panels(
        rows, report.out / "scalability", time_limit=limit
    )
    largest = [r for r in rows if r["n"] == max(sizes)]
    paper_45 = next((r for r in rows if r["n"] == 45 and r["formulation"] == "paper"), None)
    report.summary.append(
        {
            "experiment": "scalability study",
            "ours": "n={}: compact {:,} vars / {:,} rows; paper {:,} vars / {:,} rows".format(
                max(sizes),
                largest[0]["variables"],
                largest[0]["rows"],
                largest[1]["variables"],
                largest[1]["rows"],
            ),
            "paper": "n=45: > 1.6 M variables, > 6.2 M constraints",
            "agrees": "n=45 is in --full only"
            if paper_45 is None
            else _yes(1.6e6 < paper_45["variables"] < 1.7e6 and 6.2e6 < paper_45["rows"] < 6.3e6),
            "notes": _flag_lines(rows, f" (limit {limit:g} s)"),
        }
    )


# -- 4. attack figures -----------------------------------------------------------------------


def _attacks(report: ReproduceReport, grid_rows: list[dict[str, Any]], tick: Progress) -> None:
    n = 5
    sensors = {OBSERVATIONS[k]: cells for k, cells in sensor_cells(n).items()}
    places: dict[str, Any] = {"start": (0, 0), "goal": (n - 1, n - 1), "decoy": hazard_cell(n)}
    report.figures["grid_layout"] = figures.grid_layout(
        n, sensors, stem=report.out / "grid_layout", **places
    )
    by_budget = {r["budget"]: r for r in grid_rows}
    panels, visit_rows = [], []
    for budget in ATTACK_BUDGETS:
        row = by_budget[budget]
        visits = np.asarray(row["_visits"]).reshape(n, n)  # state y*n+x -> [y, x]
        panels.append(
            {
                "budget": budget,
                "visits": visits,
                "probability": row["probability"],
                "goal_probability": row["goal_probability"],
                "alteration": row["_alteration"],
            }
        )
        visit_rows += [
            {"budget": budget, "x": x, "y": y, "expected_visits": float(visits[y, x])}
            for y in range(n)
            for x in range(n)
        ]
    report.figures["attacks"] = figures.attack_heatmaps(
        n, sensors, panels=panels, stem=report.out / "attacks", note=CONTROLLER_NOTE, **places
    )
    report.tables["attack_visits"] = Table(
        "attack_visits",
        "Expected visits per cell under the optimal attack (data of the attack figure)",
        ["budget", "x", "y", "expected_visits"],
        visit_rows,
    )
    tick("attack figures", 1, 1)


# -- report ----------------------------------------------------------------------------------


def _write_report(report: ReproduceReport, solver: str, limit: float, sizes: list[int]) -> None:
    lines = [
        "# misdirect reproduce: the paper's Section VII",
        "",
        f"Mode `{report.mode}`, solver `{solver}`, time limit {limit:g} s per solve, grid sizes "
        f"{sizes}; {report.time_s:.1f} s on {platform.platform()} (Python "
        f"{platform.python_version()}).",
        "",
        "| experiment | ours | paper | agrees | notes |",
        "|---|---|---|---|---|",
        *(
            f"| {s['experiment']} | {s['ours']} | {s['paper']} | {s['agrees']} | "
            + ("<br>".join(s.get("notes", [])) or "—")
            + " |"
            for s in report.summary
        ),
        "",
    ]
    for name in ("reduction", "grid", "scalability"):
        lines += [report.tables[name].markdown(), f"Data: [{name}.csv]({name}.csv)", ""]
    lines += [
        "### Figures",
        "",
        "![scalability](scalability.png)",
        "",
        "![grid layout](grid_layout.png) ![attacks](attacks.png)",
        "",
        "Heat-map data: [attack_visits.csv](attack_visits.csv). SVG versions sit beside each PNG.",
    ]
    write_output(report.out / "report.md", "\n".join(lines) + "\n", field="out")


def _label(row: dict[str, Any]) -> str:
    return f"{row['formulation']} n={row['n']}" if "n" in row else row["formulation"]


def _flag_lines(rows: Sequence[dict[str, Any]], limit_text: str = "") -> list[str]:
    """One short line per kind of problem: unverified answers and time-outs."""
    lines = []
    for formulation in dict.fromkeys(r["formulation"] for r in rows):
        wrong = [r for r in rows if r["formulation"] == formulation and r["status"] == "unverified"]
        if wrong:
            pairs = "; ".join(
                (f"n={r['n']}: " if "n" in r else "")
                + f"claims {_value(r['solver_probability'])}, exact {_value(r['probability'])}"
                for r in wrong
            )
            lines.append(f"UNVERIFIED {formulation} MILP answer ({pairs})")
    late = [_label(r) for r in rows if r.get("solver_status") == "time_limit"]
    if late:
        lines.append(f"timed out{limit_text}: {', '.join(late)}")
    return lines


def _flags(rows: Sequence[dict[str, Any]], limit_text: str) -> str:
    """The same problems as a paragraph for the Markdown tables (empty when there are none)."""
    text = ""
    for formulation in dict.fromkeys(r["formulation"] for r in rows):
        wrong = [r for r in rows if r["formulation"] == formulation and r["status"] == "unverified"]
        if not wrong:
            continue
        pairs = "; ".join(
            (f"n = {r['n']}: " if "n" in r else "")
            + f"claims {_value(r['solver_probability'])}, exact value "
            f"{_value(r['probability'])}"
            for r in wrong
        )
        text += (
            f"**Unverified: the {formulation} formulation's answers are wrong.** Its MILP claims "
            f"an optimum its own alteration does not reach ({pairs}). docs/milp.md explains why: "
            "its Bellman equalities admit the value 1 on states that cycle forever without "
            "reaching "
            "the decoy, so its answer and solve time are those of a wrong optimum. "
        )
    late = [_label(r) for r in rows if r.get("solver_status") == "time_limit"]
    if late:
        text += (
            f"**Timed out{limit_text}:** {', '.join(late)}. The solver stopped at the limit "
            "without proving optimality; the value shown is the exact value of its incumbent, "
            "and the solve time is a lower bound (a triangle, not joined to the line, in the "
            "figure). "
        )
    return text + ("\n\n" if text else "")


def _value(x: float | None) -> str:
    if x is None:
        return "nothing (no incumbent)"
    return f"{x:.6f}".rstrip("0").rstrip(".") if x >= SHOWN_FIXED or x == 0 else f"{x:.3g}"


def _parse(text: str) -> dict[str, str]:
    if text == "none":
        return {}
    return dict(part.split(" → ") for part in text.split(", "))


def _yes(flag: bool) -> str:
    return "yes" if flag else "NO"


def _join(numbers: Sequence[int]) -> str:
    return ", ".join(map(str, numbers))
