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

With ``randomized=True`` the master is :class:`~misdirect.defence.robust_gradient.
GradientMaster` instead: randomized controllers with ``memory`` nodes, a local search by exact
adjoint gradients. With ``master="paynt"`` it is :class:`~misdirect.defence.robust_paynt.
PayntMaster`: PAYNT on one POMDP whose hidden first step picks the member of ``K`` (the
average), tightened toward the worst case by multiplicative weights. Neither proves a bound
(``master_bound`` is None, no gap); the oracle's side (the certified worst case of the
controller returned) holds as above.

Every value reported is re-evaluated through :func:`misdirect.core.evaluate.decoy_value` (the
project's exact evaluation); the master's own batched solves only rank candidates.
"""

from __future__ import annotations

import math
import time
from collections.abc import Iterable
from dataclasses import dataclass, field, replace
from typing import Any, NamedTuple

import numpy as np

from misdirect.core import tolerance
from misdirect.core.model import Controller, Problem
from misdirect.defence.attack import attacker_budget, shared_deadline
from misdirect.defence.robust_baselines import (
    KINDS,
    Baseline,
    Skipped,
    best_blind,
    blind_controllers,
)
from misdirect.defence.robust_baselines import baselines as measure_baselines
from misdirect.defence.robust_gradient import (
    ChainModel,
    GradientMaster,
    better,
    controller_of,
    embedded,
    mu_of,
)
from misdirect.defence.robust_oracle import (
    Worst,
    can_trap,
    goal_states,
    memoryless_controller,
    objective_value,
    oracle,
    target_and_worth,
)
from misdirect.defence.robust_paynt import PayntMaster, single_changes
from misdirect.errors import ProblemError
from misdirect.solvers.deadline import Deadline

OBJECTIVES = ("decoy", "goal")
MASTERS = ("exact", "gradient", "paynt")
MAX_CANDIDATES = 5_000_000  # controllers the exact master enumerates at most
_BATCH = 2048  # candidates solved at once (each a dense product chain)
GRADIENT_ROUNDS = 50  # rounds of the gradient master at most, by default
SEED_CANDIDATES = 100_000  # one-node classes up to this size: the exact master's answer seeds
# the randomized one (the paper's grid: 65,536)
SEED_SHARE = 0.5  # of the time left, the exact one-node seed may take at most this share


@dataclass(frozen=True)
class RobustRound:
    """One round of constraint generation."""

    k_size: int  # |K| the master solved against
    master_value: float  # the master's value over K (a bound on the min-max, see module doc)
    worst_case: float  # the exact value of the oracle's attack on the master's controller
    oracle_bound: float  # the oracle's proven bound on that controller's worst case
    certified: bool  # the oracle proved its answer optimal
    alteration: dict[str, str]
    candidates: int  # controllers the master looked at (gradient master: its starts)
    time_s: float
    iterations: int = 0  # the gradient master's optimiser iterations (0 for the exact master)

    def to_dict(self) -> dict[str, Any]:
        return {
            "k_size": self.k_size,
            "master_value": self.master_value,
            "worst_case": self.worst_case,
            "oracle_bound": self.oracle_bound,
            "certified": self.certified,
            "alteration": self.alteration,
            "candidates": self.candidates,
            "iterations": self.iterations,
            "time_s": self.time_s,
        }


@dataclass(frozen=True)
class Seed:
    """A controller of the class the randomized master started from, with its certified
    worst case: the answer is never worse (the seed is the loop's incumbent)."""

    name: str
    worst_case: float
    bound: float
    certified: bool
    note: str | None = None

    def to_dict(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "worst_case": self.worst_case,
            "bound": self.bound,
            "certified": self.certified,
            "note": self.note,
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
    master: str = "exact"  # "exact" (enumeration), "gradient" or "paynt" (no bound)
    master_bound: float | None = None  # the master's side of the bounds (None: not exact)
    seed: int | None = None  # the gradient master's seed
    restarts: int | None = None  # the gradient master's starts per round
    nominal_goal: float | None = None  # Pr(goal) with no alteration
    min_goal: float | None = None  # the floor asked for on the nominal Pr(goal)
    certified: bool = False  # the oracle proved ``worst_case`` for ``controller``
    skipped_baselines: tuple[Skipped, ...] = ()  # baselines not computed, with the reason
    seeds: tuple[Seed, ...] = ()  # the randomized master's seeds (empty for the exact master)

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
            "certified": self.certified,
            "alteration": self.alteration,
            "nominal": self.nominal,
            "nominal_goal": self.nominal_goal,
            "min_goal": self.min_goal,
            "lower_bound": self.lower,
            "upper_bound": self.upper,
            "gap": self.gap,
            "optimal": self.optimal,
            "k_size": self.k_size,
            "master": self.master,
            "master_bound": self.master_bound,
            "randomized": self.master == "gradient",
            "seed": self.seed,
            "restarts": self.restarts,
            "rounds": [r.to_dict() for r in self.rounds],
            "baselines": [b.to_dict() for b in self.baselines],
            "skipped_baselines": [b.to_dict() for b in self.skipped_baselines],
            "seeds": [b.to_dict() for b in self.seeds],
            "controller": controller_dict(self.controller),
            "time_s": self.time_s,
            "stop_reason": self.stop_reason,
            "notes": list(self.notes),
        }


def controller_dict(controller: Controller) -> dict[str, Any]:
    """The controller in the JSON output: the tables ``action``/``update`` of a deterministic
    one; ``moves[node][reading]`` = ``[[action, next node, probability], ...]`` otherwise."""
    out: dict[str, Any] = {
        "nodes": list(controller.nodes),
        "deterministic": controller.is_deterministic,
    }
    if controller.is_deterministic:
        out["action"] = np.asarray(controller.action).tolist()
        out["update"] = np.asarray(controller.update).tolist()
        return out
    out["moves"] = [
        [[list(entry) for entry in controller.move_table(int(m))] for m in row]
        for row in controller.move
    ]
    return out


class _Evaluator:
    """Batched values of deterministic controllers of one class on dense product chains.

    Ranks candidates for the master only: every number reported is re-evaluated exactly."""

    def __init__(self, problem: Problem, objective: str, memory: int) -> None:
        pomdp = problem.pomdp
        self.n_s, self.k = pomdp.n_states, memory
        self.dense = np.stack(
            [pomdp.transition_matrix(a).toarray() for a in range(pomdp.n_actions)]
        )  # (A, S, S)
        target, worth = target_and_worth(problem, objective)
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


@dataclass(frozen=True)
class _Floor:
    """The floor on the nominal Pr(goal) the exact master enforces (``--min-goal``)."""

    evaluator: _Evaluator  # the goal objective, same class
    identity: np.ndarray  # no alteration
    min_goal: float


class _Cache:
    """What the exact master learnt of each candidate in earlier rounds (``K`` only grows):
    the largest ``sense * value`` over the members it was solved against (a lower bound on
    its max over ``K``; ``inf`` below the floor), which members (a bit per member, the first
    64), and whether the floor was checked. A candidate already known worse than the
    incumbent is cut without a solve; one solved against a member is not solved again."""

    BITS = 64

    def __init__(self, total: int) -> None:
        self.lower = np.full(total, -math.inf)
        self.done = np.zeros(total, dtype=np.uint64)
        self.floor_checked = np.zeros(total, dtype=bool)
        self.top_goal = -math.inf


class _MasterAnswer(NamedTuple):
    value: float  # sense * the best max over K (inf: no candidate, e.g. none meets the floor)
    action: np.ndarray
    update: np.ndarray
    looked: int  # candidates enumerated
    finished: bool  # False: the deadline cut the enumeration short
    top_goal: float  # the highest nominal Pr(goal) seen (with a floor; else -inf)


def _master(
    evaluator: _Evaluator,
    cells: np.ndarray,
    n_actions: int,
    k: int,
    n_obs: int,
    alterations: list[np.ndarray],
    sense: float,
    deadline: Deadline,
    floor: _Floor | None = None,
    cache: _Cache | None = None,
) -> _MasterAnswer:
    """min over the class of max over ``alterations`` of ``sense * value`` (sense = 1 for
    decoy, -1 for goal); with ``floor``, over the controllers whose nominal Pr(goal) meets it
    only (the others are dropped before any member of ``K`` is evaluated)."""
    n_moves = n_actions * k
    n_cells = cells.size  # (node, reading) cells that matter, flattened node * n_obs + o
    total = n_moves**n_cells
    best = math.inf
    best_action = np.zeros((k, n_obs), dtype=np.int64)
    best_update = np.zeros((k, n_obs), dtype=np.int64)
    looked = 0
    top_goal = -math.inf if cache is None else cache.top_goal
    # the newest attack cuts most candidates off first
    order = list(reversed(list(enumerate(alterations))))
    for begin in range(0, total, _BATCH):
        if deadline.expired():
            return _MasterAnswer(best, best_action, best_update, looked, False, top_goal)
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
        worst = np.full(index.size, -math.inf) if cache is None else cache.lower[index].copy()
        alive = np.arange(index.size)[worst < best + tolerance.PRUNE]
        if floor is not None:
            need = alive if cache is None else alive[~cache.floor_checked[index[alive]]]
            if need.size:
                goal = floor.evaluator.values(action[need], update[need], floor.identity)
                top_goal = max(top_goal, float(goal.max()))
                short = need[goal < floor.min_goal - tolerance.slack(floor.min_goal)]
                worst[short] = math.inf
                if cache is not None:
                    cache.floor_checked[index[need]] = True
                    cache.lower[index[short]] = math.inf
                alive = alive[worst[alive] < math.inf]
        for j, alpha in order:
            if alive.size == 0:
                break
            todo = alive
            if cache is not None and j < _Cache.BITS:
                bit = np.uint64(1 << j)
                todo = alive[(cache.done[index[alive]] & bit) == 0]
            if todo.size:
                v = sense * evaluator.values(action[todo], update[todo], alpha)
                worst[todo] = np.maximum(worst[todo], v)
                if cache is not None:
                    cache.lower[index[todo]] = worst[todo]
                    if j < _Cache.BITS:
                        cache.done[index[todo]] |= bit
            alive = alive[worst[alive] < best + tolerance.PRUNE]  # near-ties stay
        if alive.size:
            i = alive[np.argmin(worst[alive])]
            if worst[i] < best:
                best, best_action, best_update = float(worst[i]), action[i], update[i]
    if cache is not None:
        cache.top_goal = top_goal
    return _MasterAnswer(best, best_action, best_update, looked, True, top_goal)


# -- the loop -----------------------------------------------------------------------------------


def robust_controller(
    problem: Problem,
    budget: float | None = None,
    *,
    memory: int = 1,
    objective: str = "decoy",
    randomized: bool = False,
    restarts: int = 4,
    seed: int = 0,
    min_goal: float | None = None,
    time_limit: float | None = None,
    baselines: bool | Iterable[str] = True,
    max_rounds: int | None = None,
    exact_seed: bool = True,
    master: str | None = None,
) -> RobustResult:
    """The controller with ``memory`` nodes that holds up best against every alteration
    within ``budget``, by constraint generation: a master over the class against a finite set
    ``K`` of alterations, :func:`misdirect.solve` as the certified oracle.

    Parameters
    ----------
    problem : Problem
        The POMDP, costs and decoy; its controller is the baseline "given controller".
    budget : float, optional
        The attacker's budget ``B`` (default: the problem's).
    memory : int
        Memory nodes of the controllers searched (node ``n0`` is initial).
    objective : {"decoy", "goal"}
        ``"decoy"``: minimise the worst-case Pr(decoy) (the expected decoy weight with weighted
        decoys); ``"goal"``: maximise the worst-case Pr(goal), a goal being an absorbing state
        that is neither a decoy nor an alarm.
    randomized : bool
        False: deterministic controllers, the exact master (enumeration; the min–max is
        bounded from both sides). True: randomized controllers, the gradient master
        (:mod:`misdirect.defence.robust_gradient`; a local search: the worst case of the
        controller returned is certified, its optimality is not, and the master proves no
        bound, ``master_bound`` is None).
    restarts : int
        The gradient master's starts per round (the previous round's answer, the uniform
        controller, each distinct seed, then seeded random ones; at least the fixed ones).
        The seeds (``seeds`` in the result) are deterministic controllers of the class,
        certified before the first round and kept as incumbents: the given one (at most
        ``memory`` nodes), the best observation-blind one, PAYNT's nominal one (when that
        baseline is measured) and, with ``exact_seed``, the exact one-node answer.
    seed : int
        The gradient master's seed (its random starts).
    min_goal : float, optional
        ``"decoy"`` only: a floor ``q`` on the nominal Pr(goal). The exact master excludes
        every controller whose nominal Pr(goal) is below ``q`` (the bounds are then on the
        min–max over the others; none left is a ProblemError). The gradient master penalises
        falling short of it and ranks a controller meeting it above any that does not; the
        result says whether the controller returned meets it (``nominal_goal``).
    time_limit : float, optional
        Seconds for the loop (the master and the oracle's solves); then the best controller so
        far with the bounds proven so far.
    baselines : bool or iterable of str
        Which baselines to measure at the same budget (each with its certified worst case):
        ``"given"``, ``"blind"``, ``"harden"``, ``"paynt"`` (:mod:`misdirect.defence.
        robust_baselines`); True for all, False for none. One that cannot be computed (PAYNT
        missing, costs that share no unit with protection) is in ``skipped_baselines``.
    max_rounds : int, optional
        Rounds at most (default 1000 for the exact master, 50 for the gradient and PAYNT
        masters).
    exact_seed : bool
        The gradient and PAYNT masters: seed them with the exact master's one-node answer where
        the one-node class has at most :data:`SEED_CANDIDATES` controllers (False: the cheap
        seeds only, the given, blind and PAYNT controllers).
    master : {"exact", "gradient", "paynt"}, optional
        The master (default: ``"gradient"`` with ``randomized``, else ``"exact"``).
        ``"paynt"``: PAYNT synthesizes deterministic ``memory``-node controllers on one POMDP
        whose hidden first step picks the member of ``K`` (their weighted average), the
        weights moved toward the members it fares worst against between a few syntheses
        (:mod:`misdirect.defence.robust_paynt`); like the gradient master it proves no bound,
        its seeds are incumbents. Needs PAYNT (a ProblemError otherwise).

    Returns
    -------
    RobustResult
        The controller, its worst case (exact value of the attack achieving it) and the
        oracle's proven bound on it, its nominal value, the bounds on the min–max and their
        gap, the rounds, and the baselines. For ``"decoy"`` ``lower`` is the master's value over
        ``K`` and ``upper`` the best oracle bound; for ``"goal"`` the other way round (module
        docstring). The gradient master gives only the oracle's side.
    """
    began = time.perf_counter()
    if objective not in OBJECTIVES:
        raise ProblemError(
            f"must be one of {', '.join(OBJECTIVES)}, got {objective!r}", field="objective"
        )
    if not (isinstance(memory, int) and memory >= 1):
        raise ProblemError(f"must be a whole number of at least 1, got {memory!r}", field="memory")
    if not (isinstance(restarts, int) and restarts >= 1):
        raise ProblemError(
            f"must be a whole number of at least 1, got {restarts!r}", field="restarts"
        )
    if min_goal is not None:
        if objective != "decoy":
            raise ProblemError(
                "a floor on the nominal Pr(goal) needs the decoy objective", field="min_goal"
            )
        if not (math.isfinite(min_goal) and 0 <= min_goal <= 1):
            raise ProblemError(f"must be a probability in [0, 1], got {min_goal}", field="min_goal")
    if master is None:
        master = "gradient" if randomized else "exact"
    if master not in MASTERS:
        raise ProblemError(f"must be one of {', '.join(MASTERS)}, got {master!r}", field="master")
    if randomized and master != "gradient":
        raise ProblemError(
            f"randomized controllers are the gradient master's; the {master} master searches "
            "deterministic ones",
            field="master",
        )
    budget = attacker_budget(problem, budget)
    pomdp = problem.pomdp
    n_obs, n_actions = pomdp.n_observations, pomdp.n_actions
    sense = 1.0 if objective == "decoy" else -1.0
    gradient: GradientMaster | None = None
    search: GradientMaster | PayntMaster | None = None  # a master without a bound
    if master == "paynt":
        search = PayntMaster(problem, objective, memory, min_goal)
        rounds_cap = GRADIENT_ROUNDS if max_rounds is None else max_rounds
    elif master == "gradient":
        target, worth = target_and_worth(problem, objective)
        goal = goal_states(problem)
        gradient = GradientMaster(
            ChainModel(pomdp, target, worth, memory),
            sense,
            restarts=restarts,
            seed=seed,
            floor=None
            if min_goal is None
            else (
                ChainModel(pomdp, goal, goal.astype(float), memory),
                problem.identity(),
                min_goal,
            ),
        )
        search = gradient
        rounds_cap = GRADIENT_ROUNDS if max_rounds is None else max_rounds
    else:
        receivable = _receivable(problem, budget)
        cells = (np.arange(memory)[:, None] * n_obs + np.flatnonzero(receivable)[None, :]).ravel()
        count = (n_actions * memory) ** cells.size
        if count > MAX_CANDIDATES:
            raise ProblemError(
                f"the exact master would enumerate {count:,} controllers ({n_actions} actions x "
                f"{memory} nodes per cell, {cells.size} cells), more than {MAX_CANDIDATES:,}; "
                "larger classes need the randomized master (docs/robust.md)",
                field="memory",
            )
        evaluator = _Evaluator(problem, objective, memory)
        floor = (
            None
            if min_goal is None
            else _Floor(_Evaluator(problem, "goal", memory), problem.identity(), min_goal)
        )
        rounds_cap = 1000 if max_rounds is None else max_rounds
        cache = _Cache(count)
    deadline = shared_deadline(time_limit)
    notes: list[str] = []
    alterations: list[np.ndarray] = [problem.identity()]
    if isinstance(search, PayntMaster) and search.warm:
        # PAYNT meets many members at once (one copy each): K starts with every single change
        warm = single_changes(problem, budget)
        alterations += warm
        if warm:
            notes.append(
                f"PAYNT master: K started with the {len(warm)} single changes within the budget"
            )
    rounds: list[RobustRound] = []
    # ((shortfall below the floor, sense * bound, tie-break), controller, worst)
    best: tuple[tuple[float, float, float], Controller, Worst] | None = None
    master_bound = -math.inf  # sense * the master's value: a bound from below in sense terms
    stop = "time limit"

    def worst_over_k(controller: Controller) -> float:
        candidate = replace(problem, controller=controller)
        return max(sense * objective_value(candidate, objective, a) for a in alterations)

    def nominal_rank(controller: Controller) -> tuple[float, float]:
        """The shortfall below the floor (the floor is on Pr(goal), with the decoy objective
        only), and the other objective's nominal value as a tie-break (for decoy, a higher
        Pr(goal) is better; for goal, a lower Pr(decoy))."""
        other = "goal" if objective == "decoy" else "decoy"
        nominal = objective_value(
            replace(problem, controller=controller), other, problem.identity()
        )
        short = 0.0 if min_goal is None else max(min_goal - nominal, 0.0)
        return short, -sense * nominal

    def ranked(controller: Controller) -> tuple[float, float, float]:
        """The gradient master's exact ranking: the shortfall, the worst over K, the
        tie-break."""
        short, tie = nominal_rank(controller)
        return short, worst_over_k(controller), tie

    def certified_rank(controller: Controller, held: Worst) -> tuple[float, float, float]:
        """How the loop keeps its best: the shortfall, the certified bound, and (a master
        without a bound) the tie-break."""
        if search is None:
            return 0.0, sense * held.bound, 0.0
        short, tie = nominal_rank(controller)
        return short, sense * held.bound, tie

    kinds = KINDS if baselines is True else () if baselines is False else tuple(baselines)
    unknown = sorted(set(kinds) - set(KINDS))
    if unknown:
        raise ProblemError(
            f"unknown baseline {unknown[0]!r}: choose from {', '.join(KINDS)}", field="baselines"
        )
    # the baselines take at most a quarter of the time limit (BASELINES_SHARE); measured
    # first, so that the randomized master can start from their controllers
    refs, skipped = measure_baselines(
        problem, objective, budget, memory, min_goal, kinds, deadline=deadline
    )
    seeds: list[Seed] = []
    if search is not None:
        # the seeds (controllers of the class: the baselines, the exact one-node answer) are
        # the incumbents the rounds must beat: the answer is then never worse than any of
        # them (certified), even when the time runs out
        for name, given_controller, note in _seed_controllers(
            problem, objective, budget, memory, min_goal, refs, deadline, exact_seed
        ):
            mu = embedded(mu_of(given_controller, n_obs, n_actions), n_obs, n_actions, memory)
            incumbent = controller_of(mu, memory, n_obs, n_actions)
            held = oracle(problem, incumbent, objective, budget, deadline.remaining())
            seeds.append(Seed(name, held.value, held.bound, held.certified, note))
            if gradient is not None and not any(
                np.array_equal(mu, other) for other in gradient.seeds
            ):
                gradient.seeds.append(mu)  # one start per distinct controller
            score = certified_rank(incumbent, held)
            if held.certified and (best is None or better(score, best[0])):
                best = (score, incumbent, held)
    for _ in range(rounds_cap):
        round_began = time.perf_counter()
        iterations = 0
        if search is not None:
            answer = search.solve(alterations, deadline, ranked)
            if answer is None:
                break
            controller, looked, iterations = answer.controller, answer.candidates, answer.iterations
            exact = sense * answer.value  # already the project's exact evaluation over K
        else:
            found = _master(
                evaluator,
                cells,
                n_actions,
                memory,
                n_obs,
                alterations,
                sense,
                deadline,
                floor,
                cache,
            )
            value, action, update, looked = found.value, found.action, found.update, found.looked
            if found.finished and min_goal is not None and not math.isfinite(value):
                raise ProblemError(
                    f"no deterministic controller with {memory} node(s) has a nominal Pr(goal) "
                    f"of at least {min_goal:g} (the highest is {found.top_goal:.6f})",
                    field="min_goal",
                )
            if not found.finished or not math.isfinite(value):
                break
            controller = memoryless_controller(problem, action, update)
            # the master's value re-evaluated exactly on its controller
            exact = worst_over_k(controller)
            master_bound = max(master_bound, min(exact, value))
        worst = oracle(problem, controller, objective, budget, deadline.remaining())
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
                iterations=iterations,
            )
        )
        score = certified_rank(controller, worst)
        if best is None or better(score, best[0]):
            best = (score, controller, worst)
        if search is None and best[0][1] - master_bound <= tolerance.CERTIFY and best[2].certified:
            stop = "bounds met"
            break
        known = any(np.array_equal(worst.alteration, a) for a in alterations)
        if known and isinstance(search, PayntMaster) and search.moved:
            # the same K, other weights: PAYNT's next syntheses answer another average
            if deadline.expired():
                break
            continue
        if known:
            stop = (
                "the oracle's attack is already in K: the controller's worst case is its value "
                "over K (a local optimum of the master, no bound)"
                if search is not None and worst.certified
                else "the oracle's attack is already in K (its solve was not certified)"
            )
            break
        alterations.append(worst.alteration)
        if deadline.expired():
            break
    else:
        stop = "round limit"
    failures = [] if not isinstance(search, PayntMaster) else search.failures
    if best is None and failures:
        raise ProblemError(f"PAYNT gave no controller: {failures[-1]}", field="master")
    if best is None:
        raise ProblemError(
            "the time limit ran out before the master's first controller; give more time",
            field="time_limit",
        )
    _, controller, worst = best
    candidate = replace(problem, controller=controller)
    proven = [r.certified for r in rounds]
    lower_sense = master_bound if search is None else -math.inf  # sense-terms lower bound
    upper_sense = best[0][1] if worst.certified or any(proven) else math.inf
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
    if search is None and min_goal is not None:
        notes.append(
            f"floor on the nominal Pr(goal): the exact master searched only the controllers "
            f"whose nominal Pr(goal) is at least {min_goal:g}; the bounds are on the min-max "
            "over those"
        )
    if gradient is not None:
        notes.append(
            "randomized master (gradient, a local search): the worst case reported is the "
            "oracle's certified answer for this controller; no bound on the best controller of "
            "the class, and no gap, is claimed"
        )
    if isinstance(search, PayntMaster):
        notes.append(
            "PAYNT master (deterministic controllers synthesized on one POMDP whose hidden "
            "first step picks the member of K, reweighted toward the worst case): the worst "
            "case reported is the oracle's certified answer for this controller; no bound on "
            "the best controller of the class, and no gap, is claimed"
        )
        if failures:
            notes.append(
                f"PAYNT found no controller {len(failures)} time(s); the last: {failures[-1]}"
            )
    nominal_goal = objective_value(candidate, "goal", problem.identity())
    if min_goal is not None and nominal_goal < min_goal - tolerance.slack(min_goal):
        notes.append(
            f"no controller found meets the floor: nominal Pr(goal) {nominal_goal:.6f} < "
            f"{min_goal:g} (the one returned falls short the least)"
        )
    master_side = lower_out if objective == "decoy" else upper_out
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
        master=master,
        master_bound=None if search is not None else master_side,
        seed=seed if gradient is not None else None,
        restarts=restarts if gradient is not None else None,
        nominal_goal=nominal_goal,
        min_goal=min_goal,
        certified=worst.certified,
        skipped_baselines=skipped,
        seeds=tuple(seeds),
    )


