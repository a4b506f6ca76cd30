"""``--method branch-and-bound``: depth-first over observations, bounded by the per-state
relaxation, backed up by the segment search on large chains.

An alteration picks one candidate per relevant observation. The search fixes them one at a
time, observations owning the most live product states first (they move the value most, so
fixing them early tightens the bounds fastest); each node's bound is the per-state relaxation
(:mod:`misdirect.solvers.engines.per_state`), solved from its parent's policy, so a node
typically costs one or two evaluations.

Incumbent: at every node the relaxation's policy is rounded to an alteration (per free
observation, the affordable candidate its states use most, within the remaining budget) and
evaluated exactly; a hill climb improves the previous budget's answer before each search.
Pruning and the proven bound are the shared bookkeeping of
:mod:`misdirect.solvers.engines.incumbent`.

Where this search does not certify a budget of a large chain without end components (and
without a monitor), the segment search (:mod:`misdirect.solvers.engines.segment_search`)
takes it over from its incumbent; the two bounds are both proven, and the smaller one is
reported. How time is shared between them is :mod:`misdirect.solvers.schedule`'s.

Budgets go smallest first, except where the curve levels off: once two budgets in a row are
certified at the same value, the largest budget is solved next. If it is certified at that
value too, every budget between is proven by it (its optimum lies between the two), without a
search of its own; a larger budget's tree is often no bigger than a smaller one's.
"""

from __future__ import annotations

import time
import uuid
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import Any, ClassVar

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from misdirect.core import tolerance
from misdirect.core.attack import AttackInstance, prepare
from misdirect.core.blas import one_blas_thread
from misdirect.core.model import AlterationArray, Problem, reachable_from
from misdirect.core.reachability import reach_probability_bounded
from misdirect.errors import OptionError
from misdirect.solvers import schedule
from misdirect.solvers.base import ProgressCallback, Solution, method_deadline, report, thread_count
from misdirect.solvers.certification import exact_values
from misdirect.solvers.deadline import Deadline, DeadlineExpiredError
from misdirect.solvers.engines.alarm import AlarmConstraint, Verdict, alarm_constraint
from misdirect.solvers.engines.covering import CoverRule, covering_bound
from misdirect.solvers.engines.incumbent import Incumbent, IncumbentSearch, Picks
from misdirect.solvers.engines.lagrangian import LagrangianBound, lagrangian_bound
from misdirect.solvers.engines.per_state import PerStateRelaxation
from misdirect.solvers.engines.segment_relaxation import SegmentRelaxation
from misdirect.solvers.engines.segment_search import SegmentSearch
from misdirect.solvers.engines.subtrees import DistributedSegmentSearch
from misdirect.solvers.options import SolveOptions
from misdirect.solvers.stats import BranchAndBoundStats, SegmentStats
from misdirect.solvers.status import Status, StopReason

GREEDY_TRIES = 8  # local search: candidates evaluated exactly per step
SEGMENT_MIN_STATES = 1_000  # from this many product states, the segment search backs this one up
SEGMENT_ENUMERATE_AT = 300_000  # it enumerates a node with at most this many completions
# max_alarm: the multipliers λ of the Lagrangian node bound (engines.lagrangian); empty: off.
# Measured on the paper grid under the consistency monitor, (100.0,) pruned 41 % of the nodes
# at δ = 0 and the curves still took longer (docs/benchmarks.md, "Stealth")
LAGRANGE_MULTIPLIERS: tuple[float, ...] = ()
# node relaxations kept for the other budgets and δ of a curve, at most this many bytes of
# policies (one group per product state: 11 kB each on the 1,367-state monitored paper grid,
# so about 6,000 of them; a chain of 10^6 states keeps 8)
KNOWN_BYTES = 64 * 2**20
# a union's relaxation on a kept basis, against a node bound on the whole chain: the first
# cover's estimate, on the safe side (0.027 on the 64-sensor turn-back grid, 27 ms against
# 1.0 s; above 1 on a 12x12 one, whose whole chain solves in a few ms); every later cover of
# the search uses what the last one measured
KEPT_BASIS_SHARE = 0.5
# a cover given up is tried once more at the same node where the time per union it measured
# pays for finer groups (smaller unions: fewer of them at the largest value)
COVER_TRIES = 2


