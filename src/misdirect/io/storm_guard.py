"""Storm is native code reading untrusted text: what it is given is checked first, and it runs
in a child process, so that nothing in a model file can crash, hang or exhaust this one.

Storm's parsers recurse (2,000 nested parentheses overflow the C stack: SIGSEGV), divide
without asking (a probability ``0/0``: SIGFPE) and allocate what a file announces (a DRN
observation id of 10^8 sizes vectors by it). So:

* the text is checked before Storm sees it (:func:`check_nesting`, :func:`check_drn_text`):
  parentheses nested at most :data:`MAX_NESTING` deep, DRN observation ids and counts within
  the model's own size;
* the work is done in a forked child (:func:`run_isolated`) with an address-space limit
  (``RLIMIT_AS``) and a time limit; the child hands back plain data (arrays, our own
  dataclasses) through a pipe, and a crash, a timeout or an exhausted memory becomes one
  :class:`~misdirect.errors.ProblemError` naming the file. Untrusted files are only ever
  parsed, in the child: what crosses the pipe was pickled by our own code.

``MISDIRECT_STORM_TIME_LIMIT`` (seconds), ``MISDIRECT_STORM_MEMORY`` (bytes; default what the
machine has available) set the limits; ``MISDIRECT_STORM_ISOLATION=0`` reads in this process
(for debugging: a crash then takes the process down).
"""

from __future__ import annotations

import contextlib
import faulthandler
import os
import re
import select
import signal
import sys
import threading
import time
import traceback
from collections.abc import Callable
from multiprocessing.connection import Connection
from typing import Any, TypeVar

import numpy as np

from misdirect.core.memory import available_memory
from misdirect.errors import MisdirectError, ProblemError, ProblemsError

T = TypeVar("T")

MAX_NESTING = 200  # parentheses; Storm's recursive parsers overflow the stack in the thousands
TIME_LIMIT_ENV = "MISDIRECT_STORM_TIME_LIMIT"
MEMORY_ENV = "MISDIRECT_STORM_MEMORY"
ISOLATION_ENV = "MISDIRECT_STORM_ISOLATION"
DEFAULT_TIME_LIMIT = 600.0  # seconds: far above any model that fits in memory
MIN_MEMORY = 1024**3  # the child may always grow by this much, whatever is reported available
POLL_S = 0.1  # how often the parent looks for the child's answer (and lets Ctrl-C in)


# -- checks of the text --------------------------------------------------------------------------


def nesting_depth(text: str) -> int:
    """Deepest nesting of parentheses in ``text`` (vectorised: one pass of numpy)."""
    data = np.frombuffer(text.encode("utf-8", "surrogatepass"), dtype=np.uint8)
    if data.size == 0:
        return 0
    parens = data[(data == ord("(")) | (data == ord(")"))]  # the rest does not matter
    level = np.cumsum(np.where(parens == ord("("), 1, -1))
    # measured from the lowest level before: stray ")" first must not hide the "(" after them
    return int((level - np.minimum.accumulate(np.minimum(level, 0))).max(initial=0))


def check_nesting(text: str, *, field: str, what: str) -> None:
    """Refuse ``text`` (``what`` it is, for the message) nested deeper than
    :data:`MAX_NESTING`: Storm's parser would overflow its stack on it."""
    if text.count("(") <= MAX_NESTING:  # the common case, at the speed of a C loop
        return
    depth = nesting_depth(text)
    if depth > MAX_NESTING:
        raise ProblemError(
            f"{what} nests parentheses {depth:,} deep, more than the limit of {MAX_NESTING}",
            field=field,
        )


# each starts with a literal "\n" (the text is searched with one prepended), which the regular
# expression engine looks for at C speed; Storm's DRN lines start at the line's first character
_STATE = re.compile(rb"\nstate[ \t]+(\S+)[^\n{]*\{[ \t]*([^}\s]*)[ \t]*\}")
_OBSERVATION = re.compile(rb"\nstate[ \t]+\S+[^\n{]*\{[ \t]*([^}\s]*)[ \t]*\}")
_COUNT = re.compile(rb"\n@(nr_states|nr_choices)[ \t]*\r?\n[ \t]*(\S+)")


