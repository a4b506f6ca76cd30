"""The covering bound (issue 50): sound against exhaustive enumeration on random problems with
cycles (their controllers loop) and unequal costs, and never above the relaxation with every
sensor free, of which it is a refinement."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from misdirect import decoy_probability, solve
from misdirect.core.attack import prepare
from misdirect.core.memory import available_cores
from misdirect.scenarios import random_problem
from misdirect.scenarios.sensor_grid import sensor_grid
from misdirect.solvers.branch_and_bound import BranchAndBoundSolver
from misdirect.solvers.engines import covering
from misdirect.solvers.engines.covering import (
    CoverBound,
    CoverRule,
    covering_bound,
    maximal_group_sets,
    stratified_groups,
)
from misdirect.solvers.engines.per_state import PerStateRelaxation, relaxation_bound
from misdirect.solvers.options import SolveOptions
from misdirect.solvers.status import Status


def brute_force(problem, budget: float, fixed: dict[int, int] | None = None, space=None) -> float:
    """The best exact value over every alteration function within ``budget`` (Fractions
    decide the budget: CostModel.fits), with ``fixed`` choices (of ``space``) as given."""
    n = problem.pomdp.n_observations
    init = problem.pomdp.initial_observation  # never altered
    options = [
        [o] if o == init else list(np.flatnonzero(np.isfinite(problem.cost.row(o))))
        for o in range(n)
    ]
    for i, k in (fixed or {}).items():
        choice = space.choices[i]
        options[choice.observation] = [int(choice.targets[k])]
    best = 0.0
    for combo in itertools.product(*options):
        alpha = np.array(combo, dtype=np.int64)
        if problem.cost.fits(alpha, budget):
            best = max(best, decoy_probability(problem, alpha))
    return best


def test_maximal_group_sets_by_hand():
    """Groups costing 1, 1, 2 and 5 within 3: {0, 1} (2), {0, 2} (3), {1, 2} (3); the group of
    5 never fits. Every set that fits lies inside one of them."""
    sets = maximal_group_sets([1.0, 1.0, 2.0, 5.0], lambda total: total <= 3.0)
    assert sorted(sets) == [(0, 1), (0, 2), (1, 2)]
    assert maximal_group_sets([1.0, 1.0], lambda total: total <= 5.0) == [(0, 1)]
    assert maximal_group_sets([4.0], lambda total: total <= 3.0) == [()]


@pytest.mark.parametrize("case", range(24))
def test_the_covering_bound_holds_against_enumeration(case):
    rng = np.random.default_rng(case)
    budget = float(rng.choice([1.0, 1.5, 2.0, 3.0]))
    for seed in range(100 * case, 100 * case + 100):  # the first with a choice to make
        problem = random_problem(seed, states=8, actions=3, observations=5, nodes=3, budget=3.0)
        instance = prepare(problem, budget)
        if instance.space.choices:
            break
    relax = PerStateRelaxation(problem, instance.space, instance.chain, instance.cycling)
    scale = instance.space.scale
    choices = list(range(len(instance.space.choices)))
    groups = stratified_groups(choices, int(rng.integers(1, len(choices) + 1)))
    found = covering_bound(relax, groups, scale.cap(budget))
    assert found is not None
    truth = brute_force(problem, budget)
    assert found.bound >= truth - 1e-9 * max(truth, 1e-300), (seed, found.bound, truth)
    # a refinement of the relaxation with every sensor free (one union: every group)
    assert found.bound <= relaxation_bound(problem, budget) + 1e-12
    # every union split (twice over): still above the truth, never above the cover itself
    refined = covering_bound(relax, groups, scale.cap(budget), refine_above=0.0, refine_depth=2)
    assert refined is not None
    assert refined.bound >= truth - 1e-9 * max(truth, 1e-300), (seed, refined.bound, truth)
    assert refined.bound <= found.bound
    assert not found.given_up and found.solved >= len(found.unions)
    # a bound the caller has already, at or below the first union's: the cover stops there,
    # given up (no bound), and says what it spent
    stopped = covering_bound(relax, groups, scale.cap(budget), give_up_at=-1.0)
    assert stopped is not None and stopped.given_up
    assert len(stopped.unions) == 1 and stopped.solved == 1
    # a node: the first choice fixed to its first alteration, the budget left for the rest
    first = instance.space.choices[0]
    if first.size > 1 and first.costs[1] <= scale.cap(budget):
        left = scale.remaining(budget, float(first.costs[1]))
        rest = stratified_groups(choices[1:], 2)
        node = covering_bound(relax, rest, scale.cap(left), fixed={0: 1})
        assert node is not None
        truth = brute_force(problem, budget, {0: 1}, instance.space)
        assert node.bound >= truth - 1e-9 * max(truth, 1e-300), (seed, node.bound, truth)


@pytest.mark.parametrize("seed", range(6))
def test_refined_unions_hold_against_enumeration_on_a_larger_problem(seed):
    """Groups of several choices, so each union splits into halves and again: with unequal
    costs, a sub-union is every maximal set of halves whose cheapest options fit; the refined
    bound still lies above the best alteration (enumerated), and below the cover's own."""
    rng = np.random.default_rng(100 + seed)
    budget = float(rng.choice([1.0, 2.0, 3.0]))
    for attempt in range(100):
        problem = random_problem(
            50 * seed + attempt, states=10, actions=3, observations=6, nodes=3, budget=3.0
        )
        instance = prepare(problem, budget)
        if len(instance.space.choices) >= 4:
            break
    relax = PerStateRelaxation(problem, instance.space, instance.chain, instance.cycling)
    cap = instance.space.scale.cap(budget)
    choices = list(range(len(instance.space.choices)))
    groups = stratified_groups(choices, 2)
    found = covering_bound(relax, groups, cap)
    refined = covering_bound(relax, groups, cap, refine_above=0.0, refine_depth=3)
    assert found is not None and refined is not None
    truth = brute_force(problem, budget)
    assert refined.bound >= truth - 1e-9 * max(truth, 1e-300), (seed, refined.bound, truth)
    assert refined.bound <= found.bound


