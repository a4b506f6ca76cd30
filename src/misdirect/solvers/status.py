"""How far one budget's answer got: the status every method reports and every result shows.

Backends' own codes (HiGHS, SCIP, Gurobi) are normalised to these at the solver boundary, and
only :mod:`misdirect.solvers.certification` turns a method's stop into ``optimal``.
"""

from __future__ import annotations

from enum import StrEnum


class Status(StrEnum):
    """A ``str``, so JSON and comparisons see the name."""

    OPTIMAL = "optimal"  # a proven bound meets the exact value (a method: it finished)
    TIME_LIMIT = "time_limit"  # the best found when time ran out, with the bound proven so far
    GAP_LIMIT = "gap_limit"  # the MILP stopped at the relative gap it was given
    FEASIBLE = "feasible"  # an allowed alteration, not (yet) proven best (a node limit)
    UNVERIFIED = "unverified"  # the solver's claim and the exact chain disagree
    INTERRUPTED = "interrupted"  # stopped on request (Ctrl-C) with the best found so far

    @property
    def cut_short(self) -> bool:
        """An incumbent of a search that did not finish: its bound may still be open."""
        return self in (Status.TIME_LIMIT, Status.GAP_LIMIT, Status.FEASIBLE)
