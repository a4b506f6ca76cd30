"""Maximal reachability in an MDP, and the MDP that adds a remaining budget to its states.

The online attacker (:mod:`misdirect.defence.online`) is an MDP player: it sees the state and
picks each altered reading as it goes. Its value is the optimum of this MDP problem; the
algorithm is kept apart from the attacker so that its correctness argument (policy iteration
from the least fixed point, docs/defence.md) can be read and tested on its own.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from misdirect.core.choice_product import ChoiceProduct
from misdirect.solvers.deadline import Deadline
from misdirect.solvers.engines.policy_iteration import MaxReachability

MAX_POLICY_ROUNDS = 100_000


def max_reach(
    owner: np.ndarray,
    transitions: sp.csr_matrix,
    target: np.ndarray,
    *,
    blocks: np.ndarray | None = None,
    value: np.ndarray | None = None,
    deadline: Deadline | None = None,
) -> tuple[np.ndarray, np.ndarray, int]:
    """Maximal reachability of ``target`` in an MDP given by its choices (with ``value``, a
    score per target state: the maximal expected score of the first target state entered).

    Choice ``g`` belongs to state ``owner[g]`` and moves by row ``g`` of ``transitions``.
    Policy iteration from the least fixed point, the same as the relaxations'
    (:class:`misdirect.solvers.engines.policy_iteration.MaxReachability`, whose docstring
    gives the correctness argument; docs/defence.md). Returns ``(values, policy,
    evaluations)``; raises :class:`~misdirect.solvers.deadline.DeadlineExpiredError` once
    ``deadline`` has passed (checked before every round).
    """
    mdp, values, policy = _optimised(owner, transitions, target, blocks, value, deadline)
    return values, policy, mdp.evaluations


def _optimised(
    owner: np.ndarray,
    transitions: sp.csr_matrix,
    target: np.ndarray,
    blocks: np.ndarray | None,
    value: np.ndarray | None,
    deadline: Deadline | None,
) -> tuple[MaxReachability, np.ndarray, np.ndarray]:
    """The MDP, and policy iteration's values and policy on it."""
    mdp = MaxReachability(owner, transitions, target, blocks=blocks, value=value)
    values, policy = mdp.optimise(
        mdp.first_choices(), max_rounds=MAX_POLICY_ROUNDS, deadline=deadline
    )
    return mdp, values, policy


def max_reach_bounded(
    owner: np.ndarray,
    transitions: sp.csr_matrix,
    target: np.ndarray,
    state: int,
    *,
    blocks: np.ndarray | None = None,
    value: np.ndarray | None = None,
    deadline: Deadline | None = None,
) -> tuple[float, float, int]:
    """:func:`max_reach` at ``state``, with a proven upper bound on it: ``(value, bound,
    evaluations)``. Policy iteration's values are rounded solutions; the bound is a
    pre-fixed point of the Bellman operator checked with its rounding
    (:meth:`~misdirect.solvers.engines.policy_iteration.MaxReachability.proven_bound`), what
    a claim "the online attacker gets at most this" needs."""
    mdp, values, policy = _optimised(owner, transitions, target, blocks, value, deadline)
    bound = mdp.proven_bound(values, policy, state, deadline=deadline)
    return float(values[state]), max(bound, float(values[state])), mdp.evaluations


def budgeted_mdp(
    chain: ChoiceProduct, group_units: np.ndarray, levels: int
) -> tuple[np.ndarray, sp.csr_matrix, np.ndarray, int]:
    """The MDP over (product state, remaining units): state ``r * Q + q``; group ``g`` in
    level ``r ≥ cost(g)`` moves like ``g`` into level ``r - cost(g)``.

    Returns ``(owner, transitions, target, initial)`` in the form :func:`max_reach` takes."""
    n_q = chain.n_states
    allowed = group_units[:, None] <= np.arange(levels)[None, :]
    groups, level = np.nonzero(allowed)
    rows = chain.transitions[groups].tocsr()
    shift = (level - group_units[groups]) * n_q
    indices = rows.indices.astype(np.int64) + np.repeat(shift, np.diff(rows.indptr))
    matrix = sp.csr_matrix((rows.data, indices, rows.indptr), shape=(groups.size, n_q * levels))
    owner = level * n_q + chain.group_state[groups]
    target = np.tile(chain.target, levels)
    return owner, matrix, target, (levels - 1) * n_q + chain.initial
