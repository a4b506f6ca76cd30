"""Randomized controllers: in node n reading o the robot draws (action, next node) from a
distribution (joint, or factored: action and next node drawn independently).

Oracles: a hand calculation; Storm's exact check of the product it builds itself from a PRISM
encoding (tests/prism_product.py); brute force over every alteration function (as in
tests/test_exhaustive.py); PAYNT's own induced chain of a randomized FscFactored."""

from __future__ import annotations

import json
import textwrap
from pathlib import Path

import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from misdirect import decoy_probability, load_problem, solve
from misdirect.cli import app
from misdirect.core.model import Controller
from misdirect.core.simulate import simulate
from misdirect.errors import ProblemError
from misdirect.io.paynt import controller_to_paynt
from misdirect.io.problem_file import problem_text
from misdirect.scenarios import random_problem
from misdirect.solvers.incremental import NotApplicableError
from prism_product import random_allowed_alteration, storm_probability
from test_exhaustive import brute_force_curve

runner = CliRunner()
DATA = Path(__file__).parent / "data"

# s0 --a--> s1 (prob 1); s0 --b--> goal. s1 --a--> trap (decoy), s1 --b--> goal.
# One observation for s0 and s1 (o), one for goal and trap (g). Two nodes.
TINY = textwrap.dedent(
    """
    format: misdirect/v1
    pomdp:
      states: [s0, s1, goal, trap]
      actions: [a, b]
      initial: s0
      observe: {s0: o, s1: o, goal: g, trap: g}
      transitions:
        - [s0, a, s1, 1.0]
        - [s0, b, goal, 1.0]
        - [s1, a, trap, 1.0]
        - [s1, b, goal, 1.0]
      absorbing: [goal, trap]
    controller:
      nodes: [n0, n1]
      initial: n0
      rules:
        - {node: n0, obs: o, action: {a: 0.75, b: 0.25}, next: {n0: 0.5, n1: 0.5}}
        - node: n1
          obs: o
          moves: [{action: a, next: n1, p: 0.2}, {action: b, next: n0, p: 0.8}]
        - {node: "*", obs: g, action: a, next: n0}
    deception:
      decoy: [trap]
      budget: 1
    """
)


def _tiny(tmp_path: Path, text: str = TINY) -> Path:
    path = tmp_path / "tiny.yaml"
    path.write_text(text)
    return path


def test_tiny_randomized_controller_by_hand(tmp_path):
    """From (s0, n0): a with 3/4 reaches s1, in n0 or n1 with 1/2 each (b: goal, lost).
    In (s1, n0): a with 3/4 -> trap. In (s1, n1): a with 1/5 -> trap.
    Pr = 3/4 · (1/2 · 3/4 + 1/2 · 1/5) = 3/4 · 19/40 = 57/160."""
    problem = load_problem(_tiny(tmp_path))
    assert not problem.controller.is_deterministic
    assert decoy_probability(problem, problem.identity()) == pytest.approx(57 / 160, abs=1e-15)
    # the factored rule is the product: four (action, next) pairs in node n0
    o = problem.pomdp.observations.index("o")
    _, action, nxt, p = problem.controller.entries(np.array([0]), np.array([o]))
    assert sorted(zip(action.tolist(), nxt.tolist(), p.tolist(), strict=True)) == [
        (0, 0, 0.375),
        (0, 1, 0.375),
        (1, 0, 0.125),
        (1, 1, 0.125),
    ]


def test_randomized_controller_has_no_action_table(tmp_path):
    controller = load_problem(_tiny(tmp_path)).controller
    with pytest.raises(ProblemError, match="randomized"):
        _ = controller.action


def test_deterministic_rules_give_the_deterministic_controller():
    action = np.array([[0, 1, 1], [1, 0, 1]])
    update = np.array([[0, 1, 0], [1, 1, 0]])
    one = Controller(nodes=("x", "y"), initial_node=0, action=action, update=update)
    node, obs = np.indices(action.shape)
    two = Controller.from_entries(
        nodes=("x", "y"),
        initial_node=0,
        n_observations=3,
        node=node.ravel(),
        observation=obs.ravel(),
        action=action.ravel(),
        next_node=update.ravel(),
        probability=np.ones(6),
    )
    assert one.is_deterministic and two.is_deterministic
    assert np.array_equal(two.action, action) and np.array_equal(two.update, update)
    assert np.array_equal(one.move, two.move)


