"""Problem file format ``misdirect/v1`` (YAML or JSON): schema, loading and writing.

Loading has two stages. The pydantic schema checks shape and types (so a typo in a field name
or a NaN probability is caught with its location); :func:`compile_problem` then resolves names,
checks that distributions sum to 1 and that the controller covers every (node, observation),
and produces the array model. Every failure is a :class:`ProblemError` naming file and field.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import math
import os
import re
from collections.abc import Iterator, Mapping
from fractions import Fraction
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
import yaml
from pydantic import (
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Discriminator,
    Field,
    Tag,
    ValidationError,
    WithJsonSchema,
    model_validator,
)

from misdirect.core import tolerance
from misdirect.core.alterations import max_alteration_cost
from misdirect.core.memory import check_memory
from misdirect.core.model import Controller, CostModel, Pomdp, Problem, factored_entries
from misdirect.core.monitor import DEFAULT_MAX_STATES, monitor_from_spec, with_monitor
from misdirect.core.objective import DecoySet
from misdirect.core.objective_property import ReachProperty, with_property
from misdirect.errors import MAX_REPORTED, ProblemError, ProblemsError
from misdirect.io.export import with_exported_names
from misdirect.io.files import (
    check_input_file,
    parse_json,
    parse_yaml,
    read_text_file,
    write_output,
)
from misdirect.io.grid_map import GridWorld, LegendEntry, compile_grid
from misdirect.io.paynt import (
    forbid_disabled_actions,
    forbid_targets,
    read_paynt_controller,
    unmet_rule_warning,
)
from misdirect.io.storm import StormPomdp, load_storm_pomdp
from misdirect.io.storm_expressions import reachability
from misdirect.io.storm_guard import run_isolated

FORMAT = "misdirect/v1"
WILDCARD = "*"
SUM_TOLERANCE = tolerance.STOCHASTIC


def _name(value: Any) -> Any:
    """Names are text: YAML turns ``1`` into an int, which we accept as "1", ``010`` into the
    octal 8, which we read as written ("010", never merged with a name ``8``), and ``yes``
    into a bool, which we refuse with a hint (quote it)."""
    if isinstance(value, bool) or value is None:
        raise ValueError(f"a name must be a string; YAML read {value!r} (quote it)")
    if isinstance(value, int):
        return getattr(value, "written", str(value))
    return value


def _number(value: Any) -> Any:
    if isinstance(value, bool):
        raise ValueError(f"expected a number, got {value!r}")
    if isinstance(value, float) and math.isnan(value):
        raise ValueError("expected a number, got NaN")
    return value


_RATIONAL = re.compile(r"\s*[+-]?\d+\s*/\s*[+-]?\d+\s*")


def rational(value: Any) -> Any:
    """A probability as PRISM writes it: ``"2/3"`` (exactly the fraction, then rounded once to
    the nearest float) or a decimal text (``"0.25"``); numbers pass through. A zero
    denominator, a non-finite value or a text that is no number is refused, naming the text."""
    if not isinstance(value, str):
        return _number(value)
    text = value.strip()
    try:
        if "/" in text:
            if not _RATIONAL.fullmatch(text):
                raise ValueError
            numerator, denominator = (int(part) for part in text.split("/"))
            if denominator == 0:
                raise ValueError(f"{value!r} has a zero denominator")
            exact = Fraction(numerator, denominator)
        else:
            exact = Fraction(text)  # refuses inf and nan
        return float(exact)
    except OverflowError:
        raise ValueError(f"{value!r} is out of range") from None
    except ValueError as error:
        reason = str(error) if "denominator" in str(error) else ""
        raise ValueError(
            reason or f'expected a number or a fraction like "2/3", got {value!r}'
        ) from None


def _cost(value: Any) -> Any:
    if isinstance(value, str) and value.strip().lower() in {"forbidden", "inf", "infinity"}:
        return math.inf
    return _number(value)


Name = Annotated[
    str,
    BeforeValidator(_name),
    Field(min_length=1),
    WithJsonSchema({"anyOf": [{"type": "string", "minLength": 1}, {"type": "integer"}]}),
]
Probability = Annotated[
    float,
    BeforeValidator(rational),
    Field(ge=0.0, le=1.0),
    WithJsonSchema(
        {
            "anyOf": [
                {"type": "number", "minimum": 0, "maximum": 1},
                {"type": "string", "pattern": r"^\s*[+-]?\d+\s*/\s*[+-]?\d+\s*$"},
            ],
            "description": 'a number in [0, 1], or a fraction as PRISM writes it ("2/3")',
        }
    ),
]
Budget = Annotated[float, BeforeValidator(_number), Field(ge=0.0, allow_inf_nan=False)]
Weight = Annotated[float, BeforeValidator(_number), Field(ge=0.0, allow_inf_nan=False)]
Cost = Annotated[
    float,
    BeforeValidator(_cost),
    Field(ge=0.0, description='non-negative number; "forbidden" (or .inf) forbids the pair'),
]


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid")


class PomdpSpec(_Strict):
    """World: states, actions, observation of each state and transition probabilities."""

    states: list[Name] = Field(min_length=1)
    actions: list[Name] = Field(min_length=1)
    initial: Name
    observe: dict[Name, Name] = Field(description="state -> observation it emits")
    observations: list[Name] | None = Field(
        default=None,
        description="all observations, in order; only needed to declare observations that no "
        "state emits (the controller may still react to them, so they are alteration targets)",
    )
    transitions: list[tuple[Name, Name, Name, Probability]] = Field(
        default_factory=list, description="[state, action, next_state, probability]"
    )
    absorbing: list[Name] = Field(
        default_factory=list, description="states with a self-loop under every action"
    )


class StormPomdpSpec(_Strict):
    """A POMDP Storm builds: a PRISM program or a DRN file (needs ``misdirect[storm]``)."""

    prism: str | None = Field(default=None, description="PRISM file, relative to this file")
    drn: str | None = Field(default=None, description="DRN file, relative to this file")
    constants: str | None = Field(default=None, description='PRISM constants, e.g. "N=5,p=0.1"')
    terminal: str | None = Field(
        default=None,
        description="states that end the run (made absorbing), as PAYNT builds its models with "
        'the property\'s target terminal: a PRISM expression over variables and labels ("goal", '
        "or goal when no variable is called that), or for DRN a label expression (!, &, |)",
    )
    terminal_from: str | None = Field(
        default=None,
        description="a property, e.g. 'P=? [F \"goal\"]', whose target states Storm builds "
        "terminal (exactly what PAYNT does with its specification)",
    )
    disabled_action: Literal["stay", "forbid"] = Field(
        default="stay",
        description="the controller picks an action Storm does not enable in the true state: "
        "stay put (stay), or forbid the alterations that can cause it (forbid)",
    )


def _pomdp_kind(value: Any) -> str:
    if isinstance(value, dict) and ("prism" in value or "drn" in value):
        return "storm"
    return "explicit"


AnyPomdpSpec = Annotated[
    Annotated[PomdpSpec, Tag("explicit")] | Annotated[StormPomdpSpec, Tag("storm")],
    Discriminator(_pomdp_kind),
]


def _choice(value: Any) -> Any:
    """A rule's ``action``/``next``: a name, or a ``{name: probability}`` map (randomized).
    Probabilities are checked when the rule is compiled, with the rule's field name."""
    if isinstance(value, dict):
        if not value:
            raise ValueError("an empty distribution; give a name or {name: probability, ...}")
        return {_name(key): p for key, p in value.items()}
    name = _name(value)
    if not isinstance(name, str) or not name:
        raise ValueError(f"expected a name or a {{name: probability}} map, got {value!r}")
    return name


Choice = Annotated[
    Any,
    BeforeValidator(_choice),
    WithJsonSchema(
        {
            "anyOf": [
                {"type": "string", "minLength": 1},
                {"type": "integer"},
                {
                    "type": "object",
                    "minProperties": 1,
                    "additionalProperties": {
                        "anyOf": [
                            {"type": "number", "minimum": 0, "maximum": 1},
                            {"type": "string", "description": 'a fraction, e.g. "2/3"'},
                        ]
                    },
                    "description": "randomized: {name: probability}, summing to 1",
                },
            ]
        }
    ),
]


