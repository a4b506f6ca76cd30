"""The segment relaxation and the segment search: a proven upper bound, and an exact search.

Every expected value comes from the exhaustive solver, never from the module itself.
"""

import numpy as np
import pytest

from misdirect.core.attack import prepare
from misdirect.core.evaluate import decoy_probability
from misdirect.scenarios import random_problem, sensor_grid
from misdirect.solvers.branch_and_bound import BranchAndBoundSolver
from misdirect.solvers.deadline import Deadline
from misdirect.solvers.engines.segment_relaxation import segment_bound, segment_relaxation
from misdirect.solvers.engines.segment_search import SegmentSearch
from misdirect.solvers.engines.transient import LOW_RANK, TransientPolicyIteration
from misdirect.solvers.exhaustive import ExhaustiveSolver
from misdirect.solvers.options import SolveOptions


def optima(problem, budgets):
    return [s.solver_probability for s in ExhaustiveSolver().solve(problem, budgets)]


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
        (8, 6, 5, "uniform"),
    ]:
        try:
            yield sensor_grid(n, k, seed=seed, costs=costs, memory=3 + seed % 3)
        except Exception:  # no decoy cell for this seed: not an instance
            continue


def check_bounds(problem, budgets):
    """Root bounds (with and without the Lagrangian) are at least the exhaustive optimum, and
    the search certifies exactly the exhaustive optimum."""
    top = max(budgets)
    best = optima(problem.with_budget(top), budgets)
    seg = segment_relaxation(problem, top)
    top_value = problem.objective.max_value
    plain = [min(seg.node({}, b, -np.inf)[0].bound, top_value) for b in budgets]
    seg.compute_entries(top)  # M_o for the top budget holds for every smaller one
    charged = [min(seg.node({}, b, -np.inf)[0].bound, top_value) for b in budgets]
    for budget, optimum, p, c in zip(budgets, best, plain, charged, strict=True):
        assert p >= optimum - 1e-9, (problem.name, budget, p, optimum)
        assert c >= optimum - 1e-9, (problem.name, budget, c, optimum)
        assert c <= p + 1e-9
    for budget, optimum in zip(budgets, best, strict=True):
        search = SegmentSearch(seg, budget)
        assert search.run(Deadline(60)) == "optimal"
        assert abs(search.best_value - optimum) <= 1e-9, (problem.name, budget)
        assert search.open_bound() >= optimum - 1e-9
        # small subtrees enumerated (low-rank updates) instead of bounded: still exact
        mixed = SegmentSearch(seg, budget, enumerate_at=ENUMERATE_AT)
        assert mixed.run(Deadline(60)) == "optimal"
        assert abs(mixed.best_value - optimum) <= 1e-9, (problem.name, budget)
        assert abs(mixed.open_bound() - optimum) <= 1e-9, (problem.name, budget)
        ENUMERATED.append(mixed.enumerated)
        # two workers on one heap: the same optimum, and a bound that closes on it
        shared = SegmentSearch(seg, budget, enumerate_at=ENUMERATE_AT)
        assert shared.run(Deadline(60), workers=2) == "optimal"
        assert abs(shared.best_value - optimum) <= 1e-9, (problem.name, budget)
        assert abs(shared.open_bound() - optimum) <= 1e-9, (problem.name, budget)
    return bool(prepare(problem, top).cycling.any())


ENUMERATE_AT = 100  # small, so that searches both bound and enumerate nodes
ENUMERATED: list[int] = []


def test_bound_is_at_least_the_optimum_on_random_models():
    """End components included: the models whose choice product has some are counted, so
    that the suite is known to exercise the stop rows."""
    cycling = sum(check_bounds(p, [0.0, 1.0, 2.0, 3.5]) for p in random_suite(40))
    assert cycling >= 5


@pytest.mark.parametrize("index", range(6))
def test_bound_is_at_least_the_optimum_on_small_sensor_grids(index):
    grids = list(small_grids())
    if index >= len(grids):
        pytest.skip("no decoy for this seed")
    check_bounds(grids[index], [0.0, 1.0, 2.0, 3.0])


def test_searches_enumerated_some_subtrees():
    """The mixed searches above really enumerated: some nodes, not all of them."""
    ENUMERATED.clear()
    for grid in list(small_grids())[1:5]:
        check_bounds(grid, [3.0])
    assert sum(ENUMERATED) > 0


def test_root_bound_helper_matches_the_node_bound():
    problem = sensor_grid(7, 6, seed=1)
    assert segment_bound(problem, 2.0) >= optima(problem.with_budget(2.0), [2.0])[0] - 1e-9


