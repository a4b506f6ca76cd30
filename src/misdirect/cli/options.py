"""The options commands share, declared once, and the parsers of their values.

A command that reads a problem is decorated with :func:`problem_input`: it declares only its
own options and a ``source: ProblemSource`` parameter; the decorator adds the problem FILE
argument, the ``--monitor --stealth`` options and the ``--scenario --size --weights --values
--capacity --seed`` options to the
signature typer reads, and hands the command their values as one :class:`ProblemSource`.
"""

from __future__ import annotations

import inspect
import math
from collections.abc import Callable
from dataclasses import dataclass, fields
from enum import StrEnum
from functools import wraps
from pathlib import Path
from typing import Annotated, Any

import typer

from misdirect.cli.alteration_file import read_alteration_file
from misdirect.cli.common import check_range, flag
from misdirect.core.model import AlterationArray, Problem
from misdirect.errors import ProblemError, ProblemsError
from misdirect.io.model_problem import problem_from_model, with_controller
from misdirect.io.problem_file import (
    CONSISTENCY,
    load_problem,
    model_kind,
    monitored,
    read_monitor,
)
from misdirect.io.storm_names import valuation_name
from misdirect.scenarios import knapsack, paper_grid, random_problem
from misdirect.solvers.milp.solver import FORMULATIONS

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


# -- option types -------------------------------------------------------------------------------

JsonOption = Annotated[bool, typer.Option("--json", help="Print one JSON object to stdout.")]
FileArgument = Annotated[
    Path | None,
    typer.Argument(
        help="Problem file (misdirect/v1, YAML or JSON), or a PRISM (.prism) or DRN (.drn) "
        "model with --controller and --decoy.",
        show_default=False,
    ),
]
ControllerOption = Annotated[
    Path | None,
    typer.Option(
        "--controller",
        help="The robot's controller: PAYNT's .fsc.json (or a YAML file of rules); replaces "
        "the controller of a problem file or scenario.",
        show_default=False,
    ),
]
DecoyOption = Annotated[
    str | None,
    typer.Option(
        "--decoy",
        help="With a PRISM/DRN model: the decoy, a state label (bad) or an expression "
        '("x=3 & y>2").',
        show_default=False,
    ),
]
GoalOption = Annotated[
    str | None,
    typer.Option(
        "--goal",
        help="With a PRISM/DRN model: states that end the run, built terminal as PAYNT does "
        "(a label or an expression; the file's pomdp.terminal).",
        show_default=False,
    ),
]
ConstantsOption = Annotated[
    str | None,
    typer.Option("--constants", help='With a PRISM model: undefined constants, e.g. "N=4,p=0.1".'),
]
TerminalFromOption = Annotated[
    str | None,
    typer.Option(
        "--terminal-from",
        help="With a PRISM/DRN model: PAYNT's property, e.g. 'P=? [F \"goal\"]'; its "
        "target states are built terminal, as PAYNT builds the model.",
        show_default=False,
    ),
]
PropertyOption = Annotated[
    str | None,
    typer.Option(
        "--property",
        help="With a PRISM/DRN model: the objective as a PRISM property, 'P=? [F \"decoy\"]', "
        '\'P=? [!"avoid" U "decoy"]\' or \'P=? [F<=k "decoy"]\'; its target is the decoy '
        "(--decoy may be left out).",
        show_default=False,
    ),
]
MonitorOption = Annotated[
    str | None,
    typer.Option(
        "--monitor",
        help="Watch the robot's readings: consistency (its plausibility check: an alarm on a "
        "reading no state it could be in emits) or a YAML file of an automaton (states, "
        "initial, alarm, transitions); replaces the file's monitor. The value becomes "
        "Pr(reach decoy before the alarm); the alarm is the outcome 'alarm' (docs/stealth.md).",
        show_default=False,
    ),
]
StealthOption = Annotated[
    bool,
    typer.Option(
        "--stealth",
        help="Maximise Pr(reach decoy before any alarm): the same as giving a monitor; "
        "without one (--monitor, or the file's monitor:) the consistency monitor.",
    ),
]
ScenarioOption = Annotated[
    Scenario | None, typer.Option(help="Use a generated problem instead of FILE.")
]
SizeOption = Annotated[int, typer.Option(help="Grid size n (paper-grid).")]
WeightsOption = Annotated[str | None, typer.Option(help="Item weights, e.g. 1,2,3 (knapsack).")]
ValuesOption = Annotated[str | None, typer.Option(help="Item values, e.g. 20,30,40 (knapsack).")]
CapacityOption = Annotated[float | None, typer.Option(help="Knapsack capacity = budget.")]
SeedOption = Annotated[int, typer.Option(help="Seed (random scenario).")]
ExactOption = Annotated[
    bool,
    typer.Option(
        "--exact",
        help="Also value the answer on the model as written: Storm builds the PRISM or DRN "
        "model in rational arithmetic and its exact engine checks the alteration "
        "(misdirect[storm]; slow on big chains).",
    ),
]
AlterOption = Annotated[
    list[str] | None,
    typer.Option(
        "--alter",
        "-a",
        help="Alteration OBS=OBS (repeatable), e.g. o1=o3; Storm's names too, e.g. [s=0]=[s=1].",
    ),
]
AlterationFileOption = Annotated[
    Path | None,
    typer.Option(
        "--alteration",
        help="Read the alteration from a file: solve's or evaluate's --json output, or a "
        "YAML mapping {observation: received observation} (as solve -o FILE.yaml writes).",
        show_default=False,
    ),
]
AtBudgetOption = Annotated[
    float | None,
    typer.Option(
        "--at-budget",
        help="With --alteration and solve's output: the budget whose alteration to take "
        "(default: the largest in the file).",
        show_default=False,
    ),
]
FormulationOption = Annotated[
    str,
    typer.Option(
        help=f"MILP formulation: {', '.join(FORMULATIONS)} (paper* are the paper's, kept as a "
        "baseline; they are not exact)."
    ),
]
AttackerBudgetOption = Annotated[
    str | None,
    typer.Option(
        "--budget",
        "--budgets",
        help="Attacker's budget B, one number (default: the file's); the answer covers every "
        "budget up to it. Written as solve's --budget, but a range or list is refused.",
        show_default=False,
    ),
]


