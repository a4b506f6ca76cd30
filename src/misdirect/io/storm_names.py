"""How misdirect names what Storm builds: states, observations and actions.

Problem files, controllers and reports refer to a Storm model by name, so names must be
readable, unique and the same however the model is built. States are named by their variable
valuation (``s=2,o=3``; a boolean as ``flag`` or ``!flag``) where Storm has one, else
``s<k>``; observations by the values of the observables in the states that emit them
(``o=3``, ``x=2,flag``) or ``obs<k>``; actions by their choice label, :data:`NO_LABEL` for an
unlabelled choice (as Storm's own DRN export writes it). Valuations are read one stormpy call
per variable and named with numpy, never by a Python loop per state.
"""

from __future__ import annotations

import re

import numpy as np

from misdirect.errors import ProblemError
from misdirect.io.storm_expressions import PrismProgram, evaluate, prism_expression

NO_LABEL = "__NOLABEL__"


def valuation_name(valuation: object) -> str:
    """Storm's valuation text as a name: ``[s=2\\t& o=3]`` -> ``s=2,o=3``.

    The one place this normalisation lives: the observation labels of PAYNT controllers
    (which PAYNT writes in Storm's form) go through it. Storm prints a true boolean as an
    empty item (``[\\t& x=3]``); empty items are dropped.
    """
    items = re.split(r"\s*&\s*", str(valuation).strip().strip("[]").strip())
    return ",".join(item for item in items if item)


def read_variables(valuations, order: tuple[str, ...] = ()) -> dict[str, np.ndarray]:
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


def valuation_names(
    values: dict[str, np.ndarray], rows: np.ndarray | None = None
) -> list[str] | None:
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


def distinct_rows(values: dict[str, np.ndarray], n: int) -> bool:
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


def state_names(model, order: tuple[str, ...]) -> tuple[dict[str, np.ndarray], tuple[str, ...]]:
    """The state valuations (variable -> values; empty without them) and the state names:
    the valuations where they tell every state apart, else ``s<k>``."""
    n_states = model.nr_states
    values = read_variables(model.state_valuations, order) if model.has_state_valuations() else {}
    if distinct_rows(values, n_states):
        named = valuation_names(values)
        assert named is not None  # distinct rows: some variable to name them by
        names = tuple(named)
    else:
        names = tuple(np.char.add("s", np.arange(n_states).astype(str)).tolist())
    return values, names


def observation_names(
    model,
    storm_ids: np.ndarray,
    observation_of: np.ndarray,
    order: tuple[str, ...],
    values: dict[str, np.ndarray],
    program: PrismProgram | None,
) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """Each observation named by the observables' values in a state that emits it.

    ``storm_ids[o]`` is Storm's number of our observation ``o`` (``observation_of`` is in our
    numbering, see :func:`emitted_observations`); without valuations, ``o`` is named
    ``obs<storm id>``, as a DRN file numbers it.

    Storm's own observation valuations (stormpy 2.0) print a true boolean as nothing and get
    named observables (``observable "u" = x + y;``) wrong, so only the list of observables is
    taken from them: variables are read from the states, and named observables evaluated on
    them from their declaration.
    """
    n_obs = storm_ids.size
    fallback = tuple(f"obs{o}" for o in storm_ids.tolist())
    if not model.has_observation_valuations():
        return fallback, ()
    valuations = model.observation_valuations
    storm_names = tuple(valuation_name(valuations.to_string(o)) for o in storm_ids.tolist())
    _, first = np.unique(observation_of, return_index=True)
    observed = read_variables(valuations, order)
    columns: dict[str, np.ndarray] = {}
    for name, column in observed.items():
        if name in values:
            columns[name] = values[name][first]
            continue
        computed = _observable_values(program, name, values, first, column.dtype == bool)
        if computed is not None:
            columns[name] = computed
        elif column.dtype == bool:  # Storm's value, when the declaration cannot be read
            columns[name] = column[storm_ids]
    if not distinct_rows(columns, n_obs):
        return fallback, storm_names
    named = valuation_names(columns)
    assert named is not None  # distinct rows: some column to name them by
    return tuple(named), storm_names


def emitted_observations(storm_observation_of: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Storm's ids of the observations some state emits, and each state's observation
    numbered among those.

    A DRN file may number its observations with gaps (1, 4, 5, ...: no 0), and Storm then
    counts every id up to the largest. An id no state emits is no observation of the model:
    no controller has a rule for it and no alteration may target it.
    """
    storm_ids, observation_of = np.unique(storm_observation_of, return_inverse=True)
    return storm_ids, observation_of.reshape(-1).astype(np.int64)


def _observable_values(
    program: PrismProgram | None,
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
        expression = prism_expression(
            program.stormpy, program.program, found[1], integer=not boolean
        )
        result = evaluate(expression, {k: v[rows] for k, v in values.items()})
    except (ProblemError, ValueError):
        return None
    result = np.broadcast_to(np.asarray(result), rows.shape)
    return result.astype(bool) if boolean else result.astype(np.int64)
