"""A proven bound on maximal reachability where end components defeat the direct check.

:meth:`~misdirect.solvers.engines.policy_iteration.MaxReachability.proven_bound` guesses a
pre-fixed point ``v + ε`` of the Bellman operator around policy iteration's values ``v``. In
an end component (states a scheduler can keep a run in forever) the operator has many fixed
points, and a guess whose offset does not fall along *every* choice inside it fails the check
although ``v`` is right: on a turn-back grid, a relaxation converged to 0.464 and was
"proven" at 1.0 only.

The standard cure (interval iteration: Haddad and Monmege, TCS 2018; Baier et al., CAV 2017)
is to collapse the maximal end components first. Among the states that can reach the target
(by the allowed choices), each maximal end component becomes one state, whose choices are its
members' choices that leave it (a run can walk to any member surely, so the optimum is the
same: de Alfaro 1997); choices inside it are dropped. The quotient has no end components, so
every policy leaves its states surely, and the reachability of the target is an expected total
reward (the mass each choice sends into the target, times the target's value) in an MDP for
which :class:`~misdirect.solvers.engines.transient.TransientPolicyIteration` proves bounds:
``u = v + δ W`` with ``W`` a proven bound on the steps of any run, ``δ`` the largest defect.

Soundness needs no trust in the floats: the quotient's rows are rounded *up* where entries are
summed (a row may then sum to a little over 1), so any ``u ≥ 0`` the proof accepts for it is a
pre-fixed point of the exact quotient's operator, hence above its least fixed point, the
optimum (Knaster–Tarski).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from misdirect.core import residual, tolerance
from misdirect.core.model import reachable_from
from misdirect.solvers.deadline import Deadline
from misdirect.solvers.engines.transient import TransientPolicyIteration


class CollapsedProof(NamedTuple):
    """A proven bound (None: none was found) and why none was (empty when one was)."""

    bound: float | None
    why: str


class UnprovenError(Exception):
    """The collapsed proof found no bound; the message says why."""


def maximal_end_components(
    owner: np.ndarray, transitions: sp.csr_matrix, active: np.ndarray, within: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(per state of ``within``, a label shared by the states of one maximal end component
    and unique otherwise, -1 outside ``within``; per choice, whether it stays inside its
    state's component), over the ``active`` choices whose every successor lies ``within``.
    The usual decomposition: strongly connected components, less the choices that leave
    theirs, until none does."""
    n = within.size
    matrix = transitions.tocsr()
    entry_row = np.repeat(np.arange(owner.size), np.diff(matrix.indptr))
    outside = np.bincount(entry_row, weights=~within[matrix.indices], minlength=owner.size)
    active = active & within[owner] & (outside == 0)
    while True:
        chosen = np.flatnonzero(active)
        rows = matrix[chosen].tocoo()
        source = owner[chosen][rows.row]
        graph = sp.csr_matrix((np.ones(rows.nnz), (source, rows.col)), shape=(n, n))
        _, scc = connected_components(graph, directed=True, connection="strong")
        leaving = np.bincount(rows.row, weights=scc[rows.col] != scc[source], minlength=chosen.size)
        if not (leaving > 0).any():
            break
        active[chosen[leaving > 0]] = False
    return np.where(within, scc, -1), active


