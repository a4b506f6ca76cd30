"""Robust controller synthesis (issue 54, docs/robust.md): the exact master with the oracle
against brute force over every (memoryless controller, alteration) pair, the goal objective,
the baselines, and the written controller loaded back on the command line."""

from __future__ import annotations

import itertools
import json
import time
from dataclasses import replace

import numpy as np
import pytest
from typer.testing import CliRunner

import misdirect
from misdirect.cli import app
from misdirect.core.evaluate import decoy_probability, evaluate
from misdirect.core.model import Controller, CostModel, Pomdp, Problem
from misdirect.io.problem_file import load_problem, write_problem
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
    return _ended_problem(seed, budget, ("goal", "decoy"), f"absorbed {seed}")


def three_ends_problem(seed: int, budget: float) -> Problem:
    """As :func:`absorbed_problem`, with a third end, a crash that is neither goal nor decoy:
    staying away from the decoy no longer means reaching the goal, so a floor on Pr(goal)
    can cost worst-case Pr(decoy)."""
    return _ended_problem(seed, budget, ("goal", "decoy", "crash"), f"three ends {seed}")


def _ended_problem(seed: int, budget: float, ends: tuple[str, ...], name: str) -> Problem:
    """Three working states reading a, b, c, then the absorbing ``ends`` (reading end; the one
    named decoy is the decoy); from each working state and action a random row, each end
    raised by 0.1."""
    rng = np.random.default_rng(seed)
    n = 3 + len(ends)
    action, source, target, probability = [], [], [], []
    for a in range(2):
        for s in range(3):
            row = rng.dirichlet(np.ones(n))
            row[3:] += 0.1
            row /= row.sum()
            for t in range(n):
                action.append(a)
                source.append(s)
                target.append(t)
                probability.append(row[t])
    pomdp = Pomdp.from_triplets(
        states=("s0", "s1", "s2", *ends),
        actions=("x", "y"),
        observations=("a", "b", "c", "end"),
        initial_state=0,
        observation_of=np.array([0, 1, 2] + [3] * len(ends)),
        action=np.array(action),
        source=np.array(source),
        target=np.array(target),
        probability=np.array(probability),
        absorbing=np.array([False] * 3 + [True] * len(ends)),
    )
    controller = Controller(
        nodes=("m",), initial_node=0, action=np.array([[0, 1, 0, 0]]), update=np.zeros((1, 4))
    )
    return Problem(
        pomdp=pomdp,
        controller=controller,
        cost=CostModel(n_observations=4),
        decoy=np.array([False] * 3 + [end == "decoy" for end in ends]),
        budget=budget,
        name=name,
    )


@pytest.mark.parametrize(
    ("maker", "seed"),
    [(three_ends_problem, 0), (three_ends_problem, 2), (three_ends_problem, 6),
     (absorbed_problem, 2), (absorbed_problem, 7)],
)  # fmt: skip
def test_exact_master_floor_matches_brute_force(maker, seed):
    """--min-goal q with the exact master: min over every memoryless controller whose nominal
    Pr(goal) is at least q of the max over every alteration of Pr(decoy), by plain loops; q
    half-way between the unconstrained min-max controllers' best Pr(goal) and the highest
    Pr(goal) of any controller, so the floor excludes every unconstrained optimum."""
    problem = maker(seed, 1.0)
    alphas = list(alterations_within(problem, 1.0))
    rows = []  # (worst Pr(decoy), nominal Pr(goal)) of every memoryless controller
    for table in itertools.product(range(2), repeat=4):
        candidate = replace(problem, controller=memoryless(problem, table))
        worst = max(decoy_probability(candidate, a) for a in alphas)
        rows.append((worst, goal_probability(candidate, problem.identity())))
    free = min(w for w, _ in rows)
    free_goal = max(g for w, g in rows if w <= free + 1e-12)
    top_goal = max(g for _, g in rows)
    assert top_goal > free_goal + 1e-6  # the floor below binds
    floor = (free_goal + top_goal) / 2
    expected = min(w for w, g in rows if g >= floor)
    assert expected > free + 1e-9  # and costs worst-case Pr(decoy)
    result = misdirect.robust_controller(problem, 1.0, min_goal=floor, baselines=False)
    assert result.optimal
    assert result.lower == pytest.approx(expected, abs=1e-9)
    assert result.upper == pytest.approx(expected, abs=1e-9)
    assert result.worst_case == pytest.approx(expected, abs=1e-9)
    chosen = replace(problem, controller=result.controller)
    assert goal_probability(chosen, problem.identity()) >= floor
    assert result.nominal_goal == pytest.approx(goal_probability(chosen, problem.identity()))
    assert max(decoy_probability(chosen, a) for a in alphas) == pytest.approx(expected, abs=1e-9)
    assert result.min_goal == floor
    assert any("floor" in note for note in result.notes)
    # a floor no controller meets is one clear error naming the field
    with pytest.raises(misdirect.ProblemError) as error:
        misdirect.robust_controller(problem, 1.0, min_goal=min(top_goal + 0.01, 1.0))
    assert error.value.field == "min_goal"


