"""Dense algebra of small matrices on one BLAS thread.

misdirect's dense steps are many small products and inverses (tens to a few hundred rows),
often from two worker threads of its own. OpenBLAS's threads then spin for cores that the
workers (or other processes) hold: measured on 2 cores, a stack of 34 products of 27x27 by
27x928 took 0.54 s with OpenBLAS's 2 threads beside one busy process, 8 ms on one
(bench/results/enumeration). Every engine that does such algebra runs it under
:func:`one_blas_thread`. The limit is process-wide (threadpoolctl sets OpenBLAS's own
setting), so it is taken by the thread that starts the workers, around all of them, never
inside a worker.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

from threadpoolctl import threadpool_limits


@contextmanager
def one_blas_thread() -> Iterator[None]:
    """BLAS and LAPACK on one thread for the block (restored after it)."""
    with threadpool_limits(limits=1, user_api="blas"):
        yield