class MoveSpec(_Strict):
    """One (action, next node) pair of a randomized rule's joint distribution."""

    action: Name
    next: Name
    p: Probability


class RuleSpec(_Strict):
    """``action`` and ``next`` (each a name or a ``{name: probability}`` map, drawn
    independently), or ``moves``: a joint distribution over (action, next node) pairs."""

    node: Name
    obs: Name
    action: Choice | None = None
    next: Choice | None = None
    moves: list[MoveSpec] | None = Field(default=None, min_length=1)

    @model_validator(mode="after")
    def _one_form(self) -> RuleSpec:
        if self.moves is not None and (self.action is not None or self.next is not None):
            raise ValueError("give either action and next, or moves, not both")
        if self.moves is None and (self.action is None or self.next is None):
            missing = "action" if self.action is None else "next"
            raise ValueError(f"missing {missing} (or give moves: [{{action, next, p}}, ...])")
        return self


class ControllerSpec(_Strict):
    """Finite-state controller as rules; the first rule matching (node, observation) wins."""

    nodes: list[Name] = Field(min_length=1)
    initial: Name
    rules: list[RuleSpec] = Field(min_length=1)


class PayntControllerSpec(_Strict):
    """A deterministic FSC in PAYNT's JSON format (``action_function``, ``update_function``)."""

    paynt: str = Field(description="PAYNT .fsc.json file, relative to this file")


def _controller_kind(value: Any) -> str:
    return "paynt" if isinstance(value, dict) and "paynt" in value else "rules"


AnyControllerSpec = Annotated[
    Annotated[ControllerSpec, Tag("rules")] | Annotated[PayntControllerSpec, Tag("paynt")],
    Discriminator(_controller_kind),
]


class DecoyLabelSpec(_Strict):
    label: Name = Field(description="a state label of the model (PRISM/DRN)")


class DecoyExpressionSpec(_Strict):
    expression: str = Field(
        min_length=1,
        description="a state condition: PRISM expression over variables and labels, or for DRN "
        "a label expression (!, &, |, parentheses)",
    )


class WeightedDecoySpec(_Strict):
    """One weighted decoy set, when its name alone does not say which states it holds."""

    weight: Weight = Field(description="the attacker's reward when this set is entered first")
    states: list[Name] | None = Field(default=None, min_length=1)
    label: Name | None = None
    expression: str | None = Field(default=None, min_length=1)


WeightedDecoys = dict[
    Name,
    Annotated[
        Annotated[Weight, Tag("<weight>")] | Annotated[WeightedDecoySpec, Tag("<set>")],
        Discriminator(lambda value: "<set>" if isinstance(value, dict) else "<weight>"),
    ],
]


def _decoy_kind(value: Any) -> str:
    if isinstance(value, dict):
        # weighted sets map names to numbers or {weight: ...}; a text value is the label or
        # expression form, misspelt or not ({lable: goal} is "label is missing")
        if any(isinstance(entry, str) for entry in value.values()):
            return "expression" if "expression" in value else "label"
        return "weighted"
    return "states"


class CostSpec(_Strict):
    default: Cost = Field(default=1.0, description="cost of o -> o' for o != o'")
    pairs: dict[Name, dict[Name, Cost]] = Field(
        default_factory=dict, description="overrides: {o: {o': cost}}"
    )
    forbidden: list[tuple[Name, Name]] = Field(
        default_factory=list, description='[o, o\'] pairs never allowed; "*" matches any'
    )
    protected: list[Name] = Field(
        default_factory=list, description="observations that cannot be altered at all"
    )


def _legend_entry(value: Any) -> Any:
    """``G: goal`` is short for ``G: {kind: goal}``."""
    return {"kind": value} if isinstance(value, str) else value


class GridCellSpec(_Strict):
    kind: Literal["blank", "goal", "decoy", "wall"] = "blank"
    start: bool = False
    sensor: Name | None = Field(default=None, description="sensor id watching this cell")


class GridSpec(_Strict):
    """A grid world drawn as a map (see misdirect.io.grid_map); replaces ``pomdp``."""

    map: str = Field(description="rows of whitespace-separated cells, north first")
    legend: dict[Name, Annotated[GridCellSpec, BeforeValidator(_legend_entry)]] = Field(
        default_factory=dict, description="symbol -> kind; digits need no entry (sensor ids)"
    )
    slip: float = Field(
        default=0.1, ge=0.0, le=0.5, description="probability of each orthogonal move"
    )
    actions: list[Name] = Field(default_factory=lambda: ["N", "E", "S", "W"], min_length=1)


class DeceptionSpec(_Strict):
    decoy: (
        Annotated[
            Annotated[list[Name], Field(min_length=1), Tag("states")]
            | Annotated[DecoyLabelSpec, Tag("label")]
            | Annotated[DecoyExpressionSpec, Tag("expression")]
            | Annotated[WeightedDecoys, Field(min_length=1), Tag("weighted")],
            Discriminator(_decoy_kind),
        ]
        | None
    ) = Field(
        default=None,
        description="decoy states, {label: ...} or {expression: ...}, or weighted decoy sets "
        "{name: weight} (name: a label or a state) or {name: {weight, states|label|expression}}; "
        "grid maps mark decoy cells in the map instead",
    )
    property: str | None = Field(
        default=None,
        min_length=1,
        description="the objective as a PRISM property over a PRISM or DRN model: "
        '\'P=? [F "decoy"]\', \'P=? [!"avoid" U "decoy"]\', \'P=? [F<=k "decoy"]\' or '
        "'P=? [a U<=k b]'; its target is the decoy (decoy may then be left out, or must name "
        "the same states)",
    )
    budget: Budget = 0.0
    cost: CostSpec = Field(default_factory=CostSpec)


class ConsistencySpec(_Strict):
    max_states: int = Field(
        default=DEFAULT_MAX_STATES,
        ge=1,
        description="the most belief supports the monitor may have (an error past it)",
    )


def _one_or_many(value: Any) -> Any:
    """A guard: one name is a list of one (``"*"``: any)."""
    return value if isinstance(value, list) else [value]


Guard = Annotated[
    list[Name],
    BeforeValidator(_one_or_many),
    Field(min_length=1),
    WithJsonSchema(
        {
            "anyOf": [
                {"type": "string", "minLength": 1},
                {"type": "integer"},
                {
                    "type": "array",
                    "minItems": 1,
                    "items": {"anyOf": [{"type": "string", "minLength": 1}, {"type": "integer"}]},
                },
            ]
        }
    ),
]


class MonitorTransitionSpec(_Strict):
    """In ``state``, on ``reading`` (and ``action``), go to ``next``. A named reading beats
    ``"*"`` (any other reading), then a named action beats ``"*"``."""

    state: Name
    reading: Guard = Field(
        description='the reading (what the robot receives), a list of them, or "*"'
    )
    action: Guard = Field(
        default_factory=lambda: [WILDCARD],
        description='the action the robot plays on that reading, a list, or "*" (default)',
    )
    next: Name


class MonitorSpec(_Strict):
    """A monitor: ``consistency: true`` (the robot's plausibility check) or an automaton
    (``states``, ``initial``, ``alarm``, ``transitions``). With a monitor the value is
    Pr(reach a decoy before the alarm) (docs/stealth.md)."""

    name: str | None = Field(default=None, description="what reports call the monitor")
    consistency: bool | ConsistencySpec | None = Field(
        default=None,
        description="the robot's plausibility check: an alarm on a reading no state of the "
        "belief support emits; true, or {max_states: N}",
    )
    states: list[Name] | None = Field(default=None, min_length=1)
    initial: Name | None = None
    alarm: list[Name] | None = Field(default=None, description="the states that raise the alarm")
    transitions: list[MonitorTransitionSpec] | None = Field(default=None, min_length=1)

    @model_validator(mode="after")
    def _one_kind(self) -> MonitorSpec:
        automaton = {
            "states": self.states,
            "initial": self.initial,
            "alarm": self.alarm,
            "transitions": self.transitions,
        }
        given = [key for key, value in automaton.items() if value is not None]
        if self.consistency not in (None, False):
            if given:
                raise ValueError(
                    f"give consistency or an automaton, not both (remove {', '.join(given)})"
                )
            return self
        missing = [key for key, value in automaton.items() if value is None]
        if missing:
            raise ValueError(f"an automaton needs {', '.join(missing)} (or give consistency: true)")
        return self

    def document(self) -> dict[str, Any]:
        """The monitor as plain data (:func:`misdirect.core.monitor.monitor_from_spec`)."""
        return self.model_dump(exclude_none=True)