def test_a_choice_left_out_of_every_group_is_refused():
    """Left out, it would count as unaltered and the bound would not hold."""
    for seed in range(50):  # the first problem with two choices to make
        problem = random_problem(seed, states=8, actions=3, observations=5, nodes=3, budget=2.0)
        instance = prepare(problem, 2.0)
        if len(instance.space.choices) >= 2:
            break
    relax = PerStateRelaxation(problem, instance.space, instance.chain, instance.cycling)
    with pytest.raises(ValueError, match="in no group"):
        covering_bound(relax, [[0]], instance.space.scale.cap(2.0))


SEARCH_CASES = 16


@pytest.fixture
def covers_everywhere(monkeypatch):
    """Branch-and-bound covers every node the rule finds groups for, chains with end
    components or not (the rule's own test is the turn-back grid's below)."""
    monkeypatch.setattr(CoverRule, "applies", staticmethod(lambda cycling: True))


def _search_case(case: int):
    """(problem, the answers of branch-and-bound over its budgets) of one random case: a
    controller that loops, unequal costs."""
    rng = np.random.default_rng(1000 + case)
    budgets = sorted({float(rng.choice([1.0, 1.5, 2.0])), 3.0})
    problem = random_problem(2000 + case, states=8, actions=3, observations=5, nodes=3, budget=3.0)
    return problem, BranchAndBoundSolver(SolveOptions()).solve(problem, budgets)


@pytest.mark.parametrize("case", range(SEARCH_CASES))
def test_branch_and_bound_with_covers_finds_the_optimum(case, covers_everywhere):
    """Every answer of a search that prunes by covers is the brute force's optimum, and its
    bound lies above it, on random problems whose controllers loop, with unequal costs."""
    problem, answers = _search_case(case)
    for answer in answers:
        truth = brute_force(problem, answer.budget)
        assert answer.status == Status.OPTIMAL
        assert answer.solver_probability == pytest.approx(truth, rel=1e-9, abs=1e-12)
        assert answer.upper_bound >= truth - 1e-9 * max(truth, 1e-300)


@pytest.mark.parametrize("case", range(0, SEARCH_CASES, 4))
def test_covers_shared_among_forked_workers_find_the_optimum(case, covers_everywhere, monkeypatch):
    """The same with every cover's unions shared among two forked workers (from one union a
    worker): still the brute force's optimum, bounds above it."""
    monkeypatch.setattr(covering, "FORK_FROM", 1)
    shared = []
    real = covering.forked_map

    def counted(work, pieces, deadline=None):
        shared.append(pieces)
        return real(work, pieces, deadline)

    monkeypatch.setattr(covering, "forked_map", counted)
    problem, answers = _search_case(case)
    if sum(a.stats.covers for a in answers):
        assert max(shared) == min(2, available_cores())  # not vacuous: covers were shared
    for answer in answers:
        truth = brute_force(problem, answer.budget)
        assert answer.status == Status.OPTIMAL
        assert answer.solver_probability == pytest.approx(truth, rel=1e-9, abs=1e-12)
        assert answer.upper_bound >= truth - 1e-9 * max(truth, 1e-300)