def collapsed_bound(
    owner: np.ndarray,
    transitions: sp.csr_matrix,
    target: np.ndarray,
    fixed: np.ndarray,
    allowed: np.ndarray,
    state: int,
    policy: np.ndarray | None = None,
    deadline: Deadline | None = None,
) -> CollapsedProof:
    """A proven upper bound at ``state`` on the maximal expected value of the first target
    state entered (target ``s`` worth ``fixed[s]``), over the ``allowed`` choices, from the MDP
    with its maximal end components collapsed; no bound, and why, where the proof fails.
    ``policy`` (a choice per state, policy iteration's) warm-starts the quotient's own policy
    iteration. Raises :class:`~misdirect.solvers.deadline.DeadlineExpiredError` once
    ``deadline`` has passed."""
    n = target.size
    matrix = transitions.tocsr()
    chosen = np.flatnonzero(allowed)
    moves = matrix[chosen].tocoo()
    graph = sp.csr_matrix(
        (np.ones(moves.nnz), (owner[chosen][moves.row], moves.col)), shape=(n, n)
    ).tocsr()
    live = reachable_from(graph.T.tocsr(), np.flatnonzero(target)) & ~target
    if not live[state]:
        # no allowed run reaches the target
        return CollapsedProof(float(fixed[state]) if target[state] else 0.0, "")
    labels, internal = maximal_end_components(owner, matrix, allowed, live)
    node_ids, node = np.unique(labels[live], return_inverse=True)
    node_of = np.full(n, -1)
    node_of[live] = node
    # the quotient's rows: allowed choices of live states that leave their component
    rows = np.flatnonzero(allowed & live[owner] & ~internal)
    if deadline is not None:
        deadline.check()
    sub = matrix[rows].tocsr()
    entry_row = np.repeat(np.arange(rows.size), np.diff(sub.indptr))
    into = live[sub.indices]
    cells = sp.csr_matrix(
        (sub.data[into], (entry_row[into], node_of[sub.indices[into]])),
        shape=(rows.size, node_ids.size),
    )
    counts = sp.csr_matrix(
        (np.ones(int(into.sum())), (entry_row[into], node_of[sub.indices[into]])),
        shape=(rows.size, node_ids.size),
    )
    cells.sum_duplicates()
    counts.sum_duplicates()
    # a cell summed from k entries is off by at most (k - 1) u of itself: rounded up past it
    cells.data = cells.data * np.where(counts.data > 1, 1 + 4 * counts.data * _U, 1.0)
    # the mass each row sends into the target, times its value, rounded up (Higham's bound)
    hit = target[sub.indices]
    worth = np.bincount(
        entry_row[hit], weights=sub.data[hit] * fixed[sub.indices[hit]], minlength=rows.size
    )
    length = np.bincount(entry_row[hit], minlength=rows.size)
    reward = worth * (1 + 2.02 * (length + 2) * _U) + np.where(worth > 0, tolerance.SMALLEST, 0.0)
    row_node = node_of[owner[rows]]
    quotient = TransientPolicyIteration(row_node, cells, node_ids.size)
    values, best, _, settled = quotient.optimise(
        reward,
        _warm_start(quotient, rows, owner, node_of, policy),
        deadline=deadline,
        max_rounds=COLLAPSED_ROUNDS,
    )
    if not settled:
        return CollapsedProof(
            None,
            f"the collapsed MDP's policy iteration did not settle (a policy it had left came "
            f"back, or over {COLLAPSED_ROUNDS} rounds): improvements at rounding level",
        )
    try:
        bound = _pre_fixed_above(quotient, reward, values, best, int(node_of[state]), deadline)
    except UnprovenError as why:
        return CollapsedProof(None, str(why))
    return CollapsedProof(bound, "")


def _pre_fixed_above(
    quotient: TransientPolicyIteration,
    reward: np.ndarray,
    values: np.ndarray,
    policy: np.ndarray,
    state: int,
    deadline: Deadline | None,
) -> float:
    """``u(state)`` for a proven pre-fixed point ``u = v + ε`` of the quotient's Bellman
    operator (every row ``a`` of every node ``x``: ``reward_a + P_a u ≤ u(x)``, checked in
    exact arithmetic); raises :class:`UnprovenError` where none is found.

    ``v`` is policy iteration's values refined in double-double, switching on any gain above
    :data:`~misdirect.core.tolerance.PROOF_COLLAPSED_GAIN`: a region a scheduler can linger
    in for 10^15 steps (steered away from its exits on a turn-back grid) has values equal to
    12 digits, and only double-double tells its choices apart. ``ε`` is the most a run
    collects, along the *tied* rows (those within the cost of the best), of a cost ``c(x)``:
    twice the largest defect of ``v`` at ``x`` plus
    :data:`~misdirect.core.tolerance.PROOF_EXTENDED_OFFSET`. A tied row then passes with
    ``c(x)/2`` to spare, and a row worse by more than ``ε`` reaches passes anyway; rows that
    fail are tied too, and ``ε`` solved again."""
    scale = max(float(np.abs(values).max(initial=0.0)), tolerance.SMALLEST)
    hi, lo, policy = _refined(quotient, reward, values, policy, scale, deadline)
    defects = _row_upper(quotient, reward, hi, lo)
    if not np.isfinite(defects).all():
        raise UnprovenError("a row's defect is not finite")
    per_node = np.zeros(quotient.n_states)
    np.maximum.at(per_node, quotient.row_state, np.maximum(defects, 0.0))
    cost = 2 * per_node + tolerance.PROOF_EXTENDED_OFFSET * scale
    tied = defects >= -cost[quotient.row_state]
    tied[policy] = True  # every node keeps a row
    for _ in range(TIE_ROUNDS):
        if deadline is not None:
            deadline.check()
        sub = np.flatnonzero(tied)
        among = TransientPolicyIteration(
            quotient.row_state[sub], quotient.matrix[sub], quotient.n_states
        )
        collected, _, _, optimal = among.optimise(
            cost[quotient.row_state[sub]], deadline=deadline, max_rounds=COLLAPSED_ROUNDS
        )
        if not (optimal and np.isfinite(collected).all()):
            raise UnprovenError("the tied rows' policy iteration failed")
        # a little more than collected: the solve's rounding, against c's slack
        u_hi, u_lo = residual.add(hi, lo, np.maximum(collected, 0.0) * (1 + 2.0**-20))
        failing = _row_upper(quotient, reward, u_hi, u_lo) > 0
        if not failing.any():
            return float(np.nextafter(u_hi[state] + u_lo[state], np.inf))
        if not (failing & ~tied).any():
            raise UnprovenError("tied rows fail the check: their rounding exceeds the cost's slack")
        tied |= failing
    raise UnprovenError(
        f"the check still failed after {TIE_ROUNDS} rounds of tying the failing rows"
    )


