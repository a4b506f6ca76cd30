"""Models from Storm (PRISM, DRN), PAYNT controllers, and writing models back out for Storm.

The maze and the 3x3 grid are the POMDPs stormpy ships as examples; the probabilities below
are worked out by hand from the PRISM source (comments), and DRN and PRISM are read through two
different Storm paths that must agree.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from misdirect import decoy_probability, load_problem
from misdirect.cli import app

stormpy = pytest.importorskip("stormpy")
SHIPPED = Path(stormpy.__file__).parent / "examples" / "files" / "pomdp"
EXAMPLES = Path(__file__).parent.parent / "examples"
runner = CliRunner()

SOUTH_CONTROLLER = {
    "nodes": ["m"],
    "initial": "m",
    "rules": [
        {"node": "*", "obs": "o=0", "action": "__NOLABEL__", "next": "m"},
        {"node": "*", "obs": "o=7", "action": "done", "next": "m"},
        {"node": "*", "obs": "*", "action": "south", "next": "m"},
    ],
}


def _problem_file(tmp_path, pomdp, controller, decoy, budget=1, name="p.yaml"):
    document = {
        "format": "misdirect/v1",
        "pomdp": pomdp,
        "controller": controller,
        "deception": {"decoy": decoy, "budget": budget},
    }
    path = tmp_path / name
    path.write_text(yaml.safe_dump(document, sort_keys=False))
    return path


def test_maze_by_hand(tmp_path):
    """Always south: from the 13 equally likely starts, only s=2, 6, 9 run down into the
    target s=13 (2->6->9->13); every other column ends against a wall. So 3/13."""
    path = _problem_file(
        tmp_path, {"prism": str(SHIPPED / "maze_2.prism")}, SOUTH_CONTROLLER, {"label": "goal"}
    )
    problem = load_problem(path)
    assert problem.pomdp.n_states == 15
    assert decoy_probability(problem, problem.identity()) == pytest.approx(3 / 13, abs=1e-12)
    # reading the target's o=7 everywhere makes the robot play `done`, which Storm enables
    # only at the target: by default (`stay`) it then never moves, so 0
    alpha = problem.alteration(
        {"o=5": "o=7", "o=1": "o=7", "o=2": "o=7", "o=3": "o=7", "o=4": "o=7", "o=6": "o=7"}
    )
    assert decoy_probability(problem, alpha) == pytest.approx(0.0, abs=1e-12)


def test_prism_and_drn_of_the_maze_agree():
    from misdirect.storm_models import load_storm_pomdp

    prism = load_storm_pomdp(SHIPPED / "maze_2.prism", kind="prism").pomdp
    drn = load_storm_pomdp(SHIPPED / "maze.drn", kind="drn").pomdp
    assert prism.actions == drn.actions
    assert np.array_equal(prism.observation_of, drn.observation_of)
    assert abs(prism.transitions - drn.transitions).max() < 1e-9


def test_disabled_actions_stay_or_forbid(tmp_path):
    """3x3 grid: 'done' is enabled only at the target (o=2). Reading o=1 as o=2 makes the
    robot play 'done' in the grid: with `stay` it stays put, with `forbid` that alteration is
    not allowed."""
    controller = {
        "nodes": ["m"],
        "initial": "m",
        "rules": [
            {"node": "*", "obs": "o=0", "action": "__NOLABEL__", "next": "m"},
            {"node": "*", "obs": "o=2", "action": "done", "next": "m"},
            {"node": "*", "obs": "*", "action": "east", "next": "m"},
        ],
    }
    grid = str(SHIPPED / "3x3grid.prism")
    stay = load_problem(_problem_file(tmp_path, {"prism": grid}, controller, {"label": "goal"}))
    o1, o2 = stay.pomdp.observations.index("o=1"), stay.pomdp.observations.index("o=2")
    assert np.isfinite(stay.cost.row(o1)[o2])
    # east forever: the target (2,0) is reached only from the bottom row starts (0,0), (1,0):
    # 2 of the 8 equally likely starts
    assert decoy_probability(stay, stay.identity()) == pytest.approx(2 / 8, abs=1e-12)
    altered = stay.identity()
    altered[o1] = o2  # the robot now "finishes" everywhere and never moves
    assert decoy_probability(stay, altered) == pytest.approx(0.0, abs=1e-12)

    forbid = load_problem(
        _problem_file(
            tmp_path,
            {"prism": grid, "disabled_action": "forbid"},
            controller,
            {"label": "goal"},
            name="f.yaml",
        )
    )
    assert not np.isfinite(forbid.cost.row(o1)[o2])


def test_paynt_controller_round_trip(tmp_path):
    source = _problem_file(
        tmp_path, {"prism": str(SHIPPED / "maze_2.prism")}, SOUTH_CONTROLLER, {"label": "goal"}
    )
    fsc = tmp_path / "robot.fsc.json"
    result = runner.invoke(app, ["export-fsc", str(source), "-o", str(fsc)])
    assert result.exit_code == 0, result.output
    exported = json.loads(fsc.read_text())
    assert exported["action_labels"][exported["action_function"][0][0]] in (
        "south",
        "done",
        "__NOLABEL__",
    )
    # PAYNT writes observation labels as Storm valuations: "[o=3]"
    exported["observation_labels"] = [f"[{name}]" for name in exported["observation_labels"]]
    fsc.write_text(json.dumps(exported))
    again = load_problem(
        _problem_file(
            tmp_path,
            {"prism": str(SHIPPED / "maze_2.prism")},
            {"paynt": "robot.fsc.json"},
            {"label": "goal"},
            name="q.yaml",
        )
    )
    original = load_problem(source)
    assert np.array_equal(again.controller.action, original.controller.action)
    assert np.array_equal(again.controller.update, original.controller.update)


@pytest.mark.parametrize("target", ["prism", "drn"])
def test_convert_round_trip_through_storm(tmp_path, target):
    """Our model written out, read back by Storm, evaluates to the same probabilities."""
    out = tmp_path / f"trap.{target}"
    result = runner.invoke(
        app, ["convert", str(EXAMPLES / "trap.yaml"), "--to", target, "-o", str(out)]
    )
    assert result.exit_code == 0, result.output
    original = load_problem(EXAMPLES / "trap.yaml")
    names = dict(enumerate(original.pomdp.observations))
    # rules in terms of the observation names Storm will give back
    obs_name = (lambda k: f"o={k}") if target == "prism" else (lambda k: f"obs{k}")
    rules = []
    for k, name in names.items():
        o = original.pomdp.observations.index(name)
        rules.append(
            {
                "node": "*",
                "obs": obs_name(k),
                "action": original.pomdp.actions[original.controller.action[0, o]],
                "next": "m",
            }
        )
    path = _problem_file(
        tmp_path,
        {target: out.name},
        {"nodes": ["m"], "initial": "m", "rules": rules},
        {"label": "decoy"},
    )
    back = load_problem(path)
    for change in ({}, {"o1": "o0"}):
        alpha = original.alteration(change)
        mapped = back.identity()
        for o, t in enumerate(alpha):
            mapped[back.pomdp.observations.index(obs_name(o))] = back.pomdp.observations.index(
                obs_name(int(t))
            )
        assert decoy_probability(back, mapped) == pytest.approx(
            decoy_probability(original, alpha), abs=1e-12
        )


@pytest.mark.parametrize(
    ("pomdp", "decoy", "field", "words"),
    [
        (
            {"prism": "broken.prism"},
            {"label": "goal"},
            "pomdp.prism, line 4, column 13",
            "expecting <update list>",
        ),
        ({"prism": "missing.prism"}, {"label": "goal"}, "pomdp.prism", "not found"),
        (
            {"prism": str(SHIPPED / "maze_2.prism")},
            {"label": "lava"},
            "deception.decoy.label",
            "no state label 'lava'",
        ),
        (
            {"prism": str(SHIPPED / "maze_2.prism"), "constnats": "N=1"},
            {"label": "goal"},
            "pomdp.constnats",
            "unknown field",
        ),
        (
            {"prism": str(SHIPPED / "maze_2.prism")},
            {"lable": "goal"},
            "deception.decoy.label",
            "Field required",
        ),
        (
            {"prism": str(SHIPPED / "maze_2_par.prism")},
            {"label": "goal"},
            "pomdp.constants",
            "constants without a value",
        ),
    ],
)
def test_storm_errors(tmp_path, pomdp, decoy, field, words):
    (tmp_path / "broken.prism").write_text(
        "pomdp\nmodule m\n  x : [0..1] init 0;\n  [a] x=0 -> ;\nendmodule\n"
    )
    path = _problem_file(tmp_path, pomdp, SOUTH_CONTROLLER, decoy)
    result = runner.invoke(app, ["evaluate", str(path), "--json"])
    assert result.exit_code == 2, result.output
    error = json.loads(result.stdout)["error"]
    assert error["field"] == field
    assert words in error["message"]
