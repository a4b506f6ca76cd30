"""Robust controller synthesis by constraint generation (issue 54; docs/robust.md).

Which deterministic finite-state controller with ``memory`` nodes should the robot run so that
the worst alteration within budget ``B`` does the least harm? A double oracle:

1. **Master**, exact: over every deterministic controller of the class (one action and one next
   node per node and reading), the one that is best against every alteration of a finite set
   ``K`` (starting with "no alteration"), by enumeration in batches with an early cut-off
   (a candidate is dropped as soon as one member of ``K`` makes it worse than the incumbent).
2. **Oracle**: :func:`misdirect.solve` on that controller at budget ``B``, certified; its attack
   joins ``K``.
3. Stop when the oracle's certified worst case meets the master's value (within
   :data:`~misdirect.core.tolerance.CERTIFY`), or at the time limit.

Bounds, with ``V*`` the min–max (``"decoy"``) or max–min (``"goal"``) over the whole class:

* ``"decoy"`` (minimise the worst Pr(decoy)): the master's value over ``K`` is a **lower**
  bound on ``V*`` (``K`` is a subset of the alterations within ``B``, so every controller's
  max over ``K`` is at most its max over all, and the master minimises over the whole class);
  each oracle's certified bound on its controller's worst case is an **upper** bound on
  ``V*`` (that controller is in the class). ``lower ≤ V* ≤ upper``.
* ``"goal"`` (maximise the worst Pr(goal), a goal being an absorbing state that is neither a
  decoy nor a monitor's alarm): the master's value over ``K`` is an **upper** bound on ``V*``,
  the oracle's certified worst case a **lower** bound. The oracle is the attacker maximising
  Pr(reach a non-goal absorbing state); ``1 -`` that is the worst Pr(goal) only when no run can
  be trapped forever, which is checked (no end component in the product with every reading the
  attacker could make the robot receive); where it cannot be ruled out, the lower bound is
  not proven and the result says so.

Every value reported is re-evaluated through :func:`misdirect.core.evaluate.decoy_value` (the
project's exact evaluation); the master's own batched solves only rank candidates.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from misdirect.core import tolerance
from misdirect.core.evaluate import decoy_value
from misdirect.core.model import Controller, Problem
from misdirect.defence.attack import Attack, attack_of, attacker_budget, shared_deadline
from misdirect.errors import ProblemError
from misdirect.solvers.deadline import Deadline
from misdirect.solvers.run import solve

OBJECTIVES = ("decoy", "goal")
MAX_CANDIDATES = 5_000_000  # controllers the exact master enumerates at most
_BATCH = 2048  # candidates solved at once (each a dense product chain)


@dataclass(frozen=True)
class RobustRound:
    """One round of constraint generation."""

    k_size: int  # |K| the master solved against
    master_value: float  # the master's value over K (a bound on the min-max, see module doc)
    worst_case: float  # the exact value of the oracle's attack on the master's controller
    oracle_bound: float  # the oracle's proven bound on that controller's worst case
    certified: bool  # the oracle proved its answer optimal
    alteration: dict[str, str]
    candidates: int  # controllers the master looked at
    time_s: float

    def to_dict(self) -> dict[str, Any]:
        return {
            "k_size": self.k_size,
            "master_value": self.master_value,
            "worst_case": self.worst_case,
            "oracle_bound": self.oracle_bound,
            "certified": self.certified,
            "alteration": self.alteration,
            "candidates": self.candidates,
            "time_s": self.time_s,
        }


@dataclass(frozen=True)
class Baseline:
    """A reference controller and its certified worst case at the same budget."""

    name: str
    controller: Controller = field(repr=False)
    nominal: float  # the objective with no alteration
    worst_case: float  # exact value of the oracle's attack
    bound: float  # the oracle's proven bound on the worst case
    certified: bool
    alteration: dict[str, str]

    def to_dict(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "nominal": self.nominal,
            "worst_case": self.worst_case,
            "bound": self.bound,
            "certified": self.certified,
            "alteration": self.alteration,
        }


@dataclass(frozen=True)
class RobustResult:
    """What :func:`robust_controller` found (``to_dict``: the ``--json`` output).

    ``lower`` and ``upper`` bound the min–max (``"decoy"``) or max–min (``"goal"``) over the
    whole controller class; ``optimal`` when they meet within the tolerance. ``worst_case`` is
    the exact value of ``alteration`` on ``controller``; ``worst_case_bound`` the oracle's proven
    bound on its worst case (equal when certified). ``nominal`` is the value with no attack.
    """

    problem: str
    objective: str
    budget: float
    memory: int
    controller: Controller = field(repr=False)
    worst_case: float
    worst_case_bound: float
    alteration: dict[str, str]
    nominal: float
    lower: float | None
    upper: float | None
    optimal: bool
    rounds: tuple[RobustRound, ...]
    baselines: tuple[Baseline, ...]
    time_s: float
    stop_reason: str
    notes: tuple[str, ...] = ()

    @property
    def gap(self) -> float | None:
        if self.lower is None or self.upper is None:
            return None
        return max(self.upper - self.lower, 0.0)

    @property
    def k_size(self) -> int:
        return self.rounds[-1].k_size if self.rounds else 1

    def to_dict(self) -> dict[str, Any]:
        return {
            "problem": self.problem,
            "objective": self.objective,
            "budget": self.budget,
            "memory": self.memory,
            "worst_case": self.worst_case,
            "worst_case_bound": self.worst_case_bound,
            "alteration": self.alteration,
            "nominal": self.nominal,
            "lower_bound": self.lower,
            "upper_bound": self.upper,
            "gap": self.gap,
            "optimal": self.optimal,
            "k_size": self.k_size,
            "rounds": [r.to_dict() for r in self.rounds],
            "baselines": [b.to_dict() for b in self.baselines],
            "controller": {
                "nodes": list(self.controller.nodes),
                "action": _named_table(self.controller, "action"),
                "update": _named_table(self.controller, "update"),
            },
            "time_s": self.time_s,
            "stop_reason": self.stop_reason,
            "notes": list(self.notes),
        }


def _named_table(controller: Controller, what: str) -> list[list[int]]:
    table = controller.action if what == "action" else controller.update
    return np.asarray(table).tolist()


# -- the objective on the product chain ---------------------------------------------------------


def goal_states(problem: Problem) -> np.ndarray:
    """The goal: absorbing states that are neither decoys nor a monitor's alarm."""
    goal = problem.pomdp.absorbing & ~np.asarray(problem.decoy, dtype=bool)
    if problem.alarm_state is not None:
        goal[problem.alarm_state] = False
    return goal