# -- the problem input --------------------------------------------------------------------------


@dataclass(frozen=True)
class ProblemSource:
    """Where a command's problem comes from: a FILE or a generated ``--scenario``, as given on
    the command line. Nothing is checked or read until :meth:`load`, so that a command checks
    its own options first."""

    file: Path | None
    controller: Path | None
    decoy: str | None
    goal: str | None
    constants: str | None
    terminal_from: str | None
    property: str | None
    monitor: str | None
    stealth: bool
    scenario: Scenario | None
    size: int
    weights: str | None
    values: str | None
    capacity: float | None
    seed: int

    def load(self) -> Problem:
        if (self.file is None) == (self.scenario is None):
            raise ProblemError(
                "give either a problem FILE (or a PRISM/DRN model) or --scenario (exactly one)"
            )
        check_range("--seed", self.seed, 0, MAX_SEED)
        if self.size > MAX_GRID_SIZE:
            check_range("--size", self.size, 5, MAX_GRID_SIZE)
        kind = model_kind(self.file) if self.file is not None else None
        self.check_model_flags(kind)
        try:
            problem = self._load(kind)
            return self._watched(problem, given=kind is None and self.file is not None)
        except ProblemError as error:
            raise with_flag_sources(error) from None

    def _watched(self, problem: Problem, *, given: bool) -> Problem:
        """The problem under ``--monitor`` (a problem file had it applied in place of its
        own: ``given``), or under the consistency monitor for ``--stealth`` without one."""
        if self.monitor is not None and not given:
            spec, where = read_monitor(self.monitor)
            return monitored(problem, spec, source=where, field="")
        if self.stealth and not problem.monitor:
            spec, where = read_monitor(CONSISTENCY)
            return monitored(problem, spec, source="stealth", field="")
        return problem

    def model_flags(self) -> dict[str, str | None]:
        """The flags that describe a PRISM or DRN model given as FILE, by parameter name."""
        return {
            "decoy": self.decoy,
            "goal": self.goal,
            "constants": self.constants,
            "terminal_from": self.terminal_from,
            "property": self.property,
        }

    def check_model_flags(self, kind: str | None) -> None:
        """--decoy (and --controller) are needed with a PRISM or DRN model, and the flags
        that describe one are refused with anything else."""
        if kind is not None:
            missing = [
                ProblemError(
                    f"is required with the {'PRISM' if kind == 'prism' else 'DRN'} model "
                    f"{self.file}: {what}",
                    source=option,
                )
                for option, value, what in (
                    ("--controller", self.controller, "the robot's controller (PAYNT's .fsc.json)"),
                    (
                        "--decoy",
                        self.decoy if self.property is None else self.property,
                        "the decoy states, a label or an expression (or --property)",
                    ),
                )
                if value is None
            ]
            if missing:
                raise ProblemsError.of(missing)
            return
        what = "a problem file" if self.file is not None else "a scenario"
        for name, value in self.model_flags().items():
            if value is not None:
                raise ProblemError(
                    f"describes a PRISM or DRN model given as FILE; {what} says it itself "
                    "(only --controller replaces part of it)",
                    source=flag(name),
                )

    def _load(self, kind: str | None) -> Problem:
        if self.file is not None and kind is not None:
            assert self.controller is not None  # checked, and --decoy or --property
            return problem_from_model(
                self.file,
                controller=self.controller,
                decoy=self.decoy,
                goal=self.goal,
                constants=self.constants,
                terminal_from=self.terminal_from,
                property=self.property,
            )
        if self.file is not None:
            return load_problem(self.file, controller=self.controller, monitor=self.monitor)
        problem = self._scenario()
        if self.controller is not None:
            problem = with_controller(problem, self.controller)
        return problem

    def _scenario(self) -> Problem:
        if self.scenario is Scenario.paper_grid:
            return paper_grid(self.size)
        if self.scenario is Scenario.knapsack:
            if self.capacity is None:
                raise ProblemError("is required for the knapsack scenario", field="--capacity")
            weights = numbers(self.weights, "--weights")
            return knapsack(weights, numbers(self.values, "--values"), self.capacity)
        return random_problem(self.seed)