def _refined(
    quotient: TransientPolicyIteration,
    reward: np.ndarray,
    values: np.ndarray,
    policy: np.ndarray,
    scale: float,
    deadline: Deadline | None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(``hi``, ``lo``, policy): policy iteration continued in double-double from
    ``values`` and ``policy``, refinement solves per policy until its rows' residuals fall
    below the switching gain; raises :class:`UnprovenError` if a solve fails."""
    hi, lo = values.copy(), np.zeros(values.size)
    before: tuple[np.ndarray, np.ndarray] | None = None  # the last policy's refined values
    for rounds in range(REFINED_SWITCHES):
        if deadline is not None:
            deadline.check()
        try:
            lu = quotient.factorise(policy)
        except (RuntimeError, ValueError):
            raise UnprovenError("a factorisation failed") from None
        rows = quotient.matrix[policy].tocsr()
        own = np.arange(quotient.n_states)
        for _ in range(REFINE_ROUNDS):
            r, _ = residual.residual(rows, hi, lo, own, reward[policy])
            if np.abs(r).max(initial=0.0) <= tolerance.PROOF_COLLAPSED_GAIN * scale:
                break
            correction = lu.solve(r)
            if not np.isfinite(correction).all():
                raise UnprovenError("a refinement solve failed")
            hi, lo = residual.add(hi, lo, correction)
        # an improvement raises every value; a fall is a solve gone wrong (a chain that
        # lingers so long, 10^16 steps, that double-double refinement cannot converge)
        if (
            before is not None
            and (
                ((hi - before[0]) + (lo - before[1])) < -tolerance.PROOF_COLLAPSED_FALL * scale
            ).any()
        ):
            raise UnprovenError(
                "values fell after a policy improvement: a chain that lingers past what "
                "double-double refinement resolves"
            )
        before = hi.copy(), lo.copy()
        gain, _ = residual.residual(quotient.matrix, hi, lo, quotient.row_state, reward)
        order = np.lexsort((-gain, quotient.row_state))
        best = order[quotient.state_start]
        switch = gain[best] - gain[policy] > tolerance.PROOF_COLLAPSED_GAIN * scale
        if not switch.any():
            break
        if rounds + 1 == REFINED_SWITCHES:
            raise UnprovenError(
                f"policy iteration in double-double still improved after {REFINED_SWITCHES} "
                "switches"
            )
        policy = np.where(switch, best, policy)
    return hi, lo, policy


def _row_upper(
    quotient: TransientPolicyIteration, reward: np.ndarray, hi: np.ndarray, lo: np.ndarray
) -> np.ndarray:
    """Per row ``a`` of node ``x``: an upper bound, in exact arithmetic, on
    ``reward_a + P_a u − u(x)`` for the double-double ``u = hi + lo``."""
    r, bound = residual.residual(quotient.matrix, hi, lo, quotient.row_state, reward)
    upper = r + 2 * (bound - np.abs(r))  # |exact - r| <= bound - |r|, doubled for rounding
    return np.where(np.isfinite(upper), upper, np.inf)


TIE_ROUNDS = 4  # rounds of tying the rows a proof fails at before giving up
# policy improvements on the collapsed MDP, at most (each a sparse LU: 65 ms on the 6,353 nodes
# of the 64-sensor turn-back grid's), a returning policy stopping it at once: the stall of
# union 1,168 of that grid's budget-4 cover was not one LU but five policies in turn, forever
COLLAPSED_ROUNDS = 50
REFINED_SWITCHES = 32  # policy improvements in double-double, at most
# refinement solves per policy, at most: each gains a factor of about cond · u, which on a
# chain that lingers 10^15 steps is 0.3
REFINE_ROUNDS = 64


_U = tolerance.UNIT_ROUNDOFF


def _warm_start(
    quotient: TransientPolicyIteration,
    rows: np.ndarray,
    owner: np.ndarray,
    node_of: np.ndarray,
    policy: np.ndarray | None,
) -> np.ndarray:
    """Per node of the quotient, a row: a member's choice under ``policy`` where that choice
    leaves the component, else the node's first row."""
    start = quotient.first_rows().copy()
    if policy is None:
        return start
    position = np.full(owner.size, -1)
    position[rows] = np.arange(rows.size)
    members = np.flatnonzero(node_of >= 0)
    taken = position[policy[members]]
    usable = taken >= 0
    start[node_of[members[usable]]] = taken[usable]
    return start