def test_some_of_those_searches_covered_a_node(covers_everywhere):
    """The test above is not vacuous: covers ran in some of its searches, and some of them
    refined a union above the incumbent (each case searched here again, so that this holds
    whichever worker or order runs the tests)."""
    stats = [a.stats for case in range(SEARCH_CASES) for a in _search_case(case)[1]]
    assert any(s.covers > 0 for s in stats)
    assert any(s.cover_refined > 0 for s in stats)
    # every union refined is solved again in parts: more relaxations than unions
    assert all(s.cover_unions >= s.covers for s in stats)


def test_the_root_of_a_turn_back_grid_is_covered():
    """On a grid where robots turn back (end components), the per-state bound at budget 2 reads
    about 1.0; branch-and-bound covers its root (the rule applies on its own) and reports a
    bound far below, still above the optimum of the low-rank enumeration (another engine)."""
    problem = sensor_grid(10, 12, goal="inside")
    answer = BranchAndBoundSolver(SolveOptions(), max_nodes=1).solve(problem, [2.0])[0]
    optimum = solve(problem, method="incremental", budgets=[2.0]).curve[0]
    assert optimum.status == "optimal"
    stats = answer.stats
    assert stats.root_bound > 0.99
    assert stats.covers == 1 and stats.root_cover_bound is not None
    assert optimum.probability <= stats.root_cover_bound < 0.9
    assert optimum.probability <= answer.upper_bound <= stats.root_cover_bound


def test_an_open_budget_says_what_holds_its_bound_up(monkeypatch):
    """``weakest_bound``: ``time`` where the root was never bounded, null once certified, and
    on a node-limited search without covers whichever of ``relaxation`` and ``proof`` its
    counts say (a proof that fell back to 1.0 is counted in ``trivial_bounds``)."""
    from misdirect.solvers.deadline import Deadline

    problem = sensor_grid(10, 12, goal="inside")
    expired = BranchAndBoundSolver(SolveOptions()).solve(problem, [2.0], deadline=Deadline(0.0))
    assert expired[0].status != Status.OPTIMAL
    assert expired[0].stats.weakest_bound == "time"
    certified = BranchAndBoundSolver(SolveOptions()).solve(problem, [1.0])[0]
    assert certified.status == Status.OPTIMAL and certified.stats.weakest_bound is None
    monkeypatch.setattr(CoverRule, "applies", staticmethod(lambda cycling: False))
    open_ = BranchAndBoundSolver(SolveOptions(), max_nodes=1).solve(problem, [2.0])[0]
    stats = open_.stats
    assert open_.status != Status.OPTIMAL and stats.covers == 0
    if stats.weakest_bound == "proof":
        assert stats.trivial_bounds > 0 and open_.upper_bound >= 1 - 1e-6
    else:
        assert stats.weakest_bound == "relaxation"


@pytest.fixture
def proofs_fail(monkeypatch):
    """Every relaxation's proof falls back to the objective's largest value, as the proof of
    {0, 11, 15} on the 64-sensor turn-back grid does (a chain that lingers past what doubles
    resolve): only the exact valuation of a union's alterations can bound it then."""
    from misdirect.solvers.engines.policy_iteration import MaxReachability

    monkeypatch.setattr(MaxReachability, "proven_bound", lambda self, *a, **k: self.top)


@pytest.mark.parametrize("case", range(12))
def test_unions_whose_proof_fails_are_valued_exactly(case, proofs_fail):
    """With every proof failed, each union of a cover is small and valued alteration by
    alteration: the cover is then the best alteration within the budget itself (every one lies
    inside some union, and each union's best is one of them), brute force's optimum, below
    the objective's largest value; refined unions too. Also at a node (one choice fixed)."""
    rng = np.random.default_rng(500 + case)
    budget = float(rng.choice([1.0, 1.5, 2.0, 3.0]))
    for seed in range(100 * case, 100 * case + 100):  # two choices, the optimum below the top
        problem = random_problem(seed, states=8, actions=3, observations=5, nodes=3, budget=3.0)
        instance = prepare(problem, budget)
        if len(instance.space.choices) < 2:
            continue
        relax = PerStateRelaxation(problem, instance.space, instance.chain, instance.cycling)
        truth = brute_force(problem, budget)
        if truth < relax.mdp.top:  # else a failed proof and a bound could not be told apart
            break
    assert truth < relax.mdp.top
    cap = instance.space.scale.cap(budget)
    choices = list(range(len(instance.space.choices)))
    for n_groups, above in ((len(choices), np.inf), (2, 0.0)):
        groups = stratified_groups(choices, n_groups)
        found = covering_bound(relax, groups, cap, refine_above=above, refine_depth=2)
        assert found is not None and found.enumerated > 0
        assert found.bound == pytest.approx(truth, rel=1e-9, abs=1e-12), (seed, found, truth)
    first = instance.space.choices[0]
    if first.size > 1 and first.costs[1] <= cap:
        left = instance.space.scale.remaining(budget, float(first.costs[1]))
        node = covering_bound(relax, [choices[1:]], instance.space.scale.cap(left), fixed={0: 1})
        assert node is not None
        truth = brute_force(problem, budget, {0: 1}, instance.space)
        assert node.bound == pytest.approx(truth, rel=1e-9, abs=1e-12), (seed, node, truth)


