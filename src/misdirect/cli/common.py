"""What every command shares: the consoles, exit codes, error handling, JSON output, signals,
progress bars and small printing helpers."""

from __future__ import annotations

import contextlib
import json
import math
import multiprocessing
import os
import re
import signal
import sys
import threading
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from functools import wraps
from pathlib import Path
from typing import Any, NoReturn

import typer
from rich.console import Console
from rich.markup import escape
from rich.progress import BarColumn, Progress, ProgressColumn, Task, TextColumn, TimeElapsedColumn
from rich.text import Text

from misdirect.core.model import format_alteration
from misdirect.errors import (
    MisdirectError,
    OptionError,
    ProblemError,
    ProblemsError,
    WriteError,
)
from misdirect.io.files import one_line, write_output
from misdirect.report import json_output
from misdirect.solvers.deadline import CancelToken

MIN_COLUMNS = 40  # a terminal narrower than this (COLUMNS=0, say) is read as this wide


def _width() -> int | None:
    """The consoles' width: COLUMNS when it is a usable width, else rich's own guess (which
    prints nothing at COLUMNS=0); never below :data:`MIN_COLUMNS`."""
    text = os.environ.get("COLUMNS", "")
    if not text:
        return None
    return max(int(text), MIN_COLUMNS) if text.strip().isdigit() else MIN_COLUMNS * 2


out = Console(width=_width())
err = Console(stderr=True, width=_width())
INPUT_ERROR = 2
INTERRUPTED = 130  # 128 + SIGINT, as a shell reports it
TERMINATED = 143  # 128 + SIGTERM


# -- checks of option values --------------------------------------------------------------------


def check_range(option: str, value: int | float, least: int | float, most: int | float) -> None:
    """A numeric option within its documented range, before anything is built from it."""
    if not least <= value <= most:
        raise ProblemError(f"must be between {least:,} and {most:,}, got {value:,}", field=option)


def check_seconds(time_limit: float | None) -> None:
    """``--time-limit``: a positive number of seconds, when given."""
    if time_limit is not None and not (math.isfinite(time_limit) and time_limit > 0):
        raise ProblemError("must be a positive number of seconds", field="--time-limit")


def check_budget(value: float | None, option: str) -> None:
    """A budget option: a non-negative number, when given."""
    if value is not None and not (math.isfinite(value) and value >= 0):
        raise ProblemError(f"must be a non-negative number, got {value:g}", field=option)


# -- library parameters as flags ---------------------------------------------------------------

# solve options the library names by parameter (misdirect.solvers.options.SolveOptions), and
# the pool's (misdirect.distributed.connect)
FLAGS = (
    *("time_limit", "threads", "solver", "formulation", "mip_gap", "verbose", "max_nodes"),
    *("cluster", "workers"),
)


# library parameters whose flag is not their name: a scenario's grid size ``n`` is --size, the
# file a function writes (``path``, ``output``) is -o, PAYNT's property ``prop`` is --props
RENAMED_FLAGS = {"n": "--size", "path": "-o", "output": "-o", "prop": "--props"}

# the fields of library errors that name a parameter, not a place in a file (pomdp.states):
# the file written, reproduce's and sweep's folder, the pool, PAYNT's constants and property
PARAMETER_FIELDS = frozenset(
    {"path", "output", "out", "cluster", "workers", "constants", "prop", "n", "observations"}
    | {"coordinates"}
)

# parameters a library message sets to a value to suggest it (try method="milp")
ASSIGNED = ("method", "solver", "formulation", "output", "coordinates")
_ASSIGNMENT = re.compile(r"\b(" + "|".join(ASSIGNED) + r')="([^"]*)"')


def flag(parameter: str) -> str:
    """The command-line flag of a library parameter: ``time_limit`` → ``--time-limit``."""
    return RENAMED_FLAGS.get(parameter, "--" + parameter.replace("_", "-"))


def as_flags(text: str) -> str:
    """A library message about solve options, with each option named as its flag."""
    pattern = r"(?<![\w-])(" + "|".join(FLAGS) + r")\b"  # not a flag already (--solver)
    return re.sub(pattern, lambda match: flag(match.group(1)), assignments_as_flags(text))


