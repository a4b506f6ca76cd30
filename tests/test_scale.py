"""Tolerances that scale (issue 29): the same problem at any scale has the same answer.

One small model, worked by hand. From ``s0`` (reading o0, the robot plays ``a``) it moves to
``s1`` with probability ``p`` and to ``s2`` otherwise. In ``s1`` (reading o1) it plays ``b``,
which enters the trap with probability 0.2; had it read o0 it would play ``a``, which enters
it with probability 0.8. ``s2`` goes to the goal whatever it plays. So, with the trap's
weight ``w``:

* altering nothing is worth ``w p 0.2``, and ``o1 -> o0`` is worth ``w p 0.8`` (p = 1/2, w = 1:
  0.1 and 0.4); no other alteration changes anything (``s0`` plays ``a`` or ``b`` to the same
  distribution, and ``s2`` always reaches the goal);
* an alteration costs ``c`` each: at budget ``B`` the optimum is ``o1 -> o0`` if ``c <= B``,
  else nothing.

Scaling ``c`` and ``B`` together, ``w``, or ``p`` (the decoy then only reachable through a
branch of probability ``p``) must not change the alteration, nor the status: every method
returns the same, and it is ``optimal``.
"""

from __future__ import annotations

import textwrap
from fractions import Fraction

import numpy as np
import pytest

from misdirect import evaluate, load_problem, solve
from misdirect.core import tolerance
from misdirect.scenarios import knapsack

METHODS = ["exhaustive", "incremental", "branch-and-bound", "milp", "auto"]


def _yaml(x: float) -> str:
    """``x`` as YAML reads a float back (``1e-10`` is a string to it; ``1.0e-10`` is not)."""
    text = repr(float(x))
    mantissa, _, exponent = text.partition("e")
    if exponent and "." not in mantissa:
        mantissa += ".0"
    return mantissa + ("e" + ("+" if exponent[0].isdigit() else "") + exponent if exponent else "")


def _model(tmp_path, *, p=0.5, weight=None, cost=1.0, budget=1.0):
    decoy = "decoy: [trap]" if weight is None else f"decoy: {{trap: {_yaml(weight)}}}"
    p, q = _yaml(p), _yaml(1 - p)
    text = textwrap.dedent(
        f"""\
        format: misdirect/v1
        name: scale
        pomdp:
          states: [s0, s1, s2, trap, goal]
          actions: [a, b]
          initial: s0
          observe: {{s0: o0, s1: o1, s2: o2, trap: g, goal: g}}
          transitions:
            - [s0, a, s1, {p}]
            - [s0, a, s2, {q}]
            - [s0, b, s1, {p}]
            - [s0, b, s2, {q}]
            - [s1, a, trap, 0.8]
            - [s1, a, goal, 0.2]
            - [s1, b, trap, 0.2]
            - [s1, b, goal, 0.8]
            - [s2, a, goal, 1.0]
            - [s2, b, goal, 1.0]
          absorbing: [trap, goal]
        controller:
          nodes: [n]
          initial: n
          rules:
            - {{node: "*", obs: o0, action: a, next: n}}
            - {{node: "*", obs: "*", action: b, next: n}}
        deception:
          {decoy}
          budget: {_yaml(budget)}
          cost: {{default: {_yaml(cost)}}}
        """
    )
    path = tmp_path / "scale.yaml"
    path.write_text(text)
    return load_problem(path)


def _answers(problem, budget):
    found = {}
    for method in METHODS:
        point = solve(problem, method=method, budgets=[budget]).curve[-1]
        found[method] = (point.status.value, point.alteration, point.probability)
    return found


@pytest.mark.parametrize("method", METHODS)
def test_cost_over_a_zero_budget_is_refused(tmp_path, method):
    """Every alteration costs 1e-10 and the budget is 0: nothing fits, so the answer is the
    baseline p 0.2 = 0.1 (before: 0.4 with o1 -> o0, 1e-10 over the budget)."""
    problem = _model(tmp_path, cost=1e-10, budget=0.0)
    point = solve(problem, method=method, budgets=[0.0]).curve[-1]
    assert point.alteration == {}
    assert point.cost == 0.0
    assert point.probability == pytest.approx(0.1, rel=1e-12)
    assert point.status == "optimal"


