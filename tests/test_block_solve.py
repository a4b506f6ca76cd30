"""The structured solvers (components, bands, separator) agree with a dense solve."""

import numpy as np
import pytest
import scipy.sparse as sp

import misdirect.core.reachability as reachability
from misdirect.core.evaluate import decoy_probability
from misdirect.core.product import build_product
from misdirect.core.reachability import prob0_prob1, solve_topological, solve_with_separator
from misdirect.scenarios import paper_grid, random_problem


def _system(problem, alteration):
    chain = build_product(problem, alteration)
    target = problem.decoy[chain.world_state]
    prob0, prob1 = prob0_prob1(chain.matrix, target)
    maybe = np.flatnonzero(~prob0 & ~prob1)
    rows = chain.matrix[maybe]
    b = np.asarray(rows[:, np.flatnonzero(prob1)].sum(axis=1)).ravel()
    return rows[:, maybe], b, chain.node[maybe]


def _dense(a, b):
    return np.linalg.solve(np.eye(a.shape[0]) - a.toarray(), b)


def _layered_chain(seed: int, layers: int = 30) -> sp.csr_matrix:
    """A substochastic chain of layers that only lead forward: cycles inside layers only.

    Layer sizes mix singletons, small dense clusters and long corridors (bandwidth 1, 2 or a
    wide one), so every route of :func:`solve_topological` runs. The layers are shuffled (each
    keeps its own state order) so that the solver has to find the order itself. Every row
    loses mass, so ``I - a`` is an M-matrix.
    """
    rng = np.random.default_rng(seed)
    sizes = rng.choice([1, 3, 40, 70], size=layers, p=[0.3, 0.3, 0.2, 0.2])
    starts = np.concatenate(([0], np.cumsum(sizes)))
    n = int(starts[-1])
    rows, cols, vals = [], [], []
    for layer, size in enumerate(sizes):
        first = starts[layer]
        reach = rng.choice([1, 2, 12]) if size > 3 else size
        for i in range(size):
            for j in range(max(0, i - reach), min(size, i + reach + 1)):
                if i != j or rng.random() < 0.3:
                    rows.append(first + i)
                    cols.append(first + j)
                    vals.append(rng.random())
            if layer + 1 < layers:  # one or two edges to later layers
                for _ in range(rng.integers(1, 3)):
                    rows.append(first + i)
                    cols.append(rng.integers(starts[layer + 1], n))
                    vals.append(rng.random())
    a = sp.csr_matrix((vals, (rows, cols)), shape=(n, n))
    a = sp.diags(rng.uniform(0.5, 0.99, n) / np.maximum(a.sum(axis=1).A1, 1e-12)) @ a
    shuffle = np.concatenate([np.arange(starts[k], starts[k + 1]) for k in rng.permutation(layers)])
    return a[shuffle][:, shuffle].tocsr()


def test_components_and_bands_equal_a_dense_solve(monkeypatch):
    monkeypatch.setattr(reachability, "CHUNK_STATES", 50)  # several sparse chunks too
    routes = {"band": 0, "sparse": 0}
    real_band, real_lu = reachability.dgbsv, reachability._lu

    def band(*args):
        routes["band"] += 1
        return real_band(*args)

    def lu(*args):
        routes["sparse"] += 1
        return real_lu(*args)

    monkeypatch.setattr(reachability, "dgbsv", band)
    monkeypatch.setattr(reachability, "_lu", lu)
    many = reachability.MANY_COLUMNS + 8  # the chunks' compiled loop over their factors
    for seed in range(8):
        a = _layered_chain(seed)
        rng = np.random.default_rng(100 + seed)
        b = rng.random(a.shape[0])
        rhs = rng.random((a.shape[0], 3))
        wide = rng.random((a.shape[0], many))
        system = sp.identity(a.shape[0]) - a
        single = solve_topological(system, b)
        several = solve_topological(system, rhs)
        all_of_them = solve_topological(system, wide)
        assert single is not None and several is not None and all_of_them is not None
        assert np.abs(single - _dense(a, b)).max() < 1e-12
        assert np.abs(several - _dense(a, rhs)).max() < 1e-12
        assert np.abs(all_of_them - _dense(a, wide)).max() < 1e-12
    assert routes["band"] >= 8 and routes["sparse"] >= 8  # both routes really ran


def test_one_big_component_is_declined():
    a = _layered_chain(0)
    strongly_connected = sp.csr_matrix(a + 0.01 * sp.random(*a.shape, density=0.5, random_state=1))
    assert solve_topological(sp.identity(a.shape[0]) - strongly_connected * 0.5, a[0]) is None


@pytest.mark.parametrize("n", [5, 9, 40])
def test_grid_separator_equals_a_dense_solve(n):
    """n = 40: grid columns and rows are corridors of 40 states, so the banded route runs."""
    problem = paper_grid(n)
    for alteration in (problem.identity(), problem.alteration({"o1": "o2", "o2": "o0"})):
        a, b, nodes = _system(problem, alteration)
        by_parts = solve_with_separator(a, b, nodes)
        assert by_parts is not None  # the grid's controller changes node at sensors only
        assert np.abs(by_parts - _dense(a, b)).max() < 1e-12


def test_random_models_through_the_structured_paths(monkeypatch):
    """With the size threshold off, every evaluation that can split does; values unchanged."""
    problems = [random_problem(seed, states=12, nodes=3) for seed in range(60)]
    alterations = [p.identity() for p in problems]
    before = [decoy_probability(p, a) for p, a in zip(problems, alterations, strict=True)]
    split = []
    real = reachability.solve_with_separator

    def spy(*args):
        result = real(*args)
        split.append(result is not None)
        return result

    monkeypatch.setattr(reachability, "DIRECT_MAX_STATES", 0)
    monkeypatch.setattr(reachability, "DENSE_MAX_STATES", 0)
    monkeypatch.setattr(reachability, "solve_with_separator", spy)
    after = [decoy_probability(p, a) for p, a in zip(problems, alterations, strict=True)]
    assert after == pytest.approx(before, abs=1e-12)
    assert sum(split) >= 10  # the separator path really ran, not only the fallback


def test_a_large_separator_is_declined(monkeypatch):
    a, b, nodes = _system(paper_grid(9), paper_grid(9).identity())
    monkeypatch.setattr(reachability, "SEPARATOR_MAX", 0)
    assert solve_with_separator(a, b, nodes) is None
