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
            assert a.cost <= a.budget
    assert "incremental" in routes  # every one of these is small enough to enumerate
    assert routes <= {"incremental", "exhaustive", "branch-and-bound", "milp"}


@pytest.mark.parametrize("n", [5, 7, 9])
def test_auto_equals_exhaustive_on_grids(n):
    mine = solve(paper_grid(n), budgets=range(6))
    oracle = solve(paper_grid(n), method="exhaustive", budgets=range(6))
    for a, b in zip(mine.curve, oracle.curve, strict=True):
        assert a.probability == pytest.approx(b.probability, abs=1e-9)


def test_auto_enumerates_a_cycling_budget_with_low_rank_updates():
    """Issue 27 (drone-4-1: branch-and-bound ran to the limit with bound 1 where exhaustive
    proved budget 1 in 20 s). A patrol that can turn back: 256 sensors, end components among
    the live states, about 1,600 alterations at budget 1: auto enumerates them with low-rank
    updates and proves the optimum the exhaustive method (the oracle) finds."""
    from misdirect.core.attack import prepare
    from turnback import turnback

    problem = turnback(8, nodes=2)
    instance = prepare(problem, 1.0)
    assert instance.cycling.any() and problem.pomdp.n_observations > 250
    assert 1_000 < instance.space.count_within(1.0, 10**6) < 5_000
    result = solve(problem, budgets=[1.0], time_limit=600)
    oracle = solve(problem, method="exhaustive", budgets=[1.0])
    assert result.status == "optimal" and oracle.status == "optimal"
    assert result.probability == pytest.approx(oracle.probability, abs=1e-12)
    assert result.certified_by == "incremental"


def test_auto_enumerates_the_small_budgets_of_a_cycling_curve(monkeypatch):
    """A curve on a chain that can cycle whose top budget is too large to enumerate in the
    time, but whose budget 1 is not: budgets 0 and 1 are enumerated (low-rank updates), the
    top searched from their answer; every point is the exhaustive optimum, certified."""
    from misdirect.core.attack import prepare
    from misdirect.solvers import schedule
    from turnback import turnback

    problem = turnback(3, nodes=1, budget=2)
    instance = prepare(problem, 2.0)
    assert instance.cycling.any()
    at_one, at_two = (instance.space.count_within(b, 10**6) for b in (1.0, 2.0))
    # within 100 s: budget 1 takes 10 s (under half), budget 2 more than all of it
    monkeypatch.setattr(schedule, "INCREMENTAL_SURE", 0)
    monkeypatch.setattr(schedule, "UPDATE_SECONDS", 10.0 / at_one)
    assert at_two * 10.0 / at_one > 100
    notes = []
    budgets = [0.0, 1.0, 2.0]
    result = solve(
        problem,
        budgets=budgets,
        time_limit=100,
        progress=lambda d, t, **info: notes.append(info.get("note")),
    )
    oracle = solve(problem, method="exhaustive", budgets=budgets)
    methods = [p.certified_by for p in result.curve]
    assert methods[:2] == ["incremental", "incremental"]
    assert methods[2] in ("branch-and-bound", "milp", "exhaustive")  # searched, or handed over
    for mine, best in zip(result.curve, oracle.curve, strict=True):
        assert mine.status == "optimal"
        assert mine.probability == pytest.approx(best.probability, abs=1e-12)
    assert any(n and "budgets up to 1 enumerated" in n for n in notes)


def test_the_stage_that_certified_a_handed_over_budget_is_named():
    """Issue 53: "certified by incremental (… the enumeration of it would not fit the time
    left, so branch-and-bound)". The enumeration stopped with a loose bound, branch-and-bound
    finished the budget, and the exact value lay an ulp above its bound, so the bound was not
    the combined one and the credit went to the enumeration. The stage that finished is
    named, and so is the one whose bound is smaller where neither finished."""
    from misdirect.solvers.auto import _better
    from misdirect.solvers.base import Solution
    from misdirect.solvers.status import Status

    value = 0.2063575515173952
    above = np.nextafter(value, 1.0)  # the front door's exact value of the same alteration
    alteration = np.zeros(3, dtype=np.int64)

    def point(status, bound, method):
        return Solution(1.0, alteration, value, status, bound, certified_by=method)

    def exact(_):
        return above

    first = point(Status.TIME_LIMIT, 0.899, "incremental")
    second = point(Status.OPTIMAL, value, "branch-and-bound")
    answer = _better(exact, first, second, "the enumeration would not fit, so branch-and-bound")
    assert answer.status == Status.OPTIMAL and answer.certified_by == "branch-and-bound"
    # neither finished, but the second's bound proves the value: it certified it
    second = point(Status.TIME_LIMIT, value, "branch-and-bound")
    answer = _better(exact, first, second, "why")
    assert answer.certified_by == "branch-and-bound"
