"""Branch-and-bound over observations with the MDP-relaxation bound: exact on every model.

Expected values come from the exhaustive solver, from brute force over every alteration
function, or from SPEC §3; never from the branch-and-bound itself.
"""

import dataclasses
import itertools

import numpy as np
import pytest

from misdirect import solve
from misdirect.core.alterations import alteration_space
from misdirect.core.choice_product import build_choice_product, end_component_states
from misdirect.core.evaluate import decoy_probability
from misdirect.core.model import Controller
from misdirect.scenarios import knapsack, paper_grid, random_problem
from misdirect.scenarios.grid import ACTIONS, BLANK, E_TYPE, N_TYPE, OBSERVATIONS, scaled
from misdirect.solvers.branch_and_bound import BranchAndBoundSolver
from misdirect.solvers.engines.per_state import relaxation_bound
from misdirect.solvers.exhaustive import ExhaustiveSolver
from searches import count_searches

SPEC_N5 = [0.084957, 0.719924, 0.860130, 0.862442, 0.863622, 0.863622]


def trap_grid(n: int, budget: float = 4.0):
    """The paper grid with three West-type sensors and a node on which the blank means West.

    The attacker can now turn the robot back and forth, so the choice product has end
    components (incremental updates do not apply), and with four behaviour classes over eleven
    observations, 20,686 alterations fit budget 4.
    """
    base = paper_grid(n, budget=budget)
    cells = [
        (scaled(1, n), scaled(3, n)),
        (scaled(3, n), scaled(1, n)),
        (scaled(1, n), scaled(1, n)),
    ]
    observation_of = base.pomdp.observation_of.copy()
    for j, (x, y) in enumerate(cells):
        observation_of[y * n + x] = len(OBSERVATIONS) + j
    names = (*OBSERVATIONS, "w0", "w1", "w2")
    pomdp = dataclasses.replace(base.pomdp, observations=names, observation_of=observation_of)
    east, north, west = (ACTIONS.index(a) for a in "ENW")
    action = np.zeros((4, len(names)), dtype=np.int64)
    update = np.zeros((4, len(names)), dtype=np.int64)
    action[:, list(E_TYPE)], update[:, list(E_TYPE)] = east, 1
    action[:, list(N_TYPE)], update[:, list(N_TYPE)] = north, 2
    action[:, len(OBSERVATIONS) :], update[:, len(OBSERVATIONS) :] = west, 3
    action[:, BLANK] = [east, east, north, west]
    update[:, BLANK] = np.arange(4)
    controller = Controller(
        nodes=("n0", "n1", "n2", "n3"), initial_node=0, action=action, update=update
    )
    cost = dataclasses.replace(base.cost, n_observations=len(names))
    return dataclasses.replace(
        base, pomdp=pomdp, controller=controller, cost=cost, name=f"trap grid {n}x{n}"
    )


def suite_problem(seed: int):
    rng = np.random.default_rng(90_000 + seed)
    return random_problem(
        seed + 9000,
        states=int(rng.integers(3, 10)),
        actions=int(rng.integers(1, 4)),
        observations=int(rng.integers(2, 6)),
        nodes=int(rng.integers(1, 4)),
    )


def has_end_component(problem) -> bool:
    chain = build_choice_product(problem, alteration_space(problem))
    live = chain.can_reach_target() & ~chain.target
    return bool(end_component_states(chain.group_state, chain.transitions, live).any())


def test_agrees_with_exhaustive_on_random_models():
    budgets = [0.0, 1.0, 2.5, 4.0]
    with_cycles = protected = forbidden = 0
    for seed in range(150):
        problem = suite_problem(seed).with_budget(4.0)
        with_cycles += has_end_component(problem)
        protected += bool(problem.cost.protected)
        forbidden += any(np.isinf(c) for c in problem.cost.pairs.values())
        mine = BranchAndBoundSolver().solve(problem, budgets)
        oracle = ExhaustiveSolver().solve(problem, budgets)
        for a, b in zip(mine, oracle, strict=True):
            exact = decoy_probability(problem, a.alteration)
            assert exact == pytest.approx(b.solver_probability, abs=1e-7), (seed, a.budget)
            assert a.solver_probability == pytest.approx(exact, abs=1e-9)
            assert a.status == "optimal"
            assert a.upper_bound >= b.solver_probability - 1e-9
            assert problem.alteration_cost(a.alteration) <= a.budget
            problem.check_alteration(a.alteration)
    assert with_cycles >= 20 and protected >= 20 and forbidden >= 100  # the suite has them


