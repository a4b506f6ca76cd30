"""The PAYNT master of robust synthesis (issue 54, docs/robust.md): the combined POMDP whose
hidden first step picks a member of K is worth the weighted average of the altered problems
(misdirect's exact evaluation on each, and PAYNT's own value of the controller it returns);
the master's controller re-evaluates, on the original problem, to the worst case it reports."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
from typer.testing import CliRunner

import misdirect
from misdirect.cli import app
from misdirect.core.evaluate import decoy_probability
from misdirect.core.model import Problem
from misdirect.defence import robust_paynt
from misdirect.defence.robust_oracle import goal_states, objective_value
from misdirect.defence.robust_paynt import combined_problem, replicated
from misdirect.io.problem_file import write_problem
from misdirect.scenarios import random_problem
from result_schema import checked
from test_robust import absorbed_problem, alterations_within

runner = CliRunner()


def two_alterations(problem: Problem, seed: int) -> list[np.ndarray]:
    """Two distinct alterations of ``problem`` that change something, picked by ``seed``."""
    changed = [
        a for a in alterations_within(problem, 2.0) if not np.array_equal(a, problem.identity())
    ]
    assert len(changed) >= 2
    picked = np.random.default_rng(seed).choice(len(changed), size=2, replace=False)
    return [changed[int(i)] for i in picked]


def small_problem(seed: int, nodes: int = 2) -> Problem:
    return random_problem(seed, states=6, actions=2, observations=3, nodes=nodes, budget=2.0)


@pytest.mark.parametrize("objective", ["decoy", "goal"])
@pytest.mark.parametrize("seed", range(6))
def test_combined_pomdp_is_worth_the_weighted_average(seed, objective):
    """Under a fixed controller (the problem's own, with memory), the combined POMDP's exact
    value is Σ w_i V_i, V_i the exact value of the original problem under alteration i: the
    hidden pick leaks nothing and the copies do not mix."""
    problem = small_problem(seed)
    members = two_alterations(problem, seed)
    weights = np.random.default_rng(seed + 100).dirichlet(np.ones(2))
    world = combined_problem(problem, members, weights)
    pomdp = world.pomdp
    # every copy reads the initial observation first, and the alteration's readings after
    assert pomdp.initial_state == 0
    assert pomdp.initial_observation == problem.pomdp.initial_observation
    n_s = problem.pomdp.n_states
    for i, alpha in enumerate(members):
        copy = pomdp.observation_of[1 + i * n_s : 1 + (i + 1) * n_s]
        assert np.array_equal(copy, alpha[problem.pomdp.observation_of])
    value = objective_value(world, objective, world.identity())
    expected = sum(
        w * objective_value(problem, objective, alpha)
        for w, alpha in zip(weights, members, strict=True)
    )
    assert value == pytest.approx(expected, abs=1e-12)
    if objective == "goal":  # the goal of the combined world is the copies of the goal
        s0 = problem.pomdp.initial_state
        assert np.array_equal(goal_states(world), replicated(goal_states(problem), s0, 2))


@pytest.mark.parametrize("seed", range(3))
def test_paynt_value_on_the_combined_pomdp_is_the_weighted_average(seed):
    """PAYNT's controller for the combined POMDP, read back as a controller of the original
    problem: PAYNT's own value of it equals Σ w_i V_i with V_i misdirect's exact value on the
    original problem under alteration i (PAYNT's controller semantics are misdirect's)."""
    pytest.importorskip("paynt")
    from misdirect.io.paynt_synthesis import synthesize_problem

    problem = small_problem(seed)
    members = two_alterations(problem, seed)
    weights = np.array([0.3, 0.7])
    world = combined_problem(problem, members, weights)
    goal = goal_states(world)
    found = synthesize_problem(world, goal, memory=2, timeout=60.0)
    assert found.synthesis.value is not None
    controller = found.controller
    assert controller.n_nodes == 2
    on_original = replace(problem, controller=controller)
    expected = sum(
        w * objective_value(on_original, "goal", alpha)
        for w, alpha in zip(weights, members, strict=True)
    )
    assert found.synthesis.value == pytest.approx(expected, abs=1e-5)  # PAYNT's precision


@pytest.mark.parametrize(
    ("objective", "min_goal"), [("decoy", None), ("goal", None), ("decoy", 0.3)]
)
@pytest.mark.parametrize("seed", range(2))
def test_paynt_master_reports_the_worst_case_of_its_controller(seed, objective, min_goal):
    """The controller the PAYNT master returns, re-evaluated on the original problem under
    every alteration within the budget (brute force), has the worst case it reports; for
    decoy misdirect.solve on it proves the same; no bound is claimed."""
    pytest.importorskip("paynt")
    # goal: every run absorbed, so the oracle can prove the worst Pr(goal)
    problem = small_problem(seed, nodes=1) if objective == "decoy" else absorbed_problem(seed, 1.0)
    budget = 1.0
    result = misdirect.robust_controller(
        problem, budget, memory=2, objective=objective, master="paynt", min_goal=min_goal,
        baselines=False, exact_seed=False, time_limit=120.0, max_rounds=4,
    )  # fmt: skip
    assert result.master == "paynt" and result.master_bound is None
    assert result.gap is None and not result.optimal
    assert result.controller.is_deterministic
    assert result.to_dict()["master"] == "paynt" and not result.to_dict()["randomized"]
    assert result.rounds, "PAYNT gave no controller in time"
    chosen = replace(problem, controller=result.controller)
    # the worst case reported is the exact value of the attack reported, on the original
    attack = problem.alteration(result.alteration)
    assert result.worst_case == pytest.approx(objective_value(chosen, objective, attack), abs=1e-12)
    values = [objective_value(chosen, objective, a) for a in alterations_within(problem, budget)]
    worst = max(values) if objective == "decoy" else min(values)
    if objective == "decoy":
        assert result.certified  # a small problem: the oracle proves its answer
        solved = misdirect.solve(chosen, budgets=[budget]).curve[-1]
        assert solved.probability == pytest.approx(worst, abs=1e-9)
    assert result.certified
    if result.certified:
        assert result.worst_case == pytest.approx(worst, abs=1e-9)
        assert result.worst_case_bound == pytest.approx(worst, abs=1e-9)
    nominal = objective_value(chosen, "goal", problem.identity())
    assert result.nominal_goal == pytest.approx(nominal, abs=1e-12)
    assert decoy_probability(chosen, problem.identity()) == pytest.approx(
        objective_value(chosen, "decoy", problem.identity()), abs=1e-12
    )


def test_paynt_master_without_paynt(monkeypatch):
    """Without PAYNT the master is refused with the install hint (no skip: nothing runs)."""
    monkeypatch.setattr(robust_paynt, "paynt_available", lambda: False)
    with pytest.raises(misdirect.ProblemError, match="needs paynt"):
        misdirect.robust_controller(small_problem(0), 1.0, master="paynt", baselines=False)


def test_refuses_randomized_with_another_master():
    with pytest.raises(misdirect.ProblemError, match="gradient master"):
        misdirect.robust_controller(
            small_problem(0), 1.0, randomized=True, master="paynt", baselines=False
        )
    with pytest.raises(misdirect.ProblemError, match="must be one of"):
        misdirect.robust_controller(small_problem(0), 1.0, master="storm", baselines=False)
    run = runner.invoke(
        app,
        [
            "controller", "robust", "--scenario", "paper-grid", "--budget", "1",
            "--randomized", "--master", "paynt", "-o", "x.fsc.json",
        ],
    )  # fmt: skip
    assert run.exit_code != 0 and "--master" in run.output


def test_cli_paynt_master_writes_a_controller_that_loads_back(tmp_path):
    """``--master paynt``: the file written loads back with ``--controller``, and
    ``solve --controller`` proves the worst case reported."""
    pytest.importorskip("paynt")
    problem = small_problem(1, nodes=1)
    path = tmp_path / "p.yaml"
    write_problem(problem, path)
    fsc = tmp_path / "robust.fsc.json"
    run = runner.invoke(
        app,
        [
            "controller", "robust", str(path), "--budget", "1", "--memory", "2",
            "--master", "paynt", "--baselines", "none", "--time-limit", "120", "-o", str(fsc),
            "--json",
        ],
    )  # fmt: skip
    assert run.exit_code == 0, run.output
    robust = checked(run.output)["robust"]  # the result schema knows the PAYNT master
    assert robust["master"] == "paynt" and robust["master_bound"] is None
    solved = runner.invoke(
        app, ["solve", str(path), "--controller", str(fsc), "--budget", "1", "--json"]
    )
    assert solved.exit_code == 0, solved.output
    final = json.loads(solved.output)["curve"][-1]
    if robust["certified"]:
        assert final["status"] == "optimal"
        assert final["value"] == pytest.approx(robust["worst_case"], abs=1e-9)


def test_single_changes_warm_start_is_within_the_budget():
    """K's warm start for the PAYNT master: alterations within the budget, one reading each,
    every reading the objective can depend on with every affordable target; none past the
    limit."""
    problem = small_problem(4)
    warm = robust_paynt.single_changes(problem, 2.0)
    identity = problem.identity()
    assert warm
    for alpha in warm:
        assert np.count_nonzero(alpha != identity) == 1
        assert problem.alteration_cost(alpha) <= 2.0 + 1e-9
    changed = {(int(o), int(a[o])) for a in warm for o in np.flatnonzero(a != identity)}
    expected = {
        (int(o), t)
        for o in problem.relevant_observations
        for t in range(problem.pomdp.n_observations)
        if t != o and problem.cost.row(int(o))[t] <= 2.0
    }
    assert changed == expected
    assert robust_paynt.single_changes(problem, 2.0, limit=len(warm) - 1) == []
