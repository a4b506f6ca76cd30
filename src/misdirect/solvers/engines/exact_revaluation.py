"""The exact-valuation guard of the low-rank enumeration: values it may not trust, re-valued.

A low-rank update of a base solve is only as good as the base's conditioning
(:func:`~misdirect.solvers.engines.lowrank_updates.update_error`): on an ill-conditioned base,
or where an update is singular (an alteration that opens or closes a class), its value may be
off by more than near-ties allow, and ranking by it could pick the wrong alteration. Such
alterations are valued here one chain each, as the least fixed point of their own chain
(:func:`~misdirect.core.reachability.reach_probability_bounded`), before the enumeration
ranks them. Every alteration a deadline leaves unvalued gets cost ``inf``, so no budget that
needs it counts as proven.
"""

from __future__ import annotations

from collections.abc import Callable
from functools import cached_property

import numpy as np
import scipy.sparse as sp

from misdirect.core import tolerance
from misdirect.core.attack import AttackInstance
from misdirect.core.elimination import fill_reducing_rank
from misdirect.core.reachability import reach_probability_bounded
from misdirect.solvers.deadline import Deadline
from misdirect.solvers.engines.lowrank_updates import update_error


class ExactChains:
    """Exact values of single alterations of one instance, each on its own chain (``chain_of``
    a choice vector: the transitions within the choice product), with a count of the chains
    solved (``evaluations``)."""

    def __init__(self, instance: AttackInstance, chain_of: Callable[[np.ndarray], sp.csr_matrix]):
        self.instance = instance
        self.chain_of = chain_of
        self.n_choices = len(instance.space.choices)
        self.evaluations = 0
        # chains valued one by one, [unproven, proven]: where most run too long for a proof,
        # each is eliminated first and an LU is tried only on those that might be proven
        self._proofs = [0, 0]

    def value(self, picked: np.ndarray) -> float:
        """Exact value at the start of the alteration taking option ``picked[i]`` of every
        choice ``i``: its chain within the choice product, solved as the least fixed point
        (past about 10^14 steps, unproven: the jump chain's value, in doubles; the search
        only ranks by it, and what is printed is evaluated again). Once most chains valued
        so far were unproven, each is eliminated first, in one order computed for all, and
        one that runs too long for a proof is not given an LU."""
        chain = self.instance.chain
        unproven, proven = self._proofs
        found = reach_probability_bounded(
            self.chain_of(picked),
            chain.target,
            chain.initial,
            blocks=chain.node,
            value=chain.target_value,
            extended_jump=False,
            elimination_rank=self._elimination_rank if unproven > 2 * proven + 8 else None,
        )
        self._proofs[bool(np.isfinite(found.error))] += 1  # a count: a lost update is harmless
        self.evaluations += 1
        return found.value

    @cached_property
    def _elimination_rank(self) -> np.ndarray:
        """A fill-reducing order of the product states, for every alteration's chain: the
        unaltered chain's (an alteration changes a few rows; the pattern of all of them
        together fills far more)."""
        return fill_reducing_rank(self.chain_of(np.zeros(self.n_choices, dtype=np.int64)))


def value_one_chain_each(
    indices: np.ndarray,
    found: np.ndarray,
    costs: np.ndarray,
    value_of: Callable[[int], float],
    deadline: Deadline,
) -> float:
    """Value the alterations ``indices`` (``value_of``: one chain each, exactly) into
    ``found``: they are the ones a low-rank update would get wrong. Those the deadline leaves
    get cost ``inf`` in ``costs``; returns the cheapest of them (``inf``: none)."""
    cut_at = np.inf
    for index in indices[np.isfinite(costs[indices])].tolist():
        if deadline.expired():
            cut_at = min(cut_at, float(costs[index]))
            costs[index] = np.inf
            continue
        found[index] = value_of(index)
    return cut_at


def guard_ill_conditioned(
    costs: np.ndarray,
    values: np.ndarray,
    unevaluated: float,
    scale: tolerance.CostScale,
    steps: float,
    top_value: float,
    value_of: Callable[[int], float],
    deadline: Deadline,
    floor: float | None = None,
) -> float:
    """Value exactly (in place, ``value_of`` each) every alteration that may be the best
    within some budget, when its base chains are so ill-conditioned (left after up to
    ``steps`` expected steps) that low-rank values may be off by more than near-ties allow
    (:func:`~misdirect.solvers.engines.lowrank_updates.update_error`, ``M``); returns the
    cheapest cost left unvalued (``unevaluated``, or less).

    Those are the alterations within ``2M`` of the best value at their cost or less: any
    other is at least ``2M`` below one of them, so, off by at most ``M`` each way, below
    its exact value. With ``floor`` (the run answers for its top budget only, and only
    about what may reach the floor), also not those more than ``2M`` below it. Those the
    deadline leaves are unvalued (cost ``inf``), as a block cut short leaves them: their
    budgets are not proven. One of cost 0 is kept, unverified, whatever the deadline: it
    fits every budget, so budget 0 always has an answer (the unaltered alteration is
    re-valued exactly by the front door); alone at cost 0 it proves budget 0 unranked."""
    margin = update_error(steps, top_value)
    precise = margin <= tolerance.slack(top_value, rel=tolerance.NEAR_TIE) / 10
    if precise or not values.size:
        return unevaluated
    order = np.lexsort((-values, costs))  # by cost, the best first among equal costs
    best_so_far = np.maximum.accumulate(values[order])
    candidates = order[values[order] >= best_so_far - 2 * margin]
    candidates = candidates[np.isfinite(costs[candidates])]
    if floor is not None:
        least = floor - 2 * margin - tolerance.slack(floor, rel=tolerance.NEAR_TIE)
        candidates = candidates[values[candidates] >= least]
    free = costs <= scale.cap(0.0)
    # an unverified free alteration competes at every budget; alone, not at budget 0
    free_open = float(costs[~free].min(initial=np.inf)) if free.sum() == 1 else 0.0
    for index in candidates[np.argsort(-values[candidates], kind="stable")].tolist():
        if deadline.expired():
            if free[index]:
                unevaluated = min(unevaluated, free_open)
                continue
            unevaluated = min(unevaluated, float(costs[index]))
            costs[index] = np.inf
            continue
        values[index] = min(max(value_of(index), 0.0), top_value)
    return unevaluated