@dataclass
class _Curve:
    """What one budget of a curve hands the next (budgets go smallest first)."""

    instance: AttackInstance
    relax: PerStateRelaxation
    policy: np.ndarray  # the last root policy: the next search starts from it
    incumbent: tuple[Picks, float] | None = None  # feasible at every larger budget
    segment_backs_up: bool = False
    segments: SegmentRelaxation | None = None  # built when first needed
    max_budget: float = 0.0  # the budget ``instance`` was prepared for
    shared_problem: object = None  # the problem as the pool's tasks receive it
    key: str = field(default_factory=lambda: uuid.uuid4().hex)  # names it on the workers
    # once the per-state search fails a budget the segment search had to take, it fails the
    # larger ones too (its bound only loosens with the budget): they go to the segment search
    per_state_failed: bool = False
    # a segment search's root bound that holds at every budget (see ``note_segment_root``)
    every_budget_bound: float = np.inf
    # max_alarm: an alteration's verdict (by its picks); None: unconstrained
    accept: Callable[[Picks], Verdict] | None = None
    # max_alarm: whether a node's fixed picks raise the alarm above δ whatever the rest
    caught: Callable[[Picks], bool] | None = None
    # max_alarm: the Lagrangian node bound (engines.lagrangian), where LAGRANGE_MULTIPLIERS asks
    lagrangian: LagrangianBound | None = None
    # the node relaxations solved (``_Search._relaxed``): every budget's, and under max_alarm
    # every δ's of a trade-off curve (the constraint's memo)
    known: dict[bytes, tuple[float, float, np.ndarray]] = field(default_factory=dict)
    # exact values of complete assignments (the incumbents' roundings), likewise shared
    values: dict[Picks, float] = field(default_factory=dict)

    def note_segment_root(self, bound: float | None, budget: float) -> None:
        """Keep a segment search's root bound if it holds at every budget: the segment MDP at
        its root offers every option it can afford, and nothing else depends on the budget
        (the search charges nothing), so where every option fitted ``budget`` every alteration
        of any budget is one of its schedulers."""
        if bound is None:
            return
        cap = self.instance.space.scale.cap(budget)
        if all(float(c.costs.max(initial=0.0)) <= cap for c in self.instance.space.choices):
            self.every_budget_bound = min(self.every_budget_bound, float(bound))

    def bounded(self, answer: Solution) -> Solution:
        """``answer`` with its bound lowered to ``every_budget_bound`` where that is tighter
        (a budget the time limit cut before its own search, say, keeps a bound below 1)."""
        if (
            answer.status == Status.OPTIMAL
            or answer.upper_bound is None
            or answer.solver_probability is None
            or not answer.upper_bound > self.every_budget_bound
        ):
            return answer
        bound = max(self.every_budget_bound, answer.solver_probability)
        return replace(answer, upper_bound=bound)


@dataclass(frozen=True)
class _Budget:
    """One budget of the curve, and where it stands in it."""

    budget: float
    done: int  # budgets already solved
    total: int
    seed: AlterationArray | None = field(default=None, repr=False)

    @property
    def left(self) -> int:
        return self.total - self.done