@pytest.mark.parametrize("seed", range(6))
def test_decoy_minmax_matches_brute_force(seed):
    budget = float(1 + seed % 2)
    problem = random_problem(seed, states=5, actions=2, observations=3, nodes=1, budget=budget)
    expected = brute_minmax(problem, budget, "decoy")
    result = misdirect.robust_controller(problem, budget, baselines=False)
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
    result = misdirect.robust_controller(problem, 1.0, baselines=False)
    assert result.optimal
    assert result.lower == pytest.approx(expected, abs=1e-9)
    assert result.upper == pytest.approx(expected, abs=1e-9)


@pytest.mark.parametrize("seed", range(4))
def test_goal_maxmin_matches_brute_force(seed):
    budget = 1.0 + seed % 2
    problem = absorbed_problem(seed, budget)
    expected = brute_minmax(problem, budget, "goal")
    result = misdirect.robust_controller(problem, budget, objective="goal", baselines=False)
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
    result = misdirect.robust_controller(problem, 1.0, baselines=("given", "blind"))
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


# -- the randomized (gradient) master -----------------------------------------------------------


def softmax_controller(problem: Problem, memory: int, seed: int):
    """A random full-support ``memory``-node controller, with its flat μ and logits."""
    from misdirect.defence.robust_gradient import controller_of, softmax

    pomdp = problem.pomdp
    shape = (memory, pomdp.n_observations, pomdp.n_actions * memory)
    theta = np.random.default_rng(seed).normal(0.0, 1.5, int(np.prod(shape)))
    mu = softmax(theta, shape)
    return controller_of(mu, memory, pomdp.n_observations, pomdp.n_actions), mu, theta, shape


