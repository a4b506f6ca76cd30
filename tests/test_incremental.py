"""Enumeration with low-rank (Woodbury) updates agrees with plain enumeration everywhere,
models that can cycle without reaching the decoy included."""

from pathlib import Path

import numpy as np
import pytest

from misdirect import load_problem, solve
from misdirect.core.attack import prepare
from misdirect.scenarios import paper_grid, random_problem, sensor_grid
from misdirect.solvers.deadline import Deadline
from misdirect.solvers.incremental import IncrementalSolver

EXAMPLES = Path(__file__).parent.parent / "examples"


@pytest.mark.parametrize("n", [5, 7, 9, 15])
def test_grid_curve_equals_exhaustive(n):
    budgets = list(range(8))
    mine = solve(paper_grid(n), method="incremental", budgets=budgets)
    oracle = solve(paper_grid(n), method="exhaustive", budgets=budgets)
    assert not mine.warnings
    for a, b in zip(mine.curve, oracle.curve, strict=True):
        assert a.probability == pytest.approx(b.probability, abs=1e-9)
        assert a.solver_probability == pytest.approx(a.probability, abs=1e-9)
        assert a.cost <= a.budget


def random_suite(count):
    """(seed, problem) of small random models, a share of them with end components."""
    for seed in range(count):
        rng = np.random.default_rng(50_000 + seed)
        yield (
            seed,
            random_problem(
                seed + 1000,
                states=int(rng.integers(3, 9)),
                actions=int(rng.integers(1, 4)),
                observations=int(rng.integers(2, 5)),
                nodes=int(rng.integers(1, 4)),
            ),
        )


def test_random_models_equal_exhaustive():
    cycling = 0
    for seed, problem in random_suite(200):
        budgets = [0.0, 1.0, 2.5, 4.0]
        mine = solve(problem, method="incremental", budgets=budgets)
        cycling += bool(prepare(problem, 4.0).cycling.any())
        oracle = solve(problem, method="exhaustive", budgets=budgets)
        for a, b in zip(mine.curve, oracle.curve, strict=True):
            assert a.probability == pytest.approx(b.probability, abs=1e-9), (seed, a.budget)
            # the updated value it claimed is the exact value of what it returned
            assert a.solver_probability == pytest.approx(a.probability, abs=1e-9), seed
    assert cycling >= 25  # the suite exercises closed classes


def test_a_trap_loop_is_valued_exactly():
    """The trap example (its description derives 0.1 and 0.4 by hand): the base chain cycles
    in ``loop`` forever, and the alteration that frees it changes a closed class's row."""
    trap = load_problem(EXAMPLES / "trap.yaml")
    answers = IncrementalSolver().solve(trap, [0.0, 1.0])
    assert [a.solver_probability for a in answers] == pytest.approx([0.1, 0.4], abs=1e-12)
    assert all(a.status == "optimal" for a in answers)
    result = solve(trap, budgets=[0, 1])
    assert [p.probability for p in result.curve] == pytest.approx([0.1, 0.4], abs=1e-12)


def test_auto_uses_updates_on_the_grid():
    result = solve(paper_grid(25), budgets=range(8))
    assert result.certified_by == "incremental"
    assert result.stats["factorisations"] == 3  # one per choice for the blank reading


