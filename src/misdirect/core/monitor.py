"""Monitors: automata that read what the robot receives, and the problem they watch over.

A :class:`Monitor` is a deterministic, complete automaton over the robot's *readings* (the
observation it receives, altered or not) and, optionally, the action it plays on that reading.
Some of its states raise the alarm. :func:`with_monitor` folds it into the problem, exactly:

* the controller becomes the product controller over reachable pairs ``(n, m)`` of a memory
  node and a monitor state: in ``(n, m)`` reading ``o`` it draws ``(a, n')`` from the
  controller's move ``μ(n, o)`` and goes to ``(n', τ(m, o, a))``;
* an entry whose monitor successor ``τ(m, o, a)`` is an alarm state plays, instead of ``a``, a
  new action that moves every non-absorbing world state to a new absorbing, non-decoy sink
  state ``alarm``, with the same probability.

A run of the monitored problem is a run of the original one, step for step, until the monitor
raises the alarm; it then ends in ``alarm``. So its Pr(reach decoy) is Pr(reach a decoy before
any alarm) of the original problem under the same alteration, and its Pr(reach ``alarm``) is
the probability the alarm is raised first. The alteration space is unchanged: the observations,
the cost model and the initial observation are the original ones (the sink emits the initial
observation, which is never altered, and is absorbing: nothing the attacker may choose reads
it). Every method, certificate, export and report of the monitored problem therefore answers
the stealth question, with nothing of its own.

Conventions: the monitor reads the reading of the step's world state; a run that is in a decoy
state has already scored, and one in an absorbing state has ended (no alarm is raised there).
The monitor's initial state reads the initial observation like every other.

:func:`consistency_monitor` builds the robot's own plausibility check: its state is the
support of the robot's belief (the world states it could be in, given its model, its
readings and its actions), and the alarm is raised on a reading that no state of the support
emits. It is built on demand, over the supports reachable from ``{s0}``, within a cap.
"""

from __future__ import annotations

import itertools
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from misdirect.core.memory import check_memory
from misdirect.core.model import Controller, Pomdp, Problem
from misdirect.core.objective import DecoySet
from misdirect.errors import ProblemError, ProblemsError

WILDCARD = "*"
ALARM = "alarm"  # the sink state's name (made unique against the model's states)
ALARM_ACTION = "alarm"  # the action into it (made unique against the model's actions)
DEFAULT_MAX_STATES = 10_000  # the consistency monitor's cap on belief supports

# bytes per monitor table entry (int32) kept while a monitor is built and folded in
_TABLE_BYTES = 4


@dataclass(frozen=True)
class Transition:
    """One transition of a user's monitor: in ``state``, on a reading among ``reading`` (a
    name, a list of names, or ``"*"``: any other reading) and an action among ``action``
    (likewise; ``"*"`` by default), go to ``next``."""

    state: str
    reading: str | Sequence[str]
    next: str
    action: str | Sequence[str] = WILDCARD