@pytest.mark.parametrize("objective", ["decoy", "goal"])
@pytest.mark.parametrize("seed", range(3))
def test_adjoint_gradient_matches_finite_differences(seed, objective):
    from misdirect.defence.robust_gradient import ChainModel, softmax, softmax_backward
    from misdirect.defence.robust_oracle import objective_value, target_and_worth

    problem = (
        absorbed_problem(seed, 1.0)
        if seed % 2
        else random_problem(seed, states=6, actions=2, observations=3, nodes=1, budget=1.0)
    )
    target, worth = target_and_worth(problem, objective)
    model = ChainModel(problem.pomdp, target, worth, 2)
    controller, mu, theta, shape = softmax_controller(problem, 2, seed)
    rng = np.random.default_rng(100 + seed)
    alpha = rng.integers(0, problem.pomdp.n_observations, problem.pomdp.n_observations)
    alpha[problem.pomdp.initial_observation] = problem.pomdp.initial_observation
    index = model.cell_index(alpha)
    value, grad_mu = model.value_and_gradient(mu, index)
    assert grad_mu is not None
    # the value is the project's exact evaluation of the same controller
    candidate = replace(problem, controller=controller)
    assert value == pytest.approx(objective_value(candidate, objective, alpha), abs=1e-12)
    grad = softmax_backward(mu, grad_mu, shape)
    step = 1e-6
    numeric = np.empty_like(theta)
    for i in range(theta.size):
        e = np.zeros_like(theta)
        e[i] = step
        up = model.value_and_gradient(softmax(theta + e, shape), index, False)[0]
        down = model.value_and_gradient(softmax(theta - e, shape), index, False)[0]
        numeric[i] = (up - down) / (2 * step)
    assert np.abs(numeric).max() > 1e-4  # the check has something to check
    np.testing.assert_allclose(grad, numeric, atol=1e-8)
    # the Krylov solves of large chains give the same value and gradient
    krylov = ChainModel(problem.pomdp, target, worth, 2, direct_limit=0)
    k_value, k_grad = krylov.value_and_gradient(mu, krylov.cell_index(alpha))
    assert k_value == pytest.approx(value, abs=1e-9)
    assert k_grad is not None
    np.testing.assert_allclose(k_grad, grad_mu, atol=1e-8)


@pytest.mark.parametrize("objective", ["decoy", "goal"])
@pytest.mark.parametrize("seed", range(3))
def test_gradient_master_reports_only_certified_worst_cases(seed, objective):
    problem = absorbed_problem(seed, 1.0)
    result = misdirect.robust_controller(
        problem, 1.0, memory=2, objective=objective, randomized=True, restarts=2, seed=seed,
        baselines=False,
    )  # fmt: skip
    chosen = replace(problem, controller=result.controller)
    alphas = list(alterations_within(problem, 1.0))
    if objective == "decoy":
        brute = max(decoy_probability(chosen, a) for a in alphas)
        assert result.upper == pytest.approx(brute, abs=1e-9)  # the oracle's side: a bound
        assert result.lower is None
    else:
        brute = min(goal_probability(chosen, a) for a in alphas)
        assert result.lower == pytest.approx(brute, abs=1e-9)
        assert result.upper is None
    assert result.worst_case == pytest.approx(brute, abs=1e-9)
    assert result.worst_case_bound == pytest.approx(brute, abs=1e-9)
    for r in result.rounds:  # every round's worst case too, for the controller of that round
        assert r.certified
        assert r.worst_case == pytest.approx(r.oracle_bound, abs=1e-9)
    assert result.certified
    assert result.master == "gradient"
    assert result.master_bound is None
    assert result.gap is None and not result.optimal
    document = result.to_dict()
    assert document["randomized"] and document["master_bound"] is None
    # no worse than the best observation-blind controller (an incumbent of the loop), whose
    # worst case is its nominal value, by brute force over the constant controllers
    from misdirect.defence.robust import blind_controllers

    blind = [
        goal_probability(replace(problem, controller=c), problem.identity())
        for c in blind_controllers(problem)
    ]
    if objective == "decoy":
        assert result.worst_case <= min(1.0 - g for g in blind) + 1e-9  # every run absorbed
    else:
        assert result.worst_case >= max(blind) - 1e-9


def test_gradient_master_floor_on_goal():
    """With a floor the blind controller meets, the answer meets it (the blind one is a start)
    and its worst case is certified."""
    problem = absorbed_problem(1, 1.0)
    from misdirect.defence.robust import blind_controllers

    floor = max(
        goal_probability(replace(problem, controller=c), problem.identity())
        for c in blind_controllers(problem)
    )
    result = misdirect.robust_controller(
        problem, 1.0, memory=2, randomized=True, restarts=2, min_goal=floor
    )
    chosen = replace(problem, controller=result.controller)
    assert result.nominal_goal == pytest.approx(goal_probability(chosen, problem.identity()))
    assert result.nominal_goal >= floor - 1e-9
    brute = max(decoy_probability(chosen, a) for a in alterations_within(problem, 1.0))
    assert result.worst_case == pytest.approx(brute, abs=1e-9)
    with pytest.raises(misdirect.ProblemError):
        misdirect.robust_controller(problem, 1.0, objective="goal", min_goal=0.5)
    with pytest.raises(misdirect.ProblemError):
        misdirect.robust_controller(problem, 1.0, randomized=True, min_goal=1.5)