@pytest.mark.parametrize("compiled", [True, False])
@pytest.mark.parametrize("chunk_entries", [1, 4_000_000])
@pytest.mark.parametrize("seed", range(8))
def test_every_corrected_value_equals_a_dense_solve(seed, chunk_entries, compiled, monkeypatch):
    """The Woodbury corrections, against a dense solve of every alteration's chain: one
    alteration per batch (``chunk_entries=1``) and batches padded to mixed widths, by the
    compiled loop and by its numpy twin; the alterations' tree indexed a few entries at a
    time (odd seeds) or at once."""
    import scipy.sparse as sp

    from misdirect.core.alterations import AlterationSpace, ObservationChoices
    from misdirect.solvers.engines import lowrank_updates
    from misdirect.solvers.engines.lowrank_updates import add_corrections, row_deltas

    if seed % 2:
        monkeypatch.setattr(lowrank_updates, "TREE_CHUNK", 5)  # chunks split alterations

    rng = np.random.default_rng(seed)
    m = 14
    groups_of = [rng.integers(0, 10**6, size=int(rng.integers(1, 4))) for _ in range(m)]
    owner = np.repeat(np.arange(m), [len(g) for g in groups_of])
    rows = rng.random((owner.size, m)) * (rng.random((owner.size, m)) < 0.3)
    rows *= (0.85 * rng.random(owner.size) / np.maximum(rows.sum(axis=1), 1e-12))[:, None]
    to_target = 0.95 - rows.sum(axis=1) - 0.1 * rng.random(owner.size)
    inside = sp.csr_matrix(rows)
    first_group = np.searchsorted(owner, np.arange(m))
    base_groups = first_group.copy()  # every state's first group in the base
    regions = np.split(rng.permutation(m)[:9], [2, 3, 6])  # four inner observations
    n_options = [int(rng.integers(2, 4)) for _ in regions]
    groups = []
    for region, size in zip(regions, n_options, strict=True):
        table = np.empty((region.size, size), dtype=np.int64)
        table[:, 0] = base_groups[region]
        for k in range(1, size):
            picks = [rng.integers(len(groups_of[q])) for q in region]
            table[:, k] = first_group[region] + np.array(picks)
        groups.append(table)
    inner_rows = np.concatenate(regions)

    def solve_with(groups_per_state):
        system = np.eye(m) - rows[groups_per_state]
        return np.linalg.solve(system, to_target[groups_per_state])

    base = np.eye(m) - rows[base_groups]
    x0 = np.linalg.solve(base, to_target[base_groups])
    unit = np.zeros((m, inner_rows.size))
    unit[inner_rows, np.arange(inner_rows.size)] = 1.0
    W = np.linalg.solve(base, unit)
    deltas = row_deltas(groups, base_groups[inner_rows], inside, to_target, x0, W)
    free = AlterationSpace(  # every option costs 0: every alteration, each once
        tuple(ObservationChoices(j, np.arange(k), np.zeros(k)) for j, k in enumerate(n_options))
    )
    altered = free.altered_within(0.0)  # options that change no row included
    table = [altered.picks(a, len(n_options)) for a in range(altered.costs.size)]
    assert len({tuple(row) for row in table}) == int(np.prod(n_options))
    start = int(rng.integers(m))
    found = np.full(len(table), x0[start])
    done = add_corrections(
        found, altered, deltas, W[start], chunk_entries=chunk_entries, compiled=compiled
    )
    assert done.all()
    for row, value in zip(table, found, strict=True):
        chosen = base_groups.copy()
        for region, group, k in zip(regions, groups, row, strict=True):
            chosen[region] = group[:, k]
        assert value == pytest.approx(solve_with(chosen)[start], abs=1e-12)


def test_small_enumerations_leave_the_compiled_loop_alone(monkeypatch):
    """Under ``COMPILED_FROM`` alterations the numpy twin corrects, so a small solve never pays
    numba's load; its curve is the compiled loop's (bounds within rounding)."""
    from misdirect.solvers.engines import lowrank, lowrank_updates

    calls = []
    compiled_loop = lowrank_updates._schur_corrections

    def counted(*args):
        calls.append(args[-1].size)
        compiled_loop(*args)

    monkeypatch.setattr(lowrank_updates, "_schur_corrections", counted)
    budgets = list(range(8))
    small = solve(paper_grid(15), budgets=budgets)
    assert small.certified_by == "incremental" and not calls
    monkeypatch.setattr(lowrank, "COMPILED_FROM", 0)
    loop = solve(paper_grid(15), budgets=budgets)
    assert calls
    for a, b in zip(small.curve, loop.curve, strict=True):
        assert (a.status, a.alteration, a.probability) == (b.status, b.alteration, b.probability)
        assert a.upper_bound == pytest.approx(b.upper_bound, abs=1e-14)


