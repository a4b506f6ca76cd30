"""Robust controller synthesis (issue 54, docs/robust.md): the exact master with the oracle
against brute force over every (memoryless controller, alteration) pair, the goal objective,
the baselines, and the written controller loaded back on the command line."""

from __future__ import annotations

import itertools
import json
from dataclasses import replace

import numpy as np
import pytest
from typer.testing import CliRunner

import misdirect
from misdirect.cli import app
from misdirect.core.evaluate import decoy_probability, evaluate
from misdirect.core.model import Controller, CostModel, Pomdp, Problem
from misdirect.io.problem_file import write_problem
from misdirect.scenarios import random_problem

runner = CliRunner()


def alterations_within(problem: Problem, budget: float):
    """Every alteration function the costs allow within ``budget`` (initial observation fixed)."""
    n = problem.pomdp.n_observations
    o_init = problem.pomdp.initial_observation
    choices = []
    for o in range(n):
        row = problem.cost.row(o)
        choices.append([o] if o == o_init else [t for t in range(n) if np.isfinite(row[t])])
    for picked in itertools.product(*choices):
        alpha = np.array(picked)
        cost = sum(problem.cost.row(o)[t] for o, t in enumerate(picked) if t != o)
        if cost <= budget + 1e-9:
            yield alpha


def memoryless(problem: Problem, table) -> Controller:
    n = problem.pomdp.n_observations
    return Controller(
        nodes=("m",),
        initial_node=0,
        action=np.array([table]),
        update=np.zeros((1, n), dtype=int),
    )


def goal_probability(problem: Problem, alpha) -> float:
    """Pr(first absorbing state entered is not a decoy), read off evaluate's outcomes."""
    return sum(
        row["probability"]
        for row in evaluate(problem, np.asarray(alpha)).outcome_list()
        if row["kind"] == "goal"
    )


def brute_minmax(problem: Problem, budget: float, objective: str) -> float:
    """min over every memoryless deterministic controller of max over every alteration within
    budget of Pr(decoy) (or max of min of Pr(goal)), by plain loops."""
    pomdp = problem.pomdp
    alphas = list(alterations_within(problem, budget))
    best = None
    for table in itertools.product(range(pomdp.n_actions), repeat=pomdp.n_observations):
        candidate = replace(problem, controller=memoryless(problem, table))
        if objective == "decoy":
            value = max(decoy_probability(candidate, a) for a in alphas)
            best = value if best is None else min(best, value)
        else:
            value = min(goal_probability(candidate, a) for a in alphas)
            best = value if best is None else max(best, value)
    assert best is not None
    return best


def worst_decoy(problem: Problem, budget: float) -> float:
    return max(decoy_probability(problem, a) for a in alterations_within(problem, budget))


def absorbed_problem(seed: int, budget: float) -> Problem:
    """Three working states reading a, b, c, a goal and a decoy (both reading end), two
    actions; every move ends the run with probability at least 0.1, so no run is trapped."""
    rng = np.random.default_rng(seed)
    states = ("s0", "s1", "s2", "goal", "decoy")
    action, source, target, probability = [], [], [], []
    for a in range(2):
        for s in range(3):
            row = rng.dirichlet(np.ones(5))
            row[3:] += 0.1
            row /= row.sum()
            for t in range(5):
                action.append(a)
                source.append(s)
                target.append(t)
                probability.append(row[t])
    pomdp = Pomdp.from_triplets(
        states=states,
        actions=("x", "y"),
        observations=("a", "b", "c", "end"),
        initial_state=0,
        observation_of=np.array([0, 1, 2, 3, 3]),
        action=np.array(action),
        source=np.array(source),
        target=np.array(target),
        probability=np.array(probability),
        absorbing=np.array([False, False, False, True, True]),
    )
    controller = Controller(
        nodes=("m",), initial_node=0, action=np.array([[0, 1, 0, 0]]), update=np.zeros((1, 4))
    )
    return Problem(
        pomdp=pomdp,
        controller=controller,
        cost=CostModel(n_observations=4),
        decoy=np.array([False, False, False, False, True]),
        budget=budget,
        name=f"absorbed {seed}",
    )


@pytest.mark.parametrize("seed", range(6))
def test_decoy_minmax_matches_brute_force(seed):
    budget = float(1 + seed % 2)
    problem = random_problem(seed, states=5, actions=2, observations=3, nodes=1, budget=budget)
    expected = brute_minmax(problem, budget, "decoy")
    result = misdirect.robust_controller(problem, budget)
    assert result.optimal
    assert result.lower == pytest.approx(expected, abs=1e-9)
    assert result.upper == pytest.approx(expected, abs=1e-9)
    assert result.worst_case == pytest.approx(expected, abs=1e-9)
    # the returned controller's worst case, by brute force over alterations
    chosen = replace(problem, controller=result.controller)
    assert worst_decoy(chosen, budget) == pytest.approx(expected, abs=1e-9)
    assert result.nominal == pytest.approx(decoy_probability(chosen, problem.identity()))
    assert result.rounds[0].k_size == 1
    assert [r.k_size for r in result.rounds] == list(range(1, len(result.rounds) + 1))