class BranchAndBoundSolver:
    """Exact optimum by branch-and-bound; see the module docstring."""

    name: ClassVar[str] = "branch-and-bound"
    curve_is_free: ClassVar[bool] = False
    accepts: ClassVar[tuple[str, ...]] = ("time_limit", "threads", "pool", "max_alarm")

    def __init__(self, options: SolveOptions | None = None, *, max_nodes: int = 20_000):
        if max_nodes < 1:
            raise OptionError(f"must be at least 1, got {max_nodes}", parameter="max_nodes")
        self.options = options or SolveOptions()
        self.max_nodes = max_nodes

    def workers(self) -> int:
        """Threads of the segment search and processes of a cover: ``threads``, else both
        cores."""
        return thread_count(self.options.threads)

    def solve(
        self,
        problem: Problem,
        budgets: Sequence[float],
        *,
        progress: ProgressCallback | None = None,
        deadline: Deadline | None = None,
        seeds: Sequence[AlterationArray | None] | None = None,
        below: Solution | None = None,
    ) -> list[Solution]:
        """``seeds`` (one per budget, optional): known good alterations, e.g. a MILP's
        incumbents, that the search starts from. ``below``: a certified answer of a smaller
        budget (an earlier stage's), the first incumbent; where no seed beats it, the curve
        may have levelled off there, and the largest budget is solved first (see the module
        docstring)."""
        deadline = method_deadline(deadline, self.options.time_limit)
        constraint = None
        if self.options.max_alarm is not None:  # δ = 1 too: the per-state search alone
            # the decoy's value on the space of both values (engines.alarm); the incumbent
            # keeps only alterations proven feasible, and the relaxation's bound (of the
            # unconstrained problem) bounds the constrained one too
            constraint = alarm_constraint(problem, self.options.max_alarm)
            problem = constraint.decoy_problem
        instance = prepare(problem, max(budgets))
        report(progress, 0, 0, stage="bounds")  # the relaxation the search bounds with
        relax = PerStateRelaxation(problem, instance.space, instance.chain, instance.cycling)
        accept = None if constraint is None else _feasibility(constraint, relax)
        # a node whose fixed picks already raise the alarm too often is pruned
        caught = (
            None
            if constraint is None or constraint.trivial
            else _caught(relax, constraint.limit, _floors(constraint, relax))
        )
        curve = _Curve(
            instance,
            relax,
            policy=relax.best_groups(relax.live_groups.astype(np.float64))[0],
            # the segment search backs a budget up on large chains, not on monitored ones (their
            # product states are many copies of few world states: on the paper grid with the
            # consistency monitor the per-state search certifies budget 4 in a few seconds,
            # the segment search took 30 s; docs/benchmarks.md, "Stealth"); with a pool,
            # every budget goes to the (distributed) segment search
            segment_backs_up=accept is None
            and (
                (instance.chain.n_states >= SEGMENT_MIN_STATES and not problem.monitor)
                or self.options.pool is not None
            ),
            max_budget=max(budgets),
            accept=accept,
            caught=caught,
            lagrangian=None
            if constraint is None or caught is None or not LAGRANGE_MULTIPLIERS
            else lagrangian_bound(relax, instance.cycling, constraint.limit, LAGRANGE_MULTIPLIERS),
        )
        if constraint is not None:  # every δ of a trade-off curve bounds the same nodes
            curve.known = _memo(constraint, relax, "node relaxations")
            curve.values = _memo(constraint, relax, "exact values")
        if below is not None and below.alteration is not None:
            picks = relax.picks_of(below.alteration)  # feasible at every larger budget
            if picks is not None:
                curve.incumbent = (picks, relax.value_of(picks))
        if self.options.pool is not None:
            curve.shared_problem = self.options.pool.share(problem)
        pending = sorted(range(len(budgets)), key=lambda j: budgets[j])
        answers: dict[int, Solution] = {}
        last = below  # the last budget solved in order

        def solve(j: int) -> Solution:
            seed = None if seeds is None else seeds[j]
            step = _Budget(float(budgets[j]), len(answers), len(budgets), seed)
            answers[j] = self._solve_budget(curve, step, deadline, progress)
            report(progress, len(answers), len(budgets), stage="branch-and-bound")
            return answers[j]

        if last is not None and len(pending) >= 2 and _no_seed_beats(problem, last, seeds):
            self._jump_to_top(curve, last, pending, budgets, answers, solve)
        while pending:
            answer = solve(pending.pop(0))
            if len(pending) >= 2 and last is not None and _level(last, answer):
                self._jump_to_top(curve, answer, pending, budgets, answers, solve)
            last = answer
        return [answers[j] for j in range(len(budgets))]

    @staticmethod
    def _jump_to_top(
        curve: _Curve,
        level: Solution,
        pending: list[int],
        budgets: Sequence[float],
        answers: dict[int, Solution],
        solve: Callable[[int], Solution],
    ) -> None:
        """The curve levelled off at ``level``'s value: solve the largest budget left next;
        if it is certified at that value, every budget ``pending`` between is proven by it
        (taken out of ``pending``, with ``level``'s alteration and the top's bound)."""
        kept = curve.incumbent  # the top's answer may not fit the budgets between
        top = solve(pending.pop())
        curve.incumbent = kept
        if not _level(level, top):
            return
        assert top.upper_bound is not None and level.solver_probability is not None
        bound = max(top.upper_bound, level.solver_probability)
        for j in pending:
            answers[j] = replace(level, budget=float(budgets[j]), upper_bound=bound)
        pending.clear()

    def _solve_budget(
        self, curve: _Curve, step: _Budget, deadline: Deadline, progress: ProgressCallback | None
    ) -> Solution:
        relax, budget = curve.relax, step.budget
        # with a pool, the per-state search bounds its root only: the pool takes the rest
        nodes = 1 if self.options.pool is not None and curve.accept is None else self.max_nodes
        search = _Search(
            relax, budget, nodes, curve.incumbent, curve.policy, curve.accept, values=curve.values
        )
        search.caught = curve.caught
        search.lagrangian = curve.lagrangian
        search.known = curve.known
        if CoverRule.applies(bool(curve.instance.cycling.any())):
            search.cover_with(CoverRule(workers=self.workers()), _strengths(curve))
        picks = None if step.seed is None else relax.picks_of(step.seed)
        if picks is not None and relax.fits(picks, budget):
            search.incumbent.offer_exact(picks)
        # a good incumbent before the search: the previous budget's, improved locally
        if search.best_value < 0:
            search.incumbent.offer_exact(search.best_picks)
        climb = schedule.climb(deadline, step.left)
        climbed = (search.best_picks, search.best_value)
        if curve.incumbent is None:  # no smaller budget's answer to start from: greedy first
            climbed = _hill_climb(relax, *climbed, budget, climb, first_improvement=True)
        climbed = _hill_climb(relax, *climbed, budget, climb)
        search.incumbent.offer(*climbed)
        limit = schedule.per_state_search(
            deadline,
            step.left,
            segment_backs_up=curve.segment_backs_up,
            per_state_failed=curve.per_state_failed,
        )

        def tick() -> None:
            stage = f"branch-and-bound, budget {budget:g}"
            report(progress, step.done, step.total, stage=stage, detail=search.describe())

        # its dense solves are small (the dense path of chains of at most a few hundred
        # states, e.g. ``_caught``'s): OpenBLAS's threads stalled one of 189 states for 0.1 s
        # on the shared 2-core machine, against 1 ms on one (docs/benchmarks.md, "Stealth")
        with one_blas_thread():
            answer = search.run(limit, tick)
        # how the per-state search stopped: finished, its node limit, or its time
        answer = replace(answer, stop_reason=StopReason.of(answer.status, deadline.cancelled))
        if not schedule.segment_has_time(deadline):
            curve.segment_backs_up = False  # too little time left to build and search it
        if answer.status != Status.OPTIMAL and curve.segment_backs_up and curve.segments is None:
            curve.segments = SegmentRelaxation(curve.instance, relax, threads=1)  # one a worker
        if answer.status != Status.OPTIMAL and curve.segments is not None:
            curve.per_state_failed = True
            answer = self._segment_phase(curve, search, answer, step, deadline, progress)
        if search.best_value >= 0:  # under max_alarm, none may be feasible
            curve.incumbent = (search.best_picks, search.best_value)
        curve.policy = search.root_policy
        answer = curve.bounded(answer)
        if curve.accept is not None and search.best_value < 0:
            answer = _none_feasible(answer, search, relax)
        if answer.status != Status.OPTIMAL and _budget_blind(answer, curve.instance):
            answer.notes["trivial_bound"] = (
                f"no budget-aware bound on this chain: {int(curve.instance.cycling.sum()):,} "
                "live product states lie in end components (the robot can circle back), where "
                "the relaxations cannot charge for the budget; only enumerating a budget "
                "proves it"
            )
        return answer

    def _segment_phase(
        self,
        curve: _Curve,
        search: _Search,
        answer: Solution,
        step: _Budget,
        deadline: Deadline,
        progress: ProgressCallback | None,
    ) -> Solution:
        """Continue a budget the per-state search did not certify with the segment search,
        from its incumbent; keep the better answer and the smaller of the two proven bounds."""
        segments = curve.segments
        assert segments is not None
        second: SegmentSearch | DistributedSegmentSearch
        if self.options.pool is None:
            second = SegmentSearch(
                segments, step.budget, seeds=[search.best_picks], enumerate_at=SEGMENT_ENUMERATE_AT
            )
        else:
            second = DistributedSegmentSearch(
                segments,
                step.budget,
                self.options.pool,
                problem=curve.shared_problem,
                key=curve.key,
                max_budget=curve.max_budget,
                seeds=[search.best_picks],
                enumerate_at=SEGMENT_ENUMERATE_AT,
            )

        def tick() -> None:
            report(
                progress,
                step.done,
                step.total,
                stage=f"segment search, budget {step.budget:g}",
                detail=f"incumbent {second.best_value:.6f}, bound {second.open_bound():.6f}"
                f", {second.nodes:,} nodes, {second.enumerated:,} enumerated",
            )

        status = second.run(
            schedule.segment_search(deadline, step.left),
            tick,
            max_nodes=self.max_nodes,
            workers=self.workers(),
        )
        search.incumbent.offer(second.best_picks, second.best_value)  # carried to the next budget
        curve.note_segment_root(second.root_bound, step.budget)
        claimed = answer.solver_probability
        assert claimed is not None, "the per-state search always has an incumbent"
        value = max(second.best_value, claimed)
        picks = second.best_picks if second.best_value > claimed else None
        assert answer.upper_bound is not None
        bound = max(min(second.open_bound(), answer.upper_bound), value)
        finished = status == Status.OPTIMAL
        assert isinstance(answer.stats, BranchAndBoundStats)
        segment = SegmentStats(
            nodes=second.nodes,
            root_bound=second.root_bound,
            enumerated=second.enumerated,
            enumerated_alterations=second.enumerated_alterations,
        )
        stats = replace(answer.stats, segment=segment)
        return Solution(
            budget=answer.budget,
            alteration=answer.alteration if picks is None else segments.relax.alteration(picks),
            solver_probability=value,
            status=Status.OPTIMAL if finished else answer.status,
            # finished too: what it pruned or enumerated as a tie may lie a tie above ``value``
            upper_bound=bound,
            stats=stats,
            stop_reason=StopReason.of(status, deadline.cancelled),  # the segment search's stop
        )


