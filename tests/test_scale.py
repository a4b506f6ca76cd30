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

from fractions import Fraction

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from misdirect import evaluate, load_problem, solve
from misdirect.core import tolerance
from misdirect.scenarios import knapsack
from scale_model import scale_model_text

METHODS = ["exhaustive", "incremental", "branch-and-bound", "milp", "auto"]


def _model(tmp_path, *, p=0.5, weight=None, cost=1.0, budget=1.0):
    path = tmp_path / "scale.yaml"
    path.write_text(scale_model_text(p=p, weight=weight, cost=cost, budget=budget))
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


# p = 1e-10 x weight 1e-12: o1 -> o0 is worth 1e-12 x 1e-10 x 0.8 = 8e-23, nothing 2e-23
MILP_CASES = {
    "p=1e-10": ({"p": 1e-10}, 8e-11),
    "p=1e-12": ({"p": 1e-12}, 8e-13),
    "weight=1e-12": ({"weight": 1e-12}, 4e-13),
    "weight=1e+12": ({"weight": 1e12}, 4e11),
    "p=1e-10,weight=1e-12": ({"p": 1e-10, "weight": 1e-12}, 8e-23),
}


@pytest.mark.parametrize("case", list(MILP_CASES))
@pytest.mark.parametrize("backend", ["highs", "scip"])
def test_milp_certifies_the_optimum_at_any_scale(tmp_path, backend, case):
    """The MILP on both backends: o1 -> o0 with its value (by hand, above), its claim and
    bound that value, and ``optimal`` (before: HiGHS claimed 0 with a bound of 0 on the 1e-10
    branch, ``unverified``; SCIP said ``optimal`` for the unaltered 2e-11)."""
    options, value = MILP_CASES[case]
    problem = _model(tmp_path, **options)
    point = solve(problem, method="milp", budgets=[1.0], solver=backend).curve[-1]
    assert point.alteration == {"o1": "o0"}
    assert point.probability == pytest.approx(value, rel=1e-12)
    assert point.solver_probability == pytest.approx(value, rel=1e-9)
    assert point.upper_bound == pytest.approx(value, rel=1e-9)
    assert point.status == "optimal"


@pytest.mark.parametrize("p", [1e-10, 1e-12])
@pytest.mark.parametrize("backend", ["highs", "scip"])
def test_pinned_paper_milp_at_small_probabilities(tmp_path, backend, p):
    """The paper's formulation (pinned; unsound, so never ``optimal``) on the 1e-10 and 1e-12
    branches: o1 -> o0, claimed 0.8 p as the chain gives it (before: nothing, claimed 0)."""
    problem = _model(tmp_path, p=p)
    point = solve(
        problem, method="milp", budgets=[1.0], solver=backend, formulation="paper-pinned"
    ).curve[-1]
    assert point.alteration == {"o1": "o0"}
    assert point.solver_probability == pytest.approx(0.8 * p, rel=1e-9)
    assert point.probability == pytest.approx(0.8 * p, rel=1e-12)


def test_value_scales_bound_every_alteration(tmp_path):
    """The scales the MILP divides its value columns by are powers of two at least the value
    of every state under every alteration (brute force over the model's alterations within
    the budget, each chain built on its own), within a factor 4 of the largest (so the
    backend's numbers are about 1); a state of value about 1 keeps 1."""
    from itertools import product

    from misdirect.core.attack import prepare
    from misdirect.core.product import full_product_matrix
    from misdirect.core.reachability import reach_probabilities
    from misdirect.solvers.engines.per_state import relaxation_values
    from misdirect.solvers.milp.scaling import value_scales

    problem = _model(tmp_path, p=1e-10, weight=1e-12)
    instance = prepare(problem, 1.0)
    chain, live = instance.chain, instance.live
    top = problem.objective.max_value
    scales = value_scales(chain, live, relaxation_values(problem, 1.0)[1], top)
    n, nodes = problem.pomdp.n_observations, problem.controller.n_nodes
    weights = problem.objective.value
    best = np.zeros(chain.n_states)
    for targets in product(range(n), repeat=n - 1):  # o0, the initial reading, is never altered
        alteration = np.array([0, *targets])
        if not problem.cost.fits(alteration, problem.budget):
            continue
        full = full_product_matrix(problem, alteration)  # every (s, n): s |N| + n
        values = reach_probabilities(
            full, np.repeat(problem.objective.target, nodes), value=np.repeat(weights, nodes)
        )
        best = np.maximum(best, values[chain.world_state * nodes + chain.node] / top)
    assert live.sum() == 2  # s0 (value 0.8e-10 at most) and s1 (0.8)
    assert np.all(np.log2(scales) == np.round(np.log2(scales)))
    assert np.all(scales[live] >= best[live])
    assert np.all(scales[live] < 4 * np.maximum(best[live], 2.0**-10))
    s0, s1 = chain.initial, np.flatnonzero(live & (np.arange(chain.n_states) != chain.initial))
    assert scales[s0] < 2.0**-30 and np.all(scales[s1] == 1.0)


