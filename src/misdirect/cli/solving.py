"""The attacker's commands: evaluate, solve, simulate, show."""

from __future__ import annotations

import csv
import dataclasses
import io
import math
import signal
import time
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import numpy as np
import typer
from rich.markup import escape
from rich.table import Table

from misdirect.cli.cluster import ClusterOption, WorkersOption, check_workers
from misdirect.cli.common import (
    INTERRUPTED,
    TERMINATED,
    ProgressBars,
    check_range,
    check_seconds,
    err,
    flag,
    fmt_alteration,
    json_text,
    out,
    print_handovers,
    print_json,
    stop_gracefully,
    wrote,
)
from misdirect.cli.options import (
    MAX_RUNS,
    MAX_SAMPLES,
    MAX_SEED,
    MAX_STEPS,
    AlterationFileOption,
    AlterOption,
    AtBudgetOption,
    BudgetOption,
    ExactOption,
    JsonOption,
    ProblemSource,
    alteration,
    parse_budgets,
    problem_input,
)
from misdirect.cli.pictures import (
    CoordinatesOption,
    PictureOption,
    check_picture_suffix,
    picture_cells,
)
from misdirect.core.alterations import max_alteration_cost
from misdirect.core.evaluate import Evaluation, decoy_probability
from misdirect.core.evaluate import evaluate as evaluate_alteration
from misdirect.core.model import AlterationArray, Problem
from misdirect.core.tolerance import CERTIFY
from misdirect.errors import ProblemError
from misdirect.io.files import check_output_path, one_line, write_output
from misdirect.report import json_output
from misdirect.solvers import SOLVERS
from misdirect.solvers.milp.backends import BACKENDS
from misdirect.solvers.milp.solver import FORMULATIONS
from misdirect.solvers.options import MILP_OPTIONS, implied_method
from misdirect.solvers.run import BudgetResult, SolveResult
from misdirect.solvers.run import solve as solve_problem
from misdirect.solvers.stats import AutoStats, MethodStats, MilpStats
from misdirect.solvers.status import Status

if TYPE_CHECKING:
    from misdirect.core.simulate import Simulation
    from misdirect.io.exact_model import ExactValue

# -- evaluate -----------------------------------------------------------------------------------


@problem_input
def evaluate(
    source: ProblemSource,
    alter: AlterOption = None,
    alteration_file: AlterationFileOption = None,
    at_budget: AtBudgetOption = None,
    exact: ExactOption = False,
    as_json: JsonOption = False,
) -> None:
    """Exact probability of reaching the decoy under one alteration (none by default)."""
    problem = source.load()
    altered = alteration(problem, alter, alteration_file, at_budget)
    result = evaluate_alteration(problem, altered)
    baseline = (
        result.probability
        if not result.alteration
        else decoy_probability(problem, problem.identity())
    )
    as_written = exact_values(problem, [altered])[0] if exact else None
    notes = [*result.notes, *exact_notes([result.error_bound], [as_written])]
    if as_json:
        payload = json_output.evaluation(result, baseline, as_written)
        payload["notes"] = notes
        print_json(payload)
    else:
        _print_evaluation(result, baseline, problem, as_written)
        _print_notes(notes)
    _print_warnings(result.warnings)
    if result.warnings:
        raise typer.Exit(1)


def _print_warnings(warnings: Iterable[str]) -> None:
    for warning in warnings:
        err.print(f"[bold red]warning:[/] {escape(one_line(warning))}", highlight=False)


def _print_notes(notes: Iterable[str]) -> None:
    """Notes on stderr (``--json`` carries them in ``notes``): no change of exit code."""
    for text in notes:
        err.print(f"[bold]note:[/] {escape(one_line(text))}", highlight=False)


def exact_values(
    problem: Problem, alterations: Sequence[AlterationArray | None]
) -> list[ExactValue | None]:
    """Each alteration's value on the model as written (``--exact``), Storm run once per
    distinct alteration (None where there is no alteration to check)."""
    from misdirect.io.exact_model import exact_model

    model = exact_model(problem)
    found: dict[bytes, ExactValue] = {}
    for altered in alterations:
        if altered is not None and np.asarray(altered).tobytes() not in found:
            found[np.asarray(altered).tobytes()] = model.value(altered)
    return [None if a is None else found[np.asarray(a).tobytes()] for a in alterations]


