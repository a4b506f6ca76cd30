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
from misdirect.core.model import reachable_from
from misdirect.core.reachability import reach_probabilities
from misdirect.errors import SolverError

IMPROVE_TOLERANCE = 1e-12  # policy iteration switches a state only on a larger gain
MAX_POLICY_ROUNDS = 100_000


def max_reach(
    owner: np.ndarray,
    transitions: sp.csr_matrix,
    target: np.ndarray,
    *,
    blocks: np.ndarray | None = None,
    value: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, int]:
    """Maximal reachability of ``target`` in an MDP given by its choices (with ``value``, a
    score per target state: the maximal expected score of the first target state entered).

    Choice ``g`` belongs to state ``owner[g]`` and moves by row ``g`` of ``transitions``.
    Policy iteration: each policy is evaluated exactly as the *least* fixed point
    (:func:`misdirect.core.reachability.reach_probabilities`), and a state switches only on a
    strict gain. At termination the values are a fixed point of the Bellman operator that some
    policy attains; every fixed point lies above the least one, which is the optimum, and no
    policy lies above the optimum — so they are the optimum (docs/defence.md). Returns
    ``(values, policy, evaluations)``.
    """
    n_states = target.size
    owner = np.asarray(owner, dtype=np.int64)
    if np.bincount(owner, minlength=n_states).min(initial=1) == 0:
        raise SolverError("every state of the MDP needs at least one choice")
    structure = (transitions != 0).astype(np.float64)
    owners = sp.csr_matrix(
        (np.ones(owner.size), (owner, np.arange(owner.size))), shape=(n_states, owner.size)
    )
    graph = (owners @ structure).tocsr()
    live = reachable_from(graph.T.tocsr(), np.flatnonzero(target)) & ~target
    order = np.argsort(owner, kind="stable")
    first = order[np.concatenate([[0], np.flatnonzero(np.diff(owner[order])) + 1])]
    policy = first.copy()  # the lowest-numbered choice of every state
    for evaluations in range(1, MAX_POLICY_ROUNDS + 1):
        values = reach_probabilities(
            transitions[policy].tocsr(), target, blocks=blocks, value=value
        )
        score = np.asarray(transitions @ values).ravel()
        ranked = np.lexsort((-score, owner))
        best = ranked[np.concatenate([[0], np.flatnonzero(np.diff(owner[ranked])) + 1])]
        switch = live & (score[best] > score[policy] + IMPROVE_TOLERANCE)
        if not switch.any():
            return values, policy, evaluations
        policy = np.where(switch, best, policy)
    raise SolverError(f"policy iteration did not settle in {MAX_POLICY_ROUNDS:,} rounds")


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
