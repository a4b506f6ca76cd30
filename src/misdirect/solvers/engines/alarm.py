"""``max_alarm``: the best attack whose Pr(alarm) is at most δ, decided soundly.

A monitored problem (:func:`misdirect.core.monitor.with_monitor`) ends a caught run in its
absorbing ``alarm`` sink, so under one alteration Pr(alarm first) is a second reachability
value of the same product chain: the decoy states (where a run has scored) and the sink are
both stopping states, the sink worth 1 and the decoys 0. Every method reads it through two
problems that differ only in what the stopping states are worth (:class:`AlarmConstraint`):

* ``decoy_problem``: the decoy sets as given and the sink as a decoy of weight 0. Its value
  is the monitored problem's (the sink is absorbing and worth nothing); its stopping states
  are the decoys *and* the sink, so the attacker's space (the live states, the options that
  change them) is built for both values, not for the decoy's alone (an option the decoy's
  value cannot see may still change Pr(alarm));
* ``alarm_problem``: the same stopping states, the decoys of weight 0 and the sink of weight
  1: its value is Pr(alarm before decoy).

Both have the same alteration space (the same stopping states, the same rows), so a method
that values every alteration of one (the enumerations) values them of the other in the same
order. Whether an alteration is feasible is :meth:`AlarmConstraint.verdict`'s: exact for
δ = 0 (the sink reachable in the altered chain's graph, or not), else the evaluator's value
and its proven error; an alteration neither proven feasible nor proven infeasible is
``undecided`` and never taken as an answer that is called optimal.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Callable, Iterable, Iterator
from contextvars import ContextVar
from dataclasses import replace
from enum import StrEnum
from functools import cached_property

import numpy as np
import scipy.sparse as sp

from misdirect.core import tolerance
from misdirect.core.model import AlterationArray, Problem, reachable_from
from misdirect.core.objective import DecoySet
from misdirect.core.product import ProductChain, build_product
from misdirect.core.reachability import Bounded, reach_probability_bounded
from misdirect.errors import OptionError
from misdirect.solvers.base import best_fitting


class Verdict(StrEnum):
    """Whether an alteration keeps Pr(alarm) within δ, as far as is proven."""

    FEASIBLE = "feasible"
    INFEASIBLE = "infeasible"
    UNDECIDED = "undecided"


def check_max_alarm(problem: Problem, max_alarm: float) -> float:
    """``max_alarm`` as a float in [0, 1], for a monitored problem; else an OptionError
    naming ``max_alarm`` and why."""
    try:
        limit = float(max_alarm)
    except (TypeError, ValueError):
        raise OptionError(
            f"must be a probability in [0, 1], got {max_alarm!r}", parameter="max_alarm"
        ) from None
    if not (math.isfinite(limit) and 0.0 <= limit <= 1.0):
        raise OptionError(
            f"must be a probability in [0, 1], got {max_alarm}", parameter="max_alarm"
        )
    if problem.alarm_state is None:
        raise OptionError(
            "bounds Pr(alarm), and this problem has no alarm: give it a monitor "
            "(misdirect.core.monitor.with_monitor; the command line's monitor and stealth "
            "options)",
            parameter="max_alarm",
        )
    return limit


class AlarmValues:
    """What does not depend on δ, shared by the solves of one trade-off curve
    (:func:`tradeoff_scope`): the two valued problems, each alteration's exact Pr(alarm), and
    what a method computed once for every δ (``memo``: the enumerations' tables)."""

    def __init__(self, problem: Problem):
        self.problem = problem
        self._alarms: dict[bytes, Bounded] = {}
        self.memo: dict[tuple[object, ...], object] = {}

    @cached_property
    def sink(self) -> np.ndarray:
        """(|S|,) bool: the alarm sink."""
        mask = np.zeros(self.problem.pomdp.n_states, dtype=bool)
        assert self.problem.alarm_state is not None
        mask[self.problem.alarm_state] = True
        return mask

    @cached_property
    def decoy_problem(self) -> Problem:
        """The problem's value, with the sink a stopping state of weight 0 (module docstring)."""
        problem = self.problem
        sets = problem.decoy_sets or (DecoySet("decoy", 1.0, np.asarray(problem.decoy, bool)),)
        return replace(
            problem,
            decoy=np.asarray(problem.decoy, bool) | self.sink,
            decoy_sets=(*sets, DecoySet("alarm", 0.0, self.sink)),
        )

    @cached_property
    def alarm_problem(self) -> Problem:
        """Pr(alarm before decoy) as the value: the same stopping states, the sink worth 1."""
        problem = self.problem
        decoy = np.asarray(problem.decoy, bool)
        return replace(
            problem,
            decoy=decoy | self.sink,
            decoy_sets=(DecoySet("decoy", 0.0, decoy), DecoySet("alarm", 1.0, self.sink)),
        )

    def alarm(self, alteration: AlterationArray) -> Bounded:
        """Pr(alarm before decoy) of ``alteration`` and a proven bound on its error."""
        alpha = np.asarray(alteration, dtype=np.int64)
        key = alpha.tobytes()
        if key not in self._alarms:
            self._alarms[key] = alarm_value(self.problem, alpha)
        return self._alarms[key]


class AlarmConstraint:
    """Pr(alarm) ≤ ``limit`` on the monitored ``problem``: its two valued problems, the exact
    alarm value of each alteration (with its proven error) and the verdicts, each once."""

    def __init__(self, problem: Problem, limit: float):
        self.problem = problem
        self.limit = check_max_alarm(problem, limit)
        shared = _shared.get()
        self.values = shared if shared is not None and _same(shared.problem, problem) else None
        if self.values is None:
            self.values = AlarmValues(problem)
        self._verdicts: dict[bytes, Verdict] = {}

    @property
    def decoy_problem(self) -> Problem:
        """:attr:`AlarmValues.decoy_problem`."""
        assert self.values is not None
        return self.values.decoy_problem

    @property
    def alarm_problem(self) -> Problem:
        """:attr:`AlarmValues.alarm_problem`."""
        assert self.values is not None
        return self.values.alarm_problem

    @property
    def memo(self) -> dict[tuple[object, ...], object]:
        """:attr:`AlarmValues.memo`: what the solves of every δ share."""
        assert self.values is not None
        return self.values.memo

    @property
    def trivial(self) -> bool:
        """δ ≥ 1: every alteration is feasible."""
        return self.limit >= 1.0

    def alarm(self, alteration: AlterationArray) -> Bounded:
        """Pr(alarm before decoy) of ``alteration`` and a proven bound on its error."""
        assert self.values is not None
        return self.values.alarm(alteration)

    def verdict(self, alteration: AlterationArray, estimate: float | None = None) -> Verdict:
        """Feasible, infeasible or undecided. ``estimate``: a search's own value of its alarm;
        more than :data:`~misdirect.core.tolerance.ALARM_MARGIN` above δ, it decides
        (the same numbers the search's bounds stand on); otherwise the exact value does."""
        if self.trivial:
            return Verdict.FEASIBLE
        if estimate is not None and estimate > self.limit + tolerance.ALARM_MARGIN:
            return Verdict.INFEASIBLE
        alpha = np.asarray(alteration, dtype=np.int64)
        key = alpha.tobytes()
        if key not in self._verdicts:
            self._verdicts[key] = self._decide(alpha)
        return self._verdicts[key]

    def _decide(self, alpha: np.ndarray) -> Verdict:
        if self.limit == 0.0:  # exactly: can the run reach the sink at all?
            assert self.values is not None
            chain = build_product(self.problem, alpha)
            reached = _reaches_sink(self.problem, chain, self.values.sink)
            return Verdict.INFEASIBLE if reached else Verdict.FEASIBLE
        value, error = self.alarm(alpha)
        if value + error <= self.limit:
            return Verdict.FEASIBLE
        if value - error > self.limit:
            return Verdict.INFEASIBLE
        return Verdict.UNDECIDED


def _same(first: Problem, second: Problem) -> bool:
    """The same problem but perhaps for its budget (``with_budget`` keeps every part)."""
    return first is second or (
        first.pomdp is second.pomdp
        and first.controller is second.controller
        and first.cost is second.cost
        and first.decoy is second.decoy
        and first.decoy_sets == second.decoy_sets
        and first.alarm_state == second.alarm_state
    )


def alarm_value(problem: Problem, alteration: AlterationArray) -> Bounded:
    """Pr(the monitor's alarm before any decoy) under ``alteration``, with a proven error bound
    (``inf`` where none could be proven)."""
    chain = build_product(problem, np.asarray(alteration, dtype=np.int64))
    assert problem.alarm_state is not None
    sink = chain.world_state == problem.alarm_state
    stop = np.asarray(problem.decoy, bool)[chain.world_state] | sink
    return reach_probability_bounded(
        chain.matrix, stop, chain.initial, blocks=chain.node, value=sink.astype(np.float64)
    )


def _reaches_sink(problem: Problem, chain: ProductChain, sink: np.ndarray) -> bool:
    """Whether some run of ``chain`` enters the sink before any decoy state: a path in its
    graph with no decoy state before its end."""
    decoy = np.asarray(problem.decoy, bool)[chain.world_state]
    keep = sp.diags((~decoy).astype(np.float64))
    graph = (keep @ chain.matrix).tocsr()
    graph.eliminate_zeros()
    reached = reachable_from(graph, np.array([chain.initial]))
    return bool((reached & sink[chain.world_state]).any())


def best_feasible(
    costs: np.ndarray,
    values: np.ndarray,
    budget: float,
    scale: tolerance.CostScale,
    verdict_of: Callable[[int], Verdict],
    *,
    excluded: np.ndarray | None = None,
    tie: float = tolerance.TIE,
    terms: Callable[[int], Iterable[float]] | None = None,
) -> tuple[int | None, float]:
    """Index of the best feasible candidate within ``budget`` (None: none is), and the best
    value of a candidate within it whose verdict is ``undecided`` (``-inf``: none), which a
    proven bound must cover. ``excluded``: candidates already known infeasible."""
    masked = np.asarray(costs, dtype=np.float64).copy()
    if excluded is not None:
        masked[excluded] = np.inf
    undecided = -np.inf
    while True:
        index = best_fitting(masked, values, budget, scale, tie, terms)
        if index is None or not math.isfinite(masked[index]):
            return None, undecided
        verdict = verdict_of(index)
        if verdict == Verdict.FEASIBLE:
            return index, undecided
        if verdict == Verdict.UNDECIDED:
            undecided = max(undecided, float(values[index]))
        masked[index] = np.inf


_current: ContextVar[AlarmConstraint | None] = ContextVar("misdirect_alarm", default=None)
_shared: ContextVar[AlarmValues | None] = ContextVar("misdirect_alarm_values", default=None)


@contextlib.contextmanager
def tradeoff_scope(problem: Problem) -> Iterator[AlarmValues]:
    """Within this block, every :class:`AlarmConstraint` of ``problem`` (whatever its δ)
    shares one :class:`AlarmValues`: a trade-off curve pays once for what δ does not change."""
    token = _shared.set(AlarmValues(problem))
    try:
        yield _shared.get()  # type: ignore[misc]
    finally:
        _shared.reset(token)


@contextlib.contextmanager
def constraint_scope(constraint: AlarmConstraint) -> Iterator[AlarmConstraint]:
    """Within this block, :func:`alarm_constraint` of the same problem and δ is ``constraint``
    (its verdicts shared by every stage of one solve)."""
    token = _current.set(constraint)
    try:
        yield constraint
    finally:
        _current.reset(token)


def alarm_constraint(problem: Problem, limit: float) -> AlarmConstraint:
    """The current solve's constraint if it is ``problem``'s at ``limit``; else a new one."""
    current = _current.get()
    if current is not None and current.problem is problem and current.limit == limit:
        return current
    return AlarmConstraint(problem, limit)
