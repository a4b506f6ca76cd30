"""``max_alarm`` (issue 52): the best attack whose Pr(alarm) is at most δ, certified.

Expected values come from brute force over every alteration the budget affords, each valued by
the independent product of tests/test_monitor.py (:func:`reference`: world, controller and
monitor as explicit triples, solved densely); feasibility there is Pr(alarm) <= δ on those
numbers, and δ = 0 on the reference's own graph (a caught move reachable at all).
"""

from __future__ import annotations

import itertools
import json

import numpy as np
import pytest
from typer.testing import CliRunner

import misdirect
from misdirect.cli import app
from misdirect.core.monitor import with_monitor
from misdirect.errors import OptionError
from misdirect.scenarios import random_problem
from result_schema import checked
from test_monitor import (
    HAND_MONITOR,
    _hand,
    _hand_step,
    _random_monitor,
    affordable,
    reference,
)

runner = CliRunner()
METHODS = ("exhaustive", "incremental", "branch-and-bound", "milp", "auto")
DELTAS = (0.0, 0.05, 1.0)


def _brute_force(problem, step, m0, budget, deltas):
    """Per δ: the constrained optimum (None: no alteration is feasible), and every
    alteration's (value, alarm) by its bytes."""
    valued = {}
    for alpha in affordable(problem, budget):
        valued[alpha.tobytes()] = reference(problem, alpha, step, m0)
    best = {}
    for delta in deltas:
        feasible = [v for v, a in valued.values() if a <= delta + 1e-12]
        best[delta] = max(feasible) if feasible else None
    return best, valued


def _check(result, best, valued, delta, method):
    for point in result.curve:
        assert point.budget == result.budget
    if best is None:
        assert str(result.status) == "infeasible", method
        return
    assert str(result.status) == "optimal", (method, delta, result.curve[-1].notes)
    assert result.probability == pytest.approx(best, abs=1e-9), (method, delta)
    value, alarm = valued[np.asarray(result.alteration_array).tobytes()]
    assert value == pytest.approx(result.probability, abs=1e-9)
    assert alarm <= delta + 1e-12, (method, delta, alarm)
    assert result.alarm == pytest.approx(alarm, abs=1e-9)
    assert result.max_alarm == delta


@pytest.mark.parametrize("seed", [0, 1, 4, 33])  # 33: δ = 0 costs the attacker
def test_random_monitors_every_method_against_brute_force(seed):
    rng = np.random.default_rng(seed)
    problem = random_problem(seed, randomized=seed % 2 == 1)
    monitor, step = _random_monitor(problem, rng, 3)
    watched = with_monitor(problem, monitor)
    best, valued = _brute_force(problem, step, "m0", problem.budget, DELTAS)
    for delta in DELTAS:
        for method in METHODS:
            result = misdirect.solve(
                watched, budgets=[problem.budget], method=method, max_alarm=delta
            )
            _check(result, best[delta], valued, delta, method)
        # with a time limit, auto solves the unconstrained problem first and hands on only the
        # budgets whose answer breaks the constraint
        limited = misdirect.solve(watched, budgets=[problem.budget], max_alarm=delta, time_limit=60)
        _check(limited, best[delta], valued, delta, "auto, time limit")


def test_incremental_with_the_alarm_enumerated(monkeypatch):
    """The enumeration's second table (every alteration's alarm), which a constraint that cuts
    deep calls for: the same answers as the lazy walk's."""
    from misdirect.solvers import incremental

    monkeypatch.setattr(incremental, "LAZY_VERDICTS", 0)
    seed = 33
    problem = random_problem(seed, randomized=True)
    monitor, step = _random_monitor(problem, np.random.default_rng(seed), 3)
    watched = with_monitor(problem, monitor)
    best, valued = _brute_force(problem, step, "m0", problem.budget, DELTAS)
    curves = misdirect.solve_tradeoff(
        watched, DELTAS, budgets=[problem.budget], method="incremental"
    )
    for delta, result in zip(DELTAS, curves, strict=True):
        _check(result, best[delta], valued, delta, "incremental")


def _search_space(watched, budget):
    """The per-state relaxation branch-and-bound searches on, for ``watched`` under a δ."""
    from misdirect.core.attack import prepare
    from misdirect.solvers.engines.alarm import alarm_constraint
    from misdirect.solvers.engines.per_state import PerStateRelaxation

    constraint = alarm_constraint(watched, 0.05)
    decoy = constraint.decoy_problem
    instance = prepare(decoy, budget)
    return constraint, PerStateRelaxation(decoy, instance.space, instance.chain, instance.cycling)