@pytest.mark.parametrize("seed", range(6))
def test_altered_entries_list_every_affordable_alteration_once(seed):
    """The sparse listing against itertools.product over the options: the same alterations
    (each once, with its cost), dropped options left out, and ``limit`` exact."""
    import itertools

    from misdirect.core.alterations import AlterationSpace, ObservationChoices

    rng = np.random.default_rng(seed)
    sizes = rng.integers(1, 4, size=int(rng.integers(2, 7)))
    choices = tuple(
        ObservationChoices(i, np.arange(s), np.r_[0.0, rng.choice([0.0, 0.5, 1.0, 2.0], s - 1)])
        for i, s in enumerate(sizes)
    )
    space = AlterationSpace(choices)
    indices = list(rng.permutation(len(choices))[: len(choices) - 1])
    usable = rng.random((len(indices), 3)) < 0.7
    budget = 2.0
    expected = {}
    for picks in itertools.product(*(range(choices[i].size) for i in indices)):
        cost = sum(choices[i].costs[k] for i, k in zip(indices, picks, strict=True))
        if cost <= budget and all(k == 0 or usable[j, k] for j, k in enumerate(picks)):
            expected[picks] = cost
    altered = space.altered_within(budget, indices, usable=usable)
    listed = [tuple(altered.picks(a, len(indices))) for a in range(altered.costs.size)]
    assert sorted(listed) == sorted(expected)
    assert [expected[p] for p in listed] == pytest.approx(altered.costs.tolist())
    assert np.all(altered.option >= 1)
    for a in range(1, altered.costs.size):  # a parent: the alteration without its last entry
        last = np.searchsorted(altered.alteration, a, side="right") - 1
        without = altered.picks(a, len(indices))
        without[altered.choice[last]] = 0
        assert np.array_equal(altered.picks(altered.parent[a], len(indices)), without)
    assert np.all(np.diff(altered.parent[1:]) >= 0)  # the children of a parent consecutive
    assert space.altered_within(budget, indices, limit=len(expected) - 1, usable=usable) is None
    assert space.altered_within(budget, indices, limit=len(expected), usable=usable) is not None


def brute_force_with(problem, instance, budget, fixed):
    """Best exact value over the alterations within ``budget`` that agree with ``fixed``,
    each evaluated by a full solve (no updates)."""
    from misdirect.core.evaluate import decoy_probability

    table, costs = instance.space.within(budget)
    agree = np.ones(len(costs), dtype=bool)
    for i, k in fixed.items():
        agree &= table[:, i] == k
    return max(
        decoy_probability(problem, instance.space.alteration(problem, row)) for row in table[agree]
    )


@pytest.mark.parametrize(
    "n, k, seed, costs", [(7, 6, 1, "uniform"), (8, 8, 2, "random"), (9, 10, 4, "random")]
)
def test_best_with_fixed_choices_equals_brute_force(n, k, seed, costs):
    """Subtrees of a search, enumerated with bases kept between calls (a later call updates
    a kept base in low rank): each best equals the brute-force best of that subtree."""
    from misdirect.core.attack import prepare
    from misdirect.core.evaluate import decoy_probability
    from misdirect.scenarios import sensor_grid
    from misdirect.solvers.deadline import Deadline
    from misdirect.solvers.engines.lowrank import BasisCache, LowRankEnumeration

    problem = sensor_grid(n, k, seed=seed, costs=costs, memory=3 + seed % 3)
    budget = 3.0
    instance = prepare(problem, budget)
    choices = instance.space.choices
    rng = np.random.default_rng(seed)
    bases = BasisCache()
    enumeration = LowRankEnumeration(instance)
    checked = roomy = 0
    for _ in range(12):
        picked = rng.choice(len(choices), size=min(2, len(choices)), replace=False)
        fixed = {int(i): int(rng.integers(choices[i].size)) for i in picked}
        if sum(choices[i].costs[o] for i, o in fixed.items()) > budget:
            continue
        value, vector, complete, _ = enumeration.best_with(budget, fixed, Deadline(None), bases)
        assert complete
        assert all(vector[i] == o for i, o in fixed.items())
        assert sum(c.costs[o] for c, o in zip(choices, vector, strict=True)) <= budget + 1e-9
        exact = decoy_probability(problem, instance.space.alteration(problem, vector))
        assert value == pytest.approx(exact, abs=1e-9)
        assert value == pytest.approx(brute_force_with(problem, instance, budget, fixed), abs=1e-9)
        checked += 1
        left = budget - sum(choices[i].costs[o] for i, o in fixed.items())
        inner = [i for i in enumeration.natural_inner if i not in fixed]
        roomy += any(min(choices[i].costs[1:]) <= left for i in inner)
    assert checked >= 4
    # a subtree with room for inner alterations uses a kept base (the others are one
    # alteration each, valued on its own chain)
    assert bool(bases._bases) == (roomy > 0)