def test_branch_and_bound_backed_by_the_segment_search_stays_honest():
    """A chain above SEGMENT_MIN_STATES, cut short by the node limit: the segment phase runs,
    and every answer re-evaluates to its claim, below its bound, the bound above the optimum."""
    problem = sensor_grid(20, 8, seed=0)
    budgets = [0.0, 1.0, 2.0]
    best = optima(problem.with_budget(2.0), budgets)
    answers = BranchAndBoundSolver(SolveOptions(threads=1), max_nodes=2).solve(problem, budgets)
    assert any("segment_nodes" in a.stats for a in answers)
    assert any("segment_enumerated" in a.stats for a in answers)
    for answer, optimum in zip(answers, best, strict=True):
        value = decoy_probability(problem, np.asarray(answer.alteration))
        assert abs(value - answer.solver_probability) <= 1e-9
        assert answer.upper_bound >= optimum - 1e-9
        assert value <= optimum + 1e-9
        if answer.status == "optimal":
            assert abs(value - optimum) <= 1e-9


def test_bounds_hold_with_weighted_decoys():
    """Decoy weights up to 3 (tests/test_weighted_decoys.py): the segment bounds still lie
    above the exhaustive optimum, and the search certifies it exactly."""
    from test_weighted_decoys import weighted_random

    for seed in range(12):  # every one, with end components or without
        check_bounds(weighted_random(seed), [0.0, 1.0, 2.0, 3.0])


def test_threads_are_checked_and_shares_favour_the_next_budget():
    from misdirect.errors import ProblemError

    with pytest.raises(ProblemError, match="at least 1"):
        BranchAndBoundSolver(SolveOptions(threads=0))
    assert Deadline(None).front_share(3) is None
    clock = Deadline(100.0)
    # the next of 3 pieces gets twice each later one's: 2/4 of what is left, then 1/4 each
    assert clock.front_share(3) == pytest.approx(50.0, abs=0.5)
    assert clock.front_share(1) == pytest.approx(100.0, abs=0.5)


def test_local_search_finds_the_best_one_sensor_extension_of_its_seed():
    """From a seed, the local search reaches at least the best alteration that adds one
    sensor to it, found here by evaluating every such extension exactly."""
    problem = sensor_grid(9, 10, seed=4, costs="random", memory=5)
    seg = segment_relaxation(problem, 3.0)
    space = seg.space
    seed = SegmentSearch(seg, 1.0, enumerate_at=10**6)
    assert seed.run(Deadline(60)) == "optimal"
    picks = dict(zip(seg.order, seed.best_picks, strict=True))
    best_extension = seed.best_value
    for i in seg.order:
        if picks[i]:
            continue
        for k in range(1, space.choices[i].size):
            extended = {**picks, i: k}
            vector = np.zeros(len(space.choices), dtype=np.int64)
            for j, option in extended.items():
                vector[j] = option
            cost = sum(float(space.choices[j].costs[o]) for j, o in enumerate(vector))
            if cost > 3.0 + 1e-9:
                continue
            value = decoy_probability(problem, space.alteration(problem, vector))
            best_extension = max(best_extension, value)
    search = SegmentSearch(seg, 3.0, seeds=[seed.best_picks], enumerate_at=10**6)
    search.local_search(Deadline(60))
    assert best_extension > seed.best_value + 1e-6  # one more sensor does help here
    assert search.best_value >= best_extension - 1e-9
    assert abs(search.best_value - decoy_probability(problem, _alteration(seg, search))) <= 1e-9


def _alteration(seg, search):
    vector = np.zeros(len(seg.space.choices), dtype=np.int64)
    for i, option in zip(seg.order, search.best_picks, strict=True):
        vector[i] = option
    return seg.space.alteration(seg.problem, vector)


@pytest.mark.parametrize("changed", [1, 5, LOW_RANK])
def test_a_few_switched_rows_are_solved_exactly_from_the_old_factorisation(changed):
    """Woodbury from the LU of one policy's system solves a policy that switches a few rows,
    both ways, as a fresh sparse solve does (the bound is this policy's value)."""
    import scipy.sparse as sp
    from scipy.sparse.linalg import spsolve

    rng = np.random.default_rng(changed)
    n, choices = 60, 2
    rows = []
    for _ in range(n * choices):  # substochastic rows: every policy's chain is transient
        row = np.zeros(n)
        hit = rng.choice(n, 3, replace=False)
        row[hit] = rng.dirichlet(np.ones(3)) * 0.9
        rows.append(row)
    matrix = sp.csr_matrix(np.array(rows))
    row_state = np.repeat(np.arange(n), choices)
    iteration = TransientPolicyIteration(row_state, matrix, n)
    first = iteration.first_rows()
    other = first.copy()
    switched = rng.choice(n, changed, replace=False)
    other[switched] += 1
    solver = iteration.updated(iteration.factorise(first), first, other)
    system = (sp.identity(n, format="csc") - matrix[other]).tocsc()
    b = rng.random(n)
    assert np.allclose(solver.solve(b), spsolve(system, b), rtol=0, atol=1e-12)
    assert np.allclose(solver.solve(b, trans="T"), spsolve(system.T.tocsc(), b), atol=1e-12)
    many = other.copy()
    unswitched = np.setdiff1d(np.arange(n), switched)
    many[rng.choice(unswitched, LOW_RANK + 1 - changed, replace=False)] += 1
    assert iteration.updated(iteration.factorise(first), first, many) is None  # refactorise


