"""Issue 53, item 7: pictures of any model with coordinates (``--coordinates x,y``, a regex on
state names, or a PRISM model's x and y found without the flag) for ``show``, ``audit -o``'s
map and ``simulate --picture``; states without coordinates are left out and counted; legends
that say what the colours mean."""

from __future__ import annotations

import json
import re
from pathlib import Path
from types import SimpleNamespace

import matplotlib.pyplot as plt
import numpy as np
import pytest
import yaml
from matplotlib.colors import to_rgba
from typer.testing import CliRunner

from misdirect import load_problem
from misdirect.cli import app
from misdirect.core.grid import state_cells
from misdirect.errors import ProblemError
from misdirect.report.figures import WALL_FILL, grid_arrays, grid_figure
from misdirect.scenarios import paper_grid

runner = CliRunner()
ROOT = Path(__file__).resolve().parents[1]
GRID = ROOT / "tests" / "data" / "grid_avoid.prism"
# grid_avoid at N=3 (tests/test_prism_route.py): start, north to the top row, then east
GRID_RULES = {
    "nodes": ["m"],
    "initial": "m",
    "rules": [
        {"node": "*", "obs": "!started,y=0,!wall,!crashed", "action": "__NOLABEL__", "next": "m"},
        {"node": "*", "obs": "started,y=2,!wall,!crashed", "action": "east", "next": "m"},
        {"node": "*", "obs": "*", "action": "north", "next": "m"},
    ],
}
# tiny's states renamed to cells: s0 (0,0), s1 (1,0), s2 (0,1), goal (1,1); the trap keeps
# its name, so it has no coordinates
CELLS = {"s0": "cell0_0", "s1": "cell1_0", "s2": "cell0_1", "goal": "cell1_1"}
REGEX = r"cell(\d+)_(\d+)"


def _tiny_cells(tmp_path: Path) -> Path:
    document = yaml.safe_load((ROOT / "examples" / "tiny.yaml").read_text())
    text = yaml.safe_dump(document["pomdp"])
    for old, new in CELLS.items():
        text = re.sub(rf"\b{old}\b", new, text)
    document["pomdp"] = yaml.safe_load(text)
    path = tmp_path / "cells.yaml"
    path.write_text(yaml.safe_dump(document, sort_keys=False))
    return path


def _grid_flags(tmp_path: Path) -> list[str]:
    controller = tmp_path / "grid-controller.yaml"
    controller.write_text(yaml.safe_dump(GRID_RULES))
    return [
        str(GRID),
        *("--controller", str(controller), "--decoy", "bad"),
        *("--constants", "N=3", "--goal", "goal"),
    ]


def _grid_problem(tmp_path: Path):
    pytest.importorskip("stormpy")
    from misdirect.io.model_problem import problem_from_model

    controller = tmp_path / "grid-controller.yaml"
    controller.write_text(yaml.safe_dump(GRID_RULES))
    return problem_from_model(
        GRID, controller=controller, decoy="bad", constants="N=3", goal="goal"
    )


def _error(result) -> dict:
    assert result.exit_code == 2, result.output
    return json.loads(result.stdout)["error"]


# -- the one function ---------------------------------------------------------------------------


def test_grid_worlds_keep_their_cells():
    problem = paper_grid(5)
    cells = state_cells(problem)
    assert cells is not None and cells.placed.all() and cells.origin == (0, 0)
    assert (cells.width, cells.height) == (5, 5) and cells.caption() == ""
    for s, name in enumerate(problem.pomdp.states):
        assert f"({cells.xy[s, 0]},{cells.xy[s, 1]})" == name


def test_prism_x_and_y_are_found_without_the_flag(tmp_path):
    problem = _grid_problem(tmp_path)
    cells = state_cells(problem)
    assert cells is not None and cells.how == "PRISM variables x,y"
    expected = set()
    for name in problem.pomdp.states:
        items = dict(item.split("=") for item in name.split(",") if "=" in item)
        expected.add((int(items["x"]), int(items["y"])))
    assert {tuple(c) for c in cells.xy[cells.placed].tolist()} == expected
    # the picture's cells are the distinct (x, y): every other cell is a wall
    _, walls = grid_arrays(problem, cells, np.ones(problem.pomdp.n_states))
    assert int((~walls).sum()) == len(expected) == 9
    # and the flag names the same variables
    by_flag = state_cells(problem, "x,y")
    assert by_flag is not None and np.array_equal(by_flag.xy, cells.xy)


