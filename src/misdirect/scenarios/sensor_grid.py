"""Sensor networks on the paper's slippery grid: ``k`` sensors, each covering 1–6 cells.

The paper's grid has 7 sensors; real networks have dozens to hundreds, which is where the
attack becomes NP-hard (every sensor is an item of the knapsack). This family generalises the
paper's case study so that everyone can reproduce the hard instances:

* the ``n x n`` grid and its dynamics are the paper's (``grid.grid_transitions``); the robot
  starts at ``(0, 0)`` (its own observation ``start``, never altered), the goal ``(n-1, n-1)``
  is absorbing, and so is the decoy, one cell placed as described below;
* ``k`` sensors ``s0 … s{k-1}`` cover disjoint blobs of 1–6 cells (fewer when the grid is
  crowded: at most 60 % of the cells are covered); every other cell reads ``b`` (blank);
* the controller generalises the paper's: a sensor at ``(x, y)`` tells the robot to head East
  when ``x ≤ y`` and North otherwise (back towards the diagonal), and moves the memory to one of
  the nodes of that direction (chosen at random per sensor; node ``j ≥ 1`` stands for East when
  ``j`` is odd, North when even); on a blank cell the robot keeps the direction of its node
  (node 0, the start, heads East). With ``memory = 3`` this is exactly the paper's controller;
  more nodes give the attacker more behaviour classes to choose from;
* costs: ``uniform`` (every alteration costs 1) or ``random`` (altering sensor ``o`` costs an
  integer drawn from 1..3, whatever it is altered to: the effort of spoofing that sensor);
* the decoy is the first cell, in a seeded random order over the middle band of the grid, whose
  unattacked decoy probability lies strictly between 0 and 1/2 (so both the goal and the decoy
  are reached without attack, and the attack has something to gain).

Without attack the robot never gets stuck: moving North along the top edge (or East along the
right one) it slips sideways and drifts into the goal corner, so every run ends at the goal or
the decoy.
"""

from __future__ import annotations

import numpy as np

from misdirect.core.model import Controller, CostModel, Pomdp, Problem
from misdirect.errors import OptionError
from misdirect.scenarios.grid import ACTIONS, MOVES, grid_transitions

MAX_COVERED = 0.6  # share of the cells that sensors may cover
MAX_SIZE = 1_000  # the grid side the generator accepts
MAX_MEMORY = 64


