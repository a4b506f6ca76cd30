"""``--method auto``: a portfolio of the exact methods, run as a table of stages in one deadline.

auto is the one module that composes the methods (the others stand on the engines alone). It
measures the instance once (:class:`_Facts`), then takes the first stage of :data:`STAGES`
that applies; that stage names the stages that take over the budgets it leaves uncertified,
each started from the answers before it. Every stage says whether it applies (and why, in the
words the user reads as ``auto_reason``), what it would cost, and how it runs within a
deadline from seed incumbents. How time is shared is :mod:`misdirect.solvers.schedule`'s.

1. ``incremental``, the low-rank enumeration, when the alterations within the budget are few
   enough for the time left (:func:`~misdirect.solvers.schedule.enumeration_fits`); on chains
   with end components too (the alterations that could close a class are checked, and valued
   exactly where one does). A curve whose top budget is too large has its small budgets
   enumerated first, and the rest searched from their best answer.
2. ``exhaustive`` when at most ``ENUMERATION_LIMIT`` alterations fit the budget, or as many as
   one-by-one evaluation gets through in ``EVALUATION_SURE`` seconds (one evaluation's cost
   measured on a sample of alterations).
3. the MILP when every relevant observation owns at most ``KNAPSACK_STATES`` live product
   states (knapsack-like): the per-state relaxation then only drops the budget, its bound is
   weak and branch-and-bound degenerates to enumeration, while the MILP's LP handles the budget
   row. A budget the MILP does not certify goes to branch-and-bound, started from its answer.
4. ``branch-and-bound`` otherwise (its relaxation is tight where few observations own many
   states, where the MILP's is weak), with the MILP taking over any budget on which it hits
   its node limit; on a tiny chain (under ``TINY_CHAIN`` product states) it has no node limit,
   since a node costs microseconds there. Where the enumeration would finish, but not soon, the
   search goes first with part of the time and the enumeration takes what it did not certify.

Every hand-over is reported to the progress callback, and every answer records which method
certified it and why.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Callable, Iterator, Sequence
from contextvars import ContextVar
from dataclasses import dataclass, field, replace
from functools import cached_property
from typing import ClassVar

import numpy as np

from misdirect.core import tolerance
from misdirect.core.attack import AttackInstance, prepare
from misdirect.core.evaluate import decoy_probability
from misdirect.core.model import AlterationArray, Problem
from misdirect.solvers import schedule
from misdirect.solvers.base import ProgressCallback, Solution, method_deadline, report
from misdirect.solvers.branch_and_bound import BranchAndBoundSolver
from misdirect.solvers.certification import ExactValues, exact_values
from misdirect.solvers.deadline import Deadline
from misdirect.solvers.engines.alarm import AlarmConstraint, Verdict, alarm_constraint
from misdirect.solvers.engines.lowrank import (
    MAX_ALTERATIONS,
    LowRankEnumeration,
    NotApplicableError,
)
from misdirect.solvers.exhaustive import MAX_EVALUATIONS, ExhaustiveSolver
from misdirect.solvers.incremental import IncrementalSolver
from misdirect.solvers.milp.solver import MilpSolver
from misdirect.solvers.options import SolveOptions
from misdirect.solvers.stats import AutoStats, MethodStats
from misdirect.solvers.status import Status, StopReason

ENUMERATION_LIMIT = 300  # alterations within the budget for plain enumeration
INCREMENTAL_LIMIT = MAX_ALTERATIONS  # the most the low-rank enumeration is given
EXHAUSTIVE_LIMIT = MAX_EVALUATIONS  # the most auto gives the exhaustive enumeration
KNAPSACK_STATES = 2  # observations owning at most this many live states: knapsack-like
NODE_LIMIT = 5_000  # branch-and-bound nodes per budget before the MILP takes over
BASES_SAMPLED_FROM = 64  # base solves from which auto costs them before enumerating
TINY_CHAIN = 1_000  # product states below which branch-and-bound keeps going (no MILP)
UNLIMITED_NODES = 10**9
UNWATCHED_FIRST = True  # a monitored problem's plain twin first (False: measured without)
UNWATCHED_PARTS = 4  # a monitored problem's plain twin gets a quarter of the time left
LIFT_TARGETS = 64  # per altered observation, the twin's answer tries at most this many targets

# the twins solved in this trade-off curve: (id of the plain problem, budgets) -> (it, answers)
_Twin = list[tuple[Solution, float | None]]  # the plain twin's answers, with their bounds
_twins: ContextVar[dict[tuple[int, tuple[float, ...]], tuple[object, _Twin]] | None] = ContextVar(
    "misdirect_twins", default=None
)


@contextlib.contextmanager
def twin_scope() -> Iterator[None]:
    """Within this block (a trade-off curve: one solve per δ), a monitored problem's plain
    twin is solved once for each list of budgets, and its answers shared by every δ."""
    token = _twins.set({})
    try:
        yield
    finally:
        _twins.reset(token)


@dataclass
class _Facts:
    """What auto measures of an instance, once, and the reasons it gives for its choices."""

    problem: Problem
    instance: AttackInstance
    count: int  # alterations within the top budget (INCREMENTAL_LIMIT + 1: more)
    top: float = 0.0  # the top budget
    reasons: list[str] = field(default_factory=list)

    @classmethod
    def measure(cls, problem: Problem, budgets: Sequence[float]) -> _Facts:
        instance = prepare(problem, max(budgets))
        count = instance.space.count_within(max(budgets), INCREMENTAL_LIMIT)
        facts = cls(problem, instance, count, max(budgets))
        if instance.left_out:
            facts.reasons.append(
                f"{instance.left_out:,} options left out (each moves the robot as no "
                "alteration or a cheaper option does wherever the decoy can still be reached)"
            )
        facts.reasons.append(
            (
                "1 alteration fits the budget"
                if count == 1
                else f"{count:,} alterations fit the budget"
            )
            if count <= INCREMENTAL_LIMIT
            else f"more than {INCREMENTAL_LIMIT:,} alterations fit the budget"
        )
        return facts

    @property
    def reason(self) -> str:
        return "; ".join(self.reasons)

    @property
    def cycling(self) -> bool:
        """Whether an alteration can make the chain cycle without reaching the decoy."""
        return bool(self.instance.cycling.any())

    @cached_property
    def evaluation_s(self) -> float:
        """Seconds for one exact evaluation as the exhaustive enumeration makes it: the mean
        over the unaltered chain and single-sensor alterations spread over the space (an
        altered chain that cycles may cost several times the unaltered one, another a fraction
        of it: docs/benchmarks.md, "Chains with cycles"), sampled within about
        ``SAMPLE_SECONDS``.
        Evaluated afresh, not from the solve's table."""
        problem, choices = self.problem, self.instance.space.choices
        spread = np.linspace(0, len(choices) - 1, schedule.SAMPLE_EVALUATIONS - 1)
        samples = [problem.identity()]
        for j in np.unique(spread.round().astype(np.int64)) if choices else ():
            alpha = problem.identity()
            choice = choices[int(j)]
            alpha[choice.observation] = choice.targets[1 + int(j) % (choice.size - 1)]
            samples.append(alpha)
        began = time.perf_counter()
        taken = 0
        for alpha in samples:
            decoy_probability(problem, alpha)
            taken += 1
            if time.perf_counter() - began > schedule.SAMPLE_SECONDS:
                break
        return (time.perf_counter() - began) / taken

    @cached_property
    def _enumeration(self) -> LowRankEnumeration:
        return LowRankEnumeration(self.instance, threads=1, max_evaluations=INCREMENTAL_LIMIT)

    def bases_s(self, budget: float) -> float:
        """About the seconds the low-rank enumeration at ``budget`` spends on base solves
        (:func:`schedule.bases_seconds`); 0 below ``BASES_SAMPLED_FROM`` bases, where the
        enumeration's own pace decides (and one exact evaluation is not worth measuring).
        Monitored problems only: it was measured there (docs/benchmarks.md, "Stealth"); the
        hard instances without a monitor were not re-measured with it, so they keep the
        enumeration's plan as it was."""
        if not self.instance.space.choices or not self.problem.monitor:
            return 0.0
        bases = self._enumeration.bases_within(budget)
        if bases < BASES_SAMPLED_FROM:
            return 0.0
        return schedule.bases_seconds(bases, self.evaluation_s)

    def enumeration_s(self, budget: float, count: int) -> tuple[float, float]:
        """About the seconds the low-rank enumeration of ``count`` alterations at ``budget``
        takes, and those of them spent on base solves."""
        bases = self.bases_s(budget)
        return schedule.enumeration_seconds(count) + bases, bases

    @cached_property
    def largest_observation(self) -> int:
        """Live product states owned by the relevant observation that owns the most."""
        choices = self.instance.space.choices
        observations = np.array([c.observation for c in choices], dtype=np.int64)
        counts = self.instance.live_states_per_observation
        return int(counts[observations].max(initial=0))

    @property
    def product_states(self) -> int:
        return int(self.instance.chain.n_states)