def _seed_controllers(
    problem: Problem,
    objective: str,
    budget: float,
    memory: int,
    min_goal: float | None,
    refs: tuple[Baseline, ...],
    deadline: Deadline,
    exact_seed: bool = True,
) -> list[tuple[str, Controller, str | None]]:
    """The deterministic controllers the randomized master starts from, each with at most
    ``memory`` nodes: the given one, the best observation-blind one, PAYNT's nominal one
    (when measured), and the exact master's one-node answer when that class has at most
    :data:`SEED_CANDIDATES` controllers (within a share of the time left)."""
    out: list[tuple[str, Controller, str | None]] = []
    if problem.controller.n_nodes <= memory:
        out.append(("given controller", problem.controller, None))
    out.append(("observation-blind", best_blind(problem, objective, min_goal), None))
    out += [("PAYNT nominal", b.controller, b.note) for b in refs if b.kind == "paynt"]
    out = [entry for entry in out if entry[1].n_nodes <= memory]
    if not exact_seed:
        return out
    count = problem.pomdp.n_actions ** int(_receivable(problem, budget).sum())
    if count > SEED_CANDIDATES:
        return out
    remaining = deadline.remaining()
    if remaining is not None and remaining * SEED_SHARE < 1e-3:
        return out
    try:
        exact = robust_controller(
            problem,
            budget,
            memory=1,
            objective=objective,
            min_goal=min_goal,
            time_limit=None if remaining is None else remaining * SEED_SHARE,
            baselines=False,
        )
    except ProblemError:  # no one-node controller meets the floor, or no time for one
        return out
    note = f"{count:,} one-node controllers, {exact.stop_reason}, {exact.time_s:.1f} s"
    out.append(("exact one-node", exact.controller, note))
    return out


__all__ = [
    "Baseline",
    "RobustResult",
    "RobustRound",
    "Seed",
    "Skipped",
    "blind_controllers",
    "can_trap",
    "goal_states",
    "robust_controller",
]
