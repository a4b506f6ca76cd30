"""The paper's MILP (Section VI), kept as a baseline: its size and its flaw are both results.

Columns, as in the paper (with its successor filter):
    x[o, o']                binary, o is altered to o' (forbidden pairs get upper bound 0)
    z[s, n, o]              Pr(reach decoy) in (s, n) when O(s) is received as o, times x[O(s), o]
    l[s, o, s', n', o']     x[O(s), o] · z[s', n', o'], for s' a successor of s under some action
Rows:
    budget; x[O(s0), O(s0)] = 1; Σ_o' x[o, o'] = 1 per o (the paper omits it; SPEC §1 needs it);
    z[s, n, o] = x[O(s), o] for decoys; the Bellman *equalities*
    z[s, n, o] = Σ_{s', o'} P(s, γ(n, o), s') l[s, o, s', δ(n, o), o'];
    and four rows per l: l ≥ 0, l ≤ z, l ≤ x, l ≥ z - (1 - x).

Counts: |Ω|² + |S||N||Ω| + E|Ω|²|N| variables and 2 + |Ω| + |S||N||Ω| + 4E|Ω|²|N| rows, with E
the number of (s, s') successor pairs. On the scaled grid E = 4n² - 9, so n = 45 gives
1,602,136 variables and 6,262,498 rows (SPEC §5: "just over 1.6 M and 6.2 M").

Unsound as written (SPEC §2): the equalities z = Pz also hold for any constant on a set of
states the chain never leaves (the absorbing goal: z_goal = z_goal), and the maximiser sets it
to 1. ``pin_unreachable=True`` fixes z to 0 where no alteration reaches the decoy, which mends
that case but not states that cycle under some alterations and escape under others.
"""

from __future__ import annotations

import time
from typing import TypeVar, cast

import numpy as np
import numpy.typing as npt

from misdirect.core.alterations import alteration_space
from misdirect.core.attack import prepare
from misdirect.core.choice_product import ChoiceProduct, build_choice_product
from misdirect.core.memory import check_memory
from misdirect.core.model import AlterationArray, Problem
from misdirect.errors import SolverError
from misdirect.solvers.milp.model import BUILD_BYTES_PER_NONZERO, MilpModel, ModelBuilder
from misdirect.solvers.milp.scaling import value_scales

Index = TypeVar("Index", int, npt.NDArray[np.int64])  # one column index, or an array of them