@pytest.mark.parametrize("suffix", [".fsc.json", ".yaml"])
def test_randomized_controller_round_trip_and_storm(tmp_path, suffix):
    """A full-support randomized controller written in PAYNT's format and in misdirect's rules
    loads back with --controller to the same numbers, and Storm checks the induced chain."""
    stormpy = pytest.importorskip("stormpy")
    from misdirect.io.paynt import controller_to_paynt
    from misdirect.io.problem_file import controller_to_document, problem_document_text

    problem = absorbed_problem(3, 1.0)
    controller, *_ = softmax_controller(problem, 2, 7)
    assert not controller.is_deterministic
    path = tmp_path / "p.yaml"
    write_problem(problem, path)
    written = tmp_path / f"c{suffix}"
    if suffix == ".yaml":
        written.write_text(problem_document_text(controller_to_document(controller, problem.pomdp)))
    else:
        written.write_text(json.dumps(controller_to_paynt(controller, problem.pomdp)))
    alpha = np.array([1, 0, 2, 3])  # a -> b, b -> a (the initial reading a stays: state s0)
    alpha[problem.pomdp.initial_observation] = problem.pomdp.initial_observation
    chosen = replace(problem, controller=controller)
    alter = [f"{problem.pomdp.observations[o]}={problem.pomdp.observations[t]}"
             for o, t in enumerate(alpha) if o != t]  # fmt: skip
    flags = [item for a in alter for item in ("--alter", a)]
    run = runner.invoke(
        app, ["evaluate", str(path), "--controller", str(written), *flags, "--json"]
    )
    assert run.exit_code == 0, run.output
    assert json.loads(run.output)["value"] == pytest.approx(
        decoy_probability(chosen, alpha), abs=1e-12
    )
    chain = tmp_path / "chain.drn"
    run = runner.invoke(
        app,
        ["export-chain", str(path), "--controller", str(written), *flags, "-o", str(chain),
         "--json"],
    )  # fmt: skip
    assert run.exit_code == 0, run.output
    model = stormpy.build_model_from_drn(str(chain))
    formula = stormpy.parse_properties('P=? [F "decoy"]')[0]
    storm = stormpy.model_checking(model, formula).get_value(model.initial_states[0])
    assert storm == pytest.approx(decoy_probability(chosen, alpha), abs=1e-6)


def test_cli_randomized_writes_a_controller_that_loads_back(tmp_path):
    problem = absorbed_problem(0, 1.0)
    path = tmp_path / "p.yaml"
    write_problem(problem, path)
    for name in ("r.fsc.json", "r.yaml"):
        out = tmp_path / name
        run = runner.invoke(
            app,
            ["controller", "robust", str(path), "--budget", "1", "--memory", "2",
             "--randomized", "--restarts", "2", "--seed", "3", "-o", str(out), "--json"],
        )  # fmt: skip
        assert run.exit_code == 0, run.output
        robust = json.loads(run.output)["robust"]
        assert robust["master"] == "gradient" and robust["master_bound"] is None
        solved = runner.invoke(
            app, ["solve", str(path), "--controller", str(out), "--budget", "1", "--json"]
        )
        assert solved.exit_code == 0, solved.output
        final = json.loads(solved.output)["curve"][-1]
        assert final["value"] == pytest.approx(robust["worst_case"], abs=1e-9)
        loaded = runner.invoke(app, ["evaluate", str(path), "--controller", str(out), "--json"])
        assert json.loads(loaded.output)["value"] == pytest.approx(robust["nominal"], abs=1e-9)
    shown = runner.invoke(
        app,
        ["controller", "robust", str(path), "--budget", "1", "--memory", "2", "--randomized",
         "--restarts", "1", "--baselines", "none", "-o", str(tmp_path / "s.yaml")],
    )  # fmt: skip
    assert shown.exit_code == 0, shown.output
    assert "seed observation-blind: worst case" in shown.output
    assert "seed exact one-node: worst case" in shown.output
    bad = runner.invoke(
        app,
        ["controller", "robust", str(path), "--budget", "1", "--min-goal", "0.5",
         "--objective", "goal", "-o", str(tmp_path / "x.fsc.json")],
    )  # fmt: skip
    assert bad.exit_code == 2
    assert "Traceback" not in bad.output