class ProblemFileV1(_Strict):
    """A misdirect problem: POMDP, controller, and what the attacker may do."""

    format: Literal["misdirect/v1"]
    name: str = ""
    description: str | None = None
    pomdp: AnyPomdpSpec | None = None
    grid: GridSpec | None = None
    controller: AnyControllerSpec
    deception: DeceptionSpec
    monitor: MonitorSpec | None = Field(
        default=None,
        description="a monitor watching the robot's readings: the value becomes "
        "Pr(reach a decoy before the alarm)",
    )


# -- reading ------------------------------------------------------------------------------------


# pydantic puts the tag of a tagged union into error locations; users never wrote it
_UNION_TAGS = {
    "pomdp": {"explicit", "storm"},
    "controller": {"rules", "paynt"},
    "decoy": {"states", "label", "expression", "weighted"},
}


_ANYWHERE_TAGS = {"<weight>", "<set>"}  # tags of unions inside user-named maps


def error_field(loc: tuple[Any, ...]) -> str:
    """A pydantic error's location as a field path: ``budgets[0]``, ``pomdp.states``."""
    text = ""
    previous = None
    for part in loc:
        if part in _ANYWHERE_TAGS or (
            isinstance(previous, str) and part in _UNION_TAGS.get(previous, ())
        ):
            previous = None
            continue
        previous = part
        if isinstance(part, int):
            text += f"[{part}]"
        else:
            text += f".{part}" if text else str(part)
    return text


def read_spec(path: str | Path) -> ProblemFileV1:
    """The problem file's document, validated but not compiled (what it names, as written)."""
    path = Path(path)
    try:
        return parse_spec(_read_document(path))
    except ProblemError as error:
        raise error.located(str(path)) from None


# suffixes of the models Storm reads (PAYNT's sketches are PRISM programs named *.templ)
MODEL_SUFFIXES = {".prism": "prism", ".pm": "prism", ".nm": "prism", ".templ": "prism"}
MODEL_SUFFIXES[".drn"] = "drn"
PROBLEM_SUFFIXES = (".yaml", ".yml", ".json")
_PRISM_START = re.compile(r"^(?:\s|//[^\n]*\n)*(?:pomdp|mdp|dtmc|ctmc|nondeterministic)\b")
_DRN_START = re.compile(r"^(?:\s|//[^\n]*\n)*@type\b")


def model_kind(path: str | Path, text: str | None = None) -> str | None:
    """``prism`` or ``drn`` when ``path`` is a model Storm reads rather than a problem file:
    by its suffix (``.prism``, ``.nm``, ``.pm``, ``.templ``; ``.drn``), or, for a name with
    another suffix, by how ``text`` (the file's text, read when not given) begins."""
    suffix = Path(path).suffix.lower()
    if suffix in MODEL_SUFFIXES:
        return MODEL_SUFFIXES[suffix]
    if suffix in PROBLEM_SUFFIXES:
        return None
    if text is None:
        try:
            with open(path, encoding="utf-8", errors="replace") as handle:
                text = handle.read(4096)
        except OSError:
            return None
    if _PRISM_START.match(text):
        return "prism"
    if _DRN_START.match(text):
        return "drn"
    return None


def not_a_problem_file(path: Path, kind: str) -> ProblemError:
    """What to do with a PRISM or DRN model given where a problem file was expected."""
    what = "a PRISM program" if kind == "prism" else "a DRN model"
    return ProblemError(
        f"{what}, not a misdirect/v1 problem file: name it in one (pomdp: {{{kind}: "
        f"{path.name}}}), or build the problem from it, its controller and its decoy "
        "(misdirect.problem_from_model; the commands that take FILE take the model with "
        "its controller and decoy as options)",
        source=str(path),
    )


def _read_document(path: Path) -> Any:
    """The parsed file: a regular file within the size limit, JSON by suffix, else YAML, with
    depth, alias and duplicate-key limits (misdirect.io.files). A PRISM or DRN model is
    refused as one, not as invalid YAML."""
    text = read_text_file(path)
    if path.suffix.lower() == ".json":
        return parse_json(text, source=str(path))
    kind = model_kind(path, text)
    if kind is not None:
        raise not_a_problem_file(path, kind)
    return parse_yaml(text, source=str(path))


def error_reason(item: Any) -> str:
    """A pydantic error's message in our words (our validators' own, unknown fields named)."""
    if item["type"] == "extra_forbidden":
        return "unknown field (check the spelling)"
    message = str(item["msg"])
    return message.removeprefix("Value error, ")  # our validators' own words


def parse_spec(document: Any) -> ProblemFileV1:
    """Validate the document's shape; every schema error (up to
    :data:`misdirect.errors.MAX_REPORTED`) is reported, each naming its field."""
    if not isinstance(document, dict):
        raise ProblemError("the file must contain a mapping with format, pomdp, controller, ...")
    if document.get("format") != FORMAT:
        raise ProblemError(
            f"expected format: {FORMAT}, got {document.get('format')!r}", field="format"
        )
    _check_key_names(document)
    try:
        return ProblemFileV1.model_validate(document)
    except ValidationError as error:
        found = [
            ProblemError(error_reason(item), field=error_field(item["loc"]))
            for item in error.errors()
        ]
        raise ProblemsError.of(found) from None


def _check_key_names(document: dict) -> None:
    """Keys are names, and names are text: a mapping (built in Python, say) whose keys ``1``
    and ``"1"`` would become one name is refused, not silently merged. (The YAML reader keeps
    every key as written, so a file reports such keys as duplicates.)"""
    pending: list[tuple[Any, str]] = [(document, "")]
    while pending:
        value, where = pending.pop()
        if isinstance(value, list):  # of dicts (rules): lists of scalars hold no keys
            pending.extend((v, f"{where}[{i}]") for i, v in enumerate(value) if type(v) is dict)
            continue
        if not all(type(key) is str for key in value):
            seen: dict[str, Any] = {}
            for key in value:
                text = key if isinstance(key, str) else getattr(key, "written", str(key))
                if text in seen:
                    raise ProblemError(
                        f"keys {seen[text]!r} and {key!r} are the same name {text!r}",
                        field=where.lstrip(".") or None,
                    )
                seen[text] = key
        pending.extend(
            (item, f"{where}.{key}") for key, item in value.items() if type(item) in (dict, list)
        )


def load_problem(
    path: str | Path,
    *,
    controller: str | Path | None = None,
    monitor: str | Path | MonitorSpec | None = None,
) -> Problem:
    """Read and check a problem file (YAML or JSON; docs/problem-format.md).

    Parameters
    ----------
    path : str or Path
        A ``misdirect/v1`` problem file: JSON by its ``.json`` suffix, else YAML. Files it
        names (a PRISM or DRN model, a PAYNT controller) are found relative to it.
    controller : str or Path, optional
        A controller file to use instead of the file's own: PAYNT's ``.fsc.json``, or a YAML
        file of rules (relative to the working directory, not to the problem file).
    monitor : str, Path or MonitorSpec, optional
        A monitor to use instead of the file's own ``monitor:`` (:func:`read_monitor`:
        ``"consistency"`` or a YAML file of an automaton); with one, the value is
        Pr(reach a decoy before the alarm).

    Returns
    -------
    Problem
        The checked problem, names compiled into integer arrays.

    Raises
    ------
    ProblemError
        The file cannot be read, or is not a valid problem: the message names the file, the
        field and the reason (``model.yaml: pomdp.transitions: ...``).

    Examples
    --------
    >>> import misdirect
    >>> problem = misdirect.load_problem("examples/paper-grid-map.yaml")
    >>> problem.pomdp.n_states, problem.budget
    (25, 4.0)
    """
    path = Path(path)
    spec = read_spec(path)
    if controller is not None:
        replaced = controller_document(controller)
        spec = spec.model_copy(update={"controller": _controller_spec(replaced, controller)})
    try:
        problem = compile_problem(spec, source=str(path))
    except ProblemError as error:
        if controller is not None:
            error = controller_error(error, str(controller))
        raise error.located(str(path)) from None
    if monitor is not None:
        given, where = read_monitor(monitor)
        return monitored(problem, given, source=where, field="")
    if spec.monitor is not None:
        return monitored(problem, spec.monitor, source=str(path))
    return problem


