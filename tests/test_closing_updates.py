"""Alterations that close a class (the robot trapped for ever, never reaching the decoy),
valued by low rank on chains with end components (issue 27): the base solve's update with the
trapped changed rows emptied. Every value against the exact solve of its own chain, the optima
against exhaustive search, and the loop that finds the safe states against the time limit."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from misdirect import solve
from misdirect.core.attack import prepare
from misdirect.core.evaluate import decoy_probability
from misdirect.scenarios import drone, sensor_grid
from misdirect.solvers.deadline import Deadline
from misdirect.solvers.engines import closed_classes
from misdirect.solvers.engines.lowrank import BasisCache, LowRankEnumeration

CASES = {
    "turn-back 6": (lambda: sensor_grid(6, 4, seed=0, goal="inside"), 3, None),
    "turn-back 8": (lambda: sensor_grid(8, 6, seed=1, goal="inside"), 2, None),
    # two alterations of three sensors almost trap the robot: their Woodbury systems read a
    # condition number of 1e11, and a low-rank update was 4e-7 off; they are valued exactly
    "turn-back 8, budget 3": (lambda: sensor_grid(8, 6, seed=1, goal="inside"), 3, None),
    "turn-back 10": (lambda: sensor_grid(10, 8, seed=2, goal="inside"), 2, None),
    # 13,945 alterations: a sample (about one in seven closes a class)
    "drone 5x5": (lambda: drone(5, agents=1, rows=2), 2, 700),
}


@pytest.mark.parametrize("case", list(CASES))
def test_every_value_equals_the_exact_value_of_its_chain(case):
    make, top, sample = CASES[case]
    problem = make()
    instance = prepare(problem, top)
    assert instance.cycling.any()
    enumeration = LowRankEnumeration(instance)
    found = enumeration.run(top)
    assert found.complete_for(top)
    assert enumeration.trap_updates > 0  # some alterations closed a class, valued by low rank
    indices = np.arange(found.values.size)
    if sample is not None:
        indices = np.random.default_rng(0).choice(indices, size=sample, replace=False)
    for index in indices.tolist():
        alteration = instance.space.alteration(problem, found.picks(index))
        exact = decoy_probability(problem, alteration)  # the chain solved on its own
        assert found.values[index] == pytest.approx(exact, abs=1e-9), index


@pytest.mark.parametrize(
    ("case", "top"), [("turn-back 6", 3), ("turn-back 8", 3), ("drone 5x5", 1)]
)
def test_the_curve_equals_exhaustive_search(case, top):
    problem = CASES[case][0]()
    budgets = list(range(top + 1))
    mine = solve(problem, method="incremental", budgets=budgets)
    oracle = solve(problem, method="exhaustive", budgets=budgets)
    for a, b in zip(mine.curve, oracle.curve, strict=True):
        assert a.status == "optimal"
        assert a.probability == pytest.approx(b.probability, abs=1e-9), a.budget
        assert a.solver_probability == pytest.approx(a.probability, abs=1e-9), a.budget


def test_kept_bases_with_fixed_sensors_value_closing_alterations_too():
    """A search's subtrees: a kept base updated in low rank for the fixed sensors, then each
    closing alteration's emptied rows read from that updated base. Each subtree's best
    against the best of its alterations, each solved exactly here."""
    problem = sensor_grid(8, 6, seed=1, goal="inside")
    budget = 3.0
    instance = prepare(problem, budget)
    choices = instance.space.choices
    table, costs = instance.space.within(budget)
    exact = np.array(
        [decoy_probability(problem, instance.space.alteration(problem, row)) for row in table]
    )
    enumeration = LowRankEnumeration(instance)
    bases = BasisCache()
    rng = np.random.default_rng(3)
    checked = 0
    for _ in range(12):
        picked = rng.choice(len(choices), size=2, replace=False)
        fixed = {int(i): int(rng.integers(1, choices[i].size)) for i in picked}
        agree = np.ones(len(costs), dtype=bool)
        for i, k in fixed.items():
            agree &= table[:, i] == k
        if not agree.any():
            continue
        answer = enumeration.best_with(budget, fixed, Deadline(None), bases)
        assert answer is not None
        value, vector, complete, _ = answer
        assert complete
        assert all(vector[i] == k for i, k in fixed.items())
        assert value == pytest.approx(exact[agree].max(), abs=1e-9)
        checked += 1
    assert checked >= 4
    assert enumeration.trap_updates > 0


class _ExpiresAt(Deadline):
    """A deadline that expires at its ``looks``-th look (no wall clock involved)."""

    def __init__(self, looks: int):
        super().__init__(None)
        self.looks, self.seen = looks, 0

    def expired(self) -> bool:
        self.seen += 1
        return self.seen >= self.looks


def test_the_safe_states_loop_stops_at_the_deadline():
    """Finding the safe states is a greatest fixed point, one pass per state removed at worst:
    it looks at the deadline every pass, and past it calls no state safe (every option then
    goes through the trap search, which stops at the deadline too)."""
    instance = prepare(sensor_grid(8, 6, seed=1, goal="inside"), 2)
    enumeration = LowRankEnumeration(instance)
    chosen = np.zeros(instance.chain.options.size, dtype=bool)
    chosen[enumeration.first_option[:-1]] = True
    inner = enumeration.natural_inner

    def safe(deadline: Deadline | None) -> np.ndarray:
        cycles = enumeration._solved_base(chosen, inner, deadline).cycles
        assert cycles is not None
        return cycles.classes.safe

    assert safe(None).any()
    assert not safe(Deadline(0.0)).any()
    looking = _ExpiresAt(2)  # passes the first look, expires at the second pass
    assert not safe(looking).any()
    assert looking.seen == 2
    # the whole enumeration with its time already up: nothing beyond the unaltered chain
    # is claimed complete, and it returns
    found = enumeration.run(2.0, deadline=Deadline(0.0))
    assert not found.complete_for(1.0)


@pytest.mark.parametrize("case", ["turn-back 6", "turn-back 8, budget 3", "drone 5x5"])
def test_the_trap_search_flags_exactly_the_alterations_that_close_or_open_a_class(case):
    """The trap search finds the alterations that close a class without listing every
    changed row of every alteration; checked against the definition, one chain each: an
    alteration closes a class when a changed state cannot reach a leaking row or a state that
    leaves under every alteration (or a base closed class). Those, the ones that change a
    row of a base closed class, and all their extensions are flagged, and no other."""
    from misdirect.core.model import reachable_from
    from misdirect.solvers.engines.closed_classes import with_extensions

    make, top, _ = CASES[case]
    problem = make()
    instance = prepare(problem, top)
    enumeration = LowRankEnumeration(instance)
    chosen = np.zeros(instance.chain.options.size, dtype=bool)
    chosen[enumeration.first_option[:-1]] = True
    inner = enumeration.natural_inner
    base = enumeration._solved_base(chosen, inner, None)
    cycles, table = base.cycles, base.deltas
    assert cycles is not None
    altered = instance.space.altered_within(float(top), inner)
    trap = enumeration._trap_search(altered, base, Deadline(None))
    assert trap.closes is not None

    inside, leaks = enumeration._inside, enumeration._leaks
    stop = cycles.classes.safe | cycles.classes.closed
    closing = np.zeros(altered.costs.size, dtype=bool)
    opening = np.zeros(altered.costs.size, dtype=bool)
    for a in range(altered.costs.size):
        groups = cycles.base_groups.copy()
        changed = []
        for e in np.flatnonzero(altered.alteration == a):
            j, k = altered.choice[e], altered.option[e]
            slots = table.flat_start[j, k] + np.arange(table.flat_length[j, k])
            groups[cycles.slot_state[slots]] = cycles.slot_group[slots]
            changed.extend(cycles.slot_state[slots].tolist())
        if not changed:
            continue
        moves = inside[groups].tocsr()
        exits = np.flatnonzero(leaks[groups] | stop)
        can_leave = reachable_from(moves.T.tocsr(), exits)
        closing[a] = not can_leave[changed].all()
        opening[a] = cycles.classes.closed[changed].any()
    expected = np.flatnonzero(with_extensions(altered.parent, np.flatnonzero(closing | opening)))
    assert closing.any()  # the case exercises it
    assert np.array_equal(trap.flagged, expected)
    assert np.array_equal(trap.closes, (closing | opening)[expected])


def test_alterations_that_open_a_closed_class_are_valued_by_blocks_of_their_own(monkeypatch):
    """With one sensor fixed, the drone's base chain has closed classes (the drone circles for
    ever); an alteration that changes one of their rows may open it. Those sharing an opening
    option are a block of their own (that option fixed, its base solved once, the others by
    low rank): each value so found (a sample) against the exact solve of its own chain."""
    from misdirect.solvers.engines import lowrank

    monkeypatch.setattr(lowrank, "OPENED_BLOCK_FROM", 1)  # every group, however small
    problem = drone(5, agents=1, rows=2)
    top = 3.0
    instance = prepare(problem, top)
    choices = instance.space.choices
    opened: list[tuple[np.ndarray, float]] = []  # (choice vector, value found)
    value_opening = LowRankEnumeration._value_opening

    def recording(self, indices, found, inner_costs, altered, base, block, inner_run, deadline):
        cut_at, valued = value_opening(
            self, indices, found, inner_costs, altered, base, block, inner_run, deadline
        )
        outer, outer_pick, inner = block
        for index in valued.tolist():
            picked = np.zeros(len(choices), dtype=np.int64)
            picked[outer] = outer_pick
            picked[inner] = altered.picks(index, len(inner))
            opened.append((picked, found[index]))
        return cut_at, valued

    monkeypatch.setattr(LowRankEnumeration, "_value_opening", recording)
    rng = np.random.default_rng(0)
    for _ in range(6):
        i = int(rng.integers(len(choices)))
        fixed = {i: int(rng.integers(1, choices[i].size))}
        assert LowRankEnumeration(instance).run(top, fixed, Deadline(None)).complete_for(top)
    values = np.array([value for _, value in opened])
    assert len(opened) >= 1000 and np.unique(values.round(9)).size >= 10  # the case exercises it
    for j in np.random.default_rng(1).choice(len(opened), size=300, replace=False).tolist():
        picked, value = opened[j]
        exact = decoy_probability(problem, instance.space.alteration(problem, picked))
        assert value == pytest.approx(exact, abs=1e-9), picked


@pytest.mark.parametrize("looks", [3, 10, 13, 16, 25, 40, 60, 120, 200])
def test_a_deadline_inside_the_opening_blocks_leaves_values_unvalued_never_wrong(
    looks, monkeypatch
):
    """Cut anywhere (in a block of alterations that open a class, in its base, in its own
    corrections), every alteration the run still prices has the value and cost of the uncut
    run, and a budget it calls complete has the uncut run's best."""
    from misdirect.solvers.engines import lowrank

    monkeypatch.setattr(lowrank, "OPENED_BLOCK_FROM", 1)
    problem = drone(5, agents=1, rows=2)
    instance = prepare(problem, 3.0)
    fixed = {35: 3}  # its base chain has closed classes that later options open
    full = LowRankEnumeration(instance).run(3.0, fixed, Deadline(None))
    assert full.complete_for(3.0)
    enumeration = LowRankEnumeration(instance)
    cut = enumeration.run(3.0, fixed, _ExpiresAt(looks))
    assert cut.costs.size <= full.costs.size
    priced = np.flatnonzero(np.isfinite(cut.costs))
    assert np.array_equal(cut.costs[priced], full.costs[priced])
    assert np.allclose(cut.values[priced], full.values[priced], rtol=0, atol=1e-12)
    for budget in (1.0, 2.0, 3.0):
        if cut.complete_for(budget):
            mine, theirs = cut.best_within([budget])[0], full.best_within([budget])[0]
            assert cut.values[mine] == pytest.approx(full.values[theirs], abs=1e-12)


