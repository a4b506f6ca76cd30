"""Modelling traps named: a start cell that shares its reading, the flagship example where an
attack helps, PRISM-style fractions as probabilities, and every validation problem of a file
reported at once."""

import itertools
import json
from fractions import Fraction
from pathlib import Path

import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from misdirect import evaluate, load_problem, solve
from misdirect.cli import app
from misdirect.errors import MAX_REPORTED, ProblemError, ProblemsError

ROOT = Path(__file__).parents[1]
TINY = ROOT / "examples" / "tiny.yaml"
runner = CliRunner()


def _write(tmp_path: Path, document: dict, name: str = "p.yaml") -> Path:
    path = tmp_path / name
    path.write_text(yaml.safe_dump(document, sort_keys=False))
    return path


def _chain(probabilities: list) -> dict:
    """s0 -a-> s1 | s2 with the given probabilities; decoy s1."""
    return {
        "format": "misdirect/v1",
        "pomdp": {
            "states": ["s0", "s1", "s2"],
            "actions": ["a"],
            "initial": "s0",
            "observe": {"s0": "o0", "s1": "o1", "s2": "o2"},
            "transitions": [
                ["s0", "a", "s1", probabilities[0]],
                ["s0", "a", "s2", probabilities[1]],
            ],
            "absorbing": ["s1", "s2"],
        },
        "controller": {
            "nodes": ["n"],
            "initial": "n",
            "rules": [{"node": "*", "obs": "*", "action": "a", "next": "n"}],
        },
        "deception": {"decoy": ["s1"], "budget": 0},
    }


# -- the flagship example ----------------------------------------------------------------------


def test_tiny_attack_helps_at_budget_one():
    """By hand (examples/tiny.yaml's description): 0.2 without attack; o2 -> o1 gives
    0.5 * 0.2 + 0.5 * 1 = 0.6 at budget 1..3; o1 -> o2 with o2 -> o1 (cost 4) gives 1."""
    problem = load_problem(TINY)
    assert problem.budget == 1
    result = solve(problem, budgets=[0, 1, 2, 3, 4])
    assert [point.probability for point in result.curve] == pytest.approx(
        [0.2, 0.6, 0.6, 0.6, 1.0], abs=1e-12
    )
    assert result.curve[1].cost <= 1


def test_tiny_optimum_by_brute_force():
    """Every alteration the cost model allows, enumerated here, none better than 0.6 at
    budget 1, and some reaching it."""
    problem = load_problem(TINY)
    names = problem.pomdp.observations
    cost = problem.cost.matrix()
    alterable = [o for o in range(len(names)) if names[o] not in ("o0", "g")]  # initial, protected
    best = 0.0
    for targets in itertools.product(range(len(names)), repeat=len(alterable)):
        alteration = np.arange(len(names))
        alteration[alterable] = targets
        total = sum(cost[o, t] for o, t in zip(alterable, targets, strict=True) if o != t)
        if total <= 1:
            best = max(best, evaluate(problem, alteration).probability)
    assert best == pytest.approx(0.6, abs=1e-12)


# -- the start cell's reading ------------------------------------------------------------------

GRID = """
. . G
S 1 X
. 2 .
"""


def _grid(tmp_path: Path, start: dict) -> Path:
    document = {
        "format": "misdirect/v1",
        "grid": {"map": GRID, "legend": {"S": start, "G": "goal", "X": "decoy", ".": "blank"}},
        "controller": {
            "nodes": ["n"],
            "initial": "n",
            "rules": [{"node": "*", "obs": "*", "action": "E", "next": "n"}],
        },
        "deception": {"budget": 1},
    }
    return _write(tmp_path, document)


def test_start_cell_without_sensor_is_named(tmp_path):
    """S reads b, as do the four '.' cells: those four can never be altered; the map has
    seven open non-absorbing cells (S, 1, 2 and four blanks)."""
    problem = load_problem(_grid(tmp_path, {"start": True}))
    (note,) = [text for text in problem.notes if "never altered" in text]
    assert "'b'" in note and "the 4 other states" in note and "4 of the 7" in note
    assert "sensor" in note  # says what to do
    result = runner.invoke(app, ["solve", str(_grid(tmp_path, {"start": True}))])
    assert result.exit_code == 0, result.output
    assert "never altered" in result.stderr


def test_start_cell_with_its_own_sensor_is_quiet(tmp_path):
    problem = load_problem(_grid(tmp_path, {"start": True, "sensor": "9"}))
    assert not [text for text in problem.notes if "never altered" in text]


# -- fractions ---------------------------------------------------------------------------------


def test_fractions_are_exact_then_rounded_once(tmp_path):
    problem = load_problem(_write(tmp_path, _chain(["1/3", "2/3"])))
    matrix = problem.pomdp.transition_matrix(0).toarray()
    assert matrix[0, 1] == float(Fraction(1, 3)) and matrix[0, 2] == float(Fraction(2, 3))
    assert evaluate(problem).probability == pytest.approx(1 / 3, abs=1e-15)


