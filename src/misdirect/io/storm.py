"""POMDPs from Storm: PRISM programs and DRN files, read through stormpy (``misdirect[storm]``).

Storm lets each state enable only some actions, and an altered observation can make the
controller pick one that is not enabled. The problem file decides what then happens:
``disabled_action: stay`` (the robot stays where it is; default) or ``forbid`` (alterations
that can make the controller pick a disabled action are not allowed at all).

Loading is bulk: stormpy has no array accessor for the transition matrix, so the model is
written once as a UMB archive (Storm's binary format: CSR arrays, one file each) and read
back with numpy; variable values come from one call per variable. Nothing on this path
loops in Python per state, choice or transition.

Names: states are named by their variable valuation (``s=2,o=3``; a boolean as ``flag`` or
``!flag``) where Storm has one, else ``s<k>``; observations by the values of the observables
in the states that emit them (``o=3``, ``x=2,flag``) or ``obs<k>``; actions by their choice
label, ``__NOLABEL__`` for an unlabelled choice (as Storm's own DRN export writes it).
"""

from __future__ import annotations

import dataclasses
import itertools
import json
import re
import tarfile
import tempfile
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from misdirect.core.model import Pomdp
from misdirect.errors import ProblemError

NO_LABEL = "__NOLABEL__"
SUM_TOLERANCE = 1e-9


@dataclass(frozen=True)
class StormPomdp:
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


@dataclass(frozen=True)
class PayntView:
    """The model as PAYNT 0.5 builds it, matched to ours.

    PAYNT's ``.fsc.json`` has one column per observation of *its* model, in its order; its
    ``observation_labels`` are only Storm's text of them (stormpy 2.0 prints most of them
    wrongly, and several observations alike), and its action labels include names it made up
    for unlabelled PRISM commands (``maze_cmd_8``). So the columns are matched by position
    against a rebuild of PAYNT's model, not by label.
    """

    labels: tuple[str, ...]  # what PAYNT writes as observation_labels[k]
    # (columns,) our observation for PAYNT's observation k; -1: no state of ours, -2: several
    observation: np.ndarray
    actions: dict[str, str]  # PAYNT's action label -> our action name
    available: tuple[frozenset[str], ...]  # PAYNT's action labels enabled at its observation k


def _stormpy(field: str):
    try:
        import stormpy
        import stormpy.pomdp  # registers the POMDP model classes
    except ImportError:
        raise ProblemError(
            "reading PRISM or DRN models needs stormpy: pip install 'misdirect[storm]'",
            field=field,
        ) from None
    return stormpy


def _storm_message(error: Exception) -> str:
    return " ".join(str(error).split())


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
    stormpy = _stormpy(field)
    # Storm logs parse errors to stderr itself; we report them once, in our own words
    stormpy.developer.set_log_level(stormpy.developer.LogLevel.OFF)
    path = (base / path) if base is not None and not Path(path).is_absolute() else Path(path)
    if not path.exists():
        raise ProblemError(f"file not found: {path}", field=field)
    if terminal is not None and terminal_from is not None:
        raise ProblemError("give terminal or terminal_from, not both", field="pomdp.terminal")
    program = None
    try:
        if kind == "prism":
            program = stormpy.parse_prism_program(str(path))
            if constants:
                program = _instantiate(stormpy, program, constants)
            if program.has_undefined_constants:
                missing = ", ".join(c.name for c in program.constants if not c.defined)
                raise ProblemError(
                    f'constants without a value: {missing} (give them as constants: "N=5")',
                    field="pomdp.constants",
                )
            _check_state_space(program)
            formulas = []
            if terminal is not None:
                formulas = [_prism_target(stormpy, program, terminal, "pomdp.terminal")]
            elif terminal_from is not None:
                formulas = [_prism_property(stormpy, program, terminal_from)]
            # one formula: Storm makes its target states terminal, as PAYNT's builder does
            options = stormpy.BuilderOptions(formulas) if formulas else stormpy.BuilderOptions()
            options.set_build_state_valuations()
            options.set_build_choice_labels()
            options.set_build_observation_valuations()
            options.set_build_all_labels()
            model = stormpy.build_model(program, options=options)
        else:
            options = stormpy.developer.DirectEncodingParserOptions()
            options.build_choice_labeling = True
            model = stormpy.build_model_from_drn(str(path), options=options)
        if not model.is_partially_observable:
            raise ProblemError(
                f"{path.name} is a {model.model_type.name}, not a POMDP", field=field
            )
    except ProblemError:
        raise
    except Exception as error:  # Storm reports parse errors as RuntimeError/StormError
        message = _storm_message(error)
        if "label init is invalid" in message:
            raise ProblemError(
                f"{path.name} has no initial state (no state is marked init); "
                "misdirect needs exactly one",
                field=field,
            ) from None
        where = re.search(r"at (\d+):(\d+)", message)
        located = f"{field}, line {where[1]}, column {where[2]}" if where else field
        raise ProblemError(f"Storm cannot read {path.name}: {message}", field=located) from None
    prism = None
    if program is not None:
        source = _strip_comments(path.read_text(encoding="utf-8", errors="replace"))
        prism = _Program(stormpy, program, source)
    try:
        world = _translate(stormpy, model, field, path, prism)
    except RuntimeError as error:  # a DRN file without `init` fails only when it is read
        if "label init is invalid" not in str(error):
            raise
        raise ProblemError(
            f"{path.name} has no initial state (no state is marked init); "
            "misdirect needs exactly one",
            field=field,
        ) from None
    if kind == "drn" and (terminal is not None or terminal_from is not None):
        world = _make_terminal_drn(stormpy, world, terminal, terminal_from)
    built = world

    def paynt_view() -> PayntView:
        return _paynt_view(
            stormpy,
            path,
            kind,
            built,
            constants=constants,
            terminal=terminal,
            terminal_from=terminal_from,
        )

    return dataclasses.replace(world, paynt_view=paynt_view)


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


