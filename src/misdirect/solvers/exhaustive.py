"""Exact optimum by enumeration of the behaviour-class alteration space (the test oracle).

Every combination of per-observation candidates whose cost fits the largest budget is evaluated
exactly; the best one within each budget is the optimum there, so one run gives the whole
budget curve.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence

import numpy as np

from misdirect.alterations import AlterationSpace, alteration_space
from misdirect.errors import SolverError
from misdirect.evaluate import decoy_probability
from misdirect.model import Problem
from misdirect.solvers.base import ProgressCallback, Solution, best_per_budget


def _combinations(space: AlterationSpace, budget: float) -> Iterator[tuple[tuple[int, ...], float]]:
    """All choice vectors (one candidate index per observation) with total cost ≤ budget."""
    choices = space.choices

    def walk(depth: int, picked: tuple[int, ...], spent: float):
        if depth == len(choices):
            yield picked, spent
            return
        for k, cost in enumerate(choices[depth].costs):
            if spent + cost <= budget + 1e-9:
                yield from walk(depth + 1, (*picked, k), spent + cost)

    yield from walk(0, (), 0.0)


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
        combos = []
        for combo in _combinations(space, top):
            combos.append(combo)
            if len(combos) > self.max_evaluations:
                raise SolverError(
                    f"more than {self.max_evaluations:,} alterations fit the budget; "
                    "exhaustive search would take too long (try --method milp)"
                )
        costs = np.array([spent for _, spent in combos])
        values = np.empty(len(combos))
        alterations = []
        for i, (picked, _) in enumerate(combos):
            alpha = problem.identity()
            for choice, k in zip(space.choices, picked, strict=True):
                alpha[choice.observation] = choice.targets[k]
            alterations.append(alpha)
            values[i] = decoy_probability(problem, alpha)
            if progress is not None:
                progress(i + 1, len(combos))
        stats = {
            "evaluations": len(combos),
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