# -- monitors -----------------------------------------------------------------------------------

CONSISTENCY = "consistency"


def read_monitor(value: str | Path | MonitorSpec) -> tuple[MonitorSpec, str]:
    """A monitor as given on a command line or to :func:`load_problem`, and what its errors
    name: ``"consistency"`` (the robot's plausibility check), a YAML or JSON file holding an
    automaton (``states``, ``initial``, ``alarm``, ``transitions``, as under ``monitor:`` in a
    problem file) or a problem file whose monitor is taken, or a :class:`MonitorSpec`."""
    if isinstance(value, MonitorSpec):
        return value, "monitor"
    if str(value) == CONSISTENCY:
        return MonitorSpec(consistency=True), "monitor"
    path = Path(value)
    if not path.exists():
        raise ProblemError(
            f"file not found: {path} (give consistency or a monitor file)", source="monitor"
        )
    check_input_file(path, source="monitor")
    document = _read_document(path)
    if isinstance(document, dict) and "format" in document and "monitor" in document:
        document = document["monitor"]  # another problem file's monitor
    return parse_monitor(document, source=str(path)), str(path)


def parse_monitor(document: Any, *, source: str, field: str = "") -> MonitorSpec:
    """A monitor's document validated (every schema error at once, each naming ``source``
    and its field)."""
    if not isinstance(document, dict):
        raise ProblemError(
            "expected a monitor: a mapping with states, initial, alarm and transitions, or "
            "consistency: true",
            source=source,
            field=field or None,
        )
    try:
        return MonitorSpec.model_validate(document)
    except ValidationError as error:
        found = [
            ProblemError(
                error_reason(item),
                source=source,
                field=".".join(part for part in (field, error_field(item["loc"])) if part) or None,
            )
            for item in error.errors()
        ]
        raise ProblemsError.of(found) from None


def monitored(
    problem: Problem, spec: MonitorSpec, *, source: str | None, field: str = "monitor"
) -> Problem:
    """``problem`` watched by the monitor ``spec`` describes (:func:`misdirect.core.monitor.
    with_monitor`); errors name ``source`` and the field."""
    try:
        return with_monitor(problem, monitor_from_spec(problem, spec.document(), field=field))
    except ProblemError as error:
        raise error.located(source) if source is not None else error from None


_RULES_SUFFIXES = (".yaml", ".yml")


def relative_path(path: str | Path, relative_to: Path | None) -> str:
    """``path`` as a problem file in ``relative_to`` names it (absolute when there is none)."""
    if relative_to is None:
        return str(Path(path).absolute())
    return os.path.relpath(Path(path).absolute(), Path(relative_to).absolute())


def controller_document(path: str | Path, *, relative_to: Path | None = None) -> dict[str, Any]:
    """The ``controller:`` entry of a document for the controller in ``path``.

    A ``.yaml``/``.yml`` file holds rules (``nodes``, ``initial``, ``rules``, as under
    ``controller:`` in a problem file) or is a problem file whose controller is taken; any
    other file is PAYNT's ``.fsc.json``, named (relative to ``relative_to``, the folder of
    the document, or absolute) and read when the problem is compiled."""
    path = Path(path)
    if path.suffix.lower() not in _RULES_SUFFIXES:
        return {"paynt": relative_path(path, relative_to)}
    if not path.exists():
        raise ProblemError(f"file not found: {path}", source="controller")
    check_input_file(path, source="controller")
    document = parse_yaml(read_text_file(path), source=str(path))
    if isinstance(document, dict) and "format" in document and "controller" in document:
        controller = document["controller"]  # another problem file's controller
        if isinstance(controller, dict) and isinstance(controller.get("paynt"), str):
            return {"paynt": relative_path(path.parent / controller["paynt"], relative_to)}
        document = controller
    if not isinstance(document, dict) or "rules" not in document:
        raise ProblemError(
            "expected a controller: a mapping with nodes, initial and rules (as under "
            "controller: in a problem file), or a problem file",
            source=str(path),
        )
    return document


def _controller_spec(document: dict[str, Any], path: str | Path) -> Any:
    """A controller file's ``controller:`` entry, validated (errors name the file)."""
    try:
        return parse_spec({"format": FORMAT, "controller": document, "deception": {}}).controller
    except ProblemError as error:
        raise controller_error(error, str(path)) from None


def controller_error(error: ProblemError, controller: str) -> ProblemError:
    """An error about the ``controller:`` of a document that a controller file (given as a
    setting, ``--controller``) filled in: a missing file names the setting, a rule the file."""
    if isinstance(error, ProblemsError):
        problems = [controller_error(problem, controller) for problem in error.problems]
        return ProblemsError.of(problems, error.total)
    field = error.field or ""
    if error.source is not None or not field.startswith("controller"):
        return error
    if field == "controller.paynt":
        return ProblemError(error.reason, source="controller")
    inside = field[len("controller") :].lstrip(".") or None
    return ProblemError(error.reason, source=controller, field=inside)


def problem_from_dict(
    document: Mapping[str, Any], *, source: str = "<dict>", base_dir: str | Path | None = None
) -> Problem:
    """Build a problem from a ``misdirect/v1`` document already in memory.

    The same document as a problem file's (docs/problem-format.md), as nested dicts and
    lists: ``problem_from_dict(yaml.safe_load(text))`` is ``load_problem`` of that text.

    Parameters
    ----------
    document : mapping
        The problem: ``format: misdirect/v1``, then ``pomdp`` (or ``grid``), ``controller``
        and ``deception``.
    source : str
        What error messages name as the file.
    base_dir : str or Path, optional
        Where relative file names inside the document (a PRISM model, a PAYNT controller)
        are found; default the current directory.

    Returns
    -------
    Problem
        The checked problem.

    Raises
    ------
    ProblemError
        The document is not a valid problem; the message names ``source``, the field and
        the reason.

    Examples
    --------
    >>> import misdirect
    >>> problem = misdirect.problem_from_dict({
    ...     "format": "misdirect/v1",
    ...     "pomdp": {
    ...         "states": ["start", "loop", "exit", "goal", "decoy"],
    ...         "actions": ["stay", "go"],
    ...         "initial": "start",
    ...         "observe": {"start": "o0", "loop": "o1", "exit": "o2", "goal": "g", "decoy": "g"},
    ...         "transitions": [
    ...             ["start", "stay", "loop", 0.6], ["start", "stay", "exit", 0.4],
    ...             ["start", "go", "loop", 0.6], ["start", "go", "exit", 0.4],
    ...             ["loop", "stay", "loop", 1.0],
    ...             ["loop", "go", "decoy", 0.5], ["loop", "go", "goal", 0.5],
    ...             ["exit", "stay", "decoy", 0.25], ["exit", "stay", "goal", 0.75],
    ...             ["exit", "go", "goal", 1.0],
    ...         ],
    ...         "absorbing": ["goal", "decoy"],
    ...     },
    ...     "controller": {"nodes": ["m"], "initial": "m", "rules": [
    ...         {"node": "*", "obs": "o0", "action": "go", "next": "m"},
    ...         {"node": "*", "obs": "*", "action": "stay", "next": "m"},
    ...     ]},
    ...     "deception": {"decoy": ["decoy"], "budget": 1},
    ... })
    >>> misdirect.solve(problem).alteration   # the loop's sensor read as the start's
    {'o1': 'o0'}
    """
    where = source if base_dir is None else str(Path(base_dir) / source)
    try:
        spec = parse_spec(dict(document))
        problem = compile_problem(spec, source=where)
    except ProblemError as error:
        raise error.located(source) from None
    if spec.monitor is not None:
        return monitored(problem, spec.monitor, source=source)
    return problem


