"""What a solver hands back, and the interface every solver implements.

A solver only proposes alterations. :func:`misdirect.solve` then re-computes every value
exactly with the evaluator, so no number a user sees depends on a solver's arithmetic.
"""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from enum import StrEnum
from typing import Any, Protocol

import numpy as np

from misdirect.core.model import Alteration, Problem

CERTIFY_TOLERANCE = 1e-9  # "optimal" means: a proven bound within this of the exact value


class Status(StrEnum):
    """How far one budget's answer got. A ``str``, so JSON and comparisons see the name."""

    OPTIMAL = "optimal"  # a proven bound within CERTIFY_TOLERANCE of the exact value
    TIME_LIMIT = "time_limit"  # the best found when time ran out, with the bound proven so far
    GAP_LIMIT = "gap_limit"  # the MILP stopped at the relative gap it was given
    FEASIBLE = "feasible"  # an allowed alteration, not (yet) proven best
    UNVERIFIED = "unverified"  # the solver's claim and the exact chain disagree
    INTERRUPTED = "interrupted"  # stopped on request (Ctrl-C) with the best found so far

    @property
    def cut_short(self) -> bool:
        """An incumbent of a search that did not finish: its bound may still be open."""
        return self in (Status.TIME_LIMIT, Status.GAP_LIMIT, Status.FEASIBLE)


class ProgressCallback(Protocol):
    """What a solver tells whoever watches: ``done`` of ``total`` steps of ``stage``.

    ``detail`` is a short status line (incumbent, bound, gap, rate); ``note`` a hand-over worth
    a line of its own (e.g. "branch-and-bound hit its node limit at budget 4: the MILP takes
    over").
    """

    def __call__(
        self,
        done: int,
        total: int,
        *,
        stage: str | None = None,
        detail: str | None = None,
        note: str | None = None,
    ) -> None: ...


_stop = threading.Event()  # set by request_stop(): every deadline has passed


def request_stop() -> None:
    """Make every :class:`Deadline` expire now (Ctrl-C in the CLI): solvers stop at their next
    check and hand back the best they have, as if their time were up."""
    _stop.set()


def stop_requested() -> bool:
    return _stop.is_set()


def clear_stop() -> None:
    _stop.clear()


class Deadline:
    """A wall-clock limit shared by every stage and budget of one ``solve`` call."""

    def __init__(self, seconds: float | None):
        self.seconds = seconds
        self.end = None if seconds is None else time.perf_counter() + seconds

    def remaining(self) -> float | None:
        """Seconds left (never negative), None without a limit."""
        if _stop.is_set():
            return 0.0
        return None if self.end is None else max(self.end - time.perf_counter(), 0.0)

    def expired(self) -> bool:
        return _stop.is_set() or (self.end is not None and time.perf_counter() >= self.end)

    def share(self, parts: int) -> float | None:
        """An even share of what is left for the next of ``parts`` pieces of work; what a
        piece does not use rolls over to the pieces after it."""
        left = self.remaining()
        return None if left is None else left / max(parts, 1)

    def front_share(self, parts: int) -> float | None:
        """Twice the share of each later piece (``2 / (parts + 1)`` of what is left): for a
        curve's budgets, smallest first, where the next one is the likelier to finish (a
        sensor network's budget 4 certifies in 30 s, its budget 5 needs minutes)."""
        left = self.remaining()
        return None if left is None else 2 * left / (max(parts, 1) + 1)


NO_DEADLINE = Deadline(None)


@dataclass(frozen=True)
class Solution:
    """One solver answer for one budget."""

    budget: float
    alteration: Alteration
    solver_probability: float | None  # the solver's own value for it (None: no incumbent)
    status: Status = Status.OPTIMAL
    upper_bound: float | None = None  # proven bound on the optimum, if the solver has one
    # the method's own counters: ExhaustiveStats, IncrementalStats, BranchAndBoundStats,
    # MilpStats (TypedDicts beside each method), or auto's hand-over record around them
    stats: Mapping[str, Any] = field(default_factory=dict)
    certified_by: str | None = None  # auto: the method whose answer (or bound) this is


class Solver(Protocol):
    name: str
    curve_is_free: bool  # solving for B also yields the optimum at every smaller budget

    def solve(
        self,
        problem: Problem,
        budgets: Sequence[float],
        *,
        progress: ProgressCallback | None = None,
        deadline: Deadline | None = None,
    ) -> list[Solution]:
        """One :class:`Solution` per budget, in the order given, by ``deadline`` (default:
        the solver's own ``time_limit``, counted from the call)."""
        ...


def report(
    progress: ProgressCallback | None,
    done: int,
    total: int,
    *,
    stage: str | None = None,
    detail: str | None = None,
    note: str | None = None,
) -> None:
    """Call ``progress`` if there is one (solvers report through this, never directly)."""
    if progress is not None:
        progress(done, total, stage=stage, detail=detail, note=note)


def refuse_options(method: str, options: dict[str, Any], accepted: Sequence[str] = ()) -> None:
    """A clear error for an option ``method`` does not take (never a TypeError)."""
    from misdirect.errors import ProblemError

    for name, value in options.items():
        if value is not None and name not in accepted:
            flag = "--" + name.replace("_", "-")
            flags = ", ".join("--" + a.replace("_", "-") for a in accepted)
            takes = f"takes only {flags}" if accepted else "takes no options"
            raise ProblemError(
                f"does not apply to --method {method} ({method} {takes}; --solver, "
                "--mip-gap and --formulation are MILP options, for --method milp or auto)",
                field=flag,
            )


def check_time_limit(time_limit: float | None) -> None:
    from misdirect.errors import ProblemError

    if time_limit is not None and not (time_limit > 0 and np.isfinite(time_limit)):
        raise ProblemError(
            f"must be a positive number of seconds, got {time_limit}", field="--time-limit"
        )


def check_threads(threads: int | None) -> None:
    from misdirect.errors import ProblemError

    if threads is not None and threads < 1:
        raise ProblemError(f"must be at least 1, got {threads}", field="--threads")


def thread_count(threads: int | None, default: int) -> int:
    """Threads to use: ``threads``, else ``default``, never more than the machine's cores."""
    return min(threads or default, os.cpu_count() or 1)


def best_per_budget(
    costs: np.ndarray, values: np.ndarray, budgets: Sequence[float], tolerance: float = 1e-12
) -> list[int]:
    """Index of the best candidate within each budget: highest value, then lowest cost.

    Preferring the cheaper of two equally good alterations means the answer never spends more of
    the budget than it needs.
    """
    picks = []
    for budget in budgets:
        within = np.flatnonzero(costs <= budget + 1e-9)
        best = values[within].max()
        tied = within[values[within] >= best - tolerance]
        picks.append(int(tied[np.argmin(costs[tied])]))
    return picks
