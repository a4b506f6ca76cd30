"""``--method incremental``: the whole budget curve by the low-rank enumeration.

Every alteration within the largest budget is valued
(:mod:`misdirect.solvers.engines.lowrank`: one base solve per outer choice, a tiny Woodbury
solve per alteration), so one run gives the optimum at every budget. Cut short by its
deadline, it has still valued every alteration of the budgets below the first outer block it
did not reach (those stay proven); the others get the per-state relaxation's bound.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import ClassVar

from misdirect.core.attack import prepare
from misdirect.core.evaluate import decoy_probability
from misdirect.core.model import Problem
from misdirect.solvers import schedule
from misdirect.solvers.base import ProgressCallback, Solution, thread_count
from misdirect.solvers.deadline import Deadline
from misdirect.solvers.engines.lowrank import (
    MAX_ALTERATIONS,
    LowRankEnumeration,
    NotApplicableError,
)
from misdirect.solvers.engines.per_state import relaxation_bound
from misdirect.solvers.options import SolveOptions
from misdirect.solvers.stats import IncrementalStats
from misdirect.solvers.status import Status

__all__ = ["IncrementalSolver", "NotApplicableError"]


class IncrementalSolver:
    name: ClassVar[str] = "incremental"
    curve_is_free: ClassVar[bool] = True
    accepts: ClassVar[tuple[str, ...]] = ("time_limit", "threads")

    def __init__(
        self, options: SolveOptions | None = None, *, max_evaluations: int = MAX_ALTERATIONS
    ):
        self.options = options or SolveOptions()
        self.max_evaluations = max_evaluations
        self.threads = thread_count(self.options.threads)

    def solve(
        self,
        problem: Problem,
        budgets: Sequence[float],
        *,
        progress: ProgressCallback | None = None,
        deadline: Deadline | None = None,
    ) -> list[Solution]:
        deadline = deadline or Deadline(self.options.time_limit)
        top = max(budgets)
        instance = prepare(problem, top)
        enumeration = LowRankEnumeration(
            instance, threads=self.threads, max_evaluations=self.max_evaluations
        )
        if not instance.space.choices:
            value = decoy_probability(problem, problem.identity())
            return [Solution(b, problem.identity(), value, upper_bound=value) for b in budgets]
        found = enumeration.run(top, deadline=deadline, progress=progress)
        stats = IncrementalStats(
            evaluations=found.evaluations,
            factorisations=found.blocks_done,
            inner_observations=len(found.inner),
            outer_observations=len(found.outer),
        )
        complete = [found.complete_for(b) for b in budgets]
        # the relaxation at the largest budget bounds every smaller one too
        relaxed = (
            None
            if all(complete)
            else relaxation_bound(problem, top, schedule.closing_bound(deadline))
        )
        solutions = []
        for budget, index, finished in zip(
            budgets, found.best_within(budgets), complete, strict=True
        ):
            within = found.values[found.costs <= problem.cost.scale.cap(budget)]
            bound = float(within.max())  # every alteration within the budget was enumerated
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
                )
            )
        return solutions
