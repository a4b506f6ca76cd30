"""A drone among patrolling agents: a large POMDP shaped like the drone benchmarks of PAYNT.

A drone crosses an ``n x n`` grid with a few buildings from the south-west corner to the goal in
the north-east corner, while agents patrol bands of rows at random. Turns alternate: the drone
moves (its intended step happens with ``1 - slip``, else it drifts to one side), then one
agent, chosen uniformly, steps to a random neighbouring cell of its band or stays. The drone
crashes when it shares a cell with an agent (one absorbing crash state per cell). A decoy
landing pad sits off the route: a drone that steps on it lands there (absorbing, the decoy).

The drone sees its own cell and, for the nearest agent within ``radius`` (Chebyshev distance),
the compass sector it is in and whether a second agent is visible too: 17 readings per cell,
one observation per cell in the agents' turn, so about ``18 n²`` observations. Its memoryless
controller heads along a shortest path to the goal (a staircase) and dodges: when the nearest
visible agent lies in the direction it wants to go, it steps away from it instead. Dodging
sends the drone back and forth, so the product chain is one strongly connected component that
spans the drone's cells and every agent position, as the real benchmarks' chains are.

Sizes (POMDP states / observations / product states): ``drone(8)`` 53,654 / 1,047 / 51,499;
``drone(8, agents=3, rows=2)`` 339,362 / 1,047 / 123,291 (closest to PAYNT's drone-2-8-1 that
issue 16 measured: 520,190 / 889 / 118,504); ``drone(10)`` 147,302 / 1,695 / 143,621. The
model exists to measure evaluation on chains of that shape; the generator is plain numpy and
builds each in a second or two.

Small configurations are shaped like PAYNT's drone-4-1/4-2 and network benchmarks as issue 27
measured them (1–3k product states, hundreds of observations, end components in the
attacker's choice product), the C2 instances of ``bench/hard_instances.py``: ``drone(7,
agents=2, rows=1)`` 3,057 / 777 / 1,689 product states; ``drone(8, agents=1, rows=2)``
1,802 / 1,047 / 1,725; ``drone(8, agents=1, rows=3)`` 2,614 / 1,047 / 2,520 (``misdirect
scenario drone --size 8 --agents 1 --rows 2``).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import shortest_path

from misdirect.core.memory import check_memory
from misdirect.core.model import Controller, CostModel, Pomdp, Problem
from misdirect.errors import OptionError

ACTIONS = ("N", "E", "S", "W", "stay")
MOVES = np.array([(0, 1), (1, 0), (0, -1), (-1, 0), (0, 0)])  # (dx, dy), same order
SECTORS = 8  # compass sectors of the nearest visible agent
READINGS = 1 + 2 * SECTORS  # none, or (sector, one or two agents visible)
MAX_SIZE = 40
DRONE_BYTES_PER_STATE = 4096  # building it, per world state (drone(8, agents=3): 3.6 KiB)
MAX_STATES = 2_000_000  # world states the generator builds (drone(8, agents=3, rows=2): 339,362)


def _buildings(n: int) -> set[tuple[int, int]]:
    """A few building cells in the middle of the grid, clear of corners, pad and bands' ends."""
    if n < 5:
        return set()
    mid = n // 2
    return {(mid - 1, mid), (mid, mid), (1, n - 3), (n - 2, 2)}


