"""A Lagrangian node bound for branch-and-bound under ``max_alarm`` (off by default).

For λ ≥ 0 and every alteration α with Pr_α(alarm) ≤ δ,

    decoy(α) ≤ decoy(α) − λ (alarm(α) − δ) = L_λ(α) − λ (1 − δ),

with L_λ(α) = decoy(α) + λ (1 − alarm(α)). The alarm sink is absorbing; where the live states
(those that can reach a stopping state) hold no end component, every run leaves them and ends
in a decoy, in the sink, or in a dead state (one reaching no stopping state), so
1 − alarm = Pr(decoy) + Pr(dead), and L_λ is the value of the same chain with each decoy worth
its weight + λ, the dead states λ and the sink 0: a weighted reachability objective with
weights ≥ 0, whose per-state relaxation and proven bound (:mod:`.policy_iteration`) are the
ones the search already uses. The dead states are exactly the chain's states that are neither
live nor stopping, the same for every option, so the reweighted problem has the live states
and the alteration space of the search's own. With end components the never-absorbed runs
would need a bound of their own: :func:`lagrangian_bound` is refused there.

Measured on the paper grid under the consistency monitor (docs/benchmarks.md, "Stealth"): it
prunes nodes where δ binds (λ = 100: 41 % fewer at δ = 0, 27 % at δ = 0.01, none at 0.05) but
each bound is a second policy iteration with its proof, and the curves took longer; at the
root the relaxation's own optimum barely moves (δ = 0: 0.555 against 0.858), and the λ that
minimises the root bound is 0 for δ ≥ 0.05. So branch-and-bound does not use it unless asked
(:data:`misdirect.solvers.branch_and_bound.LAGRANGE_MULTIPLIERS`).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from misdirect.solvers.deadline import Deadline
from misdirect.solvers.engines.per_state import PerStateRelaxation
from misdirect.solvers.engines.policy_iteration import MaxReachability

# rounding of ``bound - λ (1 - δ)`` (two operations, each within one unit roundoff of the
# larger operand): a few ulps of the operands, added so the result stays a proven bound
SUBTRACTION_ULPS = 4.0


class LagrangianBound:
    """The reweighted relaxations of :func:`lagrangian_bound`, one per λ, on ``relax``'s chain
    (``alarm``: its sink states)."""

    def __init__(
        self, relax: PerStateRelaxation, alarm: np.ndarray, limit: float, lambdas: Sequence[float]
    ):
        chain = relax.chain
        if not all(lam >= 0.0 for lam in lambdas) or not lambdas:
            raise ValueError(f"the multipliers must be at least one λ >= 0, got {lambdas!r}")
        self.relax, self.limit = relax, float(limit)
        self.lambdas = tuple(float(lam) for lam in lambdas)
        dead = ~relax.live & ~chain.target
        decoy = chain.target & ~alarm
        self.mdps = []
        for lam in self.lambdas:
            value = np.where(decoy, chain.target_value + lam, 0.0)
            value[dead] = lam
            self.mdps.append(
                MaxReachability(
                    chain.group_state,
                    chain.transitions,
                    chain.target | dead,
                    blocks=chain.node,
                    value=value,
                    live=relax.live,
                    cycling=np.zeros(chain.n_states, dtype=bool),
                )
            )
        self.bounds = 0  # node bounds asked for

    def bound(
        self, allowed_groups: np.ndarray, policy: np.ndarray, deadline: Deadline | None = None
    ) -> float:
        """A proven upper bound on Pr(decoy) over the completions the node allows
        (``allowed_groups``) whose Pr(alarm) is at most δ: the smallest over λ of the
        reweighted relaxation's proven bound less λ (1 − δ). ``policy``: a warm start (the
        node's own relaxation's policy)."""
        self.bounds += 1
        penalty = np.where(allowed_groups, 0.0, -np.inf)
        start = self.relax.chain.initial
        best = np.inf
        for lam, mdp in zip(self.lambdas, self.mdps, strict=True):
            values, chosen = mdp.optimise(policy.copy(), penalty, deadline=deadline)
            proven = mdp.proven_bound(values, chosen, start, penalty, deadline)
            shift = lam * (1.0 - self.limit)
            slack = SUBTRACTION_ULPS * np.finfo(np.float64).eps * (abs(proven) + shift)
            best = min(best, proven - shift + slack)
        return float(best)


def lagrangian_bound(
    relax: PerStateRelaxation, cycling: np.ndarray, limit: float, lambdas: Sequence[float]
) -> LagrangianBound | None:
    """The Lagrangian node bound of the module docstring for ``relax`` (a monitored
    problem's decoy relaxation, :mod:`.alarm`) at δ = ``limit``; None where it is not sound
    as built: live states in end components (``cycling``), or no alarm sink."""
    problem = relax.problem
    if problem.alarm_state is None or bool(np.asarray(cycling).any()):
        return None
    alarm = relax.chain.world_state == problem.alarm_state
    return LagrangianBound(relax, alarm, limit, lambdas)