def exact_notes(
    error_bounds: Sequence[float | None],
    values: Sequence[ExactValue | None],
    budgets: Sequence[float] | None = None,
) -> list[str]:
    """A note where the model as written moves a value by more than what it is proven to on
    the chain as loaded (the input's rounding in doubles decides digits), once per value with
    the budgets it is about."""
    moved = []
    for i, (bound, value) in enumerate(zip(error_bounds, values, strict=True)):
        if value is None or abs(value.difference) <= max(bound or 0.0, CERTIFY):
            continue
        text = (
            f"on the model as written the value is {float(value.value):.12g}, "
            f"{value.difference:+.2e} from the chain as loaded in doubles, more than the "
            f"{CERTIFY:g} it is proven to there: the rounding of the model's probabilities "
            "decides these digits (docs/exactness.md)"
        )
        moved.append((text, None if budgets is None else budgets[i]))
    return _once_per_text(moved)


def _print_evaluation(
    result: Evaluation, baseline: float, problem: Problem, exact: ExactValue | None = None
) -> None:
    table = Table(title=escape(problem.title), show_header=False, box=None)
    table.add_column(no_wrap=True)
    table.add_column(overflow="fold")  # an alteration's names wrap, never cut
    table.add_row("alteration", fmt_alteration(result.alteration))
    budget_note = "" if result.within_budget else f"  [red](over budget {problem.budget:g})[/]"
    table.add_row("cost", f"{result.cost:g}{budget_note}")
    table.add_row(problem.objective.label, f"[bold]{result.probability:.6f}[/]")
    table.add_row(
        "  proven error",
        "none proven" if result.error_bound is None else f"at most {result.error_bound:.1e}",
    )
    if exact is not None:
        table.add_row(
            "  on the model as written",
            f"{float(exact.value):.12g} (Storm, rational arithmetic; "
            f"{exact.difference:+.1e} from the chain as loaded)",
        )
    for name, probability in result.decoy_sets.items():
        table.add_row(f"  Pr(first decoy in {escape(name)})", f"{probability:.6f}")
    table.add_row("without alteration", f"{baseline:.6f}")
    for state, probability in result.outcomes.items():
        table.add_row(f"  first hits {escape(state)}", f"{probability:.6f}")
    if result.never_absorbed > 0:
        table.add_row("  never absorbed", f"{result.never_absorbed:.6f}")
    for observation, reading, probability in result.alarm_readings():
        read = reading if reading == observation else f"{observation} read as {reading}"
        table.add_row(f"  alarm raised on {escape(read)}", f"{probability:.6f}")
    table.add_row(
        "product chain",
        f"{result.product_states:,} states, "
        f"{result.product_transitions:,} transitions ({result.time_s:.3f} s)",
    )
    out.print(table)


# -- solve --------------------------------------------------------------------------------------