def _feasibility(
    constraint: AlarmConstraint, relax: PerStateRelaxation
) -> Callable[[Picks], Verdict]:
    """An incumbent's test under ``max_alarm``: the verdict of the picks' alteration."""

    def verdict(picks: Picks) -> Verdict:
        return constraint.verdict(relax.alteration(picks))

    return verdict


def _caught(
    relax: PerStateRelaxation, limit: float, floors: dict[Picks, tuple[bool, float | None]]
) -> Callable[[Picks], bool]:
    """Under ``max_alarm`` (δ = ``limit``): whether the picks fixed so far (a prefix of
    ``relax.order``) already raise the alarm with probability above δ, whatever the free
    choices take. The states whose rows the prefix decides (one group each: its options'
    groups, and the states with no choice) form a chain in which a free choice's states end
    the run (scoring 0); a run of it that reaches the sink is a run of every completion, so
    its Pr(sink) is a lower bound on every completion's Pr(alarm). δ = 0: the sink reachable
    in its graph; δ > 0: its value less its proven error above δ. Then the subtree holds no
    feasible alteration.

    ``floors`` keeps, per prefix, whether its chain reaches the sink and its proven floor
    (None until a δ > 0 asks for it): they depend on neither the budget nor δ, and the same
    prefixes come back at every budget and every δ of a curve."""
    chain = relax.chain
    problem = relax.problem
    assert problem.alarm_state is not None
    sink = chain.world_state == problem.alarm_state
    stop = chain.target  # the decoys and the sink (the decoy problem's stopping states)
    n = chain.n_states
    rows = chain.transitions.tocoo()  # every group's row, once: a node masks them
    row_owner = chain.group_state[rows.row]
    row_kept = ~stop[row_owner]

    def floor(picks: Picks, value: bool) -> tuple[bool, float | None]:
        options = np.zeros(relax.option_cost.size, dtype=bool)
        for i, k in zip(relax.order, picks, strict=False):
            options[relax.first_option[i] + k] = True
        decided = relax.allowed_groups(options)[rows.row] & row_kept
        owner, col, data = row_owner[decided], rows.col[decided], rows.data[decided]
        graph = sp.csr_matrix((np.ones(owner.size), (owner, col)), shape=(n, n))
        seen = reachable_from(graph, np.array([chain.initial]))
        if not (seen & sink).any():
            return False, 0.0  # an unreachable sink bounds nothing
        if not value:
            return True, None  # reachable: exactly what δ = 0 asks
        # the chain on the states the start reaches (closed under its moves: the same values
        # there), numbered in place: a node's decided part is often a small share of the
        # chain, and the solve costs by its size
        place = np.full(n, -1, dtype=np.int64)
        kept = np.flatnonzero(seen)
        place[kept] = np.arange(kept.size)
        inside = seen[owner]
        ended = seen.copy()  # undecided and stopping states: a self-loop each
        ended[owner] = False
        loops = place[np.flatnonzero(ended)]
        matrix = sp.csr_matrix(
            (
                np.concatenate([data[inside], np.ones(loops.size)]),
                (
                    np.concatenate([place[owner[inside]], loops]),
                    np.concatenate([place[col[inside]], loops]),
                ),
            ),
            shape=(kept.size, kept.size),
        )
        found = reach_probability_bounded(matrix, sink[kept], int(place[chain.initial]))
        return True, float(found.value - found.error)

    def caught(picks: Picks) -> bool:
        known = floors.get(picks)
        if known is None or (known[1] is None and limit > 0.0):
            known = floors[picks] = floor(picks, limit > 0.0)
        reached, lowest = known
        if limit == 0.0 or not reached:
            return reached
        assert lowest is not None
        return lowest > limit

    return caught