class _CancelAfter:
    """A cancel token that reads as cancelled from its ``reads``-th look on: a deadline that
    passes part way through an enumeration, at a point that does not depend on the clock."""

    def __init__(self, reads: int):
        self.reads = reads

    @property
    def cancelled(self) -> bool:
        self.reads -= 1
        return self.reads < 0


def test_an_enumeration_cut_short_offers_the_best_it_valued_and_proves_nothing():
    """Cut at every point of its run, a subtree's enumeration returns nothing, or an
    alteration of the subtree whose value is its exact value and which is flagged as no
    proof; left to finish, it is the brute-force best. Some cut returns a candidate."""
    from misdirect.core.attack import prepare
    from misdirect.core.evaluate import decoy_probability
    from misdirect.scenarios import sensor_grid
    from misdirect.solvers.deadline import Deadline
    from misdirect.solvers.engines.lowrank import BasisCache, LowRankEnumeration

    problem = sensor_grid(7, 6, seed=1, memory=4)
    budget = 2.0
    instance = prepare(problem, budget)
    choices = instance.space.choices
    enumeration = LowRankEnumeration(instance)
    fixed = {enumeration.natural_inner[0]: 1}
    best = brute_force_with(problem, instance, budget, fixed)
    candidates = 0
    for reads in range(0, 400, 7):
        deadline = Deadline(None, cancel=_CancelAfter(reads))  # type: ignore[arg-type]
        found = enumeration.best_with(budget, fixed, deadline, BasisCache())
        if found is None:
            continue
        value, vector, complete, _ = found
        assert all(vector[i] == o for i, o in fixed.items())
        assert sum(c.costs[o] for c, o in zip(choices, vector, strict=True)) <= budget
        exact = decoy_probability(problem, instance.space.alteration(problem, vector))
        assert value == pytest.approx(exact, abs=1e-9)
        assert value <= best + 1e-9
        if complete:
            assert value == pytest.approx(best, abs=1e-9)
        else:
            candidates += 1
    assert candidates > 0
    value, _, complete, _ = enumeration.best_with(budget, fixed, Deadline(None), BasisCache())
    assert complete and value == pytest.approx(best, abs=1e-9)


def test_every_value_on_chains_with_end_components_equals_its_chain():
    """Each value the enumeration lists (low-rank, or exact where an alteration may close a
    class, and the extensions of those), against the exact value of its own chain; the
    suite has alterations that do close a class."""
    from misdirect.core.evaluate import decoy_probability
    from misdirect.solvers.engines.lowrank import LowRankEnumeration

    exactly, by_update = 0, 0
    for seed, problem in random_suite(120):
        instance = prepare(problem, 4.0)
        if not instance.cycling.any():
            continue
        enumeration = LowRankEnumeration(instance)
        found = enumeration.run(4.0)
        exactly += enumeration.exact_evaluations > 0
        by_update += enumeration.trap_updates > 0
        space = instance.space
        for index in range(len(found.values)):
            alteration = space.alteration(problem, found.picks(index))
            exact = decoy_probability(problem, alteration)
            assert found.values[index] == pytest.approx(exact, abs=1e-9), (seed, index)
    # both routes are exercised: a class closed by low rank (its trapped rows emptied), and
    # one opened (a base closed class's row changed), solved whole
    assert exactly >= 5 and by_update >= 5


def test_a_cut_curve_keeps_its_small_budgets_proven(monkeypatch):
    """With a time limit the curve is enumerated budget by budget: a run cut short at the top
    budget leaves the smaller ones proven, with the optimum that exhaustive search (every
    alteration evaluated exactly) gives (and the cut one is not called optimal)."""
    from misdirect.solvers import schedule

    problem = sensor_grid(8, 6, seed=0)
    alone = {b: solve(problem, method="exhaustive", budgets=[b]).curve[-1] for b in (0, 1)}
    _runs_out_of_time_from(monkeypatch, 2)  # the run at budget 2 runs out of time at once
    monkeypatch.setattr(schedule, "STAGE_FROM", 0)  # each budget its own run, however small
    curve = solve(problem, method="incremental", budgets=[0, 1, 2], time_limit=600).curve
    for point in curve[:2]:
        assert point.status == "optimal"
        assert point.probability == pytest.approx(alone[point.budget].probability, abs=1e-12)
    assert curve[2].status != "optimal"