@dataclass(frozen=True, eq=False, repr=False)
class Monitor:
    """A deterministic, complete automaton over the robot's readings and actions.

    ``next_state[m, o, a]`` is the state after reading ``o`` and playing ``a`` in state ``m``;
    ``alarm[m]`` marks the states that raise the alarm (entering one ends the run; their own
    rows are never read). Build one with :meth:`from_transitions` (a user's automaton, checked)
    or :func:`consistency_monitor`; fold it into a problem with :func:`with_monitor`.
    """

    name: str
    states: tuple[str, ...]
    initial: int
    alarm: np.ndarray  # (M,) bool
    next_state: np.ndarray  # (M, |Ω|, |A|) int32
    observations: tuple[str, ...]
    actions: tuple[str, ...]

    def __repr__(self) -> str:
        return (
            f"Monitor({self.name!r}: {self.n_states} states, "
            f"{int(self.alarm.sum())} raising the alarm)"
        )

    @property
    def n_states(self) -> int:
        return len(self.states)

    @classmethod
    def from_transitions(
        cls,
        *,
        states: Sequence[str],
        initial: str,
        alarm: Iterable[str],
        transitions: Sequence[Transition],
        observations: Sequence[str],
        actions: Sequence[str],
        name: str = "monitor",
        field: str = "monitor",
    ) -> Monitor:
        """A user's automaton over the given readings and actions, checked.

        A transition naming its reading beats one whose reading is ``"*"``; among those,
        one naming its action beats one whose action is ``"*"``. Where the best matches of
        a (state, reading, action) disagree on the next state, the monitor is
        nondeterministic; where none matches a state that is not an alarm state, it is
        incomplete. Every problem (unknown names, nondeterminism, incompleteness) is reported
        at once, each naming ``field`` and the place in it.
        """
        problems: list[ProblemError] = []

        def problem(reason: str, where: str) -> None:
            problems.append(ProblemError(reason, field=where))

        state_names = list(states)
        index = {s: i for i, s in enumerate(state_names)}
        if not state_names:
            problem("a monitor needs at least one state", _at(field, "states"))
        for i, s in enumerate(state_names):
            if state_names.index(s) != i:
                problem(f"state {s!r} is listed twice", _at(field, "states"))
        obs_index = {o: i for i, o in enumerate(observations)}
        act_index = {a: i for i, a in enumerate(actions)}
        n_m, n_o, n_a = len(state_names), len(obs_index), len(act_index)
        alarm_mask = np.zeros(n_m, dtype=bool)
        for s in alarm:
            if s in index:
                alarm_mask[index[s]] = True
            else:
                known = _preview(state_names)
                problem(f"unknown alarm state {s!r} (states: {known})", _at(field, "alarm"))
        start = index.get(initial, -1)
        if start < 0:
            problem(
                f"unknown initial state {initial!r} (states: {_preview(state_names)})",
                _at(field, "initial"),
            )
        elif alarm_mask[start]:
            problem(
                f"the initial state {initial!r} raises the alarm: every run would be caught "
                "before it starts",
                _at(field, "initial"),
            )
        check_memory(
            float(n_m) * n_o * n_a * _TABLE_BYTES * 3,
            f"a monitor table of {n_m:,} states x {n_o:,} readings x {n_a:,} actions",
            field=_at(field, "states"),
        )
        # each (state, reading, action): the best priority seen and the next state it gives
        best = np.full((n_m, n_o, n_a), -1, dtype=np.int8)
        target = np.full((n_m, n_o, n_a), -1, dtype=np.int32)
        source = np.full((n_m, n_o, n_a), -1, dtype=np.int32)  # the transition that set it
        doubtful = np.zeros(n_m, dtype=bool)  # a state with a transition left unresolved
        for i, t in enumerate(transitions):
            where = _at(field, f"transitions[{i}]")
            found = len(problems)
            m = index.get(t.state, -1)
            if m < 0:
                problem(f"unknown state {t.state!r} (states: {_preview(state_names)})", where)
            to = index.get(t.next, -1)
            if to < 0:
                problem(f"unknown next state {t.next!r} (states: {_preview(state_names)})", where)
            readings = _guard(t.reading, obs_index, "reading", observations, where, problems)
            acts = _guard(t.action, act_index, "action", actions, where, problems)
            if len(problems) > found or readings is None or acts is None:
                if m >= 0:
                    doubtful[m] = True
                continue
            level = 2 * (_listed(t.reading) != [WILDCARD]) + (_listed(t.action) != [WILDCARD])
            cells = np.ix_([m], readings, acts)
            here_best, here_target = best[cells], target[cells]
            clash = (here_best == level) & (here_target != to)
            if clash.any():
                _, o, a = (int(k[0]) for k in np.nonzero(clash))
                other = int(source[cells][0, o, a])
                problem(
                    f"nondeterministic: in state {t.state!r} reading "
                    f"{observations[readings[o]]!r} with action {actions[acts[a]]!r} it goes "
                    f"to {state_names[to]!r} and, by transitions[{other}], to "
                    f"{state_names[int(here_target[0, o, a])]!r}",
                    where,
                )
                doubtful[m] = True
                continue
            better = here_best < level
            best[cells] = np.where(better, level, here_best)
            target[cells] = np.where(better, to, here_target)
            source[cells] = np.where(better, i, source[cells])
        # incompleteness, where it is sure: not in states with a transition in doubt
        checked = ~alarm_mask & ~doubtful
        if n_m:
            missing = np.argwhere((target < 0) & checked[:, None, None])
            if missing.size:
                m, o, a = (int(k) for k in missing[0])
                more = f" (and {len(missing) - 1:,} more)" if len(missing) > 1 else ""
                problem(
                    f"incomplete: no transition of state {state_names[m]!r} reads "
                    f"{observations[o]!r} with action {actions[a]!r}{more}; add one, or a "
                    'catch-all with reading "*"',
                    _at(field, "transitions"),
                )
        if problems:
            raise ProblemsError.of(problems)
        target[alarm_mask] = np.arange(n_m, dtype=np.int32)[alarm_mask, None, None]
        return cls(
            name=name,
            states=tuple(state_names),
            initial=start,
            alarm=alarm_mask,
            next_state=target,
            observations=tuple(observations),
            actions=tuple(actions),
        )