def assignments_as_flags(text: str) -> str:
    """A library message with each suggested setting as its flag: ``method="milp"`` →
    ``--method milp``."""
    return _ASSIGNMENT.sub(lambda match: f"{flag(match[1])} {match[2]}", text)


def field_flag(field: str | None) -> str | None:
    """The field of a library error as the command line shows it: a parameter as its flag,
    anything else (a place in a file) as it is."""
    return flag(field) if field is not None and field in PARAMETER_FIELDS else field


def shown_lines(error: ProblemError) -> list[str]:
    """A library error's lines (one per problem) as the command line shows them: the
    parameters it names as their flags."""
    if isinstance(error, ProblemsError):
        problems = [line for problem in error.problems for line in shown_lines(problem)]
        return problems + error.lines[len(error.problems) :]  # and the count of the rest
    if isinstance(error, OptionError):
        return [f"{flag(error.parameter)}: {as_flags(error.reason)}"]
    where = ": ".join(part for part in (error.source, field_flag(error.field)) if part)
    reason = assignments_as_flags(error.reason)
    return [f"{where}: {reason}" if where else reason]


# -- output -------------------------------------------------------------------------------------


def finite_json(value: Any) -> Any:
    """``value`` with every float that JSON cannot hold (NaN, ±inf) as ``null``: a mean over
    no finished run, an objective the backend left undefined. JSON has no NaN, and a reader
    that meets one fails on the whole document; each such field's schema says when it is
    null."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: finite_json(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [finite_json(v) for v in value]
    if hasattr(value, "dtype") and getattr(value, "shape", None) == ():  # a numpy scalar
        return finite_json(value.item())
    return value


def print_json(payload: dict[str, Any]) -> None:
    """The one JSON object of ``--json`` on stdout: a document of
    :mod:`misdirect.report.json_output`, which names its schema. A stdout that cannot take it
    (a full disk, ``> /dev/full``) is a WriteError, and what is left unwritten is dropped."""
    text = json_text(payload)
    try:
        sys.stdout.write(text)
        sys.stdout.flush()
    except OSError as error:
        _drop_stdout()
        raise WriteError(f"cannot write standard output: {error.strerror or error}") from None


def json_text(payload: dict[str, Any]) -> str:
    """The text of a ``--json`` document (as printed, and as ``solve -o FILE.json`` writes
    it): NaN and infinities as null."""
    assert payload.get("schema") == json_output.SCHEMA, "built by report.json_output"
    safe = finite_json(payload)
    return json.dumps(safe, indent=2, default=_json_default, allow_nan=False) + "\n"


def _drop_stdout() -> None:
    """Point stdout at /dev/null, so that the buffered rest neither fails again nor prints a
    traceback when Python flushes it at exit."""
    with contextlib.suppress(OSError, ValueError):
        sink = os.open(os.devnull, os.O_WRONLY)
        os.dup2(sink, sys.stdout.fileno())
        os.close(sink)


def _json_default(value: Any) -> Any:
    if hasattr(value, "tolist"):
        return value.tolist()
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")


def note(text: str) -> None:
    """One line on stderr (``wrote ...``), names escaped."""
    err.print(escape(one_line(text)), highlight=False, soft_wrap=True)


def wrote(text: str) -> None:
    """The summary of what a command wrote (``wrote FILE (...)``), one line on stdout: every
    command that writes files says so where its output goes, names escaped."""
    out.print(escape(one_line(text)), highlight=False, soft_wrap=True)


def print_notes(notes: list[str]) -> None:
    """A result's notes on stderr, one line each."""
    for text in notes:
        err.print(f"note: {escape(one_line(text))}", highlight=False)


def fmt_alteration(alteration: dict[str, str]) -> str:
    return escape(format_alteration(alteration))


def write_text(command: str, text: str, output: Path | None, as_json: bool, **about: Any) -> None:
    """Write ``text`` to ``output``, or to standard output when there is none (with --json,
    as the ``content`` of the one JSON object)."""
    if output is not None:
        write_output(output, text)  # atomic; a bad path or a failed write is one line
    if as_json:
        print_json(json_output.text_output(command, output, text, **about))
    elif output is None:
        sys.stdout.write(text)