def test_an_enumeration_that_hands_over_never_calls_a_budget_it_skipped_proven(monkeypatch):
    """A staged enumeration with a search to hand over to stops before a budget that will
    not fit; the budgets it skipped are not proven by the smaller runs (which never listed
    their costlier alterations), and auto's search then certifies exhaustive search's optima."""
    from misdirect.solvers import schedule

    problem = sensor_grid(8, 6, seed=0)
    oracle = solve(problem, method="exhaustive", budgets=[0, 1, 2]).curve
    assert oracle[2].probability > oracle[0].probability + 1e-6  # budget 2 gains something

    monkeypatch.setattr(schedule, "next_level_fits", lambda *args, **kwargs: False)
    monkeypatch.setattr(schedule, "STAGE_FROM", 0)  # each budget its own run, however small
    solver = IncrementalSolver(hand_over=True)
    found = solver.solve(problem, [0, 1, 2], deadline=Deadline(600))
    assert found[0].status == "optimal"
    assert found[0].solver_probability == pytest.approx(oracle[0].probability, abs=1e-12)
    for point, truth in zip(found[1:], oracle[1:], strict=True):
        assert point.status != "optimal"
        assert point.upper_bound >= truth.probability - 1e-12

    curve = solve(problem, budgets=[0, 1, 2], time_limit=600).curve
    for point, truth in zip(curve, oracle, strict=True):
        assert point.status == "optimal"
        assert point.probability == pytest.approx(truth.probability, abs=1e-12)


def test_a_small_budget_is_proven_by_the_next_run_when_that_one_is_cheap(monkeypatch):
    """Budgets whose next budget has few alterations are not enumerated on their own: the one
    run at the larger budget proves them too, with the optima exhaustive search gives."""
    from misdirect.solvers.engines import lowrank

    problem = sensor_grid(8, 6, seed=0)
    oracle = solve(problem, method="exhaustive", budgets=[0, 1, 2]).curve
    tops = []
    original = lowrank.LowRankEnumeration.run

    def counted(self, top, *args, **kwargs):
        tops.append(top)
        return original(self, top, *args, **kwargs)

    monkeypatch.setattr(lowrank.LowRankEnumeration, "run", counted)
    found = IncrementalSolver().solve(problem, [0, 1, 2], deadline=Deadline(600))
    assert tops == [2]  # a few hundred alterations: one run
    for point, truth in zip(found, oracle, strict=True):
        assert point.status == "optimal"
        assert point.solver_probability == pytest.approx(truth.probability, abs=1e-12)


def test_auto_searches_what_its_enumeration_left_unproven_without_enumerating_it_again(
    monkeypatch,
):
    """A curve split into small budgets (enumerated) and large ones (searched): a small budget
    the enumeration leaves unproven goes to the search, not to another enumeration (which
    would leave it unproven again, and again), and the search certifies exhaustive's optima."""
    from misdirect.solvers import incremental, schedule

    problem = sensor_grid(8, 6, seed=0)
    budgets = [0, 1, 2, 3]
    oracle = solve(problem, method="exhaustive", budgets=budgets).curve
    space = prepare(problem, 3).space
    small = space.count_within(1, 10**9)
    monkeypatch.setattr(
        schedule, "enumeration_fits", lambda count, needed, deadline, **_: count <= small
    )
    _runs_out_of_time_from(monkeypatch, 1)  # every run above budget 0 runs out at once
    calls = []
    solve_enumeration = incremental.IncrementalSolver.solve

    def counted(self, *args, **kwargs):
        calls.append(1)
        return solve_enumeration(self, *args, **kwargs)

    monkeypatch.setattr(incremental.IncrementalSolver, "solve", counted)
    curve = solve(problem, budgets=budgets, time_limit=600).curve
    assert len(calls) == 1
    for point, truth in zip(curve, oracle, strict=True):
        assert point.status == "optimal"
        assert point.probability == pytest.approx(truth.probability, abs=1e-12)


def _runs_out_of_time_from(monkeypatch, budget: float) -> None:
    """From now on, every low-rank enumeration at ``budget`` or above finds its deadline
    passed at once."""
    from misdirect.solvers.engines import lowrank

    original = lowrank.LowRankEnumeration.run

    def cut(self, top, *args, **kwargs):
        if top >= budget:
            kwargs["deadline"] = Deadline(0.0)
        return original(self, top, *args, **kwargs)

    monkeypatch.setattr(lowrank.LowRankEnumeration, "run", cut)


