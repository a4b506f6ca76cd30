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

The factors are dense (two ``m x m`` arrays): :data:`MAX_STATES` bounds the chains they serve.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from misdirect.core.jit import njit

MAX_STATES = 3_000  # unknown states: the dense factors take 16 m² bytes (144 MB here)
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


@njit(cache=True, nogil=True)
def _factorise(
    qh: np.ndarray, ql: np.ndarray, lh: np.ndarray, ll: np.ndarray
) -> None:  # pragma: no cover (compiled)
    """In place: the elimination of ``q = qh + ql`` (row ``k`` keeps ``q_kj`` for ``j > k``,
    column ``k`` below it the multipliers ``q_ik / s_k``, the diagonal the pivots ``s_k``);
    ``l = lh + ll``: each row's mass to the known states, updated as states go. Row ``k``'s
    nonzero columns are listed once per pivot, so each row it updates costs its nonzeros,
    not ``m`` (a chain's factors are mostly zeros)."""
    m = qh.shape[0]
    columns = np.empty(m, dtype=np.int64)
    for k in range(m):
        sh, sl = lh[k], ll[k]
        count = 0
        for j in range(k + 1, m):
            if qh[k, j] != 0.0:
                sh, sl = _add(sh, sl, qh[k, j], ql[k, j])
                columns[count] = j
                count += 1
        qh[k, k], ql[k, k] = sh, sl
        if sh == 0.0:
            continue  # a closed class: its states never leave (the caller refuses it)
        for i in range(k + 1, m):
            if qh[i, k] == 0.0:
                continue
            fh, fl = _div(qh[i, k], ql[i, k], sh, sl)
            qh[i, k], ql[i, k] = fh, fl
            if lh[k] != 0.0:
                th, tl = _mul(fh, fl, lh[k], ll[k])
                lh[i], ll[i] = _add(lh[i], ll[i], th, tl)
            for c in range(count):
                j = columns[c]
                if j != i:
                    th, tl = _mul(fh, fl, qh[k, j], ql[k, j])
                    qh[i, j], ql[i, j] = _add(qh[i, j], ql[i, j], th, tl)


@njit(cache=True, nogil=True)
def _solve(
    qh: np.ndarray, ql: np.ndarray, bh: np.ndarray, bl: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:  # pragma: no cover (compiled)
    """``(I − Q)⁻¹ b`` for a nonnegative ``b = bh + bl``, from :func:`_factorise`."""
    m = qh.shape[0]
    yh, yl = bh.copy(), bl.copy()
    for k in range(m):
        if yh[k] == 0.0:
            continue
        for i in range(k + 1, m):
            if qh[i, k] != 0.0:
                th, tl = _mul(qh[i, k], ql[i, k], yh[k], yl[k])
                yh[i], yl[i] = _add(yh[i], yl[i], th, tl)
    xh, xl = np.zeros(m), np.zeros(m)
    for k in range(m - 1, -1, -1):
        ah, al = yh[k], yl[k]
        for j in range(k + 1, m):
            if qh[k, j] != 0.0 and xh[j] != 0.0:
                th, tl = _mul(qh[k, j], ql[k, j], xh[j], xl[j])
                ah, al = _add(ah, al, th, tl)
        xh[k], xl[k] = _div(ah, al, qh[k, k], ql[k, k])
    return xh, xl


@njit(cache=True, nogil=True)
def _factorise_double(q: np.ndarray, leak: np.ndarray) -> None:  # pragma: no cover (compiled)
    """:func:`_factorise` in doubles: the same elimination, every operation one rounding."""
    m = q.shape[0]
    columns = np.empty(m, dtype=np.int64)
    for k in range(m):
        s = leak[k]
        count = 0
        for j in range(k + 1, m):
            if q[k, j] != 0.0:
                s += q[k, j]
                columns[count] = j
                count += 1
        q[k, k] = s
        if s == 0.0:
            continue
        for i in range(k + 1, m):
            if q[i, k] == 0.0:
                continue
            f = q[i, k] / s
            q[i, k] = f
            if leak[k] != 0.0:
                leak[i] += f * leak[k]
            for c in range(count):
                j = columns[c]
                if j != i:
                    q[i, j] += f * q[k, j]


@njit(cache=True, nogil=True)
def _solve_double(q: np.ndarray, b: np.ndarray) -> np.ndarray:  # pragma: no cover (compiled)
    """:func:`_solve` in doubles, from :func:`_factorise_double`."""
    m = q.shape[0]
    y = b.copy()
    for k in range(m):
        if y[k] == 0.0:
            continue
        for i in range(k + 1, m):
            if q[i, k] != 0.0:
                y[i] += q[i, k] * y[k]
    x = np.zeros(m)
    for k in range(m - 1, -1, -1):
        a = y[k]
        for j in range(k + 1, m):
            if q[k, j] != 0.0 and x[j] != 0.0:
                a += q[k, j] * x[j]
        x[k] = a / q[k, k]
    return x


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
    ):
        """``q``: transitions among the unknown states (``m x m``, nonnegative, as loaded);
        ``leak``: per state, its mass to the known states as a double-double, summed from
        those entries (not ``1 − Σ q``)."""
        dense = np.array(q, dtype=np.float64) if isinstance(q, np.ndarray) else q.toarray()
        self.high = np.ascontiguousarray(dense, dtype=np.float64)
        self.extended = extended
        if extended:
            self.low = np.zeros_like(self.high)
            _factorise(self.high, self.low, leak[0].astype(np.float64), leak[1].astype(np.float64))
        else:
            _factorise_double(self.high, (leak[0] + leak[1]).astype(np.float64))
        self.proper = bool((np.diag(self.high) > 0).all())

    def solve(self, b: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """``(I − Q)⁻¹ b`` for a nonnegative double-double ``b``, as a double-double (its low
        part zero in doubles)."""
        if not self.extended:
            x = _solve_double(self.high, (b[0] + b[1]).astype(np.float64))
            return x, np.zeros_like(x)
        high, low = _solve(self.high, self.low, b[0].astype(np.float64), b[1].astype(np.float64))
        return high, low


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
