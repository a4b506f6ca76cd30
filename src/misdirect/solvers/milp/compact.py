"""The compact exact MILP: one binary per attacker option, one probability per product state.

Columns
    ``alteration``  y[k]   binary, option k of the alteration space is taken
    ``probability`` z[q]   Pr(reach decoy) from product state q, for states that can reach the
                           decoy under some alteration and are not decoys themselves (divided
                           by a power of two u_q bounding it where it is far below 1, so that
                           a backend sees it near 1: :mod:`misdirect.solvers.milp.scaling`)
    (only where the chain can cycle without reaching the decoy under some alteration:)
    ``witness``     w[q]   continuous in [0, 1], positive only if q has a path to an exit
    ``witness_edge`` t[e]  binary, edge e = (q, q') is q's next step on that path
    ``rank``        r[q]   continuous in [0, 1], strictly decreasing along witness edges

Rows
    ``one_target``  Σ_k y[k] = 1 per altered observation (α is a function)
    ``budget``      Σ_k cost[k] y[k] ≤ B
    ``bellman``     per product state and group (choice) g:
                    z[q] - Σ_{q'} P_g(q, q') z[q'] ≤ P_g(q, decoy) + (1 - Σ_{k selects g} y[k]);
                    states with a single group have no y term (the row always holds)
    ``witness_*``   z[q] ≤ w[q]; w[q] ≤ Σ_{q' ∈ succ_g(q)} t[q, q'] + (1 - Σ y) per closed group;
                    t[q, q'] ≤ w[q']; r[q] ≥ r[q'] + ε when t[q, q'] = 1 (same SCC only)

Why it is exact. For the chosen alteration α, ``z ≤ P_α z`` on the states kept, with 0 on the
states that cannot reach the decoy under any alteration. If the chain of α restricted to the
kept states has no closed class, ``I - P_α`` is an invertible M-matrix there and z is bounded
by the least fixed point, the true probability; maximising then attains it. Closed classes of
α are end components of the choice MDP, and the witness rows force z = 0 on them: a state in an
end component may carry probability only if α leaves it a path to a state outside every end
component (Wimmer et al., TCS 2014; Storm's MILPMinimalLabelSetGenerator). Models without end
components (the paper's grid) get no witness columns at all.
"""

from __future__ import annotations

import time

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from misdirect.core.attack import prepare
from misdirect.core.choice_product import ChoiceProduct
from misdirect.core.model import AlterationArray, Problem
from misdirect.core.reachability import reach_probabilities
from misdirect.solvers.milp.model import MilpModel, ModelBuilder
from misdirect.solvers.milp.scaling import value_scales

# Bellman rows are scaled up so that a solver's feasibility tolerance (1e-6 in HiGHS) allows
# only 1e-9 of slack in probability: unscaled, random_problem(19) at budget 2 came back with a
# bound 1e-6 above the exact optimum, too loose to certify it (the limit is 1e-9)
BELLMAN_SCALE = 1e3


