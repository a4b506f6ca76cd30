"""The first-entry gain bound (``solvers.engines.entry_gain``) against brute force: from a base
alteration, every alteration that changes up to two more observations is worth at most the
bound, on random models with self-loops and traps (end components), on the stress models whose
probabilities go down to 1e-12, with weighted decoys, and on a turn-back grid, for the gains
counted on every entry and on the first only; and hand-made chains give the gains worked out
on paper."""

from __future__ import annotations

import itertools
from functools import partial

import numpy as np
import pytest
import scipy.sparse as sp

from misdirect import decoy_probability
from misdirect.core.product import build_product
from misdirect.scenarios import random_problem, sensor_grid
from misdirect.solvers.engines.entry_gain import entry_gains, first_entry_gains
from stress_model import stress_model


def _gains(problem, base, gains_of=entry_gains):
    chain = build_product(problem, base)
    objective = problem.objective
    world = chain.world_state
    region = problem.pomdp.observation_of[world].copy()
    region[problem.pomdp.absorbing[world]] = -1  # their rows never change
    region[world == problem.pomdp.initial_state] = -1  # the initial reading is never altered
    region[region == problem.pomdp.initial_observation] = -1
    return gains_of(
        chain.matrix.tocsr(),
        objective.target[world],
        objective.value[world],
        chain.initial,
        region,
        problem.pomdp.n_observations,
        objective.max_value,
    )


def _options(problem):
    """Per alterable observation, the readings it may be altered to."""
    n = problem.pomdp.n_observations
    alterable = [o for o in range(n) if o != problem.pomdp.initial_observation]
    return {
        o: [t for t in range(n) if t != o and np.isfinite(problem.cost.row(o)[t])]
        for o in alterable
    }


def _check(problem, base, gains_of=entry_gains) -> int:
    """Every alteration of up to two more observations on top of ``base`` is within the
    bound; returns how many bounds were below 1 (the bound is not vacuous)."""
    gains = _gains(problem, base, gains_of)
    if gains_of is first_entry_gains:  # never above the gains of every entry
        assert (gains.gains <= _gains(problem, base).gains).all()
    assert gains.value >= decoy_probability(problem, base) - 1e-12
    options = {o: ts for o, ts in _options(problem).items() if base[o] == o}
    useful = 0
    for size in (1, 2):
        for observations in itertools.combinations(sorted(options), size):
            for targets in itertools.product(*(options[o] for o in observations)):
                altered = base.copy()
                altered[list(observations)] = targets
                value = decoy_probability(problem, altered)
                bound = gains.bounds(np.zeros(size, dtype=np.int64), np.array(observations), 1)[0]
                assert value <= bound + 1e-12, (observations, targets, value, bound)
                useful += bound < problem.objective.max_value
    return useful


GAINS = [entry_gains, first_entry_gains]


@pytest.mark.parametrize("gains_of", GAINS)
@pytest.mark.parametrize("seed", range(12))
def test_no_alteration_beats_the_bound_on_random_models(seed, gains_of):
    problem = random_problem(seed, states=7, observations=4, randomized=seed % 3 == 2)
    _check(problem, problem.identity(), gains_of)
    first = next(iter(_options(problem).items()), None)
    if first is not None:
        base = problem.identity()
        base[first[0]] = first[1][0]
        _check(problem, base, gains_of)


@pytest.mark.parametrize("gains_of", GAINS)
@pytest.mark.parametrize("seed", range(8))
def test_no_alteration_beats_the_bound_where_rounding_bites(seed, gains_of):
    problem = stress_model(seed)
    _check(problem, problem.identity(), gains_of)


@pytest.mark.parametrize("gains_of", GAINS)
def test_the_bound_holds_and_says_something_on_a_turn_back_grid(gains_of):
    problem = sensor_grid(8, 6, goal="inside")
    assert _check(problem, problem.identity(), gains_of) > 0