def goal_attack_problem(problem: Problem) -> Problem:
    """The problem whose attacker maximises Pr(reach an absorbing state that is not a goal):
    ``1 -`` its value is Pr(goal) whenever every run is absorbed."""
    bad = problem.pomdp.absorbing & ~goal_states(problem)
    return replace(problem, decoy=bad, decoy_sets=())


def objective_value(problem: Problem, objective: str, alteration: np.ndarray) -> float:
    """The exact value (project's evaluation) of ``objective`` under ``alteration``."""
    if objective == "decoy":
        return decoy_value(problem, alteration).value
    goal = replace(problem, decoy=goal_states(problem), decoy_sets=())
    return decoy_value(goal, alteration).value


def _target_and_worth(problem: Problem, objective: str) -> tuple[np.ndarray, np.ndarray]:
    if objective == "decoy":
        o = problem.objective
        return np.asarray(o.target, dtype=bool), np.asarray(o.value, dtype=float)
    goal = goal_states(problem)
    return goal, goal.astype(float)


class _Evaluator:
    """Batched values of deterministic controllers of one class on dense product chains.

    Ranks candidates for the master only: every number reported is re-evaluated exactly."""

    def __init__(self, problem: Problem, objective: str, memory: int) -> None:
        pomdp = problem.pomdp
        self.n_s, self.k = pomdp.n_states, memory
        self.dense = np.stack(
            [pomdp.transition_matrix(a).toarray() for a in range(pomdp.n_actions)]
        )  # (A, S, S)
        target, worth = _target_and_worth(problem, objective)
        n = self.n_s * memory
        self.target = np.repeat(target, memory)  # product state s * k + node
        self.worth = np.repeat(worth, memory)
        self.obs = pomdp.observation_of
        self.start = pomdp.initial_state * memory  # initial node 0
        self.n = n

    def values(self, action: np.ndarray, update: np.ndarray, alpha: np.ndarray) -> np.ndarray:
        """Values of controllers ``action``/``update`` (B, k, |Ω|) under ``alpha``."""
        b, k, n_s = action.shape[0], self.k, self.n_s
        read = alpha[self.obs]  # (S,) the reading received in each state
        act = action[:, :, read]  # (B, k, S)
        nxt = update[:, :, read]
        rows = self.dense[act, np.arange(n_s)[None, None, :], :]  # (B, k, S, S')
        chain: np.ndarray = np.zeros((b, n_s, k, n_s, k))
        bi = np.arange(b)[:, None, None]
        ni = np.arange(k)[None, :, None]
        si = np.arange(n_s)[None, None, :]
        chain[bi, si, ni, :, nxt] = rows
        chain = np.asarray(chain.reshape(b, self.n, self.n))
        target = self.target
        chain[:, target, :] = 0.0
        # states that can reach the target (graph closure), the others are worth 0
        reach = np.broadcast_to(target, (b, self.n)).copy()
        edges = chain > 0
        for _ in range(self.n):
            grown = reach | np.einsum("bij,bj->bi", edges, reach)
            if np.array_equal(grown, reach):
                break
            reach = grown
        solve_mask = reach & ~target[None, :]
        rhs = (chain[:, :, target] @ self.worth[target]) * solve_mask
        system = np.where(solve_mask[:, :, None] & solve_mask[:, None, :], -chain, 0.0)
        idx = np.arange(self.n)
        system[:, idx, idx] += 1.0
        x = np.linalg.solve(system, rhs[:, :, None])[:, :, 0]
        x = np.where(solve_mask, x, 0.0)
        x = np.where(target[None, :], self.worth[None, :], x)
        return x[:, self.start]