def test_behaviour_classes_compare_distributions():
    """Observations 0 and 2 get the same distribution on every node (given in another
    order and split into repeated entries), observation 1 a different one on node 1 only."""
    rows = [  # node, obs, action, next, p
        (0, 0, 0, 0, 0.5), (0, 0, 1, 1, 0.5),
        (0, 2, 1, 1, 0.25), (0, 2, 0, 0, 0.5), (0, 2, 1, 1, 0.25),
        (0, 1, 0, 0, 0.5), (0, 1, 1, 1, 0.5),
        (1, 0, 1, 0, 1.0), (1, 2, 1, 0, 1.0),
        (1, 1, 1, 0, 0.5), (1, 1, 1, 1, 0.5),
    ]  # fmt: skip
    node, obs, action, nxt, p = (np.array(c) for c in zip(*rows, strict=True))
    controller = Controller.from_entries(
        nodes=("x", "y"),
        initial_node=0,
        n_observations=3,
        node=node,
        observation=obs,
        action=action,
        next_node=nxt,
        probability=p,
    )
    classes = controller.behaviour_class
    assert classes[0] == classes[2] != classes[1]


# -- against Storm ------------------------------------------------------------------------------

stormpy = pytest.importorskip("stormpy")


def test_tiny_agrees_with_storm(tmp_path):
    problem = load_problem(_tiny(tmp_path))
    assert storm_probability(tmp_path, problem, problem.identity()) == pytest.approx(
        57 / 160, abs=1e-12
    )


def test_random_randomized_chains_agree_with_storm(tmp_path):
    rng = np.random.default_rng(7)
    checked, nontrivial = 0, 0
    for seed in range(40):
        problem = random_problem(
            seed, states=int(rng.integers(3, 9)), nodes=int(rng.integers(1, 4)), randomized=True
        )
        assert not problem.controller.is_deterministic
        alpha = random_allowed_alteration(problem, rng)
        ours = decoy_probability(problem, alpha)
        theirs = storm_probability(tmp_path, problem, alpha)
        assert ours == pytest.approx(theirs, abs=1e-9), f"seed {seed}"
        checked += 1
        nontrivial += 1e-6 < ours < 1 - 1e-6
    assert checked >= 30
    assert nontrivial >= 10  # not only 0/1 answers


def test_simulation_agrees_with_evaluation():
    hits = 0
    for seed in (1, 4, 9):
        problem = random_problem(seed, states=6, nodes=2, randomized=True)
        exact = decoy_probability(problem, problem.identity())
        sim = simulate(problem, runs=40_000, seed=seed)
        low, high = sim.confidence_interval(z=4.0)
        assert low <= exact <= high, (seed, exact, low, high)
        hits += 0.01 < exact < 0.99
    assert hits >= 1


# -- every solver against brute force -------------------------------------------------------

BUDGETS = [0.0, 1.0, 2.0, 3.0]


def _suite():
    return [
        random_problem(seed, states=5, observations=3, nodes=2, budget=3, randomized=True)
        for seed in range(25)
    ]


@pytest.fixture(scope="module")
def suite_and_truth():
    problems = _suite()
    return problems, [brute_force_curve(p, BUDGETS) for p in problems]


@pytest.mark.parametrize(
    "method,options",
    [
        ("exhaustive", {}),
        ("branch-and-bound", {}),
        ("milp", {}),
        ("auto", {}),
    ],
)
def test_solvers_equal_brute_force_on_randomized_controllers(suite_and_truth, method, options):
    problems, truth = suite_and_truth
    positive = 0
    for problem, expected in zip(problems, truth, strict=True):
        result = solve(problem, method=method, budgets=BUDGETS, **options)
        for point, best in zip(result.curve, expected, strict=True):
            where = (problem.name, method, point.budget)
            assert point.probability == pytest.approx(best, abs=1e-9), where
            assert point.cost <= point.budget, where
            alpha = problem.alteration(point.alteration)
            assert decoy_probability(problem, alpha) == pytest.approx(best, abs=1e-9), where
            assert point.status == "optimal", where
            positive += best > 1e-6
    assert positive >= 20  # the suite is not all zeros


def test_incremental_on_randomized_controllers(suite_and_truth):
    problems, truth = suite_and_truth
    tried = 0
    for problem, expected in zip(problems, truth, strict=True):
        try:
            result = solve(problem, method="incremental", budgets=BUDGETS)
        except NotApplicableError as error:
            assert "cycle" in str(error)
            continue
        tried += 1
        for point, best in zip(result.curve, expected, strict=True):
            assert point.probability == pytest.approx(best, abs=1e-9), (problem.name, point)
    assert tried >= 3


