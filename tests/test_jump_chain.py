"""Chains absorbed only after about 10^17 steps: the value by elimination without subtraction.

Five states in a cycle leak to a decoy and a goal with probabilities of a few 10^-18, far
below the rounding of the other entries (the doubles of a row sum to 1 only within about
10^-16). LU then gets even the first digit wrong, and nothing can be proven; the value
reported is the jump chain's (each state leaves by its other entries), computed without
cancellation. The references are exact rational solves written out here: the jump chain of
the very doubles, and the model of the decimals before they were rounded.
"""

from __future__ import annotations

from decimal import Decimal
from fractions import Fraction

import numpy as np
import pytest
import scipy.sparse as sp

from misdirect.core import reachability
from rational import gauss_jordan

UNIT = Decimal("3e-18")
CYCLE = 5
MOVES = {  # in-cycle moves; the entry left as None takes what the leaks leave
    0: {1: "0.6", 3: None},
    1: {2: "0.3", 0: "0.5", 4: None},
    2: {3: "0.7", 2: "0.1", 0: None},
    3: {4: "0.45", 1: None},
    4: {0: "0.8", 2: None},
}
LEAKS = {0: (3, 4), 1: (1, 8), 2: (6, 2), 3: (2, 2), 4: (5, 5)}  # (to decoy, to goal) in UNITs
DECOY, GOAL = CYCLE, CYCLE + 1


def _rows() -> list[dict[int, Decimal]]:
    """Each state's row as decimals summing to exactly 1."""
    rows = []
    for i in range(CYCLE):
        row = {DECOY: LEAKS[i][0] * UNIT, GOAL: LEAKS[i][1] * UNIT}
        given = {j: Decimal(p) for j, p in MOVES[i].items() if p is not None}
        rest = 1 - sum(row.values()) - sum(given.values())
        row.update(given)
        row.update({j: rest for j, p in MOVES[i].items() if p is None})
        rows.append(row)
    return rows


def _model_value(rows: list[dict[int, Decimal]]) -> Fraction:
    """Pr(decoy) from state 0 of the decimal model, exactly."""
    a = [
        [Fraction(int(i == j)) - Fraction(rows[i].get(j, 0)) for j in range(CYCLE)]
        for i in range(CYCLE)
    ]
    return gauss_jordan(a, [Fraction(rows[i][DECOY]) for i in range(CYCLE)])[0]


def _jump_value(p: np.ndarray) -> Fraction:
    """Pr(decoy) from state 0 of the jump chain of the doubles ``p``, exactly: each state
    leaves by its other entries (its self-loop is what they leave)."""
    q = [[Fraction(float(p[i, j])) for j in range(p.shape[1])] for i in range(CYCLE)]
    a = [
        [
            sum((q[i][k] for k in range(p.shape[1]) if k != i), Fraction(0)) if i == j else -q[i][j]
            for j in range(CYCLE)
        ]
        for i in range(CYCLE)
    ]
    return gauss_jordan(a, [q[i][DECOY] for i in range(CYCLE)])[0]


def _chain() -> np.ndarray:
    p = np.zeros((CYCLE + 2, CYCLE + 2))
    for i, row in enumerate(_rows()):
        for j, value in row.items():
            p[i, j] = float(value)
    p[DECOY, DECOY] = p[GOAL, GOAL] = 1.0
    return p


def test_the_chain_defeats_double_precision():
    """The premise: the doubles' rows miss 1 by more than the leaks, and LU is off in the
    first digits."""
    p = _chain()
    defects = [abs(sum(Fraction(float(x)) for x in p[i]) - 1) for i in range(CYCLE)]
    assert max(defects) > Fraction(float(max(p[:CYCLE, DECOY])))
    model = _model_value(_rows())
    lu = np.linalg.solve(np.eye(CYCLE) - p[:CYCLE, :CYCLE], p[:CYCLE, DECOY])[0]
    assert abs(lu - float(model)) > 1e-3


@pytest.mark.parametrize("route", ["dense", "lu"])
def test_the_value_is_the_jump_chains_and_the_models_unproven(route, monkeypatch):
    if route == "lu":
        monkeypatch.setattr(reachability, "DENSE_MAX_STATES", 0)
    p = _chain()
    target = np.zeros(p.shape[0], dtype=bool)
    target[DECOY] = True
    found = reachability.reach_probability_bounded(sp.csr_matrix(p), target, 0)
    assert found.error == np.inf  # nothing is proven: never `optimal`
    jump, model = _jump_value(p), _model_value(_rows())
    assert found.value == pytest.approx(float(jump), rel=1e-13)
    # the jump chain of the rounded entries is a relative perturbation of the model's
    assert found.value == pytest.approx(float(model), rel=1e-13)


@pytest.mark.parametrize("extended", [True, False])
def test_the_jump_chain_in_doubles_agrees_with_the_exact_one(extended):
    """The search ranks ill-conditioned alterations by the jump chain in doubles: the same
    elimination without subtraction, one rounding per operation; it must still agree with the
    exact rational value (here on the cycle above; on a random 24-state one below)."""
    p = _chain()
    target = np.zeros(p.shape[0], dtype=bool)
    target[DECOY] = True
    found = reachability.reach_probability_bounded(
        sp.csr_matrix(p), target, 0, extended_jump=extended
    )
    assert found.error == np.inf
    assert found.value == pytest.approx(float(_jump_value(p)), rel=1e-13)


def test_a_larger_jump_chain_in_doubles_keeps_its_digits():
    rng = np.random.default_rng(7)
    n = 24
    p = np.zeros((n + 2, n + 2))
    for i in range(n):
        succ = rng.choice(n, size=4, replace=False)
        p[i, succ] = rng.dirichlet(np.ones(4))
        p[i, n] = float(rng.integers(1, 9)) * 1e-18  # to the decoy
        p[i, n + 1] = float(rng.integers(1, 9)) * 1e-18  # to a goal
    p[n, n] = p[n + 1, n + 1] = 1.0
    target = np.zeros(n + 2, dtype=bool)
    target[n] = True
    q = [[Fraction(float(p[i, j])) for j in range(n + 2)] for i in range(n)]
    a = [
        [
            sum((q[i][k] for k in range(n + 2) if k != i), Fraction(0)) if i == j else -q[i][j]
            for j in range(n)
        ]
        for i in range(n)
    ]
    exact = float(gauss_jordan(a, [q[i][n] for i in range(n)])[0])
    for extended in (True, False):
        found = reachability.reach_probability_bounded(
            sp.csr_matrix(p), target, 0, extended_jump=extended
        )
        assert found.error == np.inf  # the premise: LU's answer cannot be proven here
        assert found.value == pytest.approx(exact, rel=1e-12)