def sensor_grid(
    n: int,
    sensors: int,
    *,
    seed: int = 0,
    memory: int = 3,
    costs: str = "uniform",
    budget: float = 3,
) -> Problem:
    """A seeded sensor-network problem; the same arguments always give the same problem."""
    _check(n, sensors, memory, costs)
    rng = np.random.default_rng(seed)
    cells = n * n
    start, goal = 0, cells - 1
    region = _place_sensors(n, sensors, rng, reserved={start, goal})
    x, y = np.arange(cells) % n, np.arange(cells) // n

    blank, start_obs = sensors, sensors + 1
    observation_of = np.where(region >= 0, region, blank)
    observation_of[start] = start_obs
    observations = (*(f"s{i}" for i in range(sensors)), "b", "start")

    controller = _controller(n, sensors, region, memory, rng, x, y)
    action, source, target, probability = grid_transitions(n)
    names = tuple(f"({i % n},{i // n})" for i in range(cells))
    cost = _costs(sensors, len(observations), costs, rng)

    def problem_with_decoy(decoy_cell: int) -> Problem:
        absorbing = np.zeros(cells, dtype=bool)
        absorbing[[goal, decoy_cell]] = True
        pomdp = Pomdp.from_triplets(
            states=names,
            actions=ACTIONS,
            observations=observations,
            initial_state=start,
            observation_of=observation_of,
            action=action,
            source=source,
            target=target,
            probability=probability,
            absorbing=absorbing,
        )
        decoy = np.zeros(cells, dtype=bool)
        decoy[decoy_cell] = True
        return Problem(
            pomdp=pomdp,
            controller=controller,
            cost=cost,
            decoy=decoy,
            budget=float(budget),
            name=f"sensor grid {n}x{n}, {sensors} sensors (seed {seed})",
        )

    from misdirect.core.evaluate import decoy_probability

    band = (x >= n // 4) & (x <= n - 1 - n // 4) & (y >= n // 4) & (y <= n - 1 - n // 4)
    candidates = np.flatnonzero(band & (region < 0))
    candidates = candidates[(candidates != start) & (candidates != goal)]
    for cell in rng.permutation(candidates)[:200]:
        problem = problem_with_decoy(int(cell))
        value = decoy_probability(problem, problem.identity())
        if 1e-12 < value < 0.5:
            return problem
    raise OptionError(
        f"no decoy cell with an unattacked probability in (0, 1/2) for seed {seed}; "
        "try another seed",
        parameter="seed",
    )


def _check(n: int, sensors: int, memory: int, costs: str) -> None:
    if not 5 <= n <= MAX_SIZE:
        raise OptionError(f"must be between 5 and {MAX_SIZE}, got {n}", parameter="n")
    room = int(MAX_COVERED * (n * n - 2))
    if not 1 <= sensors <= room:
        raise OptionError(
            f"must be between 1 and {room:,} on a {n}x{n} grid, got {sensors}", parameter="sensors"
        )
    if not 1 <= memory <= MAX_MEMORY:
        raise OptionError(f"must be between 1 and {MAX_MEMORY}, got {memory}", parameter="memory")
    if costs not in ("uniform", "random"):
        raise OptionError(f"must be uniform or random, got {costs!r}", parameter="costs")


def _place_sensors(
    n: int, sensors: int, rng: np.random.Generator, reserved: set[int]
) -> np.ndarray:
    """Per cell the sensor covering it, -1 for none: disjoint blobs grown from random seeds."""
    cells = n * n
    sizes = rng.integers(1, 7, size=sensors)
    room = int(MAX_COVERED * (cells - len(reserved)))
    while sizes.sum() > room:  # a crowded grid: shrink every blob by one cell until they fit
        sizes = np.maximum(sizes - 1, 1)
    region = np.full(cells, -1, dtype=np.int64)
    free = np.ones(cells, dtype=bool)
    free[list(reserved)] = False
    order = rng.permutation(cells)
    cursor = 0
    for sensor, size in enumerate(sizes):
        while not free[order[cursor]]:
            cursor += 1
        blob = [int(order[cursor])]
        free[blob[0]] = False
        frontier = list(blob)
        while len(blob) < size and frontier:
            here = frontier[int(rng.integers(len(frontier)))]
            hx, hy = here % n, here // n
            options = [
                (hy + dy) * n + (hx + dx)
                for dx, dy in MOVES
                if 0 <= hx + dx < n and 0 <= hy + dy < n and free[(hy + dy) * n + (hx + dx)]
            ]
            if not options:
                frontier.remove(here)
                continue
            cell = options[int(rng.integers(len(options)))]
            free[cell] = False
            blob.append(cell)
            frontier.append(cell)
        region[blob] = sensor
    return region


def _controller(
    n: int,
    sensors: int,
    region: np.ndarray,
    memory: int,
    rng: np.random.Generator,
    x: np.ndarray,
    y: np.ndarray,
) -> Controller:
    """The paper's steering controller, generalised to ``sensors`` sensors and ``memory`` nodes."""
    east, north = ACTIONS.index("E"), ACTIONS.index("N")
    n_obs = sensors + 2
    blank, start_obs = sensors, sensors + 1
    heading = np.array([east] + [east if j % 2 else north for j in range(1, memory)])
    # each sensor's direction from where its cells lie: the mean cell of its blob
    count = np.bincount(region[region >= 0], minlength=sensors)
    mean_x = np.bincount(region[region >= 0], weights=x[region >= 0], minlength=sensors) / count
    mean_y = np.bincount(region[region >= 0], weights=y[region >= 0], minlength=sensors) / count
    direction = np.where(mean_x <= mean_y, east, north)
    action = np.zeros((memory, n_obs), dtype=np.int64)
    update = np.zeros((memory, n_obs), dtype=np.int64)
    for sensor in range(sensors):
        nodes = (
            [j for j in range(1, memory) if heading[j] == direction[sensor]]
            or [j for j in range(1, memory)]
            or [0]
        )
        action[:, sensor] = direction[sensor]
        update[:, sensor] = nodes[int(rng.integers(len(nodes)))]
    action[:, blank] = heading
    update[:, blank] = np.arange(memory)
    action[:, start_obs], update[:, start_obs] = east, 0
    return Controller(
        nodes=tuple(f"n{j}" for j in range(memory)), initial_node=0, action=action, update=update
    )


def _costs(sensors: int, n_obs: int, kind: str, rng: np.random.Generator) -> CostModel:
    if kind == "uniform":
        return CostModel(n_observations=n_obs, default=1.0)
    per_sensor = rng.integers(1, 4, size=sensors).astype(float)
    pairs = {(o, t): float(per_sensor[o]) for o in range(sensors) for t in range(n_obs) if t != o}
    return CostModel(n_observations=n_obs, default=1.0, pairs=pairs)
