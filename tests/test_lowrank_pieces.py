"""The pieces the low-rank enumeration calls, each on its own: the floor filter
(engines/entry_gain.py), the exact-valuation guard (engines/exact_revaluation.py) and the
extensions the trap handling leaves out of a batch (engines/closed_classes.py)."""

from __future__ import annotations

import numpy as np
import pytest

from misdirect.core import tolerance
from misdirect.core.alterations import AlteredEntries
from misdirect.solvers.deadline import Deadline
from misdirect.solvers.engines import exact_revaluation
from misdirect.solvers.engines.closed_classes import with_extensions
from misdirect.solvers.engines.entry_gain import floor_filter, worth_filtering
from misdirect.solvers.engines.exact_revaluation import (
    guard_ill_conditioned,
    value_one_chain_each,
)


def _four() -> AlteredEntries:
    """0 unaltered; 1 = choice 0 option 1; 2 = 1 and choice 1 option 1; 3 = choice 1 option 2."""
    return AlteredEntries(
        alteration=np.array([1, 2, 2, 3]),
        choice=np.array([0, 0, 1, 1]),
        option=np.array([1, 1, 1, 2]),
        costs=np.array([0.0, 1.0, 2.0, 1.0]),
        parent=np.array([-1, 0, 1, 0]),
    )


def test_the_floor_filter_keeps_what_may_reach_the_floor_and_its_ancestors():
    altered = _four()
    kept = floor_filter(altered, np.array([0.1, 0.2, 0.9, 0.3]), floor=0.5)
    assert kept.dropped == 1  # alteration 3 only: 1 is the parent of 2, 0 everyone's
    assert kept.reaches.tolist() == [False, False, True]
    assert kept.altered.costs.tolist() == [0.0, 1.0, 2.0]
    assert kept.altered.parent.tolist() == [-1, 0, 1]
    assert kept.altered.picks(2, 2).tolist() == [1, 1]
    # a near-tie of the floor may reach it (the cheaper of tied ones wins)
    tied = floor_filter(altered, np.array([0.1, 0.2, 0.5 * (1 - tolerance.NEAR_TIE / 2), 0.3]), 0.5)
    assert tied.reaches.tolist() == [False, False, True]
    # nothing to leave out: the same entries back
    whole = floor_filter(altered, np.ones(4), floor=0.5)
    assert whole.dropped == 0 and whole.altered is altered and whole.reaches.all()


def test_a_small_block_is_not_worth_filtering():
    assert not worth_filtering(10, 5)
    assert worth_filtering(10**6, 5)
    assert not worth_filtering(10**6, 10**6)  # its gains cost a solve of a big chain


def test_extensions_follow_every_chain_of_parents():
    parent = np.array([-1, 0, 1, 2, 0, 4])
    assert with_extensions(parent, np.array([1])).tolist() == [0, 1, 1, 1, 0, 0]
    assert with_extensions(parent, np.array([4])).tolist() == [0, 0, 0, 0, 1, 1]


def test_a_well_conditioned_base_needs_no_exact_values():
    costs, values = np.array([0.0, 1.0]), np.array([0.2, 0.4])
    called = []
    left = guard_ill_conditioned(
        costs,
        values,
        np.inf,
        tolerance.CostScale.of([1.0], 2),
        10.0,
        1.0,
        lambda i: called.append(i) or 0.0,
        Deadline(),
    )
    assert left == np.inf and not called and values.tolist() == [0.2, 0.4]


def test_an_ill_conditioned_base_has_its_candidates_valued_exactly(monkeypatch):
    monkeypatch.setattr(exact_revaluation, "update_error", lambda steps, top: 1.0)
    costs, values = np.array([0.0, 1.0, 2.0]), np.array([0.1, 0.5, 0.4])
    left = guard_ill_conditioned(
        costs,
        values,
        np.inf,
        tolerance.CostScale.of([1.0], 2),
        1e12,
        1.0,
        lambda i: [0.15, 0.3, 2.0][i],
        Deadline(),
    )
    assert left == np.inf
    assert values.tolist() == [0.15, 0.3, 1.0]  # clipped to the objective's maximum
    # past the deadline: the free alteration stays (unverified), the others are unvalued
    costs, values = np.array([0.0, 1.0, 2.0]), np.array([0.1, 0.5, 0.4])
    left = guard_ill_conditioned(
        costs,
        values,
        np.inf,
        tolerance.CostScale.of([1.0], 2),
        1e12,
        1.0,
        lambda i: pytest.fail("valued past the deadline"),
        Deadline(0.0),
    )
    assert left == 1.0
    assert costs.tolist() == [0.0, np.inf, np.inf]


def test_values_one_chain_each_stop_at_the_deadline():
    found, costs = np.zeros(3), np.array([1.0, 2.0, np.inf])
    assert value_one_chain_each(np.arange(3), found, costs, lambda i: i + 0.5, Deadline()) == (
        np.inf
    )
    assert found.tolist() == [0.5, 1.5, 0.0]  # one already unvalued is left alone
    cut = value_one_chain_each(np.arange(2), found, costs, lambda i: 9.0, Deadline(0.0))
    assert cut == 1.0 and costs.tolist() == [np.inf, np.inf, np.inf]