@dataclass(frozen=True)
class _Handover:
    """A stage that takes over the budgets the ones before it did not certify."""

    stage: _Stage
    # appended to the reason: "the MILP did not certify it, so ..."; or made from the answers
    # left uncertified (how the stage before stopped)
    why: str | Callable[[Sequence[Solution]], str]


class _Stage:
    """One way auto answers budgets: ``applies`` (with the reasons it adds), ``estimate_s``
    (seconds it would take, where it can tell), ``deadline`` (its share of the time) and
    ``run`` (from seed incumbents, one per budget)."""

    method: ClassVar[str]
    announced: ClassVar[bool] = False  # says why before it runs (a stage that may take long)

    def __init__(self, auto: AutoSolver):
        self.auto = auto

    def applies(self, facts: _Facts, deadline: Deadline) -> bool:
        return True

    def estimate_s(self, facts: _Facts) -> float | None:
        return None

    def deadline(self, facts: _Facts, deadline: Deadline) -> Deadline:
        return deadline

    def handovers(self, facts: _Facts, deadline: Deadline) -> list[_Handover]:
        return []

    def run(
        self,
        problem: Problem,
        budgets: Sequence[float],
        deadline: Deadline,
        progress: ProgressCallback | None,
        seeds: Sequence[AlterationArray | None] | None,
        below: Solution | None = None,
    ) -> list[Solution]:
        raise NotImplementedError


