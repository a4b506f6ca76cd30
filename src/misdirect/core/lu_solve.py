"""Many right-hand sides through one sparse LU: the triangular solves as one compiled loop.

The low-rank enumeration solves its base chain for a unit column per row it may alter
(thousands on a big map). SuperLU's own solve sweeps its factors once per column; here each
entry of ``L`` and ``U`` is read once per block of columns and applied to the whole row of the
block (contiguous, so the inner loop vectorises), and the blocks run on threads (the loop holds
no GIL). The arithmetic is SuperLU's: the same factors, the same eliminations per column, so
the same rounding up to the order of additions. Measured in docs/benchmarks.md (H5).
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import SuperLU

from misdirect.core.jit import njit
from misdirect.core.memory import available_cores

MANY_COLUMNS = 32  # from this many right-hand sides on, the compiled loop
BLOCK_COLUMNS = 128  # columns per block: a row of one is 1 KiB, read whole per entry of L, U


@njit(cache=True, nogil=True)
def _substitute(
    l_indptr: np.ndarray,
    l_indices: np.ndarray,
    l_data: np.ndarray,
    u_indptr: np.ndarray,
    u_indices: np.ndarray,
    u_data: np.ndarray,
    u_diagonal: np.ndarray,
    x: np.ndarray,
) -> None:  # pragma: no cover (compiled; tested against SuperLU's solve and dense solves)
    """``x ← U⁻¹ L⁻¹ x`` in place, for CSC factors (``L`` unit lower triangular: its
    diagonal is not read) and a row-major block ``x``."""
    n, k = x.shape
    for j in range(n):
        for p in range(l_indptr[j], l_indptr[j + 1]):
            i = l_indices[p]
            if i > j:
                v = l_data[p]
                for c in range(k):
                    x[i, c] -= v * x[j, c]
    for j in range(n - 1, -1, -1):
        d = u_diagonal[j]
        for c in range(k):
            x[j, c] /= d
        for p in range(u_indptr[j], u_indptr[j + 1]):
            i = u_indices[p]
            if i < j:
                v = u_data[p]
                for c in range(k):
                    x[i, c] -= v * x[j, c]


def solve_many(lu: SuperLU, b: np.ndarray, threads: int | None = None) -> np.ndarray:
    """``A⁻¹ b`` for the matrix ``A`` that ``lu`` factorises and a block ``b`` (n, k):
    SuperLU's solve for few columns, the compiled loop for many."""
    b = np.asarray(b, dtype=np.float64)
    if b.ndim != 2 or b.shape[1] < MANY_COLUMNS:
        return np.asarray(lu.solve(b))
    n, k = b.shape
    # Pr A Pc = L U: A x = b is L U (Pcᵀ x) = Pr b, and (Pr b)[perm_r[i]] = b[i]
    lower, upper = sp.csc_matrix(lu.L), sp.csc_matrix(lu.U)
    factors = (
        lower.indptr.astype(np.int64),
        lower.indices.astype(np.int64),
        lower.data,
        upper.indptr.astype(np.int64),
        upper.indices.astype(np.int64),
        upper.data,
        upper.diagonal(),
    )
    row_of = np.empty(n, dtype=np.int64)
    row_of[lu.perm_r] = np.arange(n)
    solved = np.empty_like(b)

    def solve_block(first: int) -> None:
        # one block at a time: the memory beyond ``b`` and the answer is a block per thread
        block = b[row_of, first : first + BLOCK_COLUMNS]  # a C-ordered copy, Pr applied
        _substitute(*factors, block)
        solved[:, first : first + BLOCK_COLUMNS] = block[lu.perm_c]

    firsts = range(0, k, BLOCK_COLUMNS)
    workers = max(1, min(threads or available_cores(), len(firsts)))
    if workers == 1:
        for first in firsts:
            solve_block(first)
    else:
        with ThreadPoolExecutor(workers) as pool:
            list(pool.map(solve_block, firsts))
    return solved
