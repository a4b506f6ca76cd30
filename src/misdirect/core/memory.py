"""The memory guard: refuse early, with the size, work that certainly cannot fit in memory.

A model or product chain too large for the machine would otherwise end in the kernel's OOM
killer or in swapping, not in one clear line. Building the product chain (``core.product``)
and compiling a problem file (``io.problem_file``) both ask before they allocate, so the guard
lives here, below both. It reads only what Linux reports about available memory.
"""

from __future__ import annotations

import contextlib
import math
from pathlib import Path

from misdirect.errors import ProblemError

MEMORY_CHECK_FLOOR = 256 * 1024**2  # below this, an allocation is not checked against memory


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


def check_memory(needed: float, what: str, *, field: str | None = None) -> None:
    """Refuse early (ProblemError) when ``needed`` bytes are certainly not available."""
    if needed < MEMORY_CHECK_FLOOR:  # small: never worth a look at /proc
        return
    available = available_memory()
    if available is not None and needed > available:
        raise ProblemError(
            f"{what} needs about {_gib(needed)} of memory, more than the "
            f"{_gib(available)} available",
            field=field,
        )


def _gib(value: float) -> str:
    return f"{value / 1024**3:,.1f} GiB" if math.isfinite(value) else "unbounded memory"