@pytest.mark.parametrize("seed", [0, 1, 4, 33])
def test_alarm_floor_of_every_prefix_lies_below_every_completion(seed):
    """branch-and-bound prunes a prefix whose decided states alone raise the alarm above δ
    (``_caught``, its floors computed on the part of the chain the start reaches and shared
    by every budget and δ): per prefix of every assignment of the search, against the
    reference alarm of each of its completions (whatever they cost), with one floor table
    shared by the three δ as a trade-off curve shares it."""
    from misdirect.solvers import branch_and_bound

    rng = np.random.default_rng(seed)
    problem = random_problem(seed, randomized=seed % 2 == 1)
    monitor, step = _random_monitor(problem, rng, 3)
    watched = with_monitor(problem, monitor)
    _, relax = _search_space(watched, problem.budget)
    sizes = [relax.first_option[i + 1] - relax.first_option[i] for i in relax.order]
    assert int(np.prod(sizes)) <= 5_000, "too many assignments for the brute force"
    alarms = {
        picks: reference(problem, relax.alteration(picks), step, "m0")[1]
        for picks in itertools.product(*(range(k) for k in sizes))
    }
    floors: dict = {}
    checked_prefixes = 0
    for delta in (0.0, 0.05, 0.2):
        caught = branch_and_bound._caught(relax, delta, floors)
        for depth in range(len(sizes) + 1):
            for prefix in itertools.product(*(range(k) for k in sizes[:depth])):
                lowest = min(a for picks, a in alarms.items() if picks[:depth] == prefix)
                if caught(prefix):
                    assert lowest > (0.0 if delta == 0.0 else delta), (prefix, delta)
                reached, floor = floors[prefix]
                if reached:  # a run of every completion reaches the alarm
                    assert lowest > 0.0, prefix
                if floor is not None:
                    assert floor <= lowest + 1e-12, (prefix, floor, lowest)
                checked_prefixes += 1
    assert checked_prefixes > 3


@pytest.mark.parametrize(("seed", "kept"), [(0, True), (33, True), (33, False)])
def test_branch_and_bound_tradeoff_curve_against_brute_force(seed, kept, monkeypatch):
    """One trade-off curve by branch-and-bound (the δ share the alarm floors, the node
    relaxations and the exact values; ``kept`` False: no node relaxation kept), two budgets
    and every δ: the brute-force optimum, certified."""
    from misdirect.solvers import branch_and_bound

    if not kept:
        monkeypatch.setattr(branch_and_bound, "KNOWN_BYTES", 0)
    problem = random_problem(seed, randomized=seed % 2 == 1)
    monitor, step = _random_monitor(problem, np.random.default_rng(seed), 3)
    watched = with_monitor(problem, monitor)
    budgets = sorted({problem.budget / 2, problem.budget})
    deltas = (0.0, 0.02, 0.05, 0.2, 1.0)
    curves = misdirect.solve_tradeoff(watched, deltas, budgets=budgets, method="branch-and-bound")
    for budget in budgets:
        best, valued = _brute_force(problem, step, "m0", budget, deltas)
        for delta, result in zip(deltas, curves, strict=True):
            (point,) = [p for p in result.curve if p.budget == budget]
            if best[delta] is None:
                assert str(point.status) == "infeasible", (budget, delta)
                continue
            assert str(point.status) == "optimal", (budget, delta)
            assert point.probability == pytest.approx(best[delta], abs=1e-9), (budget, delta)
            value, alarm = valued[np.asarray(point.alteration_array).tobytes()]
            assert value == pytest.approx(point.probability, abs=1e-9)
            assert alarm <= delta + 1e-12


# random problems whose monitored chain has no end component among its live states (the
# Lagrangian bound is built only there) and some choice to search
NO_END_COMPONENTS = (0, 1, 2, 10, 13)