@problem_input
def solve(
    source: ProblemSource,
    budget: BudgetOption = None,
    method: Annotated[
        str | None,
        typer.Option(
            help=f"Method: {', '.join(SOLVERS)} (default auto: enumerate small alteration "
            "spaces, with low-rank updates where it can, else branch-and-bound, or the MILP "
            "on knapsack-like models; all exact). A MILP option (--solver, --formulation, "
            "--mip-gap, --verbose) without --method means --method milp.",
            show_default=False,
        ),
    ] = None,
    solver: Annotated[
        str | None, typer.Option(help=f"MILP backend: {', '.join(BACKENDS)} (default highs).")
    ] = None,
    formulation: Annotated[
        str | None,
        typer.Option(
            help=f"MILP formulation: {', '.join(FORMULATIONS)} (default compact; the paper "
            "formulations are baselines and not exact)."
        ),
    ] = None,
    time_limit: Annotated[
        float | None,
        typer.Option(
            help="Seconds for the search, every method and budget; then each budget reports "
            "its best alteration, a proven upper bound and the gap (status time_limit). Reading "
            "the model and the exact evaluation of each answer come on top."
        ),
    ] = None,
    threads: Annotated[
        int | None,
        typer.Option(
            help="Threads of the MILP solver (SCIP: its concurrent mode if > 1), of the "
            "incremental enumeration and of branch-and-bound's searches and covers (default 2)."
        ),
    ] = None,
    mip_gap: Annotated[
        float | None,
        typer.Option(
            help="MILP: relative gap to stop at (default 2.5e-10); a point whose bound is still "
            "above its value is reported as gap_limit, not optimal."
        ),
    ] = None,
    verbose: Annotated[
        bool, typer.Option("--verbose", help="MILP: show the solver's log on stdout.")
    ] = False,
    quiet: Annotated[
        bool, typer.Option("--quiet", "-q", help="No progress or hand-over lines on stderr.")
    ] = False,
    output: Annotated[
        Path | None,
        typer.Option(
            "--output",
            "-o",
            help="Write the answer for --alteration FILE of evaluate, simulate, show and "
            "export-chain: .json the whole --json document (every budget; pick one with "
            "--at-budget), else (.yaml) the answer's alteration as {observation: received}. "
            "With several δ of --max-alarm: .json, or the figure of value against δ (.png, "
            ".svg, .pdf).",
            show_default=False,
        ),
    ] = None,
    max_alarm: Annotated[
        str | None,
        typer.Option(
            "--max-alarm",
            help="δ, or a list (0,0.01,0.1,1): the best attack whose Pr(alarm) is at most δ "
            "(0: the monitor never raises the alarm), each point certified for that "
            "constraint; a list prints value against δ per budget (--json: every curve). "
            "Implies --stealth (the consistency monitor) when no monitor is given.",
            show_default=False,
        ),
    ] = None,
    cluster: ClusterOption = None,
    workers: WorkersOption = None,
    exact: ExactOption = False,
    as_json: JsonOption = False,
) -> None:
    """Optimal alteration within the budget B (--budget, default: the file's). A range or a
    list (--budget 0..B, 0,1,3) answers each budget; one budget lists the smaller whole
    budgets too where the method gets them for free (a note says when it did not). With
    --cluster or --workers, the search's subtrees run on Dask (branch-and-bound, auto)."""
    if threads is not None:
        check_range("--threads", threads, 1, 1024)
    check_seconds(time_limit)
    if output is not None:
        check_output_path(output, field="-o")
    deltas = None if max_alarm is None else parse_max_alarm(max_alarm)
    if deltas is not None:
        source = dataclasses.replace(source, stealth=True)  # a monitor: consistency if none
    with ProgressBars(enabled=not quiet, transient=True) as bars:
        if bars:  # the first phase, before the solver's own: reading and building the problem
            bars.track("solving", 0, 0, stage="loading")
        problem = source.load()
    requested = parse_budgets(budget, cap=max_alteration_cost(problem))
    if requested is not None:
        problem = problem.with_budget(max(requested))
        if len(requested) == 1:  # one budget: let the solver add the curve if it comes free
            requested = None
    milp_options = {
        "solver": solver,
        "formulation": formulation,
        "time_limit": time_limit,
        "threads": threads,
        "mip_gap": mip_gap,
        "verbose": verbose or None,
    }
    if verbose and as_json:
        raise ProblemError(
            "cannot be combined with --json: the solver's log goes to stdout", field="--verbose"
        )
    given: dict[str, Any] = {k: v for k, v in milp_options.items() if v is not None}
    method, implied = milp_method(method, given)
    check_workers(workers)
    if (cluster is not None or workers is not None) and method not in ("auto", "branch-and-bound"):
        field = "--cluster" if cluster is not None else "--workers"
        raise ProblemError(
            f"does not apply to method {method} (auto and branch-and-bound only)", field=field
        )
    from misdirect.distributed import connect

    if deltas is not None and len(deltas) > 1:
        if exact:
            raise ProblemError(
                "takes one δ of --max-alarm (the values as written, per point)", field="--exact"
            )
        with connect(cluster, workers) as pool:
            if pool is not None:
                given["pool"] = pool
            _solve_tradeoff(problem, method, requested, given, deltas, quiet, as_json, output)
        return
    if deltas is not None:
        given["max_alarm"] = deltas[0]
    with connect(cluster, workers) as pool:
        if pool is not None:
            given["pool"] = pool
        result, received = _run_solve(problem, method, requested, given, quiet or as_json, quiet)
    as_written = None
    notes = [implied] if implied else []
    if exact:
        as_written = exact_values(problem, [p.alteration_array for p in result.curve])
        bounds = [p.error_bound for p in result.curve]
        notes += exact_notes(bounds, as_written, [p.budget for p in result.curve])
    payload = json_output.solve(result, notes=notes, exact=as_written)
    if output is not None:
        payload["written"] = [str(output)]
        write_output(output, _alteration_text(payload, output), field="-o")
    if as_json:
        print_json(payload)
    else:
        _print_solve(result, problem, as_written)
        alone = budget is None and len(result.curve) == 1 and result.curve[0].budget >= 1
        single = [_single_budget_note(result.curve[0].budget)] if alone else []
        _print_notes([*result.notes, *_point_notes(result.curve), *notes, *single])
        if output is not None:
            wrote(f"wrote {output} ({_written_what(output)})")
    _finish_solve(result, received)