def test_cli_exact_master_with_floor(tmp_path):
    """`--min-goal` without `--randomized`: the exact master's answer meets the floor, and a
    floor nothing meets is one line naming the option, exit 2."""
    problem = three_ends_problem(0, 1.0)
    path = tmp_path / "p.yaml"
    write_problem(problem, path)
    out = tmp_path / "r.fsc.json"
    args = ["controller", "robust", str(path), "--budget", "1", "-o", str(out)]
    run = runner.invoke(app, [*args, "--min-goal", "0.7", "--json"])
    assert run.exit_code == 0, run.output
    robust = json.loads(run.output)["robust"]
    assert robust["master"] == "exact" and robust["min_goal"] == 0.7
    loaded = load_problem(path, controller=str(out))
    assert goal_probability(loaded, problem.identity()) >= 0.7
    bad = runner.invoke(app, [*args, "--min-goal", "0.99"])
    assert bad.exit_code == 2
    assert "Traceback" not in bad.output and "min_goal" in bad.output
    bad = runner.invoke(app, [*args, "--baselines", "given,cheapest"])
    assert bad.exit_code == 2
    assert "Traceback" not in bad.output and "--baselines" in bad.output


# -- the harden and PAYNT baselines ------------------------------------------------------------


def worst_under(problem: Problem, budget: float, protected: set[int], objective: str) -> float:
    """The worst value over every alteration within ``budget`` that leaves ``protected``
    alone, by plain loops (decoy: the largest Pr(decoy); goal: the smallest Pr(goal))."""
    alphas = [a for a in alterations_within(problem, budget) if all(a[o] == o for o in protected)]
    if objective == "decoy":
        return max(decoy_probability(problem, a) for a in alphas)
    return min(goal_probability(problem, a) for a in alphas)


@pytest.mark.parametrize("objective", ["decoy", "goal"])
@pytest.mark.parametrize("seed", [0, 2])
def test_harden_baseline_matches_brute_force(seed, objective):
    """With unit costs the defender protects as many sensors as the attacker alters (D = B =
    1): the baseline is the given controller with one sensor protected, its worst case the
    brute-force one under that protection, and no other single sensor protects better."""
    problem = three_ends_problem(seed, 1.0)
    result = misdirect.robust_controller(problem, 1.0, objective=objective, baselines=("harden",))
    (hardened,) = result.baselines
    assert hardened.kind == "harden" and hardened.certified
    assert hardened.protection is not None and len(hardened.protection) <= 1
    names = problem.pomdp.observations
    protected = {names.index(name) for name in hardened.protection}
    expected = worst_under(problem, 1.0, protected, objective)
    assert hardened.worst_case == pytest.approx(expected, abs=1e-9)
    if objective == "decoy":  # harden's own objective: its choice is the best single sensor
        best = min(worst_under(problem, 1.0, {o}, objective) for o in range(len(names)))
        assert hardened.worst_case == pytest.approx(best, abs=1e-9)
    assert hardened.nominal_goal == pytest.approx(goal_probability(problem, problem.identity()))
    assert result.skipped_baselines == ()


