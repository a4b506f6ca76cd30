"""When a solve must stop: its wall-clock limit and its own cancellation token.

Each ``solve`` call owns one :class:`CancelToken` (the caller's, or a fresh one), and every
:class:`Deadline` of that call carries it. Cancelling the token makes every deadline of that
call expire at once; other solves in the same process (threads, a notebook, a server) hold
other tokens and go on. A token cancelled before its solve starts stays cancelled: the solve
then returns its first incumbent at once instead of losing the request.
"""

from __future__ import annotations

import threading
import time


class CancelToken:
    """A stop request for the solves that hold it (Ctrl-C in the CLI, a server's abort).

    Solvers stop at their next check and hand back the best they have, as if their time were
    up; :func:`misdirect.solve` then reports the points cut short as ``interrupted``.
    """

    def __init__(self) -> None:
        self._event = threading.Event()

    def cancel(self) -> None:
        self._event.set()

    @property
    def cancelled(self) -> bool:
        return self._event.is_set()

    def __repr__(self) -> str:
        return f"CancelToken(cancelled={self.cancelled})"


class DeadlineExpiredError(Exception):
    """Raised by :meth:`Deadline.check` inside a computation whose partial result proves
    nothing (a policy iteration cut between rounds): the caller that owns the deadline catches
    it and reports what it had proven before."""


class Deadline:
    """A wall-clock limit shared by every stage and budget of one ``solve`` call (or of one
    audit or hardening, whose solves share it), expired early when its token is cancelled."""

    def __init__(
        self,
        seconds: float | None = None,
        *,
        cancel: CancelToken | None = None,
        end: float | None = None,
    ):
        self.cancel = cancel if cancel is not None else CancelToken()
        now_end = None if seconds is None else time.perf_counter() + seconds
        ends = [e for e in (now_end, end) if e is not None]
        self.end = min(ends) if ends else None

    def within(self, seconds: float | None) -> Deadline:
        """A deadline for one piece of work: ``seconds`` from now (None: no limit of its own),
        never later than this one, and cancelled with it."""
        return Deadline(seconds, cancel=self.cancel, end=self.end)

    @property
    def cancelled(self) -> bool:
        return self.cancel.cancelled

    def remaining(self) -> float | None:
        """Seconds left (never negative), None without a limit."""
        if self.cancel.cancelled:
            return 0.0
        return None if self.end is None else max(self.end - time.perf_counter(), 0.0)

    def expired(self) -> bool:
        return self.cancel.cancelled or (self.end is not None and time.perf_counter() >= self.end)

    def check(self) -> None:
        """Raise :class:`DeadlineExpiredError` once this deadline has passed or its token is
        cancelled: for loops deep inside an engine that cannot hand back a partial answer."""
        if self.expired():
            raise DeadlineExpiredError

    def share(self, parts: int) -> float | None:
        """An even share of what is left for the next of ``parts`` pieces of work; what a
        piece does not use rolls over to the pieces after it."""
        left = self.remaining()
        return None if left is None else left / max(parts, 1)

    def front_share(self, parts: int) -> float | None:
        """Twice the share of each later piece (``2 / (parts + 1)`` of what is left): for a
        curve's budgets, smallest first, where the next one is the likelier to finish."""
        left = self.remaining()
        return None if left is None else 2 * left / (max(parts, 1) + 1)


def call_deadline(
    deadline: Deadline | None = None,
    time_limit: float | None = None,
    cancel: CancelToken | None = None,
) -> Deadline:
    """The deadline of one call (a solve, an audit): a caller's shared ``deadline``, limited
    further by the call's own ``time_limit`` or ``cancel`` token, or a new one from them. The
    one place a deadline is built from a call's options, so every method runs by the clock
    the front door started, not by one of its own."""
    if deadline is None:
        return Deadline(time_limit, cancel=cancel)
    if time_limit is not None or cancel is not None:
        return Deadline(time_limit, cancel=cancel or deadline.cancel, end=deadline.end)
    return deadline
