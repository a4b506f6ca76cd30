"""POMDPs from Storm: PRISM programs and DRN files, read through stormpy (``misdirect[storm]``).

Storm lets each state enable only some actions, and an altered observation can make the
controller pick one that is not enabled. The problem file decides what then happens:
``disabled_action: stay`` (the robot stays where it is; default) or ``forbid`` (alterations
that can make the controller pick a disabled action are not allowed at all).

This module is the loader: it has Storm build the model, checks what misdirect needs of it
(one initial state, distributions, one choice per state and action) and translates it into
misdirect's arrays. What it relies on lives beside it: :mod:`~misdirect.io.storm_arrays` reads
the matrix in bulk, :mod:`~misdirect.io.storm_names` names states, observations and actions,
:mod:`~misdirect.io.storm_expressions` reads the problem file's conditions, properties and
constants, and :mod:`~misdirect.io.paynt_model` builds the same model as PAYNT does.
"""

from __future__ import annotations

import dataclasses
import re
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from misdirect.core import tolerance
from misdirect.core.model import Pomdp
from misdirect.errors import ProblemError
from misdirect.io.files import check_input_file
from misdirect.io.paynt_model import PAYNT_NO_LABEL, PayntView, build_paynt_view, paynt_prism_text
from misdirect.io.storm_arrays import StormArrays, model_arrays
from misdirect.io.storm_expressions import (
    PrismProgram,
    instantiate_constants,
    label_condition,
    parse_property,
    prism_condition,
    prism_property,
    prism_target,
    storm_message,
    strip_comments,
)
from misdirect.io.storm_guard import check_drn_text, check_nesting
from misdirect.io.storm_names import (
    NO_LABEL,
    emitted_observations,
    observation_names,
    state_names,
    valuation_name,
)

# NO_LABEL, PAYNT_NO_LABEL, PayntView, paynt_prism_text and valuation_name live beside this
# module; they stay importable from here, where they were first defined
__all__ = [
    "MAX_PRISM_STATES",
    "NO_LABEL",
    "PAYNT_NO_LABEL",
    "SUM_TOLERANCE",
    "PayntView",
    "StormPomdp",
    "load_storm_pomdp",
    "paynt_prism_text",
    "valuation_name",
]

SUM_TOLERANCE = tolerance.STOCHASTIC


@dataclass(frozen=True)
class StormPomdp:
    """A POMDP Storm built, with what problem files and controllers refer to it by."""

    pomdp: Pomdp
    labels: dict[str, np.ndarray]  # label -> state mask
    enabled: np.ndarray  # (|S|, |A|) bool: Storm enables this action here
    # state condition (text, field) -> mask: PRISM expressions, or label expressions (DRN)
    condition: Callable[[str, str], np.ndarray] | None = None
    # Storm's own text of each observation's valuation (what PAYNT writes as its label)
    storm_observation_names: tuple[str, ...] = field(default=())
    # the state variables in the order that state names list them (for matching other builds)
    state_variables: tuple[str, ...] = field(default=())
    # the same model as PAYNT builds it (PAYNT's observation numbering and action labels),
    # built on demand: only PAYNT controllers need it
    paynt_view: Callable[[], PayntView] | None = field(default=None, compare=False)
    # a property's text (text, field) -> Storm's formula, parsed against the model
    parse_property: Callable[[str, str], Any] | None = field(default=None, compare=False)


def load_stormpy(field: str):
    """stormpy, or an error naming the extra that installs it."""
    try:
        import stormpy
        import stormpy.pomdp  # registers the POMDP model classes
    except ImportError:
        raise ProblemError(
            "reading PRISM or DRN models needs stormpy: pip install 'misdirect[storm]'",
            field=field,
        ) from None
    return stormpy


