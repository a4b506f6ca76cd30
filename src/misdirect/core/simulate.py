"""Monte-Carlo simulation of the attacked robot, straight from the POMDP and the controller.

It does not step through the evaluator's product chain, so it is an independent check of the
evaluator (a randomized controller's (action, next node) is drawn per run from its move), and
it is vectorised over runs: each step advances every live run with a handful of
numpy operations. Only to stop runs that never would stop does it ask which (state, memory
node) pairs can still reach a decoy or absorbing state, on the product's transition graph.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, cast

import numpy as np

from misdirect.core.keywords import checked_keywords
from misdirect.core.model import AlterationArray, Problem, reachable_from
from misdirect.core.product import full_product_matrix


@dataclass(frozen=True)
class Simulation:
    """Outcome counts of ``runs`` simulated runs (:func:`simulate`); they add up to ``runs``:
    ``decoy_hits + sum(absorbed) + alarms + trapped + unfinished``.

    Attributes
    ----------
    runs : int
        Runs simulated.
    decoy_hits : int
        Runs that ended in a decoy state (``decoys`` splits them by state).
    absorbed : dict of str to int
        Runs that stopped in each absorbing non-decoy (goal) state; a monitored problem's
        alarm sink is not among them (``alarms``).
    unfinished : int
        Runs still going after ``max_steps``.
    mean_steps : float
        Mean length of the runs that stopped in a decoy or goal state.
    alarms : int
        Runs a monitor (or a step bound) ended by raising the alarm; 0 on a problem without.
    alarm_mean_step : float
        Mean number of readings a caught run received, the one that raised the alarm
        included (1: caught on its first reading); NaN when no run was caught.
    alarm_state : str or None
        The monitored problem's alarm sink, None without a monitor.
    trapped : int
        Runs stopped where no decoy or goal state is reachable any more.
    trajectories : list of tuple
        ``(run, step, state, memory node, observation received, action)`` of the recorded
        runs.
    """

    runs: int
    decoy_hits: int
    absorbed: dict[str, int]  # absorbing non-decoy (goal) state -> runs that stopped there
    unfinished: int  # runs still going after max_steps
    mean_steps: float  # over finished runs only: those that stopped in a decoy or goal state
    trapped: int = 0  # runs stopped in a product state from which no decoy or goal is reachable
    decoys: dict[str, int] = field(default_factory=dict)  # decoy state -> runs that ended there
    trajectories: list[tuple[int, int, str, str, str, str]] = field(default_factory=list)
    # (run, step, state, memory node, observation received, action) for the recorded runs
    visits: np.ndarray | None = field(default=None, compare=False, repr=False)
    # (|S|,) steps taken from each state over all runs (count_visits=True), else None
    alarms: int = 0  # runs ended by the monitor's alarm (a monitored problem only)
    alarm_mean_step: float = float("nan")  # mean readings received by a caught run
    alarm_state: str | None = None  # the monitored problem's alarm sink

    def confidence_interval(self, z: float = 1.96) -> tuple[float, float]:
        """Wilson score interval for the decoy frequency (z = 1.96: 95 %)."""
        return wilson_interval(self.decoy_hits, self.runs, z)

    def to_dict(self) -> dict[str, Any]:
        """The counts, the decoy frequency and its 95 % interval (trajectories left out)."""
        low, high = self.confidence_interval()
        return {
            "runs": self.runs,
            "decoy_hits": self.decoy_hits,
            "decoy_frequency": self.decoy_hits / self.runs,
            "confidence_interval": [low, high],
            "decoys": self.decoys,
            "absorbed": self.absorbed,
            "trapped": self.trapped,
            "unfinished": self.unfinished,
            "mean_steps": self.mean_steps,
            **(
                {"alarms": self.alarms, "alarm_mean_step": self.alarm_mean_step}
                if self.alarm_state is not None
                else {}
            ),
        }


def wilson_interval(hits: int, runs: int, z: float = 1.96) -> tuple[float, float]:
    """Wilson score interval for a frequency ``hits / runs`` (z = 1.96: 95 %)."""
    n, p = runs, hits / runs
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * np.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return float(centre - half), float(centre + half)


@checked_keywords
def simulate(
    problem: Problem,
    alteration: AlterationArray | None = None,
    *,
    runs: int = 10_000,
    seed: int = 0,
    max_steps: int = 10_000,
    record: int = 0,
    count_visits: bool = False,
) -> Simulation:
    """Monte-Carlo runs of the attacked robot, straight from the POMDP and the controller.

    An independent check of :func:`evaluate`: it never builds the product chain the exact
    value comes from. A run stops in a decoy or absorbing state; on a monitored problem
    (:func:`misdirect.core.monitor.with_monitor`) a run the alarm ends is counted apart
    (``alarms``), with the mean reading it is caught on.

    Parameters
    ----------
    problem : Problem
        The POMDP, controller and decoy.
    alteration : Alteration or array of int, optional
        What the robot receives for each observation. Default: no alteration.
    runs : int
        Number of runs, simulated together (vectorised over runs).
    seed : int
        Seed of the random generator: the same seed gives the same runs.
    max_steps : int
        Steps after which a run still going counts as ``unfinished``.
    record : int
        Keep the first ``record`` runs step by step (``Simulation.trajectories``).
    count_visits : bool
        Count the steps taken from each state over all runs (``Simulation.visits``; divided
        by ``runs``, the simulated counterpart of the expected visits).

    Returns
    -------
    Simulation
        The outcome counts; ``confidence_interval()`` is the Wilson interval of the decoy
        frequency.

    Examples
    --------
    >>> import misdirect
    >>> from misdirect.scenarios import paper_grid
    >>> problem = paper_grid(5)
    >>> runs = misdirect.simulate(problem, problem.alteration({"o1": "o3"}), runs=20_000)
    >>> low, high = runs.confidence_interval()
    >>> low < misdirect.evaluate(problem, problem.alteration({"o1": "o3"})).probability < high
    True

    Notes
    -----

    A run that enters a product state (world state, memory node) from which no decoy or
    absorbing state is reachable under this alteration is stopped there too and counted as
    ``trapped``: it would go on forever. The first ``record`` runs are kept step by step as
    trajectories.
    """
    rng = np.random.default_rng(seed)
    pomdp, controller = problem.pomdp, problem.controller
    alpha = problem.identity() if alteration is None else np.asarray(alteration)
    matrix = pomdp.transitions
    # Sampling s' from row r: the first entry of r whose running sum exceeds u. Adding the row
    # number to the within-row running sums makes one sorted key array for all rows.
    keys = _sampling_keys(matrix.indptr, matrix.data)
    # the same for the controller's moves: one (action, next node) entry drawn per live run
    randomized = not controller.is_deterministic
    move_keys = _sampling_keys(controller.move_ptr, controller.move_probability)

    state = np.full(runs, pomdp.initial_state)
    node = np.full(runs, controller.initial_node)
    stopped_at = np.full(runs, -1)
    steps = np.zeros(runs, dtype=np.int64)
    live = np.arange(runs)
    stop = problem.decoy | pomdp.absorbing
    n_nodes = controller.n_nodes
    can_stop = _can_stop(problem, alpha, stop)  # over product states s * |N| + n
    trapped_at = np.zeros(runs, dtype=bool)
    trajectories: list[tuple[int, int, str, str, str, str]] = []
    visits = np.zeros(pomdp.n_states, dtype=np.int64) if count_visits else None
    for step in range(max_steps + 1):
        here = state[live]
        done = stop[here]
        stuck = ~done & ~can_stop[here * n_nodes + node[live]]
        if record:
            for k in np.flatnonzero((done | stuck) & (live < record)).tolist():
                run = int(live[k])
                trajectories.append(
                    (
                        run,
                        step,
                        pomdp.states[state[run]],
                        controller.nodes[node[run]],
                        "",
                        "(stopped)" if done[k] else "(trapped: never stops)",
                    )
                )
        stopped_at[live[done]] = here[done]
        steps[live[done]] = step
        trapped_at[live[stuck]] = True
        live = live[~(done | stuck)]
        if live.size == 0 or step == max_steps:
            break
        if visits is not None:
            np.add.at(visits, state[live], 1)
        seen = alpha[pomdp.observation_of[state[live]]]
        move = controller.move[node[live], seen]
        entry = controller.move_ptr[move]
        if randomized:  # deterministic runs draw nothing here, so their streams are unchanged
            entry = np.searchsorted(move_keys, move + rng.random(live.size), side="right")
            entry = np.minimum(entry, controller.move_ptr[move + 1] - 1)
        action = controller.move_action[entry]
        if record:
            for j in np.flatnonzero(live < record):
                run = int(live[j])
                trajectories.append(
                    (
                        run,
                        step,
                        pomdp.states[state[run]],
                        controller.nodes[node[run]],
                        pomdp.observations[seen[j]],
                        pomdp.actions[action[j]],
                    )
                )
        node[live] = controller.move_next[entry]
        row = action * pomdp.n_states + state[live]
        pick = np.searchsorted(keys, row + rng.random(live.size), side="right")
        pick = np.minimum(pick, matrix.indptr[row + 1] - 1)
        state[live] = matrix.indices[pick]

    finished = stopped_at >= 0
    ended = np.bincount(stopped_at[finished], minlength=pomdp.n_states)
    goals = pomdp.absorbing & ~problem.decoy
    # a monitored problem's alarm sink is a kind of its own; a run caught on its k-th
    # reading enters it at step k (the alarm action's step)
    sink = problem.alarm_state
    caught = np.zeros(runs, dtype=bool)
    if sink is not None:
        caught = finished & (stopped_at == sink)
        goals[sink] = False
    finished &= ~caught  # the mean length is over runs that ended in a decoy or goal
    return Simulation(
        runs=runs,
        decoy_hits=int(ended[problem.decoy].sum()),
        absorbed={pomdp.states[s]: int(ended[s]) for s in np.flatnonzero(goals)},
        unfinished=int((~finished & ~caught & ~trapped_at).sum()),
        mean_steps=float(steps[finished].mean()) if finished.any() else float("nan"),
        trapped=int(trapped_at.sum()),
        decoys={pomdp.states[s]: int(ended[s]) for s in np.flatnonzero(problem.decoy)},
        trajectories=sorted(trajectories),
        visits=visits,
        alarms=int(caught.sum()),
        alarm_mean_step=float(steps[caught].mean()) if caught.any() else float("nan"),
        alarm_state=None if sink is None else pomdp.states[sink],
    )


def _sampling_keys(indptr: np.ndarray, data: np.ndarray) -> np.ndarray:
    """Row number plus the within-row running sum of each entry: one sorted key array for
    all rows, so drawing from row ``r`` is ``searchsorted(keys, r + u)`` (u uniform)."""
    lengths = np.diff(indptr)
    running = np.cumsum(data)
    running -= np.repeat(np.concatenate([[0.0], running[indptr[1:-1] - 1]]), lengths)
    return cast(np.ndarray, np.repeat(np.arange(lengths.size), lengths) + running)


def _can_stop(problem: Problem, alpha: np.ndarray, stop: np.ndarray) -> np.ndarray:
    """Mask over product states ``s * |N| + n``: some decoy or absorbing state is reachable from
    there under ``alpha``. Only this stopping test uses the product's structure; the runs
    themselves still step through the POMDP and the controller directly."""
    backwards = full_product_matrix(problem, alpha).T.tocsr()
    world = np.repeat(np.arange(problem.pomdp.n_states), problem.controller.n_nodes)
    return reachable_from(backwards, np.flatnonzero(stop[world]))