def _instantiate(stormpy, program, constants: str):
    """Set ``constants`` ("N=5,p=0.1"); a bad definition is an error in ``pomdp.constants``."""
    try:
        program, _ = stormpy.instantiate_constants(program, constants)
    except Exception as error:  # Storm raises RuntimeError (WrongFormatException) here
        message = _storm_message(error)
        message = re.sub(
            r"^(\w+Exception: )?Illegal constant definition string[^:]*: ", "", message
        )
        message = re.sub(r"^\w+Exception: ", "", message).rstrip(".")
        undefined = [c.name for c in program.constants if not c.defined]
        known = ", ".join(undefined) if undefined else "none: the program defines all of them"
        raise ProblemError(
            f"cannot set {constants!r}: {message} (constants to set: {known})",
            field="pomdp.constants",
        ) from None
    return program


def valuation_name(valuation: object) -> str:
    """Storm's valuation text as a name: ``[s=2\\t& o=3]`` -> ``s=2,o=3``.

    The one place this normalisation lives: the observation labels of PAYNT controllers
    (which PAYNT writes in Storm's form) go through it. Storm prints a true boolean as an
    empty item (``[\\t& x=3]``); empty items are dropped.
    """
    items = re.split(r"\s*&\s*", str(valuation).strip().strip("[]").strip())
    return ",".join(item for item in items if item)


# -- bulk reading ------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Arrays:
    """The sparse model as arrays: CSR with row groups (choices of a state)."""

    groups: np.ndarray  # (|S|+1,) first choice of each state
    rows: np.ndarray  # (|choices|+1,) first entry of each choice
    target: np.ndarray  # (entries,)
    probability: np.ndarray  # (entries,)
    action: np.ndarray  # (|choices|,) action index
    actions: tuple[str, ...]
    observation_of: np.ndarray  # (|S|,)
    initial: np.ndarray  # state indices
    # variables in Storm's order (UMB index), for names; empty when unknown
    state_variables: tuple[str, ...] = ()
    observation_variables: tuple[str, ...] = ()


def _bits(data: bytes, n: int) -> np.ndarray:
    return np.unpackbits(np.frombuffer(data, dtype=np.uint8), bitorder="little")[:n].astype(bool)


