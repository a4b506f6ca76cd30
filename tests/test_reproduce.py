"""`misdirect reproduce --quick`: the tables it writes carry the SPEC numbers, the figures exist,
and the heat-map data is right (expected visits re-computed by a power series)."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest
from matplotlib.image import imread
from typer.testing import CliRunner

from misdirect.cli import app
from misdirect.product import build_product
from misdirect.scenarios import paper_grid

GRID = [0.084957, 0.719924, 0.860130, 0.862442, 0.863622, 0.863622, 0.863622, 0.863622]
runner = CliRunner()


@pytest.fixture(scope="module")
def results(tmp_path_factory):
    folder = tmp_path_factory.mktemp("reproduce")
    outcome = runner.invoke(
        app, ["reproduce", "--quick", "--out", str(folder), "--time-limit", "5", "--json"]
    )
    assert outcome.exit_code == 0, outcome.output
    return folder, json.loads(outcome.stdout)


def _rows(folder, name):
    with (folder / f"{name}.csv").open() as handle:
        return list(csv.DictReader(handle))


def test_grid_table_has_spec_values(results):
    folder, _ = results
    rows = _rows(folder, "grid")
    assert [int(r["budget"]) for r in rows] == list(range(8))
    assert [float(r["probability"]) for r in rows] == pytest.approx(GRID, abs=5e-7)
    # the paper's printed value disagrees with rounding only at budget 2 (0.861 vs 0.860130)
    assert [r["budget"] for r in rows if r["rounding_agrees"] == "False"] == ["2"]
    assert float(rows[0]["goal_probability"]) == pytest.approx(0.915043, abs=5e-7)
    for row in rows:  # the paper's own alterations are optimal too (SPEC §3 table)
        assert float(row["paper_alteration_value"]) == pytest.approx(
            float(row["probability"]), abs=5e-7
        )


def test_reduction_table(results):
    folder, _ = results
    rows = {r["formulation"]: r for r in _rows(folder, "reduction")}
    assert float(rows["compact"]["probability"]) == pytest.approx(0.25, abs=1e-12)
    assert rows["compact"]["alteration"] == "o1 → o_club, o2 → o_club, o4 → o_club"
    # paper formulation with the successor filter: 9 observations, 3 nodes, 9 states and
    # 21 successor pairs (s0: 7, items: 2 each, club: 2, the two absorbing states: 1 each)
    assert int(rows["paper"]["variables"]) == 81 + 9 * 3 * 9 + 21 * 81 * 3
    assert int(rows["paper"]["rows"]) == 2 + 9 + 9 * 3 * 9 + 4 * 21 * 81 * 3
    # the printed 59,373 = x + z + l over all pairs of (s, n, o), i.e. no successor filter
    assert int(rows["paper (as printed)"]["variables"]) == 81 + 243 + (9 * 3 * 9) ** 2


def test_scalability_table(results):
    folder, summary = results
    rows = _rows(folder, "scalability")
    assert sorted({int(r["n"]) for r in rows}) == [5, 15, 25]
    for row in rows:
        n = int(row["n"])
        if row["formulation"] == "paper":
            edges = 4 * n * n - 9
            assert int(row["variables"]) == 64 + 24 * n * n + 192 * edges
        else:
            assert int(row["variables"]) < 3 * 3 * n * n
        assert row["solver_status"] in ("optimal", "time_limit")
    compact5 = next(r for r in rows if r["n"] == "5" and r["formulation"] == "compact")
    assert float(compact5["probability"]) == pytest.approx(GRID[1], abs=5e-7)  # budget 1
    assert summary["mode"] == "quick"


def test_figures_are_real_images(results):
    folder, _ = results
    for stem in ("scalability", "grid_layout", "attacks"):
        png = folder / f"{stem}.png"
        assert png.stat().st_size > 20_000
        height, width, _ = imread(png).shape
        assert width > 400 and height > 300
        assert (folder / f"{stem}.svg").read_text().lstrip().startswith("<?xml")
    report = (folder / "report.md").read_text()
    for link in ("scalability.png", "attacks.png", "grid.csv", "reduction.csv"):
        assert link in report


def test_heat_map_data_by_power_series(results):
    """Expected visits per cell, re-computed by summing the state distribution step by step."""
    folder, _ = results
    rows = _rows(folder, "attack_visits")
    problem = paper_grid(5)
    alterations = {0: {}, 1: {"o1": "o2"}}
    for budget, changes in alterations.items():
        chain = build_product(problem, problem.alteration(changes))
        stop = problem.decoy[chain.world_state] | problem.pomdp.absorbing[chain.world_state]
        moving = chain.matrix.T.tocsr()
        mass = np.zeros(chain.n_states)
        mass[chain.initial] = 1.0
        visits = np.zeros(chain.n_states)
        for _ in range(5000):
            mass[stop] = 0.0
            visits += mass
            mass = moving @ mass
            if mass[~stop].sum() < 1e-15:
                break
        per_cell = np.bincount(chain.world_state, weights=visits, minlength=25)
        written = {
            (int(r["x"]), int(r["y"])): float(r["expected_visits"])
            for r in rows
            if int(r["budget"]) == budget
        }
        for (x, y), value in written.items():
            assert value == pytest.approx(per_cell[y * 5 + x], abs=1e-9), (budget, x, y)


@pytest.mark.parametrize(
    ("args", "field"),
    [
        (["--sizes", "3"], "--sizes"),
        (["--sizes", "five"], "--sizes"),
        (["--time-limit", "0"], "--time-limit"),
    ],
)
def test_bad_reproduce_options(tmp_path, args, field):
    outcome = runner.invoke(app, ["reproduce", "--out", str(tmp_path), *args, "--json"])
    assert outcome.exit_code == 2, outcome.output
    assert json.loads(outcome.stdout)["error"]["field"] == field
