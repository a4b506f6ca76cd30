"""Where a long build in core may be stopped: the caller's check, called between its stages.

Core knows nothing of deadlines (they belong to the solvers), yet building the attacker's
choice product on a million-state grid takes longer than a whole ``--time-limit``. So a
caller that owns a deadline hands core a plain ``check()`` for the block it runs
(:func:`interruptible`); the builds call :func:`checkpoint` between their vectorised stages,
and the check raises to stop them. Nothing is half-built: the exception leaves the build
without a result, and the caller reports the stage as cut.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator
from contextvars import ContextVar

Check = Callable[[], None]

_check: ContextVar[Check | None] = ContextVar("misdirect_build_check", default=None)


@contextlib.contextmanager
def interruptible(check: Check | None) -> Iterator[None]:
    """Within this block (of this thread or task), :func:`checkpoint` calls ``check``; None
    leaves the checks of an enclosing block in place."""
    if check is None:
        yield
        return
    token = _check.set(check)
    try:
        yield
    finally:
        _check.reset(token)


def checkpoint() -> None:
    """Call the current block's check (it raises to stop the build); outside one, nothing."""
    check = _check.get()
    if check is not None:
        check()