@pytest.mark.parametrize("budget", [0.0, 1.0, 2.0])
def test_a_block_with_no_inner_alteration_is_valued_without_a_base_solve(monkeypatch, budget):
    """Where an outer pick leaves no budget for an inner alteration, its block is that one
    alteration: valued on its own chain, with no base solved for the inner rows (on a big map
    each base solves thousands of columns). Every value still equals its chain's, and a base
    is solved only for the blocks with inner alterations to value."""
    from misdirect.core.evaluate import decoy_probability
    from misdirect.solvers.engines import lowrank

    monkeypatch.setattr(lowrank, "INNER_ROWS", 12)  # most observations outer
    monkeypatch.setattr(lowrank, "INNER_ENTRIES", 0)
    solves = []
    real = lowrank.base_solve
    monkeypatch.setattr(lowrank, "base_solve", lambda *a: solves.append(1) or real(*a))
    problem = sensor_grid(8, 8, seed=3)  # uniform costs: every alteration costs 1
    instance = prepare(problem, 2.0)
    enumeration = lowrank.LowRankEnumeration(instance)
    assert enumeration.natural_outer and enumeration.natural_inner
    found = enumeration.run(budget)
    assert found.complete_for(budget)
    for index in range(len(found.values)):
        alteration = instance.space.alteration(problem, found.picks(index))
        assert found.values[index] == pytest.approx(
            decoy_probability(problem, alteration), abs=1e-9
        )
    # with uniform costs, a block has inner alterations iff its outer picks cost < budget
    outer_costs = found.costs[found.offsets[:-1]]  # each block's first: inner unaltered
    assert len(solves) == int((outer_costs < budget).sum())
    assert found.base_solves == len(solves)  # what the stats call factorisations
    # every alteration within the budget listed once: as many as the space counts
    assert len(found.values) == instance.space.count_within(budget, 10**6)


def test_a_run_with_a_share_stops_before_the_blocks_that_would_pass_it(monkeypatch):
    """With a search to hand its budget to, an enumeration stops before a block once the
    blocks left project past its share of the time (on a big map each is a base solve of
    thousands of columns). What it did is still proven: the budgets below the first outer
    pick it did not reach; without a share, or with a generous one, it values every block."""
    from misdirect.solvers.engines import lowrank

    monkeypatch.setattr(lowrank, "INNER_ROWS", 12)  # most observations outer: many blocks
    monkeypatch.setattr(lowrank, "INNER_ENTRIES", 0)
    problem = sensor_grid(8, 8, seed=3)
    instance = prepare(problem, 2.0)
    enumeration = lowrank.LowRankEnumeration(instance)
    whole = enumeration.run(2.0)
    assert len(whole.blocks) > 2 and whole.complete_for(2.0)
    assert len(enumeration.run(2.0, share=1e9).blocks) == len(whole.blocks)
    cut = enumeration.run(2.0, share=0.0)
    assert len(cut.blocks) == 1  # the first block always runs
    assert not cut.complete_for(2.0)
    assert cut.complete_for(0.0)  # the first block's outer pick is the unaltered one
    # what it proved is right: budget 0 is the unaltered chain, solved on its own
    from misdirect.core.evaluate import decoy_probability

    best = cut.best_within([0.0])[0]
    assert cut.values[best] == pytest.approx(
        decoy_probability(problem, problem.identity()), abs=1e-12
    )


def test_stacked_woodbury_systems_are_solved_and_their_conditioning_flagged():
    """One inverse per system gives each solution and its condition number: a well-conditioned
    system's solution is numpy's solve's, one above ILL_CONDITIONED and a singular one are
    flagged (NaN), and the singular one does not cost the others their values."""
    from misdirect.core import tolerance
    from misdirect.solvers.engines.lowrank_updates import solved_and_conditioned

    rng = np.random.default_rng(3)
    fine = np.eye(3) + 0.1 * rng.random((3, 3))
    ill = np.diag([1.0, 1.0, 1.0 / (100 * tolerance.ILL_CONDITIONED)])
    singular = np.array([[1.0, 2.0, 0.0], [2.0, 4.0, 0.0], [0.0, 0.0, 1.0]])
    rhs = rng.random((4, 3))
    for stack in ([fine, ill, fine], [fine, singular, ill, fine]):
        systems = np.stack(stack)
        right = rhs[: len(stack)]
        z, flagged = solved_and_conditioned(systems, right)
        expected_ill = [m is not fine for m in stack]
        assert flagged.tolist() == expected_ill
        for j, matrix in enumerate(stack):
            if matrix is fine:
                assert np.allclose(z[j], np.linalg.solve(matrix, right[j]), rtol=1e-13)
            else:
                assert np.isnan(z[j]).all()


