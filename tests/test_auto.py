"""`--method auto` (the default): small spaces are enumerated (with low-rank updates where the
chain cannot cycle), knapsack-like ones go to the MILP, the rest to branch-and-bound; the answer
is exact either way and says which method certified it."""

import numpy as np
import pytest

from misdirect import solve
from misdirect.scenarios import knapsack, paper_grid, random_problem


def knapsack_dp(weights, values, capacity):
    """Textbook 0/1 knapsack by dynamic programming over integer capacities."""
    best = [0] * (capacity + 1)
    for w, v in zip(weights, values, strict=True):
        for c in range(capacity, w - 1, -1):
            best[c] = max(best[c], best[c - w] + v)
    return best[capacity]


def test_small_space_is_enumerated():
    result = solve(paper_grid(5), budgets=range(5))
    assert result.certified_by == "incremental"
    assert [p.probability for p in result.curve] == pytest.approx(
        [0.084957, 0.719924, 0.860130, 0.862442, 0.863622], abs=5e-7
    )


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_sixty_item_knapsack_goes_to_the_milp(seed):
    rng = np.random.default_rng(seed)
    weights = rng.integers(1, 101, size=60).tolist()
    values = rng.integers(1, 101, size=60).tolist()
    capacity = sum(weights) // 2
    result = solve(knapsack(weights, values, capacity))
    assert result.certified_by == "milp"
    assert result.status == "optimal"
    best = knapsack_dp(weights, values, capacity)
    assert result.probability == pytest.approx(best / (2 * sum(values)), abs=1e-12)
    chosen = [int(o[1:]) - 1 for o in result.alteration]
    assert sum(weights[i] for i in chosen) <= capacity


def test_auto_equals_exhaustive_on_random_models():
    """Same generator as the MILP suite, other seeds; auto takes whichever route fits each."""
    routes = set()
    for seed in range(120):
        rng = np.random.default_rng(70_000 + seed)
        problem = random_problem(
            seed + 5000,
            states=int(rng.integers(3, 9)),
            actions=int(rng.integers(1, 4)),
            observations=int(rng.integers(2, 5)),
            nodes=int(rng.integers(1, 4)),
        )
        budgets = [0.0, 1.0, 2.5, 4.0]
        mine = solve(problem, budgets=budgets)
        oracle = solve(problem, method="exhaustive", budgets=budgets)
        routes.add(mine.certified_by)
        assert not mine.warnings, seed
        for a, b in zip(mine.curve, oracle.curve, strict=True):
            assert a.probability == pytest.approx(b.probability, abs=1e-9), (seed, a.budget)
            assert a.cost <= a.budget + 1e-9
    assert {"incremental", "exhaustive"} <= routes  # both enumeration routes were exercised
    assert routes <= {"incremental", "exhaustive", "branch-and-bound", "milp"}


@pytest.mark.parametrize("n", [5, 7, 9])
def test_auto_equals_exhaustive_on_grids(n):
    mine = solve(paper_grid(n), budgets=range(6))
    oracle = solve(paper_grid(n), method="exhaustive", budgets=range(6))
    for a, b in zip(mine.curve, oracle.curve, strict=True):
        assert a.probability == pytest.approx(b.probability, abs=1e-9)