def _receivable(problem: Problem, budget: float) -> np.ndarray:
    """Readings the robot can receive: emitted by a non-absorbing state, or reachable from
    one by one change the budget affords (the initial observation is never altered)."""
    pomdp = problem.pomdp
    emitted = np.zeros(pomdp.n_observations, dtype=bool)
    emitted[np.unique(pomdp.observation_of[~pomdp.absorbing])] = True
    out = emitted.copy()
    for o in np.flatnonzero(emitted):
        if o == pomdp.initial_observation or o in problem.cost.protected:
            continue
        row = problem.cost.row(int(o))
        out |= row <= budget + tolerance.FEASIBILITY
    return out


# -- the exact master ---------------------------------------------------------------------------


def _master(
    evaluator: _Evaluator,
    cells: np.ndarray,
    n_actions: int,
    k: int,
    n_obs: int,
    alterations: list[np.ndarray],
    sense: float,
    deadline: Deadline,
) -> tuple[float, np.ndarray, np.ndarray, int, bool]:
    """min over the class of max over ``alterations`` of ``sense * value`` (sense = 1 for
    decoy, -1 for goal). Returns (value, action, update, candidates looked at, finished)."""
    n_moves = n_actions * k
    n_cells = cells.size  # (node, reading) cells that matter, flattened node * n_obs + o
    total = n_moves**n_cells
    best = math.inf
    best_action = np.zeros((k, n_obs), dtype=np.int64)
    best_update = np.zeros((k, n_obs), dtype=np.int64)
    looked = 0
    order = list(reversed(alterations))  # the newest attack cuts most candidates off first
    for begin in range(0, total, _BATCH):
        if deadline.expired():
            return best, best_action, best_update, looked, False
        index = np.arange(begin, min(begin + _BATCH, total), dtype=np.int64)
        looked += index.size
        digits = np.empty((index.size, n_cells), dtype=np.int64)
        rest = index.copy()
        for c in range(n_cells):
            rest, digits[:, c] = np.divmod(rest, n_moves)
        flat_action = np.zeros((index.size, k * n_obs), dtype=np.int64)
        flat_update = np.zeros((index.size, k * n_obs), dtype=np.int64)
        flat_action[:, cells], flat_update[:, cells] = np.divmod(digits, k)
        action: np.ndarray = flat_action.reshape(-1, k, n_obs)
        update: np.ndarray = flat_update.reshape(-1, k, n_obs)
        worst = np.full(index.size, -math.inf)
        alive = np.arange(index.size)
        for alpha in order:
            v = sense * evaluator.values(action[alive], update[alive], alpha)
            worst[alive] = np.maximum(worst[alive], v)
            alive = alive[worst[alive] < best + tolerance.PRUNE]  # near-ties stay
            if alive.size == 0:
                break
        if alive.size:
            i = alive[np.argmin(worst[alive])]
            if worst[i] < best:
                best, best_action, best_update = float(worst[i]), action[i], update[i]
    return best, best_action, best_update, looked, True


