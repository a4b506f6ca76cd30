"""The knapsack reduction behind the NP-hardness proof (paper Section V, Fig. 3; SPEC §4).

Item ``i`` is observation ``o<i>``; putting it in the knapsack is altering ``o<i>`` to
``o_club`` at cost ``w_i``, which sends the robot to the decoy with probability
``v_i / (2 Σ v)``. So the optimum is ``(best knapsack value) / (2 Σ v)``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from misdirect.core.model import Controller, CostModel, Pomdp, Problem
from misdirect.errors import OptionError


def knapsack(weights: Sequence[float], values: Sequence[float], capacity: float) -> Problem:
    k = len(weights)
    if k == 0 or len(values) != k:
        raise OptionError(
            f"need as many values as weights (≥ 1), got {k} weights and {len(values)} values",
            parameter="values",
        )
    for name, numbers in (("weights", weights), ("values", values)):
        bad = [v for v in numbers if not np.isfinite(v) or v <= 0]
        if bad:
            raise OptionError(
                f"every entry must be a positive number, got {bad[0]}", parameter=name
            )
        # the probabilities divide by the values' sum, and an alteration's cost adds weights
        if not math.isfinite(sum(numbers, 0.0)):
            raise OptionError(
                f"the {name} sum to more than the largest number ({np.finfo(float).max:.3g}); "
                "scale them down",
                parameter=name,
            )
    if not np.isfinite(capacity) or capacity < 0:
        raise OptionError(f"must be a non-negative number, got {capacity}", parameter="capacity")

    items = [f"s{i}" for i in range(1, k + 1)]
    states = ("s0", *items, "s_club", "s_top", "s_bot")
    observations = tuple("o" + s[1:] for s in states)
    index = {s: i for i, s in enumerate(states)}
    a, b = 0, 1
    total = float(sum(values))
    entries = [(a, "s0", item, v / (2 * total)) for item, v in zip(items, values, strict=True)]
    entries += [(a, "s0", "s_club", 0.5), (b, "s0", "s0", 1.0)]
    for item in items:
        entries += [(a, item, "s_top", 1.0), (b, item, "s_bot", 1.0)]
    entries += [(b, "s_club", "s_top", 1.0), (a, "s_club", "s_bot", 1.0)]
    act, src, dst, prob = zip(*entries, strict=True)
    absorbing = np.zeros(len(states), dtype=bool)
    absorbing[[index["s_top"], index["s_bot"]]] = True
    pomdp = Pomdp.from_triplets(
        states=states,
        actions=("a", "b"),
        observations=observations,
        initial_state=0,
        observation_of=np.arange(len(states)),
        action=np.array(act),
        source=np.array([index[s] for s in src]),
        target=np.array([index[s] for s in dst]),
        probability=np.array(prob, dtype=float),
        absorbing=absorbing,
    )
    n_obs = len(observations)
    action = np.full((3, n_obs), b, dtype=np.int64)
    action[0, 0] = a  # γ(n0, o0) = a
    action[1, 1 : k + 1] = a  # γ(n1, o_i) = a for every item
    update = np.full((3, n_obs), 2, dtype=np.int64)
    update[0, 0] = 1  # δ(n0, o0) = n1, n2 otherwise
    controller = Controller(nodes=("n0", "n1", "n2"), initial_node=0, action=action, update=update)
    club = index["s_club"]
    cost = CostModel(
        n_observations=n_obs,
        default=np.inf,
        pairs={(i, club): float(w) for i, w in enumerate(weights, start=1)},
    )
    decoy = np.zeros(len(states), dtype=bool)
    decoy[index["s_bot"]] = True
    return Problem(
        pomdp=pomdp,
        controller=controller,
        cost=cost,
        decoy=decoy,
        budget=float(capacity),
        name=f"knapsack reduction ({k} items, capacity {capacity:g})",
    )