def test_policy_iteration_stops_only_above_the_threshold_and_below_the_optimum():
    """Stopping early (the node cannot be pruned) returns a policy worth more than the
    threshold and at most the optimum; without a threshold it returns the optimum, checked
    against value iteration run to convergence."""
    import scipy.sparse as sp

    rng = np.random.default_rng(3)
    n, choices = 40, 3
    matrix = sp.csr_matrix(
        np.array(
            [rng.dirichlet(np.ones(n)) * 0.9 * (rng.random(n) < 0.2) for _ in range(n * choices)]
        )
    )
    reward = rng.random(n * choices)
    row_state = np.repeat(np.arange(n), choices)
    values, _, _, optimal = TransientPolicyIteration(row_state, matrix, n).optimise(reward)
    assert optimal
    iterate = np.zeros(n)
    for _ in range(2000):
        iterate = (matrix @ iterate + reward).reshape(n, choices).max(axis=1)
    assert np.allclose(values, iterate, atol=1e-9)
    start = 0
    worst = TransientPolicyIteration(row_state, matrix, n).optimise(
        reward, start=start, enough=-1.0
    )
    assert worst[3] is False and -1.0 < worst[0][start] <= values[start] + 1e-12
    never = TransientPolicyIteration(row_state, matrix, n).optimise(
        reward, start=start, enough=values[start] + 1e-6
    )
    assert never[3] is True and never[0][start] == pytest.approx(values[start], abs=1e-12)


@pytest.mark.parametrize(("n", "k"), [(16, 4), (20, 4), (10, 3)])
def test_the_reported_root_bound_bounds_the_optimum_when_the_root_is_split(n, k):
    """Where one reading covers much of the map (the blank one), the search starts from one
    node per option of it instead of a root: its reported root bound is the largest of their
    bounds, so at least the optimum (exhaustive search's), not the first node's own (which
    read 7e-7 against an optimum of 0.046)."""
    from misdirect.solvers.engines.segment_search import BIG_REGION

    problem = sensor_grid(n, k)
    seg = segment_relaxation(problem, 2)
    assert any(seg.region_size[i] >= BIG_REGION * seg.live_total for i in seg.order)
    search = SegmentSearch(seg, 2.0)
    search.run()
    optimum = ExhaustiveSolver().solve(problem, [2.0])[0].solver_probability
    assert search.root_bound is not None
    assert search.root_bound >= optimum - 1e-12


@pytest.mark.parametrize("blind", [True, False])
def test_where_bounds_cannot_see_the_budget_a_node_with_small_children_is_enumerated(
    blind, monkeypatch
):
    """A drone among patrolling agents has end components: the segment bound charges
    nothing. Its root has more completions than ``enumerate_at``, but each child that alters
    one more observation would be a tiny enumeration: the search enumerates the root whole
    (no node bounded). Told the bound sees the budget, it bounds the root and branches. Both
    certify the optimum that solving every alteration on its own chain gives."""
    from misdirect.scenarios.drone import drone
    from misdirect.solvers.engines.segment_relaxation import SegmentRelaxation

    problem = drone(n=5, agents=1, rows=1)
    budget = 2.0
    seg = segment_relaxation(problem, budget)
    assert seg.budget_blind
    assert all((choice.costs[1:] == 1.0).all() for choice in seg.space.choices)
    if not blind:
        monkeypatch.setattr(SegmentRelaxation, "budget_blind", property(lambda self: False))
    whole = seg.completions({}, budget, 10**9)
    child = seg.completions({}, budget - 1.0, 10**9)  # every option costs 1 here
    enumerate_at = max(-(-whole // 8), 16 * child)
    assert enumerate_at < whole  # the root is above the plain threshold
    search = SegmentSearch(seg, budget, enumerate_at=enumerate_at)
    assert search.run(Deadline(120.0), workers=1) == "optimal"
    assert search.best_value == pytest.approx(optima(problem.with_budget(budget), [budget])[0])
    if blind:
        assert search.nodes == 0 and search.enumerated == 1
    else:
        assert search.nodes >= 1
