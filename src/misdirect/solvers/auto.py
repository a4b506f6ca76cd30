"""``--method auto``: enumerate when the alteration space is small, otherwise the MILP.

Both are exact; the choice is only about time. Enumeration costs one exact evaluation per
alteration that fits the budget and gives the whole budget curve at once; the MILP's cost does
not grow with the number of alterations. The answer records which method certified it.
"""

from __future__ import annotations

from collections.abc import Sequence
from itertools import islice
from typing import Any

from misdirect.alterations import alteration_space
from misdirect.model import Problem
from misdirect.solvers.base import ProgressCallback, Solution
from misdirect.solvers.exhaustive import ExhaustiveSolver, _combinations
from misdirect.solvers.milp import MilpSolver

ENUMERATION_LIMIT = 5_000  # alterations within the budget; above this the MILP takes over


class AutoSolver:
    name = "auto"
    curve_is_free = False

    def __init__(self, enumeration_limit: int = ENUMERATION_LIMIT, **milp_options: Any):
        self.enumeration_limit = enumeration_limit
        self.milp = MilpSolver(**milp_options)  # validates the options up front

    def solve(
        self,
        problem: Problem,
        budgets: Sequence[float],
        *,
        progress: ProgressCallback | None = None,
    ) -> list[Solution]:
        top = max(budgets)
        space = alteration_space(problem.with_budget(top))
        count = sum(1 for _ in islice(_combinations(space, top), self.enumeration_limit + 1))
        small = count <= self.enumeration_limit
        inner = ExhaustiveSolver() if small else self.milp
        solutions = inner.solve(problem, budgets, progress=progress)
        reason = (
            f"{count:,} alterations fit the budget"
            if small
            else f"more than {self.enumeration_limit:,} alterations fit the budget"
        )
        return [
            Solution(
                budget=s.budget,
                alteration=s.alteration,
                claimed_probability=s.claimed_probability,
                status=s.status,
                upper_bound=s.upper_bound,
                stats={**s.stats, "certified_by": inner.name, "auto_reason": reason},
            )
            for s in solutions
        ]