def _bands(n: int, agents: int, rows: int) -> list[tuple[int, int]]:
    """Row ranges ``[lo, hi)`` patrolled by each agent, spread between rows 1 and n - 1."""
    free = n - 2
    if agents * rows > free and agents > 1:
        starts = np.linspace(1, n - 1 - rows, agents).round().astype(int)
    else:
        starts = 1 + np.arange(agents) * max(1, free // max(agents, 1))
    return [(int(lo), int(min(n - 1, lo + rows))) for lo in starts]


def _check(n: int, agents: int, rows: int, radius: int, slip: float, budget: float) -> None:
    """One clear line per bad argument, naming the parameter (the CLI shows its flag)."""
    if not 4 <= n <= MAX_SIZE:
        raise OptionError(f"must be between 4 and {MAX_SIZE}, got {n}", parameter="n")
    if not 1 <= agents <= 3:
        raise OptionError(f"must be between 1 and 3, got {agents}", parameter="agents")
    if not 1 <= rows <= n - 2:
        raise OptionError(
            f"must be between 1 and {n - 2} on a {n}x{n} grid, got {rows}", parameter="rows"
        )
    if not 0 <= radius <= n:
        raise OptionError(f"must be between 0 and {n}, got {radius}", parameter="radius")
    if not 0 <= slip < 1:
        raise OptionError(f"must be in [0, 1), got {slip}", parameter="slip")
    if not (np.isfinite(budget) and budget >= 0):
        raise OptionError(f"must be a non-negative number, got {budget}", parameter="budget")


def drone(
    n: int = 8,
    *,
    agents: int = 2,
    rows: int = 3,
    radius: int = 2,
    slip: float = 0.2,
    budget: float = 2,
) -> Problem:
    """The drone model on an ``n x n`` grid with ``agents`` agents patrolling ``rows`` rows each."""
    _check(n, agents, rows, radius, slip, budget)
    goal_cell, pad_cell = (n - 1, n - 1), (n // 2 + 1, n // 2 - 1)
    blocked = _buildings(n) - {pad_cell}
    cells = [(x, y) for y in range(n) for x in range(n) if (x, y) not in blocked]
    cell_id = {c: i for i, c in enumerate(cells)}
    n_cells = len(cells)
    xy = np.array(cells)
    goal, pad = cell_id[goal_cell], cell_id[pad_cell]

    # Where a step from each cell leads (blocked or off-grid: stay).
    step = np.empty((n_cells, len(MOVES)), dtype=np.int64)
    for a, (dx, dy) in enumerate(MOVES):
        for i, (x, y) in enumerate(cells):
            step[i, a] = cell_id.get((x + dx, y + dy), i)

    # Agents: each patrols the free cells of its band; a move goes to a uniform neighbour or stays.
    bands = _bands(n, agents, rows)
    band_cells = [
        np.array([cell_id[c] for c in cells if lo <= c[1] < hi and c not in (goal_cell, pad_cell)])
        for lo, hi in bands
    ]
    sizes = [b.size for b in band_cells]
    n_configs = int(np.prod(sizes))
    if 2 * n_cells * n_configs > MAX_STATES:  # before the arrays of that size are allocated
        raise OptionError(
            f"the model would have about {2 * n_cells * n_configs:,} states (at most "
            f"{MAX_STATES:,}): take a smaller grid, fewer agents or fewer rows",
            parameter="n",
        )
    check_memory(
        2 * n_cells * n_configs * DRONE_BYTES_PER_STATE,
        f"the drone model ({2 * n_cells * n_configs:,} states)",
        field="n",
    )
    # config index -> cell of each agent (mixed radix over the bands)
    config_cells = np.stack(
        [
            band_cells[k][(np.arange(n_configs) // int(np.prod(sizes[k + 1 :]))) % sizes[k]]
            for k in range(agents)
        ],
        axis=1,
    )
    radix = np.array([int(np.prod(sizes[k + 1 :])) for k in range(agents)])
    local = np.full((agents, n_cells), -1)  # cell -> its index within agent k's band
    for k, b in enumerate(band_cells):
        local[k, b] = np.arange(b.size)

    # World states: turn 0 (drone moves) / 1 (an agent moves) x drone cell x agent config,
    # for drone cells that are not goal or pad; then sinks: goal, pad, one crash per cell.
    drone_cells = np.array([i for i in range(n_cells) if i not in (goal, pad)])
    drone_pos = np.full(n_cells, -1)
    drone_pos[drone_cells] = np.arange(drone_cells.size)
    n_live = 2 * drone_cells.size * n_configs
    goal_state, pad_state = n_live, n_live + 1
    crash_state = n_live + 2 + np.arange(n_cells)
    n_states = n_live + 2 + n_cells

    def live(turn: np.ndarray, cell: np.ndarray, config: np.ndarray) -> np.ndarray:
        return (turn * drone_cells.size + drone_pos[cell]) * n_configs + config

    live_ids = np.arange(n_live)
    turn = live_ids // (drone_cells.size * n_configs)
    d_cell = drone_cells[(live_ids // n_configs) % drone_cells.size]
    config = live_ids % n_configs
    occupied = config_cells[config]  # (n_live, agents)
    valid = ~(occupied == d_cell[:, None]).any(axis=1)  # drone on an agent: never entered

    def landing(cell: np.ndarray, cfg: np.ndarray, next_turn: int) -> np.ndarray:
        """State entered when the drone is in ``cell`` and the agents in ``cfg``."""
        crash = (config_cells[cfg] == cell[:, None]).any(axis=1)
        out = np.where(crash, crash_state[cell], 0)
        out = np.where(cell == goal, goal_state, out)
        out = np.where(cell == pad, pad_state, out)
        ordinary = ~crash & (cell != goal) & (cell != pad)
        safe_cell = np.where(ordinary, cell, drone_cells[0])
        return np.where(ordinary, live(np.full(cell.size, next_turn), safe_cell, cfg), out)

    src, dst, act, prob = [], [], [], []
    # Drone's turn: the intended step with 1 - slip; with slip it drifts to one side (half each;
    # blocked: it stays). "stay" stays for sure.
    mover = np.flatnonzero((turn == 0) & valid)
    here = d_cell[mover]
    for a in range(len(ACTIONS)):
        if a == len(ACTIONS) - 1:
            legs = [(here, np.ones(mover.size))]
        else:
            left, right = (a + 3) % 4, (a + 1) % 4
            legs = [(step[here, a], np.full(mover.size, 1 - slip))]
            legs += [(step[here, side], np.full(mover.size, slip / 2)) for side in (left, right)]
        for to, p in legs:
            src.append(mover)
            dst.append(landing(to, config[mover], 1))
            act.append(np.full(mover.size, a))
            prob.append(p)
    # Agents' turn: agent k (probability 1/agents) steps to a uniform choice of its neighbours
    # within the band, or stays. Same distribution under every action.
    waiting = np.flatnonzero((turn == 1) & valid)
    for k in range(agents):
        here = occupied[waiting, k]
        options = np.stack([step[here, a] for a in range(len(MOVES))], axis=1)
        inside = np.isin(options, band_cells[k]) & (options != here[:, None])
        inside[:, -1] = True  # staying is always an option
        weight = inside / inside.sum(axis=1, keepdims=True) / agents
        for a in range(len(MOVES)):
            keep = inside[:, a]
            rows_k = waiting[keep]
            cfg = config[rows_k] + (local[k, options[keep, a]] - local[k, here[keep]]) * radix[k]
            target = landing(d_cell[rows_k], cfg, 0)
            for action in range(len(ACTIONS)):
                src.append(rows_k)
                dst.append(target)
                act.append(np.full(rows_k.size, action))
                prob.append(weight[keep, a])
    # Unreachable "drone on an agent" states: a self-loop keeps the matrix stochastic.
    dead = np.flatnonzero(~valid)
    for action in range(len(ACTIONS)):
        src.append(dead)
        dst.append(dead)
        act.append(np.full(dead.size, action))
        prob.append(np.ones(dead.size))

    # Observations: per cell, in the drone's turn, what it sees of the nearest agent; per cell,
    # in the agents' turn, one "wait" reading; then one each for goal, pad, crash.
    gap = xy[occupied] - xy[d_cell][:, None, :]  # (n_live, agents, 2)
    distance = np.abs(gap).max(axis=2)
    visible = distance <= radius
    nearest = np.argmin(np.where(visible, distance, n + 1), axis=1)
    rel = gap[np.arange(n_live), nearest]
    sector_of = {
        (0, 1): 0,
        (1, 1): 1,
        (1, 0): 2,
        (1, -1): 3,
        (0, -1): 4,
        (-1, -1): 5,
        (-1, 0): 6,
        (-1, 1): 7,
        (0, 0): 0,
    }
    sector_table = np.zeros((3, 3), dtype=np.int64)
    for (sx, sy), s in sector_of.items():
        sector_table[sx + 1, sy + 1] = s
    sector = sector_table[np.sign(rel[:, 0]) + 1, np.sign(rel[:, 1]) + 1]
    seen = visible.sum(axis=1)
    reading = np.where(seen == 0, 0, 1 + sector * 2 + (seen > 1))
    obs_drone = drone_pos[d_cell] * READINGS + reading
    obs_wait = drone_cells.size * READINGS + drone_pos[d_cell]
    n_obs_live = drone_cells.size * (READINGS + 1)
    observation_of = np.concatenate(
        [
            np.where(turn == 0, obs_drone, obs_wait),
            [n_obs_live, n_obs_live + 1],
            np.full(n_cells, n_obs_live + 2),
        ]
    )
    names = [f"({cells[c][0]},{cells[c][1]})" for c in drone_cells]
    sector_names = ("N", "NE", "E", "SE", "S", "SW", "W", "NW")
    labels = ["clear"] + [f"{s}{'+' if two else ''}" for s in sector_names for two in (0, 1)]
    observations = [f"{c}:{r}" for c in names for r in labels]
    observations += [f"{c}:wait" for c in names] + ["goal", "pad", "crash"]

    # The controller: shortest path to the goal (around buildings), dodging visible agents.
    adjacency = sp.csr_matrix(
        (np.ones(n_cells * 4), (np.repeat(np.arange(n_cells), 4), step[:, :4].ravel())),
        shape=(n_cells, n_cells),
    )
    to_goal = shortest_path(adjacency, unweighted=True, indices=goal, directed=False)
    # among the steps that get closer, a staircase: East while x <= y, else North
    closer = to_goal[step[:, :4]] < to_goal[:, None]
    rank = np.where(xy[:, :1] <= xy[:, 1:], [[1, 0, 2, 3]], [[0, 1, 2, 3]])
    toward = np.argmin(np.where(closer, rank, 9), axis=1)
    sector_step = np.array([(0, 1), (1, 1), (1, 0), (1, -1), (0, -1), (-1, -1), (-1, 0), (-1, 1)])
    table = np.full(len(observations), len(ACTIONS) - 1, dtype=np.int64)  # "stay"
    for i, c in enumerate(drone_cells):
        want = int(toward[c])
        table[i * READINGS] = want
        for s in range(SECTORS):
            away = -sector_step[s]
            toward_agent = np.dot(MOVES[want], sector_step[s]) > 0
            if not toward_agent:
                choice = want
            else:  # step away from the agent, along the axis it is furthest along
                away_moves = [
                    a
                    for a in range(4)
                    if np.dot(MOVES[a], away) > 0 and step[c, a] != c and step[c, a] != pad
                ]
                choice = away_moves[0] if away_moves else len(ACTIONS) - 1
            table[i * READINGS + 1 + 2 * s] = choice
            table[i * READINGS + 2 + 2 * s] = choice
    controller = Controller(
        nodes=("n0",),
        initial_node=0,
        action=table[None, :],
        update=np.zeros((1, len(observations)), dtype=np.int64),
    )

    start_config = int(sum(radix[k] * (sizes[k] - 1) for k in range(agents)))
    initial = int(live(np.array([0]), np.array([cell_id[(0, 0)]]), np.array([start_config]))[0])
    absorbing = np.zeros(n_states, dtype=bool)
    absorbing[n_live:] = True
    state_names = [f"s{i}" for i in range(n_live)] + ["goal", "pad"]
    state_names += [f"crash({x},{y})" for x, y in cells]
    pomdp = Pomdp.from_triplets(
        states=tuple(state_names),
        actions=ACTIONS,
        observations=tuple(observations),
        initial_state=initial,
        observation_of=observation_of,
        action=np.concatenate(act),
        source=np.concatenate(src),
        target=np.concatenate(dst),
        probability=np.concatenate(prob),
        absorbing=absorbing,
    )
    decoy = np.zeros(n_states, dtype=bool)
    decoy[pad_state] = True
    return Problem(
        pomdp=pomdp,
        controller=controller,
        cost=CostModel(n_observations=len(observations), default=1.0),
        decoy=decoy,
        budget=float(budget),
        name=f"drone {n}x{n}, {_count(agents, 'agent')}, {_count(rows, 'row')}",
    )


def _count(number: int, noun: str) -> str:
    return f"{number} {noun}{'s' if number != 1 else ''}"
