"""``--method incremental``: the whole budget curve by the low-rank enumeration.

Every alteration within the largest budget is valued
(:mod:`misdirect.solvers.engines.lowrank`: one base solve per outer choice, a tiny Woodbury
solve per alteration), so one run gives the optimum at every budget. Cut short by its
deadline, it has still valued every alteration of the budgets below the first outer block it
did not reach (those stay proven); the others get the per-state relaxation's bound.

With a time limit, a curve is enumerated budget by budget, smallest first, each run over
every alteration within its budget: the small budgets are proven even when the large one
cannot be (a single run cut inside its first block proves none). The runs before the last
cost a fraction of it, since the count of alterations grows steeply with the budget. A
caller with a search to hand budgets to (auto) asks it to stop before a budget whose
enumeration, at the rate measured on the budget before, would not fit its fair share of the
time left (:func:`~misdirect.solvers.schedule.next_level_fits`): those budgets come back
uncertified, with the time to search them still left.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from typing import ClassVar, cast

import numpy as np

from misdirect.core import tolerance
from misdirect.core.attack import AttackInstance, prepare
from misdirect.core.evaluate import decoy_probability
from misdirect.core.model import Problem
from misdirect.solvers import schedule
from misdirect.solvers.base import (
    ProgressCallback,
    Solution,
    method_deadline,
    report,
    thread_count,
)
from misdirect.solvers.deadline import Deadline
from misdirect.solvers.engines.alarm import (
    AlarmConstraint,
    Verdict,
    alarm_constraint,
    best_feasible,
)
from misdirect.solvers.engines.lowrank import (
    MAX_ALTERATIONS,
    Enumerated,
    LowRankEnumeration,
    NotApplicableError,
)
from misdirect.solvers.engines.per_state import relaxation_bound
from misdirect.solvers.options import SolveOptions
from misdirect.solvers.stats import IncrementalStats
from misdirect.solvers.status import Status, StopReason

__all__ = ["IncrementalSolver", "NotApplicableError"]

# under max_alarm, the exact verdicts tried on the best candidates before every alarm is
# enumerated (one verdict costs about what valuing one alteration on its own chain does)
LAZY_VERDICTS = 256


class IncrementalSolver:
    name: ClassVar[str] = "incremental"
    curve_is_free: ClassVar[bool] = True
    accepts: ClassVar[tuple[str, ...]] = ("time_limit", "threads", "max_alarm")

    def __init__(
        self,
        options: SolveOptions | None = None,
        *,
        max_evaluations: int = MAX_ALTERATIONS,
        hand_over: bool = False,
    ):
        self.options = options or SolveOptions()
        self.max_evaluations = max_evaluations
        # stop before a budget that will not fit (someone else searches it): see the module
        self.hand_over = hand_over
        self.threads = thread_count(self.options.threads)

    def solve(
        self,
        problem: Problem,
        budgets: Sequence[float],
        *,
        progress: ProgressCallback | None = None,
        deadline: Deadline | None = None,
    ) -> list[Solution]:
        deadline = method_deadline(deadline, self.options.time_limit)
        top = max(budgets)
        if self.options.alarm_limit is not None:
            constraint = alarm_constraint(problem, self.options.alarm_limit)
            return self._constrained(constraint, budgets, deadline, progress)
        instance = prepare(problem, top)
        enumeration = LowRankEnumeration(
            instance, threads=self.threads, max_evaluations=self.max_evaluations
        )
        if not instance.space.choices:
            value = decoy_probability(problem, problem.identity())
            return [
                Solution(
                    b,
                    problem.identity(),
                    value,
                    upper_bound=value,
                    stop_reason=StopReason.FINISHED,
                )
                for b in budgets
            ]
        runs = self._runs(enumeration, budgets, deadline, progress, self.hand_over)
        last = runs[-1][1]
        stats = IncrementalStats(
            evaluations=sum(found.evaluations for _, found in runs),
            factorisations=sum(found.base_solves for _, found in runs),
            inner_observations=len(last.inner),
            outer_observations=len(last.outer),
        )
        chosen = [_covering(runs, b) for b in budgets]
        complete = [found.complete_for(b) for b, found in zip(budgets, chosen, strict=True)]
        # the relaxation at the largest budget bounds every smaller one too
        if not all(complete):
            report(progress, 0, 0, stage="bounds")  # the relaxation bounds what was not valued
        relaxed = (
            None
            if all(complete)
            else relaxation_bound(problem, top, schedule.closing_bound(deadline))
        )
        solutions = []
        cut = StopReason.cut(deadline.cancelled)
        for budget, found, finished in zip(budgets, chosen, complete, strict=True):
            within = found.values[found.costs <= problem.cost.scale.cap(budget)]
            if not within.size:  # the deadline left nothing valued within it: alter nothing
                solutions.append(
                    Solution(
                        budget=budget,
                        alteration=problem.identity(),
                        solver_probability=None,
                        status=Status.TIME_LIMIT,
                        upper_bound=problem.objective.max_value if relaxed is None else relaxed,
                        stats=stats,
                        stop_reason=cut,
                    )
                )
                continue
            index = found.best_within([budget])[0]
            bound = _best_fitting_value(found, budget, float(found.values[index]))
            if relaxed is not None and not finished:
                bound = max(bound, relaxed)
            solutions.append(
                Solution(
                    budget=budget,
                    alteration=instance.space.alteration(problem, found.picks(index)),
                    solver_probability=float(found.values[index]),
                    status=Status.OPTIMAL if finished else Status.TIME_LIMIT,
                    upper_bound=bound,
                    stats=stats,
                    stop_reason=StopReason.FINISHED if finished else cut,
                )
            )
        return solutions

    def _constrained(
        self,
        constraint: AlarmConstraint,
        budgets: Sequence[float],
        deadline: Deadline,
        progress: ProgressCallback | None,
    ) -> list[Solution]:
        """Under ``max_alarm``: the enumeration of the decoy's value over the space of both
        values (:mod:`~misdirect.solvers.engines.alarm`), then per budget the best alteration
        proven feasible (:meth:`~.AlarmConstraint.verdict`), best candidates first. Past
        :data:`LAZY_VERDICTS` exact verdicts, the alarm's value is enumerated too (the same
        space, valued in the same order), and rules out what lies clearly above δ."""
        problem, top = constraint.problem, max(budgets)
        instance = prepare(constraint.decoy_problem, top)
        alarm_instance = prepare(constraint.alarm_problem, top)
        if not instance.space.choices:  # only the unaltered chain
            identity = problem.identity()
            feasible = constraint.verdict(identity) == Verdict.FEASIBLE
            value = decoy_probability(problem, identity)
            return [
                Solution(
                    b,
                    identity,
                    value if feasible else None,
                    status=Status.OPTIMAL if feasible else Status.INFEASIBLE,
                    upper_bound=value if feasible else None,
                    stop_reason=StopReason.FINISHED,
                )
                for b in budgets
            ]
        if not _same_space(instance, alarm_instance):
            raise NotApplicableError("the decoy's and the alarm's alteration spaces differ")
        memo = constraint.memo  # a trade-off curve's other δ may have enumerated them
        found = cast(Enumerated | None, memo.get(("incremental", top)))
        if found is None:
            found = LowRankEnumeration(
                instance, threads=self.threads, max_evaluations=self.max_evaluations
            ).run(top, deadline=deadline, progress=progress)
            if found.complete_for(top):
                memo[("incremental", top)] = found
        alarms = cast(Enumerated | None, memo.get(("incremental alarms", top)))
        picked: list[tuple[int | None, float]] | None = None
        if alarms is None:  # lazily: the exact verdicts of the best candidates first
            try:
                picked = self._pick(
                    constraint, instance, found, budgets, None, _lazy(found, constraint)
                )
            except _TooManyVerdictsError:  # the constraint cuts deep: value every alarm
                alarms = LowRankEnumeration(
                    alarm_instance, threads=self.threads, max_evaluations=self.max_evaluations
                ).run(top, deadline=deadline)
                if alarms.complete_for(top):
                    memo[("incremental alarms", top)] = alarms
        if picked is None:
            picked = self._pick(constraint, instance, found, budgets, alarms, None)
        aligned = alarms is not None and np.array_equal(alarms.costs, found.costs)
        stats = IncrementalStats(
            evaluations=found.evaluations + (0 if alarms is None else alarms.evaluations),
            factorisations=found.base_solves + (0 if alarms is None else alarms.base_solves),
            inner_observations=len(found.inner),
            outer_observations=len(found.outer),
        )
        solutions = []
        top_value = problem.objective.max_value
        cut = StopReason.cut(deadline.cancelled)
        for budget, (index, undecided) in zip(budgets, picked, strict=True):
            complete = found.complete_for(budget) and (
                alarms is None or aligned or alarms.complete_for(budget)
            )
            if index is None:
                proven = complete and undecided < 0
                solutions.append(
                    Solution(
                        budget,
                        problem.identity(),
                        None,
                        status=Status.INFEASIBLE if proven else Status.TIME_LIMIT,
                        upper_bound=None if proven else top_value,
                        stats=stats,
                        stop_reason=StopReason.FINISHED if complete else cut,
                    )
                )
                continue
            value = float(found.values[index])
            solutions.append(
                Solution(
                    budget,
                    instance.space.alteration(problem, found.picks(index)),
                    value,
                    status=Status.OPTIMAL if complete else Status.TIME_LIMIT,
                    upper_bound=max(value, undecided) if complete else top_value,
                    stats=stats,
                    stop_reason=StopReason.FINISHED if complete else cut,
                )
            )
        return solutions

    @staticmethod
    def _pick(
        constraint: AlarmConstraint,
        instance: AttackInstance,
        found: Enumerated,
        budgets: Sequence[float],
        alarms: Enumerated | None,
        most: int | None,
    ) -> list[tuple[int | None, float]]:
        """Per budget, :func:`~misdirect.solvers.engines.alarm.best_feasible` over ``found``:
        with ``alarms`` (aligned), those clearly above δ ruled out by their value; ``most``:
        raise :class:`_TooManyVerdictsError` past that many exact verdicts."""
        aligned = alarms is not None and np.array_equal(alarms.costs, found.costs)
        excluded = None
        if alarms is not None and aligned:
            excluded = alarms.values > constraint.limit + tolerance.ALARM_MARGIN
        asked = 0

        def verdict(index: int) -> Verdict:
            nonlocal asked
            asked += 1
            if most is not None and asked > most:
                raise _TooManyVerdictsError
            estimate = float(alarms.values[index]) if alarms is not None and aligned else None
            alpha = instance.space.alteration(constraint.problem, found.picks(index))
            return constraint.verdict(alpha, estimate)

        return [
            best_feasible(
                found.costs,
                found.values,
                budget,
                found.scale,
                verdict,
                excluded=excluded,
                tie=tolerance.NEAR_TIE,
                terms=found.terms,
            )
            for budget in budgets
        ]

    @staticmethod
    def _runs(
        enumeration: LowRankEnumeration,
        budgets: Sequence[float],
        deadline: Deadline,
        progress: ProgressCallback | None,
        hand_over: bool = False,
    ) -> list[tuple[float, Enumerated]]:
        """(budget, run) of each enumeration: one at the largest budget without a time limit,
        else one per budget, smallest first, until one is cut short (``hand_over``: or until
        the next will not fit its share of the time left)."""
        levels = sorted(set(budgets))
        space = enumeration.instance.space
        counts = [space.count_within(level, enumeration.max_evaluations) for level in levels]
        if deadline.remaining() is None:
            levels, counts = levels[-1:], counts[-1:]
        else:  # a budget whose next one is cheap to enumerate too is proven by that run
            kept = [j for j in range(len(levels) - 1) if counts[j + 1] > schedule.STAGE_FROM]
            kept.append(len(levels) - 1)
            levels, counts = [levels[j] for j in kept], [counts[j] for j in kept]
        runs: list[tuple[float, Enumerated]] = []
        measured: schedule.Measured | None = None
        # with end components the search's bound stays near the largest value whatever the
        # budget (docs/benchmarks.md, "Chains with cycles")
        search_sees_budget = not enumeration.instance.cycling.any()
        for level, count in zip(levels, counts, strict=True):
            if (
                hand_over
                and runs
                and not schedule.next_level_fits(
                    count,
                    enumeration.bases_within(level),
                    measured,
                    deadline,
                    search_sees_budget=search_sees_budget,
                )
            ):
                break
            began = time.perf_counter()
            share = (
                schedule.fair_share(deadline, search_sees_budget=search_sees_budget)
                if hand_over
                else None
            )
            found = enumeration.run(level, deadline=deadline, progress=progress, share=share)
            measured = schedule.Measured(
                time.perf_counter() - began,
                found.evaluations,
                found.base_solves,
                found.base_seconds,
            )
            runs.append((level, found))
            if not found.complete_for(level):
                break
        return runs


def _best_fitting_value(found: Enumerated, budget: float, answer: float) -> float:
    """The best value of an alteration within ``budget`` (every one was enumerated): the
    answer's, or that of one its tie let pass; a cost the scale calls ambiguous counts only
    if its terms fit."""
    scale = found.scale
    surely = found.values[found.costs <= scale.sure_cap(budget)]
    best = max(answer, float(surely.max(initial=-np.inf)))
    unsure = np.flatnonzero(scale.ambiguous(found.costs, budget) & (found.values > best))
    for i in unsure[np.argsort(-found.values[unsure])].tolist():
        if scale.fits_exactly(found.terms(i), budget):
            return float(found.values[i])
    return best


def _lazy(found: Enumerated, constraint: AlarmConstraint) -> int | None:
    """How many exact verdicts the lazy walk may ask for (None: any): for δ = 0 any (a
    verdict is a graph search, cheaper than valuing an alarm); where the enumeration valued
    each alteration on its own chain, as many as it valued (a verdict costs about one); else
    :data:`LAZY_VERDICTS` (low-rank updates value the alarms far more cheaply)."""
    if constraint.limit == 0.0:
        return None
    return int(found.values.size) if not found.inner else LAZY_VERDICTS


class _TooManyVerdictsError(Exception):
    """The lazy walk asked for more exact verdicts than enumerating every alarm would cost."""


def _same_space(first: AttackInstance, second: AttackInstance) -> bool:
    """Whether two instances offer the same options, in the same order."""
    a, b = first.space.choices, second.space.choices
    return len(a) == len(b) and all(
        x.observation == y.observation and np.array_equal(x.targets, y.targets)
        for x, y in zip(a, b, strict=True)
    )


def _covering(runs: list[tuple[float, Enumerated]], budget: float) -> Enumerated:
    """The run that answers ``budget``: the first whose budget covers it and that valued every
    alteration within it, else the last one (the largest, cut short)."""
    for level, found in runs:
        if level >= budget and found.complete_for(budget):
            return found
    return runs[-1][1]