class _Found:
    """The problems found while compiling, reported together: each independent part (a
    transition, a rule, a cost entry, ...) is checked in its own :meth:`check` block, so one
    mistake does not hide the others; :meth:`raise_any` then raises them all at once."""

    def __init__(self) -> None:
        self.problems: list[ProblemError] = []
        self.total = 0

    @contextlib.contextmanager
    def check(self) -> Iterator[None]:
        try:
            yield
        except ProblemsError as error:
            self.problems.extend(error.problems)
            self.total += error.total
        except ProblemError as error:
            self.add(error)

    def add(self, error: ProblemError) -> None:
        if len(self.problems) < MAX_REPORTED:
            self.problems.append(error)
        self.total += 1

    def uncounted(self, more: int) -> None:
        """``more`` further problems of a kind already shown, counted but not listed."""
        self.total += max(more, 0)

    def raise_any(self) -> None:
        if self.total:
            raise ProblemsError.of(self.problems, self.total)


@dataclasses.dataclass(frozen=True)
class _Names:
    """A world's names alone: enough to check the controller, the costs and the decoys of an
    explicit model whose transitions have problems of their own."""

    states: tuple[str, ...]
    actions: tuple[str, ...]
    observations: tuple[str, ...]


def _index(names: list[str], field: str) -> dict[str, int]:
    index: dict[str, int] = {}
    for i, name in enumerate(names):
        if name in index:
            raise ProblemError(f"duplicate name {name!r}", field=f"{field}[{i}]")
        index[name] = i
    return index


def _lookup(index: dict[str, int], name: str, kind: str, field: str) -> int:
    try:
        return index[name]
    except KeyError:
        known = ", ".join(list(index)[:8]) + (", …" if len(index) > 8 else "")
        raise ProblemError(f"unknown {kind} {name!r} (known: {known})", field=field) from None


def _resolve(name: str, base: Path | None) -> Path:
    path = Path(name)
    return path if base is None or path.is_absolute() else base / path


def _compile_weighted_decoys(
    spec: dict[str, Any], pomdp: Pomdp | _Names, labels: dict[str, np.ndarray], condition=None
) -> tuple[np.ndarray, tuple[DecoySet, ...]]:
    """Named decoy sets with their weights; a bare name is a label, else a state."""
    state_index = {name: i for i, name in enumerate(pomdp.states)}
    sets = []
    found = _Found()
    for name, entry in spec.items():
        with found.check():
            sets.append(_weighted_decoy(name, entry, pomdp, labels, condition, state_index))
    found.raise_any()
    if all(decoy_set.weight == 0 for decoy_set in sets):
        raise ProblemError(
            "every decoy weight is 0: there is nothing to gain", field="deception.decoy"
        )
    decoy = np.logical_or.reduce([decoy_set.states for decoy_set in sets])
    return decoy, tuple(sets)


def _weighted_decoy(
    name: str,
    entry: Any,
    pomdp: Pomdp | _Names,
    labels: dict[str, np.ndarray],
    condition: Any,
    state_index: dict[str, int],
) -> DecoySet:
    """One named decoy set: a weight (the name is a label or a state), or its states given."""
    field = f"deception.decoy.{name}"
    if isinstance(entry, WeightedDecoySpec):
        given = [k for k in ("states", "label", "expression") if getattr(entry, k) is not None]
        if len(given) > 1:
            raise ProblemError(f"give one of {', '.join(given)}, not several", field=field)
        weight = entry.weight
        if not given:
            states = _named_set(name, pomdp, labels, state_index, field)
        elif entry.states is not None:
            states = np.zeros(len(pomdp.states), dtype=bool)
            for i, state in enumerate(entry.states):
                states[_lookup(state_index, state, "state", f"{field}.states[{i}]")] = True
        else:  # one set by label or expression, checked as the unweighted forms are
            kind = "label" if entry.label is not None else "expression"
            form: DecoyLabelSpec | DecoyExpressionSpec
            if entry.label is not None:
                form = DecoyLabelSpec(label=entry.label)
            else:
                assert entry.expression is not None  # one of the three is given
                form = DecoyExpressionSpec(expression=entry.expression)
            try:
                states = _compile_decoy(form, pomdp, labels, condition)
            except ProblemError as error:  # named in this set, not in deception.decoy
                raise ProblemError(error.reason, field=f"{field}.{kind}") from None
    else:
        weight, states = float(entry), _named_set(name, pomdp, labels, state_index, field)
    return DecoySet(name=name, weight=float(weight), states=states)


def _named_set(
    name: str,
    pomdp: Pomdp | _Names,
    labels: dict[str, np.ndarray],
    state_index: dict[str, int],
    field: str,
) -> np.ndarray:
    if name in labels:
        states = labels[name].copy()
        if not states.any():
            raise ProblemError(f"no state carries label {name!r}", field=field)
        return states
    if name in state_index:
        states = np.zeros(len(pomdp.states), dtype=bool)
        states[state_index[name]] = True
        return states
    known = ", ".join(sorted(labels)) or "none (explicit models have no labels)"
    raise ProblemError(
        f"{name!r} is neither a state label (labels: {known}) nor a state; or give "
        "{weight: ..., states: [...]}",
        field=field,
    )


def _compile_decoy(
    spec: Any, pomdp: Pomdp | _Names, labels: dict[str, np.ndarray], condition=None
) -> np.ndarray:
    if spec is None:
        raise ProblemError("list the decoy states, or give {label: ...}", field="deception.decoy")
    if isinstance(spec, DecoyExpressionSpec):
        field = "deception.decoy.expression"
        if condition is None:
            raise ProblemError(
                "an expression needs a PRISM or DRN model (list the states instead)", field=field
            )
        decoy = condition(spec.expression, field)
        if not decoy.any():
            raise ProblemError(f"no state satisfies {spec.expression!r}", field=field)
        return decoy
    if isinstance(spec, DecoyLabelSpec):
        if spec.label not in labels:
            known = ", ".join(sorted(labels)) or "none (explicit models have no labels)"
            raise ProblemError(
                f"no state label {spec.label!r} (labels: {known})", field="deception.decoy.label"
            )
        decoy = labels[spec.label].copy()
        if not decoy.any():
            raise ProblemError(f"no state carries label {spec.label!r}", field="deception.decoy")
        return decoy
    state_index = {name: i for i, name in enumerate(pomdp.states)}
    decoy = np.zeros(len(pomdp.states), dtype=bool)
    found = _Found()
    for i, name in enumerate(spec):
        with found.check():
            decoy[_lookup(state_index, name, "state", f"deception.decoy[{i}]")] = True
    found.raise_any()
    return decoy


def _compile_property(text: str, world: Any, condition) -> ReachProperty:
    """The problem file's ``deception.property`` over a Storm model, as a
    :class:`~misdirect.core.objective_property.ReachProperty`."""
    field = "deception.property"
    assert isinstance(world, StormPomdp) and world.parse_property is not None
    assert condition is not None
    parts = reachability(world.parse_property(text, field), text, field)
    target = condition(parts.target, field)
    if not target.any():
        raise ProblemError(f"no state satisfies the target {parts.target!r}", field=field)
    stay = None if parts.stay is None else condition(parts.stay, field)
    return ReachProperty(text=text, target=target, stay=stay, bound=parts.bound)


def compile_problem(spec: ProblemFileV1, *, source: str | None = None) -> Problem:
    """Resolve names and check consistency; returns the array model.

    A PRISM or DRN model is read by Storm, native code that a malformed file can crash: that
    whole compilation runs in a child process (:func:`~misdirect.io.storm_guard.run_isolated`),
    which hands back the finished Problem, so a crash becomes one error naming the file."""
    if isinstance(spec.pomdp, StormPomdpSpec) and spec.grid is None:
        model = spec.pomdp.prism or spec.pomdp.drn or ""
        kind = "prism" if spec.pomdp.prism is not None else "drn"
        return run_isolated(
            _compile_problem, spec, source, name=Path(model).name, field=f"pomdp.{kind}"
        )
    return _compile_problem(spec, source)


