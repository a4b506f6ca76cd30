"""Every class of bad input, through the CLI: exit code 2, one message naming the file, the
field and the reason, and no traceback."""

import json
import textwrap

import pytest
import yaml
from typer.testing import CliRunner

from misdirect.cli import app

runner = CliRunner()
GOOD = yaml.safe_load(
    textwrap.dedent(
        """
        format: misdirect/v1
        pomdp:
          states: [s0, s1, goal, trap]
          actions: [a, b]
          initial: s0
          observe: {s0: o0, s1: o1, goal: g, trap: g}
          transitions:
            - [s0, a, s1, 0.5]
            - [s0, a, goal, 0.5]
            - [s0, b, s0, 1.0]
            - [s1, a, goal, 1.0]
            - [s1, b, trap, 1.0]
          absorbing: [goal, trap]
        controller:
          nodes: [n0]
          initial: n0
          rules:
            - {node: "*", obs: o1, action: a, next: n0}
            - {node: "*", obs: "*", action: a, next: n0}
        deception:
          decoy: [trap]
          budget: 1
        """
    )
)


def run(tmp_path, document=None, *, text=None, args=(), suffix=".yaml"):
    path = tmp_path / f"problem{suffix}"
    path.write_text(text if text is not None else yaml.safe_dump(document))
    return runner.invoke(app, ["evaluate", str(path), *args]), path


def mutate(change):
    document = json.loads(json.dumps(GOOD))
    change(document)
    return document


def assert_input_error(result, path, *fragments):
    assert result.exit_code == 2, result.output
    assert "Traceback" not in result.output
    assert result.exception is None or isinstance(result.exception, SystemExit)
    message = result.stderr
    assert message.count("\n") == 1, message  # one line
    if path is not None:
        assert str(path) in message
    for fragment in fragments:
        assert fragment in message, message


