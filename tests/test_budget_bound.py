"""The segment relaxation (budget_bound.py): a proven upper bound, and an exact search.

Every expected value comes from the exhaustive solver, never from the module itself.
"""

import numpy as np
import pytest

from misdirect.scenarios import random_problem, sensor_grid
from misdirect.solvers.base import Deadline
from misdirect.solvers.budget_bound import SegmentSearch, segment_bound, segment_relaxation
from misdirect.solvers.exhaustive import ExhaustiveSolver


def optima(problem, budgets):
    return [s.claimed_probability for s in ExhaustiveSolver().solve(problem, budgets)]


def random_suite(count):
    for seed in range(count):
        rng = np.random.default_rng(70_000 + seed)
        yield random_problem(
            seed + 7000,
            states=int(rng.integers(3, 12)),
            actions=int(rng.integers(1, 4)),
            observations=int(rng.integers(2, 7)),
            nodes=int(rng.integers(1, 4)),
        )


def small_grids():
    for n, k, seed, costs in [
        (6, 4, 0, "uniform"),
        (7, 6, 1, "uniform"),
        (8, 8, 2, "random"),
        (8, 10, 3, "uniform"),
        (9, 10, 4, "random"),
        (10, 8, 5, "uniform"),
    ]:
        try:
            yield sensor_grid(n, k, seed=seed, costs=costs, memory=3 + seed % 3)
        except Exception:  # no decoy cell for this seed: not an instance
            continue


def check_bounds(problem, budgets):
    """Root bounds (with and without the Lagrangian) are at least the exhaustive optimum, and
    the search certifies exactly the exhaustive optimum. Returns False if not applicable."""
    top = max(budgets)
    if segment_relaxation(problem.with_budget(top), top) is None:
        return False
    best = optima(problem.with_budget(top), budgets)
    for budget, optimum in zip(budgets, best, strict=True):
        plain = segment_bound(problem, budget)
        charged = segment_bound(problem, budget, lagrangian=True)
        assert plain >= optimum - 1e-9, (problem.name, budget, plain, optimum)
        assert charged >= optimum - 1e-9, (problem.name, budget, charged, optimum)
        assert charged <= plain + 1e-9
    seg = segment_relaxation(problem, top)
    seg.compute_entries(top)
    for budget, optimum in zip(budgets, best, strict=True):
        search = SegmentSearch(seg, budget)
        assert search.run(Deadline(60)) == "optimal"
        assert abs(search.best_value - optimum) <= 1e-9, (problem.name, budget)
        assert search.open_bound() >= optimum - 1e-9
    return True


def test_bound_is_at_least_the_optimum_on_random_models():
    applied = sum(check_bounds(p, [0.0, 1.0, 2.0, 3.5]) for p in random_suite(40))
    assert applied >= 15  # most random models have no end component


@pytest.mark.parametrize("index", range(6))
def test_bound_is_at_least_the_optimum_on_small_sensor_grids(index):
    grids = list(small_grids())
    if index >= len(grids):
        pytest.skip("no decoy for this seed")
    assert check_bounds(grids[index], [0.0, 1.0, 2.0, 3.0])