def memoryless_controller(problem: Problem, action: np.ndarray, update: np.ndarray) -> Controller:
    k = action.shape[0]
    names = ("n0",) if k == 1 else tuple(f"n{i}" for i in range(k))
    return Controller(nodes=names, initial_node=0, action=action, update=update)


# -- the oracle ---------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Worst:
    value: float  # exact objective value under the attack
    bound: float  # proven bound on the worst case (objective's own sense)
    certified: bool
    alteration: np.ndarray
    changes: dict[str, str]


def _oracle(
    problem: Problem, controller: Controller, objective: str, budget: float, seconds: float | None
) -> _Worst:
    candidate = replace(problem, controller=controller)
    attacked = candidate if objective == "decoy" else goal_attack_problem(candidate)
    limit = Deadline(None if seconds is None else max(seconds, 0.05))
    result = solve(attacked.with_budget(budget), budgets=[budget], deadline=limit)
    attack: Attack = attack_of(result.curve[-1], attacked)
    alpha = (
        np.asarray(attack.alteration_array, dtype=np.int64)
        if attack.alteration_array is not None
        else candidate.identity()
    )
    value = objective_value(candidate, objective, alpha)
    if objective == "decoy":
        return _Worst(value, attack.upper, attack.certified, alpha, attack.alteration)
    proven = attack.certified and not can_trap(candidate, budget)
    bound = 1.0 - attack.upper if proven else 0.0
    return _Worst(value, min(bound, value), proven, alpha, attack.alteration)


def can_trap(problem: Problem, budget: float) -> bool:
    """Whether some alteration within ``budget`` could keep a run of the product chain from
    being absorbed forever: an end component among the non-absorbing product states when, in
    each state, the robot may receive any reading one affordable change gives (a superset of
    what any alteration does, so ``False`` is a proof)."""
    pomdp, ctrl = problem.pomdp, problem.controller
    k, n_s = ctrl.n_nodes, pomdp.n_states
    recv = _receivable_from(problem, budget)
    choices: list[list[np.ndarray]] = []  # per product state, successor sets of its choices
    for s in range(n_s):
        for n in range(k):
            options = []
            if not pomdp.absorbing[s]:
                for r in recv[int(pomdp.observation_of[s])]:
                    m = int(ctrl.move[n, r])
                    lo, hi = ctrl.move_ptr[m], ctrl.move_ptr[m + 1]
                    succ: list[int] = []
                    for a, nn in zip(ctrl.move_action[lo:hi], ctrl.move_next[lo:hi], strict=True):
                        row = pomdp.transition_matrix(int(a)).getrow(s)
                        succ.extend(int(t) * k + int(nn) for t in row.indices)
                    options.append(np.unique(np.asarray(succ, dtype=np.int64)))
            choices.append(options)
    alive = np.array([bool(c) for c in choices])
    while True:
        rows, cols = [], []
        for p in np.flatnonzero(alive):
            for option in choices[p]:
                rows.extend([p] * option.size)
                cols.extend(option.tolist())
        graph = sp.csr_matrix((np.ones(len(rows)), (rows, cols)), shape=(alive.size,) * 2)
        _, label = connected_components(graph, directed=True, connection="strong")
        changed = False
        for p in np.flatnonzero(alive):
            kept = [
                succ
                for succ in choices[p]
                if np.all(alive[succ]) and np.all(label[succ] == label[p])
            ]
            if len(kept) != len(choices[p]):
                choices[p] = kept
                changed = True
            if not kept:
                alive[p] = False
                changed = True
        if not changed:
            return bool(alive.any())


