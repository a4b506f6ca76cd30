"""Where independent work runs: in this process, or on a cluster behind the same interface.

A sweep's rows, an audit's re-solves and the distributed segment search's subtrees are
independent tasks. They are handed to a :class:`TaskPool`: :class:`LocalPool` runs each in
this process when submitted (today's behaviour, no dependency), and
:class:`misdirect.distributed.DaskPool` runs them on Dask workers. Nothing here imports Dask.
"""

from __future__ import annotations

import threading
from collections import deque
from collections.abc import Callable, Hashable
from typing import Any, Protocol


class SharedBest(Protocol):
    """A value every task can read and raise: the best value found anywhere (the incumbent a
    search prunes against). Picklable, so that tasks on other machines get it."""

    def get(self) -> float: ...

    def offer(self, value: float) -> None: ...


class TaskPool(Protocol):
    """Runs tasks, ``size`` at a time, and hands back each result as it completes."""

    @property
    def size(self) -> int:
        """How many tasks run at once."""
        ...

    def share(self, value: Any) -> Any:
        """``value`` as tasks should receive it (on a cluster, sent to the workers once)."""
        ...

    def submit(self, fn: Callable[..., Any], *args: Any) -> Hashable:
        """Start ``fn(*args)``; the ticket identifies it in :meth:`next_done`."""
        ...

    def next_done(self) -> tuple[Hashable, Any, BaseException | None]:
        """The ticket, result and exception (None when it returned) of a finished task; waits
        for one. Only call with tasks pending."""
        ...

    def pending(self) -> int:
        """Tasks submitted and not yet returned by :meth:`next_done`."""
        ...

    def shared_best(self, initial: float) -> SharedBest:
        """A new :class:`SharedBest` starting at ``initial``."""
        ...


class _LocalBest:
    def __init__(self, value: float):
        self._value = value
        self._lock = threading.Lock()

    def get(self) -> float:
        return self._value

    def offer(self, value: float) -> None:
        with self._lock:
            self._value = max(self._value, value)


class LocalPool:
    """Every task runs in this process, at once, when submitted: the default, with no cluster."""

    size = 1

    def __init__(self) -> None:
        self._done: deque[tuple[int, Any, BaseException | None]] = deque()
        self._count = 0

    def share(self, value: Any) -> Any:
        return value

    def submit(self, fn: Callable[..., Any], *args: Any) -> Hashable:
        self._count += 1
        try:
            self._done.append((self._count, fn(*args), None))
        except Exception as error:  # handed back by next_done, as a cluster's pool does
            self._done.append((self._count, None, error))
        return self._count

    def next_done(self) -> tuple[Hashable, Any, BaseException | None]:
        return self._done.popleft()

    def pending(self) -> int:
        return len(self._done)

    def shared_best(self, initial: float) -> SharedBest:
        return _LocalBest(initial)