# the settings of misdirect.io.model_problem, which errors name as their source, as flags
_SETTINGS = (
    "decoy",
    "goal",
    "constants",
    "terminal_from",
    "property",
    "controller",
    "budget",
    "monitor",
    "stealth",
)


def with_flag_sources(error: ProblemError) -> ProblemError:
    """A library error whose source is a setting (``decoy``) with the flag as its source."""
    if isinstance(error, ProblemsError):
        problems = [with_flag_sources(problem) for problem in error.problems]
        return ProblemsError.of(problems, error.total)
    if error.source in _SETTINGS:
        return ProblemError(error.reason, source=flag(error.source), field=error.field)
    return error


def _keyword(name: str, annotation: Any, default: Any) -> inspect.Parameter:
    return inspect.Parameter(
        name, inspect.Parameter.KEYWORD_ONLY, annotation=annotation, default=default
    )


# The parameters problem_input adds, with the names of ProblemSource's fields: FILE where the
# command declares ``source``, the options just before --json.
_FILE = _keyword("file", FileArgument, None)
_OPTIONS = (
    _keyword("controller", ControllerOption, None),
    _keyword("decoy", DecoyOption, None),
    _keyword("goal", GoalOption, None),
    _keyword("constants", ConstantsOption, None),
    _keyword("terminal_from", TerminalFromOption, None),
    _keyword("property", PropertyOption, None),
    _keyword("monitor", MonitorOption, None),
    _keyword("stealth", StealthOption, False),
    _keyword("scenario", ScenarioOption, None),
    _keyword("size", SizeOption, 5),
    _keyword("weights", WeightsOption, None),
    _keyword("values", ValuesOption, None),
    _keyword("capacity", CapacityOption, None),
    _keyword("seed", SeedOption, 0),
)
assert [p.name for p in (_FILE, *_OPTIONS)] == [f.name for f in fields(ProblemSource)]