def test_a_failed_union_above_the_limit_keeps_the_trivial_bound(proofs_fail, monkeypatch):
    """Where a union has more alterations than the limit, nothing is enumerated: the failed
    proof's bound, the objective's largest value, stands (sound, not tight)."""
    from misdirect.solvers.engines import covering

    monkeypatch.setattr(covering, "MAX_ENUMERATED", 1)  # only the unaltered alteration fits
    for seed in range(50):
        problem = random_problem(seed, states=8, actions=3, observations=5, nodes=3, budget=2.0)
        instance = prepare(problem, 2.0)
        if len(instance.space.choices) >= 2:
            break
    relax = PerStateRelaxation(problem, instance.space, instance.chain, instance.cycling)
    choices = list(range(len(instance.space.choices)))
    found = covering_bound(relax, [choices], instance.space.scale.cap(2.0))
    assert found is not None
    assert found.enumerated == 0 and found.bound == relax.mdp.top


def test_a_union_is_enumerated_alteration_by_alteration_by_hand():
    """Three choices with unit-cost options: the alterations within 1 are the unaltered one and
    each single option (1 + the options of the three), within 2 also each pair of options of
    two different choices."""
    from misdirect.solvers.engines.covering import _alterations

    problem = sensor_grid(8, 8, goal="inside")
    instance = prepare(problem, 2.0)
    relax = PerStateRelaxation(problem, instance.space, instance.chain, instance.cycling)
    scale = instance.space.scale
    sizes = [len(relax.affordable(i, scale.cap(2.0))) for i in range(3)]
    assert all(relax.option_cost[relax.first_option[i] + 1 :].max() == 1.0 for i in range(1))
    for budget, expected in (
        (1.0, 1 + sum(sizes)),
        (2.0, 1 + sum(sizes) + sum(a * b for a, b in itertools.combinations(sizes, 2))),
    ):
        cap = scale.cap(budget)
        found = _alterations(relax, [0, 1, 2], cap, lambda t, c=cap: scale.fits(t, c), 10_000)
        assert found is not None and len(found) == expected
        assert len({tuple(sorted(p.items())) for p in found}) == expected  # each once
        assert _alterations(relax, [0, 1, 2], cap, lambda t, c=cap: scale.fits(t, c), 3) is None


def test_a_cover_given_up_is_tried_again_with_finer_groups(monkeypatch):
    """The first cover of a search sizes its groups by a guess; where it gives up, what it
    measured sizes a second try at the same node, with more groups (the guess here made
    too slow on purpose, and the first cover made to give up: the second try's groups must
    be finer, and its bound is the root's, between the optimum and 0.9 as above)."""
    import misdirect.solvers.branch_and_bound as bb

    calls: list[int] = []
    real = bb.covering_bound

    def first_gives_up(relax, groups, cap, fixed, deadline, **options):
        calls.append(len(groups))
        found = real(relax, groups, cap, fixed, deadline, **options)
        if len(calls) == 1:  # given up at once, one cheap union solved
            return CoverBound(found.bound, found.unions[:1], solved=1, given_up=True)
        return found

    allowed: list[int] = []
    unions_allowed = CoverRule.unions_allowed

    def guessed_slow_at_first(rule, seconds_left, seconds_per_union):
        # the first guess affords 4 unions: coarse groups; then the measured time decides
        allowed.append(4 if not allowed else unions_allowed(rule, seconds_left, seconds_per_union))
        return allowed[-1]

    monkeypatch.setattr(bb, "covering_bound", first_gives_up)
    monkeypatch.setattr(CoverRule, "unions_allowed", guessed_slow_at_first)
    problem = sensor_grid(10, 12, goal="inside")
    answer = BranchAndBoundSolver(SolveOptions(time_limit=60), max_nodes=1).solve(problem, [2.0])
    stats = answer[0].stats
    assert len(calls) == 2 and calls[1] > calls[0]
    assert stats.covers_given_up == 1 and stats.covers == 1
    optimum = solve(problem, method="incremental", budgets=[2.0]).curve[0]
    assert stats.root_cover_bound is not None
    assert optimum.probability <= stats.root_cover_bound < 0.9
