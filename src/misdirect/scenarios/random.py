"""Seeded random problems that exercise every corner the exact solvers must get right.

Each model has an absorbing non-decoy ``goal`` (where the Bellman equalities of the paper's MILP
admit spurious solutions), states whose action self-loops (the chain can cycle forever without
reaching anything), observations shared across states, an observation only the controller knows,
random costs with forbidden pairs and sometimes a protected observation.
"""

from __future__ import annotations

import numpy as np

from misdirect.core.memory import check_memory
from misdirect.core.model import Controller, CostModel, Pomdp, Problem

# its cost table, per pair of observations (a dict entry for 45 % of them, and their writing)
RANDOM_BYTES_PER_PAIR = 256


def random_problem(
    seed: int,
    *,
    states: int = 6,
    actions: int = 2,
    observations: int = 4,
    nodes: int = 2,
    budget: float | None = None,
    randomized: bool = False,
) -> Problem:
    """A random OSA_DGM instance; the same ``seed`` always gives the same problem.

    ``randomized`` draws a randomized controller (:func:`random_moves`) instead of a
    deterministic one; the rest of the problem is the same as without it."""
    rng = np.random.default_rng(seed)
    core = [f"s{i}" for i in range(states)]
    names = (*core, "goal", "decoy")
    goal, decoy_state = states, states + 1
    n_s = len(names)

    act, src, dst, prob = [], [], [], []
    for s in range(states):
        for a in range(actions):
            if rng.random() < 0.2:  # a self-loop: the controller can get stuck here forever
                targets, weights = np.array([s]), np.array([1])
            else:
                targets = rng.choice(n_s, size=rng.integers(1, 4), replace=False)
                weights = rng.integers(1, 10, size=targets.size)
            act += [a] * targets.size
            src += [s] * targets.size
            dst += targets.tolist()
            prob += (weights / weights.sum()).tolist()

    obs_names = (*(f"o{i}" for i in range(observations)), "ghost")  # ghost: emitted by none
    observation_of = rng.integers(0, observations, size=n_s)
    absorbing = np.zeros(n_s, dtype=bool)
    absorbing[[goal, decoy_state]] = True
    pomdp = Pomdp.from_triplets(
        states=names,
        actions=tuple(f"a{i}" for i in range(actions)),
        observations=obs_names,
        initial_state=0,
        observation_of=observation_of,
        action=np.array(act),
        source=np.array(src),
        target=np.array(dst),
        probability=np.array(prob),
        absorbing=absorbing,
    )
    n_obs = len(obs_names)
    controller = Controller(
        nodes=tuple(f"n{i}" for i in range(nodes)),
        initial_node=0,
        action=rng.integers(0, actions, size=(nodes, n_obs)),
        update=rng.integers(0, nodes, size=(nodes, n_obs)),
    )
    if randomized:  # its own generator, so the rest of the problem does not change
        controller = random_moves(
            np.random.default_rng([seed, 1]), controller.nodes, n_obs, actions
        )
    check_memory(
        n_obs * n_obs * RANDOM_BYTES_PER_PAIR,
        f"the random model's cost table ({n_obs:,} observations, every pair drawn)",
        field="observations",
    )
    pairs: dict[tuple[int, int], float] = {}
    for o in range(n_obs):
        for t in range(n_obs):
            if o != t:
                roll = rng.random()
                if roll < 0.2:
                    pairs[o, t] = np.inf
                elif roll < 0.45:
                    pairs[o, t] = float(rng.choice([0.5, 1.0, 2.0, 3.0]))
    protected = frozenset({int(rng.integers(0, n_obs))}) if rng.random() < 0.3 else frozenset()
    cost = CostModel(
        n_observations=n_obs,
        default=float(rng.choice([1.0, 2.0])),
        pairs=pairs,
        protected=protected,
    )
    decoy = np.zeros(n_s, dtype=bool)
    decoy[decoy_state] = True
    if rng.random() < 0.3:  # sometimes a non-absorbing decoy state as well
        decoy[int(rng.integers(1, states))] = True
    return Problem(
        pomdp=pomdp,
        controller=controller,
        cost=cost,
        decoy=decoy,
        budget=float(rng.integers(0, 5)) if budget is None else float(budget),
        name=f"random model (seed {seed})",
    )


def random_moves(
    rng: np.random.Generator, nodes: tuple[str, ...], n_observations: int, n_actions: int
) -> Controller:
    """A randomized controller: per (node, observation) a deterministic pair (about a third of
    the cells), a factored draw (action and next node independent), or a joint distribution
    over two or three (action, next node) pairs. Probabilities are ratios of small integers,
    so an exact checker (Storm with rationals) reads them exactly."""
    n_nodes = len(nodes)
    entries: list[tuple[int, int, int, int, float]] = []

    def weights(k: int) -> np.ndarray:
        w = rng.integers(1, 5, size=k)
        return w / w.sum()

    for n in range(n_nodes):
        for o in range(n_observations):
            kind = rng.integers(0, 3)
            if kind == 0:
                moves = [(int(rng.integers(n_actions)), int(rng.integers(n_nodes)), 1.0)]
            elif kind == 1:
                a = rng.choice(n_actions, size=min(2, n_actions), replace=False)
                m = rng.choice(n_nodes, size=min(2, n_nodes), replace=False)
                pa, pm = weights(a.size), weights(m.size)
                moves = [
                    (int(x), int(y), float(p * q))
                    for x, p in zip(a, pa, strict=True)
                    for y, q in zip(m, pm, strict=True)
                ]
            else:
                k = int(rng.integers(2, 4))
                pairs = rng.integers(0, [n_actions, n_nodes], size=(k, 2))
                moves = [
                    (int(x), int(y), float(p)) for (x, y), p in zip(pairs, weights(k), strict=True)
                ]
            entries += [(n, o, a, m, p) for a, m, p in moves]
    node, observation, action, next_node, probability = (
        np.array(column) for column in zip(*entries, strict=True)
    )
    return Controller.from_entries(
        nodes=nodes,
        initial_node=0,
        n_observations=n_observations,
        node=node,
        observation=observation,
        action=action,
        next_node=next_node,
        probability=probability,
    )
