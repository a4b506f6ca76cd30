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
    # under max_alarm: proven that no alteration within the budget keeps Pr(alarm) <= δ
    INFEASIBLE = "infeasible"

    @property
    def cut_short(self) -> bool:
        """An incumbent of a search that did not finish: its bound may still be open."""
        return self in (Status.TIME_LIMIT, Status.GAP_LIMIT, Status.FEASIBLE)


class StopReason(StrEnum):
    """How a method's work on one budget ended, in the method's own words: kept apart from
    :class:`Status`, which certification decides (a method that *finished* has searched all
    it set out to; only a proven bound meeting the exact value makes its answer ``optimal``).
    A ``str``, so JSON and comparisons see the name."""

    FINISHED = "finished"  # the method ran to its end on this budget
    TIME = "time"  # its time limit (or its share of the call's) ran out
    NODES = "nodes"  # a search hit its node limit
    GAP = "gap"  # the MILP stopped at the relative gap it was given
    CANCELLED = "cancelled"  # stopped on request (Ctrl-C, a cancel token)

    @classmethod
    def cut(cls, cancelled: bool) -> StopReason:
        """A method cut short by its deadline: on request when its token was ``cancelled``,
        else by time."""
        return cls.CANCELLED if cancelled else cls.TIME

    @classmethod
    def of(cls, status: Status, cancelled: bool) -> StopReason:
        """The stop a method's own ``status`` records (before certification): finished where
        it claims its optimum, a node or gap limit where it says so, else cut by time or
        (``cancelled``) on request."""
        if status == Status.OPTIMAL:
            return cls.FINISHED
        if status == Status.FEASIBLE:
            return cls.NODES
        if status == Status.GAP_LIMIT:
            return cls.GAP
        if status == Status.INTERRUPTED:
            return cls.CANCELLED
        if status == Status.INFEASIBLE:
            return cls.FINISHED
        return cls.cut(cancelled)