def test_first_entry_gains_by_hand():
    """0 -> region r (state 1); 1 -> 2; 2 -> back to 1 w.p. 1/2, goal 3 w.p. 1/4, decoy 4
    w.p. 1/4. V = 1/2 at 0, 1 and 2. Region r is entered twice on average, each time worth
    at most 1 - 1/2: 1 counted on every entry; the first entry alone is worth 1/2, which
    making 1's row go to the decoy reaches (the bound is tight)."""
    p = np.zeros((5, 5))
    p[0, 1] = p[1, 2] = 1.0
    p[2, 1], p[2, 3], p[2, 4] = 0.5, 0.25, 0.25
    p[3, 3] = p[4, 4] = 1.0
    target = np.array([False, False, False, False, True])
    region = np.array([-1, 0, -1, -1, -1])
    args = (sp.csr_matrix(p), target, target.astype(float), 0, region, 1, 1.0)
    every, first = entry_gains(*args), first_entry_gains(*args)
    assert every.value == pytest.approx(0.5, rel=1e-12)
    assert every.gains[0] == pytest.approx(1.0, rel=1e-12)
    assert first.gains[0] == pytest.approx(0.5, rel=1e-12)
    assert first.gains[0] >= 0.5  # proven from above
    # a trap in the region, entered before any of its transient states: worth M
    p[2, 4], p[2, 0] = 0.0, 0.25  # no decoy left: 2 -> 1, 3 or back to 0
    p = np.pad(p, ((0, 1), (0, 1)))
    p[0, 1], p[0, 5], p[5, 5] = 0.5, 0.5, 1.0  # 0 -> trap 5 (in region r) w.p. 1/2
    region = np.array([-1, 0, -1, -1, -1, 0])
    target = np.array([False, False, False, False, True, False])
    args = (sp.csr_matrix(p), target, target.astype(float), 0, region, 1, 1.0)
    # V = 0: every first entry gains 1; r is entered first w.p. 1 (trap or state 1)
    assert first_entry_gains(*args).gains[0] == pytest.approx(1.0, rel=1e-12)
    assert entry_gains(*args).gains[0] > 1.0


def test_gains_by_hand():
    """0 -> region r (state 1) w.p. 1/2, -> goal 3 w.p. 1/2; 1 -> decoy 2 w.p. 1/4, -> goal
    3 w.p. 3/4. V(1) = 1/4 and region r is entered with probability 1/2: g_r = 1/2 (1 - 1/4)
    = 3/8, and the base is worth 1/8."""
    p = sp.csr_matrix(
        np.array([[0, 0.5, 0, 0.5], [0, 0, 0.25, 0.75], [0, 0, 1, 0], [0, 0, 0, 1]], dtype=float)
    )
    target = np.array([False, False, True, False])
    region = np.array([-1, 0, -1, -1])
    gains = entry_gains(p, target, target.astype(float), 0, region, 1, 1.0)
    assert gains.value == pytest.approx(1 / 8, abs=1e-15)
    assert gains.gains[0] == pytest.approx(3 / 8, rel=1e-12)
    assert gains.gains[0] >= 3 / 8  # proven from above
    # a trap that meets the region: 0 -> 1 <-> 4 (a closed class of no value, in region r)
    trap = sp.csr_matrix(
        np.array(
            [
                [0, 0.5, 0, 0.5, 0],
                [0, 0, 0, 0, 1],
                [0, 0, 1, 0, 0],
                [0, 0, 0, 1, 0],
                [0, 1, 0, 0, 0],
            ],
            dtype=float,
        )
    )
    target = np.array([False, False, True, False, False])
    region = np.array([-1, 0, -1, -1, -1])
    gains = entry_gains(trap, target, target.astype(float), 0, region, 1, 1.0)
    assert gains.value == pytest.approx(0.0, abs=1e-290)  # proven: underflow allowed for
    assert gains.gains[0] == pytest.approx(0.5, rel=1e-12)  # the mass the trap takes


def test_searches_whose_enumerations_filter_by_the_bound_still_find_the_optimum(monkeypatch):
    """Every enumeration of the segment search filtered (no size threshold): the searches of
    tests/test_segment_relaxation.py still certify the exhaustive optimum exactly on random
    models (end components included), small sensor grids and weighted decoys, and the filter
    did leave alterations out."""
    from misdirect.solvers.engines import entry_gain, lowrank
    from test_segment_relaxation import check_bounds, random_suite, small_grids
    from test_weighted_decoys import weighted_random

    monkeypatch.setattr(entry_gain, "FILTER_FROM", 0)
    monkeypatch.setattr(entry_gain, "FILTER_PER_STATE", 0)
    left_out = []
    filtered = lowrank.LowRankEnumeration._filtered

    def counted(self, altered, *args):
        kept, reaches = filtered(self, altered, *args)
        left_out.append(len(altered.costs) - int(reaches.sum()))
        return kept, reaches

    monkeypatch.setattr(lowrank.LowRankEnumeration, "_filtered", counted)
    cycling = sum(check_bounds(p, [0.0, 1.0, 2.0, 3.5]) for p in random_suite(25))
    for grid in list(small_grids())[1:4]:
        check_bounds(grid, [2.0, 3.0])
    for seed in range(6):
        check_bounds(weighted_random(seed), [1.0, 3.0])
    assert cycling >= 3
    assert sum(left_out) > 0


