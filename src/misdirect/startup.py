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
import signal
import sys
import threading
from typing import Any

_CODES: dict[int, tuple[int, bytes]] = {
    signal.SIGINT: (130, b"error: interrupted\n"),
    signal.SIGTERM: (143, b"error: terminated (SIGTERM)\n"),
}
_installed: dict[int, Any] = {}


def _is_command_line() -> bool:
    main = sys.modules.get("__main__")
    name = os.path.basename(getattr(main, "__file__", None) or "")
    return (
        name.split(".")[0] in ("misdirect", "misdirect-script")
        and not sys.flags.interactive
        and threading.current_thread() is threading.main_thread()
    )


def _quit(signum: int, frame: Any) -> None:
    code, line = _CODES.get(signum, (128 + signum, b"error: interrupted\n"))
    try:
        os.write(2, line)
    finally:
        os._exit(code)


def release() -> None:
    """Give SIGINT and SIGTERM back (Python's defaults) once the command line is imported."""
    for signum, previous in _installed.items():
        if signal.getsignal(signum) is _quit:
            signal.signal(signum, previous)
    _installed.clear()


if _is_command_line():
    for _signum in _CODES:
        _installed[_signum] = signal.signal(_signum, _quit)