def test_states_sharing_a_cell_are_added_up(tmp_path):
    """!started,x=0,y=0 and started,x=0,y=0 share the cell (0,0): its visits are theirs."""
    from misdirect.core.evaluate import evaluate

    problem = _grid_problem(tmp_path)
    cells = state_cells(problem)
    assert cells is not None
    visits = evaluate(problem, problem.identity()).expected_visits
    values, _ = grid_arrays(problem, cells, visits)
    names = problem.pomdp.states
    at_origin = [s for s, n in enumerate(names) if "x=0" in n.split(",") and "y=0" in n.split(",")]
    assert len(at_origin) == 2
    assert values[0, 0] == pytest.approx(visits[at_origin].sum())
    fig = grid_figure(problem, problem.identity(), cells)
    try:
        drawn = np.ma.filled(fig.axes[0].images[0].get_array().astype(float), np.nan)
        assert drawn[0, 0] == pytest.approx(visits[at_origin].sum())
    finally:
        plt.close(fig)


def test_a_regex_places_states_and_leaves_the_others_out(tmp_path):
    problem = load_problem(_tiny_cells(tmp_path))
    cells = state_cells(problem, REGEX)
    assert cells is not None and cells.left_out == 1  # the trap
    trap = problem.pomdp.states.index("trap")
    assert not cells.placed[trap]
    for s, name in enumerate(problem.pomdp.states):
        if name in CELLS.values():
            x, y = (int(v) for v in re.fullmatch(REGEX, name).groups())
            assert tuple(cells.xy[s]) == (x, y)
    assert "1 state without coordinates" in cells.caption()
    # named groups say which is which
    swapped = state_cells(problem, r"cell(?P<y>\d+)_(?P<x>\d+)")
    assert swapped is not None and np.array_equal(swapped.xy, cells.xy[:, ::-1])
    fig = grid_figure(problem, problem.identity(), cells)
    try:
        assert "1 state without coordinates" in fig.axes[0].get_title()
    finally:
        plt.close(fig)


def test_origin_moves_to_the_smallest_coordinates():
    named = SimpleNamespace(pomdp=SimpleNamespace(states=("p=3,q=-2", "p=5,q=-1", "sink")))
    cells = state_cells(named, "p,q")
    assert cells is not None and cells.origin == (3, -2)
    assert cells.xy[:2].tolist() == [[0, 0], [2, 1]] and cells.left_out == 1


@pytest.mark.parametrize(
    ("states", "coordinates", "words"),
    [
        (("a", "b"), r"cell(\d+)_(\d+)", "matches no state name"),
        (("a", "b"), "col,row", "no state has 'col' or 'row'"),
        (("a11", "b11"), r"(\d)(\d)", "falls in one cell"),
        (("cellA_1",), r"cell(\w)_(\d)", "not a whole number"),
        (("x=1,y=2",), r"x=(\d+)", "has 1 group(s)"),
        (("x=1,y=2",), r"x=(\d+", "not a regular expression"),
        (("flag,x=1",), "flag,x", "'true', not a whole number"),
        (("x=0,y=0", "x=4000,y=4000"), None, "a picture stops at"),
    ],
)
def test_coordinates_that_cannot_be_drawn_are_named(states, coordinates, words):
    problem = SimpleNamespace(pomdp=SimpleNamespace(states=states))
    with pytest.raises(ProblemError) as caught:
        state_cells(problem, coordinates)
    assert caught.value.field == "coordinates" and words in str(caught.value)


def test_no_coordinates_without_the_flag_is_none():
    problem = SimpleNamespace(pomdp=SimpleNamespace(states=("s0", "s1")))
    assert state_cells(problem) is None
    # three integer variables: not a picture without the flag
    three = SimpleNamespace(pomdp=SimpleNamespace(states=("x=0,y=0,z=1", "x=1,y=0,z=0")))
    assert state_cells(three) is None


# -- the three commands -------------------------------------------------------------------------


def test_show_draws_a_prism_model_by_its_x_and_y(tmp_path):
    pytest.importorskip("stormpy")
    picture = tmp_path / "grid.png"
    result = runner.invoke(app, ["show", *_grid_flags(tmp_path), "-o", str(picture)])
    assert result.exit_code == 0, result.output
    assert picture.read_bytes()[:4] == b"\x89PNG"


def test_show_takes_a_regex_and_names_the_flag_when_nothing_matches(tmp_path):
    path = _tiny_cells(tmp_path)
    picture = tmp_path / "cells.svg"
    result = runner.invoke(app, ["show", str(path), "-o", str(picture), "--coordinates", REGEX])
    assert result.exit_code == 0, result.output
    assert picture.exists()
    no_match = runner.invoke(
        app, ["show", str(path), "-o", str(picture), "--coordinates", r"room(\d)_(\d)", "--json"]
    )
    error = _error(no_match)
    assert error["field"] == "--coordinates" and "matches no state name" in error["message"]
    without = _error(runner.invoke(app, ["show", str(path), "-o", str(picture), "--json"]))
    assert without["field"] == "-o" and "--coordinates col,row" in without["message"]