def check_drn_text(text: str, *, name: str, field: str) -> None:
    """Refuse a DRN file whose numbers Storm would allocate by before it reads the states:
    ``@nr_states``/``@nr_choices`` beyond the states and actions the file lists, or an
    observation id outside 0..(a few times the number of states)."""
    check_nesting(text, field=field, what=name)
    data = b"\n" + text.encode("utf-8", "surrogatepass")
    listed = {b"nr_states": data.count(b"\nstate"), b"nr_choices": data.count(b"action")}
    for match in _COUNT.finditer(data):
        key, value = match[1], match[2].decode("ascii", "replace")
        if value.isdigit() and (len(value) > 18 or int(value) > max(listed[key], 1)):
            raise ProblemError(
                f"{name}: @{key.decode()} says {value[:20]}, but the file lists "
                f"{listed[key]:,} {'states' if key == b'nr_states' else 'choices'}",
                field=field,
            )
    found = _OBSERVATION.findall(data)  # the observation of each state, in C
    if not found:
        return
    ids = np.array(found)
    # Storm sizes its observation tables by the largest id: a few per state at most (a file
    # may leave gaps), and never negative (Storm would read -1 as 4294967295)
    limit = max(4 * len(found), 1024)
    try:
        values = ids.astype(np.int64)
    except (ValueError, OverflowError):  # a number too long for int64, or no number at all
        numbers = [re.fullmatch(rb"-?\d+", i) is not None for i in ids.tolist()]
        values = np.array(
            [
                int(i) if n and len(i) < 19 else (limit if n else 0)
                for i, n in zip(ids.tolist(), numbers, strict=True)
            ],
            dtype=np.int64,
        )  # not a number: left to Storm, which says what is wrong with it
    bad = np.flatnonzero((values < 0) | (values >= limit))
    if not bad.size:
        return
    at = int(bad[0])
    match = next(m for k, m in enumerate(_STATE.finditer(data)) if k == at)
    state = match[1].decode("utf-8", "replace")[:20]
    value = ids[at].decode("ascii", "replace")
    value = value if len(value) <= 20 else value[:17] + "..."
    raise ProblemError(
        f"{name}: state {state} has observation {value}; observation ids must be from 0 to "
        f"{limit - 1:,} (a few per state: this file lists {len(found):,} states)",
        field=field,
    )


# -- the child process --------------------------------------------------------------------------


def isolation_enabled() -> bool:
    """Whether Storm runs in a child: on Linux with ``fork``, unless switched off."""
    if os.environ.get(ISOLATION_ENV, "1").strip() in ("0", "no", "off", "false"):
        return False
    return sys.platform.startswith("linux") and hasattr(os, "fork")


def _seconds() -> float:
    text = os.environ.get(TIME_LIMIT_ENV)
    if text is None:
        return DEFAULT_TIME_LIMIT
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not (value > 0 and value < float("inf")):
        raise ProblemError(
            f"expected a positive number of seconds, got {text!r}", source=TIME_LIMIT_ENV
        )
    return value


def _memory_limit() -> int | None:
    """Bytes of address space the child may have: what it has at the fork, plus what the
    machine has available (or ``MISDIRECT_STORM_MEMORY``); None where Linux does not say."""
    text = os.environ.get(MEMORY_ENV)
    if text is not None:
        if not text.strip().isdigit() or int(text) < 1:
            raise ProblemError(f"expected a number of bytes, got {text!r}", source=MEMORY_ENV)
        extra: int | None = int(text)
    else:
        available = available_memory()
        extra = None if available is None else max(available, MIN_MEMORY)
    if extra is None:
        return None
    try:
        with open("/proc/self/status", encoding="ascii") as status:
            size = next(
                int(line.split()[1]) * 1024 for line in status if line.startswith("VmSize:")
            )
    except (OSError, StopIteration, ValueError, IndexError):
        return None
    return size + extra


def _child(conn: Connection, function: Callable[..., Any], args: tuple, memory: int | None) -> None:
    """The forked child: ``function(*args)`` under the limits, its answer sent over ``conn``."""
    # Ctrl-C reaches the process group: the parent handles it and kills this child (which
    # must not run the parent's handlers, inherited through fork)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    faulthandler.disable()  # a crash here is reported by the parent, in one line
    with contextlib.suppress(OSError, ValueError):  # Storm's own messages are not ours to print
        sink = os.open(os.devnull, os.O_WRONLY)
        os.dup2(sink, 1)
        os.dup2(sink, 2)
    if memory is not None:
        import resource

        with contextlib.suppress(OSError, ValueError):
            _, hard = resource.getrlimit(resource.RLIMIT_AS)
            if hard != resource.RLIM_INFINITY:
                memory = min(memory, hard)
            resource.setrlimit(resource.RLIMIT_AS, (memory, hard))
    answer: tuple[str, Any]
    try:
        answer = ("ok", function(*args))
    except ProblemError as error:  # every problem found (ProblemsError), or the one
        found = getattr(error, "problems", [error])
        answer = (
            "problem",
            ([(e.reason, e.source, e.field) for e in found], getattr(error, "total", 1)),
        )
    except MisdirectError as error:
        answer = ("error", str(error))
    except MemoryError:
        answer = ("memory", None)
    except BaseException as error:  # a bug: its text and traceback for the parent
        answer = ("bug", (f"{type(error).__name__}: {error}", traceback.format_exc()))
    try:
        conn.send(answer)
    except MemoryError:
        with contextlib.suppress(Exception):
            conn.send(("memory", None))
    except Exception as error:  # an answer that does not pickle: a bug
        with contextlib.suppress(Exception):
            conn.send(("bug", (f"{type(error).__name__}: {error}", traceback.format_exc())))


