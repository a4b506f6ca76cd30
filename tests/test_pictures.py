"""`misdirect show` on a grid that is not square and has a wall: the heat map and the wall layer
have the map's shape, every cell sits where the map puts it, and every goal and decoy is
marked."""

from __future__ import annotations

import math

import matplotlib.pyplot as plt
import numpy as np
import yaml
from matplotlib import patheffects
from typer.testing import CliRunner

from misdirect import load_problem
from misdirect.cli import app
from misdirect.report.figures import grid_arrays, grid_cells, grid_figure

runner = CliRunner()
# 4 wide, 2 high; the wall at (1,0). Without slip the robot goes N from S (sensor 0) to (0,1),
# then E over (1,1) into the decoy X at (2,1): each of S, (0,1), (1,1) is visited exactly once.
MAP = {
    "format": "misdirect/v1",
    "name": "wide",
    "grid": {
        "map": "1 2 X G\nS # G X\n",
        "legend": {"S": {"start": True, "sensor": "0"}, "G": "goal", "X": "decoy", "#": "wall"},
        "slip": 0,
    },
    "controller": {
        "nodes": ["m"],
        "initial": "m",
        "rules": [
            {"node": "*", "obs": "0", "action": "N", "next": "m"},
            {"node": "*", "obs": "*", "action": "E", "next": "m"},
        ],
    },
    "deception": {"budget": 1},
}


def _problem(tmp_path):
    path = tmp_path / "wide.yaml"
    path.write_text(yaml.safe_dump(MAP))
    return path, load_problem(path)


def test_grid_arrays_follow_the_map(tmp_path):
    _, problem = _problem(tmp_path)
    cells = grid_cells(problem)
    marker = np.arange(problem.pomdp.n_states, dtype=float)
    values, walls = grid_arrays(problem, cells, marker)
    assert values.shape == walls.shape == (2, 4)  # [y, x]: 2 rows, 4 columns
    assert walls.tolist() == [[False, True, False, False], [False, False, False, False]]
    for s, name in enumerate(problem.pomdp.states):
        x, y = (int(v) for v in name.strip("()").split(","))
        assert values[y, x] == s
    assert math.isnan(values[0, 1])


def test_drawn_heat_map_walls_and_marks(tmp_path):
    _, problem = _problem(tmp_path)
    fig = grid_figure(problem, problem.identity(), grid_cells(problem))
    try:
        ax = fig.axes[0]
        heat, wall_layer = ax.images
        drawn = np.ma.filled(heat.get_array().astype(float), np.nan)
        assert drawn.shape == (2, 4)
        assert heat.get_extent() == [-0.5, 3.5, -0.5, 1.5]
        # by hand: visited once each, [y, x]
        for x, y in [(0, 0), (0, 1), (1, 1)]:
            assert drawn[y, x] == 1.0
        for x, y in [(1, 0), (2, 0), (3, 0), (3, 1)]:  # the wall and never-visited cells
            assert math.isnan(drawn[y, x])
        assert np.ma.getmaskarray(wall_layer.get_array()).tolist() == [
            [True, False, True, True],
            [True, True, True, True],
        ]
        assert ax.get_xlim() == (-0.5, 3.5) and ax.get_ylim() == (-0.5, 1.5)
        marks = {}
        for text in ax.texts:
            if text.get_text() in ("S", "G", "X"):
                x, y = text.get_position()
                marks.setdefault(text.get_text(), set()).add((round(x), round(y + 0.12)))
                if text.get_text() == "S":
                    (halo,) = text.get_path_effects()
                    assert isinstance(halo, patheffects.withStroke)
        assert marks == {"S": {(0, 0)}, "G": {(3, 1), (2, 0)}, "X": {(2, 1), (3, 0)}}
    finally:
        plt.close(fig)


def test_show_writes_the_non_square_picture(tmp_path):
    path, _ = _problem(tmp_path)
    picture = tmp_path / "wide.png"
    result = runner.invoke(app, ["show", str(path), "-a", "2=1", "-o", str(picture)])
    assert result.exit_code == 0, result.output
    image = plt.imread(picture)
    height, width = image.shape[:2]
    assert width > 1.3 * height  # a 4x2 map is drawn wide, not stretched into a square