@pytest.mark.parametrize("kind", ["turn-back grid", "sensor grid"])
def test_an_enumeration_with_a_floor_keeps_every_alteration_that_reaches_it(monkeypatch, kind):
    """Subtrees of a search (two sensors fixed), every alteration solved exactly here: with
    the subtree's own optimum as the floor, the filtered enumeration still returns it (the
    bound never drops an alteration that reaches the floor); with a floor above it, nothing
    it returns beats the floor. Some alterations are left out along the way."""
    from misdirect.core.attack import prepare
    from misdirect.solvers.deadline import Deadline
    from misdirect.solvers.engines import entry_gain, lowrank

    monkeypatch.setattr(entry_gain, "FILTER_FROM", 0)
    monkeypatch.setattr(entry_gain, "FILTER_PER_STATE", 0)
    if kind == "turn-back grid":
        problem = sensor_grid(8, 6, seed=1, goal="inside")
    else:
        problem = sensor_grid(9, 10, seed=4, costs="random", memory=5)
    budget = 3.0
    instance = prepare(problem, budget)
    choices = instance.space.choices
    table, _ = instance.space.within(budget)
    exact = np.array(
        [decoy_probability(problem, instance.space.alteration(problem, row)) for row in table]
    )
    rng = np.random.default_rng(5)
    checked = 0
    enumeration = lowrank.LowRankEnumeration(instance)
    for _ in range(10):
        picked = rng.choice(len(choices), size=1, replace=False)
        fixed = {int(i): int(rng.integers(1, choices[i].size)) for i in picked}
        agree = np.ones(len(table), dtype=bool)
        for i, k in fixed.items():
            agree &= table[:, i] == k
        if not agree.any():
            continue
        best = float(exact[agree].max())
        found = enumeration.best_with(budget, fixed, Deadline(None), lowrank.BasisCache(), best)
        assert found is not None and found[2]
        assert found[0] == pytest.approx(best, abs=1e-9)
        above = enumeration.best_with(
            budget, fixed, Deadline(None), lowrank.BasisCache(), best + 0.05
        )
        assert above is not None and above[2] and above[0] <= best + 1e-9
        checked += 1
    assert checked >= 5
    assert enumeration.filtered > 0


def test_a_run_with_a_floor_answers_for_its_top_budget_only(monkeypatch):
    """Alterations below the floor are left out, so a cheaper budget's best may be missing:
    the run says it is complete for its own budget, not for the ones below."""
    from misdirect.core.attack import prepare
    from misdirect.solvers.deadline import Deadline
    from misdirect.solvers.engines import entry_gain, lowrank

    monkeypatch.setattr(entry_gain, "FILTER_FROM", 0)
    monkeypatch.setattr(entry_gain, "FILTER_PER_STATE", 0)
    problem = sensor_grid(8, 6, seed=1, goal="inside")
    enumeration = lowrank.LowRankEnumeration(prepare(problem, 2.0))
    plain = enumeration.run(2.0, deadline=Deadline(None))
    floored = enumeration.run(2.0, deadline=Deadline(None), floor=float(plain.values.max()))
    assert plain.complete_for(1.0) and plain.complete_for(2.0)
    assert floored.complete_for(2.0) and not floored.complete_for(1.0)
    assert enumeration.filtered > 0


def test_first_entry_gains_cut_short_keep_the_gains_on_every_entry():
    """Regions left undone when ``stop()`` says so keep their gains counted on every entry
    (a bound still); the largest go first."""
    problem = sensor_grid(8, 6, goal="inside")
    every = _gains(problem, problem.identity())
    assert (
        _gains(
            problem, problem.identity(), partial(first_entry_gains, stop=lambda: True)
        ).gains.tolist()
        == every.gains.tolist()
    )
    calls = iter(range(100))
    one = _gains(
        problem, problem.identity(), partial(first_entry_gains, stop=lambda: next(calls) >= 1)
    )
    largest = int(np.argmax(every.gains))
    changed = np.flatnonzero(one.gains != every.gains)
    assert changed.tolist() == [largest]
    assert one.gains[largest] < every.gains[largest]