class _Enumeration(_Stage):
    method = "incremental"

    def applies(self, facts: _Facts, deadline: Deadline) -> bool:
        if facts.count > INCREMENTAL_LIMIT:
            return False
        needed, bases = facts.enumeration_s(facts.top, facts.count)
        fits = schedule.enumeration_fits(
            facts.count,
            needed,
            deadline,
            limit=INCREMENTAL_LIMIT,
            bases_s=bases,
            search_sees_budget=not facts.cycling,
        )
        if not fits and not facts.cycling and schedule.mostly_bases(needed, bases):
            facts.reasons.append(
                f"their enumeration is mostly base solves (at least {bases:.3g} s)"
            )
        return fits

    def estimate_s(self, facts: _Facts) -> float:
        if facts.count > INCREMENTAL_LIMIT:
            return schedule.enumeration_seconds(facts.count)
        return facts.enumeration_s(facts.top, facts.count)[0]

    def handovers(self, facts: _Facts, deadline: Deadline) -> list[_Handover]:
        # a budget the enumeration stops before (its measured rate says it will not fit)
        why = "the enumeration of it would not fit the time left, so branch-and-bound"
        return [_Handover(_Search(self.auto, UNLIMITED_NODES), why)]  # the deadline is the limit

    def run(
        self,
        problem: Problem,
        budgets: Sequence[float],
        deadline: Deadline,
        progress: ProgressCallback | None,
        seeds: Sequence[AlterationArray | None] | None,
        below: Solution | None = None,
    ) -> list[Solution]:
        solver = IncrementalSolver(SolveOptions(threads=self.auto.options.threads), hand_over=True)
        return solver.solve(problem, budgets, progress=progress, deadline=deadline)


class _Exhaustive(_Stage):
    method = "exhaustive"

    def applies(self, facts: _Facts, deadline: Deadline) -> bool:
        why = self.takes(facts, facts.count, deadline)
        if why:
            facts.reasons.append(why)
        return why is not None

    def takes(self, facts: _Facts, count: int, deadline: Deadline) -> str | None:
        """Whether it enumerates ``count`` alterations before anything else: None if not,
        else the words of the reason (empty: so few that none are needed)."""
        if count <= self.auto.enumeration_limit:
            return ""
        if count > _exhaustive_limit():
            return None
        needed = schedule.enumeration_seconds(count, facts.evaluation_s)
        if needed <= schedule.EVALUATION_SURE:
            return (
                f"one evaluation is quick enough to try all within {schedule.EVALUATION_SURE:g} s"
            )
        return None  # the low-rank enumeration, far cheaper per alteration, did not fit

    def estimate_s(self, facts: _Facts) -> float:
        return schedule.enumeration_seconds(facts.count, facts.evaluation_s)

    def run(
        self,
        problem: Problem,
        budgets: Sequence[float],
        deadline: Deadline,
        progress: ProgressCallback | None,
        seeds: Sequence[AlterationArray | None] | None,
        below: Solution | None = None,
    ) -> list[Solution]:
        return ExhaustiveSolver().solve(problem, budgets, progress=progress, deadline=deadline)


def _exhaustive_limit() -> int:
    """The most alterations auto enumerates one by one (counts are known up to
    ``INCREMENTAL_LIMIT``, the most :class:`_Facts` counts)."""
    return min(EXHAUSTIVE_LIMIT, INCREMENTAL_LIMIT)


class _Milp(_Stage):
    method = "milp"
    announced = True

    def applies(self, facts: _Facts, deadline: Deadline) -> bool:
        largest = facts.largest_observation
        if largest > KNAPSACK_STATES:
            return False
        facts.reasons.append(
            "no observation owns a live product state: no alteration changes the value, so "
            "the MILP proves it"
            if largest == 0
            else f"knapsack-like (each observation owns at most {largest} live product "
            "states), so the MILP"
        )
        return True

    def handovers(self, facts: _Facts, deadline: Deadline) -> list[_Handover]:
        why = "the MILP did not certify it, so branch-and-bound from its answer"
        return [_Handover(_Search(self.auto, UNLIMITED_NODES), why)]  # the deadline is the limit

    def run(
        self,
        problem: Problem,
        budgets: Sequence[float],
        deadline: Deadline,
        progress: ProgressCallback | None,
        seeds: Sequence[AlterationArray | None] | None,
        below: Solution | None = None,
    ) -> list[Solution]:
        # the MILP warm-starts from its own previous budget, not from seeds
        return self.auto.milp.solve(problem, budgets, progress=progress, deadline=deadline)