def build_compact(
    problem: Problem,
    budget: float | None = None,
    state_values: np.ndarray | None = None,
    *,
    max_alarm: float | None = None,
) -> MilpModel:
    """The compact formulation for ``problem`` (budget row set to ``budget``); ``state_values``,
    the states' values under the per-state relaxation, scale the probability columns
    (:mod:`misdirect.solvers.milp.scaling`; None: unscaled). ``max_alarm`` (δ, with
    ``problem`` a monitored problem whose alarm sink is a stopping state,
    :attr:`~misdirect.solvers.engines.alarm.AlarmConstraint.decoy_problem`): the alarm's
    system too (:func:`_add_alarm_rows`), its value at the start at most δ."""
    started = time.perf_counter()
    budget = problem.budget if budget is None else float(budget)
    instance = prepare(problem, budget)
    chain, live = instance.chain, instance.live
    options = chain.options
    z_of = np.full(chain.n_states, -1, dtype=np.int64)
    z_of[live] = np.arange(int(live.sum()))

    model = ModelBuilder()
    y0 = model.columns("alteration", options.size, 0.0, 1.0, integer=True)
    z0 = model.columns("probability", int(live.sum()), 0.0, 1.0)

    observations, per_option = np.unique(options.observation, return_inverse=True)
    model.rows(
        "one_target",
        observations.size,
        (per_option, y0 + np.arange(options.size), np.ones(options.size)),
        1.0,
        1.0,
    )
    budget_row = model.rows(
        "budget",
        1,
        (np.zeros(options.size), y0 + np.arange(options.size), options.cost),
        -np.inf,
        budget,
    )

    groups = np.flatnonzero(live[chain.group_state])
    owner = chain.group_state[groups]
    switched = chain.groups_per_state[owner] > 1  # rows that need an on/off term
    transitions = chain.transitions[groups].tocoo()
    # z is the value divided by the largest decoy weight (1 for a plain probability) and by
    # the state's scale u (a power of two bounding it; 1 but for values far below 1), so that
    # it lies in [0, 1] and 1 is the big-M of a switched-off row; the row of q is divided by
    # u_q, its successor q' enters with P(q, q') u_q' / u_q (all exact: powers of two)
    top = problem.objective.max_value or 1.0
    scale = value_scales(chain, live, state_values, top)
    to_target = chain.one_step(groups) / top / scale[owner]
    inside = live[transitions.col]
    successor = transitions.data[inside] * (
        scale[transitions.col[inside]] / scale[owner[transitions.row[inside]]]
    )
    selectors = chain.group_options[groups].tocoo()
    on = switched[selectors.row]
    model.rows(
        "bellman",
        groups.size,
        (
            np.concatenate([np.arange(groups.size), transitions.row[inside], selectors.row[on]]),
            np.concatenate(
                [z0 + z_of[owner], z0 + z_of[transitions.col[inside]], y0 + selectors.col[on]]
            ),
            np.concatenate([np.ones(groups.size), -successor, np.ones(int(on.sum()))]),
        ),
        -np.inf,
        to_target + switched,
        scale=BELLMAN_SCALE,
    )

    cycling = instance.cycling
    if cycling.any():
        _add_witness_rows(model, chain, cycling, z0, z_of, y0)

    if max_alarm is not None:
        _add_alarm_rows(model, problem, chain, live, groups, switched, y0, z_of, max_alarm)

    objective = np.zeros(model.n_columns)
    offset = 0.0
    if live[chain.initial]:
        objective[z0 + z_of[chain.initial]] = top * scale[chain.initial]
    elif chain.target[chain.initial]:
        offset = float(chain.target_value[chain.initial])

    def decode(values: np.ndarray) -> AlterationArray:
        return options.decode(problem, values[y0 : y0 + options.size])

    def start_for(alteration: AlterationArray) -> tuple[np.ndarray, np.ndarray]:
        """A start for the solver: the binaries, and the probabilities too when the model has
        no witness columns. A complete start spares the solver its own completion LP, which is
        where HiGHS crashed on the 45x45 grid."""
        binaries = (y0 + np.arange(options.size), options.encode(alteration))
        if cycling.any() or max_alarm is not None:
            return binaries
        chosen = chain.selected_groups(alteration)
        values = reach_probabilities(
            chain.transitions[chosen].tocsr(), chain.target, value=chain.target_value / top
        )
        return (
            np.concatenate([binaries[0], z0 + np.arange(int(live.sum()))]),
            np.concatenate([binaries[1], values[live] / scale[live]]),
        )

    return model.build(
        formulation="compact",
        objective=objective,
        offset=offset,
        budget_row=budget_row,
        decode=decode,
        start_for=start_for,
        alteration_columns=(y0 + np.arange(options.size), options.observation, options.target),
        sound=True,
        build_time_s=time.perf_counter() - started,
        notes={
            "product_states": chain.n_states,
            "product_groups": chain.n_groups,
            "states_fixed_to_zero": int((~live & ~chain.target).sum()),
            "end_component_states": int(cycling.sum()),
            "states_scaled": int((live & (scale < 1.0)).sum()),
        },
    )


def _add_alarm_rows(
    model: ModelBuilder,
    problem: Problem,
    chain: ChoiceProduct,
    live: np.ndarray,
    groups: np.ndarray,
    switched: np.ndarray,
    y0: int,
    z_of: np.ndarray,
    max_alarm: float,
) -> None:
    """Columns a[q] in [0, 1] and, per live group g of q, the row
    ``a[q] - Σ_{q'} P_g(q, q') a[q'] >= P_g(q, alarm) - (1 - Σ_{k selects g} y[k])``: for the
    chosen alteration, ``a >= P_α a + b``, whose every solution lies above the least one,
    Pr(alarm before decoy) (decoys and the sink are stopping states, outside the live ones);
    a group switched off holds for every ``a`` in [0, 1]. So ``a[start] <= δ`` is feasible
    exactly when the alteration's Pr(alarm) is at most δ: no witness rows are needed (a
    closed class only raises ``a`` above the least solution, which the row allows)."""
    assert problem.alarm_state is not None
    a0 = model.columns("alarm_probability", int(live.sum()), 0.0, 1.0)
    owner = chain.group_state[groups]
    transitions = chain.transitions[groups].tocoo()
    sink = (chain.world_state == problem.alarm_state).astype(np.float64)
    to_alarm = np.asarray(chain.transitions[groups] @ sink).ravel()
    inside = live[transitions.col]
    selectors = chain.group_options[groups].tocoo()
    on = switched[selectors.row]
    model.rows(
        "alarm",
        groups.size,
        (
            np.concatenate([np.arange(groups.size), transitions.row[inside], selectors.row[on]]),
            np.concatenate(
                [a0 + z_of[owner], a0 + z_of[transitions.col[inside]], y0 + selectors.col[on]]
            ),
            np.concatenate(
                [np.ones(groups.size), -transitions.data[inside], -np.ones(int(on.sum()))]
            ),
        ),
        to_alarm - switched,
        np.inf,
        scale=BELLMAN_SCALE,
    )
    if live[chain.initial]:
        model.rows(
            "max_alarm",
            1,
            (np.zeros(1), np.array([a0 + z_of[chain.initial]]), np.ones(1)),
            -np.inf,
            max_alarm,
            scale=BELLMAN_SCALE,
        )


