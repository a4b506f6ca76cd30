"""`misdirect show` on a grid that is not square and has a wall: the heat map and the wall layer
have the map's shape, every cell sits where the map puts it, and every goal and decoy is
marked."""

from __future__ import annotations

import json
import math
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
import yaml
from matplotlib import patheffects
from typer.testing import CliRunner

from misdirect import load_problem
from misdirect.cli import app
from misdirect.report.figures import grid_arrays, grid_cells, grid_figure

runner = CliRunner()
ROOT = Path(__file__).parents[1]
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


# -- issue 28: the criticality map, harden's report, titles --------------------------------------


def _nameless_grid(tmp_path):
    """The paper's map without its name, the start cell without a sensor (it reads b)."""
    document = yaml.safe_load((ROOT / "examples" / "paper-grid-map.yaml").read_text())
    del document["name"]
    document["grid"]["legend"]["S"] = {"start": True}
    document["controller"]["rules"] = [
        rule for rule in document["controller"]["rules"] if str(rule["obs"]) != "0"
    ]
    path = tmp_path / "nameless-grid.yaml"
    path.write_text(yaml.safe_dump(document))
    return path


def test_criticality_map_is_log_scaled_readable_and_keeps_b_apart(tmp_path):
    from matplotlib.colors import LogNorm

    from misdirect.defence import audit
    from misdirect.report.defence import map_figure

    problem = load_problem(_nameless_grid(tmp_path))
    result = audit(problem, budget=2)
    fig = map_figure(problem, result)
    ax = fig.axes[0]
    assert isinstance(ax.images[0].norm, LogNorm)
    texts = [t for t in ax.texts if t.get_text()]
    assert texts and min(t.get_fontsize() for t in texts) >= 9
    assert "b" not in {t.get_text() for t in texts}  # the blank reading is not labelled a sensor
    legend = " ".join(t.get_text() for t in fig.legends[0].get_texts())
    assert "no sensor (reads b" in legend
    assert ax.get_title().startswith("nameless-grid.yaml:")  # the file name, no name given


def test_harden_writes_report_and_tradeoff(tmp_path):
    out = tmp_path / "hard"
    result = runner.invoke(
        app,
        [
            "harden",
            str(ROOT / "examples" / "tiny.yaml"),
            "--protect-budget",
            "1",
            "--budget",
            "1",
            "-o",
            str(out),
            "--json",
        ],
    )
    assert result.exit_code == 0, result.output
    payload = json.loads(result.stdout)
    assert sorted(Path(p).name for p in payload["written"]) == ["report.md", "tradeoff.png"]
    report = (out / "report.md").read_text()
    # tiny at B = 1: o2 -> o1 or o2 -> g gives 0.6 (by hand); protecting o2 leaves the
    # attacker nothing that helps (o1 -> o0 or g keeps a): 0.2
    assert "0.600000000" in report and "0.200000000" in report
    assert (out / "tradeoff.png").read_bytes()[:4] == b"\x89PNG"


def test_tables_never_cut_names(tmp_path):
    """Long observation names in a narrow terminal wrap; no name is cut to 'beac…'."""
    long1, long2 = "beacon_north_corridor_sensor_one", "beacon_south_corridor_sensor_two"
    text = (ROOT / "examples" / "tiny.yaml").read_text()
    text = text.replace("o1", long1).replace("o2", long2)
    path = tmp_path / "long.yaml"
    path.write_text(text)
    for args in (
        ["solve", str(path), "--budget", "0..4"],
        ["evaluate", str(path), "--alter", f"{long2}={long1}"],
        ["audit", str(path), "--budget", "1"],
    ):
        result = runner.invoke(app, args, env={"COLUMNS": "60"})
        assert result.exit_code == 0, result.output
        assert "…" not in result.stdout
        flat = "".join(ch for ch in result.stdout if ch not in " \n│┃")
        assert long1 in flat and long2 in flat, args