def problem_input(command: Callable[..., None]) -> Callable[..., None]:
    """Give ``command`` the shared problem input: typer sees the FILE argument (in the place
    of the command's ``source`` parameter) and the ``--scenario/--size/--weights/--values/
    --capacity/--seed`` options (just before ``--json``) in its signature, and the command
    receives their values as ``source``, one :class:`ProblemSource`.

    A command that declares its own ``seed`` (``simulate --seed``) keeps it, and the same
    value seeds the random scenario: there is one ``--seed`` option, not two."""
    own = inspect.signature(command, eval_str=True)
    if "source" not in own.parameters:
        raise TypeError(f"{command.__name__} takes no 'source: ProblemSource' parameter")
    has_seed = "seed" in own.parameters
    added = [p for p in _OPTIONS if not (has_seed and p.name == "seed")]
    kept = [
        _FILE if p.name == "source" else p.replace(kind=inspect.Parameter.KEYWORD_ONLY)
        for p in own.parameters.values()
    ]
    at = next((i for i, p in enumerate(kept) if p.name == "as_json"), len(kept))
    parameters = [*kept[:at], *added, *kept[at:]]

    @wraps(command)
    def wrapper(**kwargs: Any) -> None:
        given = {p.name: kwargs.pop(p.name) for p in (_FILE, *added)}
        if has_seed:  # the command's own --seed, which it keeps
            given["seed"] = kwargs["seed"]
        command(source=ProblemSource(**given), **kwargs)

    # typer reads inspect.signature (which stops at __signature__) and get_type_hints
    # (which reads __annotations__): both get the real annotation objects
    wrapper.__signature__ = own.replace(parameters=parameters)  # type: ignore[attr-defined]
    wrapper.__annotations__ = {p.name: p.annotation for p in parameters}
    wrapper.__annotations__["return"] = own.return_annotation
    return wrapper


# -- parsers of option values -------------------------------------------------------------------


def numbers(text: str | None, option: str) -> list[float]:
    """``--weights 1,2,3``: comma-separated numbers."""
    if text is None:
        raise ProblemError("is required for the knapsack scenario", field=option)
    try:
        return [float(part) for part in text.split(",") if part.strip()]
    except ValueError:
        raise ProblemError(
            f"expected comma-separated numbers, got {text!r}", field=option
        ) from None


def observation_name(text: str, known: set[str] | frozenset[str]) -> str:
    """``text`` as the observation it names: itself when known, else Storm's valuation text of
    one (``[s=0]``, ``[x=2\t& y=0]``, as PAYNT's controller files write them) as the model
    names it (``s=0``, ``x=2,y=0``); unknown names are returned as they are (and reported)."""
    if text in known or not (text.startswith("[") and text.endswith("]")):
        return text
    name = valuation_name(text)
    return name if name in known else text


def _split_alter(pair: str, observations: tuple[str, ...]) -> tuple[str, str]:
    """``OBS=OBS`` split at the ``=`` that leaves two known observations, so that names with
    an ``=`` in them (Storm's ``o=2``, ``[s=0]``) can be altered; if none does, at the first
    ``=`` (the unknown name is then reported)."""
    known = set(observations)
    splits = [(pair[:i].strip(), pair[i + 1 :].strip()) for i, c in enumerate(pair) if c == "="]
    splits = [
        (observation_name(a, known), observation_name(b, known)) for a, b in splits if a and b
    ]
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


def parse_alter(pairs: list[str], observations: tuple[str, ...] = ()) -> dict[str, str]:
    """``--alter o1=o3 --alter o2=o4`` as a mapping (each observation altered at most once)."""
    changes: dict[str, str] = {}
    for pair in pairs:
        original, received = _split_alter(pair, observations)
        if original in changes:
            raise ProblemError(f"{original!r} is altered twice", field="--alter")
        changes[original] = received
    return changes