FIGURE_SUFFIXES = (".png", ".svg", ".pdf")


def parse_max_alarm(text: str) -> list[float]:
    """``--max-alarm``: one probability or a comma-separated list, each in [0, 1]."""
    deltas = []
    for part in text.split(","):
        try:
            delta = float(part)
        except ValueError:
            raise ProblemError(
                f"must be a probability in [0, 1] or a list of them, got {part.strip()!r}",
                field="--max-alarm",
            ) from None
        if not (math.isfinite(delta) and 0.0 <= delta <= 1.0):
            raise ProblemError(
                f"must be a probability in [0, 1], got {part.strip()}", field="--max-alarm"
            )
        deltas.append(delta)
    return sorted(set(deltas))


def _solve_tradeoff(
    problem: Problem,
    method: str,
    budgets: list[float] | None,
    options: dict[str, Any],
    deltas: list[float],
    quiet: bool,
    as_json: bool,
    output: Path | None = None,
) -> None:
    """``--max-alarm`` with several δ: one certified curve per δ; a table of the value (and
    its status) against δ per budget, or (``--json``) every curve; ``-o`` writes the JSON
    (``.json``) or the figure of value against δ (``.png``, ``.svg``, ``.pdf``)."""
    if output is not None and output.suffix.lower() not in (".json", *FIGURE_SUFFIXES):
        raise ProblemError(
            "with several δ of --max-alarm, -o writes the --json document (.json) or the "
            f"figure of value against δ ({', '.join(FIGURE_SUFFIXES)}), not {output.name!r}",
            field="-o",
        )
    from misdirect.core.attack import shared_preparation
    from misdirect.solvers.engines.alarm import tradeoff_scope

    results = []
    with shared_preparation(), tradeoff_scope(problem):  # what δ does not change, once
        for delta in deltas:
            result, received = _run_solve(
                problem, method, budgets, {**options, "max_alarm": delta}, quiet or as_json, quiet
            )
            results.append(result)
            if received:
                _finish_solve(result, received)
    payload = json_output.solve(results[-1])
    payload["tradeoff"] = [r.to_dict() for r in results]
    if output is not None:
        payload["written"] = [str(output)]
        if output.suffix.lower() == ".json":
            write_output(output, json_text(payload), field="-o")
        else:
            from misdirect.report.figures import tradeoff_figure

            tradeoff_figure(results, output, title=problem.title)
    if as_json:
        print_json(payload)
    else:
        table = Table(
            title=escape(f"{problem.title} — value against Pr(alarm) <= δ ({results[0].method})")
        )
        table.add_column("budget", justify="right")
        for delta in deltas:
            table.add_column(f"δ = {delta:g}", justify="right")
        for j, point in enumerate(results[0].curve):
            cells = []
            for result in results:
                p = result.curve[j]
                shown = "—" if p.status == "infeasible" else f"{p.probability:.6f}"
                cells.append(f"{shown} {p.status}")
            table.add_row(f"{point.budget:g}", *cells)
        out.print(table)
        _print_notes([*results[-1].notes])
        if output is not None:
            wrote(f"wrote {output}")
    warnings = [w for r in results for w in r.warnings]
    _print_warnings(warnings)
    if warnings:
        raise typer.Exit(1)


def _written_what(output: Path) -> str:
    if output.suffix.lower() == ".json":
        return "every budget's answer: --alteration FILE --at-budget B reads one"
    return "the answer's alteration: --alteration FILE reads it"


def _alteration_text(payload: dict[str, Any], output: Path) -> str:
    """What ``solve -o`` writes: the ``--json`` document for a ``.json`` file, else the
    answer's alteration as a YAML mapping (with a comment saying what it is)."""
    if output.suffix.lower() == ".json":
        return json_text(payload)
    import yaml

    head = (
        f"# misdirect solve: {payload['problem']}, {payload['status']} alteration at budget "
        f"{payload['budget']:g} (value {payload['value']:.6f}); read by --alteration FILE\n"
    )
    body = payload["alteration"] or {}
    return head + yaml.safe_dump(body, sort_keys=False, allow_unicode=True, width=10**6)