# -- errors and signals -------------------------------------------------------------------------


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised like Ctrl-C so that the same clean-up (a solver's worker killed, temporary
    files removed) runs before the command exits with 143."""


def _terminate(signum: int, frame: Any) -> None:
    raise Terminated


STOP_GRACE_S = 1.0  # after a signal, the command's own stop gets this long, then exits hard


class _Watchdog:
    """Sees SIGINT and SIGTERM as they arrive, whatever the main thread is doing.

    Python runs a signal handler only between bytecodes of the main thread, so one long call
    into numpy, scipy or a solver would hold a signal back until it returns (SIGTERM waited
    120 s on a 1000x1000 grid). The C handler also writes the signal's number to a wakeup
    pipe at once; this thread reads it, cancels the command's solves (``cancel``) and gives
    the command :data:`STOP_GRACE_S` to stop by itself. If it has not, it kills the solver
    workers and exits hard with the signal's exit code. (A call that holds the GIL throughout
    holds this thread back too; the engines keep such calls short.)"""

    def __init__(self, as_json: bool | str) -> None:
        self.as_json = as_json
        self.cancel: CancelToken | None = None  # set while a solve runs (stop_gracefully)
        self.finished = threading.Event()
        self._read, self._write = os.pipe()
        os.set_blocking(self._write, False)
        self._previous = signal.set_wakeup_fd(self._write, warn_on_full_buffer=False)
        self._thread = threading.Thread(target=self._watch, name="misdirect-signals", daemon=True)
        self._thread.start()

    def _watch(self) -> None:
        while True:
            try:
                data = os.read(self._read, 64)
            except OSError:
                return
            if not data or self.finished.is_set():
                return
            signals = [n for n in data if n in (signal.SIGINT, signal.SIGTERM)]
            if not signals:
                continue
            if self.cancel is not None:
                self.cancel.cancel()  # the solves hand back their best at their next check
            if self.finished.wait(STOP_GRACE_S):
                return
            _exit_hard(signals[0], self.as_json)

    def close(self) -> None:
        self.finished.set()
        signal.set_wakeup_fd(self._previous)
        with contextlib.suppress(OSError):
            os.write(self._write, b"\0")  # wake the thread: it sees ``finished`` and returns
        self._thread.join(timeout=1.0)
        for fd in (self._read, self._write):
            with contextlib.suppress(OSError):
                os.close(fd)


_watchdog: _Watchdog | None = None  # the running command's (main thread only)


def _exit_hard(signum: int, as_json: bool | str) -> None:
    """The command did not stop within the grace period: stop its solver workers, say so in
    one line (and the one JSON object), exit with the signal's code."""
    for child in multiprocessing.active_children():  # a HiGHS worker
        with contextlib.suppress(Exception):
            child.kill()
    name = "terminated (SIGTERM)" if signum == signal.SIGTERM else "interrupted"
    message = f"{name}: stopped at once (the work under way did not stop within {STOP_GRACE_S:g} s)"
    with contextlib.suppress(OSError):
        if as_json:
            command = as_json if isinstance(as_json, str) else None
            document = json_output.error_document(command, message)
            os.write(1, (json.dumps(document) + "\n").encode())
        os.write(2, f"error: {message}\n".encode())
    os._exit(TERMINATED if signum == signal.SIGTERM else INTERRUPTED)


@contextlib.contextmanager
def _signals_as_exceptions(as_json: bool | str = False) -> Iterator[None]:
    """SIGINT raises KeyboardInterrupt and SIGTERM :class:`Terminated` while a command runs
    (restored afterwards, so an embedding program keeps its own handlers); a command still
    running :data:`STOP_GRACE_S` after the signal exits hard (:class:`_Watchdog`)."""
    global _watchdog
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGTERM, _terminate)
    previous_int = signal.signal(signal.SIGINT, signal.default_int_handler)
    outer, _watchdog = _watchdog, _Watchdog(as_json)
    try:
        yield
    finally:
        _watchdog.close()
        _watchdog = outer
        signal.signal(signal.SIGTERM, previous)
        signal.signal(signal.SIGINT, previous_int)