@pytest.mark.parametrize("seed", NO_END_COMPONENTS)
def test_lagrangian_bound_lies_above_every_subtrees_constrained_optimum(seed):
    """The Lagrangian node bound (engines.lagrangian) at every prefix of the search, two
    budgets and several δ, for each λ alone and for a few together: at least
    the best reference value among the prefix's completions within the budget whose
    reference alarm is at most δ."""
    from misdirect.solvers.engines.lagrangian import lagrangian_bound

    problem = random_problem(seed, randomized=seed % 2 == 1)
    monitor, step = _random_monitor(problem, np.random.default_rng(seed), 3)
    watched = with_monitor(problem, monitor)
    _, relax = _search_space(watched, problem.budget)
    cycling = np.zeros(relax.chain.n_states, dtype=bool)  # NO_END_COMPONENTS
    sizes = [relax.first_option[i + 1] - relax.first_option[i] for i in relax.order]
    scored = {
        picks: reference(problem, relax.alteration(picks), step, "m0")
        for picks in itertools.product(*(range(k) for k in sizes))
    }
    alarms = [alarm for _, alarm in scored.values()]
    # fixed ones, and where the constraint cuts through these alarms (they may all lie high)
    deltas = (0.0, 0.05, 0.2, *np.quantile(alarms, [0.25, 0.5]).tolist())
    start = relax.best_groups(relax.live_groups.astype(np.float64))[0]
    tighter = checked = 0
    for budget in sorted({problem.budget / 2, problem.budget}):
        cap = relax.space.scale.cap(budget)
        for delta in deltas:
            bounds = [
                lagrangian_bound(relax, cycling, delta, lambdas)
                for lambdas in ((0.0,), (0.5,), (3.0,), (100.0,), (0.5, 3.0, 100.0))
            ]
            for depth in range(len(sizes) + 1):
                for prefix in itertools.product(*(range(k) for k in sizes[:depth])):
                    if relax.cost(prefix) > cap:
                        continue
                    feasible = [
                        value
                        for picks, (value, alarm) in scored.items()
                        if picks[:depth] == prefix and relax.fits(picks, budget) and alarm <= delta
                    ]
                    if not feasible:
                        continue
                    allowed = relax.allowed_groups(
                        relax.allowed_options(prefix, cap - relax.cost(prefix))
                    )
                    own, _, policy = relax.optimise(allowed, start.copy())
                    for lagrangian in bounds:
                        assert lagrangian is not None
                        found = lagrangian.bound(allowed, policy)
                        assert found >= max(feasible) - 1e-10, (budget, delta, prefix, found)
                        tighter += found < own - 1e-9
                        checked += 1
    assert checked > 0
    if seed == 1:  # the largest space: the bound is below the relaxation's own somewhere
        assert tighter > 0


@pytest.mark.parametrize("seed", NO_END_COMPONENTS)
def test_branch_and_bound_with_the_lagrangian_bound_against_brute_force(seed, monkeypatch):
    """branch-and-bound with the Lagrangian node bound switched on: the brute-force optimum
    at every δ, certified."""
    from misdirect.solvers import branch_and_bound

    monkeypatch.setattr(branch_and_bound, "LAGRANGE_MULTIPLIERS", (0.5, 100.0))
    problem = random_problem(seed, randomized=seed % 2 == 1)
    monitor, step = _random_monitor(problem, np.random.default_rng(seed), 3)
    watched = with_monitor(problem, monitor)
    best, valued = _brute_force(problem, step, "m0", problem.budget, DELTAS)
    for delta in DELTAS:
        result = misdirect.solve(
            watched, budgets=[problem.budget], method="branch-and-bound", max_alarm=delta
        )
        _check(result, best[delta], valued, delta, "branch-and-bound, Lagrangian")


def test_auto_hands_open_budgets_on(monkeypatch):
    """auto's constrained search stopped after one node: the enumeration takes the budget
    over, and the answer is still the brute-force optimum, certified."""
    from misdirect.solvers import auto

    monkeypatch.setattr(auto, "NODE_LIMIT", 1)
    seed = 33
    problem = random_problem(seed, randomized=True)
    monitor, step = _random_monitor(problem, np.random.default_rng(seed), 3)
    watched = with_monitor(problem, monitor)
    best, valued = _brute_force(problem, step, "m0", problem.budget, (0.0, 0.05))
    for delta in (0.0, 0.05):
        result = misdirect.solve(watched, budgets=[problem.budget], max_alarm=delta)
        _check(result, best[delta], valued, delta, "auto")


def test_delta_one_is_the_plain_stealth_optimum():
    problem = random_problem(1)
    monitor, _ = _random_monitor(problem, np.random.default_rng(1), 3)
    watched = with_monitor(problem, monitor)
    plain = misdirect.solve(watched, method="exhaustive")
    for method in METHODS:
        bounded = misdirect.solve(watched, method=method, max_alarm=1.0)
        assert bounded.probability == pytest.approx(plain.probability, abs=1e-12)
        assert str(bounded.status) == "optimal"


def test_hand_made_curve_against_hand_values():
    """The hand-made problem of test_monitor: o2 -> o0 and o1 -> o0 are caught with
    probability 1/2 (and then score nothing), o1 -> g (0.15) never: 0.15 at every δ."""
    watched = _hand(**HAND_MONITOR)
    best, valued = _brute_force(_hand(), _hand_step, "start", 1.0, (0.0, 0.49, 0.5))
    assert best == {0.0: pytest.approx(0.15), 0.49: pytest.approx(0.15), 0.5: pytest.approx(0.15)}
    for delta in (0.0, 0.49, 0.5):
        for method in METHODS:
            result = misdirect.solve(watched, budgets=[1], method=method, max_alarm=delta)
            _check(result, best[delta], valued, delta, method)


