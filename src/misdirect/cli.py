"""Command-line interface: a thin layer that parses options, calls the library, formats results.

Every command takes ``--json`` and then prints exactly one JSON object on stdout. Bad input of
any kind exits with code 2 and one line naming the file (or option), the field and the reason.
"""

from __future__ import annotations

import contextlib
import csv
import io
import json
import math
import os
import signal
import sys
import threading
from collections.abc import Callable, Iterator
from enum import StrEnum
from functools import wraps
from pathlib import Path
from typing import Annotated, Any

import typer
from rich.console import Console
from rich.markup import escape
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

from misdirect import __version__
from misdirect.core.alterations import max_alteration_cost
from misdirect.core.evaluate import decoy_probability
from misdirect.core.evaluate import evaluate as evaluate_alteration
from misdirect.core.model import Problem, format_alteration
from misdirect.errors import MisdirectError, ProblemError
from misdirect.io.files import check_output_path, one_line, prepare_output_dir, write_output
from misdirect.io.problem_file import json_schema, load_problem, write_problem
from misdirect.scenarios import knapsack, paper_grid, random_problem, sensor_grid
from misdirect.solvers import SOLVERS
from misdirect.solvers.base import Status
from misdirect.solvers.milp.backends import BACKENDS, write_model
from misdirect.solvers.milp.solver import FORMULATIONS, build_formulation
from misdirect.solvers.run import SolveResult
from misdirect.solvers.run import solve as solve_problem

app = typer.Typer(
    name="misdirect",
    help="Optimal sensor deception: which sensor readings to alter, within a budget, so that a "
    "robot driven by a finite-state controller ends up in a decoy state.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)
scenario_app = typer.Typer(help="Write a generated problem file.", no_args_is_help=True)
app.add_typer(scenario_app, name="scenario")
controller_app = typer.Typer(
    help="The robot's controller: synthesize it with PAYNT.", no_args_is_help=True
)
app.add_typer(controller_app, name="controller")

out = Console()
err = Console(stderr=True)
INPUT_ERROR = 2
INTERRUPTED = 130  # 128 + SIGINT, as a shell reports it
TERMINATED = 143  # 128 + SIGTERM

# Largest values of the numeric options, checked before anything is allocated (README, Limits)
MAX_GRID_SIZE = 2_000  # paper-grid n: 4 million states, 8 million product states
MAX_SEED = 2**64 - 1
MAX_RUNS = 10_000_000  # simulate: about 60 bytes per run are held at once
MAX_STEPS = 100_000_000
MAX_SAMPLES = 100_000
MAX_RANDOM = {"--states": 100_000, "--actions": 100, "--observations": 10_000, "--nodes": 1_000}


class Scenario(StrEnum):
    paper_grid = "paper-grid"
    knapsack = "knapsack"
    random = "random"


# -- shared options -----------------------------------------------------------------------------

JsonOption = Annotated[bool, typer.Option("--json", help="Print one JSON object to stdout.")]
FileArgument = Annotated[
    Path | None,
    typer.Argument(help="Problem file (misdirect/v1, YAML or JSON).", show_default=False),
]
ScenarioOption = Annotated[
    Scenario | None, typer.Option(help="Use a generated problem instead of FILE.")
]
SizeOption = Annotated[int, typer.Option(help="Grid size n (paper-grid).")]
WeightsOption = Annotated[str | None, typer.Option(help="Item weights, e.g. 1,2,3 (knapsack).")]
ValuesOption = Annotated[str | None, typer.Option(help="Item values, e.g. 20,30,40 (knapsack).")]
CapacityOption = Annotated[float | None, typer.Option(help="Knapsack capacity = budget.")]
SeedOption = Annotated[int, typer.Option(help="Seed (random scenario).")]
FormulationOption = Annotated[
    str,
    typer.Option(
        help=f"MILP formulation: {', '.join(FORMULATIONS)} (paper* are the paper's, kept as a "
        "baseline; they are not exact)."
    ),
]


def _numbers(text: str | None, option: str) -> list[float]:
    if text is None:
        raise ProblemError("is required for the knapsack scenario", field=option)
    try:
        return [float(part) for part in text.split(",") if part.strip()]
    except ValueError:
        raise ProblemError(
            f"expected comma-separated numbers, got {text!r}", field=option
        ) from None


def check_range(option: str, value: int | float, least: int | float, most: int | float) -> None:
    """A numeric option within its documented range, before anything is built from it."""
    if not least <= value <= most:
        raise ProblemError(f"must be between {least:,} and {most:,}, got {value:,}", field=option)


def _scenario_problem(
    scenario: Scenario,
    size: int,
    weights: str | None,
    values: str | None,
    capacity: float | None,
    seed: int,
) -> Problem:
    if scenario is Scenario.paper_grid:
        return paper_grid(size)
    if scenario is Scenario.knapsack:
        if capacity is None:
            raise ProblemError("is required for the knapsack scenario", field="--capacity")
        return knapsack(_numbers(weights, "--weights"), _numbers(values, "--values"), capacity)
    return random_problem(seed)


def _load_input(
    file: Path | None,
    scenario: Scenario | None,
    size: int,
    weights: str | None,
    values: str | None,
    capacity: float | None,
    seed: int,
) -> Problem:
    if (file is None) == (scenario is None):
        raise ProblemError("give either a problem FILE or --scenario (exactly one)")
    check_range("--seed", seed, 0, MAX_SEED)
    if size > MAX_GRID_SIZE:
        check_range("--size", size, 5, MAX_GRID_SIZE)
    if file is not None:
        return load_problem(file)
    return _scenario_problem(scenario, size, weights, values, capacity, seed)


def _split_alter(pair: str, observations: tuple[str, ...]) -> tuple[str, str]:
    """``OBS=OBS`` split at the ``=`` that leaves two known observations, so that names with
    an ``=`` in them (Storm's ``o=2``) can be altered; if none does, at the first ``=`` (the
    unknown name is then reported)."""
    known = set(observations)
    splits = [(pair[:i].strip(), pair[i + 1 :].strip()) for i, c in enumerate(pair) if c == "="]
    splits = [(a, b) for a, b in splits if a and b]
    if not splits:
        raise ProblemError(f"expected OBS=OBS (e.g. o1=o3), got {pair!r}", field="--alter")
    matching = [(a, b) for a, b in splits if a in known and b in known]
    if len(matching) > 1:
        readings = " or ".join(f"{a!r} -> {b!r}" for a, b in matching)
        raise ProblemError(
            f"{pair!r} is ambiguous: {readings} (observations contain '=')", field="--alter"
        )
    if matching:
        return matching[0]
    # no reading names two known observations: report the one that is unknown
    return next(((a, b) for a, b in splits if a in known), splits[0])


def _parse_alter(pairs: list[str], observations: tuple[str, ...] = ()) -> dict[str, str]:
    changes: dict[str, str] = {}
    for pair in pairs:
        original, received = _split_alter(pair, observations)
        if original in changes:
            raise ProblemError(f"{original!r} is altered twice", field="--alter")
        changes[original] = received
    return changes


def parse_budgets(
    budget: str | None, budgets: str | None, cap: float | None = None
) -> list[float] | None:
    """``--budget 4``, ``--budget 0..7`` (each whole budget in it) or ``--budgets 0,1,2``.

    A range is expanded only up to ``cap`` (the most expensive complete alteration: every
    budget beyond it gives the same answer), then its upper end, which solve clamps and
    reports; so ``0..1000000000`` never materialises a billion budgets."""
    if budget is not None and budgets is not None:
        raise ProblemError("give --budget or --budgets, not both", field="--budgets")
    option = "--budgets" if budgets is not None else "--budget"
    try:
        if budgets is not None:
            parsed = [float(b) for b in budgets.split(",") if b.strip()]
        elif budget is not None and ".." in budget:
            low, high = (int(part) for part in budget.split("..", 1))
            if low < 0 or high < low:
                raise ProblemError(
                    f"expected a range low..high with 0 ≤ low ≤ high, got {budget!r}", field=option
                )
            top = high if cap is None else min(high, max(low, math.ceil(cap)))
            if top - low > 1_000_000:
                raise ProblemError(
                    f"a range of {top - low + 1:,} budgets is too many; give fewer", field=option
                )
            parsed = [float(b) for b in range(low, top + 1)]
            if top < high:
                parsed.append(float(high))
        elif budget is not None:
            parsed = [float(budget)]
        else:
            return None
    except (ValueError, OverflowError) as error:
        if isinstance(error, ProblemError):
            raise
        raise ProblemError(
            "expected a number, a range like 0..7, or a list like 0,1,2", field=option
        ) from None
    if not parsed or any(not math.isfinite(b) or b < 0 for b in parsed):
        raise ProblemError("budgets must be non-negative numbers", field=option)
    return parsed


def _print_json(payload: dict[str, Any]) -> None:
    sys.stdout.write(json.dumps(payload, indent=2, default=_json_default) + "\n")


def _json_default(value: Any) -> Any:
    if hasattr(value, "tolist"):
        return value.tolist()
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised like Ctrl-C so that the same clean-up (a solver's worker killed, temporary
    files removed) runs before the command exits with 143."""


def _terminate(signum: int, frame: Any) -> None:
    raise Terminated


@contextlib.contextmanager
def _signals_as_exceptions() -> Iterator[None]:
    """SIGINT raises KeyboardInterrupt and SIGTERM :class:`Terminated` while a command runs
    (restored afterwards, so an embedding program keeps its own handlers)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGTERM, _terminate)
    previous_int = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)
        signal.signal(signal.SIGINT, previous_int)


