"""What a solver hands back, and the interface every solver implements.

A solver only proposes alterations. :func:`misdirect.solve` then re-computes every value
exactly with the evaluator, so no number a user sees depends on a solver's arithmetic.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from misdirect.model import Alteration, Problem

ProgressCallback = Callable[[int, int], None]  # (done, total)


@dataclass(frozen=True)
class Solution:
    """One solver answer for one budget."""

    budget: float
    alteration: Alteration
    claimed_probability: float  # the solver's own value for it
    status: str = "optimal"  # "optimal" | "time_limit" | "feasible"
    upper_bound: float | None = None  # proven bound on the optimum, if the solver has one
    stats: dict[str, Any] = field(default_factory=dict)


class Solver(Protocol):
    name: str
    curve_is_free: bool  # solving for B also yields the optimum at every smaller budget

    def solve(
        self,
        problem: Problem,
        budgets: Sequence[float],
        *,
        progress: ProgressCallback | None = None,
    ) -> list[Solution]:
        """One :class:`Solution` per budget, in the order given."""
        ...


def best_per_budget(
    costs: np.ndarray, values: np.ndarray, budgets: Sequence[float], tolerance: float = 1e-12
) -> list[int]:
    """Index of the best candidate within each budget: highest value, then lowest cost.

    Preferring the cheaper of two equally good alterations means the answer never spends more of
    the budget than it needs.
    """
    picks = []
    for budget in budgets:
        within = np.flatnonzero(costs <= budget + 1e-9)
        best = values[within].max()
        tied = within[values[within] >= best - tolerance]
        picks.append(int(tied[np.argmin(costs[tied])]))
    return picks