def test_max_alarm_needs_a_monitor_and_a_probability():
    with pytest.raises(OptionError, match="max_alarm"):
        misdirect.solve(random_problem(0), max_alarm=0.1)
    watched = _hand(**HAND_MONITOR)
    for bad in (-0.1, 1.5, float("nan")):
        with pytest.raises(OptionError, match="max_alarm"):
            misdirect.solve(watched, max_alarm=bad)


@pytest.mark.parametrize("given", ["-0.1", "1.5", "nan", "abc", "0.1,x"])
def test_cli_bad_max_alarm_is_one_line_exit_2(given):
    result = runner.invoke(app, ["solve", "--scenario", "paper-grid", "--max-alarm", given])
    assert result.exit_code == 2, result.output
    assert "--max-alarm" in result.output
    assert "Traceback" not in result.output


def test_cli_tradeoff_table_and_json(tmp_path):
    """The paper's grid at budget 1 under --max-alarm (which implies --stealth): δ = 0.25
    keeps the stealthy optimum o1 -> o2 (0.647903, caught 0.210195: docs/stealth.md); δ = 0
    must give it up for an attack the consistency monitor never catches."""
    args = ["solve", "--scenario", "paper-grid", "--budget", "0..1", "--method", "exhaustive"]
    shown = runner.invoke(app, [*args, "--max-alarm", "0,0.25"])
    assert shown.exit_code == 0, shown.output
    assert "δ = 0.25" in shown.output and "0.647903 optimal" in shown.output
    written = runner.invoke(app, [*args, "--max-alarm", "0,0.25", "--json"])
    assert written.exit_code == 0, written.output
    curves = {c["max_alarm"]: c for c in checked(written.output)["tradeoff"]}
    top = curves[0.25]["curve"][-1]
    assert top["value"] == pytest.approx(0.647903, abs=1e-6)
    assert top["alarm"] == pytest.approx(0.210195, abs=1e-6)
    never = curves[0.0]["curve"][-1]
    assert never["alarm"] == 0.0 and never["status"] == "optimal"
    assert never["value"] < top["value"]
    figure = tmp_path / "tradeoff.png"
    drawn = runner.invoke(app, [*args, "--max-alarm", "0,0.25", "-o", str(figure)])
    assert drawn.exit_code == 0, drawn.output
    assert figure.stat().st_size > 0
    refused = runner.invoke(app, [*args, "--max-alarm", "0,0.25", "-o", str(tmp_path / "a.yaml")])
    assert refused.exit_code == 2 and "-o" in refused.output
    single = checked(runner.invoke(app, [*args, "--max-alarm", "0.25", "--json"]).output)
    assert single["max_alarm"] == 0.25 and single["value"] == pytest.approx(top["value"])
    assert single["curve"][-1]["alarm_error"] is not None


def test_an_infeasible_budget_in_the_json():
    """Seed 1's monitor raises the alarm on the unaltered robot (0.78): nothing keeps
    Pr(alarm) <= 0.2 (brute force in the test above), status infeasible, schema-valid."""
    problem = random_problem(1, randomized=True)
    monitor, _ = _random_monitor(problem, np.random.default_rng(1), 3)
    result = misdirect.solve(with_monitor(problem, monitor), method="exhaustive", max_alarm=0.2)
    assert str(result.status) == "infeasible"
    from misdirect.report import json_output

    checked(json.dumps(json_output.solve(result)))


def test_a_wrong_infeasible_claim_is_caught(monkeypatch):
    """A method that says nothing fits where altering nothing does (Pr(alarm) 0 under the
    consistency monitor) is contradicted: a warning, and the point is not certified."""
    from misdirect.core.monitor import consistency_monitor
    from misdirect.solvers import exhaustive
    from misdirect.solvers.base import Solution
    from misdirect.solvers.status import Status

    def claims_infeasible(constraint, budgets, *args):
        identity = constraint.problem.identity()
        return [Solution(b, identity, None, status=Status.INFEASIBLE) for b in budgets]

    monkeypatch.setattr(exhaustive, "_constrained", claims_infeasible)
    problem = random_problem(0)
    watched = with_monitor(problem, consistency_monitor(problem))
    result = misdirect.solve(watched, method="exhaustive", max_alarm=0.0)
    assert str(result.status) == "feasible"
    assert any("altering nothing does" in w for w in result.warnings)