def _single_budget_note(budget: float) -> str:
    """Why the table has one row: the method did not get the smaller budgets for free, and
    how to ask for them."""
    asked = f"0..{budget:g}" if budget.is_integer() else f"0,1,{budget:g}"
    return f"budget {budget:g} alone was solved: --budget {asked} answers each budget"


POINT_NOTES = ("trivial_bound", "not_certified")  # why a point is open: shown under the table


def _point_notes(curve: Sequence[BudgetResult]) -> list[str]:
    """The notes that say why a budget is left open, each once with the budgets it is about
    (``--json`` has every point's under ``certification``)."""
    return _once_per_text(
        (point.notes[key], point.budget)
        for point in curve
        for key in POINT_NOTES
        if key in point.notes
    )


def _once_per_text(notes: Iterable[tuple[str, float | None]]) -> list[str]:
    """Each note's text once, prefixed with the budgets it is about (none: as it is)."""
    budgets: dict[str, list[str]] = {}
    for text, budget in notes:
        budgets.setdefault(text, []).append("" if budget is None else f"{budget:g}")
    return [
        text
        if not listed[0]
        else f"budget{'s' if len(listed) > 1 else ''} {', '.join(listed)}: {text}"
        for text, listed in budgets.items()
    ]


def milp_method(method: str | None, given: dict[str, Any]) -> tuple[str, str | None]:
    """The method to run, and the note saying so when a MILP option chose it.

    A MILP-only flag means what it says: without ``--method`` it selects the MILP, by the
    library's rule for ``method="auto"`` (:func:`~misdirect.solvers.options.implied_method`);
    with another method named, even ``--method auto``, it is refused in one line."""
    flags = [flag(name) for name in MILP_OPTIONS if name in given]
    if flags and method not in (None, "milp"):
        raise ProblemError(
            f"is a MILP option: it applies to --method milp only, not --method {method} "
            "(leave out --method to run the MILP)",
            field=flags[0],
        )
    resolved, implying = implied_method(method or "auto", given)
    if method is None and implying:
        return resolved, f"{', '.join(map(flag, implying))} implies --method milp"
    return resolved, None


def _run_solve(
    problem: Problem,
    method: str,
    budgets: list[float] | None,
    options: dict[str, Any],
    silent: bool,
    quiet: bool,
) -> tuple[SolveResult, list[int]]:
    """Solve with progress bars on a terminal (none with --quiet), else the hand-overs as
    lines (none when ``silent``); a first Ctrl-C or SIGTERM keeps the best answers so far."""
    with ProgressBars(enabled=not quiet, transient=True) as bars:
        progress = bars.task("solving") if bars else None
        if progress is None and not silent:
            progress = print_handovers  # no terminal: hand-overs still get a line each
        with stop_gracefully() as stop:
            result = solve_problem(
                problem,
                method=method,
                budgets=budgets,
                progress=progress,
                cancel=stop.token,
                **options,
            )
    return result, stop.received


def _finish_solve(result: SolveResult, received: list[int]) -> None:
    """Warnings on stderr, and the exit code: 1 after a warning, 130/143 after a signal."""
    _print_warnings(result.warnings)
    if received:  # the best answer so far is printed above, marked interrupted
        name = "terminated (SIGTERM)" if received[0] == signal.SIGTERM else "interrupted"
        err.print(f"{name}: the best answers found so far are shown", highlight=False)
        raise typer.Exit(TERMINATED if received[0] == signal.SIGTERM else INTERRUPTED)
    if result.warnings:
        raise typer.Exit(1)


