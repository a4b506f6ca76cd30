"""What a solver hands back, and the interface every solver implements.

A solver only proposes alterations. :func:`misdirect.solve` then re-computes every value
exactly with the evaluator, so no number a user sees depends on a solver's arithmetic.
"""

from __future__ import annotations

import inspect
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from typing import ClassVar, Protocol

import numpy as np

from misdirect.core import tolerance
from misdirect.core.memory import available_cores
from misdirect.core.model import AlterationArray, Problem
from misdirect.solvers.deadline import Deadline, call_deadline
from misdirect.solvers.stats import MethodStats, NoStats
from misdirect.solvers.status import Status, StopReason


class ProgressCallback(Protocol):
    """What a solver tells whoever watches: ``done`` of ``total`` steps of ``stage``.

    ``detail`` is a short status line (incumbent, bound, gap, rate); ``note`` a hand-over worth
    a line of its own (e.g. "branch-and-bound hit its node limit at budget 4: the MILP takes
    over"); ``rate`` steps done per second, where a stage measures one (the enumeration:
    alterations valued a second), for a watcher to estimate the time left. A stage with
    ``total`` 0 is a phase without a count ("product": building the product chain,
    "bounds"). ``rate`` is passed only to a callback that takes it (a ``rate`` parameter or
    ``**kwargs``), so a callback written before it keeps working.
    """

    def __call__(
        self,
        done: int,
        total: int,
        *,
        stage: str | None = None,
        detail: str | None = None,
        note: str | None = None,
        rate: float | None = None,
    ) -> None: ...


@dataclass(frozen=True)
class Solution:
    """One solver answer for one budget."""

    budget: float
    alteration: AlterationArray
    solver_probability: float | None  # the solver's own value for it (None: no incumbent)
    status: Status = Status.OPTIMAL
    upper_bound: float | None = None  # proven bound on the optimum, if the solver has one
    # the method's own counters (misdirect.solvers.stats), or auto's record around them
    stats: MethodStats = field(default_factory=NoStats)
    certified_by: str | None = None  # auto: the method whose answer (or bound) this is
    # what the method says of its answer for the point's notes (why its bound is no proof)
    notes: dict[str, str] = field(default_factory=dict)
    # how the method's work on this budget ended, in its own words (None: it did not say);
    # ``status`` is what certification makes of it
    stop_reason: StopReason | None = None


class Solver(Protocol):
    name: ClassVar[str]
    curve_is_free: ClassVar[bool]  # solving for B also yields the optimum at every smaller budget
    accepts: ClassVar[tuple[str, ...]]  # the SolveOptions fields it takes

    def solve(
        self,
        problem: Problem,
        budgets: Sequence[float],
        *,
        progress: ProgressCallback | None = None,
        deadline: Deadline | None = None,
    ) -> list[Solution]:
        """One :class:`Solution` per budget, in the order given, by ``deadline`` (default:
        no limit). ``status`` says how the method stopped; certification is the front door's."""
        ...


def method_deadline(deadline: Deadline | None, time_limit: float | None) -> Deadline:
    """The deadline a method's ``solve`` runs by: the one it is given (:func:`misdirect.solve`
    always gives one, with the call's time limit and cancel token in it), else, for a method
    called on its own, one from its options' ``time_limit``
    (:func:`~misdirect.solvers.deadline.call_deadline`, where every call's deadline is built)."""
    return deadline if deadline is not None else call_deadline(None, time_limit)


def report(
    progress: ProgressCallback | None,
    done: int,
    total: int,
    *,
    stage: str | None = None,
    detail: str | None = None,
    note: str | None = None,
    rate: float | None = None,
) -> None:
    """Call ``progress`` if there is one (solvers report through this, never directly);
    ``rate`` only where the callback takes it (:class:`ProgressCallback`)."""
    if progress is None:
        return
    if rate is not None and _takes_rate(progress):
        progress(done, total, stage=stage, detail=detail, note=note, rate=rate)
    else:
        progress(done, total, stage=stage, detail=detail, note=note)


def _takes_rate(progress: Callable[..., None]) -> bool:
    """Whether ``progress`` accepts a ``rate`` keyword (callbacks older than it do not)."""
    try:
        parameters = inspect.signature(progress).parameters.values()
    except (TypeError, ValueError):  # a callable without a signature: keep to the old call
        return False
    return any(
        p.kind == p.VAR_KEYWORD or (p.name == "rate" and p.kind != p.POSITIONAL_ONLY)
        for p in parameters
    )


DEFAULT_THREADS = 2  # both cores of the machines misdirect is tuned for


def thread_count(threads: int | None, default: int = DEFAULT_THREADS) -> int:
    """Threads to use: ``threads``, else ``default``, never more than the cores this process
    may run on."""
    return min(threads or default, available_cores())


def best_per_budget(
    costs: np.ndarray,
    values: np.ndarray,
    budgets: Sequence[float],
    scale: tolerance.CostScale,
    tie: float = tolerance.TIE,
    terms: Callable[[int], Iterable[float]] | None = None,
) -> list[int]:
    """Index of the best candidate within each budget (``scale`` says which fit exactly):
    highest value, then lowest cost; values within ``tie`` (relative) of the best are tied.

    Preferring the cheaper of two equally good alterations means the answer never spends more of
    the budget than it needs. Every budget needs a candidate (callers keep the unaltered
    alteration, which fits any): a budget with none is a caller's bug, named as such. A cost
    the float sum cannot place (:meth:`~misdirect.core.tolerance.CostScale.ambiguous`) is
    decided by its candidate's ``terms`` (the costs it adds up), and only for candidates that
    would be picked: without ``terms`` such a candidate is left out (never an answer over its
    budget).
    """
    picks = []
    for budget in budgets:
        best = best_fitting(costs, values, budget, scale, tie, terms)
        if best is None:
            raise ValueError(f"no candidate alteration fits budget {budget:g}")
        picks.append(best)
    return picks


def best_fitting(
    costs: np.ndarray,
    values: np.ndarray,
    budget: float,
    scale: tolerance.CostScale,
    tie: float = tolerance.TIE,
    terms: Callable[[int], Iterable[float]] | None = None,
) -> int | None:
    """:func:`best_per_budget` for one budget; None where no candidate fits it."""
    within = np.flatnonzero(costs <= scale.cap(budget))
    unsure = set(within[scale.ambiguous(costs[within], budget)].tolist())
    while within.size:
        best = values[within].max()
        tied = within[values[within] >= best - tolerance.slack(best, rel=tie)]
        over = []
        for i in unsure.intersection(tied.tolist()):
            unsure.discard(i)
            if terms is None or not scale.fits_exactly(terms(i), budget):
                over.append(i)
        if not over:
            return int(tied[np.argmin(costs[tied])])
        within = np.setdiff1d(within, over, assume_unique=True)
    return None