def test_harden_baseline_skipped_when_costs_differ():
    problem = absorbed_problem(0, 1.0)
    problem = replace(problem, cost=CostModel(n_observations=4, pairs={(0, 1): 0.5}))
    result = misdirect.robust_controller(problem, 1.0, baselines=("harden",))
    assert result.baselines == ()
    (skipped,) = result.skipped_baselines
    assert skipped.kind == "harden" and "costs" in skipped.reason
    document = result.to_dict()
    assert document["skipped_baselines"] == [{"kind": "harden", "reason": skipped.reason}]


def test_paynt_baseline_is_nominally_optimal_and_its_worst_case_certified():
    """PAYNT's one-node controller reaches the goal as often as the best of every memoryless
    deterministic controller (brute force), and its worst case is the brute-force one, and
    misdirect.solve's on that controller."""
    pytest.importorskip("paynt")
    problem = three_ends_problem(2, 1.0)
    result = misdirect.robust_controller(problem, 1.0, baselines=("paynt",))
    if result.skipped_baselines:
        pytest.skip(result.skipped_baselines[0].reason)
    (paynt,) = result.baselines
    assert paynt.kind == "paynt" and paynt.certified
    best_goal = max(
        goal_probability(replace(problem, controller=memoryless(problem, t)), problem.identity())
        for t in itertools.product(range(2), repeat=4)
    )
    assert paynt.nominal_goal == pytest.approx(best_goal, abs=1e-6)  # PAYNT's own precision
    chosen = replace(problem, controller=paynt.controller)
    assert paynt.worst_case == pytest.approx(worst_decoy(chosen, 1.0), abs=1e-9)
    solved = misdirect.solve(chosen, budgets=[1.0]).curve[-1]
    assert solved.probability == pytest.approx(paynt.worst_case, abs=1e-9)


def test_paynt_baseline_skipped_without_paynt(monkeypatch):
    from misdirect.io import paynt_synthesis

    def missing():
        raise misdirect.ProblemError(paynt_synthesis.NEEDS_PAYNT)

    monkeypatch.setattr(paynt_synthesis, "_paynt", missing)
    result = misdirect.robust_controller(absorbed_problem(0, 1.0), 1.0, baselines=("paynt",))
    assert result.baselines == ()
    (skipped,) = result.skipped_baselines
    assert skipped.kind == "paynt" and "needs paynt" in skipped.reason


@pytest.mark.parametrize("objective", ["decoy", "goal"])
@pytest.mark.parametrize("seed", range(3))
def test_gradient_master_no_worse_than_its_seeds(seed, objective):
    """The randomized answer's certified worst case is no worse than that of any controller
    it was seeded with, each computed independently: the exact one-node min-max by brute force
    over every (controller, alteration) pair, the given and blind ones by misdirect.solve on
    that controller (decoy) or brute force over the alterations (goal)."""
    problem = three_ends_problem(seed, 1.0)
    result = misdirect.robust_controller(
        problem, 1.0, memory=2, objective=objective, randomized=True, restarts=1, seed=seed,
        baselines=("given", "blind"), max_rounds=1,
    )  # fmt: skip
    names = {s.name for s in result.seeds}
    assert {"given controller", "observation-blind", "exact one-node"} <= names
    assert all(s.certified for s in result.seeds)
    alphas = list(alterations_within(problem, 1.0))

    def worst(controller: Controller) -> float:
        chosen = replace(problem, controller=controller)
        if objective == "decoy":
            return misdirect.solve(chosen, budgets=[1.0]).curve[-1].probability
        return min(goal_probability(chosen, a) for a in alphas)

    chosen = replace(problem, controller=result.controller)
    if objective == "decoy":
        answer = max(decoy_probability(chosen, a) for a in alphas)
    else:
        answer = min(goal_probability(chosen, a) for a in alphas)
    assert result.worst_case == pytest.approx(answer, abs=1e-9)
    expected = [worst(b.controller) for b in result.baselines]  # given, blind
    expected.append(brute_minmax(problem, 1.0, objective))  # the exact one-node answer
    for value in expected:
        if objective == "decoy":
            assert answer <= value + 1e-9
        else:
            assert answer >= value - 1e-9
    # the seeds' reported worst cases are those values (the one-node answer's: the min-max)
    reported = sorted(s.worst_case for s in result.seeds)
    for value in expected:
        assert min(abs(r - value) for r in reported) <= 1e-9