def test_inner_rows_are_capped_by_what_each_chain_keeps(monkeypatch):
    """Without end components a base's ``W`` lives only while it is solved, so the inner
    choices may own more rows (to the transient cap, within the memory limit); with them it
    is kept per basis and the smaller cap holds. Sizes counted by hand from the regions."""
    from misdirect.core.memory import MEMORY_LIMIT_ENV
    from misdirect.solvers.engines import lowrank

    def inner_rows(instance):
        sizes = instance.live_states_per_observation
        chosen = lowrank.inner_choices(instance)
        return sum(int(sizes[instance.space.choices[i].observation]) for i in chosen)

    corner = prepare(sensor_grid(12, 16, seed=0), 2.0)
    turning = prepare(sensor_grid(10, 8, seed=0, goal="inside"), 2.0)
    assert not corner.cycling.any() and turning.cycling.any()
    monkeypatch.setattr(lowrank, "INNER_ROWS", 1)
    for instance in (corner, turning):
        n_live = int(instance.live.sum())
        monkeypatch.setattr(lowrank, "INNER_ENTRIES", 20 * n_live)
        monkeypatch.setattr(lowrank, "TRANSIENT_ENTRIES", 60 * n_live)
        monkeypatch.delenv(MEMORY_LIMIT_ENV, raising=False)
        cap = 20 if instance.cycling.any() else 60
        assert 0 < inner_rows(instance) <= cap
        # a memory limit too small for the transient cap leaves the kept one
        monkeypatch.setenv(MEMORY_LIMIT_ENV, "1K")
        assert 0 < inner_rows(instance) <= 20
    monkeypatch.delenv(MEMORY_LIMIT_ENV)
    monkeypatch.setattr(lowrank, "INNER_ENTRIES", 20 * int(corner.live.sum()))
    assert inner_rows(corner) > 20  # the bigger cap is used where W is not kept


@pytest.mark.parametrize("goal", ["corner", "inside"])
def test_a_kept_basis_keeps_w_only_where_rows_are_read_on_demand(goal):
    """Bases kept between a search's enumerations hold ``W`` (live states x inner rows) only
    on chains with end components, whose trap alterations read its rows; elsewhere the
    options' table and the start's row, and the subtrees' bests still equal brute force."""
    from misdirect.core.evaluate import decoy_probability
    from misdirect.solvers.engines.lowrank import BasisCache, LowRankEnumeration

    problem = sensor_grid(8, 6, seed=1, goal=goal)
    instance = prepare(problem, 2.0)
    enumeration = LowRankEnumeration(instance)
    bases = BasisCache()
    first = enumeration.natural_inner[0]
    fixed = {first: 1}
    value, vector, complete, _ = enumeration.best_with(2.0, fixed, Deadline(None), bases)
    assert complete
    (kept,) = bases._bases.values()
    assert (kept.basis.W is not None) == bool(instance.cycling.any())
    assert kept.basis.w_start is not None
    assert value == pytest.approx(brute_force_with(problem, instance, 2.0, fixed), abs=1e-9)
    exact = decoy_probability(problem, instance.space.alteration(problem, vector))
    assert value == pytest.approx(exact, abs=1e-9)


@pytest.mark.parametrize("goal", ["corner", "inside"])
def test_bases_within_counts_the_base_solves_of_a_run(goal):
    """A run's base solves are known before it starts: one per outer block with room for an
    inner alteration (what the staged enumeration weighs before its next budget)."""
    from misdirect.solvers.engines import lowrank

    problem = sensor_grid(8, 6, seed=2, goal=goal)
    instance = prepare(problem, 3.0)
    enumeration = lowrank.LowRankEnumeration(instance)
    # a small inner set leaves several outer choices, hence several blocks
    enumeration.natural_inner = enumeration.natural_inner[:3]
    enumeration.natural_outer = [
        i for i in range(len(instance.space.choices)) if i not in enumeration.natural_inner
    ]
    for top in (0.0, 1.0, 2.0, 3.0):
        found = enumeration.run(top)
        assert enumeration.bases_within(top) == found.base_solves
    assert found.base_solves > 1