def handle_errors(command: Callable[..., None]) -> Callable[..., None]:
    """Turn library errors into exit code 2 and one readable line, never a traceback;
    Ctrl-C and SIGTERM into one line and exit code 130 or 143."""

    @wraps(command)
    def wrapper(*args: Any, **kwargs: Any) -> None:
        as_json = kwargs.get("as_json", False)
        try:
            with _signals_as_exceptions():
                command(*args, **kwargs)
        except ProblemError as error:
            _fail(error.message, INPUT_ERROR, as_json, field=error.field, source=error.source)
        except MisdirectError as error:
            _fail(str(error), 1, as_json)
        except (typer.Exit, typer.Abort):
            raise
        except Terminated:
            _fail("terminated (SIGTERM)", TERMINATED, as_json)
        except KeyboardInterrupt:
            _fail("interrupted", INTERRUPTED, as_json)
        except MemoryError:
            _fail(
                "out of memory: the model is too large for this machine (see Limits in the README)",
                1,
                as_json,
            )
        except OSError as error:  # an I/O failure no check foresaw (a disk filling up, ...)
            where = f"{error.filename}: " if error.filename else ""
            _fail(f"{where}{error.strerror or error}", 1, as_json)
        except Exception as error:  # a bug: keep the traceback behind an opt-in
            if os.environ.get("MISDIRECT_DEBUG"):
                raise
            _fail(
                f"internal error: {type(error).__name__}: {error} "
                "(set MISDIRECT_DEBUG=1 for the traceback)",
                1,
                as_json,
            )

    return wrapper


def _fail(message: str, code: int, as_json: bool, **context: Any) -> None:
    message = one_line(message)  # a name with a newline must not split the one line
    if as_json:
        _print_json({"error": {"message": message, **{k: v for k, v in context.items() if v}}})
    err.print(f"[bold red]error:[/] {escape(message)}", highlight=False, soft_wrap=True)
    raise typer.Exit(code)


def _note(text: str) -> None:
    """One line on stderr (``wrote ...``), names escaped."""
    err.print(escape(one_line(text)), highlight=False, soft_wrap=True)


def _fmt_alteration(alteration: dict[str, str]) -> str:
    return escape(format_alteration(alteration))


# -- commands -----------------------------------------------------------------------------------


