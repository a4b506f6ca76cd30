"""PAYNT controllers (``controller: {paynt: FILE}``) on an explicit model, no Storm needed: a good
file loads to the controller it describes, and every malformed one is a one-line error naming
the .fsc.json file, the field inside it and the reason, with exit code 2."""

from __future__ import annotations

import json

import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from misdirect import decoy_probability, load_problem
from misdirect.cli import app

runner = CliRunner()

# start --a--> s1 (0.5) or goal (0.5); s1 --a--> goal, s1 --b--> trap (the decoy)
PROBLEM = {
    "format": "misdirect/v1",
    "pomdp": {
        "states": ["start", "s1", "goal", "trap"],
        "actions": ["a", "b"],
        "initial": "start",
        "observe": {"start": "o0", "s1": "o1", "goal": "g", "trap": "g"},
        "transitions": [
            ["start", "a", "s1", 0.5],
            ["start", "a", "goal", 0.5],
            ["start", "b", "start", 1.0],
            ["s1", "a", "goal", 1.0],
            ["s1", "b", "trap", 1.0],
        ],
        "absorbing": ["goal", "trap"],
    },
    "controller": {"paynt": "robot.fsc.json"},
    "deception": {"decoy": ["trap"], "budget": 1},
}
# two nodes: n0 plays a on o1 and stays; on g (never seen unaltered) it plays b and moves to n1
GOOD = {
    "num_nodes": 2,
    "num_observations": 3,
    "action_function": [[0, 0, 1], [1, 1, 1]],
    "update_function": [[0, 0, 1], [1, 1, 1]],
    "action_labels": ["a", "b"],
    "observation_labels": ["o0", "o1", "g"],
}


def _write(tmp_path, fsc):
    (tmp_path / "robot.fsc.json").write_text(
        fsc if isinstance(fsc, str) else json.dumps(fsc), encoding="utf-8"
    )
    path = tmp_path / "p.yaml"
    path.write_text(yaml.safe_dump(PROBLEM))
    return path


def test_good_file_loads_and_evaluates_by_hand(tmp_path):
    """Unaltered: a at s1, the goal: 0. o1 read as g: node n0 plays b at s1, into the trap:
    0.5 (the other half went to the goal from the start)."""
    problem = load_problem(_write(tmp_path, GOOD))
    assert problem.controller.action.tolist() == [[0, 0, 1], [1, 1, 1]]
    assert problem.controller.update.tolist() == [[0, 0, 1], [1, 1, 1]]
    assert decoy_probability(problem, problem.identity()) == pytest.approx(0.0, abs=1e-12)
    assert decoy_probability(problem, problem.alteration({"o1": "g"})) == pytest.approx(0.5)


def test_labels_are_matched_by_name_in_any_order(tmp_path):
    fsc = dict(GOOD, observation_labels=["g", "o1", "o0"], action_labels=["b", "a"])
    # the same controller with columns and action indices permuted
    fsc["action_function"] = [[0, 1, 1], [0, 0, 0]]
    fsc["update_function"] = [[1, 0, 0], [1, 1, 1]]
    problem = load_problem(_write(tmp_path, fsc))
    assert problem.controller.action.tolist() == [[0, 0, 1], [1, 1, 1]]
    assert problem.controller.update.tolist() == [[0, 0, 1], [1, 1, 1]]


def _bad(**changes):
    fsc = json.loads(json.dumps(GOOD))
    fsc.update(changes)
    return fsc


