"""Block elimination by memory node gives the same values as one LU, wherever it applies."""

import numpy as np
import pytest

import misdirect.reachability as reachability
from misdirect.evaluate import decoy_probability
from misdirect.product import build_product
from misdirect.reachability import prob0_prob1, solve_by_blocks
from misdirect.scenarios import paper_grid, random_problem


def _system(problem, alteration):
    chain = build_product(problem, alteration)
    target = problem.decoy[chain.world_state]
    prob0, prob1 = prob0_prob1(chain.matrix, target)
    maybe = np.flatnonzero(~prob0 & ~prob1)
    rows = chain.matrix[maybe]
    b = np.asarray(rows[:, np.flatnonzero(prob1)].sum(axis=1)).ravel()
    return rows[:, maybe], b, chain.node[maybe]


@pytest.mark.parametrize("n", [5, 9, 30])
def test_grid_blocks_equal_one_lu(n):
    problem = paper_grid(n)
    for alteration in (problem.identity(), problem.alteration({"o1": "o2", "o2": "o0"})):
        a, b, nodes = _system(problem, alteration)
        by_blocks = solve_by_blocks(a, b, nodes)
        assert by_blocks is not None  # the grid's controller changes node at sensors only
        direct = np.linalg.solve(np.eye(a.shape[0]) - a.toarray(), b)
        assert np.abs(by_blocks - direct).max() < 1e-12


def test_random_models_through_the_block_path(monkeypatch):
    """With the size threshold off, every evaluation that can split does; values unchanged."""
    problems = [random_problem(seed, states=12, nodes=3) for seed in range(60)]
    alterations = [p.identity() for p in problems]
    before = [decoy_probability(p, a) for p, a in zip(problems, alterations, strict=True)]
    split = []
    real = reachability.solve_by_blocks

    def spy(*args):
        result = real(*args)
        split.append(result is not None)
        return result

    monkeypatch.setattr(reachability, "PARALLEL_MIN_STATES", 0)
    monkeypatch.setattr(reachability, "solve_by_blocks", spy)
    after = [decoy_probability(p, a) for p, a in zip(problems, alterations, strict=True)]
    assert after == pytest.approx(before, abs=1e-12)
    assert sum(split) >= 10  # the block path really ran, not only the fallback


def test_a_large_separator_is_declined(monkeypatch):
    a, b, nodes = _system(paper_grid(9), paper_grid(9).identity())
    monkeypatch.setattr(reachability, "SEPARATOR_MAX", 0)
    assert solve_by_blocks(a, b, nodes) is None
