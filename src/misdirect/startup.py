"""Ctrl-C (or SIGTERM) while the ``misdirect`` command is still importing: one line and exit
code 130 (143), not a traceback from whichever module was importing.

The console script imports the whole package before its ``main()`` runs, which takes a second
or so; a signal then would raise KeyboardInterrupt deep in an import. This module is the
package's first import: when this process is the ``misdirect`` command (never in a library
user's program or an interactive session) it makes those signals end the process quietly, until
:func:`release` hands them back to the command line's own handling.
"""

from __future__ import annotations

import os
import sys

# the C module itself: ``signal`` imports enum, ``threading`` and ``typing`` take milliseconds
# more, and every millisecond before the handlers are in place is one where Ctrl-C would
# print a traceback from the middle of an import
_signal = __import__("_signal")

_CODES: dict[int, tuple[int, bytes]] = {
    _signal.SIGINT: (130, b"error: interrupted\n"),
    _signal.SIGTERM: (143, b"error: terminated (SIGTERM)\n"),
}
_installed: dict[int, object] = {}
_COMMANDS = ("misdirect", "misdirect-script")


def _is_command_line() -> bool:
    """Whether this process is the ``misdirect`` command: its script, or ``python -m
    misdirect`` (whose ``__main__`` is not yet ours while the package imports: the
    interpreter's own arguments say it)."""
    if sys.flags.interactive:
        return False
    main = sys.modules.get("__main__")
    name = os.path.basename(getattr(main, "__file__", None) or "")
    if name.split(".")[0] in _COMMANDS:
        return True
    arguments = iter(getattr(sys, "orig_argv", [])[1:])
    for argument in arguments:  # the interpreter's options, up to the module or script
        if argument.startswith("-m"):
            module = argument[2:] or next(arguments, "")
            return module in ("misdirect", "misdirect.cli")
        if argument in ("-X", "-W"):
            next(arguments, None)  # its value
        elif argument.startswith("-c") or not argument.startswith("-"):
            return False
    return False


def _quit(signum: int, frame: object) -> None:
    code, line = _CODES.get(signum, (128 + signum, b"error: interrupted\n"))
    try:
        os.write(2, line)
    finally:
        os._exit(code)


def _cannot_start(kind: type[BaseException], value: BaseException, tb: object) -> None:
    """An import that fails for want of resources (numba's compiler, llvmlite, under an
    address-space limit of 400 MB; a library missing): one line, not the import's traceback;
    anything else as Python shows it."""
    if issubclass(kind, (OSError, MemoryError, ImportError)):
        reason = str(value).splitlines()[0] if str(value) else kind.__name__
        os.write(
            2,
            (
                f"error: misdirect could not start: {kind.__name__}: {reason} (too little "
                "memory or address space for its libraries? check `ulimit -v`)\n"
            ).encode(),
        )
        os._exit(1)
    sys.__excepthook__(kind, value, tb)  # type: ignore[arg-type]


def release() -> None:
    """Give SIGINT and SIGTERM back (Python's defaults) once the command line is imported,
    and failures after the imports back to the command line's own handling."""
    for signum, previous in _installed.items():
        if _signal.getsignal(signum) is _quit:
            _signal.signal(signum, previous)
    _installed.clear()
    if sys.excepthook is _cannot_start:
        sys.excepthook = sys.__excepthook__


if _is_command_line():
    sys.excepthook = _cannot_start
    try:
        for _signum in _CODES:
            _installed[_signum] = _signal.signal(_signum, _quit)
    except ValueError:  # not the main thread (an embedding program): its signals, not ours
        pass
