"""Residuals of a linear system, computed far beyond double precision, with a proven bound.

Iterative refinement of a chain's solve needs the residual ``r = b - A x`` more accurately
than the double-precision ``x`` itself: on a chain absorbed after 10^9 steps the error of
``x`` is up to 10^9 times its residual, so the residual must be known to about 10^-20 to
prove 10^-11. Error-free transformations (Knuth's TwoSum, Dekker's TwoProduct with
Veltkamp's split) give every product and every partial sum exactly as two doubles; the
leading parts are summed exactly in a pairwise tree, the trailing ones in plain double, whose
rounding is second order. ``x`` itself is a double-double ``hi + lo``, so the refinement can
hold it to about 10^-32. Plain numpy, vectorised over all rows at once; no FMA is needed.
"""

from __future__ import annotations

from typing import cast

import numpy as np
import scipy.sparse as sp

UNIT_ROUNDOFF = 2.0**-53
_SPLITTER = 2.0**27 + 1.0  # Veltkamp: splits a double into two halves of 26 bits
# What an error-free transformation may lose to underflow, per product (Ogita, Rump and Oishi
# 2005 prove 5 · 2^-1074); a generous 2^-1000 keeps the bound simple and is still nothing.
_UNDERFLOW = 2.0**-1000


def two_sum(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``s + e == a + b`` exactly, ``s = fl(a + b)`` (Knuth; no branch, any order)."""
    s = a + b
    bb = s - a
    return s, (a - (s - bb)) + (b - bb)


def two_product(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``p + e == a * b`` exactly (barring underflow), ``p = fl(a * b)`` (Dekker)."""
    p = a * b
    a_hi, a_lo = _split(a)
    b_hi, b_lo = _split(b)
    return p, a_lo * b_lo - (((p - a_hi * b_hi) - a_lo * b_hi) - a_hi * b_lo)


def _split(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    c = _SPLITTER * a
    high = c - (c - a)
    return high, a - high


def add(hi: np.ndarray, lo: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The double-double ``hi + lo`` plus the double ``d``, renormalised (``|lo|`` about
    ``u |hi|``). Only the refinement's progress depends on its accuracy, never a bound: every
    bound is proven on the ``hi + lo`` actually stored."""
    s, e = two_sum(hi, d)
    return two_sum(s, e + lo)


def _tree_sum(
    values: np.ndarray, row: np.ndarray, n_rows: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Exact row sums of ``values`` (grouped by ``row``, ascending) as ``lead`` plus the
    returned ``errors`` (with their rows): TwoSum on neighbours, level by level, so a row of
    ``k`` terms takes ``log2 k`` vectorised levels. ``values`` is overwritten."""
    errors, error_rows = [], []
    while True:
        counts = np.bincount(row, minlength=n_rows)
        if counts.max(initial=0) <= 1:
            break
        position = np.arange(row.size) - (np.cumsum(counts) - counts)[row]
        head = position % 2 == 0
        paired = np.flatnonzero(head & (position + 1 < counts[row]))
        s, e = two_sum(values[paired], values[paired + 1])
        values[paired] = s
        errors.append(e)
        error_rows.append(row[paired])
        values, row = values[head], row[head]
    lead = np.zeros(n_rows)
    lead[row] = values
    empty = np.zeros(0)
    return (
        lead,
        np.concatenate(errors) if errors else empty,
        np.concatenate(error_rows) if error_rows else empty.astype(np.int64),
    )


def residual(
    rows: sp.csr_matrix,
    z_hi: np.ndarray,
    z_lo: np.ndarray,
    own: np.ndarray,
    const: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """``r = const + rows @ z - z[own]`` for the double-double ``z = z_hi + z_lo``: ``r``
    rounded to double, and a proven bound on ``|r|`` in exact arithmetic, row by row.

    Each product ``rows_ij z_hi_j`` is split exactly into ``p + e``; ``const``, ``-z_hi[own]``
    and the ``p`` are summed exactly (:func:`_tree_sum`); everything else (the ``e``, the tree's
    errors, ``rows @ z_lo`` and ``-z_lo[own]``, all about ``u`` times the leading terms) is
    summed in double, with Higham's bound ``γ_k Σ|terms|`` on its rounding.
    """
    n_rows = rows.shape[0]
    counts = np.diff(rows.indptr)
    p, e = two_product(rows.data, z_hi[rows.indices])
    # the exact terms, grouped by row: two of each row's own, then its products
    indptr = rows.indptr + 2 * np.arange(n_rows + 1)
    values = np.empty(p.size + 2 * n_rows)
    firsts = indptr[:-1]
    slot = np.ones(values.size, dtype=bool)
    slot[firsts] = slot[firsts + 1] = False
    values[slot] = p
    values[firsts] = 0.0 if const is None else const
    values[firsts + 1] = -z_hi[own]
    row_of = np.repeat(np.arange(n_rows), counts + 2)
    lead, errors, error_rows = _tree_sum(values, row_of, n_rows)
    small = rows @ z_lo  # rounded: γ_(k+1) (|rows| |z_lo|) at most
    small_bound = 1.01 * (counts + 1) * UNIT_ROUNDOFF * (abs(rows) @ np.abs(z_lo))
    low_terms = np.concatenate([e, errors, small, -z_lo[own]])
    low_rows = np.concatenate(
        [np.repeat(np.arange(n_rows), counts), error_rows, np.arange(n_rows), np.arange(n_rows)]
    )
    low = np.bincount(low_rows, weights=low_terms, minlength=n_rows)
    low_size = np.bincount(low_rows, weights=np.abs(low_terms), minlength=n_rows)
    terms = np.bincount(low_rows, minlength=n_rows)
    r = lead + low
    if not (np.isfinite(r).all() and np.isfinite(p).all() and np.isfinite(e).all()):
        return r, np.full(n_rows, np.inf)
    # |r_exact| <= |lead + low_exact| + rounding of the low sum and of rows @ z_lo + underflow;
    # |lead + low| <= |fl(lead + low)| (1 + 2u). Factors of 2 cover rounding in the bound itself.
    bound = (
        np.abs(r) * (1 + 4 * UNIT_ROUNDOFF)
        + 2.02 * terms * UNIT_ROUNDOFF * low_size
        + 2 * small_bound
        + _UNDERFLOW * (counts + 4)
    )
    return r, cast(np.ndarray, bound)