def _floors(
    constraint: AlarmConstraint, relax: PerStateRelaxation
) -> dict[Picks, tuple[bool, float | None]]:
    """The alarm floors of :func:`_caught`, shared by every budget of this solve and every δ
    of a trade-off curve."""
    return _memo(constraint, relax, "caught floors")


def _memo(constraint: AlarmConstraint, relax: PerStateRelaxation, name: str) -> dict[Any, Any]:
    """A table ``name`` in the constraint's memo, which every δ of a trade-off curve shares,
    per alteration space and order (a prefix's picks and a node's groups index both)."""
    space = relax.space
    key = (
        name,
        tuple(relax.order),
        relax.option_cost.tobytes(),
        tuple((c.observation, c.targets.tobytes()) for c in space.choices),
    )
    table = constraint.memo.setdefault(key, {})
    assert isinstance(table, dict)
    return table


def _none_feasible(answer: Solution, search: _Search, relax: PerStateRelaxation) -> Solution:
    """A budget whose search kept no feasible alteration: ``infeasible`` where it finished and
    no verdict was undecided, else open at its bound with no answer."""
    proven = answer.status == Status.OPTIMAL and search.incumbent.undecided < 0
    return replace(
        answer,
        alteration=relax.alteration((0,) * len(relax.order)),
        solver_probability=None,
        status=Status.INFEASIBLE if proven else answer.status,
        upper_bound=None if proven else answer.upper_bound,
    )


def _budget_blind(answer: Solution, instance: AttackInstance) -> bool:
    """Whether an open answer's bound is the relaxations' own on a chain with end components:
    no better than their bound at the root (or none yet), which does not see the budget there."""
    stats = answer.stats
    if not instance.cycling.any() or not isinstance(stats, BranchAndBoundStats):
        return False
    roots = [stats.root_bound]
    if stats.segment is not None:
        roots.append(stats.segment.root_bound)
    # the objective's maximum too: answers' bounds are clipped to it, and it is the root's
    # bound before the root is bounded
    known = [r for r in roots if r is not None] + [instance.problem.objective.max_value]
    return answer.upper_bound is None or answer.upper_bound >= min(known)


def _no_seed_beats(
    problem: Problem, level: Solution, seeds: Sequence[AlterationArray | None] | None
) -> bool:
    """Whether every seed is worth no more than ``level``'s answer (up to near-ties): an
    earlier stage found nothing better for the larger budgets."""
    if level.status != Status.OPTIMAL or level.solver_probability is None or not seeds:
        return False
    exact = exact_values(problem)  # the solve's table: each alteration valued once
    worth = [exact(seed) for seed in seeds if seed is not None]
    return bool(worth) and not any(
        tolerance.better(value, level.solver_probability, rel=tolerance.NEAR_TIE) for value in worth
    )


def _level(lower: Solution, higher: Solution) -> bool:
    """Whether two budgets' answers are both certified at the same value (up to near-ties)."""
    certified = Status.OPTIMAL == lower.status == higher.status
    low, high = lower.solver_probability, higher.solver_probability
    return (
        certified
        and low is not None
        and high is not None
        and not tolerance.better(high, low, rel=tolerance.NEAR_TIE)
    )


@dataclass
class _Node:
    """A prefix of fixed candidates (``picks`` for the first ``depth`` observations)."""

    picks: tuple[int, ...]
    remaining: float
    parent_bound: float
    policy: np.ndarray  # warm start: one group per product state
    covered_at: float = np.inf  # the budget left at the last cover on its path (inf: none)