@app.command()
@handle_errors
def evaluate(
    file: FileArgument = None,
    alter: Annotated[
        list[str] | None,
        typer.Option("--alter", "-a", help="Alteration OBS=OBS (repeatable), e.g. o1=o3."),
    ] = None,
    scenario: ScenarioOption = None,
    size: SizeOption = 5,
    weights: WeightsOption = None,
    values: ValuesOption = None,
    capacity: CapacityOption = None,
    seed: SeedOption = 0,
    as_json: JsonOption = False,
) -> None:
    """Exact probability of reaching the decoy under one alteration (none by default)."""
    problem = _load_input(file, scenario, size, weights, values, capacity, seed)
    changes = _parse_alter(alter or [], problem.pomdp.observations)
    alpha = problem.alteration(changes, source="--alter")
    result = evaluate_alteration(problem, alpha)
    baseline = (
        result.probability
        if not result.alteration
        else decoy_probability(problem, problem.identity())
    )
    payload = {"problem": problem.name, **result.to_dict(), "baseline_probability": baseline}
    if as_json:
        _print_json(payload)
        return
    table = Table(title=escape(problem.name) or None, show_header=False, box=None)
    table.add_row("alteration", _fmt_alteration(result.alteration))
    budget_note = "" if result.within_budget else f"  [red](over budget {problem.budget:g})[/]"
    table.add_row("cost", f"{result.cost:g}{budget_note}")
    table.add_row(_objective_label(problem), f"[bold]{result.probability:.6f}[/]")
    for name, probability in result.decoy_sets.items():
        table.add_row(f"  Pr(first decoy in {escape(name)})", f"{probability:.6f}")
    table.add_row("without alteration", f"{baseline:.6f}")
    for state, probability in result.outcomes.items():
        table.add_row(f"  first hits {escape(state)}", f"{probability:.6f}")
    if result.never_absorbed > 0:
        table.add_row("  never absorbed", f"{result.never_absorbed:.6f}")
    table.add_row(
        "product chain",
        f"{result.product_states:,} states, "
        f"{result.product_transitions:,} transitions ({result.time_s:.3f} s)",
    )
    out.print(table)


@app.command()
@handle_errors
def solve(
    file: FileArgument = None,
    budget: Annotated[
        str | None,
        typer.Option(help="Budget B, or a range like 0..7 (default: the file's budget)."),
    ] = None,
    budgets: Annotated[str | None, typer.Option(help="Budgets to solve, e.g. 0,1,2.")] = None,
    method: Annotated[
        str,
        typer.Option(
            help=f"Method: {', '.join(SOLVERS)} (auto: enumerate small alteration spaces, "
            "with low-rank updates where it can, else branch-and-bound, or the MILP on "
            "knapsack-like models; all exact)."
        ),
    ] = "auto",
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
            help="Seconds for the whole command, every method and budget; then each budget "
            "reports its best alteration, a proven upper bound and the gap (status time_limit)."
        ),
    ] = None,
    threads: Annotated[
        int | None, typer.Option(help="MILP: solver threads (SCIP: its concurrent mode if > 1).")
    ] = None,
    mip_gap: Annotated[
        float | None,
        typer.Option(
            help="MILP: relative gap to stop at (default 1e-9); a point whose bound is still "
            "above its value is reported as gap_limit, not optimal."
        ),
    ] = None,
    verbose: Annotated[bool, typer.Option(help="MILP: show the solver's log on stdout.")] = False,
    quiet: Annotated[
        bool, typer.Option("--quiet", "-q", help="No progress or hand-over lines on stderr.")
    ] = False,
    scenario: ScenarioOption = None,
    size: SizeOption = 5,
    weights: WeightsOption = None,
    values: ValuesOption = None,
    capacity: CapacityOption = None,
    seed: SeedOption = 0,
    as_json: JsonOption = False,
) -> None:
    """Optimal alteration within the budget, with the best value for every smaller budget."""
    if threads is not None:
        check_range("--threads", threads, 1, 1024)
    if time_limit is not None and not (math.isfinite(time_limit) and time_limit > 0):
        raise ProblemError("must be a positive number of seconds", field="--time-limit")
    problem = _load_input(file, scenario, size, weights, values, capacity, seed)
    requested = parse_budgets(budget, budgets, cap=max_alteration_cost(problem))
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
    given = {k: v for k, v in milp_options.items() if v is not None}
    if verbose and as_json:
        raise ProblemError(
            "cannot be combined with --json: the solver's log goes to stdout", field="--verbose"
        )
    with _Progress(enabled=not quiet, transient=True) as bars:
        progress = bars.task("solving") if bars else None
        if progress is None and not (quiet or as_json):
            progress = _print_handovers  # no terminal: hand-overs still get a line each
        with _stop_gracefully() as received:
            result = solve_problem(
                problem, method=method, budgets=requested, progress=progress, **given
            )
    if as_json:
        _print_json(result.to_dict())
    else:
        _print_solve(result, problem)
    if result.warnings:
        for warning in result.warnings:
            err.print(f"[bold red]warning:[/] {escape(one_line(warning))}", highlight=False)
    if received:  # the best answer so far is printed above, marked interrupted
        name = "terminated (SIGTERM)" if received[0] == signal.SIGTERM else "interrupted"
        err.print(f"{name}: the best answers found so far are shown", highlight=False)
        raise typer.Exit(TERMINATED if received[0] == signal.SIGTERM else INTERRUPTED)
    if result.warnings:
        raise typer.Exit(1)