def _add_witness_rows(
    model: ModelBuilder,
    chain: ChoiceProduct,
    cycling: np.ndarray,
    z0: int,
    z_of: np.ndarray,
    y0: int,
) -> None:
    """Rows that let z[q] > 0 on end-component states only along an acyclic path out."""
    n_cycling = int(cycling.sum())
    c_of = np.full(chain.n_states, -1, dtype=np.int64)
    c_of[cycling] = np.arange(n_cycling)
    structure = (chain.transitions != 0).astype(np.int32).tocsr()
    leaves = np.asarray(structure @ (~cycling).astype(np.int32)).ravel() > 0
    closed = np.flatnonzero(cycling[chain.group_state] & ~leaves)  # groups that cannot get out

    closed_rows = structure[closed].tocoo()
    source = chain.group_state[closed[closed_rows.row]]
    proper = closed_rows.col != source  # a self-loop is never a step towards the exit
    edge_keys = np.unique(source[proper] * chain.n_states + closed_rows.col[proper])
    edge_from, edge_to = edge_keys // chain.n_states, edge_keys % chain.n_states
    n_edges = edge_keys.size

    w0 = model.columns("witness", n_cycling, 0.0, 1.0)
    t0 = model.columns("witness_edge", n_edges, 0.0, 1.0, integer=True)
    r0 = model.columns("rank", n_cycling, 0.0, 1.0)
    states = np.flatnonzero(cycling)

    model.rows(
        "witness_bound",
        n_cycling,
        (
            np.repeat(np.arange(n_cycling), 2),
            np.stack([z0 + z_of[states], w0 + c_of[states]], axis=1).ravel(),
            np.tile([1.0, -1.0], n_cycling),
        ),
        -np.inf,
        0.0,
    )

    switched = chain.groups_per_state[chain.group_state[closed]] > 1
    edge_of_entry = np.searchsorted(edge_keys, source * chain.n_states + closed_rows.col)
    selectors = chain.group_options[closed].tocoo()
    on = switched[selectors.row]
    model.rows(
        "witness_step",
        closed.size,
        (
            np.concatenate([np.arange(closed.size), closed_rows.row[proper], selectors.row[on]]),
            np.concatenate(
                [
                    w0 + c_of[chain.group_state[closed]],
                    t0 + edge_of_entry[proper],
                    y0 + selectors.col[on],
                ]
            ),
            np.concatenate(
                [np.ones(closed.size), -np.ones(int(proper.sum())), np.ones(int(on.sum()))]
            ),
        ),
        -np.inf,
        switched.astype(np.float64),
    )
    model.rows(
        "witness_chain",
        n_edges,
        (
            np.repeat(np.arange(n_edges), 2),
            np.stack([t0 + np.arange(n_edges), w0 + c_of[edge_to]], axis=1).ravel(),
            np.tile([1.0, -1.0], n_edges),
        ),
        -np.inf,
        0.0,
    )

    # ranks only matter inside a strongly connected part of the witness graph
    graph = sp.csr_matrix(
        (np.ones(n_edges), (c_of[edge_from], c_of[edge_to])), shape=(n_cycling, n_cycling)
    )
    _, component = connected_components(graph, directed=True, connection="strong")
    same = np.flatnonzero(component[c_of[edge_from]] == component[c_of[edge_to]])
    epsilon = 1.0 / max(int(np.bincount(component).max()), 1)
    model.rows(
        "witness_rank",
        same.size,
        (
            np.repeat(np.arange(same.size), 3),
            np.stack(
                [r0 + c_of[edge_from[same]], r0 + c_of[edge_to[same]], t0 + same], axis=1
            ).ravel(),
            np.tile([1.0, -1.0, -(1.0 + epsilon)], same.size),
        ),
        -1.0,
        np.inf,
    )