class _Search(IncumbentSearch):
    """Depth-first branch-and-bound for one budget."""

    def __init__(
        self,
        relax: PerStateRelaxation,
        budget: float,
        max_nodes: int,
        seed: tuple[Picks, float] | None,
        policy: np.ndarray,
        accept: Callable[[Picks], Verdict] | None = None,
        *,
        values: dict[Picks, float] | None = None,
    ):
        """``values``: exact values of complete assignments, shared along the curve
        (:class:`Incumbent`)."""
        self.relax, self.budget, self.max_nodes = relax, budget, max_nodes
        self.incumbent = Incumbent(
            relax, (0,) * len(relax.order), budget, accept=accept, values=values
        )
        if seed is not None:  # the smaller budget's answer stays feasible
            self.incumbent.offer(*seed)
        self.root_policy = policy
        # a node's ``remaining`` is the budget's cap less what it spent: ``cost <= remaining``
        self.stack = [_Node((), relax.space.scale.cap(budget), np.inf, policy)]
        self.nodes = 0
        self.root_bound: float | None = None
        self.cover_rule: CoverRule | None = None  # covering bounds (cover_with)
        self.strength: np.ndarray | None = None
        self.node_seconds = 0.0  # the last node bound's time
        self.union_seconds: float | None = None  # a cover's time per union, once measured
        self.covers = self.cover_unions = self.cover_pruned = self.covers_given_up = 0
        self.cover_refined = 0
        self.root_cover_bound: float | None = None
        self.evaluations_before = relax.evaluations
        self.caught: Callable[[Picks], bool] | None = None  # max_alarm (_caught)
        self.caught_pruned = 0
        self.lagrangian: LagrangianBound | None = None  # max_alarm, off by default
        self.lagrangian_pruned = 0
        # relaxations solved, by their allowed groups (``_relaxed``), shared along the curve
        self.known: dict[bytes, tuple[float, float, np.ndarray]] | None = None
        self.reused = 0
        mdp = relax.mdp
        self.proofs_before = (
            mdp.proofs,
            mdp.trivial_proofs,
            mdp.collapsed_proofs,
            mdp.collapsed_proven,
        )

    def cover_with(self, rule: CoverRule, strength: np.ndarray) -> None:
        """Bound the nodes ``rule`` picks by the covering bound as well
        (:mod:`misdirect.solvers.engines.covering`), the undecided sensors dealt into groups
        by ``strength`` (per choice of the alteration space)."""
        self.cover_rule, self.strength = rule, strength

    def describe(self) -> str:
        bound = self.open_bound()
        return (
            f"incumbent {self.best_value:.6f}, bound {bound:.6f}, gap {bound - self.best_value:.2e}"
            f", {self.nodes:,} nodes"
        )

    def open_bound(self) -> float:
        return self.incumbent.proven_bound(
            max((n.parent_bound for n in self.stack), default=-np.inf)
        )

    def run(
        self, deadline: Deadline | None = None, tick: Callable[[], None] | None = None
    ) -> Solution:
        """Search until every node is pruned (``optimal``: finished), the deadline passes
        (``time_limit``) or ``max_nodes`` were bounded (``feasible``)."""
        if self.best_value < 0:
            self.incumbent.offer_exact(self.best_picks)
        while self.stack:
            if self.nodes >= self.max_nodes:
                return self._solution(Status.FEASIBLE)
            if deadline is not None and deadline.expired():
                return self._solution(Status.TIME_LIMIT)
            if tick is not None and self.nodes % 64 == 0:
                tick()
            node = self.stack.pop()
            if self.incumbent.prune(node.parent_bound):
                continue
            try:
                self._expand(node, deadline)
            except DeadlineExpiredError:  # cut inside its bound: open, with its parent's
                self.stack.append(node)
                return self._solution(Status.TIME_LIMIT)
        return self._solution(Status.OPTIMAL)

    def _expand(self, node: _Node, deadline: Deadline | None) -> None:
        """Bound ``node``, round its policy to an incumbent, and push its children."""
        relax = self.relax
        self.nodes += 1
        if self.caught is not None and self.caught(node.picks):
            self.caught_pruned += 1  # no completion is feasible: nothing to bound
            return
        allowed = relax.allowed_groups(relax.allowed_options(node.picks, node.remaining))
        bound, value, policy = self._relaxed(allowed, node.policy, deadline)
        if self.root_bound is None:
            self.root_bound, self.root_policy = bound, policy
        level = len(node.picks)
        if level == len(relax.order):  # every observation fixed: the relaxation is the chain
            # its value, not the bound above it (the two differ by the rounding proven away)
            self.incumbent.offer(node.picks, value)
            return
        usage = relax.usage(policy)
        self.incumbent.offer_exact(self._round(node.picks, node.remaining, usage))
        if self.incumbent.prune(bound):
            return
        if self.lagrangian is not None and self.best_value >= 0:
            bound = min(bound, self.lagrangian.bound(allowed, policy, deadline))
            if self.incumbent.prune(bound):
                self.lagrangian_pruned += 1
                return
        covered_at = node.covered_at
        rule = self.cover_rule
        if rule is not None and rule.due(node.remaining, node.covered_at):
            cover = self._cover(node, rule, bound, deadline)
            if cover is not None:
                covered_at = node.remaining
                bound = min(bound, cover)
                if self.incumbent.prune(bound):
                    self.cover_pruned += 1
                    return
        i = relax.order[level]
        costs = relax.option_cost[relax.first_option[i] : relax.first_option[i + 1]]
        preferred = relax.ranked(i, node.remaining, usage)
        for k in preferred[::-1]:  # the stack pops the preferred candidate first
            remaining = node.remaining - float(costs[k])
            child = _Node((*node.picks, int(k)), remaining, bound, policy, covered_at)
            self.stack.append(child)

    def _relaxed(
        self, allowed: np.ndarray, policy: np.ndarray, deadline: Deadline | None
    ) -> tuple[float, float, np.ndarray]:
        """The relaxation over the groups ``allowed``: its proven bound, its value at the start
        and its policy, from ``policy``. The relaxation is the allowed groups' alone, and the
        same groups come back at other budgets (a node whose remaining budget affords the same
        options) and at every δ of a trade-off curve: ``known`` keeps them, up to
        :data:`KNOWN_BYTES` (any proven bound of it is one, whatever policy iteration started
        from)."""
        key = np.packbits(allowed).tobytes()
        found = None if self.known is None else self.known.get(key)
        if found is not None:
            self.reused += 1
            return found
        began = time.perf_counter()
        bound, values, chosen = self.relax.optimise(allowed, policy.copy(), deadline)
        self.node_seconds = time.perf_counter() - began
        found = (bound, float(values[self.relax.chain.initial]), chosen)
        if self.known is not None and (len(self.known) + 1) * chosen.nbytes <= KNOWN_BYTES:
            self.known[key] = found
        return found

    def _cover(
        self, node: _Node, rule: CoverRule, bound: float, deadline: Deadline | None
    ) -> float | None:
        """``node``'s covering bound, where ``rule`` finds groups the time left pays for and
        it comes out below ``bound`` (the node's per-state bound). A cover given up is tried
        again (:data:`COVER_TRIES` in all) where what it measured pays for finer groups."""
        relax = self.relax
        assert self.strength is not None
        level = len(node.picks)
        fixed = {i: 0 for i in range(len(relax.space.choices))}  # owning no live state: as is
        fixed.update({relax.order[j]: k for j, k in enumerate(node.picks)})
        cheapest: dict[int, float] = {}
        for i in relax.order[level:]:
            del fixed[i]
            affordable = relax.affordable(i, node.remaining)
            if affordable.size:
                cheapest[i] = float(relax.option_cost[relax.first_option[i] + affordable].min())
        scale = relax.space.scale
        tried: list[list[int]] | None = None
        for _ in range(COVER_TRIES):
            seconds_left = None if deadline is None else deadline.remaining()
            per_union = self.union_seconds
            if per_union is None:  # not measured yet: a node bound's, less a kept basis's
                per_union = self.node_seconds * KEPT_BASIS_SHARE
            groups = rule.groups(
                list(cheapest),
                self.strength,
                cheapest,
                lambda total: bool(scale.fits(total, node.remaining)),
                rule.unions_allowed(seconds_left, per_union),
            )
            if groups is None or (tried is not None and len(groups) <= len(tried)):
                return None  # no groups, or none finer than those of the cover given up
            found = self._cover_with(node, groups, fixed, bound, rule, deadline)
            if found is not None:
                if self.root_cover_bound is None and level == 0:
                    self.root_cover_bound = found
                return found
            tried = groups
        return None

    def _cover_with(
        self,
        node: _Node,
        groups: list[list[int]],
        fixed: dict[int, int],
        bound: float,
        rule: CoverRule,
        deadline: Deadline | None,
    ) -> float | None:
        """One cover of ``node`` by ``groups``: its bound, or None where it gave up (a union
        as high as ``bound``) or ran out of its share of the time."""
        began = time.perf_counter()
        # a union above the incumbent cannot prune: its halves might (the refinement also
        # resolves the unions whose proof fails, which would otherwise give the cover up)
        refine_above = self.best_value if self.best_value >= 0 else np.inf
        try:
            found = covering_bound(
                self.relax,
                groups,
                node.remaining,
                fixed,
                rule.deadline(deadline),
                give_up_at=bound,
                refine_above=refine_above,
                workers=rule.workers,
            )
        except DeadlineExpiredError:  # the cover's own time: the node keeps its own bound
            if deadline is not None:
                deadline.check()  # ... unless the search's time is up too
            found = None
        if found is not None and found.solved:
            # what a union costs here (the first cover's estimate is a node bound's share,
            # which on a large chain is 20 times too much: bench/results/covering), measured
            # even where the cover gave up, so that the next cover's groups fit its time
            self.union_seconds = (time.perf_counter() - began) / found.solved
        if found is None or found.given_up:
            self.covers_given_up += 1
            return None
        self.covers += 1
        self.cover_unions += found.solved
        self.cover_refined += found.refined
        return found.bound

    def _round(self, picks: Picks, remaining: float, usage: np.ndarray) -> Picks:
        """Complete ``picks`` greedily: each free observation's most used affordable candidate."""
        relax = self.relax
        completed = list(picks)
        for i in relax.order[len(picks) :]:
            k = int(relax.ranked(i, remaining, usage)[0])
            completed.append(k)
            remaining -= float(relax.option_cost[relax.first_option[i] + k])
        return tuple(completed)

    def _solution(self, status: Status) -> Solution:
        mdp = self.relax.mdp
        proofs = [
            now - then
            for now, then in zip(
                (mdp.proofs, mdp.trivial_proofs, mdp.collapsed_proofs, mdp.collapsed_proven),
                self.proofs_before,
                strict=True,
            )
        ]
        stats = BranchAndBoundStats(
            nodes=self.nodes,
            pruned=self.incumbent.pruned,
            policy_evaluations=self.relax.evaluations - self.evaluations_before,
            root_bound=self.root_bound,
            relevant_observations=len(self.relax.order),
            proofs=proofs[0],
            trivial_bounds=proofs[1],
            collapsed_proofs=proofs[2],
            collapsed_proven=proofs[3],
            covers=self.covers,
            cover_unions=self.cover_unions,
            cover_refined=self.cover_refined,
            cover_pruned=self.cover_pruned,
            covers_given_up=self.covers_given_up,
            root_cover_bound=self.root_cover_bound,
            weakest_bound=None if status == Status.OPTIMAL else self._weakest(proofs[1]),
        )
        return Solution(
            budget=self.budget,
            alteration=self.relax.alteration(self.best_picks),
            solver_probability=self.best_value,
            status=status,
            upper_bound=self.open_bound(),
            stats=stats,
        )

    def _weakest(self, trivial_bounds: int) -> str:
        """What holds an open budget's bound up, for a user to tell "no proof yet" from "no
        bound known": ``time`` (the root was never bounded), ``proof`` (the bound is the
        objective's largest value and some node's proof fell back to it although its
        relaxation's value lay below) or ``relaxation`` (the relaxations' own values)."""
        if self.root_bound is None:
            return "time"
        top = self.relax.problem.objective.max_value
        if trivial_bounds and self.open_bound() >= top * (1 - tolerance.PROOF_COLLAPSE):
            return "proof"
        return "relaxation"


