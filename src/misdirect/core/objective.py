"""What the attacker maximises: the expected weight of the first decoy state the robot enters.

One decoy set of weight 1 (the paper's problem) makes this the probability of reaching the
decoy. Several weighted sets (``decoy: {trap: 1.0, guard_post: 0.4}``) rank them: a run scores
the weight of the first decoy state it enters, and 0 if it never enters one. Either way the
decoy states stop the run as far as the objective goes, so every solver sees the same shape:
a target mask and a value per target state, and everything else is reachability.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
import scipy.sparse as sp

# what the number means, by ``Objective.kind`` (the JSON's "objective"), for tables and plots
LABELS = {"probability": "Pr(reach decoy)", "expected_decoy_weight": "expected decoy weight"}


@dataclass(frozen=True, eq=False)
class DecoySet:
    """One named set of decoy states and the attacker's reward for leading the robot there."""

    name: str
    weight: float
    states: np.ndarray  # (|S|,) bool


@dataclass(frozen=True, eq=False)
class Objective:
    """Target mask and per-state value; ``sets`` keeps the sets as the user named them."""

    target: np.ndarray  # (|S|,) bool: decoy states (the first one entered decides the score)
    value: np.ndarray  # (|S|,) float ≥ 0: the weight of each decoy state, 0 elsewhere
    sets: tuple[DecoySet, ...] = ()

    @classmethod
    def single(cls, decoy: np.ndarray) -> Objective:
        """The paper's objective: Pr(reach ``decoy``)."""
        decoy = np.asarray(decoy, dtype=bool)
        return cls(target=decoy, value=decoy.astype(np.float64))

    @classmethod
    def weighted(cls, sets: tuple[DecoySet, ...]) -> Objective:
        """Several decoy sets; a state in more than one scores the largest of their weights."""
        n = sets[0].states.size
        target = np.zeros(n, dtype=bool)
        value = np.zeros(n)
        for decoy_set in sets:
            target |= decoy_set.states
            value[decoy_set.states] = np.maximum(value[decoy_set.states], decoy_set.weight)
        return cls(target=target, value=value, sets=tuple(sets))

    @cached_property
    def max_value(self) -> float:
        """The largest score a run can get: every value lies in ``[0, max_value]``."""
        return float(self.value[self.target].max()) if self.target.any() else 0.0

    @cached_property
    def is_probability(self) -> bool:
        """True when every decoy state is worth 1: the objective is Pr(reach decoy)."""
        return bool(np.all(self.value[self.target] == 1.0))

    @property
    def kind(self) -> str:
        """What the number means, as the JSON output names it."""
        return "probability" if self.is_probability else "expected_decoy_weight"

    @property
    def label(self) -> str:
        """What the number means, for tables and plots."""
        return LABELS[self.kind]

    def one_step(self, rows: sp.spmatrix, column_state: np.ndarray) -> np.ndarray:
        """Score collected in one step by each row of a product matrix whose column ``j`` is
        world state ``column_state[j]``: ``Σ_j rows[:, j] · value[column_state[j]]``."""
        return np.asarray(rows @ self.value[column_state]).ravel()
