"""Independent pieces of one computation on both cores, in forked copies of this process.

A cover's unions (:mod:`misdirect.solvers.engines.covering`) are independent relaxation
solves on one kept basis, each mostly Python and scipy between small dense solves: two threads
would take turns on the interpreter. A forked copy shares everything built before the fork
(the chain, the basis: copy-on-write, nothing pickled) and hands back only its answer. That
is what :func:`forked_map` does; where there is no ``fork`` (not Linux) it runs every piece
here, in order, with the same answers.

The parent stays in charge of time: it runs piece 0 itself, then waits for the others while
checking its deadline, and kills every child once that deadline has passed (a cancellation
included: the children's copy of the token never hears of it) or once its own piece fails.
"""

from __future__ import annotations

import contextlib
import multiprocessing
import os
import pickle
import select
import signal
import sys
import threading
import traceback
import warnings
from collections.abc import Callable, Iterator
from typing import Any, TypeVar, cast

from misdirect.core.memory import memory_limit
from misdirect.solvers.deadline import Deadline, DeadlineExpiredError

T = TypeVar("T")
POLL_S = 0.05  # how often the parent, waiting for its children, looks at its deadline
PR_SET_PDEATHSIG = 1  # prctl's option: the signal a child gets when its parent dies
FORK_ENV = "MISDIRECT_FORK"  # "0": never fork (every piece runs in this process)


def can_fork() -> bool:
    """Whether pieces may run in forked children: on Linux with ``fork``, unless switched
    off (``MISDIRECT_FORK=0``, e.g. in a server whose threads must not be copied)."""
    if os.environ.get(FORK_ENV, "1").strip().lower() in ("0", "no", "off", "false"):
        return False
    return sys.platform.startswith("linux") and hasattr(os, "fork")


class Claims:
    """The indices ``0 .. total - 1``, each handed to one worker of a :func:`forked_map`
    (whichever asks first: a worker whose pieces run long takes fewer), in a counter in
    shared memory made before the fork. :meth:`stop` hands out nothing more, to any worker."""

    def __init__(self, total: int, workers: int) -> None:
        self.total = total
        shared = workers > 1 and can_fork()
        self._shared = multiprocessing.get_context("fork").Value("q", 0) if shared else None
        self._local = 0

    def __iter__(self) -> Iterator[int]:
        while (index := self._claim()) < self.total:
            yield index

    def _claim(self) -> int:
        if self._shared is None:
            self._local += 1
            return self._local - 1
        with self._shared.get_lock():
            index = int(self._shared.value)
            self._shared.value = index + 1
        return index

    def stop(self) -> None:
        if self._shared is None:
            self._local = self.total
            return
        with self._shared.get_lock():
            self._shared.value = self.total


def forked_map(work: Callable[[int], T], pieces: int, deadline: Deadline | None = None) -> list[T]:
    """``[work(0), ..., work(pieces - 1)]``: piece 0 here, the others each in a forked child
    (all here, in order, where :func:`can_fork` says no or the copies would not fit the
    memory available). ``work`` must not depend on what another piece changes: a child's
    changes to this process's objects are lost, only its answer (pickled) comes back. A
    child's exception is raised here (as itself where it pickles, else as a RuntimeError with
    its traceback); :class:`DeadlineExpiredError` once ``deadline`` has passed, the children
    killed."""
    if pieces <= 1 or not can_fork() or not _room_for(pieces - 1):
        return [work(k) for k in range(pieces)]
    children: dict[int, tuple[int, int]] = {}  # piece: (pid, read end)
    here = [0]
    try:
        for k in range(1, pieces):
            try:
                children[k] = _fork(work, k)
            except OSError:  # no process to be had (a limit on them): this one does it
                here.append(k)
        answers: dict[int, Any] = {k: work(k) for k in here}
        for k, (pid, reader) in children.items():
            answers[k] = _collect(pid, reader, deadline)
        return [answers[k] for k in range(pieces)]
    finally:
        for pid, reader in children.values():
            _end(pid, reader)


def forked_call(work: Callable[[], T], deadline: Deadline | None) -> T:
    """``work()`` in a forked child, killed once ``deadline`` has passed
    (:class:`DeadlineExpiredError`): for one call that cannot watch a deadline itself (a
    sparse LU that drowns in fill has no place to stop). Here, unwatched, where there is no
    limit, no ``fork`` or no room for a copy. Only its answer comes back, as in
    :func:`forked_map`."""
    if deadline is None or deadline.remaining() is None or not can_fork() or not _room_for(1):
        return work()
    try:
        pid, reader = _fork(lambda _: work(), 0)
    except OSError:
        return work()
    try:
        return cast(T, _collect(pid, reader, deadline))
    finally:
        _end(pid, reader)