def _read_arrays(stormpy, model) -> _Arrays:
    """Write the model as UMB (binary CSR arrays) and read the arrays back with numpy."""
    options = stormpy.io.UmbExportOptions()
    options.compression = stormpy.io.CompressionMode.NO_COMPRESSION
    options.canonicize_pomdp = False  # keep Storm's state and observation numbering
    with tempfile.TemporaryDirectory(prefix="misdirect-") as folder:
        archive = Path(folder) / "model.umb"
        stormpy.io.export_to_umb(model, str(archive), options=options)
        with tarfile.open(archive) as tar:
            files = {m.name: tar.extractfile(m).read() for m in tar.getmembers() if m.isfile()}
    n_states, n_choices = model.nr_states, model.nr_choices

    def array(name: str, dtype: str) -> np.ndarray:
        data = np.frombuffer(files[name], dtype=np.dtype(dtype).newbyteorder("<"))
        if dtype == "f8":
            return data.astype(np.float64, copy=False)
        if dtype == "u8":  # indices < 2**63: the same bytes read as int64, no copy
            return data.view(np.dtype("<i8")).astype(np.int64, copy=False)
        return data.astype(np.int64)

    index = json.loads(files["index.json"])
    kind = index["transition-system"].get("branch-probability-type", {}).get("type", "double")
    if kind != "double":
        raise ProblemError(f"Storm exported {kind} probabilities; misdirect reads doubles")
    if "actions/choices/values.bin" in files:
        strings, offsets = (
            files["actions/choices/strings.bin"],
            array("actions/choices/string-mapping.bin", "u8"),
        )
        names = [
            strings[a:b].decode("utf-8") or NO_LABEL
            for a, b in itertools.pairwise(offsets.tolist())
        ]
        used, action = np.unique(array("actions/choices/values.bin", "u4"), return_inverse=True)
        actions = tuple(names[i] for i in used)
    else:
        action, actions = np.zeros(n_choices, dtype=np.int64), (NO_LABEL,)
    if len(set(actions)) != len(actions):  # two strings mapping to the same name
        unique, action = np.unique(np.array(actions)[action], return_inverse=True)
        actions = tuple(unique.tolist())

    def order(entity: str) -> tuple[str, ...]:
        classes = index.get("valuations", {}).get(entity, {}).get("classes", [])
        if len(classes) != 1:
            return ()
        return tuple(v["name"] for v in classes[0].get("variables", []) if "name" in v)

    return _Arrays(
        state_variables=order("states"),
        observation_variables=order("observations"),
        groups=array("state-to-choices.bin", "u8"),
        rows=array("choice-to-branches.bin", "u8"),
        target=array("branch-to-target.bin", "u8"),
        probability=array("branch-to-probability.bin", "f8"),
        action=action.astype(np.int64),
        actions=actions,
        observation_of=(
            array("observations/states/values.bin", "u8")
            if "observations/states/values.bin" in files
            else np.array(model.observations, dtype=np.int64)
        ),
        initial=np.flatnonzero(_bits(files["state-is-initial.bin"], n_states)),
    )


def _variables(valuations, order: tuple[str, ...] = ()) -> dict[str, np.ndarray]:
    """Every variable's value in every entity, one stormpy call per variable, in ``order``
    (Storm's: as declared) and then by name."""
    n = valuations.get_number_of_entities()
    rank = {name: i for i, name in enumerate(order)}
    variables = sorted(
        valuations.get_all_variables(), key=lambda v: (rank.get(v.name, len(rank)), v.name)
    )
    values: dict[str, np.ndarray] = {}
    for variable in variables:
        if variable.has_boolean_type():
            mask = np.zeros(n, dtype=bool)
            mask[np.fromiter(valuations.get_boolean_values(variable), dtype=np.int64)] = True
            values[variable.name] = mask
        elif variable.has_integer_type():
            values[variable.name] = np.array(valuations.get_int64_values(variable), dtype=np.int64)
        else:
            values[variable.name] = np.array(valuations.get_double_values(variable))
    return values


def _names(values: dict[str, np.ndarray], rows: np.ndarray | None = None) -> list[str] | None:
    """``x=2,flag,!done`` for each row.

    Each column's distinct values are formatted once and gathered with numpy; the items are
    joined by ``map(",".join, ...)`` in C, so no Python code runs per row.
    """
    parts = []
    for name, column in values.items():
        column = column if rows is None else column[rows]
        distinct, inverse = np.unique(column, return_inverse=True)
        if column.dtype == bool:
            text = [name if v else f"!{name}" for v in distinct.tolist()]
        else:
            text = [f"{name}={v}" for v in distinct.tolist()]
        parts.append(np.array(text, dtype=object)[inverse.reshape(-1)].tolist())
    if not parts:
        return None
    return list(map(",".join, zip(*parts, strict=True)))


def _distinct_rows(values: dict[str, np.ndarray], n: int) -> bool:
    """Whether the valuations of the ``n`` entities are pairwise distinct (so names are)."""
    if not values:
        return False
    key = np.zeros(n, dtype=np.int64)
    span = 1
    for column in values.values():
        _, code = np.unique(column, return_inverse=True)
        width = int(code.max()) + 1 if n else 1
        if span * width >= 2**62:  # keys would overflow: compare rows instead
            return np.unique(np.column_stack(list(values.values())), axis=0).shape[0] == n
        key += code.reshape(-1).astype(np.int64) * span
        span *= width
    return np.unique(key).size == n


