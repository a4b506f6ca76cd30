"""Budgets are compared exactly, whatever the costs' magnitudes: an alteration that costs exactly
the budget fits it, one a rounding error over does not (issue 51, item 1).

The oracle enumerates every alteration function and adds its costs as Fractions (as written:
the shortest decimal of each float, the file's meaning; the float values where the cost
scale is ``binary``, whose float sums are exact), so it shares no arithmetic with the
solvers' float sums and caps.
"""

from __future__ import annotations

import dataclasses
import itertools
from fractions import Fraction
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from misdirect import decoy_probability, load_problem, solve
from misdirect.core import tolerance
from misdirect.core.model import CostModel, Problem
from misdirect.scenarios import random_problem

EXAMPLES = Path(__file__).resolve().parent.parent / "examples"
METHODS = ["auto", "exhaustive", "incremental", "branch-and-bound", "milp"]

THIRD = 1 / 3  # 0.3333333333333333: no finite binary or short decimal sum meets 1 with it


def _value(cost: float, scale: tolerance.CostScale) -> Fraction:
    return Fraction(cost) if scale.kind == "binary" else Fraction(repr(float(cost)))


def brute_force(problem: Problem, budget: float) -> tuple[float, Fraction]:
    """The best exact value over every alteration whose exact cost fits ``budget`` (and the
    cheapest exact cost among the alterations attaining it, up to the value's rounding)."""
    n = problem.pomdp.n_observations
    scale = problem.cost.scale
    limit = _value(budget, scale)
    options = [list(np.flatnonzero(np.isfinite(problem.cost.row(o)))) for o in range(n)]
    best, cheapest = -1.0, Fraction(0)
    for combo in itertools.product(*options):
        alpha = np.array(combo, dtype=np.int64)
        terms = [problem.cost.row(o)[t] for o, t in enumerate(combo) if t != o]
        cost = sum((_value(c, scale) for c in terms), Fraction(0))
        if cost > limit:
            continue
        value = decoy_probability(problem, alpha)
        if value > best + 1e-12:
            best, cheapest = value, cost
        elif value >= best - 1e-12:
            cheapest = min(cheapest, cost)
    return best, cheapest


def _with_costs(problem: Problem, pairs: dict[tuple[int, int], float], budget: float) -> Problem:
    cost = CostModel(problem.pomdp.n_observations, default=np.inf, pairs=pairs)
    return dataclasses.replace(problem, cost=cost, budget=budget)


def _pairs(problem: Problem, costs: list[float]) -> dict[tuple[int, int], float]:
    """The four alterations of the two observations that are not the initial one (never
    altered), at ``costs``."""
    a, b = (o for o in range(3) if o != problem.pomdp.initial_observation)
    c = problem.pomdp.initial_observation
    return {(a, c): costs[0], (a, b): costs[1], (b, c): costs[2], (b, a): costs[3]}


def _check(problem: Problem, budget: float, method: str) -> None:
    truth, _ = brute_force(problem, budget)
    result = solve(problem, method=method, budgets=[budget], time_limit=60)
    point = result.curve[0]
    alpha = np.asarray(point.alteration_array, dtype=np.int64)
    assert problem.cost.fits(alpha, budget), (method, point.alteration, point.cost)
    spent = sum(
        (_value(problem.cost.row(o)[t], problem.cost.scale) for o, t in enumerate(alpha) if t != o),
        Fraction(0),
    )
    assert spent <= _value(budget, problem.cost.scale), (method, point.alteration)
    assert point.probability <= truth + 1e-9, (method, point.probability, truth)
    if point.status == "optimal":
        assert point.probability == pytest.approx(truth, rel=1e-9, abs=1e-12), (
            method,
            point.alteration,
            point.probability,
            truth,
        )


