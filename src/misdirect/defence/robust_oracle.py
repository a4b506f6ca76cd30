"""The robust controller's objective on the product chain and its certified oracle (issue 54).

The objective is Pr(decoy) or Pr(goal) (a goal: an absorbing state that is neither a decoy nor
a monitor's alarm), each evaluated by the project's exact evaluation. The oracle is
:func:`misdirect.solve` on one controller at the attacker's budget: its certified worst case,
which every master and every baseline of :mod:`misdirect.defence.robust` is measured by.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from misdirect.core import tolerance
from misdirect.core.evaluate import decoy_value
from misdirect.core.model import Controller, Problem
from misdirect.defence.attack import Attack, attack_of
from misdirect.solvers.deadline import Deadline
from misdirect.solvers.run import solve

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


def target_and_worth(problem: Problem, objective: str) -> tuple[np.ndarray, np.ndarray]:
    if objective == "decoy":
        o = problem.objective
        return np.asarray(o.target, dtype=bool), np.asarray(o.value, dtype=float)
    goal = goal_states(problem)
    return goal, goal.astype(float)


def memoryless_controller(problem: Problem, action: np.ndarray, update: np.ndarray) -> Controller:
    """The deterministic controller of the tables ``action``/``update`` (nodes, readings)."""
    k = action.shape[0]
    names = ("n0",) if k == 1 else tuple(f"n{i}" for i in range(k))
    return Controller(nodes=names, initial_node=0, action=action, update=update)


# -- the oracle ---------------------------------------------------------------------------------


@dataclass(frozen=True)
class Worst:
    """The oracle's answer for one controller."""

    value: float  # exact objective value under the attack
    bound: float  # proven bound on the worst case (objective's own sense)
    certified: bool
    alteration: np.ndarray
    changes: dict[str, str]


def oracle(
    problem: Problem, controller: Controller, objective: str, budget: float, seconds: float | None
) -> Worst:
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
        return Worst(value, attack.upper, attack.certified, alpha, attack.alteration)
    proven = attack.certified and not can_trap(candidate, budget)
    bound = 1.0 - attack.upper if proven else 0.0
    return Worst(value, min(bound, value), proven, alpha, attack.alteration)


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


__all__ = [
    "Worst",
    "can_trap",
    "goal_attack_problem",
    "goal_states",
    "memoryless_controller",
    "objective_value",
    "oracle",
    "target_and_worth",
]
