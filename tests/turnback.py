"""A patrolling robot that can turn back: a chain with end components, hundreds of sensors.

The robot walks an ``n x n`` grid with a heading (N, E, S, W). Each step it goes forward,
turns left, right or back and then moves, with slip (the step happens with 0.8, else it stays
0.1 or drifts to a side 0.05 each); a wall keeps it in place. Its sensor reports its cell and
heading, one observation each (``4 n²`` sensors). A memory-``nodes`` controller patrols: node
``k`` heads (greedily, larger gap first) to waypoint ``k``, and reaching it moves on to the
next node; the last waypoint is the goal (absorbing). The decoy is one cell off the route
(absorbing). Any sensor altered to a reading that turns the robot back makes it shuttle
between two cells forever: the choice product has end components among its live states, as
PAYNT's drone benchmarks do, and a state choosing on its own can always steer to the decoy,
so the per-state relaxation's bound is 1.

Only targets within ``reach`` cells (same or neighbouring cell, any heading) are affordable,
at cost 1; the rest cost 3 (out of budget 1). That keeps the budget-1 alterations to a few
per sensor, a few thousand in all, as in the benchmark.
"""

from __future__ import annotations

import numpy as np

from misdirect.core.model import Controller, CostModel, Pomdp, Problem

HEADINGS = np.array([(0, 1), (1, 0), (0, -1), (-1, 0)])  # N, E, S, W as (dx, dy)
TURNS = (0, 3, 1, 2)  # forward, left, right, back: the heading's change (mod 4)


def turnback(n: int = 8, *, nodes: int = 2, reach: int = 1, budget: float = 1.0) -> Problem:
    cells = [(x, y) for y in range(n) for x in range(n)]
    index = {c: i for i, c in enumerate(cells)}
    goal_cell, decoy_cell = (n - 1, n - 1), (n // 2, 1)
    waypoints = [*[(0, n - 1), (n - 1, 0)][: nodes - 1], goal_cell]
    n_moving = 4 * n * n  # (cell, heading): state cell * 4 + heading
    goal, decoy = n_moving, n_moving + 1

    def landing(cell: int, heading: int) -> int:
        x, y = cells[cell]
        dx, dy = HEADINGS[heading]
        target = (x + dx, y + dy)
        if target not in index:
            return cell * 4 + heading
        t = index[target]
        if target == goal_cell:
            return goal
        if target == decoy_cell:
            return decoy
        return t * 4 + heading

    act, src, dst, prob = [], [], [], []
    for cell in range(n * n):
        for h in range(4):
            s = cell * 4 + h
            for a, turn in enumerate(TURNS):
                d = (h + turn) % 4
                for heading, p in ((d, 0.8), ((d + 1) % 4, 0.05), ((d + 3) % 4, 0.05)):
                    act.append(a)
                    src.append(s)
                    dst.append(landing(cell, heading))
                    prob.append(p)
                act.append(a)
                src.append(s)
                dst.append(cell * 4 + d)
                prob.append(0.1)
    absorbing = np.zeros(n_moving + 2, dtype=bool)
    absorbing[[goal, decoy]] = True
    observation_of = np.concatenate([np.arange(n_moving), [n_moving, n_moving]])
    names = tuple(f"c{x}_{y}{'NESW'[h]}" for (x, y) in cells for h in range(4))
    pomdp = Pomdp.from_triplets(
        states=(*names, "goal", "decoy"),
        actions=("forward", "left", "right", "back"),
        observations=(*names, "done"),
        initial_state=index[(0, 0)] * 4 + 1,
        observation_of=observation_of,
        action=np.array(act),
        source=np.array(src),
        target=np.array(dst),
        probability=np.array(prob),
        absorbing=absorbing,
    )
    n_obs = n_moving + 1
    action = np.zeros((nodes, n_obs), dtype=np.int64)
    update = np.zeros((nodes, n_obs), dtype=np.int64)
    for k, (wx, wy) in enumerate(waypoints):
        update[k] = k
        for cell, (x, y) in enumerate(cells):
            gx, gy = wx - x, wy - y
            # the heading it wants (N, E, S, W): along the larger gap, x first on a tie
            want = (1 if gx > 0 else 3) if abs(gx) >= abs(gy) and gx != 0 else (0 if gy >= 0 else 2)
            for h in range(4):
                action[k, cell * 4 + h] = TURNS.index((want - h) % 4)
            if (x, y) == (wx, wy) and k + 1 < nodes:
                update[k, cell * 4 : cell * 4 + 4] = k + 1
    controller = Controller(
        nodes=tuple(f"n{k}" for k in range(nodes)), initial_node=0, action=action, update=update
    )
    pairs = {}
    for cell, (x, y) in enumerate(cells):
        for other, (u, v) in enumerate(cells):
            if max(abs(x - u), abs(y - v)) <= reach:
                for h in range(4):
                    for g in range(4):
                        if (cell, h) != (other, g):
                            pairs[cell * 4 + h, other * 4 + g] = 1.0
    decoy_mask = np.zeros(n_moving + 2, dtype=bool)
    decoy_mask[decoy] = True
    return Problem(
        pomdp=pomdp,
        controller=controller,
        cost=CostModel(n_observations=n_obs, default=3.0, pairs=pairs),
        decoy=decoy_mask,
        budget=budget,
        name=f"turn-back patrol {n}x{n}",
    )
