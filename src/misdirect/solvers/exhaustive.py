"""Exact optimum by enumeration of the behaviour-class alteration space (the test oracle).

Every combination of per-observation candidates whose cost fits the largest budget is evaluated
exactly; the best one within each budget is the optimum there, so one run gives the whole
budget curve. Stopped by its deadline, it reports the best alteration seen so far with status
``time_limit`` and the root bound of the per-state relaxation.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import ClassVar

import numpy as np

from misdirect.core.attack import prepare
from misdirect.core.evaluate import decoy_value
from misdirect.core.model import Problem
from misdirect.errors import SolverError
from misdirect.solvers import schedule
from misdirect.solvers.base import (
    ProgressCallback,
    Solution,
    best_per_budget,
    method_deadline,
    report,
)
from misdirect.solvers.deadline import Deadline
from misdirect.solvers.engines.alarm import AlarmConstraint, alarm_constraint, best_feasible
from misdirect.solvers.engines.per_state import relaxation_bound
from misdirect.solvers.options import SolveOptions
from misdirect.solvers.stats import ExhaustiveStats
from misdirect.solvers.status import Status, StopReason

MAX_EVALUATIONS = 2_000_000  # alterations it takes on (more: it refuses, naming the MILP)


class ExhaustiveSolver:
    name: ClassVar[str] = "exhaustive"
    curve_is_free: ClassVar[bool] = True
    accepts: ClassVar[tuple[str, ...]] = ("time_limit", "max_alarm")

    def __init__(
        self, options: SolveOptions | None = None, *, max_evaluations: int = MAX_EVALUATIONS
    ):
        self.options = options or SolveOptions()
        self.max_evaluations = max_evaluations

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
        constraint = (
            None
            if self.options.alarm_limit is None
            else alarm_constraint(problem, self.options.alarm_limit)
        )
        # under a constraint, the space of both values (engines.alarm): the same values
        space = prepare(problem if constraint is None else constraint.decoy_problem, top).space
        enumerated = space.within(top, limit=self.max_evaluations)
        if enumerated is None:
            raise SolverError(
                f"more than {self.max_evaluations:,} alterations fit the budget; "
                'exhaustive search would take too long (try method="milp")'
            )
        table, costs = enumerated
        # cheapest first ("alter nothing" leads): cut short, every budget up to the last cost
        # enumerated completely is still proven
        order = np.argsort(costs, kind="stable")
        table, costs = table[order], costs[order]
        values = np.full(len(costs), -np.inf)
        worst_error = 0.0  # of the values evaluated: the best one may be off by as much
        alterations: dict[int, np.ndarray] = {}
        done = 0
        for i, picked in enumerate(table):
            if i > 0 and deadline.expired():  # "alter nothing" (row 0) is always evaluated
                break
            alpha = space.alteration(problem, picked)
            alterations[i] = alpha
            values[i], error = decoy_value(problem, alpha)
            worst_error = max(worst_error, error)
            done = i + 1
            report(progress, done, len(costs), stage="exhaustive")
        finished = done == len(costs)
        stats = ExhaustiveStats(
            evaluations=done,
            alterations_within_budget=len(costs),
            relevant_observations=len(space.choices),
            candidates_per_observation=[c.size for c in space.choices],
        )
        # a budget is proven when every alteration it affords was evaluated
        complete = [finished or costs[done] > problem.cost.scale.cap(b) for b in budgets]
        if constraint is not None:
            return _constrained(
                constraint,
                budgets,
                costs[:done],
                values[:done],
                alterations,
                complete,
                stats,
                worst_error,
            )
        picks = best_per_budget(
            costs[:done],
            values[:done],
            budgets,
            problem.cost.scale,
            terms=lambda i: problem.cost.terms(alterations[i]),
        )
        # the relaxation at the largest budget bounds every smaller one too
        bound = (
            None
            if all(complete)
            else relaxation_bound(problem, top, schedule.closing_bound(deadline))
        )
        top_value = problem.objective.max_value
        cut = StopReason.cut(deadline.cancelled)
        return [
            Solution(
                b,
                alterations[i],
                float(values[i]),
                status=Status.OPTIMAL if proven else Status.TIME_LIMIT,
                upper_bound=_bound(float(values[i]), proven, bound, worst_error, top_value),
                stats=stats,
                # cheapest first: a budget whose every alteration was evaluated is finished
                stop_reason=StopReason.FINISHED if proven else cut,
            )
            for b, i, proven in zip(budgets, picks, complete, strict=True)
        ]


def _constrained(
    constraint: AlarmConstraint,
    budgets: Sequence[float],
    costs: np.ndarray,
    values: np.ndarray,
    alterations: dict[int, np.ndarray],
    complete: list[bool],
    stats: ExhaustiveStats,
    error: float,
) -> list[Solution]:
    """Under ``max_alarm``: per budget the best alteration proven feasible, every one evaluated
    exactly (value and verdict); a budget with none is ``infeasible`` when every alteration it
    affords was evaluated and none is undecided. An undecided alteration worth more than the
    answer keeps its value in the bound (the answer is then not certified); so does the
    largest proven ``error`` of the values compared. A budget not evaluated completely has
    only the objective's largest value as its bound."""
    problem = constraint.problem
    top = problem.objective.max_value
    solutions = []
    for budget, proven in zip(budgets, complete, strict=True):
        index, undecided = best_feasible(
            costs,
            values,
            budget,
            problem.cost.scale,
            lambda i: constraint.verdict(alterations[i]),
            terms=lambda i: problem.cost.terms(alterations[i]),
        )
        stop = StopReason.FINISHED if proven else StopReason.TIME
        if index is None:
            solutions.append(
                Solution(
                    budget,
                    problem.identity(),
                    None,
                    status=Status.INFEASIBLE if proven and undecided < 0 else Status.TIME_LIMIT,
                    upper_bound=None if proven and undecided < 0 else top,
                    stats=stats,
                    stop_reason=stop,
                )
            )
            continue
        value = float(values[index])
        bound = min(max(value, undecided) + error, top) if proven else top
        solutions.append(
            Solution(
                budget,
                alterations[index],
                value,
                status=Status.OPTIMAL if proven else Status.TIME_LIMIT,
                upper_bound=bound,
                stats=stats,
                stop_reason=stop,
            )
        )
    return solutions


def _bound(value: float, proven: bool, relaxed: float | None, error: float, top: float) -> float:
    """A budget whose every alteration was evaluated is bounded by its best value, plus the
    largest proven error of the values compared (at most ``top``, the objective's maximum)."""
    bound = min(value + error, top)
    return bound if proven or relaxed is None else max(bound, relaxed)
