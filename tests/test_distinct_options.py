"""Options that move the robot as another, cheaper option does are left out of the space.

On the drone, "up" on the top row and "stay" both stay: two behaviour classes of the
controller, one chain. Each dropped option is checked against the exact value of its own
chain, and the optimum of the smaller space against brute force over every candidate.
"""

from __future__ import annotations

import numpy as np
import pytest

from misdirect import solve
from misdirect.core.attack import prepare
from misdirect.core.evaluate import decoy_probability
from misdirect.scenarios import drone, sensor_grid


def _dropped(instance):
    """(observation, target, cost) of every candidate option the space left out, and per
    observation its kept (target, cost) pairs (itself, unaltered, included)."""
    kept = {
        c.observation: list(zip(c.targets.tolist(), c.costs.tolist(), strict=True))
        for c in instance.space.choices
    }
    dropped = []
    for c in instance.candidates.choices:
        mine = kept.get(c.observation, [(c.observation, 0.0)])
        targets = {t for t, _ in mine}
        dropped += [
            (c.observation, t, cost)
            for t, cost in zip(c.targets.tolist(), c.costs.tolist(), strict=True)
            if t not in targets
        ]
    return dropped, kept


def test_a_dropped_option_is_worth_what_a_kept_one_of_no_higher_cost_is():
    problem = drone(5, agents=1, rows=1)
    instance = prepare(problem, 2)
    dropped, kept = _dropped(instance)
    # the drone's border moves coincide: some options are left out, some observations lose all
    assert dropped
    assert len(instance.space.choices) < len(instance.candidates.choices)
    rng = np.random.default_rng(3)
    choices = instance.space.choices
    for observation, target, cost in dropped:
        for _ in range(3):
            # another sensor altered at random, so the check is not only on the base chain
            alpha = problem.identity()
            other = choices[int(rng.integers(len(choices)))]
            if other.observation != observation:
                alpha[other.observation] = other.targets[int(rng.integers(other.size))]
            alpha[observation] = target
            value = decoy_probability(problem, alpha)
            equivalents = []
            for kept_target, kept_cost in kept.get(observation, [(observation, 0.0)]):
                if kept_cost <= cost:
                    alpha[observation] = kept_target
                    equivalents.append(decoy_probability(problem, alpha))
            assert any(v == pytest.approx(value, rel=1e-12, abs=1e-15) for v in equivalents)


def test_the_optimum_over_fewer_options_is_the_brute_force_optimum_over_all():
    problem = drone(5, agents=1, rows=1)
    instance = prepare(problem, 1)
    assert instance.space.count_within(1, 10**6) < instance.candidates.count_within(1, 10**6)
    best, cheapest = -1.0, np.inf
    for c in instance.candidates.choices:
        for t, cost in zip(c.targets.tolist(), c.costs.tolist(), strict=True):
            if cost > 1:
                continue
            alpha = problem.identity()
            alpha[c.observation] = t
            value = decoy_probability(problem, alpha)
            if value > best * (1 + 1e-12):
                best, cheapest = value, cost
            elif value >= best * (1 - 1e-12):
                cheapest = min(cheapest, cost)
    for method in ("exhaustive", "incremental", "branch-and-bound"):
        point = solve(problem, budgets=[1], method=method).curve[0]
        assert point.status == "optimal"
        assert point.probability == pytest.approx(best, rel=1e-9)
        assert point.cost == cheapest


def test_a_space_with_nothing_equivalent_is_kept_as_it_is():
    # every sensor of a turn-back grid moves the robot its own way
    instance = prepare(sensor_grid(8, 6, seed=1, goal="inside"), 2)
    assert instance.space is instance.candidates
