"""Monte-Carlo simulation of the attacked robot, straight from the POMDP and the controller.

It does not use the product chain, so it is an independent check of the evaluator, and it is
vectorised over runs: each step advances every live run with a handful of numpy operations.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from misdirect.model import Alteration, Problem


@dataclass(frozen=True)
class Simulation:
    runs: int
    decoy_hits: int
    absorbed: dict[str, int]  # absorbing non-decoy state -> runs that stopped there
    unfinished: int  # runs still going after max_steps
    mean_steps: float  # over runs that stopped
    trajectories: list[tuple[int, int, str, str, str, str]] = field(default_factory=list)
    # (run, step, state, memory node, observation received, action) for the recorded runs

    @property
    def decoy_frequency(self) -> float:
        return self.decoy_hits / self.runs

    def confidence_interval(self, z: float = 1.96) -> tuple[float, float]:
        """Wilson score interval for the decoy frequency (z = 1.96: 95 %)."""
        return wilson_interval(self.decoy_hits, self.runs, z)


def wilson_interval(hits: int, runs: int, z: float = 1.96) -> tuple[float, float]:
    """Wilson score interval for a frequency ``hits / runs`` (z = 1.96: 95 %)."""
    n, p = runs, hits / runs
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * np.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return float(centre - half), float(centre + half)


def simulate(
    problem: Problem,
    alteration: Alteration | None = None,
    *,
    runs: int = 10_000,
    seed: int = 0,
    max_steps: int = 10_000,
    record: int = 0,
) -> Simulation:
    """Run the robot ``runs`` times; a run stops in a decoy or absorbing state.

    The first ``record`` runs are kept step by step as trajectories.
    """
    rng = np.random.default_rng(seed)
    pomdp, controller = problem.pomdp, problem.controller
    alpha = problem.identity() if alteration is None else np.asarray(alteration)
    matrix = pomdp.transitions
    # Sampling s' from row r: the first entry of r whose running sum exceeds u. Adding the row
    # number to the within-row running sums makes one sorted key array for all rows.
    row_of_entry = np.repeat(np.arange(matrix.shape[0]), np.diff(matrix.indptr))
    running = np.cumsum(matrix.data)
    running -= np.repeat(
        np.concatenate([[0.0], running[matrix.indptr[1:-1] - 1]]), np.diff(matrix.indptr)
    )
    keys = row_of_entry + running

    state = np.full(runs, pomdp.initial_state)
    node = np.full(runs, controller.initial_node)
    stopped_at = np.full(runs, -1)
    steps = np.zeros(runs, dtype=np.int64)
    live = np.arange(runs)
    stop = problem.decoy | pomdp.absorbing
    trajectories: list[tuple[int, int, str, str, str, str]] = []
    for step in range(max_steps + 1):
        done = stop[state[live]]
        if record:
            for run in live[done & (live < record)].tolist():
                trajectories.append(
                    (
                        run,
                        step,
                        pomdp.states[state[run]],
                        controller.nodes[node[run]],
                        "",
                        "(stopped)",
                    )
                )
        stopped_at[live[done]] = state[live[done]]
        steps[live[done]] = step
        live = live[~done]
        if live.size == 0 or step == max_steps:
            break
        seen = alpha[pomdp.observation_of[state[live]]]
        action = controller.action[node[live], seen]
        if record:
            for k in np.flatnonzero(live < record):
                run = int(live[k])
                trajectories.append(
                    (
                        run,
                        step,
                        pomdp.states[state[run]],
                        controller.nodes[node[run]],
                        pomdp.observations[seen[k]],
                        pomdp.actions[action[k]],
                    )
                )
        node[live] = controller.update[node[live], seen]
        row = action * pomdp.n_states + state[live]
        pick = np.searchsorted(keys, row + rng.random(live.size), side="right")
        pick = np.minimum(pick, matrix.indptr[row + 1] - 1)
        state[live] = matrix.indices[pick]

    finished = stopped_at >= 0
    decoy_hits = int(problem.decoy[stopped_at[finished]].sum())
    absorbed = {
        pomdp.states[s]: int((stopped_at == s).sum())
        for s in np.flatnonzero(pomdp.absorbing & ~problem.decoy)
    }
    return Simulation(
        runs=runs,
        decoy_hits=decoy_hits,
        absorbed=absorbed,
        unfinished=int((~finished).sum()),
        mean_steps=float(steps[finished].mean()) if finished.any() else float("nan"),
        trajectories=sorted(trajectories),
    )