def _strengths(curve: _Curve) -> np.ndarray:
    """Per choice of the alteration space: the first-order gain of its best single alteration
    from the unaltered chain (what the covering bound deals its groups by)."""
    relax = curve.relax
    strength = np.zeros(len(relax.space.choices))
    moves = _first_order_moves(relax, (0,) * len(relax.order), curve.max_budget)
    for gain, position, _ in moves or []:
        i = relax.order[position]
        strength[i] = max(strength[i], gain)
    return strength


def _first_order_moves(
    relax: PerStateRelaxation, picks: tuple[int, ...], budget: float
) -> list[tuple[float, int, int]] | None:
    """:func:`_ranked_moves` from ``picks`` (their chain solved for values and visits); None
    where the start cannot leave the live states under it (nothing to rank by)."""
    chain, live = relax.chain, relax.live
    policy = relax.policy_of(picks)
    values = relax.evaluate(policy)
    moved = chain.transitions[policy]
    # the live states that can still leave the live set: the rest sit in closed classes
    # of this chain (it cycles there forever), where expected visits are infinite
    leaving = reachable_from(moved.T.tocsr(), np.flatnonzero(~live)) & live
    inner = np.flatnonzero(leaving)
    if not leaving[chain.initial]:
        return None
    position = np.full(chain.n_states, -1)
    position[inner] = np.arange(inner.size)
    block = moved[inner][:, inner].tocsc()
    system = (sp.identity(inner.size, format="csc") - block).T.tocsc()
    start = np.zeros(inner.size)
    start[position[chain.initial]] = 1.0
    visits = spla.splu(system).solve(start)
    return _ranked_moves(relax, picks, values, visits, inner, position, budget)