def test_fractions_in_randomized_rules(tmp_path):
    document = _chain([0.5, 0.5])
    document["pomdp"]["actions"] = ["a", "b"]
    document["pomdp"]["transitions"] += [["s0", "b", "s2", 1.0]]
    document["controller"]["rules"] = [
        {"node": "*", "obs": "*", "action": {"a": "1/4", "b": "3/4"}, "next": "n"}
    ]
    problem = load_problem(_write(tmp_path, document))
    # a with 1/4 reaches s1 with 1/2; b never: 1/8
    assert evaluate(problem).probability == pytest.approx(1 / 8, abs=1e-15)
    document["controller"]["rules"] = [
        {
            "node": "*",
            "obs": "*",
            "moves": [
                {"action": "a", "next": "n", "p": "1/4"},
                {"action": "b", "next": "n", "p": "3/4"},
            ],
        }
    ]
    assert evaluate(load_problem(_write(tmp_path, document))).probability == pytest.approx(1 / 8)


@pytest.mark.parametrize(
    ("given", "said"),
    [
        ("1/0", "zero denominator"),
        ("inf", "fraction like"),
        ("nan", "fraction like"),
        ("2/3x", "fraction like"),
        ("1/3/4", "fraction like"),
        ("1" + "0" * 400 + "/1", "out of range"),
    ],
)
def test_bad_fractions_are_refused_naming_file_and_field(tmp_path, given, said):
    path = _write(tmp_path, _chain([given, "1/2"]))
    with pytest.raises(ProblemError) as caught:
        load_problem(path)
    assert said in caught.value.reason
    assert caught.value.source == str(path)
    assert caught.value.field == "pomdp.transitions[0][3]"


def test_bad_fraction_in_a_rule_is_refused(tmp_path):
    document = _chain([0.5, 0.5])
    document["controller"]["rules"] = [
        {"node": "*", "obs": "*", "action": {"a": "1/0"}, "next": "n"}
    ]
    with pytest.raises(ProblemError, match="zero denominator") as caught:
        load_problem(_write(tmp_path, document))
    assert caught.value.field == "controller.rules[0].action"


# -- every problem at once ---------------------------------------------------------------------


def test_every_schema_problem_is_reported(tmp_path):
    document = _chain(["1/0", 1.5])
    document["pomdp"]["bogus"] = 1
    path = _write(tmp_path, document)
    with pytest.raises(ProblemsError) as caught:
        load_problem(path)
    fields = {problem.field for problem in caught.value.problems}
    assert fields == {"pomdp.transitions[0][3]", "pomdp.transitions[1][3]", "pomdp.bogus"}
    assert all(problem.source == str(path) for problem in caught.value.problems)
    result = runner.invoke(app, ["evaluate", str(path)])
    assert result.exit_code == 2
    lines = [line for line in result.stderr.splitlines() if line.startswith("error:")]
    assert len(lines) == 3 and all(str(path) in line for line in lines)
    result = runner.invoke(app, ["evaluate", str(path), "--json"])
    assert len(json.loads(result.stdout)["error"]["problems"]) == 3


def test_every_semantic_problem_is_reported(tmp_path):
    """Three independent mistakes found after the schema stage (a row summing to 0.9, a rule
    on an observation no state emits, a protected observation that does not exist): each is
    reported with file and field, in the terminal and in the --json error document."""
    document = _chain([0.5, 0.4])
    document["controller"]["rules"].insert(
        0, {"node": "n", "obs": "o9", "action": "a", "next": "n"}
    )
    document["deception"]["cost"] = {"protected": ["o1", "oX"]}
    path = _write(tmp_path, document)
    expected = {
        "pomdp.transitions": "probabilities of ('s0', 'a') sum to 0.9, not 1",
        "controller.rules[0]": "unknown observation 'o9'",
        "deception.cost.protected[1]": "unknown observation 'oX'",
    }
    with pytest.raises(ProblemsError) as caught:
        load_problem(path)
    found = {problem.field: problem.reason for problem in caught.value.problems}
    assert set(found) == set(expected) and caught.value.total == 3
    assert all(found[field].startswith(reason) for field, reason in expected.items())
    assert all(problem.source == str(path) for problem in caught.value.problems)
    result = runner.invoke(app, ["solve", str(path)])
    assert result.exit_code == 2 and "Traceback" not in result.output
    lines = [line for line in result.stderr.splitlines() if line.startswith("error:")]
    assert len(lines) == 3
    for field, reason in expected.items():
        assert any(f"{path}: {field}: {reason}" in line for line in lines), (field, lines)
    result = runner.invoke(app, ["solve", str(path), "--json"])
    assert result.exit_code == 2
    problems = json.loads(result.stdout)["error"]["problems"]
    assert sorted(p.split(": ")[1] for p in problems) == sorted(expected)


def test_semantic_problems_beyond_the_limit_are_counted(tmp_path):
    document = _chain([0.5, 0.5])
    extra = MAX_REPORTED + 3
    document["deception"]["cost"] = {"protected": [f"x{i}" for i in range(extra)]}
    with pytest.raises(ProblemsError) as caught:
        load_problem(_write(tmp_path, document))
    assert caught.value.total == extra and len(caught.value.problems) == MAX_REPORTED
    assert caught.value.lines[-1] == "… and 3 more problems"


def test_problems_beyond_the_limit_are_counted(tmp_path):
    document = _chain([0.5, 0.5])
    extra = MAX_REPORTED + 5
    document["pomdp"]["transitions"] = [["s0", "a", "s1", "1/0"]] * extra
    with pytest.raises(ProblemsError) as caught:
        load_problem(_write(tmp_path, document))
    assert caught.value.total == extra and len(caught.value.problems) == MAX_REPORTED
    assert caught.value.lines[-1] == "… and 5 more problems"