@dataclass
class StopRequest:
    """The cancel token of a command's solves, and the signals that cancelled it."""

    token: CancelToken = field(default_factory=CancelToken)
    received: list[int] = field(default_factory=list)


@contextlib.contextmanager
def stop_gracefully() -> Iterator[StopRequest]:
    """While solving, the first Ctrl-C or SIGTERM cancels the command's solves (they hand back
    their best answers); a second one stops at once, as elsewhere."""
    request = StopRequest()
    if threading.current_thread() is not threading.main_thread():
        yield request
        return

    def ask(signum: int, frame: Any) -> None:
        if request.received:
            raise Terminated if signum == signal.SIGTERM else KeyboardInterrupt
        request.received.append(signum)
        request.token.cancel()

    previous = {sig: signal.signal(sig, ask) for sig in (signal.SIGINT, signal.SIGTERM)}
    watchdog = _watchdog
    if watchdog is not None:  # cancels at once even while a long call holds the main thread
        watchdog.cancel = request.token
    try:
        yield request
    finally:
        if watchdog is not None:
            watchdog.cancel = None
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def handle_errors(command: Callable[..., None], name: str | None = None) -> Callable[..., None]:
    """Turn library errors into exit code 2 and one readable line, never a traceback;
    Ctrl-C and SIGTERM into one line and exit code 130 or 143. ``name``: the command as typed
    (``scenario knapsack``), the ``command`` of its ``--json`` error."""

    @wraps(command)
    def wrapper(*args: Any, **kwargs: Any) -> None:
        as_json: bool | str = kwargs.get("as_json", False) and (name or command.__name__)
        try:
            with _signals_as_exceptions(as_json):
                command(*args, **kwargs)
        except OptionError as error:  # the library names the parameter, the CLI its flag
            field, reason = flag(error.parameter), as_flags(error.reason)
            fail(f"{field}: {reason}", INPUT_ERROR, as_json, field=field)
        except ProblemsError as error:  # one line each, so every problem shows at once
            first, *more = lines = shown_lines(error)
            fail(
                first,
                INPUT_ERROR,
                as_json,
                more=more,
                field=field_flag(error.field),
                source=error.source,
                problems=[one_line(line) for line in lines],
            )
        except ProblemError as error:  # a parameter it names is shown as its flag
            (message,) = shown_lines(error)
            fail(message, INPUT_ERROR, as_json, field=field_flag(error.field), source=error.source)
        except MisdirectError as error:
            fail(assignments_as_flags(str(error)), 1, as_json)
        except (typer.Exit, typer.Abort):
            raise
        except Terminated:
            fail("terminated (SIGTERM)", TERMINATED, as_json)
        except KeyboardInterrupt:
            fail("interrupted", INTERRUPTED, as_json)
        except MemoryError:
            fail(
                "out of memory: the model is too large for this machine (see Limits in the README)",
                1,
                as_json,
            )
        except RuntimeError as error:
            if "can't start new thread" not in str(error):
                _internal(error, as_json)
            # a thread's stack did not fit the address space left (ulimit -v): as at import
            fail(
                f"misdirect could not start a thread: {error} (too little memory or address "
                "space? check `ulimit -v`)",
                1,
                as_json,
            )
        except OSError as error:  # an I/O failure no check foresaw (a disk filling up, ...)
            where = f"{error.filename}: " if error.filename else ""
            fail(f"{where}{error.strerror or error}", 1, as_json)
        except Exception as error:  # a bug: keep the traceback behind an opt-in
            _internal(error, as_json)

    return wrapper


def _internal(error: Exception, as_json: bool | str) -> NoReturn:
    """A bug: one line, the traceback behind MISDIRECT_DEBUG=1."""
    if os.environ.get("MISDIRECT_DEBUG"):
        raise error
    fail(
        f"internal error: {type(error).__name__}: {error} "
        "(set MISDIRECT_DEBUG=1 for the traceback)",
        1,
        as_json,
    )