def _compile_problem(spec: ProblemFileV1, source: str | None) -> Problem:
    base = Path(source).parent if source is not None else None
    enabled = None  # Storm's enabled actions, when disabled ones must be forbidden
    aliases: tuple[str, ...] = ()  # Storm's own observation texts (PAYNT's labels)
    paynt_view = None  # builds the model as PAYNT does: its observation numbering and labels
    never = np.zeros(0, dtype=np.int64)  # observations a PAYNT controller says never occur
    paynt = None
    labels: dict[str, np.ndarray] = {}  # Storm's state labels (PAYNT's terminal candidates)
    decoy_sets: tuple[DecoySet, ...] = ()  # weighted decoys, if the file gives weights
    found = _Found()  # the decoys, costs and controller are checked independently
    pomdp: Pomdp | None = None
    known: Pomdp | _Names  # the model, or only an explicit model's names when it has problems
    if (spec.pomdp is None) == (spec.grid is None):
        raise ProblemError("give exactly one of pomdp (explicit lists) or grid (a map)")
    reach: ReachProperty | None = None  # the objective, given as a PRISM property
    world: GridWorld | StormPomdp | None = None
    if spec.deception.property is not None and not isinstance(spec.pomdp, StormPomdpSpec):
        raise ProblemError(
            "a property needs a PRISM or DRN model (pomdp: {prism: ...} or {drn: ...}); "
            "for other models, list the decoy states",
            field="deception.property",
        )
    if spec.grid is not None:
        if spec.deception.decoy is not None:
            raise ProblemError(
                "with a grid map, decoy cells are marked in the map (legend kind: decoy)",
                field="deception.decoy",
            )
        world = compile_grid(
            spec.grid.map,
            {
                symbol: LegendEntry(kind=entry.kind, start=entry.start, sensor=entry.sensor)
                for symbol, entry in spec.grid.legend.items()
            },
            slip=spec.grid.slip,
            actions=spec.grid.actions,
        )
        pomdp = known = world.pomdp
        decoy = world.decoy
        if not decoy.any():
            raise ProblemError("the map has no decoy cell (legend kind: decoy)", field="grid.map")
    else:
        if isinstance(spec.pomdp, StormPomdpSpec):
            kind = "prism" if spec.pomdp.prism is not None else "drn"
            if spec.pomdp.prism is not None and spec.pomdp.drn is not None:
                raise ProblemError("give prism or drn, not both", field="pomdp")
            model_name = spec.pomdp.prism or spec.pomdp.drn
            if model_name is None:  # `prism: null` and no drn: the schema lets it through
                raise ProblemError("give the path of a prism or a drn file", field="pomdp")
            model_file = _resolve(model_name, base)
            if model_file.exists():  # a FIFO or a device would hang Storm: refuse it first
                check_input_file(model_file, field=f"pomdp.{kind}")
            world = load_storm_pomdp(
                Path(model_name),
                kind=kind,
                constants=spec.pomdp.constants,
                base=base,
                terminal=spec.pomdp.terminal,
                terminal_from=spec.pomdp.terminal_from,
            )
            # the names a PRISM or DRN file misdirect wrote keeps in its header
            world = dataclasses.replace(
                world, pomdp=with_exported_names(world.pomdp, model_file, kind)
            )
            pomdp, labels, condition = world.pomdp, world.labels, world.condition
            known = pomdp
            aliases, paynt_view = world.storm_observation_names, world.paynt_view
            if spec.pomdp.disabled_action == "forbid":
                enabled = world.enabled
        else:
            assert spec.pomdp is not None  # exactly one of pomdp and grid
            names, observation_of = _pomdp_names(spec.pomdp)
            labels, condition = {}, None
            with found.check():  # the rest is checked against the names all the same
                pomdp = _compile_pomdp(spec.pomdp, names, observation_of)
            known = names if pomdp is None else pomdp
        with found.check():
            if spec.deception.property is not None:
                reach = _compile_property(spec.deception.property, world, condition)
            if reach is not None and spec.deception.decoy is None:
                decoy = reach.target
            elif isinstance(spec.deception.decoy, dict):
                decoy, decoy_sets = _compile_weighted_decoys(
                    spec.deception.decoy, known, labels, condition
                )
            else:
                decoy = _compile_decoy(spec.deception.decoy, known, labels, condition)
    if isinstance(spec.controller, ControllerSpec):
        with found.check():
            controller = _compile_controller(spec.controller, known)
    elif pomdp is not None:  # PAYNT's controller is matched to the model itself
        paynt_file = _resolve(spec.controller.paynt, base)
        with found.check():
            if paynt_file.exists():
                check_input_file(paynt_file, field="controller.paynt")
            paynt = read_paynt_controller(paynt_file, pomdp, aliases=aliases, view=paynt_view)
            controller, never = paynt.controller, paynt.never_read
    obs_index = {name: i for i, name in enumerate(known.observations)}
    with found.check():
        cost = _compile_cost(spec.deception.cost, obs_index)
    found.raise_any()
    assert pomdp is not None  # no problem found: the model compiled
    if never.size:  # no state may be made to read an observation the controller never meets
        cost = forbid_targets(cost, never)
    if enabled is not None:
        cost = forbid_disabled_actions(cost, pomdp, controller, enabled, decoy)
    problem = Problem(
        pomdp=pomdp,
        controller=controller,
        cost=cost,
        decoy=decoy,
        budget=spec.deception.budget,
        name=spec.name,
        source=source,
        decoy_sets=decoy_sets,
    )
    # checked once here, so the file is named: every solve, audit and harden adds them up
    max_alteration_cost(problem)
    if reach is not None:
        try:
            problem = with_property(problem, reach)
        except ProblemError as error:
            raise ProblemError(error.reason, field="deception.property") from None
    if paynt is not None:
        terminal_given = isinstance(spec.pomdp, StormPomdpSpec) and (
            spec.pomdp.terminal is not None or spec.pomdp.terminal_from is not None
        )
        warning = unmet_rule_warning(
            problem, paynt.undefined, paynt_file, terminal_given=terminal_given, labels=labels
        )
        if warning is not None:
            problem = dataclasses.replace(problem, warnings=(warning,))
    return problem


def _pomdp_names(spec: PomdpSpec) -> tuple[_Names, np.ndarray]:
    """The explicit model's names, checked, and the observation of each state."""
    found = _Found()
    with found.check():
        _index(spec.states, "pomdp.states")
    with found.check():
        _index(spec.actions, "pomdp.actions")
    states = {name: i for i, name in enumerate(spec.states)}
    for name in spec.observe:
        with found.check():
            _lookup(states, name, "state", f"pomdp.observe.{name}")
    missing = [s for s in spec.states if s not in spec.observe]
    if missing:
        found.add(ProblemError(f"state {missing[0]!r} has no observation", field="pomdp.observe"))
    emitted = list(dict.fromkeys(spec.observe[s] for s in spec.states if s in spec.observe))
    observations = emitted if spec.observations is None else spec.observations
    if spec.observations is not None:
        with found.check():
            _index(observations, "pomdp.observations")
        for name in emitted:
            if name not in spec.observations:
                found.add(
                    ProblemError(
                        f"observation {name!r} is emitted by a state but not declared",
                        field="pomdp.observations",
                    )
                )
    found.raise_any()
    obs_index = {name: i for i, name in enumerate(observations)}
    observation_of = np.array([obs_index[spec.observe[s]] for s in spec.states], dtype=np.int64)
    names = _Names(tuple(spec.states), tuple(spec.actions), tuple(observations))
    return names, observation_of


