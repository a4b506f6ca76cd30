"""The attacker's real choices: per relevant observation, one candidate per behaviour class.

Two targets on which the controller acts identically (same γ and δ on every node) lead to the
same product chain, so only the cheapest one of each class is worth paying for. This turns the
``|Ω|^|Ω|`` alteration functions into a product of a few choices per observation, and it is the
shared search space of the exhaustive solver and the MILP.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from misdirect.model import Problem


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
