"""Exact rational linear algebra for the tests' references (no floating point anywhere)."""

from __future__ import annotations

from fractions import Fraction


def gauss_jordan(a: list[list[Fraction]], b: list[Fraction]) -> list[Fraction]:
    """The solution of ``a x = b`` (``a`` non-singular), by Gauss-Jordan in Fractions."""
    n = len(b)
    m = [[*a[i], b[i]] for i in range(n)]
    for c in range(n):
        pivot = next(r for r in range(c, n) if m[r][c] != 0)
        m[c], m[pivot] = m[pivot], m[c]
        for r in range(n):
            if r != c and m[r][c] != 0:
                f = m[r][c] / m[c][c]
                m[r] = [x - f * y for x, y in zip(m[r], m[c], strict=True)]
    return [m[i][n] / m[i][i] for i in range(n)]
