"""Exact value of one alteration: the probability of misleading the robot into the decoy.

:func:`decoy_probability` is the lean number every solver needs; :func:`evaluate` is the full
report a person reads (outcomes, sizes, expected visits per cell).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from misdirect.model import Alteration, Problem
from misdirect.product import ProductChain, build_product
from misdirect.reachability import occupation, reach_probabilities


def decoy_probability(problem: Problem, alteration: Alteration) -> float:
    """Pr(reach decoy) from ``(s0, n0)`` under ``alteration``, exactly (sparse LU)."""
    chain = build_product(problem, alteration)
    return _decoy_probability(problem, chain)


def evaluation_time(problem: Problem, repeats: int = 3) -> float:
    """Best-of-``repeats`` wall time of one exact evaluation of the unaltered chain.

    The floor of every solver: none can certify an optimum faster than evaluating its answer,
    so benchmarks report their times against this.
    """
    best = float("inf")
    for _ in range(repeats):
        began = time.perf_counter()
        decoy_probability(problem, problem.identity())
        best = min(best, time.perf_counter() - began)
    return best


def _decoy_probability(problem: Problem, chain: ProductChain) -> float:
    values = reach_probabilities(chain.matrix, problem.decoy[chain.world_state], blocks=chain.node)
    return float(values[chain.initial])


@dataclass(frozen=True)
class Evaluation:
    """Everything known about one alteration, computed exactly."""

    probability: float
    alteration: dict[str, str]
    cost: float
    within_budget: bool
    outcomes: dict[str, float]  # first decoy/absorbing state entered -> probability
    never_absorbed: float  # runs that cycle forever without a decoy or absorbing state
    product_states: int
    product_transitions: int
    time_s: float
    expected_visits: np.ndarray = field(repr=False)  # (|S|,) expected steps spent per world state

    def to_dict(self) -> dict:
        return {
            "probability": self.probability,
            "alteration": self.alteration,
            "cost": self.cost,
            "within_budget": self.within_budget,
            "outcomes": self.outcomes,
            "never_absorbed": self.never_absorbed,
            "product_states": self.product_states,
            "product_transitions": self.product_transitions,
            "time_s": self.time_s,
        }


def evaluate(problem: Problem, alteration: Alteration | None = None) -> Evaluation:
    """Exact report for ``alteration`` (the identity when ``None``)."""
    started = time.perf_counter()
    alpha = problem.identity() if alteration is None else np.asarray(alteration, dtype=np.int64)
    chain = build_product(problem, alpha)
    probability = _decoy_probability(problem, chain)

    pomdp = problem.pomdp
    decoy = problem.decoy[chain.world_state]
    terminal = decoy | pomdp.absorbing[chain.world_state]
    occ = occupation(chain.matrix, terminal, chain.initial)
    first_entry = np.bincount(
        chain.world_state, weights=np.where(terminal, occ.entered, 0.0), minlength=pomdp.n_states
    )
    terminal_states = np.flatnonzero(problem.decoy | pomdp.absorbing)
    outcomes = {pomdp.states[s]: float(first_entry[s]) for s in terminal_states}
    visits = np.bincount(chain.world_state, weights=occ.visits, minlength=pomdp.n_states)
    cost = problem.alteration_cost(alpha)
    return Evaluation(
        probability=probability,
        alteration=problem.changed_observations(alpha),
        cost=cost,
        within_budget=cost <= problem.budget + 1e-9,
        outcomes=outcomes,
        never_absorbed=float(occ.entered[occ.trapped].sum()),
        product_states=chain.n_states,
        product_transitions=chain.n_transitions,
        time_s=time.perf_counter() - started,
        expected_visits=visits,
    )