def _compile_pomdp(spec: PomdpSpec, names: _Names, observation_of: np.ndarray) -> Pomdp:
    """The explicit model's transitions; every wrong one, duplicate or row not summing to 1
    is reported."""
    found = _Found()
    states = {name: i for i, name in enumerate(names.states)}
    actions = {name: i for i, name in enumerate(names.actions)}
    initial = 0
    with found.check():  # reported with the transitions' problems, not before them
        initial = _lookup(states, spec.initial, "state", "pomdp.initial")
    absorbing = np.zeros(len(states), dtype=bool)
    for i, name in enumerate(spec.absorbing):
        with found.check():
            absorbing[_lookup(states, name, "state", f"pomdp.absorbing[{i}]")] = True

    n_t = len(spec.transitions)
    source = np.empty(n_t, dtype=np.int64)
    action = np.empty(n_t, dtype=np.int64)
    target = np.empty(n_t, dtype=np.int64)
    probability = np.empty(n_t)
    for i, (s, a, t, p) in enumerate(spec.transitions):
        field = f"pomdp.transitions[{i}]"
        with found.check():
            source[i] = _lookup(states, s, "state", field)
        with found.check():
            action[i] = _lookup(actions, a, "action", field)
        with found.check():
            target[i] = _lookup(states, t, "state", field)
        probability[i] = p
        if s in states and absorbing[states[s]]:
            found.add(
                ProblemError(
                    f"state {s!r} is absorbing (self-loop under every action); "
                    "remove its transitions or take it out of pomdp.absorbing",
                    field=field,
                )
            )
    found.raise_any()  # the checks below need every name resolved
    n_s, n_a = len(states), len(actions)
    keys = (source * n_a + action) * n_s + target
    _, first, counts = np.unique(keys, return_index=True, return_counts=True)
    if (counts > 1).any():
        repeated = np.isin(keys, keys[first[counts > 1]])
        repeated[first] = False  # the first listing of each is not the repeat
        listed = np.flatnonzero(repeated)
        for dup in listed[:MAX_REPORTED]:
            found.add(
                ProblemError(
                    "the same (state, action, next_state) is listed twice",
                    field=f"pomdp.transitions[{dup}]",
                )
            )
        found.uncounted(listed.size - MAX_REPORTED)
    sums = np.bincount(source * n_a + action, weights=probability, minlength=n_s * n_a)
    bad = np.flatnonzero((np.abs(sums - 1.0) > SUM_TOLERANCE) & ~np.repeat(absorbing, n_a))
    found.uncounted(bad.size - MAX_REPORTED)
    for row in bad[:MAX_REPORTED]:
        bad_s, bad_a = divmod(int(row), n_a)
        pair = f"({names.states[bad_s]!r}, {names.actions[bad_a]!r})"
        reason = (
            f"no transitions for {pair}: list them, or mark {names.states[bad_s]!r} absorbing"
            if sums[row] == 0
            else f"probabilities of {pair} sum to {sums[row]:.12g}, not 1"
        )
        found.add(ProblemError(reason, field="pomdp.transitions"))
    found.raise_any()
    return Pomdp.from_triplets(
        states=names.states,
        actions=names.actions,
        observations=names.observations,
        initial_state=initial,
        observation_of=observation_of,
        action=action,
        source=source,
        target=target,
        probability=probability,
        absorbing=absorbing,
    )


def compile_controller(spec: ControllerSpec, pomdp: Pomdp) -> Controller:
    """A controller of rules, resolved against ``pomdp``'s names and checked."""
    return _compile_controller(spec, pomdp)


def _compile_controller(spec: ControllerSpec, pomdp: Pomdp | _Names) -> Controller:
    found = _Found()
    nodes = _index(spec.nodes, "controller.nodes")
    with found.check():
        initial = _lookup(nodes, spec.initial, "node", "controller.initial")
    actions = {name: i for i, name in enumerate(pomdp.actions)}
    observations = {name: i for i, name in enumerate(pomdp.observations)}
    n_observations = len(pomdp.observations)
    shape = (len(nodes), n_observations)
    check_memory(  # two dense tables, and the product chain needs |S|·|N| states on top
        16.0 * shape[0] * shape[1],
        f"a controller table of {shape[0]:,} nodes x {shape[1]:,} observations",
        field="controller.nodes",
    )
    rule_of = np.full(shape, -1, dtype=np.int64)
    moves: list[list[tuple[int, int, float]]] = []  # per rule: (action, next node, probability)
    where = []
    for i, rule in enumerate(spec.rules):
        field = f"controller.rules[{i}]"
        node: int | slice = slice(None)
        obs: int | slice = slice(None)
        if rule.node != WILDCARD:
            with found.check():
                node = _lookup(nodes, rule.node, "node", field)
        if rule.obs != WILDCARD:
            with found.check():
                obs = _lookup(observations, rule.obs, "observation", field)
        where.append((node, obs))
        with found.check():
            moves.append(_rule_moves(rule, actions, nodes, field))
    found.raise_any()  # coverage is only meaningful once every rule resolved
    for i in reversed(range(len(where))):  # earlier rules overwrite later ones
        rule_of[where[i]] = i
    uncovered = np.argwhere(rule_of < 0)
    if uncovered.size:
        n, o = uncovered[0]
        raise ProblemError(
            f"no rule covers node {spec.nodes[n]!r} with observation "
            f'{pomdp.observations[o]!r} (add a rule, or a catch-all with node/obs "*")',
            field="controller.rules",
        )
    # every cell gets its rule's entries
    size = np.array([len(m) for m in moves])
    flat = np.array([entry for m in moves for entry in m], dtype=np.float64).reshape(-1, 3)
    first = np.concatenate([[0], np.cumsum(size)[:-1]])
    cell = rule_of.ravel()
    count = size[cell]
    at = np.repeat(first[cell] - (np.cumsum(count) - count), count) + np.arange(count.sum())
    cell_index = np.repeat(np.arange(cell.size), count)
    return Controller.from_entries(
        nodes=tuple(spec.nodes),
        initial_node=initial,
        n_observations=n_observations,
        node=cell_index // n_observations,
        observation=cell_index % n_observations,
        action=flat[at, 0].astype(np.int64),
        next_node=flat[at, 1].astype(np.int64),
        probability=flat[at, 2],
    )


def _rule_moves(
    rule: RuleSpec, actions: dict[str, int], nodes: dict[str, int], field: str
) -> list[tuple[int, int, float]]:
    """A rule as its distribution over (action, next node): ``action`` and ``next`` drawn
    independently, or the joint ``moves``."""
    if rule.moves is not None:
        entries = [
            (
                _lookup(actions, move.action, "action", f"{field}.moves[{k}]"),
                _lookup(nodes, move.next, "node", f"{field}.moves[{k}]"),
                float(move.p),
            )
            for k, move in enumerate(rule.moves)
        ]
        _check_sum(sum(p for _, _, p in entries), f"{field}.moves")
        return entries
    assert rule.action is not None and rule.next is not None  # RuleSpec: moves, or both
    found = _Found()
    with found.check():
        by_action = _rule_distribution(rule.action, actions, "action", f"{field}.action")
    with found.check():
        by_next = _rule_distribution(rule.next, nodes, "node", f"{field}.next")
    found.raise_any()
    return factored_entries(by_action, by_next)


def _rule_distribution(
    value: str | dict[str, Any], index: dict[str, int], kind: str, field: str
) -> dict[int, float]:
    """``N`` or ``{N: 0.9, E: 0.1}`` as ``{index: probability}``, checked."""
    if isinstance(value, str):
        return {_lookup(index, value, kind, field): 1.0}
    distribution: dict[int, float] = {}
    for name, given in value.items():
        try:
            p = rational(given)
        except ValueError as error:
            raise ProblemError(f"the probability of {name!r}: {error}", field=field) from None
        if (
            isinstance(p, bool)
            or not isinstance(p, int | float)
            or not (math.isfinite(p) and 0 <= p <= 1)
        ):
            raise ProblemError(
                f"the probability of {name!r} must be a number in [0, 1], got {given!r}",
                field=field,
            )
        i = _lookup(index, name, kind, field)
        distribution[i] = distribution.get(i, 0.0) + float(p)
    _check_sum(sum(distribution.values()), field)
    return distribution


def _check_sum(total: float, field: str) -> None:
    if abs(total - 1.0) > SUM_TOLERANCE:
        raise ProblemError(f"probabilities sum to {total:.12g}, not 1", field=field)