def _translate(
    stormpy, model, field: str, path: Path, program: _Program | None = None
) -> StormPomdp:
    n_states = model.nr_states
    try:
        arrays = _read_arrays(stormpy, model)
    except (AttributeError, KeyError):  # stormpy < 2.0 has no UMB export
        arrays = _read_arrays_slowly(model)
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
    values = (
        _variables(model.state_valuations, arrays.state_variables)
        if model.has_state_valuations()
        else {}
    )
    names = tuple(
        _names(values)
        if _distinct_rows(values, n_states)
        else np.char.add("s", np.arange(n_states).astype(str)).tolist()
    )

    choice_counts = np.diff(arrays.groups)
    source_of_choice = np.repeat(np.arange(n_states), choice_counts)
    entries = np.diff(arrays.rows)
    choice_of_entry = np.repeat(np.arange(arrays.action.size), entries)
    act = arrays.action[choice_of_entry]
    src = source_of_choice[choice_of_entry]
    dst, prob = arrays.target, arrays.probability
    _check_distributions(arrays, source_of_choice, choice_of_entry, names, path, field)
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
    enabled = np.zeros((n_states, n_actions), dtype=bool)
    enabled[source_of_choice, arrays.action] = True
    # a state whose every enabled choice stays put is absorbing (as under `stay`, its disabled
    # actions do too): runs end there, and outcomes and simulation report it as such. Storm's
    # terminal states (PAYNT's targets) are built that way.
    leaves = np.bincount(src[dst != src], minlength=n_states) > 0
    absorbing = ~leaves
    observations, storm_names = _observation_names(
        model, arrays.observation_of, arrays.observation_variables, values, program
    )
    # a disabled (state, action) is a self-loop in the matrix; `forbid` is enforced on costs
    loops_s, loops_a = np.nonzero(~enabled)
    pomdp = Pomdp.from_triplets(
        states=names,
        actions=arrays.actions,
        observations=observations,
        initial_state=int(arrays.initial[0]),
        observation_of=arrays.observation_of,
        action=np.concatenate([act, loops_a]),
        source=np.concatenate([src, loops_s]),
        target=np.concatenate([dst, loops_s]),
        probability=np.concatenate([prob, np.ones(loops_s.size)]),
        absorbing=absorbing,
    )
    labels = {}
    for label in model.labeling.get_labels():
        mask = np.zeros(n_states, dtype=bool)
        mask[np.fromiter(model.labeling.get_states(label), dtype=np.int64)] = True
        labels[label] = mask
    if program is not None:
        condition = _prism_condition(stormpy, program.program, values, labels)
    else:
        condition = _label_condition(labels)
    return StormPomdp(
        pomdp=pomdp,
        labels=labels,
        enabled=enabled,
        condition=condition,
        storm_observation_names=storm_names,
        state_variables=arrays.state_variables if values else (),
    )


