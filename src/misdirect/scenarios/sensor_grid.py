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

``goal="inside"``: robots that turn back. The goal is the centre cell ``(n//2, n//2)``; the
robot moves N/E/S/W; each sensor points it towards the goal (the heading that shrinks the
larger of ``|dx|``, ``|dy|`` from the blob's mean cell, East/West on a tie); node ``j`` of the
``memory ≥ 4`` nodes stands for heading ``j mod 4`` (N, E, S, W), a sensor moves the memory to
one of its heading's nodes (at random), and a blank cell keeps the node. The robot overshoots
and is turned back by the next sensor, so an altered reading can send it round in circles:
the attacker's choice product has end components. Sensors 0–3 grow from a random cell of the
top, right, bottom and left edge, which keeps the unattacked robot from wandering forever:
heading into an edge it slides along it (the slips) until that edge's sensor turns it, and
from a sensor cell that its heading points towards the goal, intended moves and slips, each
one step closer, reach the goal (or the decoy) with positive probability. A blob straddling
the goal's row or column can point some of its cells away, so this is an argument, not a
proof: the generator checks absorption on the unattacked chain and refuses the seed if it
fails (without the edge sensors about a third of small seeds would; with them none of 440
tried did). The decoy rule is the corner family's. The blank reading cannot be altered
(it is protected in the cost model): a blank cell has no sensor to spoof, and a robot that
reads one fixed heading on every blank cell drifts into a band along an edge and circles
there until it meets the decoy, so one such alteration would give nearly 1 at budget 1 and
leave nothing to search for. A sensor can still be made to read blank (jammed).
"""

from __future__ import annotations

import numpy as np

from misdirect.core.memory import check_memory
from misdirect.core.model import Controller, CostModel, Pomdp, Problem
from misdirect.errors import OptionError
from misdirect.scenarios.grid import ACTIONS, GRID_BYTES_PER_CELL, MOVES, grid_transitions

MAX_COVERED = 0.6  # share of the cells that sensors may cover
MAX_SIZE = 1_000  # the grid side the generator accepts
MAX_MEMORY = 64
# A generated decoy is one the robot reaches at least this often without attack. Absolute on
# purpose: the generator's own probabilities (slips of 0.1 on a grid) have scale 1, this only
# excludes cells the robot practically never reaches, and a new number would change the
# problem every seed generates.
MIN_DECOY_PROBABILITY = 1e-12


def sensor_grid(
    n: int,
    sensors: int,
    *,
    seed: int = 0,
    memory: int | None = None,
    costs: str = "uniform",
    budget: float = 3,
    goal: str = "corner",
) -> Problem:
    """A seeded sensor-network problem; the same arguments always give the same problem.

    ``goal="corner"`` (the default) is the paper's East/North family; ``goal="inside"`` puts
    the goal at the centre and lets the robot turn back (module docstring). ``memory``
    defaults to 3 (corner) or 4 (inside: one node per heading)."""
    if memory is None:
        memory = 4 if goal == "inside" else 3
    _check(n, sensors, memory, costs, goal)
    check_memory(n * n * GRID_BYTES_PER_CELL, f"the {n}x{n} sensor grid", field="n")
    rng = np.random.default_rng(seed)
    cells = n * n
    x, y = np.arange(cells) % n, np.arange(cells) // n
    start = 0
    if goal == "inside":
        goal_cell = (n // 2) * n + n // 2
        edges = [np.flatnonzero(side) for side in (y == n - 1, x == n - 1, y == 0, x == 0)]
        region = _place_sensors(n, sensors, rng, reserved={start, goal_cell}, anchors=edges)
    else:
        goal_cell = cells - 1
        region = _place_sensors(n, sensors, rng, reserved={start, goal_cell})

    blank, start_obs = sensors, sensors + 1
    observation_of = np.where(region >= 0, region, blank)
    observation_of[start] = start_obs
    observations = (*(f"s{i}" for i in range(sensors)), "b", "start")

    if goal == "inside":
        controller = _turning_controller(n, sensors, region, memory, rng, x, y)
    else:
        controller = _controller(n, sensors, region, memory, rng, x, y)
    action, source, target, probability = grid_transitions(n)
    names = tuple(f"({i % n},{i // n})" for i in range(cells))
    cost = _costs(sensors, len(observations), costs, rng)
    if goal == "inside":  # a blank cell has no sensor to spoof (module docstring)
        cost = CostModel(cost.n_observations, cost.default, cost.pairs, frozenset({blank}))

    where = ", goal inside" if goal == "inside" else ""

    def problem_with_decoy(decoy_cell: int) -> Problem:
        absorbing = np.zeros(cells, dtype=bool)
        absorbing[[goal_cell, decoy_cell]] = True
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
            name=f"sensor grid {n}x{n}, {sensors} sensors{where} (seed {seed})",
        )

    from misdirect.core.evaluate import decoy_probability

    band = (x >= n // 4) & (x <= n - 1 - n // 4) & (y >= n // 4) & (y <= n - 1 - n // 4)
    candidates = np.flatnonzero(band & (region < 0))
    candidates = candidates[(candidates != start) & (candidates != goal_cell)]
    for cell in rng.permutation(candidates)[:200]:
        problem = problem_with_decoy(int(cell))
        value = decoy_probability(problem, problem.identity())
        if MIN_DECOY_PROBABILITY < value < 0.5:
            if goal == "inside" and not _always_absorbed(problem):
                raise OptionError(  # the edge sensors should rule this out (module docstring)
                    f"without attack the robot can wander forever for seed {seed}; "
                    "try another seed",
                    parameter="seed",
                )
            return problem
    raise OptionError(
        f"no decoy cell with an unattacked probability in (0, 1/2) for seed {seed}; "
        "try another seed",
        parameter="seed",
    )


def _check(n: int, sensors: int, memory: int, costs: str, goal: str) -> None:
    if goal not in ("corner", "inside"):
        raise OptionError(f"must be corner or inside, got {goal!r}", parameter="goal")
    if not 5 <= n <= MAX_SIZE:
        raise OptionError(f"must be between 5 and {MAX_SIZE}, got {n}", parameter="n")
    room = int(MAX_COVERED * (n * n - 2))
    least = 4 if goal == "inside" else 1  # inside: one sensor on each edge
    if not least <= sensors <= room:
        raise OptionError(
            f"must be between {least} and {room:,} on a {n}x{n} grid"
            + (" with the goal inside" if goal == "inside" else "")
            + f", got {sensors}",
            parameter="sensors",
        )
    fewest = 4 if goal == "inside" else 1  # inside: one node per heading
    if not fewest <= memory <= MAX_MEMORY:
        raise OptionError(
            f"must be between {fewest} and {MAX_MEMORY}"
            + (" with the goal inside (one node per heading)" if goal == "inside" else "")
            + f", got {memory}",
            parameter="memory",
        )
    if costs not in ("uniform", "random"):
        raise OptionError(f"must be uniform or random, got {costs!r}", parameter="costs")


def _always_absorbed(problem: Problem) -> bool:
    """Whether, without attack, every run ends in an absorbing state (the goal or the decoy):
    every reachable product state can reach one (graph search, no numbers)."""
    from misdirect.core.product import build_product
    from misdirect.core.reachability import prob0_prob1

    chain = build_product(problem, problem.identity())
    _, sure = prob0_prob1(chain.matrix, problem.pomdp.absorbing[chain.world_state])
    return bool(sure.all())


def _place_sensors(
    n: int,
    sensors: int,
    rng: np.random.Generator,
    reserved: set[int],
    anchors: list[np.ndarray] | None = None,
) -> np.ndarray:
    """Per cell the sensor covering it, -1 for none: disjoint blobs grown from random seeds.

    Sensor ``i < len(anchors)`` grows from a random free cell of ``anchors[i]`` (if it has
    one left); the others from the next free cell of a random order of the grid."""
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
    anchors = anchors or []
    for sensor, size in enumerate(sizes):
        spots = anchors[sensor][free[anchors[sensor]]] if sensor < len(anchors) else []
        if len(spots):
            blob = [int(spots[rng.integers(len(spots))])]
        else:
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


def _turning_controller(
    n: int,
    sensors: int,
    region: np.ndarray,
    memory: int,
    rng: np.random.Generator,
    x: np.ndarray,
    y: np.ndarray,
) -> Controller:
    """The goal-inside controller: node ``j`` heads ``ACTIONS[j % 4]`` (N, E, S, W); a sensor
    points towards the goal and moves the memory to a random node of that heading; a blank
    cell keeps the node, so the robot overshoots and must be turned back by a sensor."""
    n_obs = sensors + 2
    blank, start_obs = sensors, sensors + 1
    goal = n // 2
    covered = region >= 0
    count = np.bincount(region[covered], minlength=sensors)
    mean_x = np.bincount(region[covered], weights=x[covered], minlength=sensors) / count
    mean_y = np.bincount(region[covered], weights=y[covered], minlength=sensors) / count
    direction = _heading(goal - mean_x, goal - mean_y)
    # the nodes of heading h are h, h + 4, h + 8, …: pick one of them per sensor
    per_heading = (memory - np.arange(4) + 3) // 4
    node = direction + 4 * rng.integers(0, per_heading[direction])
    heading = np.arange(memory) % 4
    action = np.empty((memory, n_obs), dtype=np.int64)
    update = np.empty((memory, n_obs), dtype=np.int64)
    action[:, :sensors], update[:, :sensors] = direction, node
    action[:, blank], update[:, blank] = heading, np.arange(memory)
    first = int(_heading(np.array([goal]), np.array([goal]))[0])  # from the start (0, 0)
    action[:, start_obs], update[:, start_obs] = first, first
    return Controller(
        nodes=tuple(f"n{j}-{ACTIONS[j % 4]}" for j in range(memory)),
        initial_node=first,
        action=action,
        update=update,
    )


def _heading(dx: np.ndarray, dy: np.ndarray) -> np.ndarray:
    """The action that shrinks the larger of ``|dx|``, ``|dy|`` (East/West on a tie)."""
    n_, e_, s_, w_ = (ACTIONS.index(a) for a in ("N", "E", "S", "W"))
    across = np.where(dx >= 0, e_, w_)
    along = np.where(dy > 0, n_, s_)
    return np.where(np.abs(dx) >= np.abs(dy), across, along).astype(np.int64)


def _costs(sensors: int, n_obs: int, kind: str, rng: np.random.Generator) -> CostModel:
    if kind == "uniform":
        return CostModel(n_observations=n_obs, default=1.0)
    per_sensor = rng.integers(1, 4, size=sensors).astype(float)
    pairs = {(o, t): float(per_sensor[o]) for o in range(sensors) for t in range(n_obs) if t != o}
    return CostModel(n_observations=n_obs, default=1.0, pairs=pairs)