def _compile_cost(spec: CostSpec, observations: dict[str, int]) -> CostModel:
    found = _Found()
    pairs: dict[tuple[int, int], float] = {}
    for source_name, costs in spec.pairs.items():
        try:
            o = _lookup(
                observations, source_name, "observation", f"deception.cost.pairs.{source_name}"
            )
        except ProblemError as error:
            found.add(error)
            continue
        for target_name, cost in costs.items():
            field = f"deception.cost.pairs.{source_name}.{target_name}"
            with found.check():
                pairs[o, _lookup(observations, target_name, "observation", field)] = cost
    everything = list(observations.values())
    for i, forbidden in enumerate(spec.forbidden):
        field = f"deception.cost.forbidden[{i}]"
        with found.check():
            sources, targets = (
                everything
                if name == WILDCARD
                else [_lookup(observations, name, "observation", field)]
                for name in forbidden
            )
            for o in sources:
                for t in targets:
                    if o != t:
                        pairs[o, t] = math.inf  # forbidding wins over any listed cost
    protected = set()
    for i, name in enumerate(spec.protected):
        with found.check():
            protected.add(
                _lookup(observations, name, "observation", f"deception.cost.protected[{i}]")
            )
    found.raise_any()
    return CostModel(
        n_observations=len(observations),
        default=spec.default,
        pairs=pairs,
        protected=frozenset(protected),
    )


# -- writing ------------------------------------------------------------------------------------


def _decoy_document(problem: Problem) -> Any:
    """The decoy states, or the weighted sets with their states listed."""
    states = problem.pomdp.states
    if not problem.decoy_sets:
        return [states[s] for s in np.flatnonzero(problem.decoy)]
    return {
        decoy_set.name: {
            "weight": decoy_set.weight,
            "states": [states[s] for s in np.flatnonzero(decoy_set.states)],
        }
        for decoy_set in problem.decoy_sets
    }


def _move_rule(controller: Controller, move: int, actions: tuple[str, ...]) -> dict[str, Any]:
    """A move as a rule's body: ``action``/``next`` names, ``{name: probability}`` maps when
    the move is the product of its marginals, else the joint ``moves``."""
    nodes = controller.nodes
    factored = controller.factored_move(int(move))
    if factored is None:
        return {
            "moves": [
                {"action": actions[a], "next": nodes[n], "p": p}
                for a, n, p in controller.move_table(int(move))
            ]
        }
    by_action, by_next = factored

    def shown(distribution: dict[int, float], names: tuple[str, ...]) -> Any:
        if len(distribution) == 1:
            return names[next(iter(distribution))]
        return {names[i]: p for i, p in distribution.items()}

    return {"action": shown(by_action, actions), "next": shown(by_next, nodes)}


def controller_to_document(controller: Controller, pomdp: Pomdp) -> dict[str, Any]:
    """The ``controller:`` entry of ``controller`` (``nodes``, ``initial``, ``rules``; a
    randomized move as ``{name: probability}`` maps or joint ``moves``). Written alone to a
    ``.yaml`` file, it loads back with ``--controller``."""
    actions, obs, nodes = pomdp.actions, pomdp.observations, controller.nodes
    rules = []
    for o in range(pomdp.n_observations):
        distinct = np.unique(controller.move[:, o])
        if distinct.size == 1:
            body = _move_rule(controller, distinct[0], actions)
            rules.append({"node": WILDCARD, "obs": obs[o], **body})
            continue
        for node in range(controller.n_nodes):
            body = _move_rule(controller, controller.move[node, o], actions)
            rules.append({"node": nodes[node], "obs": obs[o], **body})
    return {"nodes": list(nodes), "initial": nodes[controller.initial_node], "rules": rules}


def problem_to_document(problem: Problem) -> dict[str, Any]:
    """The explicit ``misdirect/v1`` document of ``problem`` (loads back to the same model)."""
    pomdp, controller = problem.pomdp, problem.controller
    states, actions, obs = pomdp.states, pomdp.actions, pomdp.observations
    coo = pomdp.transitions.tocoo()
    act, src = np.divmod(coo.row, pomdp.n_states)
    keep = ~pomdp.absorbing[src]
    order = np.lexsort((coo.col[keep], act[keep], src[keep]))
    transitions = [
        [states[s], actions[a], states[t], float(p)]
        for s, a, t, p in zip(
            src[keep][order],
            act[keep][order],
            coo.col[keep][order],
            coo.data[keep][order],
            strict=True,
        )
    ]
    cost = problem.cost
    pairs: dict[str, dict[str, float]] = {}
    forbidden = []
    for (o, t), value in sorted(cost.pairs.items()):
        if math.isinf(value):
            forbidden.append([obs[o], obs[t]])
        else:
            pairs.setdefault(obs[o], {})[obs[t]] = value
    # `observations` is only needed when it is not "emitted ones, in order of first appearance"
    emitted_in_order = [obs[o] for o in dict.fromkeys(pomdp.observation_of.tolist())]
    document: dict[str, Any] = {
        "format": FORMAT,
        "name": problem.name,
        "pomdp": {
            "states": list(states),
            "actions": list(actions),
            "initial": states[pomdp.initial_state],
            "observe": {states[s]: obs[o] for s, o in enumerate(pomdp.observation_of)},
            **({"observations": list(obs)} if emitted_in_order != list(obs) else {}),
            "transitions": transitions,
            "absorbing": [states[s] for s in np.flatnonzero(pomdp.absorbing)],
        },
        "controller": controller_to_document(controller, pomdp),
        "deception": {
            "decoy": _decoy_document(problem),
            "budget": problem.budget,
            "cost": {
                "default": "forbidden" if math.isinf(cost.default) else cost.default,
                "pairs": pairs,
                "forbidden": forbidden,
                "protected": [obs[o] for o in sorted(cost.protected)],
            },
        },
    }
    return document


class _FlowListDumper(getattr(yaml, "CSafeDumper", yaml.SafeDumper)):  # type: ignore[misc]
    """Short lists of scalars (transitions, forbidden pairs) on one line, as people write them."""


def _represent_list(dumper: yaml.SafeDumper, data: list) -> yaml.Node:
    flow = all(not isinstance(item, list | dict) for item in data) and len(data) <= 8
    return dumper.represent_sequence("tag:yaml.org,2002:seq", data, flow_style=flow)


def _represent_dict(dumper: yaml.SafeDumper, data: dict) -> yaml.Node:
    flow = all(not isinstance(v, list | dict) for v in data.values()) and len(data) <= 4
    return dumper.represent_mapping("tag:yaml.org,2002:map", data.items(), flow_style=flow)


_FlowListDumper.add_representer(list, _represent_list)
_FlowListDumper.add_representer(dict, _represent_dict)


WRITE_BYTES_PER_ENTRY = 2048  # the YAML writer's peak, per transition (paper_grid(300): 1.8 KiB)


def write_problem(problem: Problem, path: str | Path) -> None:
    """Write ``problem`` as YAML, or JSON when the file name ends in ``.json``."""
    path = Path(path)
    entries = problem.pomdp.transitions.nnz + len(problem.cost.pairs)
    check_memory(
        entries * WRITE_BYTES_PER_ENTRY,
        f"writing {problem.name} ({entries:,} transitions and cost pairs) as text",
        field="output",
    )
    write_output(path, problem_text(problem, as_json=path.suffix.lower() == ".json"))


def problem_text(problem: Problem, *, as_json: bool = False) -> str:
    """The explicit ``misdirect/v1`` document of ``problem`` as YAML (or JSON) text."""
    return problem_document_text(problem_to_document(problem), as_json=as_json)


def problem_document_text(document: dict[str, Any], *, as_json: bool = False) -> str:
    """A ``misdirect/v1`` document as YAML (or JSON) text."""
    if as_json:
        return json.dumps(document, indent=1) + "\n"
    return yaml.dump(
        document, Dumper=_FlowListDumper, sort_keys=False, width=100, allow_unicode=True
    )


def json_schema() -> dict[str, Any]:
    """JSON Schema of the v1 format (published as ``docs/problem-format.schema.json``)."""
    schema = ProblemFileV1.model_json_schema()
    # the legend's string shorthand (``G: goal``) is applied before validation, so pydantic
    # cannot see it; publish it
    legend = schema["$defs"]["GridSpec"]["properties"]["legend"]
    legend["additionalProperties"] = {
        "anyOf": [{"enum": ["blank", "goal", "decoy", "wall"]}, legend["additionalProperties"]]
    }
    schema["$schema"] = "https://json-schema.org/draft/2020-12/schema"
    schema["$id"] = "https://misdirect.dev/schema/problem-v1.json"
    return schema
