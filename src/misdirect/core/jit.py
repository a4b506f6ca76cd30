"""numba's compiled loops, cached wherever a cache can be written.

numba keeps compiled code beside the source (``__pycache__``) or in the user's cache folder. A
read-only install with a read-only HOME has neither, and numba then refuses ``cache=True``
with a RuntimeError as the module is imported: every command would die at start. So
:func:`njit` falls back to a private folder in the temporary directory, and where even that
cannot be written, to no cache (the loop is compiled on its first use in each process).
``NUMBA_CACHE_DIR``, when set, is numba's and taken as it is.
"""

from __future__ import annotations

import contextlib
import os
import stat
import tempfile
from collections.abc import Callable
from typing import Any

import numba
from numba.core import config as numba_config


def njit(**options: Any) -> Callable[[Callable[..., Any]], Any]:
    """``numba.njit(**options)``, with ``cache=True`` falling back as the module explains."""

    def decorate(function: Callable[..., Any]) -> Any:
        try:
            return numba.njit(**options)(function)
        except RuntimeError as error:  # "cannot cache function ...: no locator available"
            if not options.get("cache") or "cannot cache" not in str(error):
                raise
        folder = _private_cache_dir()
        if folder is not None:
            previous = numba_config.CACHE_DIR  # type: ignore[attr-defined]
            # read as the function is decorated, then restored (numba declares no types)
            numba_config.CACHE_DIR = folder  # type: ignore[attr-defined]
            try:
                return numba.njit(**options)(function)
            except RuntimeError:
                pass
            finally:
                numba_config.CACHE_DIR = previous  # type: ignore[attr-defined]
        return numba.njit(**{**options, "cache": False})(function)

    return decorate


def _private_cache_dir() -> str | None:
    """``<tmp>/misdirect-numba-<uid>``, made for this user alone (mode 700); None where it
    cannot be made, or is not a folder of this user's (a shared temporary directory)."""
    uid = os.getuid() if hasattr(os, "getuid") else 0
    folder = os.path.join(tempfile.gettempdir(), f"misdirect-numba-{uid}")
    with contextlib.suppress(OSError):
        os.mkdir(folder, 0o700)
    try:
        info = os.lstat(folder)
    except OSError:
        return None
    if not stat.S_ISDIR(info.st_mode) or (hasattr(os, "getuid") and info.st_uid != uid):
        return None
    return folder