class _Search(_Stage):
    method = "branch-and-bound"
    announced = True

    def __init__(self, auto: AutoSolver, max_nodes: int | None = None):
        super().__init__(auto)
        self.max_nodes = max_nodes
        self.search_first_s: float | None = None
        self.then: _Stage | None = None  # the enumeration after the search, if any

    def applies(self, facts: _Facts, deadline: Deadline) -> bool:
        facts.reasons.append(
            f"the largest observation owns {facts.largest_observation:,} live product states"
        )
        if self.max_nodes is None:
            self.max_nodes = self.auto.node_limit
            if facts.product_states < TINY_CHAIN:
                # a node costs microseconds here, while the MILP's start-up alone costs more
                facts.reasons.append(
                    f"a tiny chain ({facts.product_states:,} product states): no node limit"
                )
                self.max_nodes = UNLIMITED_NODES
        later = _Enumeration(self.auto)
        limit = INCREMENTAL_LIMIT
        enumerating = later.estimate_s(facts)
        bases = facts.count <= limit and schedule.mostly_bases(
            enumerating, facts.enumeration_s(facts.top, facts.count)[1]
        )
        search_s = schedule.search_before_enumerating(
            facts.count, enumerating, deadline, limit=limit, bases=bases
        )
        if search_s is not None:
            # the enumeration would likely finish, but not soon: the search goes first (it
            # often certifies in seconds) and the enumeration takes what it did not certify
            self.search_first_s = search_s
            self.then = later
            facts.reasons.append(
                f"{facts.count:,} alterations kept for enumeration (about {enumerating:.3g} s) "
                f"after the search ({search_s:.3g} s)"
            )
        return True

    def deadline(self, facts: _Facts, deadline: Deadline) -> Deadline:
        if self.search_first_s is None:
            return deadline
        return deadline.within(self.search_first_s)

    def handovers(self, facts: _Facts, deadline: Deadline) -> list[_Handover]:
        later: list[_Handover] = []
        if self.then is not None:
            kind = "exhaustive enumeration" if self.then.method == "exhaustive" else "enumeration"
            why = f"branch-and-bound did not certify it, so {kind}"
            later.append(_Handover(self.then, why))
        later.append(_Handover(_Milp(self.auto), _why_the_milp))
        return later

    def run(
        self,
        problem: Problem,
        budgets: Sequence[float],
        deadline: Deadline,
        progress: ProgressCallback | None,
        seeds: Sequence[AlterationArray | None] | None,
        below: Solution | None = None,
    ) -> list[Solution]:
        solver = self.auto.branch_and_bound(self.max_nodes or self.auto.node_limit)
        return solver.solve(
            problem, budgets, progress=progress, deadline=deadline, seeds=seeds, below=below
        )


# the first stage that applies answers every budget; its hand-overs take what it leaves
STAGES: tuple[Callable[[AutoSolver], _Stage], ...] = (_Enumeration, _Exhaustive, _Milp, _Search)