@pytest.mark.parametrize("seed", range(4))
def test_decoy_minmax_on_absorbed_problems(seed):
    problem = absorbed_problem(seed, 1.0)
    expected = brute_minmax(problem, 1.0, "decoy")
    result = misdirect.robust_controller(problem, 1.0)
    assert result.optimal
    assert result.lower == pytest.approx(expected, abs=1e-9)
    assert result.upper == pytest.approx(expected, abs=1e-9)


@pytest.mark.parametrize("seed", range(4))
def test_goal_maxmin_matches_brute_force(seed):
    budget = 1.0 + seed % 2
    problem = absorbed_problem(seed, budget)
    expected = brute_minmax(problem, budget, "goal")
    result = misdirect.robust_controller(problem, budget, objective="goal")
    assert result.optimal, result.notes
    # goal: the master's value over K is the upper bound, the oracle's the lower
    assert result.lower == pytest.approx(expected, abs=1e-9)
    assert result.upper == pytest.approx(expected, abs=1e-9)
    chosen = replace(problem, controller=result.controller)
    worst = min(goal_probability(chosen, a) for a in alterations_within(problem, budget))
    assert worst == pytest.approx(expected, abs=1e-9)
    assert result.worst_case == pytest.approx(expected, abs=1e-9)


@pytest.mark.parametrize("seed", range(3))
def test_baselines(seed):
    problem = absorbed_problem(seed, 1.0)
    result = misdirect.robust_controller(problem, 1.0)
    given, blind = result.baselines
    assert given.name == "given controller"
    assert given.certified
    assert given.worst_case == pytest.approx(worst_decoy(problem, 1.0), abs=1e-9)
    # the blind controller: the best of the constant ones, and no alteration changes it
    values = []
    for a in range(2):
        constant = replace(problem, controller=memoryless(problem, [a] * 4))
        values.append(worst_decoy(constant, 1.0))
        assert values[-1] == pytest.approx(decoy_probability(constant, problem.identity()))
    assert blind.worst_case == pytest.approx(min(values), abs=1e-9)
    assert blind.nominal == pytest.approx(blind.worst_case, abs=1e-12)
    # the robust controller is no worse than either
    assert result.worst_case <= min(given.worst_case, blind.worst_case) + 1e-9


def test_json_fields():
    problem = absorbed_problem(0, 1.0)
    document = misdirect.robust_controller(problem, 1.0).to_dict()
    for key in ("worst_case", "lower_bound", "upper_bound", "gap", "rounds", "baselines"):
        assert key in document
    assert document["gap"] == pytest.approx(0.0, abs=1e-9)


def test_refuses_bad_options():
    problem = absorbed_problem(0, 1.0)
    with pytest.raises(misdirect.ProblemError):
        misdirect.robust_controller(problem, 1.0, objective="speed")
    with pytest.raises(misdirect.ProblemError):
        misdirect.robust_controller(problem, 1.0, memory=0)


@pytest.mark.parametrize("objective", ["decoy", "goal"])
def test_cli_writes_a_controller_that_loads_back(tmp_path, objective):
    problem = absorbed_problem(2, 1.0)
    path = tmp_path / "p.yaml"
    write_problem(problem, path)
    fsc = tmp_path / "robust.fsc.json"
    run = runner.invoke(
        app,
        [
            "controller", "robust", str(path), "--budget", "1", "--objective", objective,
            "-o", str(fsc), "--json",
        ],
    )  # fmt: skip
    assert run.exit_code == 0, run.output
    robust = json.loads(run.output)["robust"]
    assert robust["optimal"]
    expected = brute_minmax(problem, 1.0, objective)
    assert robust["worst_case"] == pytest.approx(expected, abs=1e-9)
    solved = runner.invoke(
        app, ["solve", str(path), "--controller", str(fsc), "--budget", "1", "--json"]
    )
    assert solved.exit_code == 0, solved.output
    curve = json.loads(solved.output)["curve"]
    final = curve[-1]
    assert final["status"] == "optimal"
    if objective == "decoy":
        assert final["value"] == pytest.approx(robust["worst_case"], abs=1e-9)
    # the controller read back is the one reported
    loaded = runner.invoke(app, ["evaluate", str(path), "--controller", str(fsc), "--json"])
    assert loaded.exit_code == 0, loaded.output
    value = json.loads(loaded.output)["value"]
    if objective == "decoy":
        assert value == pytest.approx(robust["nominal"], abs=1e-9)
    # plain output runs too
    plain = runner.invoke(app, ["controller", "robust", str(path), "--budget", "1", "-o", str(fsc)])
    assert plain.exit_code == 0, plain.output
    assert "robust" in plain.output