def test_the_next_budget_is_enumerated_only_if_its_bases_fit_the_fair_share():
    """Few alterations are not enough when each of many bases costs seconds (a big map's base
    solves thousands of columns): the measured seconds per base count, as the fair share
    (half the time left) does."""
    from misdirect.solvers import schedule

    deadline = Deadline(20.0)  # fair share: about 10 s
    assert schedule.next_level_fits(300_000, 1, None, deadline)  # 1.5 s of updates
    assert schedule.next_level_fits(1_000, 1, schedule.Measured(4.0, 100, 1), deadline)  # 4 s
    # four bases of about 4 s each: 16 s
    assert not schedule.next_level_fits(1_000, 4, schedule.Measured(4.0, 100, 1), deadline)
    assert schedule.next_level_fits(1_000, 4, schedule.Measured(0.4, 100, 1), deadline)
    # a trusted rate (measured on RATE_SAMPLE alterations or more) counts too
    assert not schedule.next_level_fits(10**6, 1, schedule.Measured(1.0, 50_000, 1), deadline)


def test_where_the_search_cannot_see_the_budget_the_enumeration_is_costed_at_its_truer_rate():
    """A run that was mostly its base (0.8 of its 1.0 s) predicts 40 s for two million
    alterations at its whole rate, 8.8 s at its alterations' own; where the search's bound is
    blind to the budget (the caller says), the truer figure decides, against nine tenths of
    the time left instead of half."""
    from misdirect.solvers import schedule

    deadline = Deadline(20.0)  # half: about 10 s; nine tenths: about 18 s
    assert schedule.fair_share(deadline) <= 10.0
    assert 17.0 <= schedule.fair_share(deadline, search_sees_budget=False) <= 18.0
    mostly_base = schedule.Measured(1.0, 50_000, 1, base_seconds=0.8)
    assert not schedule.next_level_fits(2 * 10**6, 1, mostly_base, deadline)
    blind = {"search_sees_budget": False}
    assert schedule.next_level_fits(2 * 10**6, 1, mostly_base, deadline, **blind)
    # alterations that are slow on their own stay too slow: a million at 20 us is 20 s
    slow = schedule.Measured(1.0, 50_000, 1, base_seconds=0.0)
    assert not schedule.next_level_fits(10**6, 1, slow, deadline, **blind)
    # so do many bases at the measured seconds per base: 5 x 4 s
    bases = schedule.Measured(4.0, 100, 1, base_seconds=4.0)
    assert not schedule.next_level_fits(1_000, 5, bases, deadline, **blind)
    assert schedule.next_level_fits(1_000, 4, bases, deadline, **blind)


@pytest.mark.parametrize("goal", ["corner", "inside"])
def test_the_staged_enumeration_says_whether_the_search_sees_the_budget(goal, monkeypatch):
    """Only chains with end components (the turn-back grid) are costed as if the search's
    bound were blind, and the measured run carries the seconds of its bases."""
    from misdirect.solvers import schedule

    seen = []

    def record(count, bases, measured, deadline, *, search_sees_budget=True):
        seen.append((measured, search_sees_budget))
        return len(seen) < 2  # budget 1 runs (after budget 0's one alteration), not 2

    monkeypatch.setattr(schedule, "next_level_fits", record)
    monkeypatch.setattr(schedule, "STAGE_FROM", 0)
    problem = sensor_grid(8, 6, seed=1, goal=goal)
    assert prepare(problem, 2.0).cycling.any() == (goal == "inside")
    IncrementalSolver(hand_over=True).solve(problem, [0, 1, 2], deadline=Deadline(600))
    assert len(seen) == 2
    assert all(sees == (goal == "corner") for _, sees in seen)
    measured = seen[1][0]  # budget 1's run: a base solve and its alterations
    assert measured.base_solves >= 1
    assert 0.0 < measured.base_seconds <= measured.seconds