class AutoSolver:
    name: ClassVar[str] = "auto"
    curve_is_free: ClassVar[bool] = False
    accepts: ClassVar[tuple[str, ...]] = (*MilpSolver.accepts, "pool")

    def __init__(
        self,
        options: SolveOptions | None = None,
        *,
        enumeration_limit: int | None = None,
        node_limit: int | None = None,
    ):
        self.options = options or SolveOptions()
        self.enumeration_limit = (
            ENUMERATION_LIMIT if enumeration_limit is None else enumeration_limit
        )
        self.node_limit = NODE_LIMIT if node_limit is None else node_limit
        self.milp = MilpSolver(self.options)  # checks the MILP options up front

    def branch_and_bound(self, max_nodes: int) -> BranchAndBoundSolver:
        """The search of the search stages (a hook: tests give auto a scripted one)."""
        options = SolveOptions(threads=self.options.threads, pool=self.options.pool)
        return BranchAndBoundSolver(options, max_nodes=max_nodes)

    def solve(
        self,
        problem: Problem,
        budgets: Sequence[float],
        *,
        progress: ProgressCallback | None = None,
        deadline: Deadline | None = None,
        seeds: Sequence[AlterationArray | None] | None = None,
    ) -> list[Solution]:
        """``seeds`` (one alteration per budget, optional) start the searches."""
        if self.options.max_alarm is not None:
            return self._constrained(problem, budgets, progress, deadline, seeds)
        if problem.unwatched is not None and UNWATCHED_FIRST:
            return self._watched(problem, budgets, progress, deadline, seeds)
        return self._solve(problem, budgets, progress, deadline, seeds, may_split=True)

    def _watched(
        self,
        problem: Problem,
        budgets: Sequence[float],
        progress: ProgressCallback | None,
        deadline: Deadline | None,
        seeds: Sequence[AlterationArray | None] | None,
    ) -> list[Solution]:
        """A monitored problem (``--stealth``): its plain twin first (:meth:`_twin_answers`);
        the budgets its bound does not certify are searched on the monitored chain, from the
        twin's attacks, and keep the tighter of the two bounds."""
        deadline = method_deadline(deadline, self.options.time_limit)
        exact = exact_values(problem)
        answers = self._twin_answers(problem, budgets, progress, deadline, None)
        open_at = [j for j, a in enumerate(answers) if not _certified(a)]
        if not open_at or deadline.expired():
            return answers
        given = list(seeds) if seeds is not None else [None] * len(budgets)
        later = self._solve(
            problem,
            [budgets[j] for j in open_at],
            progress,
            deadline,
            [given[j] if given[j] is not None else answers[j].alteration for j in open_at],
            may_split=True,
        )
        for j, second in zip(open_at, later, strict=True):
            answers[j] = _better(exact, answers[j], second, "the monitored problem searched")
        return answers

    def _twin_answers(
        self,
        problem: Problem,
        budgets: Sequence[float],
        progress: ProgressCallback | None,
        deadline: Deadline,
        constraint: AlarmConstraint | None,
    ) -> list[Solution]:
        """Per budget, the answer of the monitored problem's plain twin (the same world,
        controller and alterations without the monitor, solved within a quarter of the time,
        once per trade-off curve: :func:`twin_scope`), lifted to the monitored problem
        (:func:`_lifted`; under ``constraint``, among the alterations it proves feasible),
        with the twin's proven bound.

        A monitor only takes runs away from the decoy: under any alteration a run is the
        same with and without it until the alarm, which then ends it with nothing, so the
        twin's proven bounds bound the monitored optimum too (and the constrained one,
        which is at most that). The twin's chain is smaller and its relaxations tighter (a
        monitored drone's 74,606 product states against 1,689). Where its optimal attacks,
        lifted, go unnoticed, they meet that bound and are certified at once."""
        memo = _twins.get()
        key = (id(problem.unwatched), tuple(budgets))
        if memo is not None and key in memo:
            twin = memo[key][1]
        else:
            plain = problem.without_monitor()
            note = "auto: the problem without its monitor first (it bounds it)"
            report(progress, 0, 0, note=note)
            unconstrained = AutoSolver(
                replace(self.options, max_alarm=None),
                enumeration_limit=self.enumeration_limit,
                node_limit=self.node_limit,
            )
            solved = unconstrained._solve(
                plain,
                budgets,
                progress,
                deadline.within(deadline.share(UNWATCHED_PARTS)),
                None,
                may_split=True,
            )
            # each answer with its bound, as the front door would take it: never below its
            # exact value (an alteration traded for one the controller treats alike has
            # the same plain chain, so that value holds for it too)
            plain_value = ExactValues(plain)
            twin = [
                (
                    answer,
                    None
                    if answer.upper_bound is None
                    else max(answer.upper_bound, plain_value(answer.alteration)),
                )
                for answer in solved
            ]
            if memo is not None:
                memo[key] = (problem.unwatched, twin)  # kept alive: its id stays its own
        exact = exact_values(problem)

        def allowed(alteration: np.ndarray) -> bool:
            return constraint is None or constraint.verdict(alteration) == Verdict.FEASIBLE

        why = (
            "the problem without its monitor: a monitor only takes runs away from the decoy, "
            "so its proven bound bounds this one"
        )
        answers = []
        for answer, twin_bound in twin:
            alteration = np.asarray(answer.alteration, dtype=np.int64)
            bound = twin_bound
            if bound is not None and not (
                allowed(alteration) and tolerance.proven(exact(alteration), bound)
            ):
                alteration = _lifted(problem, alteration, answer.budget, exact, deadline, allowed)
            if bound is not None:
                bound = max(bound, exact(alteration))
            found = Solution(
                budget=answer.budget,
                alteration=alteration,
                # an alteration the constraint does not allow is no incumbent
                solver_probability=exact(alteration) if allowed(alteration) else None,
                status=Status.FEASIBLE,
                upper_bound=bound,
                stats=AutoStats(_answer(answer.stats), why),
                certified_by="unmonitored",
                notes={} if bound is None else {"bound_from": why},
            )
            # proven by the twin's bound: nothing left to do (else cut, if nothing follows)
            done = _certified(found)
            stop = StopReason.FINISHED if done else StopReason.cut(deadline.cancelled)
            answers.append(replace(found, stop_reason=stop))
        return answers

    def _constrained(
        self,
        problem: Problem,
        budgets: Sequence[float],
        progress: ProgressCallback | None,
        deadline: Deadline | None,
        seeds: Sequence[AlterationArray | None] | None,
    ) -> list[Solution]:
        """Under ``max_alarm``: on a monitored problem its plain twin first
        (:meth:`_twin_answers`: its bound holds under the constraint too, its lifted attacks
        count where they are proven feasible); then, for the budgets it leaves open,
        branch-and-bound under the constraint (its incumbents proven
        feasible, subtrees whose fixed picks already raise the alarm too often pruned, no
        segment search: on monitored chains the per-state search alone is the faster), with
        :data:`NODE_LIMIT` nodes a budget; a budget it leaves open goes to the constrained
        enumeration where it applies and the alterations are few enough, else to the MILP
        with the alarm's system. δ = 1 too, as the unconstrained problem."""
        assert self.options.max_alarm is not None
        deadline = method_deadline(deadline, self.options.time_limit)
        constraint = alarm_constraint(problem, self.options.max_alarm)
        if problem.unwatched is None or not UNWATCHED_FIRST:
            return self._constrained_search(problem, budgets, progress, deadline, constraint)
        twin = self._twin_answers(problem, budgets, progress, deadline, constraint)
        open_at = [j for j, a in enumerate(twin) if not _certified(a)]
        if not open_at or deadline.expired():
            return twin
        left = [budgets[j] for j in open_at]
        found = self._constrained_search(problem, left, progress, deadline, constraint)
        exact = exact_values(problem)
        for j, answer in zip(open_at, found, strict=True):
            twin[j] = _better_feasible(exact, constraint, twin[j], answer)
        return twin

    def _constrained_search(
        self,
        problem: Problem,
        budgets: Sequence[float],
        progress: ProgressCallback | None,
        deadline: Deadline,
        constraint: AlarmConstraint,
    ) -> list[Solution]:
        """:meth:`_constrained`'s search, for ``budgets``."""
        assert self.options.max_alarm is not None
        options = SolveOptions(threads=self.options.threads, max_alarm=self.options.max_alarm)
        search = BranchAndBoundSolver(options, max_nodes=self.node_limit)
        why = "branch-and-bound under the constraint"
        solutions = _label(
            search.solve(problem, budgets, progress=progress, deadline=deadline),
            "branch-and-bound",
            why,
        )
        open_at = [
            j
            for j, s in enumerate(solutions)
            if s.status not in (Status.OPTIMAL, Status.INFEASIBLE)
        ]
        if not open_at or deadline.expired():
            return solutions
        left = [budgets[j] for j in open_at]
        count = prepare(constraint.decoy_problem, max(left)).space.count_within(
            max(left), INCREMENTAL_LIMIT
        )
        second: list[Solution] | None = None
        method = "incremental"
        if count <= INCREMENTAL_LIMIT:
            try:
                second = IncrementalSolver(options).solve(
                    problem, left, progress=progress, deadline=deadline
                )
            except NotApplicableError:
                second = None
        if second is None:
            method = "milp"
            second = self.milp.solve(  # its options carry max_alarm
                problem, left, progress=progress, deadline=deadline
            )
        why = "branch-and-bound left it open under the constraint"
        exact = exact_values(problem)
        for j, answer in zip(open_at, _label(second, method, why), strict=True):
            solutions[j] = _better_feasible(exact, constraint, solutions[j], answer)
        return solutions

    def _solve(
        self,
        problem: Problem,
        budgets: Sequence[float],
        progress: ProgressCallback | None,
        deadline: Deadline | None,
        seeds: Sequence[AlterationArray | None] | None,
        *,
        may_split: bool,
        below: Solution | None = None,
    ) -> list[Solution]:
        """:meth:`solve`; ``may_split``: whether a curve's small budgets may be enumerated
        first (not for budgets an enumeration has just left unproven: it would only start
        over on them); ``below``: a smaller budget's certified answer (where the curve may
        have levelled off, :meth:`BranchAndBoundSolver.solve`)."""
        deadline = method_deadline(deadline, self.options.time_limit)
        facts = _Facts.measure(problem, budgets)
        split = self._split_curve(facts, budgets, deadline, progress) if may_split else None
        if split is not None:
            return split
        first = next(
            stage for stage in (make(self) for make in STAGES) if stage.applies(facts, deadline)
        )
        handovers = first.handovers(facts, deadline)
        reason = facts.reason
        if first.announced:
            report(progress, 0, len(budgets), stage=first.method, note=f"auto: {reason}")
        solutions = first.run(
            problem, budgets, first.deadline(facts, deadline), progress, seeds, below=below
        )
        solutions = _label(solutions, first.method, reason)
        exact = exact_values(problem)  # the front door's: each answer is evaluated once
        for handover in handovers:
            said = handover.why
            why = f"{reason}; {said if isinstance(said, str) else said(solutions)}"
            solutions = self._hand_over(
                handover.stage, problem, budgets, solutions, exact, why, progress, deadline
            )
        return solutions

    def _split_curve(
        self,
        facts: _Facts,
        budgets: Sequence[float],
        deadline: Deadline,
        progress: ProgressCallback | None,
    ) -> list[Solution] | None:
        """A curve whose top budget is too large to enumerate may still have small budgets
        that are: prove those first, and search the larger ones from their best answer."""
        if len(budgets) < 2:
            return None
        enumeration = _Enumeration(self)
        limit = INCREMENTAL_LIMIT

        def takes(budget: float, count: int) -> str | None:
            if count > limit:
                return None
            needed, bases = facts.enumeration_s(budget, count)
            fits = schedule.enumeration_fits(
                count,
                needed,
                deadline,
                limit=limit,
                bases_s=bases,
                search_sees_budget=not facts.cycling,
            )
            return "" if fits else None

        if takes(facts.top, facts.count) is not None:
            return None
        space = facts.instance.space
        ordered = sorted(budgets)
        small = [b for b in ordered if takes(b, space.count_within(b, limit)) is not None]
        if not small:
            return None
        why = takes(small[-1], space.count_within(small[-1], limit))
        first = enumeration.run(facts.problem, small, deadline, progress, None)
        note = f"auto: budgets up to {small[-1]:g} enumerated, the rest searched"
        reason = f"{facts.reason}; budgets up to {small[-1]:g}: {why}" if why else facts.reason
        report(progress, 0, 0, note=note)
        # what the enumeration did not prove (it stops before a budget that will not fit
        # once it has measured its own rate) is searched with the larger budgets
        proven = {b for b, s in zip(small, first, strict=True) if _certified(s)}
        rest = [b for b in ordered if b not in proven]
        certified = [s for s in first if _certified(s)]
        # the enumeration did not search these budgets: its last answer as a seed for each
        # reads as "searched, nothing better found" (the curve levelled off), which sends the
        # largest budget first; so it is one only where the enumeration's own last two
        # certified budgets are level (else the search starts from ``below``)
        seeds = [first[-1].alteration] * len(rest) if _levelled(certified) else None
        later = self._solve(
            facts.problem,
            rest,
            progress,
            deadline,
            seeds,
            may_split=proven.issuperset(b for b in rest if b in small),
            below=max(certified, key=lambda s: s.budget, default=None),
        )
        found = dict(zip(small, _label(first, enumeration.method, reason), strict=True))
        exact = exact_values(facts.problem)
        for b, second in zip(rest, later, strict=True):
            found[b] = _better(exact, found[b], second, reason) if b in found else second
        return [found[b] for b in budgets]

    def _hand_over(
        self,
        stage: _Stage,
        problem: Problem,
        budgets: Sequence[float],
        solutions: list[Solution],
        exact: ExactValues,
        why: str,
        progress: ProgressCallback | None,
        deadline: Deadline,
    ) -> list[Solution]:
        """Hand every budget that is not certified to ``stage``, if time is left; keep the
        better answer and the tighter bound of the two."""
        unfinished = [j for j, s in enumerate(solutions) if not _certified(s)]
        if not unfinished:
            return solutions
        listed = ", ".join(f"{budgets[j]:g}" for j in unfinished)
        if not schedule.can_hand_over(deadline):
            note = f"auto: budgets {listed} left at their bounds: no time left for {stage.method}"
            report(progress, 0, 0, note=f"{note} ({why})")
            return solutions
        report(progress, 0, len(unfinished), note=f"auto: budgets {listed}: {why}")
        earlier = [solutions[j] for j in unfinished]
        seeds = [s.alteration for s in earlier]
        # the largest budget proven below these: where the curve may have levelled off
        lowest = min(budgets[j] for j in unfinished)
        proven = [
            s for b, s in zip(budgets, solutions, strict=True) if b < lowest and _certified(s)
        ]
        below = max(proven, key=lambda s: s.budget, default=None)
        unfinished_budgets = [budgets[j] for j in unfinished]
        later = stage.run(problem, unfinished_budgets, deadline, progress, seeds, below=below)
        later = _label(later, stage.method, "")
        for j, second in zip(unfinished, later, strict=True):
            solutions[j] = _better(exact, solutions[j], second, why)
        return solutions