def _print_solve(
    result: SolveResult, problem: Problem, exact: Sequence[ExactValue | None] | None = None
) -> None:
    within = "" if result.max_alarm is None else f", Pr(alarm) <= {result.max_alarm:g}"
    table = Table(title=escape(f"{problem.title} — optimal alterations{within} ({result.method})"))
    bounded = any(point.status != Status.OPTIMAL for point in result.curve)
    table.add_column("budget", justify="right")
    table.add_column(f"max {problem.objective.label}", justify="right")
    if bounded:
        table.add_column("upper bound", justify="right")
    # names are never cut ("beac…"): a long alteration wraps within its column
    table.add_column(
        "optimal alteration" if not bounded else "best alteration found", overflow="fold"
    )
    table.add_column("cost", justify="right")
    table.add_column("status")
    if exact is not None:  # what the model as written gives: digits past the 6th can differ
        table.add_column("as written (exact)", justify="right")
    if result.max_alarm is not None:  # --max-alarm: the constrained probability beside
        table.add_column("Pr(alarm)", justify="right")
    for i, point in enumerate(result.curve):
        bound = (
            []
            if not bounded
            else ["—" if point.upper_bound is None else f"{point.upper_bound:.6f}"]
        )
        written = [] if exact is None else [_as_written(exact[i])]
        if result.max_alarm is not None:
            written.append("—" if point.alarm is None else f"{point.alarm:.6f}")
        table.add_row(
            f"{point.budget:g}",
            f"{point.probability:.6f}",
            *bound,
            fmt_alteration(point.alteration),
            f"{point.cost:g}",
            point.status,
            *written,
        )
    out.print(table)
    out.print(escape(" · ".join(_solve_summary(result))), highlight=False)


def _as_written(value: ExactValue | None) -> str:
    return "—" if value is None else f"{float(value.value):.12g}"


def _solve_summary(result: SolveResult) -> list[str]:
    parts = [f"without alteration {result.baseline_probability:.6f}", f"{result.time_s:.2f} s"]
    errors = [point.error_bound for point in result.curve]
    if any(e is None or e > CERTIFY for e in errors):  # the chain defeats double precision
        worst = "none proven" if None in errors else f"{max(e or 0.0 for e in errors):.1e}"
        parts.insert(0, f"values proven only within {worst} (ill-conditioned chain)")
    if result.budget_clamped_from is not None:
        parts.insert(
            0,
            f"budgets above {result.budget_clamped_to:g} solved as {result.budget_clamped_to:g} "
            "(no alteration costs more)",
        )
    stats = result.stats
    if isinstance(stats, AutoStats):
        proven = all(point.status == Status.OPTIMAL for point in result.curve)
        verb = "certified by" if proven else "method"
        parts.append(f"{verb} {result.certified_by} ({stats.reason})")
        stats = stats.answer
    if isinstance(stats, MilpStats):
        answers = [_method_stats(point.stats) for point in result.curve]
        milps = [s for s in answers if isinstance(s, MilpStats)]
        nodes = sum(s.nodes or 0 for s in milps)
        solving = sum(s.solve_time_s for s in milps)
        model = stats.model
        parts += [
            f"{stats.formulation} MILP on {stats.solver}: {model['variables']:,} variables "
            f"({model['binaries']:,} binary), {model['rows']:,} rows, "
            f"{model['nonzeros']:,} non-zeros",
            f"built in {model['build_time_s']:.2f} s, solved in {solving:.2f} s, {nodes:,} nodes",
        ]
    else:
        counts = stats.to_dict().items()
        parts += [
            _count_words(k, v)
            for k, v in counts
            if isinstance(v, int) and not (v == 0 and k in QUIET_WHEN_NONE)
        ]
    return parts


# The methods' counters in words a reader of the footer understands (the --json output keeps
# the counters' own names); a counter not listed is shown by its name.
COUNT_WORDS = {
    "evaluations": "alterations valued {:,}",
    "alterations_within_budget": "alterations within the budget {:,}",
    "relevant_observations": "sensors that can change the answer {:,}",
    "factorisations": "base chains solved {:,} (one per reading of the enumerated sensors)",
    "inner_observations": "sensors valued by low-rank updates of a base chain {:,}",
    "outer_observations": "sensors enumerated {:,} (each of their readings solves a base chain)",
    "policy_evaluations": "relaxations solved {:,}",
    "pruned": "nodes pruned by their bound {:,}",
    "covers": "nodes covered (bounded by sensor groups) {:,}",
    "cover_unions": "relaxations solved for the covers {:,}",
    "cover_refined": "cover unions refined (above the incumbent) {:,}",
    "cover_pruned": "nodes pruned by a cover {:,}",
    "covers_given_up": "covers given up {:,}",
}
# counters of what only some runs do: left out of the footer where they count nothing
QUIET_WHEN_NONE = {
    "covers",
    "cover_unions",
    "cover_refined",
    "cover_pruned",
    "covers_given_up",
    "collapsed_proofs",
    "collapsed_proven",
}


def _count_words(key: str, value: int) -> str:
    words = COUNT_WORDS.get(key)
    return words.format(value) if words else f"{key.replace('_', ' ')} {value:,}"