def fail(
    message: str, code: int, as_json: bool | str, *, more: Sequence[str] = (), **context: Any
) -> NoReturn:
    """One error line on stderr (and the error document on stdout with --json: ``as_json``
    is then the command's name), then exit; ``more``: further problems of the same input,
    one line each."""
    message = one_line(message)  # a name with a newline must not split the one line
    if as_json:
        command = as_json if isinstance(as_json, str) else None
        with contextlib.suppress(WriteError):  # stdout is full: the line on stderr remains
            print_json(json_output.error_document(command, message, **context))
    for line in (message, *map(one_line, more)):
        err.print(f"[bold red]error:[/] {escape(line)}", highlight=False, soft_wrap=True)
    raise typer.Exit(code)


# -- progress -----------------------------------------------------------------------------------


PHASES = {  # a solver's stage names, as a phase on the bar
    "loading": "loading the problem",
    "product": "building the product chain",
    "bounds": "bounds",
    "enumeration": "enumerating alterations",
}


def eta(seconds: float) -> str:
    """A time left, rounded as an estimate is: "about 3 s", "about 2 min", "about 1.5 h"."""
    if seconds < 60:
        return f"about {max(round(seconds), 1)} s"
    if seconds < 3600:
        return f"about {round(seconds / 60)} min"
    return f"about {seconds / 3600:.1f} h"


class _Count(ProgressColumn):
    """done/total, nothing for a phase without a count."""

    def render(self, task: Task) -> Text:
        if task.total is None:
            return Text("")
        return Text(f"{int(task.completed):,}/{int(task.total):,}")


class ProgressBars:
    """Progress bars on stderr, one per named task; silent under --json or without a terminal."""

    def __init__(self, enabled: bool, *, transient: bool = False):
        self.enabled = enabled and err.is_terminal
        self.transient = transient
        self.bar: Progress | None = None
        self.tasks: dict[str, Any] = {}

    def __enter__(self) -> ProgressBars | None:
        if not self.enabled:
            return None
        self.bar = Progress(
            TextColumn("{task.description:<20}"),
            BarColumn(),
            _Count(),
            TimeElapsedColumn(),
            TextColumn("{task.fields[detail]}"),
            console=err,
            transient=self.transient,
        )
        self.bar.start()
        return self

    def track(
        self,
        name: str,
        done: int,
        total: int,
        *,
        stage: str | None = None,
        detail: str | None = None,
        note: str | None = None,
        rate: float | None = None,
    ) -> None:
        """Show a report: a bar of ``done``/``total``, or, for a phase without a count
        (``total`` 0 with a ``stage``), the phase's name on a bar without an end; a ``rate``
        (steps a second) gives the detail the rate and an estimate of the time left."""
        assert self.bar is not None
        if note:
            self.bar.console.print(f"[dim]{escape(note)}[/]", highlight=False)
        if total <= 0 and stage is None:
            return
        if name not in self.tasks:
            self.tasks[name] = self.bar.add_task(name, total=None, detail="")
        description = name if stage is None else f"{name}: {PHASES.get(stage, stage)}"
        if rate is not None and rate > 0 and total > 0:
            detail = f"{rate:,.0f}/s, {eta(max(total - done, 0) / rate)} left"
        elif total <= 0 and detail is None:
            detail = ""  # a new phase: the last phase's detail no longer holds
        fields: dict[str, Any] = {} if detail is None else {"detail": detail}  # a bar column
        self.bar.update(
            self.tasks[name],
            completed=done,
            total=total if total > 0 else None,
            description=description,
            **fields,
        )

    def task(self, name: str) -> Callable[..., None]:
        return lambda done, total, **info: self.track(name, done, total, **info)

    def __exit__(self, *exc: object) -> None:
        if self.bar is not None:
            self.bar.stop()


def print_handovers(done: int, total: int, *, note: str | None = None, **_: object) -> None:
    """Progress without a terminal: only the hand-overs between methods, one line each."""
    if note:
        err.print(escape(one_line(note)), highlight=False, soft_wrap=True)
