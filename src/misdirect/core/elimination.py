"""State elimination without subtraction (Grassmann, Taksar and Heyman) in double-double: the
value of an absorbing chain however long it runs.

A chain whose runs take 10^15 steps to be absorbed makes ``I − Q`` ill-conditioned: LU in
double precision computes each pivot ``1 − q_kk`` by a subtraction that loses every digit, and
iterative refinement with those factors no longer converges. Here the pivot of a state is its
*outgoing* mass instead, summed from the entries of its row that leave it (the unknown states
still to eliminate, and the exit to the known states), never ``1 − q_kk``: the value of the
*jump chain*, whose self-loops are what the other entries leave. Every operation adds,
multiplies or divides nonnegative numbers, so nothing cancels, and a solve with a nonnegative
right-hand side keeps its digits whatever the condition number (on a drone chain absorbed
after 2.75·10^15 steps, LU gave 1.0 and elimination 0.9633149657054454; Storm's exact answer
on the model's rational probabilities is 0.9633149657054453).

The factors are sparse, computed row by row (each row gathered into a dense work row, its
pivots taken in increasing order from a bit set), so the work is the fill's, not ``m²``. Any
order of elimination is valid for an absorbing chain; a fill-reducing one (the symmetric
minimum-degree order of the LU the caller already has) roughly halves the work on the drone's
chains. :data:`MAX_STATES`, :data:`MAX_FILL` and :data:`MAX_UPDATES` bound what one
elimination may cost.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import splu

from misdirect.core.jit import njit

MAX_STATES = 20_000  # unknown states one elimination takes on
MAX_FILL = 5_000_000  # entries of the factors (24 bytes each in double-double): then it gives up
MAX_UPDATES = 100_000_000  # ... and after this many updates of an entry (about a second)
_SPLITTER = 134217729.0  # 2^27 + 1 (Dekker's split)


@njit(cache=True, nogil=True, inline="always")
def _two_sum(a: float, b: float) -> tuple[float, float]:  # pragma: no cover (compiled)
    s = a + b
    bb = s - a
    return s, (a - (s - bb)) + (b - bb)


@njit(cache=True, nogil=True, inline="always")
def _two_product(a: float, b: float) -> tuple[float, float]:  # pragma: no cover (compiled)
    p = a * b
    c = _SPLITTER * a
    a_hi = c - (c - a)
    a_lo = a - a_hi
    c = _SPLITTER * b
    b_hi = c - (c - b)
    b_lo = b - b_hi
    return p, a_lo * b_lo - (((p - a_hi * b_hi) - a_lo * b_hi) - a_hi * b_lo)


@njit(cache=True, nogil=True, inline="always")
def _add(ah: float, al: float, bh: float, bl: float) -> tuple[float, float]:  # pragma: no cover
    s, e = _two_sum(ah, bh)
    e += al + bl
    high, low = _two_sum(s, e)
    return high, low


@njit(cache=True, nogil=True, inline="always")
def _mul(ah: float, al: float, bh: float, bl: float) -> tuple[float, float]:  # pragma: no cover
    p, e = _two_product(ah, bh)
    e += ah * bl + al * bh
    high, low = _two_sum(p, e)
    return high, low


@njit(cache=True, nogil=True, inline="always")
def _div(ah: float, al: float, bh: float, bl: float) -> tuple[float, float]:  # pragma: no cover
    q1 = ah / bh
    ph, pl = _mul(q1, 0.0, bh, bl)
    rh, _ = _add(ah, al, -ph, -pl)
    q2 = rh / bh
    high, low = _two_sum(q1, q2)
    return high, low


_DE_BRUIJN = 0x03F79D71B4CB0A89  # a de Bruijn sequence: each bit's product has its own top 6 bits
_DE_BRUIJN_INDEX = np.zeros(64, dtype=np.int64)  # ... which name the bit
_DE_BRUIJN_INDEX[[((1 << b) * _DE_BRUIJN % 2**64) >> 58 for b in range(64)]] = np.arange(64)


@njit(cache=True, nogil=True, inline="always")
def _mark(bits: np.ndarray, j: int) -> None:  # pragma: no cover (compiled)
    bits[j >> 6] |= np.uint64(1) << np.uint64(j & 63)


@njit(cache=True, nogil=True)
def _grown(a: np.ndarray, need: int) -> np.ndarray:  # pragma: no cover (compiled)
    if need <= a.size:
        return a
    bigger = np.empty(max(need, 2 * a.size), dtype=a.dtype)
    bigger[: a.size] = a
    return bigger


@njit(cache=True, nogil=True)
def _factorise(
    indptr: np.ndarray,
    indices: np.ndarray,
    data: np.ndarray,
    leak_h: np.ndarray,
    leak_l: np.ndarray,
    extended: bool,
    max_fill: int,
    max_updates: int,
) -> tuple[np.ndarray, ...]:  # pragma: no cover (compiled)
    """The elimination of ``Q`` (CSR, diagonal ignored), row by row.

    Row ``i`` is gathered into a dense work row; its entries below the diagonal are taken in
    increasing column order ``k`` (a bit set, which fill joins), each becomes the multiplier
    ``q_ik / s_k`` and adds its multiple of row ``k``'s upper part (its self-loop dropped:
    the jump chain) and of ``k``'s mass to the known states (``leak``, updated in place).
    The pivot ``s_i`` is then that mass plus the row's upper part, summed in increasing
    column order. Each entry receives the same operations in the same order as the dense
    right-looking elimination, so the factors are the same to the bit. ``extended``: in
    double-double (``*_l`` the low parts; in doubles they stay unused). Returns the lower
    and upper factors as CSR arrays and the pivots, or empty arrays once the factors would
    hold more than ``max_fill`` entries or take more than ``max_updates`` updates."""
    m = indptr.size - 1
    work_h, work_l = np.zeros(m), np.zeros(m)
    seen = np.full(m, -1, dtype=np.int64)  # the row that last touched each column
    # the row's columns below the diagonal still to take, one bit each: taken in increasing
    # order by scanning the words forward (fill only ever lands after the column taken)
    pending = np.zeros((m >> 6) + 1, dtype=np.uint64)
    above = np.zeros_like(pending)  # the row's columns above the diagonal, one bit each
    capacity = max(16, 4 * indices.size)
    lower_ptr = np.zeros(m + 1, dtype=np.int64)
    lower_idx = np.empty(capacity, dtype=np.int64)
    lower_h = np.empty(capacity)
    lower_l = np.empty(capacity if extended else 1)
    upper_ptr = np.zeros(m + 1, dtype=np.int64)
    upper_idx = np.empty(capacity, dtype=np.int64)
    upper_h = np.empty(capacity)
    upper_l = np.empty(capacity if extended else 1)
    pivot_h, pivot_l = np.zeros(m), np.zeros(m)
    updates = 0
    for i in range(m):
        word = m  # the first word with a pending column
        n_upper = 0
        for p in range(indptr[i], indptr[i + 1]):
            j = indices[p]
            if j == i or data[p] == 0.0:
                continue
            work_h[j], work_l[j] = data[p], 0.0
            seen[j] = i
            if j < i:
                _mark(pending, j)
                word = min(word, j >> 6)
            else:
                _mark(above, j)
                n_upper += 1
        sh, sl = leak_h[i], leak_l[i]
        n_lower = lower_ptr[i]
        last_word = i >> 6
        while word <= last_word:
            bits = pending[word]
            if bits == 0:
                word += 1
                continue
            lowest = bits & (~bits + np.uint64(1))
            pending[word] = bits ^ lowest
            k = (word << 6) + _DE_BRUIJN_INDEX[(lowest * np.uint64(_DE_BRUIJN)) >> np.uint64(58)]
            if work_h[k] == 0.0:
                continue
            if pivot_h[k] != 0.0:  # zero: a closed class (the caller refuses it)
                if extended:
                    fh, fl = _div(work_h[k], work_l[k], pivot_h[k], pivot_l[k])
                else:
                    fh, fl = work_h[k] / pivot_h[k], 0.0
                work_h[k], work_l[k] = fh, fl
                if leak_h[k] != 0.0:
                    if extended:
                        th, tl = _mul(fh, fl, leak_h[k], leak_l[k])
                        sh, sl = _add(sh, sl, th, tl)
                    else:
                        sh += fh * leak_h[k]
                updates += upper_ptr[k + 1] - upper_ptr[k]
                for c in range(upper_ptr[k], upper_ptr[k + 1]):
                    j = upper_idx[c]
                    if j == i:
                        continue
                    if seen[j] != i:  # fill
                        seen[j] = i
                        work_h[j], work_l[j] = 0.0, 0.0
                        if j < i:
                            _mark(pending, j)
                        else:
                            _mark(above, j)
                            n_upper += 1
                    if extended:
                        th, tl = _mul(fh, fl, upper_h[c], upper_l[c])
                        work_h[j], work_l[j] = _add(work_h[j], work_l[j], th, tl)
                    else:
                        work_h[j] += fh * upper_h[c]
            if n_lower >= lower_idx.size:
                lower_idx = _grown(lower_idx, n_lower + 1)
                lower_h = _grown(lower_h, n_lower + 1)
                if extended:
                    lower_l = _grown(lower_l, n_lower + 1)
            lower_idx[n_lower] = k
            lower_h[n_lower] = work_h[k]
            if extended:
                lower_l[n_lower] = work_l[k]
            n_lower += 1
        lower_ptr[i + 1] = n_lower
        leak_h[i], leak_l[i] = sh, sl  # final: the rows below read it
        n_up = upper_ptr[i]
        if n_up + n_upper > upper_idx.size:
            upper_idx = _grown(upper_idx, n_up + n_upper)
            upper_h = _grown(upper_h, n_up + n_upper)
            if extended:
                upper_l = _grown(upper_l, n_up + n_upper)
        word = (i + 1) >> 6
        # in increasing column order; the same scan as the pivots' above, written out again:
        # as one helper returning a pair it compiles to a slower loop
        while n_upper > 0:
            bits = above[word]
            if bits == 0:
                word += 1
                continue
            lowest = bits & (~bits + np.uint64(1))
            above[word] = bits ^ lowest
            n_upper -= 1
            j = (word << 6) + _DE_BRUIJN_INDEX[(lowest * np.uint64(_DE_BRUIJN)) >> np.uint64(58)]
            if work_h[j] == 0.0:
                continue
            if extended:
                sh, sl = _add(sh, sl, work_h[j], work_l[j])
                upper_l[n_up] = work_l[j]
            else:
                sh += work_h[j]
            upper_idx[n_up] = j
            upper_h[n_up] = work_h[j]
            n_up += 1
        upper_ptr[i + 1] = n_up
        pivot_h[i], pivot_l[i] = sh, sl
        if n_lower + n_up > max_fill or updates > max_updates:
            none, nothing = np.empty(0, dtype=np.int64), np.empty(0)
            return none, none, nothing, nothing, none, none, nothing, nothing, nothing, nothing
    return (
        lower_ptr,
        lower_idx,
        lower_h,
        lower_l,
        upper_ptr,
        upper_idx,
        upper_h,
        upper_l,
        pivot_h,
        pivot_l,
    )


@njit(cache=True, nogil=True, inline="always")
def _add_row_product(
    ptr: np.ndarray,
    idx: np.ndarray,
    vh: np.ndarray,
    vl: np.ndarray,
    row: int,
    xh: np.ndarray,
    xl: np.ndarray,
    ah: float,
    al: float,
    extended: bool,
) -> tuple[float, float]:  # pragma: no cover (compiled)
    """``a + Σ v_c x_j`` over the entries ``c`` of row ``row`` of a CSR factor (``j`` their
    columns; zeros of ``x`` skipped), in double-double or, without ``extended``, doubles."""
    for c in range(ptr[row], ptr[row + 1]):
        j = idx[c]
        if xh[j] != 0.0:
            if extended:
                th, tl = _mul(vh[c], vl[c], xh[j], xl[j])
                ah, al = _add(ah, al, th, tl)
            else:
                ah += vh[c] * xh[j]
    return ah, al


@njit(cache=True, nogil=True)
def _solve(
    lower_ptr: np.ndarray,
    lower_idx: np.ndarray,
    lower_h: np.ndarray,
    lower_l: np.ndarray,
    upper_ptr: np.ndarray,
    upper_idx: np.ndarray,
    upper_h: np.ndarray,
    upper_l: np.ndarray,
    pivot_h: np.ndarray,
    pivot_l: np.ndarray,
    bh: np.ndarray,
    bl: np.ndarray,
    extended: bool,
) -> tuple[np.ndarray, np.ndarray]:  # pragma: no cover (compiled)
    """``(I − Q)⁻¹ b`` for a nonnegative ``b = bh + bl``, from :func:`_factorise`'s factors:
    forward through the multipliers, then back through the upper parts and the pivots."""
    m = pivot_h.size
    yh, yl = bh.copy(), bl.copy()
    for i in range(m):
        yh[i], yl[i] = _add_row_product(
            lower_ptr, lower_idx, lower_h, lower_l, i, yh, yl, yh[i], yl[i], extended
        )
    xh, xl = np.zeros(m), np.zeros(m)
    for k in range(m - 1, -1, -1):
        ah, al = _add_row_product(
            upper_ptr, upper_idx, upper_h, upper_l, k, xh, xl, yh[k], yl[k], extended
        )
        if extended:
            xh[k], xl[k] = _div(ah, al, pivot_h[k], pivot_l[k])
        else:
            xh[k] = ah / pivot_h[k]
    return xh, xl


class Elimination:
    """The factors of ``I − Q`` for an absorbing chain's unknown states, in double-double
    (``extended``) or in doubles.

    Both are free of cancellation. Doubles agree with double-double to a few units of
    roundoff on the drone chains (``tests/test_jump_chain.py``); a search that only ranks
    alterations by them takes doubles, while what a person reads takes double-double."""

    def __init__(
        self,
        q: sp.spmatrix | np.ndarray,
        leak: tuple[np.ndarray, np.ndarray],
        *,
        extended: bool = True,
        order: np.ndarray | None = None,
    ):
        """``q``: transitions among the unknown states (``m x m``, nonnegative, as loaded);
        ``leak``: per state, its mass to the known states as a double-double, summed from
        those entries (not ``1 − Σ q``); ``order``: the states in the order to eliminate
        them (default: as numbered). ``complete`` is False, and nothing can be solved, when
        the factors would hold more than :data:`MAX_FILL` entries or take more than
        :data:`MAX_UPDATES` updates."""
        rows = sp.csr_matrix(q, dtype=np.float64)
        leak_h = np.array(leak[0], dtype=np.float64)
        leak_l = np.array(leak[1], dtype=np.float64)
        if not extended:  # one double each
            leak_h, leak_l = leak_h + leak_l, np.zeros_like(leak_h)
        if order is not None:
            order = np.asarray(order, dtype=np.int64)
            rows = rows[order][:, order].tocsr()
            leak_h, leak_l = leak_h[order], leak_l[order]
        self.order = order
        self.extended = extended
        self._factors = _factorise(
            rows.indptr.astype(np.int64),
            rows.indices.astype(np.int64),
            rows.data,
            leak_h,
            leak_l,
            extended,
            MAX_FILL,
            MAX_UPDATES,
        )
        pivots = self._factors[-2]
        self.complete = pivots.size == rows.shape[0]
        self.proper = self.complete and bool((pivots > 0).all())

    def solve(self, b: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """``(I − Q)⁻¹ b`` for a nonnegative double-double ``b``, as a double-double (its low
        part zero in doubles)."""
        if not self.proper:
            raise ValueError("the chain has a closed class or its factors were cut short")
        high, low = np.asarray(b[0], dtype=np.float64), np.asarray(b[1], dtype=np.float64)
        if not self.extended:
            high, low = high + low, np.zeros_like(high)
        if self.order is not None:
            high, low = high[self.order], low[self.order]
        xh, xl = _solve(*self._factors, high, low, self.extended)
        if self.order is None:
            return xh, xl
        out_h, out_l = np.empty_like(xh), np.empty_like(xl)
        out_h[self.order], out_l[self.order] = xh, xl
        return out_h, out_l


@njit(cache=True, nogil=True)
def _row_products(
    indptr: np.ndarray, indices: np.ndarray, data: np.ndarray, z: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:  # pragma: no cover (compiled)
    n = indptr.size - 1
    high, low = np.zeros(n), np.zeros(n)
    for i in range(n):
        h, lo = 0.0, 0.0
        for p in range(indptr[i], indptr[i + 1]):
            if z[indices[p]] != 0.0:
                th, tl = _two_product(data[p], z[indices[p]])
                h, lo = _add(h, lo, th, tl)
        high[i], low[i] = h, lo
    return high, low


def row_products(rows: sp.csr_matrix, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``rows @ z`` as a double-double per row (for the nonnegative sums a solve starts from:
    a row's mass to the known states, its one-step value)."""
    high, low = _row_products(
        rows.indptr.astype(np.int64),
        rows.indices.astype(np.int64),
        rows.data.astype(np.float64),
        z.astype(np.float64),
    )
    return high, low


def fill_reducing_rank(pattern: sp.spmatrix) -> np.ndarray:
    """Each state's place in a fill-reducing order of elimination for chains whose transitions
    lie within ``pattern`` (SuperLU's minimum degree on ``A + Aᵀ``, the order its LU of such a
    chain takes; here of a diagonally dominant matrix of that pattern, which always has one).
    Computed once for a family of chains, it saves each of them an LU."""
    n = pattern.shape[0]
    edges = sp.csc_matrix(pattern, dtype=bool).astype(np.float64)
    system = (edges + edges.T + sp.identity(n, format="csc") * (n + 1.0)).tocsc()
    lu = splu(
        system, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options={"SymmetricMode": True}
    )
    return np.asarray(lu.perm_c, dtype=np.int64)
