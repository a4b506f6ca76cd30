"""The memory guard: refuse early, with the size, work that certainly cannot fit in memory.

A model or product chain too large for the machine would otherwise end in the kernel's OOM
killer or in swapping, not in one clear line. Building the product chain (``core.product``)
and compiling a problem file (``io.problem_file``) both ask before they allocate, so the guard
lives here, below both; so do the choice product, the MILP formulations and the MILP
backends, each with its own estimate. The limit is what Linux reports as available, or the
``MISDIRECT_MEMORY_LIMIT`` environment variable (the CLI's ``--memory-limit``) when set.
"""

from __future__ import annotations

import contextlib
import math
import os
import re
from pathlib import Path

from misdirect.errors import ProblemError

MEMORY_CHECK_FLOOR = 256 * 1024**2  # below this, an allocation is not checked against memory


def available_cores() -> int:
    """Cores this process may run on: its CPU affinity (a batch job's share of a node, not the
    node's), where the platform tells it, else the machine's count."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on every platform
        return os.cpu_count() or 1


def available_memory() -> int | None:
    """Bytes this process can still allocate, as far as Linux tells (MemAvailable, and the
    cgroup v2 limit if one is set); None where it cannot be read."""
    values = []
    with contextlib.suppress(OSError, ValueError), open("/proc/meminfo", encoding="ascii") as f:
        for line in f:
            if line.startswith("MemAvailable:"):
                values.append(int(line.split()[1]) * 1024)
                break
    with contextlib.suppress(OSError, ValueError):
        limit = Path("/sys/fs/cgroup/memory.max").read_text().strip()
        used = Path("/sys/fs/cgroup/memory.current").read_text().strip()
        if limit != "max":
            values.append(max(int(limit) - int(used), 0))
    return min(values) if values else None


MEMORY_LIMIT_ENV = "MISDIRECT_MEMORY_LIMIT"  # bytes (or 512M, 8G, 1.5GiB): overrides the default
_UNITS = {"": 1, "k": 1024, "m": 1024**2, "g": 1024**3, "t": 1024**4}


def parse_memory_size(text: str, *, field: str = MEMORY_LIMIT_ENV) -> int:
    """``8G``, ``512MiB``, ``1.5g`` or a number of bytes, as bytes (binary units)."""
    match = re.fullmatch(r"\s*([0-9]+(?:\.[0-9]*)?(?:e[0-9]+)?)\s*([kmgt]?)(?:i?b)?\s*", text, re.I)
    if match is None:
        raise ProblemError(f"expected a size such as 8G or 512M, got {text!r}", field=field)
    value = float(match.group(1)) * _UNITS[match.group(2).lower()]
    if not (math.isfinite(value) and value >= 1):
        raise ProblemError(
            f"expected a positive size such as 8G or 512M, got {text!r}", field=field
        )
    return int(value)


def memory_limit() -> tuple[int | None, str]:
    """The bytes work may take (None: unknown) and where that limit comes from: the
    ``MISDIRECT_MEMORY_LIMIT`` environment variable (the CLI's ``--memory-limit`` sets it),
    else what Linux says is available."""
    given = os.environ.get(MEMORY_LIMIT_ENV)
    if given:
        return parse_memory_size(given), MEMORY_LIMIT_ENV
    return available_memory(), "available"


def check_memory(needed: float, what: str, *, field: str | None = None) -> None:
    """Refuse early (ProblemError), with the estimate and the limit, when ``needed`` bytes
    are more than the memory limit (:func:`memory_limit`)."""
    explicit = bool(os.environ.get(MEMORY_LIMIT_ENV))
    if needed < MEMORY_CHECK_FLOOR and not explicit:  # small: never worth a look at /proc
        return
    limit, source = memory_limit()
    if limit is not None and needed > limit:
        where = (
            f"the limit of {_gib(limit)} (--memory-limit or {MEMORY_LIMIT_ENV})"
            if source == MEMORY_LIMIT_ENV
            else f"the {_gib(limit)} available (--memory-limit or {MEMORY_LIMIT_ENV} sets a limit)"
        )
        raise ProblemError(
            f"{what} needs about {_gib(needed)} of memory, more than {where}", field=field
        )


def _gib(value: float) -> str:
    if not math.isfinite(value):
        return "unbounded memory"
    gib = value / 1024**3
    return f"{gib:,.1f} GiB" if gib >= 0.1 else f"{gib:.2g} GiB"