def _lifted(
    problem: Problem,
    alteration: AlterationArray,
    budget: float,
    exact: ExactValues,
    deadline: Deadline,
    allowed: Callable[[np.ndarray], bool],
) -> AlterationArray:
    """The plain twin's ``alteration`` with its targets traded, one altered observation at a
    time, for others the controller treats alike (the same behaviour class without the
    monitor) but the monitor may not: the twin's chain is the same for all of them, so one
    that the monitor never catches is worth the twin's value. The best found within
    ``budget`` (an alteration ``allowed`` accepts before any other; at most
    :data:`LIFT_TARGETS` targets per observation, the cheapest of each class of the
    monitored controller first)."""
    assert problem.unwatched is not None
    plain_class = problem.unwatched.controller.behaviour_class
    watched_class = problem.controller.behaviour_class

    def score(candidate: np.ndarray) -> tuple[bool, float]:
        return allowed(candidate), exact(candidate)

    best = np.asarray(alteration, dtype=np.int64)
    kept = score(best)
    for o in np.flatnonzero(best != problem.identity()).tolist():
        costs = problem.cost.row(o)
        alike = np.flatnonzero((plain_class == plain_class[best[o]]) & np.isfinite(costs))
        order = alike[np.lexsort((alike, costs[alike]))]
        _, first = np.unique(watched_class[order], return_index=True)
        for target in order[np.sort(first)][:LIFT_TARGETS].tolist():
            if deadline.expired():
                return best
            if target == best[o]:
                continue
            trial = best.copy()
            trial[o] = target
            if not problem.cost.fits(trial, budget):
                continue
            found = score(trial)
            if (found[0] and not kept[0]) or (
                found[0] == kept[0] and tolerance.better(found[1], kept[1])
            ):
                best, kept = trial, found
    return best