@pytest.mark.parametrize("method", METHODS)
def test_probabilities_of_1e_10(tmp_path, method):
    """The decoy is reached through a branch of probability 1e-10: o1 -> o0 is worth
    1e-10 x 0.8 = 8e-11, against 2e-11 for nothing (before: branch-and-bound said optimal
    2e-11 with nothing, the MILP 0.0)."""
    problem = _model(tmp_path, p=1e-10)
    point = solve(problem, method=method, budgets=[1.0]).curve[-1]
    if method == "milp":
        # HiGHS's absolute feasibility tolerance (1e-6) on probabilities of 1e-10: its claim
        # is not to be trusted, and the front door must not call it optimal
        assert point.status != "optimal" or point.alteration == {"o1": "o0"}
        return
    assert point.alteration == {"o1": "o0"}
    assert point.probability == pytest.approx(8e-11, rel=1e-12)
    assert point.status == "optimal"


@pytest.mark.parametrize("method", METHODS)
def test_weight_of_1e_12(tmp_path, method):
    """A decoy of weight 1e-12: o1 -> o0 is worth 1e-12 x 0.5 x 0.8 = 4e-13 against 1e-13
    (before: optimal 1e-13 with nothing, the MILP 0.0)."""
    problem = _model(tmp_path, weight=1e-12)
    point = solve(problem, method=method, budgets=[1.0]).curve[-1]
    assert point.alteration == {"o1": "o0"}
    assert point.probability == pytest.approx(4e-13, rel=1e-12)
    assert point.status == "optimal"


def test_evaluate_at_1e_10(tmp_path):
    """``evaluate --alter o1=o0`` on the 1e-10 branch: 1e-10 x 0.8 (a 0.7 model gave 7e-11)."""
    problem = _model(tmp_path, p=1e-10)
    assert evaluate(problem, problem.alteration({"o1": "o0"})).probability == pytest.approx(
        8e-11, rel=1e-12
    )


@pytest.mark.parametrize(
    "scale",
    [1e-12, 1e12],
    ids=["small", "large"],
)
@pytest.mark.parametrize("what", ["costs", "weight"])
def test_scaled_model_has_the_same_answer(tmp_path, scale, what):
    """Costs and budget, or the decoy's weight, scaled by 10^±12: every method returns
    o1 -> o0 at budget 1 (scaled) and nothing at a budget just short of one cost, each
    ``optimal``, as at scale 1."""
    for method, answer in _answers(_model(tmp_path), 1.0).items():
        assert answer[:2] == ("optimal", {"o1": "o0"}), method
    if what == "costs":
        problem = _model(tmp_path, cost=1.0 * scale, budget=1.0 * scale)
        budgets = (1.0 * scale, 0.999 * scale)
    else:
        problem = _model(tmp_path, weight=1.0 * scale)
        budgets = (1.0, 0.999)
    top = _answers(problem, budgets[0])
    short = _answers(problem, budgets[1])
    for method in METHODS:
        assert top[method][:2] == ("optimal", {"o1": "o0"}), method
        assert short[method][:2] == ("optimal", {}), method
        factor = scale if what == "weight" else 1.0
        assert top[method][2] == pytest.approx(0.4 * factor, rel=1e-12)
        assert short[method][2] == pytest.approx(0.1 * factor, rel=1e-12)


@pytest.mark.parametrize("p", [1e-6, 1e-12])
def test_decoy_behind_a_small_branch(tmp_path, p):
    """Probabilities scaled by making the decoy reachable only through a branch of
    probability ``p``: the same alteration and status as at p = 1/2 (the MILP excepted where
    its backend's tolerance is coarser than the values: it must then not say optimal)."""
    problem = _model(tmp_path, p=p)
    for method, (status, alteration, value) in _answers(problem, 1.0).items():
        if method == "milp" and status != "optimal":
            continue
        assert (status, alteration) == ("optimal", {"o1": "o0"}), method
        assert value == pytest.approx(0.8 * p, rel=1e-9)