def _guard(
    value: str | Sequence[str],
    index: dict[str, int],
    kind: str,
    names: Sequence[str],
    where: str,
    problems: list[ProblemError],
) -> list[int] | None:
    """A guard's readings (or actions) as indices: ``"*"`` all of them."""
    listed = [value] if isinstance(value, str) else list(value)
    if WILDCARD in listed:
        if len(listed) > 1:
            problems.append(ProblemError(f'"*" is any {kind}: give it alone', field=where))
            return None
        return list(range(len(names)))
    if not listed:
        problems.append(ProblemError(f"an empty {kind} list", field=where))
        return None
    unknown = [v for v in listed if v not in index]
    for v in unknown:
        known = "observations" if kind == "reading" else "actions"
        problems.append(
            ProblemError(f"unknown {kind} {v!r} ({known}: {_preview(names)})", field=where)
        )
    return None if unknown else sorted({index[v] for v in listed})


def _listed(value: str | Sequence[str]) -> list[str]:
    return [value] if isinstance(value, str) else list(value)


def _at(field: str, inside: str) -> str:
    """``inside`` within ``field`` (``monitor.transitions[0]``; ``transitions[0]`` at the top of
    a monitor's own file)."""
    return f"{field}.{inside}" if field else inside


def _preview(names: Iterable[str], limit: int = 8) -> str:
    names = list(names)
    shown = ", ".join(names[:limit])
    return shown + (f", … ({len(names)} in all)" if len(names) > limit else "")


# -- the consistency monitor --------------------------------------------------------------------


@dataclass(frozen=True, eq=False, repr=False)
class ConsistencyMonitor(Monitor):
    """The robot's plausibility check; ``supports[m]`` is the set of world states state ``m``
    predicts (the robot could be in, before its next reading), as sorted indices.
    ``controller``: the controller whose runs it was built along (its table is exact on every
    (support, reading, action) those runs reach, and raises the alarm elsewhere), or None
    (built over every action played on a reading: exact for any node)."""

    supports: tuple[tuple[int, ...], ...] = ()
    controller: Controller | None = None


