"""Exact optimum by enumeration of the behaviour-class alteration space (the test oracle).

Every combination of per-observation candidates whose cost fits the largest budget is evaluated
exactly; the best one within each budget is the optimum there, so one run gives the whole
budget curve.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from misdirect.alterations import alteration_space
from misdirect.errors import SolverError
from misdirect.evaluate import decoy_probability
from misdirect.model import Problem
from misdirect.solvers.base import ProgressCallback, Solution, best_per_budget


class ExhaustiveSolver:
    name = "exhaustive"
    curve_is_free = True

    def __init__(self, max_evaluations: int = 2_000_000):
        self.max_evaluations = max_evaluations

    def solve(
        self,
        problem: Problem,
        budgets: Sequence[float],
        *,
        progress: ProgressCallback | None = None,
    ) -> list[Solution]:
        top = max(budgets)
        space = alteration_space(problem.with_budget(top))
        enumerated = space.within(top, limit=self.max_evaluations)
        if enumerated is None:
            raise SolverError(
                f"more than {self.max_evaluations:,} alterations fit the budget; "
                "exhaustive search would take too long (try --method milp)"
            )
        table, costs = enumerated
        values = np.empty(len(costs))
        alterations = []
        for i, picked in enumerate(table):
            alpha = space.alteration(problem, picked)
            alterations.append(alpha)
            values[i] = decoy_probability(problem, alpha)
            if progress is not None:
                progress(i + 1, len(costs))
        stats = {
            "evaluations": len(costs),
            "relevant_observations": len(space.choices),
            "candidates_per_observation": [c.size for c in space.choices],
        }
        return [
            Solution(
                budget=b,
                alteration=alterations[i],
                claimed_probability=float(values[i]),
                upper_bound=float(values[i]),
                stats=stats,
            )
            for b, i in zip(budgets, best_per_budget(costs, values, budgets), strict=True)
        ]