def test_a_subtree_fixing_an_option_that_may_close_a_class_but_does_not_keeps_the_basis(
    monkeypatch,
):
    """A search's subtree that fixes an option which only *may* close a class (the trap
    search finds none) is the kept basis updated in low rank, not a new base solve; one that
    does close a class, or changes a row of a closed class, is solved anew. Every value of
    every such subtree against the exact solve of its own chain."""
    problem = drone(5, agents=1, rows=2)
    budget = 2.0
    instance = prepare(problem, budget)
    enumeration = LowRankEnumeration(instance)
    bases = BasisCache()
    solved = []
    original = LowRankEnumeration._solved_base

    def counting(self, *args, **kwargs):
        solved.append(1)
        return original(self, *args, **kwargs)

    monkeypatch.setattr(LowRankEnumeration, "_solved_base", counting)
    assert not enumeration.natural_outer  # one basis: every choice inner
    enumeration.run(1.0, {}, Deadline(None), None, bases)  # builds it
    (kept,) = bases._bases.values()
    natural = enumeration.natural_inner
    unsafe = [
        (natural[j], int(k))
        for j, k in zip(*np.nonzero(kept.cycles.unsafe), strict=True)
        if k < instance.space.choices[natural[j]].size
    ]
    assert unsafe
    # 64 of them here: 4 change a row of a closed class, 13 close one, 47 neither
    reused = 0
    rng = np.random.default_rng(5)
    for i, k in unsafe:
        before = len(solved)
        found = enumeration.run(budget, {i: k}, Deadline(None), None, bases)
        assert found.complete_for(budget)
        reused += len(solved) == before
        size = found.values.size
        for index in rng.choice(size, size=min(size, 12), replace=False).tolist():
            alpha = instance.space.alteration(problem, found.picks(index))
            assert found.values[index] == pytest.approx(
                decoy_probability(problem, alpha), abs=1e-9
            ), (i, k, index)
    assert 0 < reused < len(unsafe)  # a new base solve only where the classes differ


def test_the_trap_search_tries_the_successor_nearest_an_exit_first():
    """Its depth-first searches pop a row's last successor first, so each row is ordered with
    the successor fewest base steps from an exit last. Four live states, one group each:
    0 -> {1, 2}, 1 -> {3}, 2 -> {0}, and 3 is an exit (a stop state): 1 is two steps from the
    exit's source, 2 four, so row 0 becomes (2, 1)."""
    inside = sp.csr_matrix(
        (np.ones(4), np.array([1, 2, 3, 0]), np.array([0, 2, 3, 4, 4])), shape=(4, 4)
    )
    stop = np.array([False, False, False, True])
    leaks = np.zeros(4, dtype=bool)
    ordered = closed_classes._nearest_exit_last(inside, leaks, stop, np.arange(4))
    assert ordered.tolist() == [2, 1, 3, 0]
    # a leaking row is an exit too: with state 2's row leaking, row 0 keeps 2 last
    leaks[2] = True
    ordered = closed_classes._nearest_exit_last(inside, leaks, stop, np.arange(4))
    assert ordered[:2].tolist() == [1, 2]
