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

from misdirect.core import elimination, reachability
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
    jump, model = _exact_jump_values(p, CYCLE)[0], _model_value(_rows())
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
    assert found.value == pytest.approx(float(_exact_jump_values(p, CYCLE)[0]), rel=1e-13)


def _exact_jump_values(p: np.ndarray, n: int) -> list[Fraction]:
    """Pr(decoy, state ``n``) from each of the first ``n`` states of the jump chain of the
    doubles ``p``, exactly."""
    q = [[Fraction(float(p[i, j])) for j in range(p.shape[1])] for i in range(n)]
    a = [
        [
            sum((q[i][k] for k in range(p.shape[1]) if k != i), Fraction(0)) if i == j else -q[i][j]
            for j in range(n)
        ]
        for i in range(n)
    ]
    return gauss_jordan(a, [q[i][n] for i in range(n)])


def _random_lingering_chain(n: int, seed: int, leak: float = 1e-18) -> np.ndarray:
    """``n`` states moving among themselves, leaking to a decoy (state ``n``) and a goal with
    a few ``leak`` each."""
    rng = np.random.default_rng(seed)
    p = np.zeros((n + 2, n + 2))
    for i in range(n):
        succ = rng.choice(n, size=4, replace=False)
        p[i, n] = float(rng.integers(1, 9)) * leak  # to the decoy
        p[i, n + 1] = float(rng.integers(1, 9)) * leak  # to a goal
        # what the leaks leave (all of it, in doubles, when they are below the rounding)
        p[i, succ] = rng.dirichlet(np.ones(4)) * (1 - p[i, n] - p[i, n + 1])
    p[n, n] = p[n + 1, n + 1] = 1.0
    return p


@pytest.mark.parametrize("route", ["dense", "lu"])
def test_a_larger_jump_chain_in_doubles_keeps_its_digits(route, monkeypatch):
    """Both routes: the dense one eliminates the states as numbered, the LU one in the LU's
    fill-reducing order."""
    if route == "lu":
        monkeypatch.setattr(reachability, "DENSE_MAX_STATES", 0)
    n = 24
    p = _random_lingering_chain(n, 7)
    exact = float(_exact_jump_values(p, n)[0])
    target = np.zeros(n + 2, dtype=bool)
    target[n] = True
    for extended in (True, False):
        found = reachability.reach_probability_bounded(
            sp.csr_matrix(p), target, 0, extended_jump=extended
        )
        assert found.error == np.inf  # the premise: LU's answer cannot be proven here
        assert found.value == pytest.approx(exact, rel=1e-12)


def test_any_order_of_elimination_gives_the_exact_value():
    """Every state's value, eliminating in three orders, against the exact jump chain (on a
    chain that leaves soon, so that the states' values differ)."""
    n = 18
    p = _random_lingering_chain(n, 11, leak=0.02)
    exact = np.array([float(v) for v in _exact_jump_values(p, n)])
    leak = (p[:n, n] + p[:n, n + 1], np.zeros(n))
    for order in (None, np.arange(n)[::-1], np.random.default_rng(3).permutation(n)):
        solver = elimination.Elimination(p[:n, :n], leak, order=order)
        assert solver.proper
        high, low = solver.solve((p[:n, n], np.zeros(n)))
        np.testing.assert_allclose(high + low, exact, rtol=1e-14)


@pytest.mark.parametrize("cap", ["MAX_FILL", "MAX_UPDATES"])
def test_an_elimination_that_would_cost_too_much_gives_up(cap, monkeypatch):
    """Past the cap on fill, or on work, the value is not the jump chain's (the caller keeps
    LU's)."""
    n = 24
    p = _random_lingering_chain(n, 7)
    exact = float(_exact_jump_values(p, n)[0])
    q, leak = p[:n, :n], (p[:n, n] + p[:n, n + 1], np.zeros(n))
    assert elimination.Elimination(q, leak).proper
    monkeypatch.setattr(elimination, cap, 2 * np.count_nonzero(q) // 3)
    cut = elimination.Elimination(q, leak)
    assert not cut.complete and not cut.proper
    with pytest.raises(ValueError):
        cut.solve((p[:n, n], np.zeros(n)))
    target = np.zeros(n + 2, dtype=bool)
    target[n] = True
    found = reachability.reach_probability_bounded(sp.csr_matrix(p), target, 0)
    assert found.error == np.inf
    assert found.value != pytest.approx(exact, rel=1e-12)  # LU's digits, not the jump chain's


def test_given_an_order_a_chain_too_long_for_a_proof_gets_no_lu(monkeypatch):
    """Runs that last about 10^18 steps: with an elimination order, the jump chain's value comes
    straight from the elimination (an LU is never tried); without one, after the LU failed."""
    monkeypatch.setattr(reachability, "DENSE_MAX_STATES", 0)
    n = 24
    p = _random_lingering_chain(n, 5, leak=1e-19)
    exact = float(_exact_jump_values(p, n)[0])
    target = np.zeros(n + 2, dtype=bool)
    target[n] = True
    chain = sp.csr_matrix(p)
    rank = elimination.fill_reducing_rank(chain)
    assert sorted(rank.tolist()) == list(range(n + 2))
    without = reachability.reach_probability_bounded(chain, target, 0)

    def no_lu(a: sp.spmatrix) -> None:
        raise AssertionError("an LU was tried")

    monkeypatch.setattr(reachability, "factorise", no_lu)
    found = reachability.reach_probability_bounded(chain, target, 0, elimination_rank=rank)
    assert found.error == without.error == np.inf
    assert found.value == pytest.approx(exact, rel=1e-13)
    assert without.value == pytest.approx(exact, rel=1e-13)


def test_given_an_order_a_chain_that_can_be_proven_still_is(monkeypatch):
    monkeypatch.setattr(reachability, "DENSE_MAX_STATES", 0)
    n = 24
    for leak in (0.02, 1e-14):  # the second lasts about 10^13 steps: proven after refinement
        p = _random_lingering_chain(n, 5, leak=leak)
        target = np.zeros(n + 2, dtype=bool)
        target[n] = True
        chain = sp.csr_matrix(p)
        rank = elimination.fill_reducing_rank(chain)
        found = reachability.reach_probability_bounded(chain, target, 0, elimination_rank=rank)
        assert found == reachability.reach_probability_bounded(chain, target, 0)
        assert np.isfinite(found.error)