MALFORMED = {
    "fewer update rows": (_bad(update_function=[[0, 0, 1]]), "update_function", "has 1 rows"),
    "short action row": (
        _bad(action_function=[[0, 0], [1, 1, 1]]),
        "action_function[0]",
        "has 2 entries, observation_labels has 3",
    ),
    "short update row": (
        _bad(update_function=[[0, 0, 1], [1]]),
        "update_function[1]",
        "has 1 entries",
    ),
    "long row": (
        _bad(action_function=[[0, 0, 1, 1], [1, 1, 1]]),
        "action_function[0]",
        "has 4 entries",
    ),
    "row not a list": (_bad(update_function=[[0, 0, 1], 7]), "update_function[1]", "a list"),
    "string action": (
        _bad(action_function=[[0, "a", 1], [1, 1, 1]]),
        "action_function[0][1]",
        "expected an action index (integer), got 'a'",
    ),
    "float node": (
        _bad(update_function=[[0, 0.5, 1], [1, 1, 1]]),
        "update_function[0][1]",
        "expected a node index (integer), got 0.5",
    ),
    "boolean node": (
        _bad(update_function=[[0, True, 1], [1, 1, 1]]),
        "update_function[0][1]",
        "got True",
    ),
    "action out of range": (
        _bad(action_function=[[0, 2, 1], [1, 1, 1]]),
        "action_function[0][1]",
        "action index 2 is out of range",
    ),
    "negative action": (
        _bad(action_function=[[0, -1, 1], [1, 1, 1]]),
        "action_function[0][1]",
        "out of range",
    ),
    "node out of range": (
        _bad(update_function=[[0, 0, 1], [1, 2, 1]]),
        "update_function[1][1]",
        "node 2 is out of range",
    ),
    "empty entry": (
        _bad(update_function=[[0, None, 1], [1, 1, 1]]),
        "update_function[0][1]",
        "empty",
    ),
    "randomized, not summing to 1": (  # randomized ones load (tests/test_randomized.py)
        _bad(action_function=[[0, {"0": 0.5, "1": 0.4}, 1], [1, 1, 1]]),
        "action_function[0][1]",
        "sum to 0.9",
    ),
    "bad randomized": (
        _bad(action_function=[[0, {"a": 1.0}, 1], [1, 1, 1]]),
        "action_function[0][1]",
        "action indices to probabilities",
    ),
    "num_nodes mismatch": (_bad(num_nodes=3), "num_nodes", "says 3"),
    "num_observations mismatch": (_bad(num_observations=4), "num_observations", "says 4"),
    "no nodes": (
        _bad(action_function=[], update_function=[], num_nodes=0),
        "action_function",
        "at least one node",
    ),
    "missing key": (
        {k: v for k, v in GOOD.items() if k != "update_function"},
        "update_function",
        "missing",
    ),
    "not a list": (_bad(action_labels="a"), "action_labels", "expected a list"),
    "unknown action": (_bad(action_labels=["a", "jump"]), "action_labels[1]", "'jump'"),
    "unknown observation": (
        _bad(observation_labels=["o0", "o9", "g"]),
        "observation_labels[1]",
        "'o9'",
    ),
    "observation twice": (
        _bad(observation_labels=["o0", "[o0]", "g"]),
        "observation_labels[1]",
        "same observation as observation_labels[0]",
    ),
    "observation missing": (
        _bad(
            observation_labels=["o0", "g"],
            num_observations=2,
            action_function=[[0, 1], [1, 1]],
            update_function=[[0, 1], [1, 1]],
        ),
        "observation_labels",
        "'o1' is not covered",
    ),
    "not an object": ([1, 2], "(top level)", "JSON object"),
    "not JSON": ("{nope", "line 1, column 2", "invalid JSON"),
}


@pytest.mark.parametrize("case", MALFORMED, ids=list(MALFORMED))
def test_malformed_paynt_file(tmp_path, case):
    fsc, field, words = MALFORMED[case]
    path = _write(tmp_path, fsc)
    result = runner.invoke(app, ["evaluate", str(path), "--json"])
    assert result.exit_code == 2, result.output
    error = json.loads(result.stdout)["error"]
    assert error["source"] == str(tmp_path / "robot.fsc.json")
    assert error["field"] == field
    assert words in error["message"], error["message"]
    assert "internal error" not in result.output and "Traceback" not in result.output
    result = runner.invoke(app, ["evaluate", str(path)])  # and the plain one-line form
    assert result.exit_code == 2
    assert result.stderr.count("\n") == 1
    assert result.stderr.startswith(f"error: {tmp_path / 'robot.fsc.json'}: {field}: ")


def test_missing_paynt_file(tmp_path):
    path = tmp_path / "p.yaml"
    path.write_text(yaml.safe_dump(PROBLEM))
    result = runner.invoke(app, ["evaluate", str(path), "--json"])
    assert result.exit_code == 2
    error = json.loads(result.stdout)["error"]
    assert error["source"] == str(path) and error["field"] == "controller.paynt"
    assert "file not found" in error["message"]


def test_export_fsc_round_trip_and_stdout(tmp_path):
    path = _write(tmp_path, GOOD)
    result = runner.invoke(app, ["export-fsc", str(path)])
    assert result.exit_code == 0, result.output
    exported = json.loads(result.stdout)
    assert exported["action_function"] == GOOD["action_function"]
    assert exported["update_function"] == GOOD["update_function"]
    (tmp_path / "robot.fsc.json").write_text(result.stdout)
    again = load_problem(path)
    assert np.array_equal(again.controller.action, np.array(GOOD["action_function"]))