def _why_the_milp(solutions: Sequence[Solution]) -> str:
    """Why the MILP takes over from branch-and-bound: its node limit, or the time it had."""
    left = [s for s in solutions if not _certified(s)]
    if any(s.status == Status.FEASIBLE for s in left):  # how it reports its node limit
        return "branch-and-bound hit its node limit, so the MILP"
    return "branch-and-bound did not certify it in its time, so the MILP"


def _levelled(certified: Sequence[Solution]) -> bool:
    """Whether the last two of these certified answers (by budget) have the same value, up to
    near-ties: the curve has levelled off there."""
    if len(certified) < 2:
        return False
    low, high = (s.solver_probability for s in sorted(certified, key=lambda s: s.budget)[-2:])
    return (
        low is not None
        and high is not None
        and not tolerance.better(high, low, rel=tolerance.NEAR_TIE)
    )


def _certified(solution: Solution) -> bool:
    """Whether a stage's answer is finished or proven by its bound (on the stage's claim;
    the front door decides on the exact value)."""
    if solution.status == Status.OPTIMAL:
        return True
    claimed = solution.solver_probability
    return claimed is not None and tolerance.proven(claimed, solution.upper_bound)


def _better(exact: ExactValues, first: Solution, second: Solution, why: str) -> Solution:
    """The better answer of two stages for one budget, with the tighter of their bounds; how
    they stopped is carried, not judged: certification is the front door's."""
    values = [exact(np.asarray(s.alteration, dtype=np.int64)) for s in (first, second)]
    pick = second if tolerance.better(values[1], values[0]) else first
    value = max(values)
    bounds = [s.upper_bound for s in (first, second) if s.upper_bound is not None]
    bound = max(min(bounds), value) if bounds else None
    proven = tolerance.proven(value, bound)
    finished = Status.OPTIMAL in (first.status, second.status)
    if finished or proven:
        status = Status.OPTIMAL if finished else pick.status
    elif Status.TIME_LIMIT in (first.status, second.status):  # the proof ran out of time
        status = Status.TIME_LIMIT
    else:
        status = pick.status
    stats = AutoStats(_answer(pick.stats), why, (first.stats, second.stats))
    # a stage that finished the budget finished it; else the last stage's stop is the answer's
    stop = StopReason.FINISHED if finished else second.stop_reason or first.stop_reason
    # the stage that finished the budget, or whose bound closed the gap, certified it (the
    # exact value may lie an ulp above its bound: compare the bounds, not the bound to it);
    # otherwise the one whose answer it is
    if finished:
        closer = second if second.status == Status.OPTIMAL else first
    else:
        closer = min(
            (first, second), key=lambda s: np.inf if s.upper_bound is None else s.upper_bound
        )
    return Solution(
        budget=pick.budget,
        alteration=pick.alteration,
        solver_probability=value,
        status=status,
        upper_bound=bound,
        stats=stats,
        certified_by=(closer if finished or proven else pick).certified_by or "auto",
        notes={**first.notes, **second.notes},  # what each method said of its answer or bound
        stop_reason=stop,
    )