@pytest.mark.parametrize("n", [5, 7, 9])
def test_agrees_with_exhaustive_on_paper_grids(n):
    budgets = [0.0, 1.0, 2.0, 3.0]  # the oracle's cost grows fast with the budget
    mine = solve(paper_grid(n, budget=5), method="branch-and-bound", budgets=[*budgets, 4, 5])
    oracle = solve(paper_grid(n, budget=3), method="exhaustive", budgets=budgets)
    assert not mine.warnings
    for a, b in zip(mine.curve, oracle.curve, strict=False):
        assert a.probability == pytest.approx(b.probability, abs=1e-7)
    for point in mine.curve:
        assert point.status == "optimal" and point.cost <= point.budget
    if n == 5:
        assert [p.probability for p in mine.curve] == pytest.approx(SPEC_N5, abs=5e-7)


def brute_force(problem, budget: float) -> float:
    """Best value over every alteration function within the budget (no behaviour classes)."""
    n_o = problem.pomdp.n_observations
    rows = [problem.cost.row(o) for o in range(n_o)]
    targets = [
        [o] if o == problem.pomdp.initial_observation else np.flatnonzero(np.isfinite(rows[o]))
        for o in range(n_o)
    ]
    best = 0.0
    for alpha in itertools.product(*targets):
        alpha = np.array(alpha, dtype=np.int64)
        if problem.alteration_cost(alpha) <= budget + 1e-9:
            best = max(best, decoy_probability(problem, alpha))
    return best


def test_root_bound_is_above_the_brute_force_optimum():
    checked = 0
    for seed in range(40):
        problem = suite_problem(seed)
        if problem.pomdp.n_observations > 4:  # keep |Ω|^|Ω| small
            continue
        for budget in (0.0, 1.0, 3.0):
            truth = brute_force(problem, budget)
            assert relaxation_bound(problem, budget) >= truth - 1e-12, (seed, budget)
            checked += 1
    assert checked >= 30


def test_node_limit_reports_feasible_with_a_valid_bound():
    problem = trap_grid(9, budget=2)
    oracle = ExhaustiveSolver().solve(problem, [2.0])[0].solver_probability
    (answer,) = BranchAndBoundSolver(max_nodes=2).solve(problem, [2.0])
    assert answer.status == "feasible"
    exact = decoy_probability(problem, answer.alteration)
    assert answer.solver_probability == pytest.approx(exact, abs=1e-9)
    assert exact <= oracle + 1e-9 <= answer.upper_bound + 2e-9
    assert problem.alteration_cost(answer.alteration) <= 2.0