def test_knapsack_of_subnormal_weights():
    """Knapsack weights and capacity 5e-324 (the least subnormal): one item fits, two do not
    (before: both were taken, 1e-323 over a capacity of 5e-324)."""
    problem = knapsack([5e-324, 5e-324], [1.0, 1.0], 5e-324)
    for method in ["exhaustive", "branch-and-bound", "milp", "auto"]:
        point = solve(problem, method=method).curve[-1]
        assert len(point.alteration) == 1, method
        assert point.cost == 5e-324
        assert point.status == "optimal"


def test_cost_scale_is_exact():
    """Budgets become caps that a float sum of costs meets exactly: decimals as written
    (0.1 + 0.2 fits 0.3), binary where decimals would not add (5e-324), and never a slack
    over the budget (1e-10 does not fit 0)."""
    decimal = tolerance.CostScale.of([0.1, 0.2], 3)
    assert decimal.kind == "decimal"
    assert decimal.fits(0.1 + 0.2, 0.3)
    assert not decimal.fits(0.1 + 0.2 + 0.1, 0.3)
    assert decimal.fits_exactly([0.1, 0.2], 0.3)
    assert float(decimal.exact([0.1, 0.2])) == 0.3
    tiny = tolerance.CostScale.of([1e-10], 4)
    assert not tiny.fits(1e-10, 0.0)
    assert tiny.fits(1e-10, 1e-10)
    assert tiny.fits(3e-10, 3e-10) and not tiny.fits(1e-10 + 1e-10 + 1e-10 + 1e-10, 3e-10)
    sub = tolerance.CostScale.of([5e-324], 2)
    assert sub.kind == "binary"
    assert sub.fits(5e-324, 5e-324) and not sub.fits(5e-324 + 5e-324, 5e-324)
    # costs 1e16 and 1: a float sum drops the 1; a rounded scale refuses what it cannot prove
    wide = tolerance.CostScale.of([1e16, 1.0, 0.3], 2)
    assert wide.fits_exactly([1e16], 1e16) and not wide.fits_exactly([1e16, 1.0], 1e16)
    assert not wide.fits(1e16 + 1.0, 1e16) or wide.kind != "rounded"
    # the remaining budget after a spend decides as the sum does
    assert decimal.fits(0.2, decimal.remaining(0.3, 0.1))
    assert not decimal.fits(0.3, decimal.remaining(0.3, 0.1))


def test_cost_scale_never_admits_over_budget():
    """Random decimal costs (two digits, scaled by 10^k) and budgets: a float sum passes the
    cap exactly when the exact (decimal) sum fits, checked with Fractions."""
    rng = np.random.default_rng(29)
    for k in (-12, -3, 0, 5, 12):
        costs = [float(f"{int(c)}e{k - 2}") for c in rng.integers(1, 300, size=6)]
        scale = tolerance.CostScale.of(costs, 6)
        for _ in range(200):
            picked = [c for c in costs if rng.random() < 0.5]
            exact = sum((Fraction(repr(c)) for c in picked), Fraction(0))
            budget = float(exact) if rng.random() < 0.5 else float(exact) * (1 - 1e-15)
            fits = exact <= Fraction(repr(budget))
            assert bool(scale.fits(float(np.sum(picked)), budget)) == fits, (k, picked, budget)


def test_online_cost_unit_is_the_costs_step_at_any_scale(tmp_path):
    """The budgeted online attacker counts costs in their common step as written; costs of
    1e-10 had none (a fraction with a denominator of at most 10^6) and were refused. By hand:
    one altered reading (o1 -> o0 at s1) is worth 0.5 x 0.8 = 0.4, none 0.5 x 0.2 = 0.1."""
    from misdirect import online_attack_value
    from misdirect.defence import cost_unit

    assert cost_unit([0.1, 0.25]) == 0.05
    assert cost_unit([1e-10, 3e-10]) == 1e-10
    for scale in (1.0, 1e-10):
        problem = _model(tmp_path, cost=scale, budget=scale)
        assert online_attack_value(problem, scale).budgeted_probability == pytest.approx(
            0.4, rel=1e-12
        )
        assert online_attack_value(problem, 0.0).budgeted_probability == pytest.approx(
            0.1, rel=1e-12
        )