@contextlib.contextmanager
def _stop_gracefully() -> Iterator[list[int]]:
    """While solving, the first Ctrl-C or SIGTERM asks the solvers to stop and hand back their
    best answers (every deadline expires at once); a second one stops at once, as elsewhere.
    Yields the list of signals received."""
    from misdirect.solvers.base import clear_stop, request_stop

    received: list[int] = []
    if threading.current_thread() is not threading.main_thread():
        yield received
        return

    def ask(signum: int, frame: Any) -> None:
        if received:
            raise Terminated if signum == signal.SIGTERM else KeyboardInterrupt
        received.append(signum)
        request_stop()

    previous = {sig: signal.signal(sig, ask) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield received
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        clear_stop()


class _Progress:
    """Progress bars on stderr, one per named task; silent under --json or without a terminal."""

    def __init__(self, enabled: bool, *, transient: bool = False):
        self.enabled = enabled and err.is_terminal
        self.transient = transient
        self.bar: Progress | None = None
        self.tasks: dict[str, Any] = {}

    def __enter__(self) -> _Progress | None:
        if not self.enabled:
            return None
        self.bar = Progress(
            TextColumn("{task.description:<20}"),
            BarColumn(),
            TextColumn("{task.completed}/{task.total}"),
            TimeElapsedColumn(),
            TextColumn("{task.fields[detail]}"),
            console=err,
            transient=self.transient,
        )
        self.bar.start()
        return self

    def track(
        self,
        name: str,
        done: int,
        total: int,
        *,
        stage: str | None = None,
        detail: str | None = None,
        note: str | None = None,
    ) -> None:
        assert self.bar is not None
        if note:
            self.bar.console.print(f"[dim]{escape(note)}[/]", highlight=False)
        if total <= 0:
            return
        if name not in self.tasks:
            self.tasks[name] = self.bar.add_task(name, total=total, detail="")
        description = name if stage is None else f"{name}: {stage}"
        self.bar.update(
            self.tasks[name],
            completed=done,
            total=total,
            description=description,
            **({} if detail is None else {"detail": detail}),
        )

    def task(self, name: str) -> Callable[..., None]:
        return lambda done, total, **info: self.track(name, done, total, **info)

    def __exit__(self, *exc: object) -> None:
        if self.bar is not None:
            self.bar.stop()


def _print_handovers(done: int, total: int, *, note: str | None = None, **_: object) -> None:
    """Progress without a terminal: only the hand-overs between methods, one line each."""
    if note:
        err.print(escape(one_line(note)), highlight=False, soft_wrap=True)


def _objective_label(problem: Problem) -> str:
    return "Pr(reach decoy)" if problem.objective.is_probability else "expected decoy weight"


def _print_solve(result: SolveResult, problem: Problem) -> None:
    title = f"{result.problem} — " if result.problem else ""
    table = Table(title=escape(f"{title}optimal alterations ({result.method})"))
    bounded = any(point.status != Status.OPTIMAL for point in result.curve)
    table.add_column("budget", justify="right")
    table.add_column(f"max {_objective_label(problem)}", justify="right")
    if bounded:
        table.add_column("upper bound", justify="right")
    table.add_column("optimal alteration" if not bounded else "best alteration found")
    table.add_column("cost", justify="right")
    table.add_column("status")
    for point in result.curve:
        bound = (
            []
            if not bounded
            else ["—" if point.upper_bound is None else f"{point.upper_bound:.6f}"]
        )
        table.add_row(
            f"{point.budget:g}",
            f"{point.probability:.6f}",
            *bound,
            _fmt_alteration(point.alteration),
            f"{point.cost:g}",
            point.status,
        )
    out.print(table)
    parts = [f"without alteration {result.baseline_probability:.6f}", f"{result.time_s:.2f} s"]
    if result.budget_clamped_from is not None:
        parts.insert(
            0,
            f"budgets above {result.budget_clamped_to:g} solved as {result.budget_clamped_to:g} "
            "(no alteration costs more)",
        )
    stats = result.stats
    if result.certified_by is not None:
        proven = all(point.status == Status.OPTIMAL for point in result.curve)
        verb = "certified by" if proven else "method"
        parts.append(f"{verb} {result.certified_by} ({stats['auto_reason']})")
    if "formulation" in stats:  # a MILP
        nodes = sum(point.stats.get("nodes") or 0 for point in result.curve)
        solving = sum(point.stats.get("solve_time_s", 0.0) for point in result.curve)
        parts += [
            f"{stats['formulation']} MILP on {stats['solver']}: {stats['variables']:,} variables "
            f"({stats['binaries']:,} binary), {stats['rows']:,} rows, "
            f"{stats['nonzeros']:,} non-zeros",
            f"built in {stats['build_time_s']:.2f} s, solved in {solving:.2f} s, {nodes:,} nodes",
        ]
    else:
        parts += [f"{k.replace('_', ' ')} {v:,}" for k, v in stats.items() if isinstance(v, int)]
    out.print(escape(" · ".join(parts)), highlight=False)


OutputOption = Annotated[Path, typer.Option("--output", "-o", help="File to write (.yaml/.json).")]


def _write_scenario(problem: Problem, output: Path, as_json: bool) -> None:
    write_problem(problem, output)  # atomic: nothing is reported unless the file is in place
    if as_json:
        _print_json(
            {"written": str(output), "problem": problem.name, "states": problem.pomdp.n_states}
        )
    else:
        _note(f"wrote {output} ({problem.name}, {problem.pomdp.n_states:,} states)")


@scenario_app.command("paper-grid")
@handle_errors
def scenario_paper_grid(
    output: OutputOption,
    size: Annotated[int, typer.Option(help="Grid size n ≥ 5.")] = 5,
    budget: Annotated[float, typer.Option(help="Budget written into the file.")] = 4,
    as_json: JsonOption = False,
) -> None:
    """The paper's n x n grid world (its Sec. VII-B case study, scaled)."""
    check_output_path(output)
    check_range("--size", size, 5, MAX_GRID_SIZE)
    if not (math.isfinite(budget) and budget >= 0):
        raise ProblemError(f"must be a non-negative number, got {budget}", field="--budget")
    _write_scenario(paper_grid(size, budget=budget), output, as_json)


@scenario_app.command("knapsack")
@handle_errors
def scenario_knapsack(
    output: OutputOption,
    weights: Annotated[str, typer.Option(help="Item weights, e.g. 1,2,3,4,5.")],
    values: Annotated[str, typer.Option(help="Item values, e.g. 20,30,40,50,60.")],
    capacity: Annotated[float, typer.Option(help="Knapsack capacity (the budget).")],
    as_json: JsonOption = False,
) -> None:
    """The knapsack reduction of the NP-hardness proof (paper Sec. V)."""
    check_output_path(output)
    problem = knapsack(_numbers(weights, "--weights"), _numbers(values, "--values"), capacity)
    _write_scenario(problem, output, as_json)


@scenario_app.command("sensor-grid")
@handle_errors
def scenario_sensor_grid(
    output: OutputOption,
    size: Annotated[int, typer.Option(help="Grid size n (5..1000).")] = 20,
    sensors: Annotated[
        int, typer.Option(help="Number of sensors k, each covering 1-6 cells.")
    ] = 16,
    seed: Annotated[int, typer.Option(help="Random seed.")] = 0,
    memory: Annotated[int, typer.Option(help="Controller memory nodes (3: the paper's).")] = 3,
    costs: Annotated[
        str, typer.Option(help="uniform (every alteration 1) or random (1..3 per sensor).")
    ] = "uniform",
    budget: Annotated[float, typer.Option(help="Budget written into the file.")] = 3,
    as_json: JsonOption = False,
) -> None:
    """A sensor network on the paper's slippery grid (docs/sensor-grid.md)."""
    problem = sensor_grid(size, sensors, seed=seed, memory=memory, costs=costs, budget=budget)
    _write_scenario(problem, output, as_json)


@scenario_app.command("random")
@handle_errors
def scenario_random(
    output: OutputOption,
    seed: Annotated[int, typer.Option(help="Random seed.")] = 0,
    states: Annotated[int, typer.Option(help="Number of non-absorbing states.")] = 6,
    actions: Annotated[int, typer.Option(help="Number of actions.")] = 2,
    observations: Annotated[int, typer.Option(help="Number of observations.")] = 4,
    nodes: Annotated[int, typer.Option(help="Controller memory nodes.")] = 2,
    as_json: JsonOption = False,
) -> None:
    """A seeded random model with traps, absorbing non-decoy states and forbidden pairs."""
    check_output_path(output)
    check_range("--seed", seed, 0, MAX_SEED)
    for option, value in (
        ("--states", states),
        ("--actions", actions),
        ("--observations", observations),
        ("--nodes", nodes),
    ):
        if value < 1:
            raise ProblemError(f"must be at least 1, got {value}", field=option)
        check_range(option, value, 1, MAX_RANDOM[option])
    problem = random_problem(
        seed, states=states, actions=actions, observations=observations, nodes=nodes
    )
    _write_scenario(problem, output, as_json)


@controller_app.command("synthesize")
@handle_errors
def controller_synthesize(
    model: Annotated[Path, typer.Argument(help="PRISM POMDP (the robot's world).")],
    output: Annotated[
        Path, typer.Option("--output", "-o", help="PAYNT .fsc.json to write (PAYNT's own JSON).")
    ],
    props: Annotated[
        str, typer.Option("--props", help='One optimizing property, e.g. Pmax=? [F "goal"].')
    ],
    constants: Annotated[
        str | None, typer.Option(help='Undefined PRISM constants, e.g. "N=5,p=0.1".')
    ] = None,
    memory: Annotated[int, typer.Option(help="Memory nodes per observation.")] = 1,
    timeout: Annotated[float, typer.Option(help="Time limit for PAYNT (s).")] = 60.0,
    as_json: JsonOption = False,
) -> None:
    """Synthesize the robot's controller with PAYNT and write PAYNT's JSON of it
    (controller: {paynt: FILE} reads it; give the property as pomdp.terminal_from)."""
    from misdirect.io.paynt_synthesis import synthesize

    check_output_path(output)
    check_range("--memory", memory, 1, 100)
    check_range("--timeout", timeout, 1, 10**6)
    result = synthesize(model, props, constants=constants, memory=memory, timeout=timeout)
    write_output(output, json.dumps(result.document, indent=4) + "\n")
    nodes = result.document.get("num_nodes")
    if as_json:
        _print_json(
            {
                "written": str(output),
                "value": result.value,
                "property": result.property,
                "nodes": nodes,
                "memory": result.memory,
                "seconds": result.seconds,
            }
        )
        return
    value = "not reported" if result.value is None else f"{result.value:.6g}"
    out.print(
        f"PAYNT's controller: {escape(result.property)} = {value} ({nodes} nodes, "
        f"{result.seconds:.1f} s)",
        highlight=False,
        soft_wrap=True,
    )
    _note(f"wrote {output}")


@app.command()
@handle_errors
def simulate(
    file: FileArgument = None,
    alter: Annotated[
        list[str] | None,
        typer.Option("--alter", "-a", help="Alteration OBS=OBS (repeatable), e.g. o1=o3."),
    ] = None,
    runs: Annotated[int, typer.Option(help="Number of simulated runs.")] = 100_000,
    seed: Annotated[int, typer.Option(help="Random seed.")] = 0,
    max_steps: Annotated[int, typer.Option(help="Stop a run after this many steps.")] = 10_000,
    trajectories: Annotated[
        Path | None, typer.Option(help="Write the first --samples runs step by step (CSV).")
    ] = None,
    samples: Annotated[int, typer.Option(help="Runs to write with --trajectories.")] = 10,
    scenario: ScenarioOption = None,
    size: SizeOption = 5,
    weights: WeightsOption = None,
    values: ValuesOption = None,
    capacity: CapacityOption = None,
    as_json: JsonOption = False,
) -> None:
    """Run the attacked robot many times: how often it ends in a decoy, in a goal (absorbing,
    not decoy) or trapped (it can no longer stop), with 95 % intervals."""
    from misdirect.core.simulate import simulate as run_simulation
    from misdirect.core.simulate import wilson_interval

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
    problem = _load_input(file, scenario, size, weights, values, capacity, seed)
    changes = _parse_alter(alter or [], problem.pomdp.observations)
    alpha = problem.alteration(changes, source="--alter")
    result = run_simulation(
        problem,
        alpha,
        runs=runs,
        seed=seed,
        max_steps=max_steps,
        record=samples if trajectories is not None else 0,
    )
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
    if trajectories is not None:
        buffer = io.StringIO(newline="")
        writer = csv.writer(buffer)
        writer.writerow(["run", "step", "state", "node", "received", "action"])
        writer.writerows(result.trajectories)
        write_output(trajectories, buffer.getvalue(), field="--trajectories")
    payload = {
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
    if as_json:
        _print_json(payload)
        return
    table = Table(title=escape(f"{problem.name} — {runs:,} runs, seed {seed}"))
    for column in ("outcome", "states", "runs", "frequency", "95 % interval"):
        table.add_column(column, justify="left" if column in ("outcome", "states") else "right")
    labels = {
        "decoy": "decoy (attacker's target)",
        "goal": "goal (absorbing, not decoy)",
        "trapped": "trapped: never stops",
        "unfinished": f"unfinished after {max_steps:,} steps",
    }
    for name, row in outcomes.items():
        if name in ("trapped", "unfinished") and row["runs"] == 0:
            continue
        states = row.get("states", {})
        listed = ", ".join(
            f"{state} ({hits:,})" if len(states) > 1 else state for state, hits in states.items()
        )
        table.add_row(
            escape(labels[name]),
            escape(listed),
            f"{row['runs']:,}",
            f"{row['frequency']:.4f}",
            f"[{row['interval_95'][0]:.4f}, {row['interval_95'][1]:.4f}]",
        )
    out.print(table)
    verdict = "inside" if payload["exact_within_interval"] else "[red]outside[/]"
    finished = result.runs - result.trapped - result.unfinished
    out.print(
        f"alteration {_fmt_alteration(payload['alteration'])} · mean steps "
        f"{result.mean_steps:.2f} (over the {finished:,} finished runs, decoy or goal) · "
        f"exact Pr(decoy) {exact:.6f} ({verdict} the interval)",
        highlight=False,
    )


@app.command()
@handle_errors
def show(
    output: Annotated[
        Path, typer.Option("--output", "-o", help="Picture (.png/.svg/.pdf) or graph (.dot).")
    ],
    file: FileArgument = None,
    alter: Annotated[
        list[str] | None,
        typer.Option("--alter", "-a", help="Alteration OBS=OBS (repeatable), e.g. o1=o3."),
    ] = None,
    scenario: ScenarioOption = None,
    size: SizeOption = 5,
    weights: WeightsOption = None,
    values: ValuesOption = None,
    capacity: CapacityOption = None,
    seed: SeedOption = 0,
    as_json: JsonOption = False,
) -> None:
    """Draw a problem under an alteration: a heat map for grid worlds, else the chain (dot)."""
    from misdirect.report.show import draw

    check_output_path(output)
    problem = _load_input(file, scenario, size, weights, values, capacity, seed)
    changes = _parse_alter(alter or [], problem.pomdp.observations)
    alpha = problem.alteration(changes, source="--alter")
    written = draw(problem, alpha, output)
    if as_json:
        _print_json({"written": str(written)})
    else:
        _note(f"wrote {written}")


@app.command()
@handle_errors
def reproduce(
    out_dir: Annotated[
        Path, typer.Option("--out", help="Folder for tables, figures and report.md.")
    ] = Path("results"),
    quick: Annotated[
        bool,
        typer.Option(
            "--quick/--full",
            help="Quick: grids 5, 15, 25 and 60 s limits; full: up to 45 and 10 min.",
        ),
    ] = True,
    solver: Annotated[str, typer.Option(help=f"MILP backend: {', '.join(BACKENDS)}.")] = "highs",
    time_limit: Annotated[
        float | None, typer.Option(help="Seconds per MILP solve (default 60 quick, 600 full).")
    ] = None,
    sizes: Annotated[
        str | None, typer.Option(help="Grid sizes of the scalability study, e.g. 5,15,25.")
    ] = None,
    as_json: JsonOption = False,
) -> None:
    """Run the paper's experiments (Section VII) and write its tables and figures beside ours."""
    from misdirect.report.reproduce import reproduce as run_reproduce

    size_list = None
    if sizes is not None:
        try:
            size_list = [int(part) for part in sizes.split(",") if part.strip()]
        except ValueError:
            raise ProblemError(
                f"expected sizes like 5,15,25, got {sizes!r}", field="--sizes"
            ) from None
        if not size_list or min(size_list) < 5:
            raise ProblemError("grid sizes must be at least 5", field="--sizes")
        if max(size_list) > MAX_GRID_SIZE:
            raise ProblemError(f"grid sizes must be at most {MAX_GRID_SIZE:,}", field="--sizes")
    if time_limit is not None and not (math.isfinite(time_limit) and time_limit > 0):
        raise ProblemError("must be a positive number of seconds", field="--time-limit")
    prepare_output_dir(out_dir, field="--out")
    with _Progress(enabled=not as_json) as bars:
        progress = bars.track if bars else None
        report = run_reproduce(
            out_dir,
            quick=quick,
            solver=solver,
            time_limit=time_limit,
            sizes=size_list,
            progress=progress,
        )
    if as_json:
        _print_json(
            {
                "out": str(report.out),
                "mode": report.mode,
                "time_s": report.time_s,
                "summary": report.summary,
                "tables": {name: f"{name}.csv" for name in report.tables},
                "figures": {
                    name: [p.name for p in paths] for name, paths in report.figures.items()
                },
            }
        )
        return
    out.print(escape(f"misdirect reproduce ({report.mode}): ours beside the paper"), style="bold")
    table = Table.grid(padding=(0, 1))
    table.add_column(style="dim", no_wrap=True)
    table.add_column(overflow="fold")
    for row in report.summary:
        agrees = row["agrees"]
        colour = "green" if agrees == "yes" else ("red" if agrees == "NO" else "yellow")
        table.add_row("", "")
        table.add_row(
            f"[bold]{escape(row['experiment'])}[/]", f"agrees: [{colour}]{escape(agrees)}[/]"
        )
        table.add_row("  ours", escape(row["ours"]))
        table.add_row("  paper", escape(row["paper"]))
        for note in row.get("notes", []):
            flagged = note.startswith(("UNVERIFIED", "timed out"))
            table.add_row("  note", f"[bold red]{escape(note)}[/]" if flagged else escape(note))
    out.print(table)
    out.print(
        escape(f"{report.time_s:.1f} s; tables, figures and report.md in {report.out}/"),
        highlight=False,
    )


class ConvertTarget(StrEnum):
    prism = "prism"
    drn = "drn"
    json = "json"
    yaml = "yaml"


@app.command()
@handle_errors
def convert(
    to: Annotated[ConvertTarget, typer.Option("--to", help="Format to write.")],
    output: Annotated[
        Path | None,
        typer.Option("--output", "-o", help="File to write (default: standard output)."),
    ] = None,
    file: FileArgument = None,
    scenario: ScenarioOption = None,
    size: SizeOption = 5,
    weights: WeightsOption = None,
    values: ValuesOption = None,
    capacity: CapacityOption = None,
    seed: SeedOption = 0,
    as_json: JsonOption = False,
) -> None:
    """Write the explicit model: PRISM or DRN for Storm (decoy as label "decoy"), or v1."""
    from misdirect.io.export import drn_text, export_notes, prism_text
    from misdirect.io.problem_file import problem_text

    if output is not None:
        check_output_path(output)
    problem = _load_input(file, scenario, size, weights, values, capacity, seed)
    if output is not None and to in (ConvertTarget.json, ConvertTarget.yaml):
        wanted = (".json",) if to is ConvertTarget.json else (".yaml", ".yml")
        if output.suffix.lower() not in wanted:
            raise ProblemError(f"--to {to.value} writes a {wanted[0]} file", field="-o")
    if to in (ConvertTarget.prism, ConvertTarget.drn):
        for note in export_notes(problem, to.value):
            _note(f"note: {note}")
    if to is ConvertTarget.prism:
        text = prism_text(problem)
    elif to is ConvertTarget.drn:
        text = drn_text(problem)
    else:
        text = problem_text(problem, as_json=to is ConvertTarget.json)
    _write_text(text, output, as_json, format=to.value)
    if output is not None and not as_json:
        _note(f"wrote {output} ({to.value}, {problem.pomdp.n_states:,} states)")


def _write_text(text: str, output: Path | None, as_json: bool, **about: Any) -> None:
    """Write ``text`` to ``output``, or to standard output when there is none (with --json,
    as the ``content`` of the one JSON object)."""
    if output is not None:
        write_output(output, text)  # atomic; a bad path or a failed write is one line
        if as_json:
            _print_json({"written": str(output), **about})
    elif as_json:
        _print_json({"written": None, **about, "content": text})
    else:
        sys.stdout.write(text)


@app.command("export-fsc")
@handle_errors
def export_fsc(
    output: Annotated[
        Path | None,
        typer.Option("--output", "-o", help="PAYNT .fsc.json to write (default: standard output)."),
    ] = None,
    file: FileArgument = None,
    scenario: ScenarioOption = None,
    size: SizeOption = 5,
    weights: WeightsOption = None,
    values: ValuesOption = None,
    capacity: CapacityOption = None,
    seed: SeedOption = 0,
    as_json: JsonOption = False,
) -> None:
    """Write the controller in PAYNT's JSON format (controller: {paynt: FILE} reads it)."""
    from misdirect.io.paynt import controller_to_paynt

    if output is not None:
        check_output_path(output)
    problem = _load_input(file, scenario, size, weights, values, capacity, seed)
    text = json.dumps(controller_to_paynt(problem.controller, problem.pomdp), indent=1) + "\n"
    _write_text(text, output, as_json, format="paynt")
    if output is not None and not as_json:
        _note(f"wrote {output} ({problem.controller.n_nodes} nodes)")


@app.command("export-milp")
@handle_errors
def export_milp(
    output: Annotated[
        Path, typer.Option("--output", "-o", help="Model file to write (.mps or .lp).")
    ],
    file: FileArgument = None,
    formulation: FormulationOption = "compact",
    budget: Annotated[
        float | None, typer.Option(help="Budget in the budget row (default: the file's).")
    ] = None,
    scenario: ScenarioOption = None,
    size: SizeOption = 5,
    weights: WeightsOption = None,
    values: ValuesOption = None,
    capacity: CapacityOption = None,
    seed: SeedOption = 0,
    as_json: JsonOption = False,
) -> None:
    """Write the MILP as MPS or LP for any other solver (columns c0, c1, …; maximise)."""
    check_output_path(output)
    if output.suffix.lower() not in (".mps", ".lp"):
        raise ProblemError(
            f"cannot write {output.suffix or 'a file without suffix'}: use .mps or .lp",
            field="-o",
        )
    problem = _load_input(file, scenario, size, weights, values, capacity, seed)
    if budget is not None and (not math.isfinite(budget) or budget < 0):
        raise ProblemError("must be a non-negative number", field="--budget")
    model = build_formulation(problem, formulation, budget)
    write_model(model, output)
    stats = {"written": str(output), **model.stats()}
    if as_json:
        _print_json(stats)
    else:
        _note(
            f"wrote {output}: {formulation} MILP, {model.n_columns:,} variables "
            f"({int(model.integer.sum()):,} binary), {model.n_rows:,} rows, "
            f"{model.matrix.nnz:,} non-zeros"
        )


@app.command()
@handle_errors
def schema(
    output: Annotated[Path | None, typer.Option("--output", "-o", help="Write to a file.")] = None,
    as_json: JsonOption = False,
) -> None:
    """Print the JSON Schema of the problem file format."""
    text = json.dumps(json_schema(), indent=2) + "\n"
    if output is None:
        sys.stdout.write(text)
    else:
        write_output(output, text)
        if as_json:
            _print_json({"written": str(output)})


def _version(value: bool) -> None:
    if value:
        out.print(f"misdirect {__version__}")
        raise typer.Exit()


@app.callback()
def _root(
    version: Annotated[
        bool, typer.Option("--version", callback=_version, is_eager=True, help="Show version.")
    ] = False,
) -> None:
    """misdirect: optimal sensor deception for POMDP robots with finite-state controllers."""


def main() -> None:
    """The console entry point: usage errors (an option that does not parse, an unknown
    command) become one line and exit code 2, like every other input error."""
    # typer may vendor click: take its classes from typer's own exceptions, by name
    usage_error = next(c for c in typer.BadParameter.__mro__ if c.__name__ == "UsageError")
    try:
        code = app(standalone_mode=False)
    except usage_error as error:
        if type(error).__name__ == "NoArgsIsHelpError":  # help, asked for by omission
            print(error.ctx.get_help())
            sys.exit(0)
        where = f"{error.ctx.command_path}: " if error.ctx is not None else ""
        message = f"error: {escape(one_line(where + error.format_message()))}"
        err.print(message, highlight=False, soft_wrap=True)
        sys.exit(INPUT_ERROR)
    except typer.Abort:
        err.print("interrupted", highlight=False)
        sys.exit(INTERRUPTED)
    sys.exit(code if isinstance(code, int) else 0)


# -- the defender's view (issue 14; docs/defence.md) ---------------------------------------------


def _check_seconds(time_limit: float | None) -> None:
    if time_limit is not None and not (math.isfinite(time_limit) and time_limit > 0):
        raise ProblemError("must be a positive number of seconds", field="--time-limit")


def _check_budget(value: float | None, option: str) -> None:
    if value is not None and not (math.isfinite(value) and value >= 0):
        raise ProblemError(f"must be a non-negative number, got {value:g}", field=option)


def _parse_protect_costs(text: str | None) -> dict[str, float]:
    """``default=1,o3=2`` (split at the last ``=``, so names like Storm's ``o=2`` work)."""
    costs: dict[str, float] = {}
    for part in (text or "").split(","):
        if not part.strip():
            continue
        name, sep, value = part.rpartition("=")
        name = name.strip()
        if not sep or not name:
            raise ProblemError(
                f"expected OBS=COST or default=COST (e.g. default=1,o3=2), got {part!r}",
                field="--protect-cost",
            )
        try:
            costs[name] = float(value)
        except ValueError:
            raise ProblemError(
                f"the cost of {name!r} must be a number, got {value!r}", field="--protect-cost"
            ) from None
    return costs


@app.command()
@handle_errors
def audit(
    file: FileArgument = None,
    budget: Annotated[
        float | None, typer.Option(help="Attacker's budget B (default: the file's).")
    ] = None,
    output: Annotated[
        Path | None,
        typer.Option(
            "--output", "-o", help="Folder for report.md, curve.csv, sensors.csv and figures."
        ),
    ] = None,
    time_limit: Annotated[
        float | None,
        typer.Option(help="Seconds for the whole audit; what is not proven is labelled."),
    ] = None,
    scenario: ScenarioOption = None,
    size: SizeOption = 5,
    weights: WeightsOption = None,
    values: ValuesOption = None,
    capacity: CapacityOption = None,
    seed: SeedOption = 0,
    as_json: JsonOption = False,
) -> None:
    """Which sensors are weak: the attacker's optimum for every budget up to B, each sensor's
    criticality and single-sensor value, and the online attacker's value."""
    from misdirect.defence import audit as run_audit

    _check_budget(budget, "--budget")
    _check_seconds(time_limit)
    if output is not None:
        prepare_output_dir(output, field="-o")
    problem = _load_input(file, scenario, size, weights, values, capacity, seed)
    result = run_audit(problem, budget=budget, time_limit=time_limit)
    written: list[str] = []
    if output is not None:
        from misdirect.report.defence import write_audit_report

        written = [str(p) for p in write_audit_report(problem, result, output)]
    if as_json:
        _print_json({**result.to_dict(), "written": written})
        return
    if output is not None:
        _note(f"wrote {len(written)} files to {output}/ (report.md, curve.csv, sensors.csv, …)")
        return
    title = f"{result.problem or 'problem'}: sensors at budget {result.budget:g}"
    table = Table(title=escape(title))
    columns = ("sensor", "criticality", "protected → optimum", "single-sensor value", "in attack")
    for column in columns:
        table.add_column(column, justify="left" if column == "sensor" else "right")
    for s in result.sensors:
        crit = (
            f"{s.criticality:.6f}" if s.exact else f"{s.criticality:.6f}..{s.criticality_upper:.6f}"
        )
        table.add_row(
            escape(s.observation),
            crit,
            f"{s.protected_probability:.6f}",
            f"{s.single_probability:.6f}",
            "yes" if s.in_optimal_attack else "",
        )
    out.print(table)
    online = result.online
    parts = [
        f"optimum at B {result.probability:.6f} ({result.status}: "
        f"{_fmt_alteration(result.alteration)})",
        f"without attack {result.baseline_probability:.6f}",
        f"online attacker: unlimited {online.unlimited_probability:.6f} (upper bound)",
    ]
    if online.budgeted_probability is not None:
        parts.append(f"paying per reading within B {online.budgeted_probability:.6f}")
    else:
        parts.append(f"budgeted online not computed: {escape(result.online_budgeted_note or '')}")
    parts.append(f"{result.time_s:.2f} s")
    out.print(" · ".join(parts), highlight=False)
    for note in result.notes:
        err.print(f"note: {escape(one_line(note))}", highlight=False)


@app.command()
@handle_errors
def harden(
    protect_budget: Annotated[
        float, typer.Option("--protect-budget", help="Total protection cost D allowed.")
    ],
    file: FileArgument = None,
    budget: Annotated[
        float | None, typer.Option(help="Attacker's budget B (default: the file's).")
    ] = None,
    protect_cost: Annotated[
        str | None,
        typer.Option(
            "--protect-cost", help="Protection costs, e.g. default=1,o3=2 (default: 1 each)."
        ),
    ] = None,
    time_limit: Annotated[
        float | None,
        typer.Option(help="Seconds; then the best protection found and a proven lower bound."),
    ] = None,
    scenario: ScenarioOption = None,
    size: SizeOption = 5,
    weights: WeightsOption = None,
    values: ValuesOption = None,
    capacity: CapacityOption = None,
    seed: SeedOption = 0,
    as_json: JsonOption = False,
) -> None:
    """Which sensors to protect: the set within cost D that minimises the attacker's optimum
    at budget B (exact min-max), with the trade-off over every protection budget up to D."""
    from misdirect.defence import harden as run_harden

    _check_budget(protect_budget, "--protect-budget")
    _check_budget(budget, "--budget")
    _check_seconds(time_limit)
    costs = _parse_protect_costs(protect_cost)
    problem = _load_input(file, scenario, size, weights, values, capacity, seed)
    try:
        result = run_harden(
            problem,
            protect_budget=protect_budget,
            budget=budget,
            protect_costs=costs,
            time_limit=time_limit,
        )
    except ProblemError as error:
        if error.field == "protect_costs":
            error.field = "--protect-cost"
        raise
    if as_json:
        _print_json(result.to_dict())
        return
    table = Table(
        title=escape(
            f"{result.problem or 'problem'}: protection against an attacker with budget "
            f"{result.budget:g}"
        )
    )
    columns = ("D", "protect", "cost", "attacker's optimum", "lower bound", "best reply", "status")
    for column in columns:
        table.add_column(column, justify="left" if column in ("protect", "best reply") else "right")
    for point in result.curve:
        table.add_row(
            f"{point.protect_budget:g}",
            escape(", ".join(point.protection) or "nothing"),
            f"{point.protection_cost:g}",
            f"{point.probability:.6f}",
            f"{point.lower_bound:.6f}",
            _fmt_alteration(point.attack),
            point.status,
        )
    out.print(table)
    out.print(
        escape(
            f"protect {', '.join(result.protection) or 'nothing'} (cost "
            f"{result.protection_cost:g}): the attacker's optimum drops from "
            f"{result.value_before:.6f} to {result.value_after:.6f} ({result.status}) · "
            f"{result.solves} attacker solves, {result.nodes} nodes · {result.time_s:.2f} s"
        ),
        highlight=False,
    )
    for note in result.notes:
        err.print(f"note: {escape(one_line(note))}", highlight=False)