def test_randomization_matters_to_the_attacker():
    """Sanity of the suite: the optimum differs from the deterministic controller's of the
    same world, so the randomized path is what is being checked."""
    differ = 0
    for seed in range(10):
        a = random_problem(seed, states=5, observations=3, nodes=2, budget=3, randomized=True)
        b = random_problem(seed, states=5, observations=3, nodes=2, budget=3)
        pa = solve(a, method="exhaustive", budgets=[3.0]).probability
        pb = solve(b, method="exhaustive", budgets=[3.0]).probability
        differ += abs(pa - pb) > 1e-6
    assert differ >= 3


# -- the v1 file ----------------------------------------------------------------------------------


@pytest.mark.parametrize("seed", range(8))
@pytest.mark.parametrize("as_json", [False, True])
def test_v1_round_trip(tmp_path, seed, as_json):
    problem = random_problem(seed, states=6, nodes=3, randomized=True)
    path = tmp_path / ("p.json" if as_json else "p.yaml")
    path.write_text(problem_text(problem, as_json=as_json))
    again = load_problem(path)
    c, d = problem.controller, again.controller
    assert not d.is_deterministic
    assert np.array_equal(c.move, d.move)  # same moves, same ids
    assert np.array_equal(c.move_ptr, d.move_ptr)
    assert np.array_equal(c.move_action, d.move_action)
    assert np.array_equal(c.move_next, d.move_next)
    assert np.allclose(c.move_probability, d.move_probability, rtol=0, atol=1e-12)
    rng = np.random.default_rng(seed)
    alpha = random_allowed_alteration(problem, rng)
    assert decoy_probability(again, alpha) == pytest.approx(
        decoy_probability(problem, alpha), abs=1e-12
    )


def test_v1_writes_factored_maps_and_joint_moves(tmp_path):
    document = yaml.safe_load(problem_text(load_problem(_tiny(tmp_path))))
    rules = document["controller"]["rules"]
    n0 = next(r for r in rules if r["node"] == "n0" and r["obs"] == "o")
    n1 = next(r for r in rules if r["node"] == "n1" and r["obs"] == "o")
    assert n0["action"] == {"a": 0.75, "b": 0.25} and n0["next"] == {"n0": 0.5, "n1": 0.5}
    assert sorted((m["action"], m["next"], m["p"]) for m in n1["moves"]) == [
        ("a", "n1", 0.2),
        ("b", "n0", 0.8),
    ]


BAD_RULES = {  # changes to rule 0 (node n0, observation o), field, words of the message
    "sum below 1": ({"action": {"a": 0.5, "b": 0.4}}, "controller.rules[0].action", "sum to 0.9"),
    "probability above 1": (
        {"next": {"n0": 1.5, "n1": -0.5}},
        "controller.rules[0].next",
        "[0, 1]",
    ),
    "not a number": ({"action": {"a": "high", "b": 0.5}}, "controller.rules[0].action", "'high'"),
    "unknown action": ({"action": {"a": 0.5, "jump": 0.5}}, "controller.rules[0].action", "jump"),
    "empty map": ({"next": {}}, "controller.rules[0].next", "empty"),
    "joint sum": (
        {
            "action": None,
            "next": None,
            "moves": [
                {"action": "a", "next": "n0", "p": 0.3},
                {"action": "b", "next": "n1", "p": 0.3},
            ],
        },
        "controller.rules[0].moves",
        "sum to 0.6",
    ),
    "both forms": (
        {"moves": [{"action": "a", "next": "n0", "p": 1.0}]},
        "controller.rules[0]",
        "not both",
    ),
}


@pytest.mark.parametrize("case", list(BAD_RULES))
def test_bad_distributions_are_one_clear_error(tmp_path, case):
    changes, field, words = BAD_RULES[case]
    document = yaml.safe_load(TINY)
    rule = document["controller"]["rules"][0]
    rule.update(changes)
    for key in [k for k, v in rule.items() if v is None]:
        del rule[key]
    path = _tiny(tmp_path, yaml.safe_dump(document))
    result = runner.invoke(app, ["evaluate", str(path)])
    assert result.exit_code == 2, result.output
    message = result.stderr
    assert message.count("\n") == 1, message
    assert str(path) in message and field in message and words in message, message


