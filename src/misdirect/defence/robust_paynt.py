"""The PAYNT master of robust synthesis (issue 54; docs/robust.md).

PAYNT synthesizes a finite-state controller for *one* POMDP. Against a finite set ``K`` of
alterations we give it one: the **combined POMDP**, whose hidden first step picks member
``i`` of ``K`` with probability ``w_i`` and then runs the world with the readings altered by
that member (``K`` copies of the states; a state of copy ``i`` emits the altered reading
``α_i(o)``; the same actions). Its value under a controller is ``Σ_i w_i V_i``, the weighted
average of the controller's values on the altered problems, so PAYNT's optimum is the best
controller on average over ``K``. The worst case over ``K`` is then approached by
multiplicative weights: the members where the controller does worst get more weight and
PAYNT synthesizes again, a few times within the time limit; the candidate kept is the one
whose exact worst case over ``K`` (the project's exact evaluation) is best.

Why the hidden step does not leak: the robot reads the initial observation before anything
else, and the initial observation is never altered (the attacker cannot touch it, see
:meth:`~misdirect.core.model.Problem.check_alteration`). So the pick is folded into the first
move: one shared initial state emits the initial observation, and its move under action
``a`` goes to state ``t`` of copy ``i`` with probability ``w_i · P(s0, a, t)``. Every copy
reads the same first observation, the controller's first step (node ``n0``, that reading) is
the one it takes in the original problem, and no extra observation or extra step shifts
PAYNT's node numbering: PAYNT's controller (node 0 initial, an action and next node per node
and reading) is a controller over the original problem's readings, as it is.

PAYNT searches deterministic controllers with ``memory`` nodes (abstraction refinement), a
search that is not exhaustive within its time, and on an average rather than the worst case:
the master proves no bound (``master_bound`` is None); the oracle's certified worst case
stands, as for the gradient master.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from misdirect.core import tolerance
from misdirect.core.model import Controller, Pomdp, Problem
from misdirect.defence.robust_gradient import ExactWorst, MasterAnswer, better
from misdirect.defence.robust_oracle import goal_states, objective_value, target_and_worth
from misdirect.errors import MisdirectError, ProblemError
from misdirect.solvers.deadline import Deadline

SYNTHESES = 3  # PAYNT syntheses per master call (rounds of multiplicative weights)
PAYNT_SECONDS = 30.0  # one synthesis at most (PAYNT's model build included): PAYNT hands
# back its best so far, and more rounds of K beat longer searches on one K
MIN_SECONDS = 2.0  # a synthesis is not started with less time than this left
STEP = 2.0  # multiplicative weights: the best member's weight shrinks by e^-STEP a round
WEIGHT_FLOOR = 0.01  # no member's weight falls below this share of a uniform weight
WARM_MEMBERS = 64  # K starts with every single change within budget when there are at most
# this many (the combined POMDP has a copy of the world per member)


def combined_problem(
    problem: Problem, alterations: list[np.ndarray], weights: np.ndarray
) -> Problem:
    """ONE POMDP for ``K``: a hidden first step picks member ``i`` with probability
    ``weights[i]``, then the world runs with the readings of member ``i``.

    State ``0`` is the shared initial state (it emits the initial observation, never
    altered); state ``1 + i·|S| + s`` is state ``s`` of copy ``i``, emitting
    ``alterations[i][o(s)]``. Same observations and actions as ``problem``, so a controller
    of either is a controller of the other. The decoys are the copies of the decoy states
    (the start's are those of the initial state). The controller is ``problem``'s.
    """
    pomdp = problem.pomdp
    n_s = pomdp.n_states
    copies = len(alterations)
    w = np.asarray(weights, dtype=float)
    if w.shape != (copies,) or copies == 0:
        raise ProblemError(f"expected {copies} weights, got {w.shape}", field="weights")
    w = w / w.sum()
    s0 = pomdp.initial_state
    matrix = pomdp.transitions.tocoo()
    action, source = matrix.row // n_s, matrix.row % n_s
    shift = 1 + np.arange(copies)[:, None] * n_s  # (copies, 1)
    parts_a = [np.tile(action, copies)]
    parts_s = [(shift + source[None, :]).ravel()]
    parts_t = [(shift + matrix.col[None, :]).ravel()]
    parts_p = [np.tile(matrix.data, copies)]
    first = source == s0  # the start's moves: the initial state's, spread over the copies
    parts_a.append(np.tile(action[first], copies))
    parts_s.append(np.zeros(int(first.sum()) * copies, dtype=np.int64))
    parts_t.append((shift + matrix.col[first][None, :]).ravel())
    parts_p.append((w[:, None] * matrix.data[first][None, :]).ravel())
    observed = np.stack([np.asarray(a, dtype=np.int64)[pomdp.observation_of] for a in alterations])
    names = tuple(f"{name}@{i}" for i in range(copies) for name in pomdp.states)
    world = Pomdp.from_triplets(
        states=("start", *names),
        actions=pomdp.actions,
        observations=pomdp.observations,
        initial_state=0,
        observation_of=np.concatenate([[pomdp.initial_observation], observed.ravel()]),
        action=np.concatenate(parts_a),
        source=np.concatenate(parts_s),
        target=np.concatenate(parts_t),
        probability=np.concatenate(parts_p),
        absorbing=replicated(pomdp.absorbing, s0, copies),
    )
    target, _ = target_and_worth(problem, "decoy")
    return replace(
        problem,
        pomdp=world,
        decoy=replicated(target, s0, copies),
        decoy_sets=(),
        alarm_state=None,
        monitor="",
        reach_property="",
        step_bound=None,
        unwatched=None,
        name=f"{problem.title} (K = {copies} alterations)",
    )


def replicated(
    mask: np.ndarray, initial_state: int, copies: int, only: int | None = None
) -> np.ndarray:
    """A set of states of the original problem as states of the combined one: the start
    takes the initial state's membership, each copy (or only copy ``only``) its own."""
    mask = np.asarray(mask, dtype=bool)
    tiled = np.tile(mask, copies)
    if only is not None:
        tiled = np.zeros_like(tiled)
        tiled[only * mask.size : (only + 1) * mask.size] = mask
        return np.concatenate([[False], tiled])
    return np.concatenate([[bool(mask[initial_state])], tiled])


def single_changes(problem: Problem, budget: float, limit: int = WARM_MEMBERS) -> list[np.ndarray]:
    """Every alteration changing one reading the objective can depend on into another, within
    ``budget``; none when there are more than ``limit`` (a warm start of ``K``: each is an
    alteration within the budget, so every bound stays valid)."""
    out: list[np.ndarray] = []
    identity = problem.identity()
    for o in problem.relevant_observations.tolist():
        if int(o) in problem.cost.protected:
            continue
        row = problem.cost.row(int(o))
        for t in np.flatnonzero(row <= budget + tolerance.FEASIBILITY).tolist():
            if t == o:
                continue
            alpha = identity.copy()
            alpha[o] = t
            out.append(alpha)
            if len(out) > limit:
                return []
    return out


def paynt_available() -> bool:
    """Whether PAYNT can be imported (the ``misdirect[paynt]`` extra)."""
    try:
        import paynt  # noqa: F401
    except ImportError:
        return False
    return True


@dataclass
class Synthesized:
    """One PAYNT synthesis of the master: the controller and the weights it was asked for."""

    controller: Controller
    weights: np.ndarray
    values: np.ndarray  # the controller's exact value under each member of K
    prop: str


class PayntMaster:
    """PAYNT on the combined POMDP of ``K``, tightened from the average to the worst case
    by multiplicative weights (module docstring).

    The weights carry over between rounds; the member the oracle adds starts at the largest
    weight (it is the attack the last controller fares worst against)."""

    def __init__(
        self,
        problem: Problem,
        objective: str,
        memory: int,
        min_goal: float | None = None,
        *,
        syntheses: int = SYNTHESES,
        seconds: float = PAYNT_SECONDS,
        warm: bool = True,
    ) -> None:
        if not paynt_available():
            from misdirect.io.paynt_synthesis import NEEDS_PAYNT

            raise ProblemError(f"the PAYNT master {NEEDS_PAYNT}", field="master")
        if objective == "decoy" and problem.decoy_sets:
            raise ProblemError(
                "the PAYNT master minimises Pr(decoy): weighted decoys need the exact or "
                "gradient master",
                field="master",
            )
        self.problem, self.objective, self.memory = problem, objective, memory
        self.sense = 1.0 if objective == "decoy" else -1.0
        self.min_goal = min_goal
        self.syntheses, self.seconds, self.warm = syntheses, seconds, warm
        self.weights = np.ones(1)
        self.history: list[Synthesized] = []
        self.failures: list[str] = []  # PAYNT's reasons, when a synthesis found nothing
        self.moved = False  # the last call moved the weights: another call asks PAYNT anew

    def _weights_for(self, size: int) -> np.ndarray:
        w = self.weights
        if w.size < size:
            w = np.concatenate([w, np.full(size - w.size, w.max())])
        return w[:size] / w[:size].sum()

    def _properties(
        self, alterations: list[np.ndarray], w: np.ndarray
    ) -> list[tuple[str, tuple[str, ...]]]:
        """(optimizing property, constraints) to try, in order: decoy with a floor first as
        PAYNT's constraint on the identity copy's Pr(goal) (``w_j · q``), then, should PAYNT
        find none meeting it, Pr(goal) maximised on average (the floor's direction)."""
        if self.objective == "goal":
            return [('Pmax=? [F "goal"]', ())]
        plain = 'Pmin=? [F "decoy"]'
        if self.min_goal is None:
            return [(plain, ())]
        identity = self.problem.identity()
        j = next((i for i, a in enumerate(alterations) if np.array_equal(a, identity)), None)
        if j is None:
            return [('Pmax=? [F "goal"]', ())]
        # fixed-point: Storm's property parser is not asked to read an exponent
        floor = f'P>={self.min_goal * float(w[j]):.15f} [F "nominal_goal"]'
        return [(plain, (floor,)), ('Pmax=? [F "goal"]', ())]

    def solve(
        self, alterations: list[np.ndarray], deadline: Deadline, exact_worst: ExactWorst
    ) -> MasterAnswer | None:
        """The best controller PAYNT finds against ``alterations`` over a few reweighted
        syntheses, or None when no synthesis gave one (time, or PAYNT found none).
        ``exact_worst(controller)`` is the loop's exact ranking (shortfall below the floor,
        ``sense ·`` the worst over K, tie-break)."""
        from misdirect.io.paynt_synthesis import synthesize_problem

        problem, copies = self.problem, len(alterations)
        s0 = problem.pomdp.initial_state
        goal = goal_states(problem)
        identity = problem.identity()
        nominal = next((i for i, a in enumerate(alterations) if np.array_equal(a, identity)), None)
        best: tuple[tuple[float, float, float], Controller] | None = None
        looked = 0
        w = self._weights_for(copies)
        start = w.copy()
        for turn in range(self.syntheses):
            left = deadline.remaining()
            if left is not None and left < MIN_SECONDS:
                break
            share = (
                self.seconds if left is None else min(self.seconds, left / (self.syntheses - turn))
            )
            world = combined_problem(problem, alterations, w)
            labels = (
                {}
                if nominal is None
                else {"nominal_goal": replicated(goal, s0, copies, only=nominal)}
            )
            found = None
            for prop, constraints in self._properties(alterations, w):
                now = deadline.remaining()  # a fallback gets what the first try left
                if now is not None and now < MIN_SECONDS:
                    break
                try:
                    found = synthesize_problem(
                        world,
                        replicated(goal, s0, copies),
                        memory=self.memory,
                        timeout=max(share if now is None else min(share, now), MIN_SECONDS),
                        prop=prop,
                        labels=labels,
                        constraints=constraints,
                    )
                except (ProblemError, MisdirectError) as error:
                    self.failures.append(f"{prop} {' '.join(constraints)}: {error}".strip())
                    continue
                break
            if found is None:
                break
            looked += 1
            controller = found.controller
            candidate = replace(problem, controller=controller)
            values = np.array([objective_value(candidate, self.objective, a) for a in alterations])
            self.history.append(Synthesized(controller, w.copy(), values, found.synthesis.property))
            score = exact_worst(controller)
            if best is None or better(score, best[0]):
                best = (score, controller)
            moved = _reweighted(w, self.sense * values)
            if np.array_equal(moved, w):  # every member alike: PAYNT would answer the same
                break
            w = moved
        self.weights = w
        self.moved = not np.array_equal(w, start)
        if best is None:
            return None
        return MasterAnswer(
            controller=best[1],
            value=self.sense * best[0][1],
            candidates=looked,
            iterations=looked,
            finished=True,
        )


def _reweighted(w: np.ndarray, loss: np.ndarray) -> np.ndarray:
    """One step of multiplicative weights: ``w_i · exp(STEP · (loss_i − max loss) / spread)``,
    the worst member keeping its weight, none below :data:`WEIGHT_FLOOR` of uniform."""
    spread = float(loss.max() - loss.min())
    if not math.isfinite(spread) or spread <= 0:
        return w
    out = w * np.exp(STEP * (loss - loss.max()) / spread)
    out = np.maximum(out / out.sum(), WEIGHT_FLOOR / w.size)
    return out / out.sum()


__all__ = ["PayntMaster", "combined_problem", "paynt_available", "replicated", "single_changes"]
