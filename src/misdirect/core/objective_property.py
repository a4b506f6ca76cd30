"""PRISM-style reachability properties as the objective, by reduction to a plain problem.

The attacker maximises ``P=? [stay U<=k target]``, where ``target`` is the decoy set, ``stay``
a set of states (all of them for ``F``) and ``k`` an optional step bound:

* ``F target`` is the problem itself: Pr(reach decoy).
* ``stay U target``: a run that enters a state outside ``stay`` and the decoy, before any
  decoy, has failed the property whatever follows. :func:`until` makes those states absorbing
  (and not decoys): such a run ends there, scoring 0, exactly as the property does. Decoy
  states (weighted or not) are untouched, so a run entering one first still scores its
  weight.
* ``... U<=k target``: the decoy must be entered within ``k`` steps. :func:`within_steps`
  folds a step counter into the controller as a monitor (:mod:`misdirect.core.monitor`):
  the robot reads one reading per world step, so the counter counts readings. After ``t``
  readings the world has made ``t`` steps; a run in a decoy state at step ``t <= k`` has
  scored, and the ``(k+1)``-th reading, which would start step ``k+1``, raises the alarm: the
  run ends in the absorbing, non-decoy sink. This is Storm's bounded until on the induced
  chain, step for step (``F<=0``: only an initial decoy state counts).

Both are problem transformations: the observations, costs and budget are unchanged, so every
method, certificate and export of the transformed problem answers the property.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from misdirect.core.memory import check_memory
from misdirect.core.model import Pomdp, Problem
from misdirect.core.monitor import Monitor, fold_monitor
from misdirect.errors import ProblemError

# bytes per entry of the counter's table (int32), three tables alive while it is folded in
_TABLE_BYTES = 4


@dataclass(frozen=True, eq=False)
class ReachProperty:
    """``P=? [stay U<=bound target]`` over a problem's states: ``stay`` None is ``true``
    (``F``), ``bound`` None is unbounded. ``text`` is what reports call it."""

    text: str
    target: np.ndarray  # (|S|,) bool: the decoy states
    stay: np.ndarray | None = None  # (|S|,) bool
    bound: int | None = None


def with_property(problem: Problem, prop: ReachProperty) -> Problem:
    """The problem whose value is the property's probability (the expected weight of the
    first decoy entered, for weighted decoys), under every alteration.

    ``prop.target`` must be the problem's decoy set (a property names the decoy).
    """
    decoy = np.asarray(problem.decoy, dtype=bool)
    target = np.asarray(prop.target, dtype=bool)
    if target.shape != decoy.shape or not np.array_equal(target, decoy):
        raise ProblemError(
            f"the property's target is not the decoy set ({int(target.sum())} states against "
            f"{int(decoy.sum())}); a property names the decoy: give one or the other, or both "
            "naming the same states",
            field="property",
        )
    if problem.reach_property:
        raise ProblemError(
            f"the problem already has the property {problem.reach_property!r}", field="property"
        )
    result = problem
    if prop.stay is not None:
        result = until(result, prop.stay)
    if prop.bound is not None:
        result = within_steps(result, prop.bound)
    return replace(result, reach_property=prop.text)


def until(problem: Problem, stay: np.ndarray) -> Problem:
    """``stay U decoy``: the states outside ``stay`` and the decoy become absorbing non-decoy
    states (a run entering one ends there, scoring 0). ``stay`` is over the problem's states
    (a monitored problem's alarm sink, if not listed, is absorbing already)."""
    pomdp = problem.pomdp
    stay = np.asarray(stay, dtype=bool)
    if stay.size < pomdp.n_states:  # the sinks transformations added: absorbing already
        stay = np.concatenate([stay, np.ones(pomdp.n_states - stay.size, dtype=bool)])
    stop = ~stay & ~np.asarray(problem.decoy, dtype=bool) & ~pomdp.absorbing
    if not stop.any():
        return problem
    coo = pomdp.transitions.tocoo()
    action, source = np.divmod(coo.row, pomdp.n_states)
    world = Pomdp.from_triplets(
        states=pomdp.states,
        actions=pomdp.actions,
        observations=pomdp.observations,
        initial_state=pomdp.initial_state,
        observation_of=pomdp.observation_of,
        action=action.astype(np.int64),
        source=source.astype(np.int64),
        target=coo.col.astype(np.int64),
        probability=coo.data,
        absorbing=pomdp.absorbing | stop,
    )
    return replace(problem, pomdp=world)


def step_counter(problem: Problem, bound: int) -> Monitor:
    """The monitor counting readings: states ``0..bound`` and ``over`` (the alarm), reached
    on the ``(bound+1)``-th reading."""
    if bound < 0:
        raise ProblemError(f"a step bound must be at least 0, got {bound}", field="property")
    pomdp = problem.pomdp
    actions = pomdp.actions[:-1] if problem.alarm_state is not None else pomdp.actions
    n_m, n_o, n_a = bound + 2, pomdp.n_observations, len(actions)
    check_memory(
        float(n_m) * n_o * n_a * _TABLE_BYTES * 3 + float(n_m) * problem.controller.n_moves * 8 * 4,
        f"a step counter of {n_m:,} states over {n_o:,} readings x {n_a:,} actions",
        field="property",
    )
    after = np.minimum(np.arange(n_m, dtype=np.int32) + 1, n_m - 1)
    table = np.broadcast_to(after[:, None, None], (n_m, n_o, n_a)).copy()
    alarm = np.zeros(n_m, dtype=bool)
    alarm[-1] = True
    return Monitor(
        name=f"at most {bound} steps",
        states=(*(f"step {t}" for t in range(bound + 1)), "over"),
        initial=0,
        alarm=alarm,
        next_state=table,
        observations=pomdp.observations,
        actions=actions,
    )


def within_steps(problem: Problem, bound: int) -> Problem:
    """Reach the decoy within ``bound`` world steps: the step counter folded into the
    controller (a monitored problem keeps its alarm sink; the run ends at the first of the
    two alarms). ``step_bound`` records the bound."""
    if problem.step_bound is not None:
        raise ProblemError(
            f"the problem already has a step bound ({problem.step_bound})", field="property"
        )
    folded = fold_monitor(problem, step_counter(problem, bound))
    return replace(folded, step_bound=bound)