CASES = {
    "yaml syntax": (
        dict(text="format: misdirect/v1\npomdp: [unclosed\n"),
        ["invalid YAML", "line"],
    ),
    "json syntax": (
        dict(text='{"format": "misdirect/v1",', suffix=".json"),
        ["invalid JSON", "line 1"],
    ),
    "wrong format tag": (dict(document=mutate(lambda d: d.update(format="v2"))), ["format"]),
    "unknown field": (
        dict(document=mutate(lambda d: d["pomdp"].update(transitoins=[]))),
        ["pomdp.transitoins", "unknown field"],
    ),
    "unknown state in transition": (
        dict(document=mutate(lambda d: d["pomdp"]["transitions"].append(["s9", "a", "s0", 1]))),
        ["pomdp.transitions[5]", "unknown state 's9'"],
    ),
    "unknown action": (
        dict(document=mutate(lambda d: d["controller"]["rules"][0].update(action="jump"))),
        ["controller.rules[0]", "unknown action 'jump'"],
    ),
    "probabilities not summing to 1": (
        dict(document=mutate(lambda d: d["pomdp"]["transitions"][0].__setitem__(3, 0.4))),
        ["pomdp.transitions", "sum to 0.9"],
    ),
    "missing transitions": (
        dict(document=mutate(lambda d: d["pomdp"]["transitions"].pop())),
        ["no transitions for ('s1', 'b')"],
    ),
    "negative probability": (
        dict(document=mutate(lambda d: d["pomdp"]["transitions"][0].__setitem__(3, -0.5))),
        ["pomdp.transitions[0][3]", "greater than or equal to 0"],
    ),
    "NaN probability": (
        dict(text=yaml.safe_dump(GOOD).replace("- 0.5\n", "- .nan\n", 1)),
        ["pomdp.transitions[0][3]", "NaN"],
    ),
    "negative budget": (
        dict(document=mutate(lambda d: d["deception"].update(budget=-1))),
        ["deception.budget", "greater than or equal to 0"],
    ),
    "NaN cost": (
        dict(document=mutate(lambda d: d["deception"].update(cost={"default": float("nan")}))),
        ["deception.cost.default", "NaN"],
    ),
    "uncovered controller entry": (
        dict(document=mutate(lambda d: d["controller"]["rules"].pop())),
        ["controller.rules", "no rule covers node 'n0' with observation 'o0'"],
    ),
    "unknown decoy": (
        dict(document=mutate(lambda d: d["deception"].update(decoy=["lava"]))),
        ["deception.decoy[0]", "unknown state 'lava'"],
    ),
    "duplicate state": (
        dict(document=mutate(lambda d: d["pomdp"]["states"].append("s1"))),
        ["pomdp.states[4]", "duplicate"],
    ),
    "state without observation": (
        dict(document=mutate(lambda d: d["pomdp"]["observe"].pop("s1"))),
        ["pomdp.observe", "'s1' has no observation"],
    ),
    "transition from absorbing state": (
        dict(document=mutate(lambda d: d["pomdp"]["transitions"].append(["goal", "a", "s0", 1]))),
        ["pomdp.transitions[5]", "absorbing"],
    ),
    "unknown observation in cost": (
        dict(document=mutate(lambda d: d["deception"].update(cost={"protected": ["o7"]}))),
        ["deception.cost.protected[0]", "unknown observation 'o7'"],
    ),
    "boolean used as a name": (
        dict(text=yaml.safe_dump(GOOD).replace("- s0\n", "- yes\n", 1)),
        ["pomdp.states[0]", "quote it"],
    ),
    "alteration of unknown observation": (
        dict(document=GOOD, args=["--alter", "o9=o1"]),
        ["--alter", "unknown observation 'o9'"],
    ),
    "malformed alteration": (dict(document=GOOD, args=["--alter", "o1"]), ["--alter", "OBS=OBS"]),
    "altering the initial observation": (
        dict(document=GOOD, args=["--alter", "o0=o1"]),
        ["--alter", "initial observation 'o0'"],
    ),
    "protected observation altered": (
        dict(
            document=mutate(lambda d: d["deception"].update(cost={"protected": ["o1"]})),
            args=["--alter", "o1=o0"],
        ),
        ["--alter", "protected"],
    ),
}


@pytest.mark.parametrize("case", CASES, ids=list(CASES))
def test_bad_input_exits_2_with_one_clear_line(tmp_path, case):
    kwargs, fragments = CASES[case]
    result, path = run(tmp_path, **kwargs)
    on_command_line = any(f.startswith("--") for f in fragments)
    assert_input_error(result, None if on_command_line else path, *fragments)


def test_missing_file(tmp_path):
    result = runner.invoke(app, ["solve", str(tmp_path / "nope.yaml")])
    assert_input_error(result, tmp_path / "nope.yaml", "file not found")


def test_bad_scenario_parameters():
    result = runner.invoke(
        app,
        [
            "solve",
            "--scenario",
            "knapsack",
            "--weights",
            "1,x",
            "--values",
            "1,2",
            "--capacity",
            "3",
        ],
    )
    assert_input_error(result, None, "--weights", "comma-separated numbers")
    result = runner.invoke(app, ["evaluate", "--scenario", "paper-grid", "--size", "3"])
    assert_input_error(result, None, "--size", "≥ 5")


def test_bad_budget_option(tmp_path):
    path = tmp_path / "p.yaml"
    path.write_text(yaml.safe_dump(GOOD))
    result = runner.invoke(app, ["solve", str(path), "--budget", "lots"])
    assert_input_error(result, None, "--budget")


def test_json_mode_reports_the_error_as_json(tmp_path):
    result, path = run(
        tmp_path, mutate(lambda d: d["deception"].update(decoy=["lava"])), args=["--json"]
    )
    assert result.exit_code == 2
    payload = json.loads(result.stdout)
    assert payload["error"]["field"] == "deception.decoy[0]"
    assert payload["error"]["source"] == str(path)