def _check_distributions(
    arrays: _Arrays,
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


def _read_arrays_slowly(model) -> _Arrays:
    """The same arrays through stormpy's per-entry accessors (stormpy without UMB)."""
    groups = np.array(model.nondeterministic_choice_indices, dtype=np.int64)
    labelling = model.choice_labeling if model.has_choice_labeling() else None
    index: dict[str, int] = {}
    action, rows, target, probability = [], [0], [], []
    for choice in range(model.nr_choices):
        labels = sorted(labelling.get_labels_of_choice(choice)) if labelling else []
        action.append(index.setdefault("+".join(labels) or NO_LABEL, len(index)))
        for entry in model.transition_matrix.get_row(choice):
            target.append(entry.column)
            probability.append(float(entry.value))
        rows.append(len(target))
    return _Arrays(
        groups=groups,
        rows=np.array(rows, dtype=np.int64),
        target=np.array(target, dtype=np.int64),
        probability=np.array(probability),
        action=np.array(action, dtype=np.int64),
        actions=tuple(index),
        observation_of=np.array(model.observations, dtype=np.int64),
        initial=np.array(sorted(model.initial_states), dtype=np.int64),
    )


# -- observation names ---------------------------------------------------------------------


def _observation_names(
    model,
    observation_of: np.ndarray,
    order: tuple[str, ...],
    values: dict[str, np.ndarray],
    program: _Program | None,
) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """Each observation named by the observables' values in a state that emits it.

    Storm's own observation valuations (stormpy 2.0) print a true boolean as nothing and get
    named observables (``observable "u" = x + y;``) wrong, so only the list of observables is
    taken from them: variables are read from the states, and named observables evaluated on
    them from their declaration.
    """
    n_obs = model.nr_observations
    fallback = tuple(f"obs{o}" for o in range(n_obs))
    if not model.has_observation_valuations():
        return fallback, ()
    valuations = model.observation_valuations
    storm_names = tuple(valuation_name(valuations.to_string(o)) for o in range(n_obs))
    emitted, first = np.unique(observation_of, return_index=True)
    if emitted.size != n_obs:
        return fallback, storm_names
    observed = _variables(valuations, order)
    columns: dict[str, np.ndarray] = {}
    for name, column in observed.items():
        if name in values:
            columns[name] = values[name][first]
            continue
        computed = _observable_values(program, name, values, first, column.dtype == bool)
        if computed is not None:
            columns[name] = computed
        elif column.dtype == bool:  # Storm's value, when the declaration cannot be read
            columns[name] = column
    if not _distinct_rows(columns, n_obs):
        return fallback, storm_names
    return tuple(_names(columns)), storm_names


def _observable_values(
    program: _Program | None,
    name: str,
    values: dict[str, np.ndarray],
    rows: np.ndarray,
    boolean: bool,
) -> np.ndarray | None:
    """Value of the named observable ``name`` (``observable "name" = expr;``) in ``rows``,
    evaluated from the state valuations; None when the declaration cannot be read."""
    if program is None or program.source is None:
        return None
    found = re.search(r'observable\s+"' + re.escape(name) + r'"\s*=\s*([^;]+);', program.source)
    if found is None:
        return None
    try:
        expression = _prism_expression(
            program.stormpy, program.program, found[1], integer=not boolean
        )
        result = _evaluate(expression, {k: v[rows] for k, v in values.items()})
    except (ProblemError, ValueError):
        return None
    result = np.broadcast_to(np.asarray(result), rows.shape)
    return result.astype(bool) if boolean else result.astype(np.int64)


# -- state conditions: PRISM expressions, label expressions ------------------------------------


@dataclass(frozen=True)
class _Program:
    """A PRISM program and what is needed to parse expressions against it."""

    stormpy: Any
    program: Any
    source: str | None


def _strip_comments(text: str) -> str:
    return re.sub(r"//[^\n]*", "", text)


def _substitute_labels(program, text: str, field: str) -> str:
    """``"goal"`` (a label, as PRISM properties write it) becomes its definition, so that the
    whole condition is one expression over variables. A bare label name that is not also a
    variable is accepted too."""
    if ";" in text or "[" in text or "]" in text:
        raise ProblemError("expected a state expression (no ';' or brackets)", field=field)
    flat = program.substitute_formulas()
    labels = {label.name: str(label.expression) for label in flat.labels}
    variables = {v.name for v in program.variables} | {c.name for c in program.constants}

    def quoted(match: re.Match) -> str:
        if match[1] not in labels:
            known = ", ".join(sorted(labels)) or "none"
            raise ProblemError(f"no label {match[1]!r} (labels: {known})", field=field)
        return f"({labels[match[1]]})"

    text = re.sub(r'"([^"]*)"', quoted, text)

    def bare(match: re.Match) -> str:
        word = match[0]
        return f"({labels[word]})" if word in labels and word not in variables else word

    return re.sub(r"(?<![\w.])[A-Za-z_]\w*(?!\s*\()", bare, text)


def _parse_property(stormpy, program, text: str, field: str):
    try:
        if program is None:
            properties = stormpy.parse_properties(text)
        else:
            properties = stormpy.parse_properties(text, program)
    except Exception as error:
        message = re.sub(r"^\w+Exception: ", "", _storm_message(error))
        raise ProblemError(f"Storm cannot parse it: {message}", field=field) from None
    if len(properties) != 1:
        raise ProblemError(f"expected one property, got {len(properties)}", field=field)
    return properties[0].get_raw_formula()


def _prism_target(stormpy, program, text: str, field: str):
    """``P=? [F (text)]`` for the program: Storm builds its target states terminal."""
    expression_text = _substitute_labels(program, text, field)
    return _parse_property(stormpy, program, f"P=? [F ({expression_text})]", field)


def _prism_property(stormpy, program, text: str):
    return _parse_property(stormpy, program, text, "pomdp.terminal_from")


def _prism_expression(stormpy, program, text: str, *, integer: bool = False, field: str = ""):
    """``text`` as a Storm expression over the program's variables (labels substituted)."""
    expression_text = _substitute_labels(program, text, field)
    wrapped = f"(({expression_text}) = 0)" if integer else f"({expression_text})"
    formula = _parse_property(stormpy, program, f"P=? [F {wrapped}]", field).subformula
    state = formula.subformula
    if not hasattr(state, "get_expression"):  # true/false come back as literal formulas
        literal = str(state).strip().lower()
        if literal in ("true", "false"):
            return literal == "true"
        raise ProblemError("expected a state expression", field=field)
    expression = state.get_expression()
    return expression.get_operand(0) if integer else expression


def _evaluate(expression, env: dict[str, np.ndarray]):
    """A Storm expression evaluated on arrays of variable values (numpy, one pass per node)."""
    if isinstance(expression, bool | int | float):
        return expression
    if expression.is_literal():
        if expression.has_boolean_type():
            return expression.evaluate_as_bool()
        if expression.has_integer_type():
            return expression.evaluate_as_int()
        return expression.evaluate_as_double()
    if expression.is_variable():
        name = expression.get_identifier()
        if name not in env:
            raise ValueError(f"no value for {name!r}")
        return env[name]
    if not expression.is_function_application:
        raise ValueError(f"cannot evaluate {expression}")
    args = [_evaluate(expression.get_operand(i), env) for i in range(expression.arity)]
    name = str(expression.operator).rsplit(".", 1)[-1]
    if name == "MINUS" and len(args) == 1:
        return np.negative(args[0])
    operation = _OPERATIONS.get(name)
    if operation is None:
        raise ValueError(f"operator {name} is not supported")
    return operation(*args)


_OPERATIONS: dict[str, Callable[..., Any]] = {
    "AND": np.logical_and,
    "OR": np.logical_or,
    "XOR": np.logical_xor,
    "NOT": np.logical_not,
    "IMPLIES": lambda a, b: np.logical_or(np.logical_not(a), b),
    "IFF": np.equal,
    "PLUS": np.add,
    "MINUS": np.subtract,
    "TIMES": np.multiply,
    "DIVIDE": np.true_divide,
    "MODULO": np.mod,
    "POWER": np.power,
    "MIN": np.minimum,
    "MAX": np.maximum,
    "FLOOR": np.floor,
    "CEIL": np.ceil,
    "EQUAL": np.equal,
    "NOT_EQUAL": np.not_equal,
    "LESS": np.less,
    "LESS_OR_EQUAL": np.less_equal,
    "GREATER": np.greater,
    "GREATER_OR_EQUAL": np.greater_equal,
    "ITE": np.where,
}


def _prism_condition(stormpy, program, values, labels) -> Callable[[str, str], np.ndarray]:
    """PRISM state conditions: expressions over variables, formulas, constants and labels."""
    n = next(iter(labels.values())).size if labels else 0

    def condition(text: str, field: str) -> np.ndarray:
        expression = _prism_expression(stormpy, program, text, field=field)
        try:
            result = np.asarray(_evaluate(expression, values))
        except ValueError as error:
            raise ProblemError(f"cannot evaluate {text!r}: {error}", field=field) from None
        if result.dtype != bool:
            raise ProblemError(f"{text!r} is not a condition (true or false)", field=field)
        return np.broadcast_to(result, (n,)).copy()

    return condition


_TOKEN = re.compile(r'\s*(?:(?P<op>[!&|()])|"(?P<quoted>[^"]*)"|(?P<name>[A-Za-z_][\w\-]*))')


def _label_condition(labels: dict[str, np.ndarray]) -> Callable[[str, str], np.ndarray]:
    """Label expressions (``!``, ``&``, ``|``, parentheses over label names) for DRN models,
    parsed here (recursive descent; nothing is evaluated as code)."""
    n = next(iter(labels.values())).size if labels else 0

    def condition(text: str, field: str) -> np.ndarray:
        tokens: list[str] = []
        position = 0
        text = text.strip()
        while position < len(text):
            match = _TOKEN.match(text, position)
            if match is None or match.end() == position:
                raise ProblemError(
                    f"unexpected {text[position:].strip()[:10]!r} at character {position + 1} "
                    "(a label expression: labels, !, &, |, parentheses)",
                    field=field,
                )
            position = match.end()
            tokens.append(match["op"] or f"@{match['quoted'] or match['name']}")
        tokens.append("")
        at = 0

        def atom() -> np.ndarray:
            nonlocal at
            token = tokens[at]
            at += 1
            if token == "!":
                return ~atom()
            if token == "(":
                value = disjunction()
                if tokens[at] != ")":
                    raise ProblemError("missing ')'", field=field)
                at += 1
                return value
            if token.startswith("@"):
                label = token[1:]
                if label in ("true", "false"):
                    return np.full(n, label == "true")
                if label not in labels:
                    known = ", ".join(sorted(labels)) or "none"
                    raise ProblemError(f"no label {label!r} (labels: {known})", field=field)
                return labels[label]
            raise ProblemError(f"unexpected {token or 'end of text'!r}", field=field)

        def conjunction() -> np.ndarray:
            nonlocal at
            value = atom()
            while tokens[at] == "&":
                at += 1
                value = value & atom()
            return value

        def disjunction() -> np.ndarray:
            nonlocal at
            value = conjunction()
            while tokens[at] == "|":
                at += 1
                value = value | conjunction()
            return value

        value = disjunction()
        if tokens[at] != "":
            raise ProblemError(f"unexpected {tokens[at].lstrip('@')!r}", field=field)
        return value.copy()

    return condition


def _make_terminal_drn(stormpy, world: StormPomdp, terminal, terminal_from) -> StormPomdp:
    """DRN models: states satisfying ``terminal`` become absorbing (Storm's DRN reader has no
    terminal states; PAYNT reads DRN files as written)."""
    if terminal_from is not None:
        formula = _parse_property(stormpy, None, terminal_from, "pomdp.terminal_from")
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


# -- the model as PAYNT builds it ----------------------------------------------------------------

PAYNT_NO_LABEL = "__no_label__"  # PAYNT's label for a choice without one (ours: __NOLABEL__)
_ONE_LINE_OBSERVABLES = re.compile(
    r"(?m)^[ \t]*observables\b[ \t]*(?P<items>[^\n]*?)[ \t]*\bendobservables\b"
    r"[ \t]*(?P<rest>[^\n]*)$"
)


def paynt_prism_text(text: str) -> str:
    """The PRISM program as PAYNT 0.5 can read it.

    PAYNT reads ``observables`` line by line: the keyword must start a line and
    ``endobservables`` must start a later one (``observables x, y endobservables`` on one line
    makes it give up on the file). Such a block is split over three lines; nothing else
    changes, so Storm builds the same model from either text.
    """

    def split(match: re.Match) -> str:
        rest = f"\n{match['rest']}" if match["rest"].strip() else ""
        return f"observables\n{match['items']}\nendobservables{rest}"

    text = _ONE_LINE_OBSERVABLES.sub(split, text)
    return re.sub(r"(?m)^[ \t]+(?=(?:end)?observables\b)", "", text)


def _paynt_rewrite(text: str) -> str:
    """PAYNT's own rewriting of an ``observables`` block (paynt/parser/prism_parser.py,
    ``load_sketch_prism``): each listed variable ``x`` becomes ``observable "x" = x;``. Storm
    then numbers and prints the observations as PAYNT sees them."""
    out: list[str] = []
    inside = False
    for line in text.splitlines(keepends=True):
        if line.startswith("observables"):
            inside = True
            line = line.split("//")[0].strip()
            if len(line) <= len("observables"):
                continue
            line = line[len("observables") :].strip()
        if inside:
            if line.startswith("endobservables"):
                inside = False
                continue
            line = line.split("//")[0].strip()
            out += [f'observable "{o.strip()}" = {o.strip()};\n' for o in line.split(",")]
            continue
        out.append(line)
    return "".join(out)


def _paynt_view(
    stormpy,
    path: Path,
    kind: str,
    world: StormPomdp,
    *,
    constants: str | None,
    terminal: str | None,
    terminal_from: str | None,
) -> PayntView:
    """Build the model the way PAYNT 0.5 does (``Sketch.load_sketch``) and match it to ours.

    PRISM: PAYNT's rewriting of ``observables``, Storm's parser in PRISM compatibility mode,
    ``label_unlabelled_commands`` (an unlabelled command of module ``m`` becomes the action
    ``m_cmd_<k>``, k its position in the module), Storm's builder with PAYNT's options and the
    property's target terminal, then ``make_canonic``. DRN: Storm's DRN reader, then
    ``make_canonic``; unlabelled choices are PAYNT's ``__no_label__``. The terminal states are
    those of the problem file (``terminal``/``terminal_from``): PAYNT's are its property's.
    """
    field = "controller.paynt"
    renamed: set[str] = set()
    try:
        if kind == "prism":
            text = _paynt_rewrite(paynt_prism_text(path.read_text(encoding="utf-8")))
            with tempfile.TemporaryDirectory(prefix="misdirect-") as folder:
                copy = Path(folder) / path.name
                copy.write_text(text, encoding="utf-8")
                program = stormpy.parse_prism_program(str(copy), prism_compatibility=True)
            if constants:
                program = _instantiate(stormpy, program, constants)
            labelled = program.label_unlabelled_commands({})

            def commands(p) -> set[str]:
                return {c.action_name for m in p.modules for c in m.commands}

            renamed = commands(labelled) - commands(program)
            formulas = []
            if terminal is not None:
                formulas = [_prism_target(stormpy, labelled, terminal, "pomdp.terminal")]
            elif terminal_from is not None:
                formulas = [_prism_property(stormpy, labelled, terminal_from)]
            options = stormpy.BuilderOptions(formulas) if formulas else stormpy.BuilderOptions()
            options.set_build_state_valuations(True)
            options.set_build_choice_origins(True)
            options.set_build_all_labels(True)
            options.set_build_choice_labels(True)
            options.set_add_overlapping_guards_label(True)
            options.set_build_observation_valuations(True)
            model = stormpy.build_model(labelled, options=options)
        else:
            options = stormpy.developer.DirectEncodingParserOptions()
            options.build_choice_labeling = True
            model = stormpy.build_model_from_drn(str(path), options=options)
        model = stormpy.pomdp.make_canonic(model)
    except ProblemError:
        raise
    except Exception as error:  # Storm's parser or builder (RuntimeError, SyntaxError)
        raise ProblemError(
            f"cannot build {path.name} the way PAYNT does: {_storm_message(error)}", field=field
        ) from None

    pomdp = world.pomdp
    n_states = model.nr_states
    ours = np.full(n_states, -1, dtype=np.int64)  # our state of each of PAYNT's states
    if world.state_variables and model.has_state_valuations():
        values = _variables(model.state_valuations, world.state_variables)
        names = _names(values) or []
        index = {name: s for s, name in enumerate(pomdp.states)}
        ours = np.array([index.get(name, -1) for name in names], dtype=np.int64)
    elif n_states == pomdp.n_states:  # no valuations (DRN): the same file, the same states
        ours = np.arange(n_states)
    paynt_obs = np.asarray(model.observations, dtype=np.int64)
    n_obs = model.nr_observations
    found = ours >= 0
    pairs = np.unique(
        np.stack([paynt_obs[found], pomdp.observation_of[ours[found]]], axis=1), axis=0
    )
    observation = np.full(n_obs, -1, dtype=np.int64)
    column, counts = np.unique(pairs[:, 0], return_counts=True)
    observation[column[counts > 1]] = -2
    single = np.isin(pairs[:, 0], column[counts == 1])
    observation[pairs[single, 0]] = pairs[single, 1]

    if model.has_observation_valuations():
        valuations = model.observation_valuations
        labels = tuple(valuations.to_string(o) for o in range(n_obs))
    else:
        labels = tuple(str(o) for o in range(n_obs))
    _, first = np.unique(paynt_obs, return_index=True)
    labelling = model.choice_labeling if model.has_choice_labeling() else None
    available: list[frozenset[str]] = []
    for o in range(n_obs):
        names_here: set[str] = set()
        if o < first.size:
            state = int(first[o])
            for offset in range(model.get_nr_available_actions(state)):
                choice = model.get_choice_index(state, offset)
                got = labelling.get_labels_of_choice(choice) if labelling else set()
                names_here.add(next(iter(got)) if len(got) == 1 else PAYNT_NO_LABEL)
        available.append(frozenset(names_here))
    actions: dict[str, str] = {}
    for label in set().union(*available) if available else set():
        if label in pomdp.actions:
            actions[label] = label
        elif (label in renamed or label == PAYNT_NO_LABEL) and NO_LABEL in pomdp.actions:
            actions[label] = NO_LABEL
    return PayntView(
        labels=labels, observation=observation, actions=actions, available=tuple(available)
    )