def load_storm_pomdp(
    path: Path,
    *,
    kind: str,
    constants: str | None = None,
    base: Path | None = None,
    terminal: str | None = None,
    terminal_from: str | None = None,
) -> StormPomdp:
    """Build the model with Storm and translate it; ``kind`` is ``prism`` or ``drn``.

    ``terminal`` (a state condition) and ``terminal_from`` (a property whose target states
    are made terminal, as PAYNT builds its models) make those states absorbing.
    """
    field = f"pomdp.{kind}"
    stormpy = load_stormpy(field)
    # Storm logs parse errors to stderr itself; we report them once, in our own words
    stormpy.developer.set_log_level(stormpy.developer.LogLevel.OFF)
    path = (base / path) if base is not None and not Path(path).is_absolute() else Path(path)
    if not path.exists():
        raise ProblemError(f"file not found: {path}", field=field)
    if terminal is not None and terminal_from is not None:
        raise ProblemError("give terminal or terminal_from, not both", field="pomdp.terminal")
    # what Storm would crash, hang or allocate without bound on is refused before it reads
    check_input_file(path, field=field)  # a FIFO or a device would hang the read
    text = path.read_text(encoding="utf-8", errors="replace")  # Storm reads bytes: so may we
    if kind == "prism":
        check_nesting(strip_comments(text), field=field, what=path.name)
    else:
        check_drn_text(text, name=path.name, field=field)
    model, program = build_storm_model(
        stormpy,
        path,
        kind,
        field,
        constants=constants,
        terminal=terminal,
        terminal_from=terminal_from,
    )
    prism = None
    if program is not None:
        source = strip_comments(text)
        prism = PrismProgram(stormpy, program, source)
    try:
        world = _translate(stormpy, model, field, path, prism)
    except RuntimeError as error:  # a DRN file without `init` fails only when it is read
        if "label init is invalid" not in str(error):
            raise
        raise _no_initial_state(path, field) from None
    if kind == "drn" and (terminal is not None or terminal_from is not None):
        world = _make_terminal_drn(stormpy, world, terminal, terminal_from)
    built = world

    def paynt_view() -> PayntView:
        return build_paynt_view(
            stormpy,
            path,
            kind,
            built.pomdp,
            built.state_variables,
            constants=constants,
            terminal=terminal,
            terminal_from=terminal_from,
        )

    program_or_none = program

    def read_property(text: str, where: str) -> Any:
        return parse_property(stormpy, program_or_none, text, where)

    return dataclasses.replace(world, paynt_view=paynt_view, parse_property=read_property)


def _no_initial_state(path: Path, field: str) -> ProblemError:
    return ProblemError(
        f"{path.name} has no initial state (no state is marked init); misdirect needs exactly one",
        field=field,
    )


# -- building -----------------------------------------------------------------------------------


def build_storm_model(
    stormpy,
    path: Path,
    kind: str,
    field: str,
    *,
    constants: str | None,
    terminal: str | None,
    terminal_from: str | None,
    exact: bool = False,
):
    """Storm's model of the file, and the PRISM program it was built from (None for DRN);
    ``exact``: with rational probabilities (:mod:`misdirect.io.exact_model`).

    Storm reports what it cannot read as RuntimeError (or its own StormError); that becomes
    one ProblemError, located at the line and column Storm names.
    """
    program = None
    try:
        if kind == "prism":
            program = _prism_program(stormpy, path, constants)
            model = _build_prism(stormpy, program, terminal, terminal_from, exact)
        else:
            options = stormpy.developer.DirectEncodingParserOptions()
            options.build_choice_labeling = True
            value_type = stormpy.Rational if exact else float
            model = stormpy.build_model_from_drn[value_type](str(path), options=options)
        if not model.is_partially_observable:
            raise ProblemError(
                f"{path.name} is a {model.model_type.name}, not a POMDP", field=field
            )
    except ProblemError:
        raise
    except Exception as error:  # Storm reports parse errors as RuntimeError/StormError
        message = storm_message(error)
        if "label init is invalid" in message:
            raise _no_initial_state(path, field) from None
        where = re.search(r"at (\d+):(\d+)", message)
        located = f"{field}, line {where[1]}, column {where[2]}" if where else field
        raise ProblemError(f"Storm cannot read {path.name}: {message}", field=located) from None
    return model, program


def _prism_program(stormpy, path: Path, constants: str | None):
    """The PRISM program with its constants set, refused if one has no value or if its
    variables span too many states."""
    program = stormpy.parse_prism_program(str(path))
    if constants:
        program = instantiate_constants(stormpy, program, constants)
    if program.has_undefined_constants:
        missing = ", ".join(c.name for c in program.constants if not c.defined)
        raise ProblemError(
            f'constants without a value: {missing} (give them as constants: "N=5")',
            field="pomdp.constants",
        )
    _check_state_space(program)
    return program