def test_audit_draws_the_map_with_coordinates(tmp_path):
    path = _tiny_cells(tmp_path)
    plain = tmp_path / "plain"
    result = runner.invoke(app, ["audit", str(path), "-o", str(plain), "--json"])
    assert result.exit_code == 0, result.output
    assert not (plain / "map.png").exists()  # no coordinates, no map
    out = tmp_path / "audit"
    result = runner.invoke(
        app, ["audit", str(path), "-o", str(out), "--coordinates", REGEX, "--json"]
    )
    assert result.exit_code == 0, result.output
    assert "map.png" in {Path(p).name for p in json.loads(result.stdout)["written"]}
    assert "map.png" in (out / "report.md").read_text()
    error = _error(runner.invoke(app, ["audit", str(path), "--coordinates", REGEX, "--json"]))
    assert error["field"] == "--coordinates" and "-o DIR" in error["message"]


def test_audit_map_of_a_prism_model(tmp_path):
    pytest.importorskip("stormpy")
    out = tmp_path / "audit"
    result = runner.invoke(app, ["audit", *_grid_flags(tmp_path), "--budget", "1", "-o", str(out)])
    assert result.exit_code == 0, result.output
    assert (out / "map.png").read_bytes()[:4] == b"\x89PNG"


def test_simulate_draws_the_simulated_visits(tmp_path):
    from misdirect.core.evaluate import evaluate
    from misdirect.core.simulate import simulate

    path = _tiny_cells(tmp_path)
    picture = tmp_path / "runs.png"
    args = ["simulate", str(path), "--runs", "2000", "--picture", str(picture)]
    result = runner.invoke(app, [*args, "--coordinates", REGEX, "--json"])
    assert result.exit_code == 0, result.output
    assert str(picture) in json.loads(result.stdout)["written"]
    assert picture.read_bytes()[:4] == b"\x89PNG"
    # the visits counted are the simulated counterpart of the expected ones
    problem = load_problem(path)
    counted = simulate(problem, runs=20_000, count_visits=True)
    expected = evaluate(problem, problem.identity()).expected_visits
    assert counted.visits is not None
    np.testing.assert_allclose(counted.visits / 20_000, expected, atol=0.03)
    # errors name the flag before any run
    error = _error(runner.invoke(app, [*args, "--json"]))
    assert error["field"] == "--picture" and "--coordinates col,row" in error["message"]
    alone = _error(runner.invoke(app, ["simulate", str(path), "--coordinates", REGEX, "--json"]))
    assert alone["field"] == "--coordinates" and "--picture" in alone["message"]


# -- item 7: the legend says what the colours mean -------------------------------------------


def _luminance(rgba) -> float:
    r, g, b, _ = rgba
    return 0.2126 * r + 0.7152 * g + 0.0722 * b


def test_the_legend_says_what_the_colours_mean():
    problem = load_problem(ROOT / "examples" / "paper-grid-map.yaml")
    cells = state_cells(problem)
    assert cells is not None
    fig = grid_figure(problem, problem.identity(), cells)
    try:
        ax = fig.axes[0]
        heat, wall_layer = ax.images
        (legend,) = fig.legends
        entries = dict(
            zip((t.get_text() for t in legend.get_texts()), legend.legend_handles, strict=True)
        )
        text = " ".join(entries) + ax.get_title()
        assert "dark grey" not in text
        # the wall entry has the colour the walls are drawn in
        (wall_label,) = [label for label in entries if label.startswith("wall")]
        wall_colour = wall_layer.get_cmap()(0)
        assert to_rgba(entries[wall_label].get_facecolor()) == pytest.approx(wall_colour)
        assert to_rgba(WALL_FILL) == pytest.approx(wall_colour)
        # "darker: more visits" is what the heat map does
        (darker,) = [label for label in entries if label.startswith("darker")]
        assert "more visits" in darker
        visits = np.ma.filled(heat.get_array().astype(float), np.nan)
        most, least = np.nanmax(visits), np.nanmin(visits[visits > 0])
        assert most > least
        cmap, norm = heat.get_cmap(), heat.norm
        assert _luminance(cmap(norm(most))) < _luminance(cmap(norm(least)))
        # and the walls look like no amount of visits: far from every colour of the map
        shades = cmap(np.linspace(0, 1, 256))[:, :3]
        assert np.min(np.linalg.norm(shades - np.array(wall_colour[:3]), axis=1)) > 0.15
    finally:
        plt.close(fig)


def test_the_audit_map_legend_names_walls(tmp_path):
    from misdirect.defence import audit
    from misdirect.report.defence import map_figure

    problem = load_problem(ROOT / "examples" / "paper-grid-map.yaml")
    fig = map_figure(problem, audit(problem, budget=1))
    try:
        (legend,) = fig.legends
        labels = [t.get_text() for t in legend.get_texts()]
        (wall,) = [i for i, label in enumerate(labels) if label.startswith("wall")]
        assert to_rgba(legend.legend_handles[wall].get_facecolor()) == pytest.approx(
            to_rgba(WALL_FILL)
        )
    finally:
        plt.close(fig)