def test_the_baselines_run_within_a_quarter_of_the_time_limit(monkeypatch):
    """Each baseline's oracle gets a share of a quarter of the time limit (the shares adding
    up to at most that quarter), harden its search within its share; without a limit, none."""
    from misdirect.defence import robust_baselines

    given: list[float | None] = []
    ends: list[float] = []  # when each oracle's share runs out
    real = robust_baselines.oracle

    def recording(problem, controller, objective, budget, seconds):
        given.append(seconds)
        if seconds is not None:
            ends.append(time.perf_counter() + seconds)
        return real(problem, controller, objective, budget, seconds)

    monkeypatch.setattr(robust_baselines, "oracle", recording)
    problem = absorbed_problem(3, 1.0)
    limit = 40.0
    quarter = robust_baselines.BASELINES_SHARE * limit
    began = time.perf_counter()
    misdirect.robust_controller(problem, 1.0, time_limit=limit, baselines=["given", "blind"])
    assert len(given) == 2 and all(s is not None for s in given)
    assert given[0] == pytest.approx(quarter / 2, rel=0.05)  # an even share of the quarter
    assert given[1] >= given[0] * 0.95  # ... and what the first left rolls over
    assert max(ends) <= began + quarter + 0.5  # none outlasts the quarter
    given.clear()
    misdirect.robust_controller(problem, 1.0, baselines=["given", "blind"])
    assert given == [None, None]


def test_a_search_baseline_with_no_time_left_is_skipped_not_an_error(monkeypatch):
    """Where the oracles before it used the baselines' whole share (a drone's first oracle
    ran past its share at --time-limit 60), harden got 0 s and the run stopped with "--time-
    limit: must be a positive number of seconds, got 0.0". It is now skipped, saying why."""
    from misdirect.defence import robust_baselines

    real = robust_baselines.oracle

    def overrunning(problem, controller, objective, budget, seconds):
        found = real(problem, controller, objective, budget, seconds)
        time.sleep(seconds + 1.0)  # past its share, and past the baselines' end
        return found

    monkeypatch.setattr(robust_baselines, "oracle", overrunning)
    problem = absorbed_problem(3, 1.0)
    result = misdirect.robust_controller(
        problem, 1.0, time_limit=4.0, baselines=["given", "blind", "harden"]
    )
    assert [b.kind for b in result.baselines] == ["given", "blind"]
    (skipped,) = result.skipped_baselines
    assert skipped.kind == "harden" and "no time left" in skipped.reason


def test_the_gradient_masters_ranking_stops_at_the_deadline():
    """Past the direct solver's size, the gradient master ranks each candidate in a forked
    copy killed at its deadline: an exact evaluation there is one sparse LU, which on the
    drone's 103,000-state chain of a sharp controller ran for more than ten minutes, past a
    60 s limit. A ranking that would take 60 s here is cut at the 1 s deadline."""
    from misdirect.defence.robust_gradient import ChainModel, GradientMaster
    from misdirect.defence.robust_oracle import target_and_worth
    from misdirect.solvers.deadline import Deadline

    problem = three_ends_problem(0, 1.0)
    target, worth = target_and_worth(problem, "decoy")
    model = ChainModel(problem.pomdp, target, worth, 2, direct_limit=0)  # "large"
    master = GradientMaster(model, -1.0, restarts=1)

    def slow(controller: Controller) -> tuple[float, float, float]:
        time.sleep(60)
        return 0.0, 0.0, 0.0

    began = time.perf_counter()
    assert master.solve([problem.identity()], Deadline(1.0), slow) is None
    assert time.perf_counter() - began < 15