def _build_prism(
    stormpy, program, terminal: str | None, terminal_from: str | None, exact: bool = False
):
    """Storm's model of the program, with the valuations and labels that names and
    conditions need (Storm's builder changes the program: build each model from its own)."""
    formulas = []
    if terminal is not None:
        formulas = [prism_target(stormpy, program, terminal, "pomdp.terminal")]
    elif terminal_from is not None:
        formulas = [prism_property(stormpy, program, terminal_from)]
    # one formula: Storm makes its target states terminal, as PAYNT's builder does
    options = stormpy.BuilderOptions(formulas) if formulas else stormpy.BuilderOptions()
    options.set_build_state_valuations()
    options.set_build_choice_labels()
    options.set_build_observation_valuations()
    options.set_build_all_labels()
    return stormpy.build_model[stormpy.Rational if exact else float](program, options=options)


MAX_PRISM_STATES = 100_000_000  # default of MISDIRECT_MAX_PRISM_STATES


def _check_state_space(program) -> None:
    """Refuse, before Storm builds it, a program whose variables span more states than the
    limit: Storm cannot be stopped once it builds, and a model that size would not fit anyway.

    The size is the product of the variables' ranges, an upper bound of the reachable states;
    ``MISDIRECT_MAX_PRISM_STATES`` raises the limit for a program whose reachable part is far
    smaller.
    """
    import os

    limit = int(os.environ.get("MISDIRECT_MAX_PRISM_STATES", MAX_PRISM_STATES))
    try:
        concrete = program.substitute_constants()
        sizes = [2] * len(concrete.global_boolean_variables)
        integers = list(concrete.global_integer_variables)
        for module in concrete.modules:
            sizes += [2] * len(module.boolean_variables)
            integers += list(module.integer_variables)
        for variable in integers:
            low = variable.lower_bound_expression.evaluate_as_int()
            high = variable.upper_bound_expression.evaluate_as_int()
            sizes.append(max(high - low + 1, 1))
    except Exception:  # an unbounded or unusual variable: leave the size to Storm
        return
    bound = 1
    for size in sizes:
        bound *= size
    if bound > limit:
        raise ProblemError(
            f"the program's variables span up to {bound:,} states, more than the limit of "
            f"{limit:,} (set MISDIRECT_MAX_PRISM_STATES to raise it if far fewer are reachable)",
            field="pomdp.prism",
        )


# -- translating ---------------------------------------------------------------------------------


def _translate(
    stormpy, model, field: str, path: Path, program: PrismProgram | None = None
) -> StormPomdp:
    """Storm's model in misdirect's arrays, with its names, labels and state conditions."""
    n_states = model.nr_states
    arrays = model_arrays(stormpy, model)
    _check_one_initial_state(arrays, path, field)
    values, names = state_names(model, arrays.state_variables)

    choice_counts = np.diff(arrays.groups)
    source_of_choice = np.repeat(np.arange(n_states), choice_counts)
    entries = np.diff(arrays.rows)
    choice_of_entry = np.repeat(np.arange(arrays.action.size), entries)
    act = arrays.action[choice_of_entry]
    src = source_of_choice[choice_of_entry]
    dst, prob = arrays.target, arrays.probability
    _check_distributions(arrays, source_of_choice, choice_of_entry, names, path, field)
    _check_one_choice_per_action(arrays, source_of_choice, names, field)
    n_actions = len(arrays.actions)
    enabled = np.zeros((n_states, n_actions), dtype=bool)
    enabled[source_of_choice, arrays.action] = True
    # a state whose every enabled choice stays put is absorbing (as under `stay`, its disabled
    # actions do too): runs end there, and outcomes and simulation report it as such. Storm's
    # terminal states (PAYNT's targets) are built that way.
    leaves = np.bincount(src[dst != src], minlength=n_states) > 0
    absorbing = ~leaves
    storm_ids, observation_of = emitted_observations(arrays.observation_of)
    observations, storm_names = observation_names(
        model, storm_ids, observation_of, arrays.observation_variables, values, program
    )
    # a disabled (state, action) is a self-loop in the matrix; `forbid` is enforced on costs
    loops_s, loops_a = np.nonzero(~enabled)
    pomdp = Pomdp.from_triplets(
        states=names,
        actions=arrays.actions,
        observations=observations,
        initial_state=int(arrays.initial[0]),
        observation_of=observation_of,
        action=np.concatenate([act, loops_a]),
        source=np.concatenate([src, loops_s]),
        target=np.concatenate([dst, loops_s]),
        probability=np.concatenate([prob, np.ones(loops_s.size)]),
        absorbing=absorbing,
    )
    labels = _labels(model)
    if program is not None:
        condition = prism_condition(stormpy, program.program, values, labels)
    else:
        condition = label_condition(labels)
    return StormPomdp(
        pomdp=pomdp,
        labels=labels,
        enabled=enabled,
        condition=condition,
        storm_observation_names=storm_names,
        state_variables=arrays.state_variables if values else (),
    )


