"""The exhaustive solver is the oracle of every later solver, so it is checked against the
definition itself: every alteration function Ω -> Ω, no behaviour classes, no pruning."""

import itertools

import numpy as np
import pytest

from misdirect import decoy_probability, solve
from misdirect.scenarios import knapsack, random_problem


def brute_force_curve(problem, budgets):
    """Best exact value within each budget over *all* allowed alteration functions."""
    n_obs = problem.pomdp.n_observations
    init = problem.pomdp.initial_observation
    options = []
    for o in range(n_obs):
        row = problem.cost.row(o)
        options.append([o] if o == init else list(np.flatnonzero(np.isfinite(row))))
    costs, values = [], []
    for combo in itertools.product(*options):
        alpha = np.array(combo)
        costs.append(problem.alteration_cost(alpha))
        values.append(decoy_probability(problem, alpha))
    costs, values = np.array(costs), np.array(values)
    return [values[costs <= b + 1e-9].max() for b in budgets]


@pytest.mark.parametrize("seed", range(40))
def test_exhaustive_equals_brute_force_on_random_models(seed):
    problem = random_problem(seed, states=5, observations=3, nodes=2, budget=3)
    budgets = [0.0, 1.0, 2.0, 3.0]
    result = solve(problem, method="exhaustive", budgets=budgets)
    expected = brute_force_curve(problem, budgets)
    for point, best in zip(result.curve, expected, strict=True):
        assert point.probability == pytest.approx(best, abs=1e-12)
        assert point.cost <= point.budget
        problem.check_alteration(problem.alteration(point.alteration))


def test_budget_curve_is_monotone_and_final_point_is_the_answer():
    problem = random_problem(11, states=7, observations=4, nodes=3, budget=4)
    result = solve(problem, method="exhaustive")
    values = [p.probability for p in result.curve]
    assert values == sorted(values)
    assert [p.budget for p in result.curve] == [0, 1, 2, 3, 4]
    assert result.probability == values[-1]
    assert result.baseline_probability == pytest.approx(values[0], abs=1e-15)


@pytest.mark.parametrize("seed", range(8))
def test_knapsack_reduction_equals_subset_enumeration(seed):
    """SPEC §4: the optimum is (best knapsack value) / (2 Σ v)."""
    rng = np.random.default_rng(seed)
    k = int(rng.integers(2, 8))
    weights = rng.integers(1, 10, size=k).tolist()
    values = rng.integers(1, 50, size=k).tolist()
    capacity = int(rng.integers(0, sum(weights) + 1))
    best = max(
        sum(values[i] for i in subset)
        for r in range(k + 1)
        for subset in itertools.combinations(range(k), r)
        if sum(weights[i] for i in subset) <= capacity
    )
    result = solve(knapsack(weights, values, capacity), method="exhaustive")
    assert result.probability == pytest.approx(best / (2 * sum(values)), abs=1e-12)
    chosen = [int(o[1:]) - 1 for o in result.alteration]
    assert sum(weights[i] for i in chosen) <= capacity
    assert sum(values[i] for i in chosen) == best


def test_counting_alterations_equals_listing_them():
    """AlterationSpace.count_within (a count per distinct total cost) against the length of
    the list ``within`` builds, on random models with fractional and forbidden costs."""
    from misdirect.core.alterations import alteration_space
    from misdirect.scenarios import random_problem

    for seed in range(30):
        problem = random_problem(seed, states=10, observations=6, nodes=2)
        for budget in (0.0, 0.5, 1.0, 2.5, 4.0):
            space = alteration_space(problem.with_budget(budget))
            listed = len(space.within(budget)[1])
            assert space.count_within(budget, 10**6) == listed
            assert space.count_within(budget, listed - 1) == listed if listed > 1 else True
