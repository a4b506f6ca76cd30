"""Grid maps: the paper's grid drawn as a map is the paper-grid scenario exactly; walls follow
hand-worked transitions; every mistake in a map is a one-line error with its location."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from misdirect import load_problem, solve
from misdirect.cli import app
from misdirect.scenarios import paper_grid

EXAMPLES = Path(__file__).parent.parent / "examples"
SPEC_GRID = [0.084957, 0.719924, 0.860130, 0.862442, 0.863622, 0.863622, 0.863622, 0.863622]
runner = CliRunner()


def test_paper_map_is_the_paper_grid():
    drawn, built = load_problem(EXAMPLES / "paper-grid-map.yaml"), paper_grid(5)
    assert drawn.pomdp.states == built.pomdp.states
    assert abs(drawn.pomdp.transitions - built.pomdp.transitions).max() == 0
    assert np.array_equal(drawn.pomdp.observation_of, built.pomdp.observation_of)
    assert np.array_equal(drawn.pomdp.absorbing, built.pomdp.absorbing)
    assert np.array_equal(drawn.decoy, built.decoy)
    assert np.array_equal(drawn.controller.action, built.controller.action)
    assert np.array_equal(drawn.controller.update, built.controller.update)


def test_paper_map_reproduces_spec_curve():
    result = solve(load_problem(EXAMPLES / "paper-grid-map.yaml"), budgets=range(8))
    assert [p.probability for p in result.curve] == pytest.approx(SPEC_GRID, abs=5e-7)
    assert result.curve[1].alteration in ({"1": "2"}, {"1": "3"}, {"1": "5"})


def _write(tmp_path, grid, *, controller=None, deception=None, **extra):
    document = {
        "format": "misdirect/v1",
        "grid": grid,
        "controller": controller
        or {
            "nodes": ["m"],
            "initial": "m",
            "rules": [{"node": "*", "obs": "*", "action": "E", "next": "m"}],
        },
        "deception": deception or {"budget": 1},
        **extra,
    }
    path = tmp_path / "map.yaml"
    path.write_text(yaml.safe_dump(document, sort_keys=False))
    return path


WALL_MAP = {
    "map": ". # G\nS . X\n",
    "legend": {"S": {"start": True}, "G": "goal", "X": "decoy", ".": "blank", "#": "wall"},
}


def test_walls_by_hand(tmp_path):
    problem = load_problem(_write(tmp_path, WALL_MAP))
    pomdp = problem.pomdp
    assert "(1,1)" not in pomdp.states  # a wall is not a state
    state = {name: i for i, name in enumerate(pomdp.states)}
    P = {a: pomdp.transition_matrix(i).toarray() for i, a in enumerate(pomdp.actions)}

    def row(action, cell):
        dist = P[action][state[cell]]
        return {pomdp.states[j]: round(dist[j], 12) for j in np.flatnonzero(dist)}

    # E from the start: ahead 0.8; north 0.1, plus the south slip (off the grid) handed to north
    assert row("E", "(0,0)") == {"(1,0)": 0.8, "(0,1)": 0.2}
    # N into the wall: stay 0.8; east and west slips 0.1 each
    assert row("N", "(1,0)") == {"(1,0)": 0.8, "(2,0)": 0.1, "(0,0)": 0.1}
    # E into the wall from (0,1): stay 0.8; the north slip leaves the grid and goes south
    assert row("E", "(0,1)") == {"(0,1)": 0.8, "(0,0)": 0.2}
    # E from (1,0): ahead 0.8; the north slip hits the wall (stay), the south slip leaves the
    # grid and is handed north, into the wall again (stay)
    assert row("E", "(1,0)") == {"(2,0)": 0.8, "(1,0)": 0.2}
    assert problem.decoy[state["(2,0)"]] and pomdp.absorbing[state["(2,1)"]]


@pytest.mark.parametrize(
    ("grid", "extra", "field", "words"),
    [
        (
            {
                "map": "S . X\nS . G",
                "legend": {"S": {"start": True}, "X": "decoy", "G": "goal", ".": "blank"},
            },
            {},
            "grid.map",
            "2 start cells",
        ),
        ({"map": ". . X", "legend": {"X": "decoy", ".": "blank"}}, {}, "grid.map", "no start"),
        (
            {"map": "S . X\n. ? .", "legend": {"S": {"start": True}, "X": "decoy", ".": "blank"}},
            {},
            "grid.map, line 2, column 3",
            "'?'",
        ),
        (
            {"map": "S . X\n. .", "legend": {"S": {"start": True}, "X": "decoy", ".": "blank"}},
            {},
            "grid.map, line 2",
            "ragged",
        ),
        (
            {"map": "S . .", "legend": {"S": {"start": True}, ".": "blank"}},
            {},
            "grid.map",
            "no decoy",
        ),
        ({**WALL_MAP, "actions": ["N", "up"]}, {}, "grid.actions", "'up'"),
        (
            {**WALL_MAP, "legend": {**WALL_MAP["legend"], "G": "lava"}},
            {},
            "grid.legend.G.kind",
            "'wall'",
        ),
        (
            {
                "map": ". # X",
                "legend": {"#": {"kind": "wall", "start": True}, "X": "decoy", ".": "blank"},
            },
            {},
            "grid.legend.#",
            "a wall is not a state",
        ),
        (
            WALL_MAP,
            {"deception": {"budget": 1, "decoy": ["(2,0)"]}},
            "deception.decoy",
            "marked in the map",
        ),
        (
            WALL_MAP,
            {"pomdp": {"states": ["a"], "actions": ["x"], "initial": "a", "observe": {"a": "o"}}},
            None,
            "exactly one of pomdp",
        ),
    ],
)
def test_map_errors(tmp_path, grid, extra, field, words):
    deception = extra.pop("deception", None)
    path = _write(tmp_path, grid, deception=deception, **extra)
    result = runner.invoke(app, ["evaluate", str(path), "--json"])
    assert result.exit_code == 2, result.output
    error = json.loads(result.stdout)["error"]
    assert error.get("field") == field
    assert words in error["message"] or words in json.dumps(error)
    assert "Traceback" not in result.output