def _receivable_from(problem: Problem, budget: float) -> dict[int, list[int]]:
    pomdp = problem.pomdp
    out: dict[int, list[int]] = {}
    for o in range(pomdp.n_observations):
        if o == pomdp.initial_observation or o in problem.cost.protected:
            out[o] = [o]
            continue
        row = problem.cost.row(o)
        targets = set(np.flatnonzero(row <= budget + tolerance.FEASIBILITY).tolist()) | {o}
        out[o] = sorted(int(t) for t in targets)
    return out


# -- the loop -----------------------------------------------------------------------------------


def robust_controller(
    problem: Problem,
    budget: float | None = None,
    *,
    memory: int = 1,
    objective: str = "decoy",
    time_limit: float | None = None,
    baselines: bool = True,
    max_rounds: int = 1000,
) -> RobustResult:
    """The deterministic controller with ``memory`` nodes that holds up best against every
    alteration within ``budget``, by constraint generation with an exact master.

    Parameters
    ----------
    problem : Problem
        The POMDP, costs and decoy; its controller is the baseline "given controller".
    budget : float, optional
        The attacker's budget ``B`` (default: the problem's).
    memory : int
        Memory nodes of the controllers searched (deterministic; node ``n0`` is initial).
    objective : {"decoy", "goal"}
        ``"decoy"``: minimise the worst-case Pr(decoy) (the expected decoy weight with weighted
        decoys); ``"goal"``: maximise the worst-case Pr(goal), a goal being an absorbing state
        that is neither a decoy nor an alarm.
    time_limit : float, optional
        Seconds for the loop (the master's enumeration and the oracle's solves); then the best
        controller so far with the bounds proven so far.
    baselines : bool
        Also compute the given controller's and the best observation-blind controller's
        certified worst cases.

    Returns
    -------
    RobustResult
        The controller, its worst case (exact value of the attack achieving it) and the
        oracle's proven bound on it, its nominal value, the bounds on the min–max and their
        gap, the rounds, and the baselines. For ``"decoy"`` ``lower`` is the master's value over
        ``K`` and ``upper`` the best oracle bound; for ``"goal"`` the other way round (module
        docstring).
    """
    began = time.perf_counter()
    if objective not in OBJECTIVES:
        raise ProblemError(
            f"must be one of {', '.join(OBJECTIVES)}, got {objective!r}", field="objective"
        )
    if not (isinstance(memory, int) and memory >= 1):
        raise ProblemError(f"must be a whole number of at least 1, got {memory!r}", field="memory")
    budget = attacker_budget(problem, budget)
    pomdp = problem.pomdp
    n_obs, n_actions = pomdp.n_observations, pomdp.n_actions
    receivable = _receivable(problem, budget)
    cells = (np.arange(memory)[:, None] * n_obs + np.flatnonzero(receivable)[None, :]).ravel()
    count = (n_actions * memory) ** cells.size
    if count > MAX_CANDIDATES:
        raise ProblemError(
            f"the exact master would enumerate {count:,} controllers ({n_actions} actions x "
            f"{memory} nodes per cell, {cells.size} cells), more than {MAX_CANDIDATES:,}; "
            "larger classes need a master not done yet (docs/robust.md)",
            field="memory",
        )
    deadline = shared_deadline(time_limit)
    sense = 1.0 if objective == "decoy" else -1.0
    evaluator = _Evaluator(problem, objective, memory)
    alterations: list[np.ndarray] = [problem.identity()]
    rounds: list[RobustRound] = []
    best: tuple[float, Controller, _Worst] | None = None  # (sense * bound, controller, worst)
    master_bound = -math.inf  # sense * the master's value: a bound from below in sense terms
    stop = "time limit"
    notes: list[str] = []
    for _ in range(max_rounds):
        round_began = time.perf_counter()
        value, action, update, looked, finished = _master(
            evaluator, cells, n_actions, memory, n_obs, alterations, sense, deadline
        )
        if not finished or not math.isfinite(value):
            break
        controller = memoryless_controller(problem, action, update)
        candidate = replace(problem, controller=controller)
        # the master's value re-evaluated exactly on its controller
        exact = max(sense * objective_value(candidate, objective, a) for a in alterations)
        master_bound = max(master_bound, min(exact, value))
        worst = _oracle(problem, controller, objective, budget, deadline.remaining())
        rounds.append(
            RobustRound(
                k_size=len(alterations),
                master_value=sense * exact,
                worst_case=worst.value,
                oracle_bound=worst.bound,
                certified=worst.certified,
                alteration=worst.changes,
                candidates=looked,
                time_s=time.perf_counter() - round_began,
            )
        )
        score = sense * worst.bound
        if best is None or score < best[0] - tolerance.IMPROVE:
            best = (score, controller, worst)
        if best[0] - master_bound <= tolerance.CERTIFY and best[2].certified:
            stop = "bounds met"
            break
        if any(np.array_equal(worst.alteration, a) for a in alterations):
            stop = "the oracle's attack is already in K (its solve was not certified)"
            break
        alterations.append(worst.alteration)
        if deadline.expired():
            break
    else:
        stop = "round limit"
    if best is None:
        raise ProblemError(
            "the time limit ran out before the master's first controller; give more time",
            field="time_limit",
        )
    _, controller, worst = best
    candidate = replace(problem, controller=controller)
    proven = [r.certified for r in rounds]
    lower_sense = master_bound  # sense-terms lower bound on the min-max
    upper_sense = best[0] if worst.certified or any(proven) else math.inf
    if objective == "decoy":
        lower, upper = lower_sense, upper_sense
    else:
        lower, upper = -upper_sense, -lower_sense
    lower_out = None if not math.isfinite(lower) else lower
    upper_out = None if not math.isfinite(upper) else upper
    optimal = (
        lower_out is not None
        and upper_out is not None
        and upper_out - lower_out <= tolerance.CERTIFY
    )
    if objective == "goal" and not worst.certified:
        notes.append(
            "the worst-case Pr(goal) is not proven: the oracle's solve was not certified, or a "
            "run might be trapped forever under some alteration (then 1 - Pr(non-goal end) is not "
            "Pr(goal))"
        )
    refs = _baselines(problem, objective, budget, deadline) if baselines else ()
    return RobustResult(
        problem=problem.title,
        objective=objective,
        budget=budget,
        memory=memory,
        controller=controller,
        worst_case=worst.value,
        worst_case_bound=worst.bound,
        alteration=worst.changes,
        nominal=objective_value(candidate, objective, problem.identity()),
        lower=lower_out,
        upper=upper_out,
        optimal=optimal,
        rounds=tuple(rounds),
        baselines=refs,
        time_s=time.perf_counter() - began,
        stop_reason=stop,
        notes=tuple(notes),
    )