def consistency_monitor(
    problem: Problem,
    *,
    max_states: int = DEFAULT_MAX_STATES,
    field: str = "monitor",
    along_controller: bool = True,
) -> ConsistencyMonitor:
    """The robot's own plausibility check: an alarm when a reading is impossible.

    Its state is the belief support predicted for the next step: the world states the robot
    could be in given its model (the POMDP as the problem states it, its initial state known),
    the readings it received and the actions it played. In state ``P`` reading ``o`` and
    playing ``a``: the support becomes ``Q = {s ∈ P : O(s) = o}``, and the next state is
    ``post(Q, a) = {s' : P(s, a, s') > 0 for some s ∈ Q}``; where ``Q`` is empty, no state the
    robot could be in emits ``o``, and the alarm is raised.

    Built over the supports reachable from ``{s0}`` along the controller's runs under every
    reading: from each reachable pair of a memory node and a support, on every reading, the
    actions that node plays (``along_controller``, the default), which are all the product
    with the controller (:func:`with_monitor`) ever reads, so folding it in gives the same
    product as the full monitor; the entries no run reaches raise the alarm, and the monitor
    folds into this controller only. Without ``along_controller``: under every action the
    controller plays on a reading in any node (exact for any node, and far larger: on
    ``sensor_grid(8, 6)`` 4,555 supports against 178, docs/benchmarks.md). More than
    ``max_states`` supports raise a :class:`~misdirect.errors.ProblemError` naming the cap.
    """
    pomdp, controller = problem.pomdp, problem.controller
    n_s, n_o, n_a = pomdp.n_states, pomdp.n_observations, pomdp.n_actions
    if max_states < 1:
        raise ProblemError(f"must be at least 1, got {max_states}", field=_at(field, "max_states"))
    if along_controller:
        return _consistency_along(problem, max_states, field)
    # the actions the controller may play on each reading (in some node)
    played = np.zeros((n_o, n_a), dtype=bool)
    owner, action, _, _ = controller.move_entries(controller.move.T.ravel())
    played[owner // controller.n_nodes, action] = True
    transitions = pomdp.transitions.tocsr()
    indptr, indices = transitions.indptr.astype(np.int64), transitions.indices.astype(np.int64)
    supports: list[tuple[int, ...]] = [(pomdp.initial_state,)]
    known = {supports[0]: 0}
    rows: list[np.ndarray] = []  # per level: (supports, |Ω|, |A|) next support (-1: alarm)
    first = 0
    while first < len(supports):
        # one breadth-first level at once: every (support, reading, action) of the level,
        # new supports numbered in the order (support, reading, action), as one at a time would
        last = len(supports)
        level = supports[first:last]
        owner, state = _members(level)
        reading = pomdp.observation_of[state].astype(np.int64)
        which, action = np.nonzero(played[reading])  # (state of the level, action) pairs
        group = (owner[which] * n_o + reading[which]) * n_a + action
        keys, targets = _successors(indptr, indices, group, action * n_s + state[which], n_s)
        groups = np.unique(group)  # every (support, reading, action), successors or none
        cut = np.searchsorted(keys, groups, side="left")
        end = np.searchsorted(keys, groups, side="right")
        table = np.full((len(level), n_o, n_a), -1, dtype=np.int64)
        present = np.unique(owner * n_o + reading)  # a support's own readings
        p_owner, p_reading = np.divmod(present, n_o)
        # actions the controller never plays on a reading: any state will do (never read)
        unplayed = ~played[p_reading]
        table[p_owner[:, None], p_reading[:, None], np.arange(n_a)] = np.where(
            unplayed, (p_owner + first)[:, None], -1
        )
        listed = targets.tolist()
        found = np.empty(groups.size, dtype=np.int64)
        for i, (lo, hi) in enumerate(zip(cut.tolist(), end.tolist(), strict=True)):
            found[i] = _number(tuple(listed[lo:hi]), supports, known, max_states, n_s, field)
        g_rest, g_action = np.divmod(groups, n_a)
        g_owner, g_reading = np.divmod(g_rest, n_o)
        table[g_owner, g_reading, g_action] = found
        rows.append(table)
        first = last
    n_m = len(supports)
    _check_table(n_m, n_o, n_a, field)
    table = np.concatenate(rows).astype(np.int32)
    table[table < 0] = n_m  # the alarm state
    table = np.concatenate([table, np.full((1, n_o, n_a), n_m, dtype=np.int32)])
    return _monitor(table, supports, problem, None)


def _consistency_along(problem: Problem, max_states: int, field: str) -> ConsistencyMonitor:
    """:func:`consistency_monitor` along the controller's runs: breadth-first over pairs
    (memory node, support) from ``(n0, {s0})``, a level at a time with array operations; each
    (support, reading, action) a pair plays is followed once."""
    pomdp, controller = problem.pomdp, problem.controller
    n_s, n_o, n_a = pomdp.n_states, pomdp.n_observations, pomdp.n_actions
    transitions = pomdp.transitions.tocsr()
    indptr, indices = transitions.indptr.astype(np.int64), transitions.indices.astype(np.int64)
    observation_of = pomdp.observation_of.astype(np.int64)
    supports: list[tuple[int, ...]] = [(pomdp.initial_state,)]
    known = {supports[0]: 0}
    followed: dict[int, int] = {}  # (support * |Ω| + reading) * |A| + action -> next (-1: alarm)
    pairs = {controller.initial_node * max_states: 0}  # node * max_states + support
    level_node = np.array([controller.initial_node], dtype=np.int64)
    level_support = np.array([0], dtype=np.int64)
    readings = np.arange(n_o, dtype=np.int64)
    while level_node.size:
        owner, action, next_node, _ = controller.entries(
            np.repeat(level_node, n_o), np.tile(readings, level_node.size)
        )
        support = level_support[owner // n_o]
        reading = owner % n_o
        key = (support * n_o + reading) * n_a + action
        new = np.unique(key)
        new = new[[k not in followed for k in new.tolist()]] if followed else new
        model = (indptr, indices, observation_of, n_o, n_a)
        _follow(new, supports, known, followed, max_states, field, n_s, model)
        after = np.fromiter((followed[k] for k in key.tolist()), dtype=np.int64, count=key.size)
        live = after >= 0
        next_pairs = np.unique(next_node[live] * max_states + after[live])
        fresh = [k for k in next_pairs.tolist() if k not in pairs]
        for k in fresh:
            pairs[k] = len(pairs)
        fresh_array = np.array(fresh, dtype=np.int64)
        level_node, level_support = np.divmod(fresh_array, max_states)
    n_m = len(supports)
    _check_table(n_m, n_o, n_a, field)
    table = np.full((n_m + 1, n_o, n_a), n_m, dtype=np.int32)  # unreached: the alarm
    if followed:
        keys = np.fromiter(followed.keys(), dtype=np.int64, count=len(followed))
        nexts = np.fromiter(followed.values(), dtype=np.int64, count=len(followed))
        rest, a = np.divmod(keys, n_a)
        m, o = np.divmod(rest, n_o)
        table[m, o, a] = np.where(nexts < 0, n_m, nexts)
    return _monitor(table, supports, problem, controller)


def _check_table(n_m: int, n_o: int, n_a: int, field: str) -> None:
    """A clear error before a monitor's table (and the product's copies of it) outgrows
    the memory."""
    check_memory(
        float(n_m + 1) * n_o * n_a * _TABLE_BYTES * 3,
        f"the consistency monitor's table ({n_m:,} supports x {n_o:,} readings x {n_a:,} actions)",
        field=_at(field, "max_states"),
    )


def _monitor(
    table: np.ndarray,
    supports: list[tuple[int, ...]],
    problem: Problem,
    controller: Controller | None,
) -> ConsistencyMonitor:
    """The consistency monitor of ``table`` (supports, then the alarm state, last)."""
    n_m = len(supports)
    alarm = np.zeros(n_m + 1, dtype=bool)
    alarm[n_m] = True
    return ConsistencyMonitor(
        name="consistency",
        states=(*(f"b{k}" for k in range(n_m)), ALARM),
        initial=0,
        alarm=alarm,
        next_state=table,
        observations=problem.pomdp.observations,
        actions=problem.pomdp.actions,
        supports=tuple(supports),
        controller=controller,
    )


def _members(supports: list[tuple[int, ...]]) -> tuple[np.ndarray, np.ndarray]:
    """Every state of every support in ``supports``, flat, with the index of its support."""
    lengths = np.fromiter((len(p) for p in supports), dtype=np.int64, count=len(supports))
    owner = np.repeat(np.arange(len(supports), dtype=np.int64), lengths)
    state = np.fromiter(
        itertools.chain.from_iterable(supports), dtype=np.int64, count=int(lengths.sum())
    )
    return owner, state


def _successors(
    indptr: np.ndarray, indices: np.ndarray, group: np.ndarray, row_of: np.ndarray, n_s: int
) -> tuple[np.ndarray, np.ndarray]:
    """The distinct (group, successor) pairs of the transition rows ``row_of`` (one per
    entry of ``group``), sorted by group: their groups and their successor states."""
    starts, counts = indptr[row_of], indptr[row_of + 1] - indptr[row_of]
    at = np.repeat(starts - (np.cumsum(counts) - counts), counts) + np.arange(counts.sum())
    pairs = np.unique(np.repeat(group, counts) * n_s + indices[at])
    return np.divmod(pairs, n_s)


def _number(
    after: tuple[int, ...],
    supports: list[tuple[int, ...]],
    known: dict[tuple[int, ...], int],
    max_states: int,
    n_s: int,
    field: str,
) -> int:
    """The number of support ``after``, a new one appended (past ``max_states``: the cap's
    error)."""
    k = known.get(after)
    if k is None:
        if len(supports) >= max_states:
            raise _cap_error(max_states, n_s, field)
        k = known[after] = len(supports)
        supports.append(after)
    return k


def _follow(
    keys: np.ndarray,
    supports: list[tuple[int, ...]],
    known: dict[tuple[int, ...], int],
    followed: dict[int, int],
    max_states: int,
    field: str,
    n_s: int,
    model: tuple[np.ndarray, np.ndarray, np.ndarray, int, int],
) -> None:
    """Follow each (support, reading, action) of ``keys`` once: its next support's number
    (new supports appended, in the order of ``keys``) or -1 (alarm), into ``followed``."""
    indptr, indices, observation_of, n_o, n_a = model
    if not keys.size:
        return
    rest, action = np.divmod(keys, n_a)
    support, reading = np.divmod(rest, n_o)
    group, state = _members([supports[k] for k in support.tolist()])
    keep = observation_of[state] == reading[group]  # Q = {s in P : O(s) = o}
    group, state = group[keep], state[keep]
    emitted = np.bincount(group, minlength=keys.size) > 0  # Q is not empty
    owners, targets = _successors(indptr, indices, group, action[group] * n_s + state, n_s)
    cut = np.searchsorted(owners, np.arange(keys.size), side="left")
    end = np.searchsorted(owners, np.arange(keys.size), side="right")
    listed = targets.tolist()
    spans = zip(keys.tolist(), emitted.tolist(), cut.tolist(), end.tolist(), strict=True)
    for key, some, lo, hi in spans:
        if not some:  # no state of the support emits the reading: the alarm
            followed[key] = -1
            continue
        # empty where no state moves: every reading then alarms
        followed[key] = _number(tuple(listed[lo:hi]), supports, known, max_states, n_s, field)


def _cap_error(max_states: int, n_s: int, field: str) -> ProblemError:
    return ProblemError(
        f"the consistency monitor needs more than {max_states:,} belief "
        f"supports (the cap) on {n_s:,} states; raise the cap "
        "(monitor: {consistency: {max_states: N}} in the problem file, "
        "consistency_monitor(problem, max_states=N)) or give a smaller "
        "monitor",
        field=_at(field, "max_states"),
    )


# -- the monitored problem ----------------------------------------------------------------------


def _fresh(name: str, taken: Iterable[str]) -> str:
    taken = set(taken)
    candidate, k = name, 1
    while candidate in taken:
        candidate, k = f"{name}_{k}", k + 1
    return candidate


def with_monitor(problem: Problem, monitor: Monitor) -> Problem:
    """The problem whose Pr(reach decoy) is Pr(reach a decoy before the monitor's alarm).

    The controller becomes the product of the controller and the monitor over reachable
    pairs; the world gets an absorbing, non-decoy state ``alarm`` and an action into it, which
    the product controller plays where the monitor raises the alarm (the module's docstring
    says why the reduction is exact). The observations, costs and budget are unchanged, so an
    alteration of the problem is an alteration of the monitored one, at the same cost.

    Parameters
    ----------
    problem : Problem
        The problem to watch over (one without a monitor).
    monitor : Monitor
        An automaton over the problem's observations and actions (:meth:`Monitor.
        from_transitions`, :func:`consistency_monitor`).

    Returns
    -------
    Problem
        The monitored problem; ``alarm_state`` is the sink's index, ``monitor`` the
        monitor's name.

    Examples
    --------
    >>> from misdirect.scenarios import paper_grid
    >>> problem = paper_grid(5)
    >>> watched = with_monitor(problem, consistency_monitor(problem))
    >>> watched.pomdp.states[watched.alarm_state]
    'alarm'
    """
    if problem.monitor:
        raise ProblemError(
            f"the problem is already watched by the monitor {problem.monitor!r}; give one "
            "monitor (an automaton can read what both would)",
            field="monitor",
        )
    folded = fold_monitor(problem, monitor)
    return replace(folded, monitor=monitor.name, unwatched=problem)


def fold_monitor(problem: Problem, monitor: Monitor) -> Problem:
    """``problem`` with ``monitor`` folded into its controller, as :func:`with_monitor` does,
    without naming it. A problem that already has an alarm sink (a step bound,
    :func:`misdirect.core.objective_property.within_steps`, or a monitor) keeps it: the new
    monitor's alarm ends the run in the same sink, so the run ends at the first alarm of
    either. The monitor reads the problem's own actions (not the alarm action, on which it
    stays where it is: the run has ended)."""
    pomdp, controller = problem.pomdp, problem.controller
    watched = problem.alarm_state is not None
    actions = pomdp.actions[:-1] if watched else pomdp.actions
    if monitor.observations != pomdp.observations or monitor.actions not in (
        actions,
        pomdp.actions,
    ):
        raise ProblemError(
            "the monitor reads other observations or actions than the problem's; build it "
            "over the problem's (Monitor.from_transitions(observations=..., actions=...))",
            field="monitor",
        )
    built_for = getattr(monitor, "controller", None)
    if built_for is not None and built_for is not controller:
        raise ProblemError(
            "the consistency monitor was built along another controller's runs; build it for "
            "this problem (consistency_monitor(problem))",
            field="monitor",
        )
    if watched:
        sink = problem.alarm_state
        alarm_action = pomdp.n_actions - 1  # _with_sink puts it last
        table = monitor.next_state
        if monitor.actions == actions:  # on the alarm action: stay (never read again)
            stay = np.broadcast_to(
                np.arange(monitor.n_states, dtype=np.int32)[:, None, None],
                (monitor.n_states, pomdp.n_observations, 1),
            )
            table = np.concatenate([table, stay], axis=2)
        monitor = replace(monitor, next_state=table, actions=pomdp.actions)
    else:
        sink = pomdp.n_states
        alarm_action = pomdp.n_actions
    nodes, entries = _product_controller(controller, monitor, alarm_action)
    n_o = pomdp.n_observations
    nodes, entries = _merge_bisimilar(nodes, entries, n_o, alarm_action)
    cell, action, next_node, probability = entries
    product = Controller.from_entries(
        nodes=tuple(f"({controller.nodes[n]}, {monitor.states[m]})" for n, m in nodes),
        initial_node=0,
        n_observations=n_o,
        node=cell // n_o,
        observation=cell % n_o,
        action=action,
        next_node=next_node,
        probability=probability,
    )
    if watched:
        return replace(problem, controller=product)
    world = _with_sink(pomdp)
    decoy = np.append(np.asarray(problem.decoy, dtype=bool), False)
    sets = tuple(
        DecoySet(d.name, d.weight, np.append(np.asarray(d.states, dtype=bool), False))
        for d in problem.decoy_sets
    )
    return replace(
        problem,
        pomdp=world,
        controller=product,
        decoy=decoy,
        decoy_sets=sets,
        alarm_state=sink,
    )


def _product_controller(
    controller: Controller, monitor: Monitor, alarm_action: int
) -> tuple[list[tuple[int, int]], tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
    """The product's nodes ``(n, m)`` reachable from ``(n0, m0)`` under any reading, and its
    entries ``(cell = node * |Ω| + o, action, next node, probability)``."""
    n_o = len(monitor.observations)
    n_m = monitor.n_states
    start = (controller.initial_node, monitor.initial)
    index = {start[0] * n_m + start[1]: 0}
    nodes = [start]
    cells, actions, nexts, probabilities = [], [], [], []
    frontier = [0]
    readings = np.arange(n_o)
    while frontier:
        batch = np.array(frontier, dtype=np.int64)
        frontier = []
        node_n = np.array([nodes[k][0] for k in batch.tolist()], dtype=np.int64)
        node_m = np.array([nodes[k][1] for k in batch.tolist()], dtype=np.int64)
        # every (product node, reading) of the batch, and its controller move's entries
        pn, po = np.repeat(node_n, n_o), np.tile(readings, batch.size)
        pm, pk = np.repeat(node_m, n_o), np.repeat(batch, n_o)
        owner, action, next_n, probability = controller.entries(pn, po)
        next_m = monitor.next_state[pm[owner], po[owner], action].astype(np.int64)
        caught = monitor.alarm[next_m]
        # an alarm entry plays the alarm action and stays (the run ends in the sink)
        keys = next_n * n_m + next_m
        stay = pk[owner]
        targets = np.empty(owner.size, dtype=np.int64)
        for i in np.flatnonzero(~caught).tolist():
            key = int(keys[i])
            k = index.get(key)
            if k is None:
                k = index[key] = len(nodes)
                nodes.append((int(next_n[i]), int(next_m[i])))
                frontier.append(k)
            targets[i] = k
        targets[caught] = stay[caught]
        cells.append(pk[owner] * n_o + po[owner])
        actions.append(np.where(caught, alarm_action, action))
        nexts.append(targets)
        probabilities.append(probability)
    return nodes, (
        np.concatenate(cells),
        np.concatenate(actions),
        np.concatenate(nexts),
        np.concatenate(probabilities),
    )


def _merge_bisimilar(
    nodes: list[tuple[int, int]],
    entries: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray],
    n_o: int,
    alarm_action: int,
) -> tuple[list[tuple[int, int]], tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
    """The product controller with bisimilar nodes merged (Moore's partition refinement).

    Two nodes are bisimilar when, for every reading, they play each action with the same
    probability into successors that are bisimilar again; an alarm entry's successor does not
    matter (the run ends). Such nodes give every run the same distribution of actions, so the
    chain's value under every alteration is the same with one node in place of the other,
    while the product chain every solver factorises shrinks: on the paper's grid with the
    consistency monitor, many (node, belief support) pairs differ only in supports that no
    reading tells apart. Each class keeps its first node (the initial node stays node 0)."""
    cell, action, next_node, probability = entries
    n_nodes = len(nodes)
    if n_nodes < 2:
        return nodes, entries
    owner = cell // n_o
    reading = cell % n_o
    caught = action == alarm_action
    classes = np.zeros(n_nodes, dtype=np.int64)
    n_classes = 1
    while True:
        # an entry's part of its node's signature: (reading, action, successor's class), the
        # entries of one node sharing it summed; an alarm entry's successor is none (-1)
        successor = np.where(caught, -1, classes[next_node])
        code = (reading * (alarm_action + 1) + action) * (n_classes + 1) + successor + 1
        pair, inverse = np.unique(owner * (code.max() + 1) + code, return_inverse=True)
        mass = np.bincount(inverse.reshape(-1), weights=probability, minlength=pair.size)
        pair_owner, pair_code = np.divmod(pair, code.max() + 1)
        counts = np.bincount(pair_owner, minlength=n_nodes)
        slot = np.arange(pair.size) - np.repeat(np.cumsum(counts) - counts, counts)
        rows = np.full((n_nodes, 1 + 2 * int(counts.max())), -1.0)
        rows[:, 0] = classes
        rows[pair_owner, 1 + 2 * slot] = pair_code
        rows[pair_owner, 2 + 2 * slot] = mass
        _, renumbered = np.unique(rows, axis=0, return_inverse=True)
        classes = renumbered.reshape(-1).astype(np.int64)
        count = int(classes.max()) + 1
        if count == n_classes:
            break
        n_classes = count
    # number the classes by their first node, so that the initial node's class is 0
    first_node = np.full(n_classes, n_nodes, dtype=np.int64)
    np.minimum.at(first_node, classes, np.arange(n_nodes))
    rank = np.empty(n_classes, dtype=np.int64)
    rank[np.argsort(first_node)] = np.arange(n_classes)
    classes = rank[classes]
    if n_classes == n_nodes:
        return nodes, entries
    keep_nodes = np.sort(first_node)
    kept = np.isin(owner, keep_nodes)
    cell, action, next_node, probability = (a[kept] for a in (cell, action, next_node, probability))
    cell = classes[cell // n_o] * n_o + cell % n_o
    next_node = classes[next_node]
    return [nodes[k] for k in keep_nodes.tolist()], (cell, action, next_node, probability)


def _with_sink(pomdp: Pomdp) -> Pomdp:
    """The world with an absorbing state ``alarm`` (emitting the initial observation, which
    is never altered) and an action that moves every non-absorbing state into it."""
    n_s, n_a = pomdp.n_states, pomdp.n_actions
    coo = pomdp.transitions.tocoo()
    live = np.flatnonzero(~pomdp.absorbing)
    action = np.concatenate([coo.row // n_s, np.full(live.size, n_a)])
    source = np.concatenate([coo.row % n_s, live])
    target = np.concatenate([coo.col, np.full(live.size, n_s)])
    probability = np.concatenate([coo.data, np.ones(live.size)])
    return Pomdp.from_triplets(
        states=(*pomdp.states, _fresh(ALARM, pomdp.states)),
        actions=(*pomdp.actions, _fresh(ALARM_ACTION, pomdp.actions)),
        observations=pomdp.observations,
        initial_state=pomdp.initial_state,
        observation_of=np.append(pomdp.observation_of, pomdp.initial_observation),
        action=action.astype(np.int64),
        source=source.astype(np.int64),
        target=target.astype(np.int64),
        probability=probability,
        absorbing=np.append(pomdp.absorbing, True),
    )


def monitor_from_spec(problem: Problem, spec: Any, *, field: str = "monitor") -> Monitor:
    """A monitor from its description as plain data (a problem file's ``monitor:``, already
    validated): ``{"consistency": true | {"max_states": N}}`` or ``{"states", "initial",
    "alarm", "transitions": [{"state", "reading", "action", "next"}]}``."""
    consistency = spec.get("consistency")
    if consistency is not None and consistency is not False:
        cap = DEFAULT_MAX_STATES
        if isinstance(consistency, dict):
            cap = int(consistency.get("max_states", cap))
        return consistency_monitor(problem, max_states=cap, field=_at(field, "consistency"))
    return Monitor.from_transitions(
        states=spec.get("states") or [],
        initial=spec.get("initial", ""),
        alarm=spec.get("alarm") or [],
        transitions=[
            Transition(
                state=t["state"],
                reading=t["reading"],
                next=t["next"],
                action=t.get("action", WILDCARD) if t.get("action") is not None else WILDCARD,
            )
            for t in spec.get("transitions") or []
        ],
        observations=problem.pomdp.observations,
        actions=problem.pomdp.actions,
        name=str(spec.get("name") or "automaton"),
        field=field,
    )