def test_cli_evaluate_solve_simulate_show_convert(tmp_path):
    path = _tiny(tmp_path)
    result = runner.invoke(app, ["evaluate", str(path), "--json"])
    assert result.exit_code == 0, result.output
    assert json.loads(result.stdout)["value"] == pytest.approx(57 / 160, abs=1e-12)
    result = runner.invoke(app, ["solve", str(path), "--json"])
    assert result.exit_code == 0, result.output
    result = runner.invoke(app, ["simulate", str(path), "--runs", "2000", "--json"])
    assert result.exit_code == 0, result.output
    dot = tmp_path / "chain.dot"
    result = runner.invoke(app, ["show", str(path), "-o", str(dot)])
    assert result.exit_code == 0, result.output
    assert "0.375" in dot.read_text()  # (s0, n0) -> (s1, n0): 3/4 · 1/2
    out = tmp_path / "again.yaml"
    result = runner.invoke(app, ["convert", str(path), "--to", "yaml", "-o", str(out)])
    assert result.exit_code == 0, result.output
    again = load_problem(out)
    assert decoy_probability(again, again.identity()) == pytest.approx(57 / 160, abs=1e-15)


# -- PAYNT files ---------------------------------------------------------------------------------


def test_export_fsc_round_trips_randomized(tmp_path):
    problem = load_problem(_tiny(tmp_path))
    fsc = controller_to_paynt(problem.controller, problem.pomdp)
    assert "transitions" in fsc  # n1's move is not a product of its marginals
    (tmp_path / "robot.fsc.json").write_text(json.dumps(fsc))
    document = yaml.safe_load(TINY)
    document["controller"] = {"paynt": "robot.fsc.json"}
    (tmp_path / "p.yaml").write_text(yaml.safe_dump(document))
    again = load_problem(tmp_path / "p.yaml")
    assert decoy_probability(again, again.identity()) == pytest.approx(57 / 160, abs=1e-15)


def test_export_fsc_writes_factored_form_when_it_is_one(tmp_path):
    problem = random_problem(3, states=6, nodes=2, randomized=True)
    factored = [m for m in range(problem.controller.n_moves) if problem.controller.factored_move(m)]
    assert factored  # the random controller has factored moves
    text = TINY.replace(
        "- node: n1\n      obs: o\n      moves: [{action: a, next: n1, p: 0.2}, "
        "{action: b, next: n0, p: 0.8}]",
        "- {node: n1, obs: o, action: {a: 0.2, b: 0.8}, next: n0}",
    )
    tiny = load_problem(_tiny(tmp_path, text))
    fsc = controller_to_paynt(tiny.controller, tiny.pomdp)
    assert "action_function" in fsc and fsc["is_deterministic"] is False
    o = tiny.pomdp.observations.index("o")
    assert fsc["action_function"][0][o] == {"0": 0.75, "1": 0.25}
    assert fsc["update_function"][0][o] == {"0": 0.5, "1": 0.5}
    assert fsc["action_function"][1][o] == {"0": 0.2, "1": 0.8}
    assert fsc["update_function"][1][o] == {"0": 1.0}


def test_paynt_joint_forms_load(tmp_path):
    """The joint form in each shape PAYNT's Fsc.transitions may be written in."""
    document = yaml.safe_load(TINY)
    problem = load_problem(_tiny(tmp_path))
    base = controller_to_paynt(problem.controller, problem.pomdp)
    o = problem.pomdp.observations.index("o")
    variants = {
        "pairs": [[0, 1, 0.2], [1, 0, 0.8]],
        "records": [
            {"action": 0, "update": 1, "probability": 0.2},
            {"action": 1, "memory": 0, "prob": 0.8},
        ],
        "keys": {"0,1": 0.2, "(1, 0)": 0.8},
    }
    for name, entry in variants.items():
        fsc = json.loads(json.dumps(base))
        fsc["transitions"][1][o] = entry
        (tmp_path / f"{name}.fsc.json").write_text(json.dumps(fsc))
        document["controller"] = {"paynt": f"{name}.fsc.json"}
        (tmp_path / f"{name}.yaml").write_text(yaml.safe_dump(document))
        again = load_problem(tmp_path / f"{name}.yaml")
        value = decoy_probability(again, again.identity())
        assert value == pytest.approx(57 / 160, abs=1e-15), name


def test_paynt_randomized_sum_error_names_field(tmp_path):
    problem = load_problem(_tiny(tmp_path))
    fsc = controller_to_paynt(problem.controller, problem.pomdp)
    fsc["transitions"][0][0] = {"(0, 0)": 0.5, "(1, 1)": 0.4}
    (tmp_path / "robot.fsc.json").write_text(json.dumps(fsc))
    document = yaml.safe_load(TINY)
    document["controller"] = {"paynt": "robot.fsc.json"}
    (tmp_path / "p.yaml").write_text(yaml.safe_dump(document))
    result = runner.invoke(app, ["evaluate", str(tmp_path / "p.yaml")])
    assert result.exit_code == 2, result.output
    assert result.stderr.count("\n") == 1
    assert "robot.fsc.json" in result.stderr and "transitions[0][0]" in result.stderr
    assert "sum to 0.9" in result.stderr