def blind_controllers(problem: Problem) -> list[Controller]:
    """One memoryless controller per action, playing it whatever it reads: no alteration can
    change what it does."""
    n_obs = problem.pomdp.n_observations
    zeros = np.zeros((1, n_obs), dtype=np.int64)
    return [
        memoryless_controller(problem, np.full((1, n_obs), a, dtype=np.int64), zeros)
        for a in range(problem.pomdp.n_actions)
    ]


def _baselines(
    problem: Problem, objective: str, budget: float, deadline: Deadline
) -> tuple[Baseline, ...]:
    sense = 1.0 if objective == "decoy" else -1.0
    blind = min(
        blind_controllers(problem),
        key=lambda c: (
            sense * objective_value(replace(problem, controller=c), objective, problem.identity())
        ),
    )
    out = []
    for name, controller in (
        ("given controller", problem.controller),
        ("observation-blind", blind),
    ):
        worst = _oracle(problem, controller, objective, budget, None)
        nominal = objective_value(
            replace(problem, controller=controller), objective, problem.identity()
        )
        out.append(
            Baseline(
                name=name,
                controller=controller,
                nominal=nominal,
                worst_case=worst.value,
                bound=worst.bound,
                certified=worst.certified,
                alteration=worst.changes,
            )
        )
    return tuple(out)


__all__ = [
    "Baseline",
    "RobustResult",
    "RobustRound",
    "blind_controllers",
    "can_trap",
    "goal_states",
    "robust_controller",
]