def run_isolated(function: Callable[..., T], *args: Any, name: str, field: str) -> T:
    """``function(*args)`` run in a forked child with memory and time limits; its value, or
    its ProblemError, as if it had run here. A crash (SIGSEGV, SIGFPE, ...), the time limit
    or exhausted memory is one ProblemError about ``name`` (the file read) in ``field``.

    Where no child can be forked (not Linux, or ``MISDIRECT_STORM_ISOLATION=0``) the function
    runs in this process, behind the same checks of the text."""
    if not isolation_enabled():
        return function(*args)
    seconds = _seconds()
    memory = _memory_limit()
    reader, writer = os.pipe()
    sys.stdout.flush()
    sys.stderr.flush()
    pid = os.fork()
    if pid == 0:  # the child: never returns into the caller's code
        code = 0
        try:
            os.close(reader)
            _child(Connection(writer, readable=False), function, args, memory)
        except BaseException:
            code = 1
        finally:
            os._exit(code)
    os.close(writer)
    conn = Connection(reader, writable=False)
    status: int | None = None
    try:
        deadline = time.monotonic() + seconds
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                raise ProblemError(
                    f"Storm did not finish reading {name} within {seconds:g} s (raise the limit "
                    f"with {TIME_LIMIT_ENV})",
                    field=field,
                )
            ready, _, _ = select.select([reader], [], [], min(left, POLL_S))
            if not ready:
                continue
            try:
                kind, payload = conn.recv()
            except (EOFError, OSError):  # the child died before it answered
                _, status = os.waitpid(pid, 0)
                raise _died(status, name, field, memory) from None
            break
    finally:
        conn.close()
        if status is None:
            with contextlib.suppress(OSError):
                os.kill(pid, signal.SIGKILL)
            # the kernel takes a while to tear a large child down: reap it in the background
            threading.Thread(target=_reap, args=(pid,), daemon=True).start()
    if kind == "ok":
        return payload
    if kind == "problem":
        found, total = payload
        raise ProblemsError.of(
            [ProblemError(reason, source=source, field=where) for reason, source, where in found],
            total,
        )
    if kind == "error":
        raise MisdirectError(payload)
    if kind == "memory":
        raise _out_of_memory(name, field, memory)
    message, trace = payload
    error = RuntimeError(f"reading {name}: {message}")
    error.add_note(f"in the child process that read it:\n{trace}")
    raise error


def _reap(pid: int) -> None:
    with contextlib.suppress(OSError):
        os.waitpid(pid, 0)


def _died(status: int, name: str, field: str, memory: int | None) -> ProblemError:
    if os.WIFSIGNALED(status):
        number = os.WTERMSIG(status)
        if number == signal.SIGKILL:  # the kernel's OOM killer, most likely
            return _out_of_memory(name, field, memory)
        try:
            what = signal.Signals(number).name
        except ValueError:
            what = f"signal {number}"
        description = signal.strsignal(number) or what
        return ProblemError(
            f"Storm crashed reading {name} ({what}: {description.lower()}); the file is "
            "malformed in a way Storm does not check",
            field=field,
        )
    code = os.WEXITSTATUS(status) if os.WIFEXITED(status) else status
    return ProblemError(f"Storm stopped reading {name} (exit code {code})", field=field)


def _out_of_memory(name: str, field: str, memory: int | None) -> ProblemError:
    limit = f" (limit {memory / 1024**3:,.1f} GiB of address space)" if memory else ""
    return ProblemError(
        f"Storm ran out of memory reading {name}{limit}; set {MEMORY_ENV} (bytes) to change "
        "the limit",
        field=field,
    )
