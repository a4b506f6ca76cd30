"""Many right-hand sides through one sparse LU (core.lu_solve), against dense solves."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from misdirect.core.lu_solve import MANY_COLUMNS, solve_many
from misdirect.core.reachability import factorise
from misdirect.scenarios import sensor_grid


def _substochastic(n: int, seed: int) -> sp.csr_matrix:
    """A random chain that leaks a little from every state (``I − a`` non-singular)."""
    rng = np.random.default_rng(seed)
    a = sp.random(n, n, density=4 / n, random_state=rng, format="csr")
    a = a + sp.diags(rng.random(n))
    rows = np.asarray(a.sum(axis=1)).ravel()
    return sp.csr_matrix(sp.diags(0.95 / rows) @ a)


@pytest.mark.parametrize("columns", [1, MANY_COLUMNS - 1, MANY_COLUMNS, 300, 700])
@pytest.mark.parametrize("seed", [0, 1])
def test_many_columns_equal_a_dense_solve(columns, seed):
    n = 400
    a = _substochastic(n, seed)
    b = np.random.default_rng(seed + 10).standard_normal((n, columns))
    expected = np.linalg.solve(np.eye(n) - a.toarray(), b)
    got = solve_many(factorise(a), b, threads=2)
    assert got.shape == b.shape
    np.testing.assert_allclose(got, expected, rtol=1e-10, atol=1e-10)


def test_a_chain_of_the_grid_with_its_partial_pivoting_fallback():
    """On a product chain (the factorisation the solvers use), and on SuperLU's default one
    with partial pivoting (row and column permutations differ): both equal SuperLU's own
    solve to rounding."""
    from scipy.sparse.linalg import splu

    from misdirect.core.attack import prepare
    from misdirect.solvers.engines.lowrank import LowRankEnumeration, selected_groups

    instance = prepare(sensor_grid(12, 8, seed=1), 1)
    chain, live = instance.chain, instance.live
    enumeration = LowRankEnumeration(instance)
    chosen = np.zeros(chain.options.size, dtype=bool)
    chosen[enumeration.first_option[:-1]] = True  # every sensor unaltered
    a = enumeration._inside[selected_groups(chain, live, chosen)]
    n = a.shape[0]
    b = np.zeros((n, 100))
    b[np.arange(100) * (n // 100), np.arange(100)] = 1.0
    for lu in (factorise(a), splu(sp.csc_matrix(sp.identity(n) - a))):
        got = solve_many(lu, b, threads=1)
        np.testing.assert_allclose(got, lu.solve(b), rtol=1e-12, atol=1e-14)