def build_paper(
    problem: Problem,
    budget: float | None = None,
    *,
    pin_unreachable: bool = False,
    state_values: np.ndarray | None = None,
) -> MilpModel:
    """The paper's MILP for ``problem`` (budget row set to ``budget``). Pinned, its value
    columns are scaled by ``state_values`` (the per-state relaxation's values of the states
    of ``prepare(problem, budget).chain``; :mod:`misdirect.solvers.milp.scaling`); the plain
    formulation stays as the paper wrote it, its flaw included (a bound would mend it)."""
    if not problem.objective.is_probability:
        raise SolverError(
            "the paper's formulation maximises a probability; weighted decoy sets need "
            'formulation="compact" (the default)'
        )
    started = time.perf_counter()
    check_paper_fits(problem)
    budget = problem.budget if budget is None else float(budget)
    pomdp, controller = problem.pomdp, problem.controller
    n_s, n_n, n_o = pomdp.n_states, controller.n_nodes, pomdp.n_observations
    graph = pomdp.successor_graph.tocoo()
    edge_from, edge_to = graph.row.astype(np.int64), graph.col.astype(np.int64)
    order = np.lexsort((edge_to, edge_from))
    edge_from, edge_to = edge_from[order], edge_to[order]
    n_edges = edge_from.size
    costs = problem.cost.matrix()
    never: np.ndarray | None = None
    scale = np.ones(n_s * n_n)  # per (s, n), index s |N| + n: z[s, n, ·] is divided by it
    if pin_unreachable:
        chain = build_choice_product(
            problem, alteration_space(problem.with_budget(budget)), reachable_only=False
        )
        never = ~chain.can_reach_target()  # states of all (s, n), index s * |N| + n
        if state_values is not None:
            scale = _scales(problem, budget, chain, ~never & ~chain.target, state_values)

    model = ModelBuilder()
    x0 = model.columns("x", n_o * n_o, 0.0, 1.0, integer=True)
    z0 = model.columns("z", n_s * n_n * n_o, 0.0, 1.0)
    l0 = model.columns("l", n_edges * n_o * n_n * n_o, 0.0, 1.0)

    def x(o: Index, o2: Index) -> Index:
        return x0 + o * n_o + o2

    def z(s: Index, n: Index, o: Index) -> Index:
        return z0 + (s * n_n + n) * n_o + o

    allowed = np.isfinite(costs).ravel()
    budget_row = model.rows(
        "budget",
        1,
        (np.zeros(int(allowed.sum())), x0 + np.flatnonzero(allowed), costs.ravel()[allowed]),
        -np.inf,
        budget,
    )
    o_init = pomdp.initial_observation
    model.rows("initial", 1, ([0], [x(o_init, o_init)], [1.0]), 1.0, 1.0)
    model.rows(
        "one_target",
        n_o,
        (np.repeat(np.arange(n_o), n_o), x0 + np.arange(n_o * n_o), np.ones(n_o * n_o)),
        1.0,
        1.0,
    )

    # z rows: one per (s, n, o), decoy or Bellman
    s, n, o = (
        a.ravel()
        for a in np.meshgrid(np.arange(n_s), np.arange(n_n), np.arange(n_o), indexing="ij")
    )
    row = np.arange(s.size)
    decoy = problem.decoy[s]
    # Bellman: successors s' of s under γ(n, o), summed over o' (for a randomized controller,
    # over the entries (a, n', p) of its move too, weighted by p)
    bellman = np.flatnonzero(~decoy)
    owner, action, next_node, weight = controller.entries(n[bellman], o[bellman])
    probs = pomdp.transitions[action * n_s + s[bellman][owner]].tocoo()
    b_row = bellman[owner[probs.row]]
    b_s, b_o, b_next = s[b_row], o[b_row], next_node[probs.row]
    probs.data *= weight[probs.row]
    # z[s, n, o] = u z'[s, n, o], and l = x z'' u'' with u'' the scale of the successor's z:
    # the row divided by u(s, n); the linearisation rows then read as written (big-Ms u)
    row_scale = scale[b_s * n_n + n[b_row]]
    probs.data *= scale[probs.col * n_n + b_next] / np.where(row_scale > 0, row_scale, 1.0)
    edge = _edge_index(edge_from, edge_to, b_s, probs.col.astype(np.int64))
    l_base = ((edge * n_o + b_o) * n_n + b_next) * n_o
    repeat = np.repeat(np.arange(b_row.size), n_o)
    o_prime = np.tile(np.arange(n_o), b_row.size)
    d_rows = np.flatnonzero(decoy)
    model.rows(
        "z",
        s.size,
        (
            np.concatenate([row, b_row[repeat], d_rows]),
            np.concatenate(
                [
                    z(s, n, o),
                    l0 + l_base[repeat] + o_prime,
                    x(pomdp.observation_of[s[d_rows]], o[d_rows]),
                ]
            ),
            np.concatenate([np.ones(s.size), -probs.data[repeat], -np.ones(d_rows.size)]),
        ),
        0.0,
        0.0,
    )

    # four linearisation rows per l[e, o, n', o'] = x[O(s_e), o] * z[s'_e, n', o']
    n_l = n_edges * n_o * n_n * n_o
    e, lo, ln, lo2 = (
        a.ravel()
        for a in np.meshgrid(
            np.arange(n_edges), np.arange(n_o), np.arange(n_n), np.arange(n_o), indexing="ij"
        )
    )
    l_cols = l0 + np.arange(n_l)
    x_cols = x(pomdp.observation_of[edge_from[e]], lo)
    z_cols = z(edge_to[e], ln, lo2)
    del e, ln, lo2
    i = np.arange(n_l)
    ones = np.ones(n_l)
    model.rows("l_nonnegative", n_l, (i, l_cols, ones), 0.0, np.inf)
    model.rows(
        "l_below_z",
        n_l,
        (np.repeat(i, 2), _pair(l_cols, z_cols), np.tile([1.0, -1.0], n_l)),
        -np.inf,
        0.0,
    )
    model.rows(
        "l_below_x",
        n_l,
        (np.repeat(i, 2), _pair(l_cols, x_cols), np.tile([1.0, -1.0], n_l)),
        -np.inf,
        0.0,
    )
    model.rows(
        "l_above",
        n_l,
        (
            np.repeat(i, 3),
            np.stack([l_cols, z_cols, x_cols], axis=1).ravel(),
            np.tile([1.0, -1.0, -1.0], n_l),
        ),
        -1.0,
        np.inf,
    )

    objective = np.zeros(model.n_columns)
    objective[z(pomdp.initial_state, controller.initial_node, o_init)] = scale[
        pomdp.initial_state * n_n + controller.initial_node
    ]
    built = model.build(
        formulation="paper-pinned" if pin_unreachable else "paper",
        objective=objective,
        offset=0.0,
        budget_row=budget_row,
        decode=lambda values: _decode(problem, values[x0 : x0 + n_o * n_o]),
        start_for=lambda alpha: (x0 + np.arange(n_o) * n_o + alpha, np.ones(n_o)),
        alteration_columns=(
            x0 + np.arange(n_o * n_o),
            np.repeat(np.arange(n_o), n_o),
            np.tile(np.arange(n_o), n_o),
        ),
        sound=False,
        notes={"successor_pairs": n_edges},
    )
    built.col_upper[x0 : x0 + n_o * n_o][~allowed] = 0.0
    if never is not None:
        pinned = z0 + (np.flatnonzero(never)[:, None] * n_o + np.arange(n_o)).ravel()
        built.col_upper[pinned] = 0.0
        built.notes["states_pinned_to_zero"] = int(never.sum())
        built.notes["states_scaled"] = int(((scale > 0.0) & (scale < 1.0)).sum())
    built.build_time_s = time.perf_counter() - started
    return built