def _better_feasible(
    exact: ExactValues, constraint: AlarmConstraint, first: Solution, second: Solution
) -> Solution:
    """Under ``max_alarm``, the better of two stages' answers for one budget among those
    proven feasible, with the tighter of their bounds (both bound the constrained optimum);
    ``optimal`` or ``infeasible`` where either stage finished so."""
    for finished in (Status.INFEASIBLE, Status.OPTIMAL):
        done = [s for s in (second, first) if s.status == finished]
        if done:
            return done[0]
    feasible = [
        s
        for s in (first, second)
        if s.solver_probability is not None
        and constraint.verdict(np.asarray(s.alteration, dtype=np.int64)) == Verdict.FEASIBLE
    ]
    pick = max(
        feasible or [second],
        key=lambda s: exact(np.asarray(s.alteration, dtype=np.int64)),
    )
    bounds = [s.upper_bound for s in (first, second) if s.upper_bound is not None]
    if not bounds:
        return pick
    value = exact(np.asarray(pick.alteration, dtype=np.int64)) if feasible else 0.0
    return replace(pick, upper_bound=max(min(bounds), value))


def _label(solutions: list[Solution], method: str, reason: str) -> list[Solution]:
    return [
        replace(s, stats=AutoStats(_answer(s.stats), reason), certified_by=method)
        for s in solutions
    ]


def _answer(stats: MethodStats) -> MethodStats:
    """The method's own record inside auto's (a stage's answer may be labelled already)."""
    return stats.answer if isinstance(stats, AutoStats) else stats