def _hill_climb(
    relax: PerStateRelaxation,
    picks: tuple[int, ...],
    value: float,
    budget: float,
    deadline: Deadline | None = None,
    tries: int = GREEDY_TRIES,
    *,
    first_improvement: bool = False,
) -> tuple[tuple[int, ...], float]:
    """Hill-climb from ``picks`` by changing one observation at a time within ``budget``.

    Candidates are ranked by a first-order estimate of their gain (the expected visits of
    the states they change times the one-step advantage of their group under the current
    values), and only the ``tries`` best are evaluated exactly: a good incumbent early,
    for the pruning and for answers cut short by the time limit. ``first_improvement``:
    each step takes the first candidate that improves (one or two exact values a step, not
    ``tries``): the cheap greedy answer of a budget solved without a smaller one before it,
    so that a short time limit does not leave it below what a smaller budget attains.
    """
    chain, live = relax.chain, relax.live
    if not live.any() or not relax.order or not live[chain.initial]:
        return picks, value
    while deadline is None or not deadline.expired():
        moves = _first_order_moves(relax, picks, budget)
        if moves is None:
            return picks, value
        best = (value, picks)
        for gain, j, k in moves[:tries]:
            if gain <= 0 or (deadline is not None and deadline.expired()):
                break
            candidate = (*picks[:j], k, *picks[j + 1 :])
            found = relax.value_of(candidate)
            if tolerance.better(found, best[0], rel=tolerance.PRUNE):
                best = (found, candidate)
                if first_improvement:
                    break
        if best[1] is picks:
            return picks, value
        value, picks = best
    return picks, value


def _ranked_moves(
    relax: PerStateRelaxation,
    picks: tuple[int, ...],
    values: np.ndarray,
    visits: np.ndarray,
    inner: np.ndarray,
    position: np.ndarray,
    budget: float,
) -> list[tuple[float, int, int]]:
    """Every change of one observation's pick within ``budget``, with its first-order gain
    (expected visits of the states it changes times their one-step advantage), best first."""
    chain = relax.chain
    state_obs = relax.problem.pomdp.observation_of[chain.world_state]
    score = np.asarray(chain.transitions @ values).ravel()
    spent, cap = relax.cost(picks), relax.space.scale.cap(budget)
    moves = []
    for position_in_order, i in enumerate(relax.order):
        first = relax.first_option[i]
        costs = relax.option_cost[first : relax.first_option[i + 1]]
        current = picks[position_in_order]
        owned = inner[state_obs[inner] == relax.space.choices[i].observation]
        for k in np.flatnonzero(spent - costs[current] + costs <= cap):
            if k == current:
                continue
            groups = chain.group_of_option[owned, first + k]
            gain = visits[position[owned]] @ (score[groups] - values[owned])
            moves.append((float(gain), position_in_order, int(k)))
    moves.sort(reverse=True)
    return moves