# the cost sets: one cost is the budget, the other of another magnitude
EXACTLY_THE_BUDGET = [
    (1.0, THIRD),
    (0.30000000000000004, 0.1),
    (1e9, 1e-6),
    (1e12, 1e-3),
    (1e12, 1e-12),
    (1e-300, 1.0),
    (1.0, 1e-300),
]


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("costs", EXACTLY_THE_BUDGET, ids=str)
def test_an_alteration_costing_exactly_the_budget_fits(method, costs):
    """The trap corridor of the examples, by hand: its loop's sensor o1 read as o0 lifts the
    decoy from 0.1 to 0.4 and costs ``costs[0]``; the exit's sensor o2 read as g (costs
    ``costs[1]``) gains nothing. At budget ``costs[0]`` the answer is o1 -> o0, optimal; a
    budget one float below it affords nothing that helps: 0.1."""
    problem = load_problem(EXAMPLES / "trap.yaml")
    names = list(problem.pomdp.observations)
    o0, o1, o2, g = (names.index(x) for x in ("o0", "o1", "o2", "g"))
    first, second = costs
    pairs = {(o1, o0): first, (o2, g): second}
    problem = _with_costs(problem, pairs, first)
    point = solve(problem, method=method, budgets=[first], time_limit=60).curve[0]
    assert point.status == "optimal"
    assert point.probability == pytest.approx(0.4, rel=1e-12)
    assert point.alteration == {"o1": "o0"}
    below = float(np.nextafter(first, 0.0))
    point = solve(problem, method=method, budgets=[below], time_limit=60).curve[0]
    assert point.probability == pytest.approx(0.1, rel=1e-12)
    assert "o1" not in point.alteration


def test_a_cost_model_of_extreme_magnitudes_is_accepted():
    """Costs 1e-300 and 1 (and 1e300) sum to a finite number: no "largest number" refusal."""
    problem = random_problem(3, states=4, observations=3, nodes=2, budget=1.0)
    pairs = _pairs(problem, [1e-300, 1.0, 1e300, 1e-300])
    problem = _with_costs(problem, pairs, 1.0)
    _check(problem, 1.0, "auto")


MAGNITUDES = st.one_of(
    st.integers(-300, 300).map(lambda k: 10.0**k),
    st.sampled_from([THIRD, 2 * THIRD, 0.1, 0.2, 0.30000000000000004, 1.0, 3.0]),
    st.integers(-20, 20).map(lambda k: THIRD * 10.0**k),
)


@settings(
    max_examples=60,
    deadline=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.too_slow],
)
@given(
    seed=st.integers(0, 10_000),
    costs=st.lists(MAGNITUDES, min_size=4, max_size=4),
    budget_from=st.lists(st.integers(0, 3), min_size=1, max_size=3, unique=True),
    nudge=st.sampled_from([0, -1, 1]),
    method=st.sampled_from(METHODS),
)
def test_mixed_scale_costs_match_brute_force(seed, costs, budget_from, nudge, method):
    """Random cost sets mixing 1e-300..1e300, thirds and tenths, and budgets that are a sum
    of some of them (rounded to the nearest float, or one float either side): every method's
    answer fits exactly, is never above the brute-force optimum, and equals it when optimal."""
    problem = random_problem(seed, states=4, observations=3, nodes=2, budget=1.0)
    pairs = _pairs(problem, costs)
    exact = sum((Fraction(repr(costs[i])) for i in budget_from), Fraction(0))
    budget = float(exact)
    if nudge:
        budget = float(np.nextafter(budget, np.inf if nudge > 0 else 0.0))
    problem = _with_costs(problem, pairs, budget)
    _check(problem, budget, method)


def test_a_subnormal_knapsack_reloads_and_solves(tmp_path):
    """Issue 51, item 11: weights 1e-320 and 1 at capacity 1e-320 wrote a file that reloaded
    as "costs sum to more than the largest number". The reduction's optimum is the best
    knapsack value over 2 Σ v (scenarios.knapsack): only the first item fits, 1 / 4."""
    from misdirect import write_problem
    from misdirect.scenarios import knapsack

    path = tmp_path / "k.yaml"
    write_problem(knapsack([1e-320, 1.0], [1.0, 1.0], 1e-320), path)
    point = solve(load_problem(path), budgets=[1e-320]).curve[0]
    assert point.status == "optimal"
    assert point.probability == pytest.approx(0.25, rel=1e-12)


@pytest.mark.parametrize("method", METHODS)
def test_a_knapsack_item_that_fills_the_capacity_exactly_is_taken(method):
    """The knapsack reduction with weights 1 and a third, values 3 and 1, capacity 1: the
    first item fills the knapsack exactly (both weigh 4/3), so the optimum is 3 / (2 · 4)."""
    from misdirect.scenarios import knapsack

    problem = knapsack([1.0, THIRD], [3.0, 1.0], 1.0)
    point = solve(problem, method=method, budgets=[1.0], time_limit=60).curve[0]
    assert point.status == "optimal"
    assert point.probability == pytest.approx(3 / 8, rel=1e-12)