def _method_stats(stats: MethodStats) -> MethodStats:
    return stats.answer if isinstance(stats, AutoStats) else stats


# -- simulate -----------------------------------------------------------------------------------


@problem_input
def simulate(
    source: ProblemSource,
    alter: AlterOption = None,
    alteration_file: AlterationFileOption = None,
    at_budget: AtBudgetOption = None,
    runs: Annotated[int, typer.Option(help="Number of simulated runs.")] = 100_000,
    seed: Annotated[int, typer.Option(help="Random seed.")] = 0,
    max_steps: Annotated[int, typer.Option(help="Stop a run after this many steps.")] = 10_000,
    trajectories: Annotated[
        Path | None,
        typer.Option(
            "--trajectories", "-o", help="Write the first --samples runs step by step (CSV)."
        ),
    ] = None,
    samples: Annotated[int, typer.Option(help="Runs to write with --trajectories.")] = 10,
    picture: PictureOption = None,
    coordinates: CoordinatesOption = None,
    as_json: JsonOption = False,
) -> None:
    """Run the attacked robot many times: how often it ends in a decoy, in a goal (absorbing,
    not decoy), caught by a monitor's alarm (--monitor, --stealth) or trapped (it can no
    longer stop), with 95 % intervals."""
    from misdirect.core.simulate import simulate as run_simulation

    for option, value, least, most in (
        ("--runs", runs, 1, MAX_RUNS),
        ("--max-steps", max_steps, 1, MAX_STEPS),
        ("--samples", samples, 0, MAX_SAMPLES),
    ):
        if value < least:
            raise ProblemError(f"must be at least {least}, got {value}", field=option)
        check_range(option, value, least, most)
    check_range("--seed", seed, 0, MAX_SEED)
    if trajectories is not None:
        check_output_path(trajectories, field="--trajectories")
    if picture is not None:
        check_output_path(picture, field="--picture")
        check_picture_suffix(picture, "--picture")
    elif coordinates is not None:
        raise ProblemError(
            "places the states of --picture's drawing: give --picture FILE", field="--coordinates"
        )
    problem = source.load()
    alpha = alteration(problem, alter, alteration_file, at_budget)
    cells = None
    if picture is not None:  # before the runs: a model without coordinates fails at once
        cells = picture_cells(problem, coordinates)
    record = samples if trajectories is not None else 0
    began = time.perf_counter()
    result = run_simulation(
        problem,
        alpha,
        runs=runs,
        seed=seed,
        max_steps=max_steps,
        record=record,
        count_visits=picture is not None,
    )
    exact = decoy_probability(problem.unweighted(), alpha)  # a run hits a decoy or not
    payload = json_output.simulation(
        problem,
        problem.changed_observations(alpha),
        result,
        exact=exact,
        seed=seed,
        max_steps=max_steps,
        time_s=time.perf_counter() - began,
        written=[p for p in (trajectories, picture) if p is not None],
    )
    if trajectories is not None:
        _write_trajectories(result.trajectories, trajectories)
    if picture is not None and cells is not None and result.visits is not None:
        from misdirect.report.figures import draw_grid

        draw_grid(
            problem,
            alpha,
            cells,
            picture,
            visits=result.visits / runs,
            visits_label=f"simulated visits per run ({runs:,} runs)",
            note=f"colours: {runs:,} simulated runs, seed {seed}; Pr values exact",
        )
    if as_json:
        print_json(payload)
    else:
        _print_simulation(payload, result, max_steps)
        if trajectories is not None:
            wrote(f"wrote {trajectories} (the first {min(samples, runs):,} runs, step by step)")
        if picture is not None:
            wrote(f"wrote {picture} (simulated visits per cell)")


def _write_trajectories(rows: Iterable[Sequence[Any]], path: Path) -> None:
    buffer = io.StringIO(newline="")
    writer = csv.writer(buffer)
    writer.writerow(["run", "step", "state", "node", "received", "action"])
    writer.writerows(rows)
    write_output(path, buffer.getvalue(), field="--trajectories")