def _scales(
    problem: Problem,
    budget: float,
    chain: ChoiceProduct,
    live: np.ndarray,
    state_values: np.ndarray,
) -> np.ndarray:
    """The scale of every (s, n) of ``chain`` (all of them), proven on it, from the values of
    the reachable chain's states (1 on the others: a bound of any value); 0 where the decoy is
    out of reach (pinned to 0: a successor there would enter a row scaled up by 1 / u with its
    probability, a coefficient of 4e9 for a branch of 1e-10), unless nothing is scaled."""
    reachable = prepare(problem, budget).chain
    if state_values.shape != (reachable.n_states,):
        return np.ones(chain.n_states)
    start = np.ones(chain.n_states)
    start[reachable.world_state * problem.controller.n_nodes + reachable.node] = state_values
    scale = value_scales(chain, live, start, 1.0)
    if np.all(scale == 1.0):
        return scale
    return np.where(live | chain.target, scale, 0.0)


def paper_size(problem: Problem) -> tuple[int, int, int]:
    """``(variables, rows, non-zeros)`` of the paper's MILP, counted before building it (the
    module docstring's counts; a Bellman row has one entry per successor and next reading)."""
    pomdp, controller = problem.pomdp, problem.controller
    n_s, n_n, n_o = pomdp.n_states, controller.n_nodes, pomdp.n_observations
    n_edges = int(pomdp.successor_graph.nnz)
    n_l = n_edges * n_o * n_n * n_o
    successors = pomdp.transitions.nnz / max(pomdp.transitions.shape[0], 1)
    if not controller.is_deterministic:
        successors *= float(controller.move_size[controller.move].mean())
    z_entries = n_s * n_n * n_o * (1 + successors * n_o)
    variables = n_o * n_o + n_s * n_n * n_o + n_l
    rows = 2 + n_o + n_s * n_n * n_o + 4 * n_l
    return variables, rows, int(8 * n_l + z_entries + 3 * n_o * n_o)


def check_paper_fits(problem: Problem) -> None:
    """Refuse, before allocating anything, a paper MILP whose build cannot fit in memory: it
    grows as |Ω|²·|N| per successor pair (a 40x40 sensor grid with 64 sensors: 670 million
    non-zeros, some 50 GiB)."""
    variables, rows, nonzeros = paper_size(problem)
    check_memory(
        nonzeros * BUILD_BYTES_PER_NONZERO,
        f"the paper's MILP ({variables:,} variables, {rows:,} rows, {nonzeros:,} non-zeros)",
        field="milp",
    )


def _pair(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.stack([a, b], axis=1).ravel()


def _edge_index(
    edge_from: np.ndarray, edge_to: np.ndarray, source: np.ndarray, target: np.ndarray
) -> np.ndarray:
    """Position of each (source, target) among the lexicographically sorted successor pairs."""
    width = int(max(edge_to.max(initial=0), target.max(initial=0))) + 1
    keys = edge_from * width + edge_to
    return cast(np.ndarray, np.searchsorted(keys, source * width + target))


def _decode(problem: Problem, x_values: np.ndarray) -> AlterationArray:
    n_o = problem.pomdp.n_observations
    return cast(AlterationArray, np.argmax(x_values.reshape(n_o, n_o), axis=1).astype(np.int64))