def _labels(model) -> dict[str, np.ndarray]:
    """Storm's state labels as masks."""
    labels = {}
    for label in model.labeling.get_labels():
        mask = np.zeros(model.nr_states, dtype=bool)
        mask[np.fromiter(model.labeling.get_states(label), dtype=np.int64)] = True
        labels[label] = mask
    return labels


def _check_one_initial_state(arrays: StormArrays, path: Path, field: str) -> None:
    if arrays.initial.size != 1:
        raise ProblemError(
            f"{path.name} has {arrays.initial.size} initial states"
            + (
                f" (states {', '.join(map(str, arrays.initial[:5].tolist()))}"
                + (", …" if arrays.initial.size > 5 else "")
                + ")"
                if arrays.initial.size
                else ""
            )
            + "; misdirect needs exactly one",
            field=field,
        )


def _check_distributions(
    arrays: StormArrays,
    source_of_choice: np.ndarray,
    choice_of_entry: np.ndarray,
    names: tuple[str, ...],
    path: Path,
    field: str,
) -> None:
    """As for v1 files: probabilities in [0, 1], each choice's summing to 1 within 1e-9."""
    prob = arrays.probability

    def where(choice: int) -> str:
        s = int(source_of_choice[choice])
        return f"state {names[s]!r}, action {arrays.actions[arrays.action[choice]]!r}"

    bad = np.flatnonzero(~((prob >= 0) & (prob <= 1)))
    if bad.size:
        choice = int(choice_of_entry[bad[0]])
        raise ProblemError(
            f"{path.name}: {where(choice)}: probability {prob[bad[0]]:.12g} is not in [0, 1]",
            field=field,
        )
    sums = np.bincount(choice_of_entry, weights=prob, minlength=arrays.action.size)
    bad = np.flatnonzero(np.abs(sums - 1.0) > SUM_TOLERANCE)
    if bad.size:
        choice = int(bad[0])
        raise ProblemError(
            f"{path.name}: {where(choice)}: probabilities sum to {sums[choice]:.12g}, not 1",
            field=field,
        )


def _check_one_choice_per_action(
    arrays: StormArrays, source_of_choice: np.ndarray, names: tuple[str, ...], field: str
) -> None:
    """Storm may give a state two choices with one label; misdirect's matrix has one row per
    (state, action)."""
    n_actions = len(arrays.actions)
    keys = source_of_choice * n_actions + arrays.action
    unique, counts = np.unique(keys, return_counts=True)
    if (counts > 1).any():
        s, a = divmod(int(unique[counts > 1][0]), n_actions)
        raise ProblemError(
            f"state {names[s]!r} has two choices labelled {arrays.actions[a]!r}; misdirect "
            "needs one distribution per (state, action)",
            field=field,
        )


def _make_terminal_drn(stormpy, world: StormPomdp, terminal, terminal_from) -> StormPomdp:
    """DRN models: states satisfying ``terminal`` become absorbing (Storm's DRN reader has no
    terminal states; PAYNT reads DRN files as written)."""
    assert world.condition is not None  # the loader gives every model one
    if terminal_from is not None:
        formula = parse_property(stormpy, None, terminal_from, "pomdp.terminal_from")
        path = formula.subformula if hasattr(formula, "subformula") else None
        if path is None or not path.is_eventually_formula:
            raise ProblemError(
                "for DRN models, give a property P=? [F target] (or use terminal:)",
                field="pomdp.terminal_from",
            )
        mask = world.condition(str(path.subformula), "pomdp.terminal_from")
    else:
        mask = world.condition(terminal, "pomdp.terminal")
    pomdp = world.pomdp
    coo = pomdp.transitions.tocoo()
    action, source = np.divmod(coo.row, pomdp.n_states)
    absorbing = pomdp.absorbing | mask
    pomdp = Pomdp.from_triplets(
        states=pomdp.states,
        actions=pomdp.actions,
        observations=pomdp.observations,
        initial_state=pomdp.initial_state,
        observation_of=pomdp.observation_of,
        action=action,
        source=source,
        target=coo.col,
        probability=coo.data,
        absorbing=absorbing,
    )
    return dataclasses.replace(world, pomdp=pomdp)
