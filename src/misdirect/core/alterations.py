"""The attacker's real choices: per relevant observation, one candidate per behaviour class.

Two targets on which the controller acts identically (same γ and δ on every node) lead to the
same product chain, so only the cheapest one of each class is worth paying for. This turns the
``|Ω|^|Ω|`` alteration functions into a product of a few choices per observation, and it is the
shared search space of the exhaustive solver and the MILP.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from misdirect.core.model import Problem


@dataclass(frozen=True)
class ObservationChoices:
    """Candidates for one observation; index 0 is always "leave it unaltered" (cost 0)."""

    observation: int
    targets: np.ndarray  # candidate received observations, one per behaviour class
    costs: np.ndarray

    @property
    def size(self) -> int:
        return int(self.targets.size)


@dataclass(frozen=True)
class AlterationSpace:
    choices: tuple[ObservationChoices, ...]

    @property
    def size(self) -> int:
        """Number of alterations (before the budget) the space contains."""
        return int(np.prod([c.size for c in self.choices], dtype=float))

    def within(
        self,
        budget: float,
        indices: Sequence[int] | None = None,
        limit: int | None = None,
    ) -> tuple[np.ndarray, np.ndarray] | None:
        """Every choice vector with total cost ≤ ``budget``: (candidate index table, costs).

        Over the choices at ``indices`` (default: all). Grown one observation at a time,
        dropping partial vectors already over the budget; since candidate 0 is free, a
        partial vector always completes, so ``None`` (more than ``limit``) is known early.
        """
        costs = np.zeros(1)
        steps = []  # per choice: (row of the previous step each vector extends, its option)
        for i in range(len(self.choices)) if indices is None else indices:
            grown = costs[:, None] + np.asarray(self.choices[i].costs, dtype=np.float64)
            keep_row, keep_option = np.nonzero(grown <= budget + 1e-9)
            if limit is not None and keep_row.size > limit:
                return None
            steps.append((keep_row, keep_option))
            costs = grown[keep_row, keep_option]
        # the table is read back from the last step to the first: growing it column by column
        # would copy the whole table once per choice
        table = np.zeros((costs.size, len(steps)), dtype=np.int64)
        row = np.arange(costs.size)
        for j in range(len(steps) - 1, -1, -1):
            keep_row, keep_option = steps[j]
            table[:, j] = keep_option[row]
            row = keep_row[row]
        return table, costs

    def count_within(self, budget: float, limit: int) -> int:
        """How many choice vectors cost at most ``budget`` (``limit + 1`` once it is more than
        ``limit``), without listing them: a count per distinct total cost."""
        counts = {0.0: 1}
        for choice in self.choices:
            grown: dict[float, int] = {}
            for total, count in counts.items():
                for cost in np.asarray(choice.costs, dtype=np.float64).tolist():
                    key = round(total + cost, 9)
                    if key <= budget + 1e-9:
                        grown[key] = grown.get(key, 0) + count
            counts = grown
            if sum(counts.values()) > limit:
                return limit + 1
        return sum(counts.values())

    def alteration(self, problem: Problem, picked: Sequence[int], indices=None) -> np.ndarray:
        """The alteration that takes candidate ``picked[j]`` for the ``j``-th choice."""
        alpha = problem.identity()
        for i, k in zip(
            range(len(self.choices)) if indices is None else indices, picked, strict=True
        ):
            choice = self.choices[i]
            alpha[choice.observation] = choice.targets[k]
        return alpha


def alteration_space(problem: Problem) -> AlterationSpace:
    """Cheapest target per behaviour class for every observation that can matter."""
    classes = problem.controller.behaviour_class
    choices = []
    for o in problem.relevant_observations:
        o = int(o)
        costs = problem.cost.row(o)
        allowed = np.flatnonzero(np.isfinite(costs) & (costs <= problem.budget + 1e-9))
        # cheapest per class; ties go to the lowest index, and o itself (cost 0) wins its class
        order = allowed[np.lexsort((allowed, allowed != o, costs[allowed]))]
        _, first = np.unique(classes[order], return_index=True)
        picked = order[np.sort(first)]
        picked = np.concatenate([[o], picked[picked != o]])
        if picked.size > 1:
            choices.append(ObservationChoices(o, picked, costs[picked]))
    return AlterationSpace(tuple(choices))


def max_alteration_cost(problem: Problem) -> float:
    """Cost of the most expensive complete alteration: for every relevant observation, its
    most expensive finite alteration. Any budget at least this large affords every alteration,
    so it is "no limit" and solvers never need to look beyond it (budgets are clamped to it).

    Read off the cost model's default and overrides, without a dense ``|Ω|`` row per
    observation."""
    cost = problem.cost
    n = cost.n_observations
    overrides = cost._pairs_by_source
    total = 0.0
    for o in problem.relevant_observations.tolist():
        if o in cost.protected:
            continue
        targets, values = overrides.get(o, (np.zeros(0, dtype=np.int64), np.zeros(0)))
        listed = values[(targets != o)]
        finite = listed[np.isfinite(listed)]
        most = float(finite.max()) if finite.size else 0.0
        uncovered = n - 1 - np.unique(targets[targets != o]).size  # targets at the default
        if uncovered > 0 and math.isfinite(cost.default):
            most = max(most, float(cost.default))
        total += most
    return total
