"""How one solve runs: its options as one typed, checked record.

In the spirit of stormpy's ``Environment`` and PAYNT's synthesis task: the caller states the
options once (:class:`SolveOptions`), they are checked once, and each method declares which of
them it takes (``Solver.accepts``), so an option a method would ignore is an error, not a
surprise. Errors name the library parameter (``time_limit``); only the CLI speaks of flags.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass, field, fields

from misdirect.errors import OptionError
from misdirect.solvers.pool import TaskPool

MILP_OPTIONS = ("solver", "formulation", "mip_gap", "verbose")


def implied_method(method: str, given: Iterable[str]) -> tuple[str, list[str]]:
    """The method that runs, and the MILP-only options (:data:`MILP_OPTIONS`) that chose it.

    A MILP-only option means what it says: with ``method="auto"`` it selects the MILP (auto
    would often not run one, and the option would silently do nothing). Any other method is
    kept as it is, and an option it does not take is refused
    (:meth:`SolveOptions.check_taken_by`).

    Parameters
    ----------
    method : str
        The method asked for.
    given : iterable of str
        The names of the options given (:meth:`SolveOptions.given`).

    Returns
    -------
    tuple of (str, list of str)
        The method to run, and the options that made it ``milp`` (empty: ``method`` as asked).

    Examples
    --------
    >>> implied_method("auto", ["time_limit", "formulation"])
    ('milp', ['formulation'])
    >>> implied_method("auto", ["time_limit"])
    ('auto', [])
    """
    names = set(given)
    implying = [name for name in MILP_OPTIONS if name in names]
    if method == "auto" and implying:
        return "milp", implying
    return method, []


def implied_note(implying: Iterable[str]) -> str:
    """The note a result carries when ``implying`` options made ``auto`` the MILP."""
    return f"{', '.join(implying)} implies method milp (a MILP option: auto might not run the MILP)"


def check_time_limit(seconds: float | None) -> None:
    """A time limit is a positive, finite number of seconds (or None: no limit)."""
    if seconds is not None and not (math.isfinite(seconds) and seconds > 0):
        raise OptionError(
            f"must be a positive number of seconds, got {seconds}", parameter="time_limit"
        )


@dataclass(frozen=True)
class SolveOptions:
    """The options of one solve; ``None`` means "the method's default"."""

    time_limit: float | None = None  # seconds for the whole call: every stage and budget
    threads: int | None = None  # worker threads (enumeration, segment search, MILP backend)
    solver: str | None = None  # MILP backend: highs (default), scip, gurobi
    formulation: str | None = None  # MILP formulation: compact (default), paper, paper-pinned
    mip_gap: float | None = None  # MILP: relative gap to stop at (default 1e-9)
    verbose: bool | None = None  # MILP: the backend's log on stdout
    # branch-and-bound: the segment search's subtrees run on this pool (a Dask cluster's,
    # misdirect.distributed.connect); None: in this process
    pool: TaskPool | None = field(default=None, compare=False)
    # the best attack subject to Pr(alarm) <= max_alarm, on a monitored problem (every method
    # takes it: misdirect.solvers.engines.alarm)
    max_alarm: float | None = None

    def __post_init__(self) -> None:
        check_time_limit(self.time_limit)
        if self.threads is not None and self.threads < 1:
            raise OptionError(f"must be at least 1, got {self.threads}", parameter="threads")
        if self.mip_gap is not None and not (0 <= self.mip_gap < float("inf")):
            raise OptionError(
                f"must be a non-negative finite number, got {self.mip_gap}", parameter="mip_gap"
            )

    @property
    def alarm_limit(self) -> float | None:
        """``max_alarm`` where it constrains anything: below 1 (every alteration keeps
        Pr(alarm) <= 1, so δ = 1 is the unconstrained problem); else None."""
        return self.max_alarm if self.max_alarm is not None and self.max_alarm < 1.0 else None

    def given(self) -> list[str]:
        """The options set (not None), in declaration order."""
        return [f.name for f in fields(self) if getattr(self, f.name) is not None]

    def check_taken_by(self, method: str, accepts: Iterable[str]) -> None:
        """An :class:`OptionError` for the first option ``method`` does not take."""
        accepted = list(accepts)
        for name in self.given():
            if name not in accepted:
                takes = f"takes only {', '.join(accepted)}" if accepted else "takes no options"
                raise OptionError(
                    f"does not apply to method {method} ({method} {takes}; solver, mip_gap "
                    "and formulation are MILP options, for method milp: with method auto they "
                    "run the MILP)",
                    parameter=name,
                )