def test_auto_sends_a_knapsack_to_the_milp():
    rng = np.random.default_rng(2026)
    weights = rng.integers(1, 101, size=60).tolist()
    values = rng.integers(1, 101, size=60).tolist()
    result = solve(knapsack(weights, values, sum(weights) // 2))
    assert result.certified_by == "milp"
    assert "knapsack-like" in result.stats["auto_reason"]
    assert result.status == "optimal"


# budget 3 and 4 optima of trap_grid(9) from ExhaustiveSolver (4,984 and 20,686 evaluations)
TRAP9_EXHAUSTIVE = {3.0: 0.9798691274109901, 4.0: 0.9985288061060325}


def test_auto_enumerates_a_large_trap_grid():
    """End components everywhere: the low-rank enumeration applies all the same (issue 27)."""
    problem = trap_grid(9, budget=4)
    assert has_end_component(problem)
    assert len(alteration_space(problem).within(4.0)[1]) > 5_000
    result = solve(problem, budgets=[3.0, 4.0])
    assert not result.warnings
    for point in result.curve:
        assert point.certified_by == "incremental"
        assert point.status == "optimal"
        assert point.probability == pytest.approx(TRAP9_EXHAUSTIVE[point.budget], abs=1e-7)
        assert point.upper_bound == pytest.approx(point.probability, abs=1e-9)
        assert point.cost <= point.budget


def test_a_levelled_curve_is_proven_by_its_largest_budget(monkeypatch):
    """The paper's grid levels off at 0.863622 from budget 4 (the paper's Table: four sensors
    altered are all it takes). Once budgets 4 and 5 are certified at that value, the largest
    budget is solved next (7: the front door clamps 8 to what the costliest alteration needs)
    and proves 6 without a search of its own; the curve is the paper's and exhaustive
    search's."""
    searched = count_searches(monkeypatch)
    budgets = list(range(9))
    result = solve(paper_grid(5), budgets=budgets, method="branch-and-bound")
    assert searched == [0, 1, 2, 3, 4, 5, 7]
    monkeypatch.undo()
    reference = solve(paper_grid(5), budgets=budgets, method="exhaustive")
    for mine, theirs in zip(result.curve, reference.curve, strict=True):
        assert mine.status.value == "optimal"
        assert mine.probability == pytest.approx(theirs.probability, abs=1e-9)
        assert mine.cost <= mine.budget
    assert [round(p.probability, 6) for p in result.curve[4:]] == [0.863622] * 5


def test_a_curve_that_rises_again_after_a_level_is_still_searched_budget_by_budget():
    """Knapsack items (weight, value) (1, 3), (3, 5), (3, 0.5): budgets 1 and 2 level at 3,
    then the curve rises (5 at 3, 8 from 4). The largest budget, solved next, is higher than
    the level, so nothing between is filled from it; every budget is the brute-force optimum
    (the reduction: the best packing's value over twice the values' sum)."""
    weights, values = [1.0, 3.0, 3.0], [3.0, 5.0, 0.5]
    problem = knapsack(weights, values, capacity=6.0)
    budgets = [1.0, 2.0, 3.0, 4.0, 5.0, 6.0]
    result = solve(problem, budgets=budgets, method="branch-and-bound")
    for point in result.curve:
        best = max(
            sum(values[i] for i in subset)
            for r in range(4)
            for subset in itertools.combinations(range(3), r)
            if sum(weights[i] for i in subset) <= point.budget
        )
        assert point.status.value == "optimal"
        assert point.probability == pytest.approx(best / (2 * sum(values)), rel=1e-9)


def test_an_earlier_stage_level_sends_the_largest_budget_first(monkeypatch):
    """Given budget 4's certified answer (as auto hands it over) and seeds no better than it,
    budgets 5..7 of the paper's grid take one search, of budget 7, which proves them all at
    the paper's 0.863622 (exhaustive search agrees)."""
    problem = paper_grid(5)
    solver = BranchAndBoundSolver()
    (below,) = solver.solve(problem, [4.0])
    searched = count_searches(monkeypatch)
    budgets = [5.0, 6.0, 7.0]
    answers = solver.solve(problem, budgets, seeds=[below.alteration] * 3, below=below)
    assert searched == [7.0]
    reference = ExhaustiveSolver().solve(problem, budgets)
    for mine, theirs in zip(answers, reference, strict=True):
        assert mine.status.value == "optimal"
        assert decoy_probability(problem, mine.alteration) == pytest.approx(
            theirs.solver_probability, abs=1e-9
        )
        assert mine.upper_bound == pytest.approx(theirs.solver_probability, abs=1e-9)
    assert round(answers[0].solver_probability, 6) == 0.863622


def test_a_seed_above_the_level_keeps_the_budgets_in_order(monkeypatch):
    """Budget 2's answer (0.860130) as ``below``, but a seed worth more (budget 4's, 0.863622,
    as the paper's table says): the curve has not levelled, so budgets 3..5 go in order."""
    problem = paper_grid(5)
    solver = BranchAndBoundSolver()
    below, richer = solver.solve(problem, [2.0, 4.0])
    assert decoy_probability(problem, richer.alteration) > below.solver_probability + 1e-3
    searched = count_searches(monkeypatch)
    answers = solver.solve(problem, [3.0, 4.0, 5.0], seeds=[richer.alteration] * 3, below=below)
    assert searched == [3.0, 4.0, 5.0]
    assert [round(a.solver_probability, 6) for a in answers] == [0.862442, 0.863622, 0.863622]


@pytest.mark.parametrize("costs", ["uniform", "random"])
def test_a_segment_root_bound_with_every_option_affordable_bounds_every_budget(costs):
    """Every option costs 1 (``uniform``): the segment search's root at budget 1 offers every
    option and charges nothing, so its bound holds at every budget, budget 5's exhaustive
    optimum included, and the curve keeps it for the budgets it has not certified. With costs
    of 1..3 (``random``) budget 1 leaves options out, and the curve keeps nothing."""
    from misdirect.core.attack import prepare
    from misdirect.scenarios import sensor_grid
    from misdirect.solvers.branch_and_bound import _Curve
    from misdirect.solvers.deadline import Deadline
    from misdirect.solvers.engines.per_state import PerStateRelaxation
    from misdirect.solvers.engines.segment_relaxation import segment_relaxation
    from misdirect.solvers.engines.segment_search import SegmentSearch
    from misdirect.solvers.status import Status

    problem = sensor_grid(12, 6, costs=costs)
    seg = segment_relaxation(problem, 5.0)
    search = SegmentSearch(seg, 1.0)
    search.run(Deadline(60))
    assert search.root_bound is not None
    (top,) = ExhaustiveSolver().solve(problem, [5.0])
    instance = prepare(problem, 5.0)
    relax = PerStateRelaxation(problem, instance.space, instance.chain)
    curve = _Curve(instance, relax, policy=np.zeros(0, dtype=np.int64))
    curve.note_segment_root(search.root_bound, 1.0)
    open_answer = dataclasses.replace(top, status=Status.TIME_LIMIT, upper_bound=1.0)
    if costs == "uniform":
        assert top.solver_probability - 1e-12 <= search.root_bound < 1.0
        assert curve.every_budget_bound == search.root_bound
        assert curve.bounded(open_answer).upper_bound == max(
            search.root_bound, top.solver_probability
        )
    else:
        assert curve.every_budget_bound == np.inf
        assert curve.bounded(open_answer).upper_bound == 1.0


def test_a_budget_alone_gets_a_cheap_greedy_answer():
    """Issue 53: a budget asked alone under a short limit printed less than a smaller budget's
    optimum (budget 5 of a 40x40 grid below budget 3's). The greedy climb it now starts with
    takes the first improving move a step, one or two exact values each: from the unaltered
    chain of the 32-sensor grid it reaches the budget-2 optimum, which the low-rank
    enumeration certifies, with fewer exact values than a climb that tries every ranked
    candidate at each step would take."""
    from misdirect.core.attack import prepare
    from misdirect.scenarios.sensor_grid import sensor_grid
    from misdirect.solvers.branch_and_bound import GREEDY_TRIES, _hill_climb
    from misdirect.solvers.engines.per_state import PerStateRelaxation

    problem = sensor_grid(40, 32)
    optimum = solve(problem, method="incremental", budgets=[2.0]).curve[0]
    assert optimum.status == "optimal"
    instance = prepare(problem, 5.0)
    relax = PerStateRelaxation(problem, instance.space, instance.chain, instance.cycling)
    start = (0,) * len(relax.order)
    before = relax.evaluations
    picks, value = _hill_climb(relax, start, relax.value_of(start), 5.0, first_improvement=True)
    assert value >= optimum.probability * (1 - 1e-9)
    assert value == pytest.approx(relax.value_of(picks), rel=1e-12)
    altered = sum(k != 0 for k in picks)
    # a best-improvement step values its chain and every one of its GREEDY_TRIES candidates
    assert relax.evaluations - before < (GREEDY_TRIES + 1) * (altered + 1)
