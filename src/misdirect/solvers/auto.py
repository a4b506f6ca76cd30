"""``--method auto``: the fastest exact method for the model's shape.

1. ``incremental`` (one factorisation per outer choice, a tiny Woodbury solve per alteration)
   when the chain cannot cycle without reaching the decoy and at most 200,000 alterations fit;
2. ``exhaustive`` (one exact evaluation per alteration) when at most 5,000 fit;
3. the MILP otherwise: its cost does not grow with the number of alterations.

All are exact; the answer records which method certified it and why.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from misdirect.alterations import alteration_space
from misdirect.model import Problem
from misdirect.solvers.base import ProgressCallback, Solution
from misdirect.solvers.exhaustive import ExhaustiveSolver
from misdirect.solvers.incremental import IncrementalSolver, NotApplicableError
from misdirect.solvers.milp import MilpSolver

ENUMERATION_LIMIT = 5_000  # alterations within the budget for plain enumeration
INCREMENTAL_LIMIT = 200_000  # ... and for enumeration with low-rank updates


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
        enumerated = space.within(top, limit=INCREMENTAL_LIMIT)
        count = INCREMENTAL_LIMIT + 1 if enumerated is None else len(enumerated[1])
        reason = (
            f"{count:,} alterations fit the budget"
            if count <= INCREMENTAL_LIMIT
            else f"more than {INCREMENTAL_LIMIT:,} alterations fit the budget"
        )
        solutions = None
        if count <= INCREMENTAL_LIMIT:
            inner: Any = IncrementalSolver()
            try:
                solutions = inner.solve(problem, budgets, progress=progress)
            except NotApplicableError:
                reason += "; no low-rank updates: the chain can cycle without reaching the decoy"
        if solutions is None:
            inner = ExhaustiveSolver() if count <= self.enumeration_limit else self.milp
            solutions = inner.solve(problem, budgets, progress=progress)
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
