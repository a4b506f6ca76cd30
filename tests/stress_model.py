"""Random small models whose probabilities go down to 1e-12: where rounding bites.

A seed makes one model, always the same. Expected values for them come from the exhaustive
enumeration (each alteration evaluated exactly, with a proven error bound)."""

from __future__ import annotations

import numpy as np

from misdirect import problem_from_dict


def stress_model(seed: int):
    """Six states with observations o0..o3, a trap (the decoy) and a goal; each state and
    action has 2-3 successors, 40 % of them of probability 1e-12 to 1e-6; a two-node
    controller; odd seeds weigh the trap 1e-12 to 1."""
    rng = np.random.default_rng(seed)
    states = [f"s{i}" for i in range(6)]
    labels = [0, 1, 2, 3, *rng.integers(0, 4, size=2)]
    labels[1:] = list(rng.permutation(labels[1:]))
    observe = {s: f"o{labels[i]}" for i, s in enumerate(states)}
    observe.update(trap="g", goal="g")
    transitions = []
    for s in states:
        for a in ["a", "b"]:
            k = rng.integers(2, 4)
            successors = rng.choice([*states, "trap", "goal"], size=k, replace=False)
            w = rng.random(k)
            tiny = rng.random(k) < 0.4
            w[tiny] = 10.0 ** rng.uniform(-12, -6, size=tiny.sum())
            w = w / w.sum()
            w[-1] = 1.0 - w[:-1].sum()
            if w[-1] <= 0:
                w = np.full(k, 1.0 / k)
            transitions += [[s, a, str(t), float(p)] for t, p in zip(successors, w, strict=True)]
    rules = [
        {
            "node": n,
            "obs": o,
            "action": str(rng.choice(["a", "b"])),
            "next": str(rng.choice(["n0", "n1"])),
        }
        for n in ["n0", "n1"]
        for o in ["o0", "o1", "o2", "o3"]
    ]
    rules.append({"node": "*", "obs": "*", "action": "a", "next": "n0"})
    decoy = {"trap": float(10.0 ** rng.uniform(-12, 0))} if seed % 2 else ["trap"]
    return problem_from_dict(
        {
            "format": "misdirect/v1",
            "name": f"stress{seed}",
            "pomdp": {
                "states": [*states, "trap", "goal"],
                "actions": ["a", "b"],
                "initial": "s0",
                "observe": observe,
                "transitions": transitions,
                "absorbing": ["trap", "goal"],
            },
            "controller": {"nodes": ["n0", "n1"], "initial": "n0", "rules": rules},
            "deception": {"decoy": decoy, "budget": 2.0, "cost": {"default": 1.0}},
        }
    )
