"""Branch-and-bound over observations, bounded by the MDP relaxation of the choice product.

An alteration picks one candidate per relevant observation. The search fixes them one at a
time, observations owning the most live product states first (they move the value most, so
fixing them early tightens the bounds fastest). At a node, the **relaxation** lets every product
state owned by a still-free observation take, on its own, the group of any candidate that fits
the remaining budget; states of fixed observations keep their candidate's group. Every feasible
completion of the node is one scheduler of that MDP, so its maximal reachability probability
bounds the subtree.

The bound is computed exactly by policy iteration: each policy is evaluated by
:func:`misdirect.core.reachability.reach_probabilities` (the least fixed point, so policies that
cycle forever score 0 and end components need no special care), and a state switches only on a
strict gain of more than ``IMPROVE_TOLERANCE``. Children start from their parent's policy, so a
node typically costs one or two evaluations.

Incumbent: at every node the relaxation's policy is rounded to an alteration (per free
observation, the affordable candidate its states use most, within the remaining budget) and
evaluated exactly. A subtree is pruned when its bound is at most the incumbent plus
``PRUNE_TOLERANCE`` (1e-9): values that close count as tied, as in the incremental solver's
``NEAR_TIE``, and the incumbent found first (seeded with the next smaller budget's answer, so
the cheaper one) is kept. The reported ``upper_bound`` is the largest bound of any pruned or
unexplored node, never below the incumbent.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import NotRequired, TypedDict

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from misdirect.core.alterations import AlterationSpace
from misdirect.core.attack import prepare
from misdirect.core.choice_product import ChoiceProduct
from misdirect.core.model import Alteration, Problem
from misdirect.core.reachability import reach_probabilities
from misdirect.errors import ProblemError
from misdirect.solvers.base import (
    Deadline,
    ProgressCallback,
    Solution,
    Status,
    check_threads,
    check_time_limit,
    refuse_options,
    report,
    thread_count,
)

GREEDY_TRIES = 8  # local search: candidates evaluated exactly per step
PRUNE_TOLERANCE = 1e-9  # a bound this close to the incumbent cannot beat it by more than a tie
IMPROVE_TOLERANCE = 1e-12  # policy iteration switches a state only on a larger gain
BUDGET_SLACK = 1e-9  # costs are compared to budgets with this slack everywhere in misdirect
SEGMENT_MIN_STATES = 1_000  # from this many product states, the segment search backs this one up
SEGMENT_MIN_SECONDS = 1.0  # ... when at least this much of the time limit is left
SEGMENT_SHARE = 0.95  # ... and takes this share of a budget's time (its bound is the tighter)
SEGMENT_FIRST_SECONDS = 5.0  # ... with no time limit, this one gets this long first (on H1
# budget 4 it spent 91 s reaching its node limit; where it certifies, it takes under 1 s)
SEGMENT_ENUMERATE_AT = 300_000  # it enumerates a node with at most this many completions


class BranchAndBoundStats(TypedDict):
    """``stats`` of a branch-and-bound answer (the JSON's ``stats``)."""

    nodes: int
    pruned: int
    policy_evaluations: int  # exact linear solves of the relaxation
    root_bound: float | None
    relevant_observations: int
    segment_nodes: NotRequired[int]  # when the segment search took the budget over
    segment_root_bound: NotRequired[float | None]
    segment_enumerated: NotRequired[int]  # nodes of it enumerated (low-rank updates)
    segment_enumerated_alterations: NotRequired[int]


@dataclass
class _Node:
    """A prefix of fixed candidates (``picks`` for the first ``depth`` observations)."""

    picks: tuple[int, ...]
    remaining: float
    parent_bound: float
    policy: np.ndarray  # warm start: one group per product state


class _Relaxation:
    """The choice product with the per-state MDP relaxation and exact policy evaluation."""

    def __init__(self, problem: Problem, space: AlterationSpace, chain: ChoiceProduct):
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
        self.group_start = np.flatnonzero(
            np.concatenate([[True], chain.group_state[1:] != chain.group_state[:-1]])
        )
        self.live_groups = self.live[chain.group_state]
        # live states whose group says which candidates they use (for rounding policies)
        self.choosing = self.live & (chain.groups_per_state > 1)
        self.evaluations = 0

    def allowed_options(self, picks: Sequence[int], remaining: float) -> np.ndarray:
        """Options a node permits: its fixed picks, and every affordable one of free ones."""
        allowed = self.option_cost <= remaining + BUDGET_SLACK
        for i, k in zip(self.order, picks, strict=False):
            allowed[self.first_option[i] : self.first_option[i + 1]] = False
            allowed[self.first_option[i] + k] = True
        return allowed

    def allowed_groups(self, allowed_options: np.ndarray) -> np.ndarray:
        hits = self.group_options @ allowed_options.astype(np.float64)
        return self.free_group | (np.asarray(hits).ravel() > 0)

    def best_groups(self, score: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per state: the group of highest score (the first on ties) and that score."""
        order = np.lexsort((-score, self.chain.group_state))
        best = order[self.group_start]
        return best, score[best]

    def evaluate(self, policy: np.ndarray) -> np.ndarray:
        """Exact reachability values of the chain that takes group ``policy[q]`` in ``q``."""
        self.evaluations += 1
        chain = self.chain
        return reach_probabilities(
            chain.transitions[policy], chain.target, blocks=chain.node, value=chain.target_value
        )

    def optimise(
        self, allowed_groups: np.ndarray, policy: np.ndarray
    ) -> tuple[float, np.ndarray, np.ndarray]:
        """Maximal reachability of the relaxation (value at the start, values, policy)."""
        chain = self.chain
        penalty = np.where(allowed_groups, 0.0, -np.inf)
        if not allowed_groups[policy].all():  # the parent's choice is no longer allowed here
            fallback, _ = self.best_groups(penalty + self.live_groups)
            policy = np.where(allowed_groups[policy], policy, fallback)
        while True:
            values = self.evaluate(policy)
            score = chain.transitions @ values + penalty
            best, best_score = self.best_groups(score)
            switch = self.live & (best_score > score[policy] + IMPROVE_TOLERANCE)
            if not switch.any():
                return float(values[chain.initial]), values, policy
            policy = np.where(switch, best, policy)

    def ranked(self, i: int, remaining: float, usage: np.ndarray) -> np.ndarray:
        """Affordable candidates of observation ``i``, most used by the policy first, then
        cheapest: the order to branch in, and the greedy completion's pick."""
        first = self.first_option[i]
        costs = self.option_cost[first : self.first_option[i + 1]]
        fits = np.flatnonzero(costs <= remaining + BUDGET_SLACK)
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

    def improve(
        self,
        picks: tuple[int, ...],
        value: float,
        budget: float,
        deadline: Deadline | None = None,
        tries: int = GREEDY_TRIES,
    ) -> tuple[tuple[int, ...], float]:
        """Hill-climb from ``picks`` by changing one observation at a time within ``budget``.

        Candidates are ranked by a first-order estimate of their gain (the expected visits of
        the states they change times the one-step advantage of their group under the current
        values), and only the ``tries`` best are evaluated exactly: a good incumbent early,
        for the pruning and for answers cut short by the time limit.
        """
        chain, live = self.chain, self.live
        inner = np.flatnonzero(live)
        if inner.size == 0 or not self.order:
            return picks, value
        position = np.full(chain.n_states, -1)
        position[inner] = np.arange(inner.size)
        state_obs = self.problem.pomdp.observation_of[chain.world_state]
        while deadline is None or not deadline.expired():
            policy = self.policy_of(picks)
            values = self.evaluate(policy)
            block = chain.transitions[policy[inner]][:, inner].tocsc()
            system = (sp.identity(inner.size, format="csc") - block).T.tocsc()
            if not live[chain.initial]:
                return picks, value
            start = np.zeros(inner.size)
            start[position[chain.initial]] = 1.0
            try:
                visits = spla.splu(system).solve(start)
            except RuntimeError:  # singular: the chain cycles without reaching the decoy
                return picks, value
            score = np.asarray(chain.transitions @ values).ravel()
            spent = self.cost(picks)
            moves = []
            for position_in_order, i in enumerate(self.order):
                first = self.first_option[i]
                costs = self.option_cost[first : self.first_option[i + 1]]
                current = picks[position_in_order]
                owned = inner[state_obs[inner] == self.space.choices[i].observation]
                for k in np.flatnonzero(spent - costs[current] + costs <= budget + BUDGET_SLACK):
                    if k == current:
                        continue
                    groups = chain.group_of_option[owned, first + k]
                    gain = visits[position[owned]] @ (score[groups] - values[owned])
                    moves.append((float(gain), position_in_order, int(k)))
            moves.sort(reverse=True)
            best = (value, picks)
            for gain, j, k in moves[:tries]:
                if gain <= 0:
                    break
                candidate = (*picks[:j], k, *picks[j + 1 :])
                found = float(self.evaluate(self.policy_of(candidate))[chain.initial])
                if found > best[0] + PRUNE_TOLERANCE:
                    best = (found, candidate)
            if best[1] is picks:
                return picks, value
            value, picks = best
        return picks, value

    def picks_of(self, alteration: Alteration) -> tuple[int, ...] | None:
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
        pairs = zip(self.order, picks, strict=False)  # ``picks`` may be a prefix
        return float(sum(self.option_cost[self.first_option[i] + k] for i, k in pairs))


class BranchAndBoundSolver:
    """Exact optimum by branch-and-bound; see the module docstring."""

    name = "branch-and-bound"
    curve_is_free = False

    def __init__(
        self,
        max_nodes: int = 20_000,
        time_limit: float | None = None,
        threads: int | None = None,
        **options: object,
    ):
        refuse_options(self.name, options, accepted=("time_limit", "threads"))
        check_time_limit(time_limit)
        if max_nodes < 1:
            raise ProblemError(f"must be at least 1, got {max_nodes}", field="max_nodes")
        check_threads(threads)
        self.max_nodes = max_nodes
        self.time_limit = time_limit
        self.threads = threads  # the segment search's workers (default: incremental's)

    def workers(self) -> int:
        """Threads of the segment search: ``threads``, else both cores."""
        from misdirect.solvers.incremental import THREADS

        return thread_count(self.threads, THREADS)

    def solve(
        self,
        problem: Problem,
        budgets: Sequence[float],
        *,
        progress: ProgressCallback | None = None,
        deadline: Deadline | None = None,
        seeds: Sequence[Alteration | None] | None = None,
    ) -> list[Solution]:
        """``seeds`` (one per budget, optional): known good alterations, e.g. a MILP's
        incumbents, that the search starts from."""
        deadline = deadline or Deadline(self.time_limit)
        top = max(budgets)
        instance = prepare(problem, top)
        space, chain = instance.space, instance.chain
        relax = _Relaxation(problem, space, chain)
        order = sorted(range(len(budgets)), key=lambda j: budgets[j])
        # the segment search backs a budget up where this search does not certify it: on
        # large chains without end components among the live states (its policy iteration
        # needs none), built only when first needed
        segment_applies = chain.n_states >= SEGMENT_MIN_STATES and not instance.cycling.any()
        segments = None
        policy = relax.best_groups(relax.live_groups.astype(np.float64))[0]
        incumbent: tuple[tuple[int, ...], float] | None = None
        answers: dict[int, Solution] = {}
        # once this search fails a budget the segment search had to take, it fails the larger
        # ones too (its bound only loosens with the budget): they go to the segment search at
        # once (H1 budget 5: 2.4 s of 119 nodes that never certify)
        per_state_failed = False
        for done, j in enumerate(order):
            budget = float(budgets[j])
            search = _Search(relax, budget, self.max_nodes, incumbent, policy)
            seed = None if seeds is None else seeds[j]
            picks = None if seed is None else relax.picks_of(seed)
            if picks is not None and relax.cost(picks) <= budget + BUDGET_SLACK:
                search.offer(picks, search.value(picks))
            # a good incumbent before the search: the previous budget's, improved locally
            if search.best_value < 0:
                search.offer(search.best_picks, search.value(search.best_picks))
            share = deadline.share(len(order) - done)
            climb = None if share is None else Deadline(share / 4)
            better, found = relax.improve(search.best_picks, search.best_value, budget, climb)
            search.offer(better, found)
            share = deadline.front_share(len(order) - done)
            if segment_applies:  # the rest for the segment search, if this one fails
                share = SEGMENT_FIRST_SECONDS if share is None else share * (1 - SEGMENT_SHARE)
                if per_state_failed:
                    share = 0.0
            limit = None if share is None else Deadline(share)

            def tick(search=search, budget=budget, done=done) -> None:
                report(
                    progress,
                    done,
                    len(order),
                    stage=f"branch-and-bound, budget {budget:g}",
                    detail=search.describe(),
                )

            answers[j] = search.run(limit, tick)
            left = deadline.remaining()
            if left is not None and left < SEGMENT_MIN_SECONDS:
                segment_applies = False  # too little time left to build and search it
            if answers[j].status != Status.OPTIMAL and segment_applies and segments is None:
                from misdirect.solvers.budget_bound import SegmentRelaxation

                segments = SegmentRelaxation(
                    problem,
                    space,
                    chain,
                    relax,
                    instance,
                    threads=1,  # one per worker
                )
            if answers[j].status != Status.OPTIMAL and segments is not None:
                per_state_failed = True
                answers[j] = _segment_phase(
                    segments,
                    relax,
                    search,
                    answers[j],
                    budget,
                    deadline,
                    len(order) - done,
                    self.max_nodes,
                    progress,
                    done,
                    len(order),
                    self.workers(),
                )
            incumbent, policy = (search.best_picks, search.best_value), search.root_policy
            report(progress, done + 1, len(order), stage="branch-and-bound")
        return [answers[j] for j in range(len(budgets))]


def _segment_phase(
    segments,
    relax,
    search,
    answer,
    budget,
    deadline,
    left,
    max_nodes,
    progress,
    done,
    total,
    workers,
):
    """Continue a budget the per-state search did not certify with the segment search
    (:mod:`misdirect.solvers.budget_bound`), from its incumbent; keep the better answer and
    the smaller of the two proven bounds."""
    from misdirect.solvers.budget_bound import SegmentSearch

    second = SegmentSearch(
        segments, budget, seeds=[search.best_picks], enumerate_at=SEGMENT_ENUMERATE_AT
    )
    share = deadline.front_share(left)
    limit = None if share is None else Deadline(share)

    def tick() -> None:
        report(
            progress,
            done,
            total,
            stage=f"segment search, budget {budget:g}",
            detail=f"incumbent {second.best_value:.6f}, bound {second.open_bound():.6f}"
            f", {second.nodes:,} nodes, {second.enumerated:,} enumerated",
        )

    status = second.run(limit, tick, max_nodes=max_nodes, workers=workers)
    search.offer(second.best_picks, second.best_value)  # carried to the next budget
    value = max(second.best_value, answer.solver_probability)
    picks = second.best_picks if second.best_value > answer.solver_probability else None
    bound = max(min(second.open_bound(), answer.upper_bound), value)
    proven = status == "optimal" or bound - value <= PRUNE_TOLERANCE
    stats: BranchAndBoundStats = {
        **answer.stats,
        "segment_nodes": second.nodes,
        "segment_root_bound": second.root_bound,
        "segment_enumerated": second.enumerated,
        "segment_enumerated_alterations": second.enumerated_alterations,
    }
    return Solution(
        budget=answer.budget,
        alteration=answer.alteration if picks is None else relax.alteration(picks),
        solver_probability=value,
        status=Status.OPTIMAL if proven else answer.status,
        upper_bound=value if status == "optimal" else bound,
        stats=stats,
    )


class _Search:
    """Depth-first branch-and-bound for one budget."""

    def __init__(
        self,
        relax: _Relaxation,
        budget: float,
        max_nodes: int,
        seed: tuple[tuple[int, ...], float] | None,
        policy: np.ndarray,
    ):
        self.relax, self.budget, self.max_nodes = relax, budget, max_nodes
        depth = len(relax.order)
        self.best_picks: tuple[int, ...] = (0,) * depth
        self.best_value = -1.0
        self.best_cost = 0.0
        self.evaluated: dict[tuple[int, ...], float] = {}
        if seed is not None:  # the smaller budget's answer stays feasible
            self.offer(seed[0], seed[1])
        self.root_policy = policy
        self.stack = [_Node((), budget, np.inf, policy)]
        self.nodes = self.pruned = 0
        self.pruned_bound = -np.inf  # largest bound of any pruned subtree
        self.root_bound: float | None = None
        self.evaluations_before = relax.evaluations

    def offer(self, picks: tuple[int, ...], value: float) -> None:
        """Keep ``picks`` if clearly better, or tied within the tolerance and cheaper."""
        cost = self.relax.cost(picks)
        better = value > self.best_value + PRUNE_TOLERANCE
        tied_cheaper = value >= self.best_value - PRUNE_TOLERANCE and cost < self.best_cost - 1e-12
        if better or tied_cheaper:
            self.best_picks, self.best_value, self.best_cost = picks, value, cost

    def value(self, picks: tuple[int, ...]) -> float:
        """Exact value of a complete assignment (the chain of its groups, least fixed point)."""
        if picks not in self.evaluated:
            relax = self.relax
            allowed = relax.allowed_groups(relax.allowed_options(picks, 0.0))
            policy, _ = relax.best_groups(np.where(allowed, 0.0, -np.inf))
            values = relax.evaluate(policy)
            self.evaluated[picks] = float(values[relax.chain.initial])
        return self.evaluated[picks]

    def _prune(self, bound: float) -> bool:
        if bound <= self.best_value + PRUNE_TOLERANCE:
            self.pruned += 1
            self.pruned_bound = max(self.pruned_bound, bound)
            return True
        return False

    def describe(self) -> str:
        bound = self.open_bound()
        return (
            f"incumbent {self.best_value:.6f}, bound {bound:.6f}, gap {bound - self.best_value:.2e}"
            f", {self.nodes:,} nodes"
        )

    def open_bound(self) -> float:
        open_bound = max((n.parent_bound for n in self.stack), default=-np.inf)
        top = self.relax.problem.objective.max_value
        return float(min(max(self.best_value, self.pruned_bound, open_bound), top))

    def run(self, deadline: Deadline | None = None, tick=None) -> Solution:
        relax = self.relax
        depth = len(relax.order)
        if self.best_value < 0:
            self.offer(self.best_picks, self.value(self.best_picks))
        while self.stack:
            if self.nodes >= self.max_nodes:
                return self._solution(Status.FEASIBLE)
            if deadline is not None and deadline.expired():
                return self._solution(Status.TIME_LIMIT)
            if tick is not None and self.nodes % 64 == 0:
                tick()
            node = self.stack.pop()
            if self._prune(node.parent_bound):
                continue
            self.nodes += 1
            allowed = relax.allowed_groups(relax.allowed_options(node.picks, node.remaining))
            bound, _, policy = relax.optimise(allowed, node.policy.copy())
            if self.root_bound is None:
                self.root_bound, self.root_policy = bound, policy
            level = len(node.picks)
            if level == depth:  # every observation fixed: the relaxation is the chain itself
                self.offer(node.picks, bound)
                continue
            usage = relax.usage(policy)
            rounded = self._round(node.picks, node.remaining, usage)
            self.offer(rounded, self.value(rounded))
            if self._prune(bound):
                continue
            i = relax.order[level]
            costs = relax.option_cost[relax.first_option[i] : relax.first_option[i + 1]]
            preferred = relax.ranked(i, node.remaining, usage)
            for k in preferred[::-1]:  # the stack pops the preferred candidate first
                self.stack.append(
                    _Node(
                        (*node.picks, int(k)),
                        node.remaining - float(costs[k]),
                        bound,
                        policy,
                    )
                )
        return self._solution(Status.OPTIMAL)

    def _round(self, picks: tuple[int, ...], remaining: float, usage: np.ndarray) -> tuple:
        """Complete ``picks`` greedily: each free observation's most used affordable candidate."""
        relax = self.relax
        completed = list(picks)
        for i in relax.order[len(picks) :]:
            k = int(relax.ranked(i, remaining, usage)[0])
            completed.append(k)
            remaining -= float(relax.option_cost[relax.first_option[i] + k])
        return tuple(completed)

    def _solution(self, status: str) -> Solution:
        bound = self.open_bound()
        stats: BranchAndBoundStats = {
            "nodes": self.nodes,
            "pruned": self.pruned,
            "policy_evaluations": self.relax.evaluations - self.evaluations_before,
            "root_bound": self.root_bound,
            "relevant_observations": len(self.relax.order),
        }
        return Solution(
            budget=self.budget,
            alteration=self.relax.alteration(self.best_picks),
            solver_probability=self.best_value,
            status=status,
            upper_bound=bound,
            stats=stats,
        )


def relaxation_bound(problem: Problem, budget: float) -> float:
    """Root bound of the search: the relaxation's optimum with every observation free."""
    instance = prepare(problem, budget)
    relax = _Relaxation(problem, instance.space, instance.chain)
    allowed = relax.allowed_groups(relax.allowed_options((), budget))
    start = relax.best_groups(relax.live_groups.astype(np.float64))[0]
    return relax.optimise(allowed, start)[0]