def _simulation_payload(
    problem: Problem,
    alpha: AlterationArray,
    result: Simulation,
    runs: int,
    seed: int,
    max_steps: int,
) -> dict[str, Any]:
    """The ``--json`` object of simulate: each outcome's count, frequency and 95 % interval,
    and the exact decoy probability beside the simulated one."""
    from misdirect.core.simulate import wilson_interval

    exact = decoy_probability(problem.unweighted(), alpha)  # a run hits a decoy or not
    low, high = result.confidence_interval()

    def outcome(hits: int, states: dict[str, int] | None, meaning: str) -> dict[str, Any]:
        row: dict[str, Any] = {
            "runs": hits,
            "frequency": hits / runs,
            "interval_95": list(wilson_interval(hits, runs)),
            "meaning": meaning,
        }
        if states is not None:
            row["states"] = states
        return row

    outcomes = {
        "decoy": outcome(
            result.decoy_hits, result.decoys, "ended in a decoy state (the attacker's target)"
        ),
        "goal": outcome(
            sum(result.absorbed.values()),
            result.absorbed,
            "ended in an absorbing state that is not a decoy (the robot's goal)",
        ),
        "trapped": outcome(
            result.trapped,
            None,
            "can no longer reach a decoy or goal state: the run would never stop",
        ),
        "unfinished": outcome(
            result.unfinished, None, f"still running after --max-steps {max_steps:,}"
        ),
    }
    outcomes["decoy"]["interval_95"] = [low, high]
    return {
        "problem": problem.name,
        "alteration": problem.changed_observations(alpha),
        "runs": runs,
        "seed": seed,
        "outcomes": outcomes,
        "unfinished": result.unfinished,
        "trapped": result.trapped,
        "mean_steps_finished": result.mean_steps,
        "exact_decoy_probability": exact,
        "exact_within_interval": low <= exact <= high,
    }


def _print_simulation(payload: dict[str, Any], result: Simulation, max_steps: int) -> None:
    runs = payload["runs"]
    table = Table(title=escape(f"{payload['problem']} — {runs:,} runs, seed {payload['seed']}"))
    for column in ("outcome", "states", "runs", "frequency", "95 % interval"):
        left = column in ("outcome", "states")
        table.add_column(column, justify="left" if left else "right", overflow="fold")
    labels = {
        "decoy": "decoy (attacker's target)",
        "goal": "goal (absorbing, not decoy)",
        "trapped": "trapped: never stops",
        "unfinished": f"unfinished after {max_steps:,} steps",
        "alarm": "alarm (monitor)",
    }
    for name, row in payload["totals"].items():
        if name in ("trapped", "unfinished") and row["runs"] == 0:
            continue
        states = {o["state"]: o["runs"] for o in payload["outcomes"] if o["kind"] == name}
        listed = ", ".join(
            f"{state} ({hits:,})" if len(states) > 1 else state for state, hits in states.items()
        )
        table.add_row(
            escape(labels[name]),
            escape(listed),
            f"{row['runs']:,}",
            f"{row['probability']:.4f}",
            f"[{row['interval_95'][0]:.4f}, {row['interval_95'][1]:.4f}]",
        )
    out.print(table)
    verdict = "inside" if payload["exact_within_interval"] else "[red]outside[/]"
    finished = result.runs - result.trapped - result.unfinished - result.alarms
    caught = (
        f" · caught on reading {result.alarm_mean_step:.2f} on average" if result.alarms else ""
    )
    out.print(
        f"alteration {fmt_alteration(payload['alteration'])} · mean steps "
        f"{result.mean_steps:.2f} (over the {finished:,} finished runs, decoy or goal){caught} · "
        f"exact Pr(decoy) {payload['value']:.6f} ({verdict} the interval)",
        highlight=False,
    )


# -- show ---------------------------------------------------------------------------------------


@problem_input
def show(
    output: Annotated[
        Path, typer.Option("--output", "-o", help="Picture (.png/.svg/.pdf) or graph (.dot).")
    ],
    source: ProblemSource,
    alter: AlterOption = None,
    alteration_file: AlterationFileOption = None,
    at_budget: AtBudgetOption = None,
    coordinates: CoordinatesOption = None,
    as_json: JsonOption = False,
) -> None:
    """Draw a problem under an alteration: a heat map of the visits for a model with
    coordinates (grid worlds, PRISM models with x and y, or --coordinates), else the chain
    (dot)."""
    from misdirect.report.show import draw

    check_output_path(output)
    problem = source.load()
    alpha = alteration(problem, alter, alteration_file, at_budget)
    written = draw(problem, alpha, output, coordinates)
    if as_json:
        print_json(json_output.written_files("show", [written], problem=problem.name))
    else:
        wrote(f"wrote {written}")