def alteration(
    problem: Problem,
    alter: list[str] | None,
    alteration_file: Path | None = None,
    at_budget: float | None = None,
) -> AlterationArray:
    """The alteration ``--alter`` names, or the one ``--alteration FILE`` holds (at
    ``--at-budget`` of a solve document), checked against ``problem``."""
    if at_budget is not None and alteration_file is None:
        raise ProblemError("needs --alteration FILE (a solve --json document)", field="--at-budget")
    if alteration_file is not None:
        if alter:
            raise ProblemError("give --alter or --alteration, not both", field="--alteration")
        known = frozenset(problem.pomdp.observations)
        written = read_alteration_file(alteration_file, at_budget)
        changes = {
            observation_name(o, known): observation_name(t, known) for o, t in written.items()
        }
        return problem.alteration(changes, source=str(alteration_file))
    changes = parse_alter(alter or [], problem.pomdp.observations)
    try:
        return problem.alteration(changes, source="--alter")
    except ProblemError as error:  # the flag is the field, as for every option
        if error.source != "--alter":
            raise
        raise ProblemError(f"{error.field}: {error.reason}", field="--alter") from None


LISTED_RANGE = 1_000  # a range of budgets this long is listed whole, even above the cap

BudgetOption = Annotated[
    str | None,
    typer.Option(
        "--budget",
        "--budgets",
        help="Budget B: a number (2), a range (0..4: each whole budget in it) or a list "
        "(0,1,3); default: the file's budget. --budgets is the same option.",
        show_default=False,
    ),
]


def parse_budgets(
    budget: str | None, budgets: str | None = None, cap: float | None = None
) -> list[float] | None:
    """``--budget`` (alias ``--budgets``): a number ``4``, a range ``0..7`` (each whole budget
    in it) or a list ``0,1,2``, each refused with the message of its own syntax.

    A range lists every whole budget in it, those above ``cap`` (the most expensive complete
    alteration: solve answers them with its answer) included. Only a range of more than
    :data:`LISTED_RANGE` budgets is expanded up to the cap and then its upper end, so
    ``0..1000000000`` never materialises a billion budgets. (``budgets``: the value of the
    separate ``--budgets`` option of earlier versions, taken the same way.)"""
    if budget is not None and budgets is not None and budget != budgets:
        raise ProblemError("give --budget or --budgets, not both", field="--budget")
    text = budget if budget is not None else budgets
    if text is None:
        return None
    if ".." in text:
        parsed = _budget_range(text, cap)
    elif "," in text:
        try:
            parsed = [float(b) for b in text.split(",") if b.strip()]
        except ValueError:
            raise ProblemError(
                f"expected a list of numbers like 0,1,3, got {text!r}", field="--budget"
            ) from None
    else:
        try:
            parsed = [float(text)]
        except ValueError:
            raise ProblemError(
                f"expected a number (2), a range (0..4) or a list (0,1,3), got {text!r}",
                field="--budget",
            ) from None
    if not parsed or any(not math.isfinite(b) or b < 0 for b in parsed):
        raise ProblemError(f"budgets must be non-negative numbers, got {text!r}", field="--budget")
    return parsed


def _budget_range(text: str, cap: float | None) -> list[float]:
    """``0..7``: each whole budget from low to high (see :func:`parse_budgets`)."""
    try:
        low, high = (int(part) for part in text.split("..", 1))
    except ValueError:
        raise ProblemError(
            f"expected a range of whole numbers like 0..4, got {text!r}", field="--budget"
        ) from None
    if low < 0 or high < low:
        raise ProblemError(
            f"expected a range low..high with 0 ≤ low ≤ high, got {text!r}", field="--budget"
        )
    top = high
    if cap is not None and high - low >= LISTED_RANGE:
        top = min(high, max(low, math.ceil(cap)))
    if top - low > 1_000_000:
        raise ProblemError(
            f"a range of {top - low + 1:,} budgets is too many; give fewer", field="--budget"
        )
    parsed = [float(b) for b in range(low, top + 1)]
    if top < high:
        parsed.append(float(high))
    return parsed


def one_budget(text: str | None, command: str) -> float | None:
    """``--budget`` of a command that answers one budget (``audit``, ``harden``): read as
    solve's (:func:`parse_budgets`), a range or list of more than one budget refused."""
    parsed = parse_budgets(text, cap=0.0)  # a long range stays two budgets, not millions
    if parsed is None:
        return None
    if len(set(parsed)) > 1:
        raise ProblemError(
            f"{command} answers one budget B (and every budget below it on the way), got "
            f"{text!r}; give one number, e.g. --budget {parsed[-1]:g} (solve takes a range "
            "or a list)",
            field="--budget",
        )
    return parsed[0]