def _end(pid: int, reader: int) -> None:
    """Close a child's pipe, kill it (gone already where it answered: harmless) and reap it
    in the background."""
    with contextlib.suppress(OSError):
        os.close(reader)
    with contextlib.suppress(OSError):
        os.kill(pid, signal.SIGKILL)
    threading.Thread(target=_reap, args=(pid,), daemon=True).start()


def _room_for(children: int) -> bool:
    """Whether ``children`` copies of this process fit the memory limit (what is available,
    or the user's ``--memory-limit``, which this process counts against too). A copy shares
    its pages until it writes them, but the interpreter writes to every object it touches
    (reference counts), so a child is costed at this process's whole resident size."""
    limit, source = memory_limit()
    if limit is None:
        return True
    try:
        with open("/proc/self/statm", encoding="ascii") as statm:
            resident = int(statm.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, IndexError):
        return True
    copies = children if source == "available" else children + 1
    return copies * resident <= limit


def _fork(work: Callable[[int], Any], k: int) -> tuple[int, int]:
    reader, writer = os.pipe()
    parent = os.getpid()
    sys.stdout.flush()
    sys.stderr.flush()
    with warnings.catch_warnings():  # Python 3.12 warns of fork beside threads: see the module
        warnings.simplefilter("ignore", DeprecationWarning)
        pid = os.fork()
    if pid == 0:  # the child: never returns into the caller's code
        code = 0
        try:
            os.close(reader)
            _die_with_parent(parent)
            # Ctrl-C reaches the whole process group: the parent handles it and kills this
            signal.signal(signal.SIGINT, signal.SIG_IGN)
            _answer(writer, work, k)
        except BaseException:
            code = 1
        finally:
            os._exit(code)
    os.close(writer)
    return pid, reader


def _die_with_parent(parent: int) -> None:
    """In the child: be killed with the parent (Linux's ``PR_SET_PDEATHSIG``), so that a
    parent killed outright (SIGKILL, SIGTERM) leaves no worker computing for nobody; and
    leave at once where the parent died before that was set."""
    with contextlib.suppress(Exception):  # not Linux's libc: the child ends with its pieces
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(PR_SET_PDEATHSIG, signal.SIGKILL)
    if os.getppid() != parent:
        os._exit(1)


def _answer(writer: int, work: Callable[[int], Any], k: int) -> None:
    """In the child: ``work(k)``'s outcome, pickled, down the pipe."""
    try:
        outcome: tuple[str, Any] = ("ok", work(k))
    except DeadlineExpiredError:
        outcome = ("expired", None)
    except BaseException as error:
        outcome = ("error", (error, f"{type(error).__name__}: {error}", traceback.format_exc()))
    try:
        data = pickle.dumps(outcome)
    except Exception:  # an exception that does not pickle: its text
        _, text, trace = outcome[1]
        data = pickle.dumps(("error", (None, text, trace)))
    with os.fdopen(writer, "wb") as pipe:
        pipe.write(data)


def _collect(pid: int, reader: int, deadline: Deadline | None) -> Any:
    """The answer of the child ``pid``, read from ``reader`` as it comes, watching
    ``deadline``."""
    chunks: list[bytes] = []
    while True:
        if deadline is not None and deadline.expired():
            raise DeadlineExpiredError
        ready, _, _ = select.select([reader], [], [], POLL_S)
        if not ready:
            continue
        chunk = os.read(reader, 1 << 20)
        if not chunk:
            break
        chunks.append(chunk)
    if not chunks:
        _, status = os.waitpid(pid, 0)
        raise RuntimeError(f"a forked worker died before it answered (wait status {status})")
    # our own child's answer, over its pipe: never a file or anything a user hands us
    kind, payload = pickle.loads(b"".join(chunks))
    if kind == "ok":
        return payload
    if kind == "expired":
        raise DeadlineExpiredError
    error, text, trace = payload
    if isinstance(error, BaseException):
        error.add_note(f"in a forked worker:\n{trace}")
        raise error
    failure = RuntimeError(f"in a forked worker: {text}")
    failure.add_note(trace)
    raise failure


def _reap(pid: int) -> None:
    with contextlib.suppress(OSError):
        os.waitpid(pid, 0)