@pytest.mark.parametrize("formulation", ["compact", "paper-pinned"])
def test_value_scales_leave_a_normal_model_as_built(formulation):
    """The paper's grid (values about 1): the MILP handed to the backend is the one built
    without the relaxation's values, entry for entry."""
    from misdirect.scenarios import paper_grid
    from misdirect.solvers.engines.per_state import relaxation_values
    from misdirect.solvers.milp import build_formulation

    problem = paper_grid(5)
    values = relaxation_values(problem, 4.0)[1]
    assert values is not None
    scaled = build_formulation(problem, formulation, 4.0, values)
    plain = build_formulation(problem, formulation, 4.0)
    assert scaled.notes["states_scaled"] == 0
    assert (scaled.matrix != plain.matrix).nnz == 0
    for name in ("objective", "row_lower", "row_upper", "col_lower", "col_upper"):
        assert np.array_equal(getattr(scaled, name), getattr(plain, name)), name


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


@settings(
    max_examples=10,
    deadline=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture],
    derandomize=True,  # the same examples in every run: CI stays reproducible
)
@given(
    cost_exponent=st.integers(-12, 12),
    weight_exponent=st.integers(-12, 12),
    branch_exponent=st.integers(0, 12),
)
def test_every_scale_at_once_has_the_same_answer(
    tmp_path, cost_exponent, weight_exponent, branch_exponent
):
    """The fuzz campaign's scaled numbers: costs and budget by 10^a, the decoy's weight by
    10^b and its branch's probability by 10^-c, all at once. Every method still returns
    o1 -> o0 at a budget of one cost and nothing just short of it, both ``optimal``, worth
    ``0.8 p w`` and ``0.2 p w`` (the module docstring's hand calculation)."""
    cost, weight = 10.0**cost_exponent, 10.0**weight_exponent
    p = 0.5 * 10.0**-branch_exponent
    problem = _model(tmp_path, p=p, weight=weight, cost=cost, budget=cost)
    top, short = _answers(problem, cost), _answers(problem, 0.999 * cost)
    for method in METHODS:
        assert top[method][:2] == ("optimal", {"o1": "o0"}), method
        assert short[method][:2] == ("optimal", {}), method
        assert top[method][2] == pytest.approx(0.8 * p * weight, rel=1e-9), method
        assert short[method][2] == pytest.approx(0.2 * p * weight, rel=1e-9), method


def test_milp_certifies_a_decoy_worth_100(tmp_path):
    """Found by the campaign above: a decoy of weight 100 (o1 -> o0 worth 0.8 * 0.5 * 100 =
    40 by hand) left the MILP at ``gap_limit``, HiGHS's bound 1e-6 above 40 (it prunes within
    its own absolute tolerance); the per-state relaxation at the budget proves it."""
    point = solve(_model(tmp_path, weight=100.0), method="milp", budgets=[1.0]).curve[-1]
    assert (point.status.value, point.alteration) == ("optimal", {"o1": "o0"})
    assert point.probability == pytest.approx(40.0, rel=1e-12)


@pytest.mark.parametrize("p", [1e-6, 1e-12])
def test_decoy_behind_a_small_branch(tmp_path, p):
    """Probabilities scaled by making the decoy reachable only through a branch of
    probability ``p``: the same alteration and status as at p = 1/2, the MILP's included (its
    value columns are scaled to the states' values, below its backend's tolerances)."""
    problem = _model(tmp_path, p=p)
    for method, (status, alteration, value) in _answers(problem, 1.0).items():
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
    # costs 1e16 and 1: a float sum drops the 1, so it proves nothing within its rounding of
    # the budget; that sum is ambiguous and its terms decide
    wide = tolerance.CostScale.of([1e16, 1.0, 0.3], 2)
    assert wide.kind == "rounded"
    assert wide.fits_exactly([1e16], 1e16) and not wide.fits_exactly([1e16, 1.0], 1e16)
    assert wide.fits(1e16 + 1.0, 1e16)  # may fit: what searches bound with
    assert wide.ambiguous(np.array([1e16 + 1.0]), 1e16).all()
    assert not wide.fits_terms(1e16 + 1.0, lambda: [1e16, 1.0], 1e16)
    assert wide.fits_terms(1e16, lambda: [1e16], 1e16)
    assert not wide.ambiguous(np.array([0.3, 2e16]), 1e16).any()  # surely in, surely out
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


def test_evaluate_takes_a_mapping_and_empty_means_unaltered(tmp_path):
    """``evaluate(problem, {})`` is the unaltered chain (before: "got shape ()"), by hand
    w p 0.2: 0.1 at p = 1/2, 2e-11 at p = 1e-10; a mapping of names is read as
    ``problem.alteration`` reads it (o1 -> o0: w p 0.8), and an unknown name is refused."""
    from misdirect.errors import ProblemError

    for p, unaltered in ((0.5, 0.1), (1e-10, 2e-11)):
        problem = _model(tmp_path, p=p)
        empty = evaluate(problem, {})
        assert empty.probability == pytest.approx(unaltered, rel=1e-12)
        assert empty.alteration == {} and empty.cost == 0.0
        altered = evaluate(problem, {"o1": "o0"})
        assert altered.probability == pytest.approx(4 * unaltered, rel=1e-12)
        assert altered.alteration == {"o1": "o0"}
    with pytest.raises(ProblemError, match="unknown observation 'o9'"):
        evaluate(problem, {"o9": "o0"})
