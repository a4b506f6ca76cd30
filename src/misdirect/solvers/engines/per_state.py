"""The per-state MDP relaxation of the choice product: every free state picks on its own.

An alteration picks one candidate per relevant observation. For a partial assignment (some
observations fixed, the others free within the remaining budget), the relaxation lets every
product state owned by a free observation take, on its own, the group of any candidate that
fits the remaining budget; states of fixed observations keep their candidate's group. Every
feasible completion is one scheduler of that MDP, so its maximal reachability probability
bounds them all.

The relaxation is solved by policy iteration: each policy is evaluated by
:func:`misdirect.core.reachability.reach_probabilities` (the least fixed point, so policies that
cycle forever score 0 and end components need no special care), and a state switches only on a
strict gain of more than :data:`~misdirect.core.tolerance.IMPROVE`. Those values are rounded
solutions; the bound is proven from them
(:meth:`~misdirect.solvers.engines.policy_iteration.MaxReachability.proven_bound`). Used by
branch-and-bound (its node bound), by the segment search (its picks and exact values), and by
every method that needs a proven bound when cut short (:func:`relaxation_bound`).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import cast

import numpy as np

from misdirect.core.alterations import AlterationSpace
from misdirect.core.attack import prepare
from misdirect.core.choice_product import ChoiceProduct
from misdirect.core.model import AlterationArray, Problem
from misdirect.solvers.deadline import Deadline, DeadlineExpiredError
from misdirect.solvers.engines.policy_iteration import MaxReachability


class PerStateRelaxation:
    """The choice product with the per-state MDP relaxation and exact policy evaluation."""

    def __init__(
        self,
        problem: Problem,
        space: AlterationSpace,
        chain: ChoiceProduct,
        cycling: np.ndarray | None = None,
    ):
        """``cycling``: the chain's live states in end components, where the caller has them
        (``AttackInstance.cycling``): policy iteration then need not find them again."""
        self.problem, self.space, self.chain = problem, space, chain
        self.live = chain.can_reach_target() & ~chain.target
        sizes = np.array([c.size for c in space.choices], dtype=np.int64)
        self.first_option = np.concatenate([[0], np.cumsum(sizes)])
        self.option_cost = chain.options.cost
        self.option_owner = np.repeat(np.arange(sizes.size), sizes)
        state_obs = problem.pomdp.observation_of[chain.world_state]
        observations = np.array([c.observation for c in space.choices], dtype=np.int64)
        per_observation = np.bincount(state_obs[self.live], minlength=problem.pomdp.n_observations)
        owned = per_observation[observations]
        # largest first; observations owning no live state never change the value: fixed to 0
        self.order = [int(i) for i in np.argsort(-owned, kind="stable") if owned[i] > 0]
        self.group_options = chain.group_options.tocsr()
        self.free_group = np.diff(self.group_options.indptr) == 0  # state has no choice at all
        self.live_groups = self.live[chain.group_state]
        # live states whose group says which candidates they use (for rounding policies)
        self.choosing = self.live & (chain.groups_per_state > 1)
        self.mdp = MaxReachability(
            chain.group_state,
            chain.transitions,
            chain.target,
            blocks=chain.node,
            value=chain.target_value,
            live=self.live,
            cycling=cycling,
        )

    @property
    def evaluations(self) -> int:
        """Exact policy evaluations (linear solves) so far."""
        return self.mdp.evaluations

    def allowed_options(self, picks: Sequence[int], remaining: float) -> np.ndarray:
        """Options a node permits: its fixed picks, and every affordable one of free ones."""
        allowed = self.option_cost <= remaining  # a cap (CostScale.cap) less what was spent
        for i, k in zip(self.order, picks, strict=False):
            allowed[self.first_option[i] : self.first_option[i + 1]] = False
            allowed[self.first_option[i] + k] = True
        return allowed

    def free_options(self, free: Sequence[int], cap: float, fixed: Mapping[int, int]) -> np.ndarray:
        """Options of a relaxation over choice indices (not a node's order): the ``free``
        choices' within ``cap``, ``fixed`` choices' own option, and every other choice
        unaltered (the covering bound's unions)."""
        first, cost = self.first_option, self.option_cost
        allowed = np.zeros(cost.size, dtype=bool)
        allowed[first[:-1]] = True  # every choice may stay unaltered...
        for i in free:
            span = slice(first[i], first[i + 1])
            allowed[span] = cost[span] <= cap
            allowed[first[i]] = True
        for i, k in fixed.items():  # ...but a decided one takes its option
            allowed[first[i] : first[i + 1]] = False
            allowed[first[i] + k] = True
        return allowed

    def affordable(self, i: int, cap: float) -> np.ndarray:
        """The alterations (option indices, 0 being unaltered) of choice ``i`` within
        ``cap``."""
        options = self.option_cost[self.first_option[i] + 1 : self.first_option[i + 1]]
        return np.flatnonzero(options <= cap) + 1

    def allowed_groups(self, allowed_options: np.ndarray) -> np.ndarray:
        hits = self.group_options @ allowed_options.astype(np.float64)
        return cast(np.ndarray, self.free_group | (np.asarray(hits).ravel() > 0))

    def best_groups(self, score: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per state: the group of highest score (the first on ties) and that score."""
        return self.mdp.best_choices(score)

    def evaluate(self, policy: np.ndarray) -> np.ndarray:
        """Exact reachability values of the chain that takes group ``policy[q]`` in ``q``."""
        return self.mdp.evaluate(policy)

    def optimise(
        self, allowed_groups: np.ndarray, policy: np.ndarray, deadline: Deadline | None = None
    ) -> tuple[float, np.ndarray, np.ndarray]:
        """Maximal reachability of the relaxation: (a proven upper bound on its optimum at the
        start, policy iteration's values, its policy). The values are floating-point
        solutions and may lie a little below the optimum; the bound
        (:meth:`MaxReachability.proven_bound`) does not. Raises :class:`DeadlineExpiredError`
        once ``deadline`` has passed."""
        penalty = np.where(allowed_groups, 0.0, -np.inf)
        if not allowed_groups[policy].all():  # the parent's choice is no longer allowed here
            fallback, _ = self.best_groups(penalty + self.live_groups)
            policy = np.where(allowed_groups[policy], policy, fallback)
        values, policy = self.mdp.optimise(policy, penalty, deadline=deadline)
        bound = self.mdp.proven_bound(values, policy, self.chain.initial, penalty, deadline)
        return bound, values, policy

    def ranked(self, i: int, remaining: float, usage: np.ndarray) -> np.ndarray:
        """Affordable candidates of observation ``i``, most used by the policy first, then
        cheapest: the order to branch in, and the greedy completion's pick."""
        first = self.first_option[i]
        costs = self.option_cost[first : self.first_option[i + 1]]
        fits = np.flatnonzero(costs <= remaining)
        return fits[np.lexsort((costs[fits], -usage[first + fits]))]

    def usage(self, policy: np.ndarray) -> np.ndarray:
        """Per option: how many live choosing states the policy's groups agree with it."""
        rows = self.group_options[policy[self.choosing]]
        return np.asarray(rows.sum(axis=0)).ravel()

    def alteration(self, picks: Sequence[int]) -> np.ndarray:
        return self.space.alteration(self.problem, picks, self.order[: len(picks)])

    def policy_of(self, picks: Sequence[int]) -> np.ndarray:
        """The group every state takes under the complete assignment ``picks``."""
        allowed = self.allowed_groups(self.allowed_options(picks, 0.0))
        return self.best_groups(np.where(allowed, 0.0, -np.inf))[0]

    def value_of(self, picks: Sequence[int]) -> float:
        """Exact value at the start of the complete assignment ``picks`` (least fixed point)."""
        return float(self.evaluate(self.policy_of(picks))[self.chain.initial])

    def picks_of(self, alteration: AlterationArray) -> tuple[int, ...] | None:
        """The search's picks for ``alteration``, None if it takes a target outside the
        space (not the cheapest of its behaviour class)."""
        picks = []
        for i in self.order:
            choice = self.space.choices[i]
            hit = np.flatnonzero(choice.targets == alteration[choice.observation])
            if hit.size == 0:
                return None
            picks.append(int(hit[0]))
        return tuple(picks)

    def cost(self, picks: Sequence[int]) -> float:
        return float(sum(self.terms(picks)))

    def terms(self, picks: Sequence[int]) -> list[float]:
        """The costs ``picks`` adds up, one per observation (``picks`` may be a prefix)."""
        pairs = zip(self.order, picks, strict=False)
        return [float(self.option_cost[self.first_option[i] + k]) for i, k in pairs]

    def fits(self, picks: Sequence[int], budget: float) -> bool:
        """Whether ``picks`` fits ``budget`` exactly (its terms decide an ambiguous sum)."""
        return self.space.scale.fits_terms(self.cost(picks), lambda: self.terms(picks), budget)


def relaxation_bound(problem: Problem, budget: float, deadline: Deadline | None = None) -> float:
    """Root bound of the search: the relaxation's optimum with every observation free; the
    objective's largest value (the trivial bound) if ``deadline`` passes first."""
    return relaxation_values(problem, budget, deadline)[0]


def relaxation_values(
    problem: Problem, budget: float, deadline: Deadline | None = None
) -> tuple[float, np.ndarray | None]:
    """:func:`relaxation_bound` and the relaxation's value of every state of the choice
    product of ``prepare(problem, budget)`` (None if ``deadline`` passes first): the MILP
    scales each state's value column by it."""
    instance = prepare(problem, budget)
    relax = PerStateRelaxation(problem, instance.space, instance.chain, instance.cycling)
    allowed = relax.allowed_groups(relax.allowed_options((), instance.space.scale.cap(budget)))
    start = relax.best_groups(relax.live_groups.astype(np.float64))[0]
    try:
        bound, values, _ = relax.optimise(allowed, start, deadline)
    except DeadlineExpiredError:
        return float(problem.objective.max_value), None
    return bound, values
