"""The paper's grid world (Section VII-B), scaled to any n ≥ 5 exactly as SPEC §3 fixes it.

Cell ``(x, y)`` has state index ``y * n + x`` (x grows East, y grows North), so per-state arrays
reshape to ``(n, n)`` images indexed ``[y, x]``.
"""

from __future__ import annotations

import numpy as np

from misdirect.core.memory import check_memory
from misdirect.core.model import Controller, CostModel, Pomdp, Problem
from misdirect.errors import OptionError

ACTIONS = ("N", "E", "S", "W")
MOVES = np.array([(0, 1), (1, 0), (0, -1), (-1, 0)])  # same order as ACTIONS
OBSERVATIONS = ("o0", "o1", "o2", "o3", "o4", "o5", "o6", "b")
BLANK = 7
E_TYPE = (0, 1, 4, 6)  # sensors after which the controller heads East
N_TYPE = (2, 3, 5)  # sensors after which it heads North


GRID_BYTES_PER_CELL = 4096  # building a grid world, per cell (bench: paper_grid(300), 2.2 KiB)


def scaled(k: int, n: int) -> int:
    """``round(k (n-1) / 4)`` with halves rounded up (SPEC §3)."""
    return int(k * (n - 1) / 4 + 0.5)


def sensor_cells(n: int) -> dict[int, list[tuple[int, int]]]:
    """Cells guarded by each sensor ``o0..o6`` on the ``n x n`` grid."""
    mid, three = scaled(2, n), scaled(3, n)
    return {
        0: [(0, 0)],
        1: [(mid, 0), (mid, 1)],
        2: [(0, mid), (1, mid)],
        3: [(n - 1, 0), (n - 1, 1)],
        4: [(0, n - 1), (1, n - 1)],
        5: [(n - 1, three)],
        6: [(three, n - 1)],
    }


def hazard_cell(n: int) -> tuple[int, int]:
    return (scaled(2, n), scaled(2, n))


def grid_transitions(
    n: int, slip: float = 0.1
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``(action, source, target, probability)`` for the slippery grid, all cells and actions.

    The intended move happens with ``1 - 2 slip`` (the robot stays put if it would leave the
    grid); each orthogonal move with ``slip`` when both are inside, ``2 slip`` for the only one
    inside when just one is.
    """
    cells = np.arange(n * n)
    x, y = cells % n, cells // n
    actions, sources, targets, probs = [], [], [], []
    for a, move in enumerate(MOVES):
        side = np.array([move[1], move[0]])  # perpendicular directions: +side and -side
        tx, ty = x + move[0], y + move[1]
        inside = (tx >= 0) & (tx < n) & (ty >= 0) & (ty < n)
        intended = np.where(inside, ty * n + tx, cells)
        legs = []
        for sign in (1, -1):
            sx, sy = x + sign * side[0], y + sign * side[1]
            ok = (sx >= 0) & (sx < n) & (sy >= 0) & (sy < n)
            legs.append((ok, np.where(ok, sy * n + sx, cells)))
        both = legs[0][0] & legs[1][0]
        entries = [(intended, np.full(cells.size, 1 - 2 * slip))]
        for ok, target in legs:
            entries.append((target, np.where(ok, np.where(both, slip, 2 * slip), 0.0)))
        for target, p in entries:
            actions.append(np.full(cells.size, a))
            sources.append(cells)
            targets.append(target)
            probs.append(p)
    action, source, target, probability = (
        np.concatenate(part) for part in (actions, sources, targets, probs)
    )
    return action, source, target, probability


def paper_controller() -> Controller:
    """Three-node controller of SPEC §3: remembers whether the last sensor was E- or N-type."""
    n_nodes, n_obs = 3, len(OBSERVATIONS)
    action = np.zeros((n_nodes, n_obs), dtype=np.int64)
    update = np.zeros((n_nodes, n_obs), dtype=np.int64)
    east, north = ACTIONS.index("E"), ACTIONS.index("N")
    action[:, list(E_TYPE)], update[:, list(E_TYPE)] = east, 1
    action[:, list(N_TYPE)], update[:, list(N_TYPE)] = north, 2
    action[:, BLANK] = [east, east, north]
    update[:, BLANK] = np.arange(n_nodes)
    return Controller(nodes=("n0", "n1", "n2"), initial_node=0, action=action, update=update)


def paper_grid(n: int = 5, *, budget: float = 4) -> Problem:
    """The ``n x n`` grid case study with the hazard as decoy and unit alteration costs."""
    if n < 5:
        raise OptionError(f"the grid needs size ≥ 5, got {n}", parameter="n")
    check_memory(n * n * GRID_BYTES_PER_CELL, f"the {n}x{n} grid", field="n")
    observation_of = np.full(n * n, BLANK, dtype=np.int64)
    for sensor, cells in sensor_cells(n).items():
        for cx, cy in cells:
            observation_of[cy * n + cx] = sensor
    hx, hy = hazard_cell(n)
    goal, hazard = (n - 1) * n + (n - 1), hy * n + hx
    absorbing = np.zeros(n * n, dtype=bool)
    absorbing[[goal, hazard]] = True
    action, source, target, probability = grid_transitions(n)
    pomdp = Pomdp.from_triplets(
        states=tuple(f"({i % n},{i // n})" for i in range(n * n)),
        actions=ACTIONS,
        observations=OBSERVATIONS,
        initial_state=0,
        observation_of=observation_of,
        action=action,
        source=source,
        target=target,
        probability=probability,
        absorbing=absorbing,
    )
    decoy = np.zeros(n * n, dtype=bool)
    decoy[hazard] = True
    return Problem(
        pomdp=pomdp,
        controller=paper_controller(),
        cost=CostModel(n_observations=len(OBSERVATIONS), default=1.0),
        decoy=decoy,
        budget=float(budget),
        name=f"paper grid {n}x{n}",
    )
