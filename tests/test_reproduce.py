"""`misdirect reproduce --quick`: the tables it writes carry the SPEC numbers, the figures exist
and flag what is not a real measurement, and the heat-map data is right (expected visits
re-computed from the SPEC's grid and controller, built here with plain loops)."""

from __future__ import annotations

import csv
import json
import re
from pathlib import Path
from typing import ClassVar

import numpy as np
import pytest
from matplotlib.image import imread
from typer.testing import CliRunner

import misdirect.cli as cli
from misdirect.cli import app
from misdirect.report import figures
from result_schema import checked

ROOT = Path(__file__).resolve().parents[1]
# SPEC §3: exact optima of the 5x5 grid for budgets 0..7
GRID = [0.084957, 0.719924, 0.860130, 0.862442, 0.863622, 0.863622, 0.863622, 0.863622]
EXPERIMENTS = {"reduction example", "grid case study", "scalability study", "attack figures"}
runner = CliRunner()


class _RecordingProgress:
    """Stands in for the CLI's progress bars (which stay silent under --json) and records."""

    calls: ClassVar[list[tuple[str, int, int]]] = []

    def __init__(self, enabled: bool, *, transient: bool = False):
        pass

    def __enter__(self):
        return self

    def __exit__(self, *exc: object) -> None:
        pass

    def track(self, name: str, done: int, total: int) -> None:
        self.calls.append((name, done, total))


@pytest.fixture(scope="module")
def results(tmp_path_factory):
    folder = tmp_path_factory.mktemp("reproduce")
    _RecordingProgress.calls = []
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(cli.reproduce, "ProgressBars", _RecordingProgress)
        outcome = runner.invoke(
            app, ["reproduce", "--quick", "--out", str(folder), "--time-limit", "5", "--json"]
        )
    assert outcome.exit_code == 0, outcome.output
    return folder, checked(outcome.stdout), list(_RecordingProgress.calls)


def _rows(folder, name):
    with (folder / f"{name}.csv").open(encoding="utf-8") as handle:
        return list(csv.DictReader(handle))


def test_grid_table_has_spec_values(results):
    folder, _, _ = results
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
    folder, _, _ = results
    rows = {r["formulation"]: r for r in _rows(folder, "reduction")}
    assert float(rows["compact"]["probability"]) == pytest.approx(0.25, abs=1e-12)
    assert rows["compact"]["alteration"] == "o1 → o_club, o2 → o_club, o4 → o_club"
    # The program builds the paper formulation WITH the successor filter (SPEC §5), so its
    # size is checked against the filtered count: 9 observations, 3 nodes, 9 states and
    # 21 successor pairs (s0: 7, items: 2 each, club: 2, the two absorbing states: 1 each).
    assert int(rows["paper"]["variables"]) == 81 + 9 * 3 * 9 + 21 * 81 * 3
    assert int(rows["paper"]["rows"]) == 2 + 9 + 9 * 3 * 9 + 4 * 21 * 81 * 3
    # the printed 59,373 = x + z + l over all pairs of (s, n, o), i.e. no successor filter;
    # the printed 236,477 rows are quoted, not rebuilt (see the table's note)
    assert int(rows["paper (as printed)"]["variables"]) == 81 + 243 + (9 * 3 * 9) ** 2
    assert "without that filter" in (folder / "reduction.md").read_text(encoding="utf-8")


def test_paper_formulation_flagged_unverified(results):
    """Without alteration the reduction never reaches s⊥ (every item and the club lead to s⊤),
    so the paper MILP's answer is worth 0 while it claims a large value (SPEC §2): the written
    tables, the report and the summary must say so, with both numbers."""
    folder, summary, _ = results
    paper = next(r for r in _rows(folder, "reduction") if r["formulation"] == "paper")
    assert paper["status"] == "unverified"
    assert float(paper["solver_probability"]) > float(paper["probability"]) + 0.5
    reduction_md = (folder / "reduction.md").read_text(encoding="utf-8")
    report = (folder / "report.md").read_text(encoding="utf-8")
    for text in (reduction_md, report):
        assert "**Unverified: the paper formulation's answers are wrong.**" in text
    exact = float(paper["probability"])
    assert f"claims {float(paper['solver_probability']):g}, exact value {exact:g}" in reduction_md

    scalability_md = (folder / "scalability.md").read_text(encoding="utf-8")
    wrong = [r for r in _rows(folder, "scalability") if r["status"] == "unverified"]
    assert any(r["formulation"] == "paper" for r in wrong)  # n = 5 solves well within 5 s
    for row in wrong:
        assert f"n = {row['n']}: claims" in scalability_md
        assert f"n = {row['n']}: claims" in report
    notes = {s["experiment"]: " ".join(s["notes"]) for s in summary["summary"]}
    assert "UNVERIFIED paper MILP" in notes["reduction example"]
    assert "UNVERIFIED paper MILP" in notes["scalability study"]
    # the reduction's sizes are in the summary too (16 x + ... for compact; paper's 59,373)
    assert (
        f"compact {int(_rows(folder, 'reduction')[0]['variables']):,} vars"
        in (notes["reduction example"])
    )
    assert "59,373 / 236,477" in notes["reduction example"]


def test_scalability_table(results):
    folder, summary, _ = results
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
    late = [f"{r['formulation']} n={r['n']}" for r in rows if r["solver_status"] == "time_limit"]
    text = (folder / "scalability.md").read_text(encoding="utf-8")
    for label in late:  # every time-out is named in the note, none is silently dropped
        assert label in text


def test_every_experiment_registers_its_bar_first(results):
    _, _, calls = results
    assert {name for name, _, _ in calls} == EXPERIMENTS
    # all four bars appear at 0/total before any experiment makes a step
    assert {name for name, done, _ in calls[:4]} == EXPERIMENTS
    assert all(done == 0 and total > 0 for _, done, total in calls[:4])
    for name in EXPERIMENTS:
        mine = [(done, total) for n, done, total in calls if n == name]
        assert mine[-1][0] == mine[-1][1]  # and each one finishes
        assert [d for d, _ in mine] == sorted(d for d, _ in mine)
    grid_total = {total for n, _, total in calls if n == "grid case study"}
    assert grid_total == {8}  # budgets 0..7


def test_figures_are_real_images(results):
    folder, _, _ = results
    for stem in ("scalability", "grid_layout", "attacks"):
        png = folder / f"{stem}.png"
        assert png.stat().st_size > 20_000
        height, width, _ = imread(png).shape
        assert width > 400 and height > 300
        assert (folder / f"{stem}.svg").read_text().lstrip().startswith("<?xml")
    report = (folder / "report.md").read_text()
    for link in ("scalability.png", "attacks.png", "grid.csv", "reduction.csv"):
        assert link in report
    attacks = (folder / "attacks.svg").read_text(encoding="utf-8")
    # matplotlib writes each text as a comment beside its glyphs: the notation is explained
    assert "altered sensor: o1→o2 means sensor o1 now reports o2" in attacks
    assert "the run ends here" in attacks


def test_timed_out_and_unverified_points_are_drawn_apart(tmp_path, monkeypatch):
    """A point stopped by the time limit is a triangle at the limit, labelled, and not on the
    line; an unverified answer is hollow and explained in the legend."""
    rows = []
    for n, solve_time, status, solver_status, claimed, exact in (
        (5, 2.0, "unverified", "optimal", 1.0, 0.084957),
        (15, 20.0, "unverified", "optimal", 1.0, 0.000317),
        (25, 60.4, "time_limit", "time_limit", None, 9.9e-7),
    ):
        rows.append(
            {
                "n": n,
                "formulation": "paper",
                "variables": 1000 * n,
                "rows": 4000 * n,
                "build_time_s": 0.01 * n,
                "solve_time_s": solve_time,
                "status": status,
                "solver_status": solver_status,
                "solver_probability": claimed,
                "probability": exact,
                "evaluation_time_s": 0.001 * n,
            }
        )
        rows.append(
            {
                **rows[-1],
                "formulation": "compact",
                "status": "optimal",
                "solver_status": "optimal",
                "solve_time_s": 0.1 * n,
                "solver_probability": 0.5,
                "probability": 0.5,
            }
        )
    drawn = []
    real_save = figures.save

    def keep(fig, stem, formats=(".png", ".svg")):
        drawn.append(fig)
        return real_save(fig, stem, formats)

    monkeypatch.setattr(figures, "save", keep)
    (svg,) = figures.scalability_panels(rows, tmp_path / "scal", formats=(".svg",), time_limit=60)
    text = svg.read_text(encoding="utf-8")
    assert 'id="timed-out' in text  # the triangle's group
    assert "<!-- timed out -->" in text
    assert "paper MILP: claimed optimum wrong (claims 1" in text
    solve_axis = drawn[0].axes[3]
    (triangle,) = [line for line in solve_axis.lines if line.get_gid() == "timed-out"]
    assert triangle.get_marker() == "^"
    assert list(triangle.get_ydata()) == [60.4]  # HiGHS overran the 60 s limit: the measured time
    for line in solve_axis.lines:
        if line.get_linestyle() in ("-", "--") and line.get_color() == "tab:red":
            assert 25 not in list(line.get_xdata())  # not joined to the measured line
    hollow = [
        line
        for line in solve_axis.lines
        if line.get_marker() == "s" and line.get_markerfacecolor() == "white"
    ]
    assert sorted(hollow[0].get_xdata()) == [5, 15]


# -- heat-map data, recomputed from SPEC §3 with plain loops ---------------------------------

N = 5
SENSORS = {
    "o0": [(0, 0)],
    "o1": [(2, 0), (2, 1)],
    "o2": [(0, 2), (1, 2)],
    "o3": [(4, 0), (4, 1)],
    "o4": [(0, 4), (1, 4)],
    "o5": [(4, 3)],
    "o6": [(3, 4)],
}
GOAL, HAZARD = (4, 4), (2, 2)
MOVES = {"N": (0, 1), "E": (1, 0), "S": (0, -1), "W": (-1, 0)}


def _observation(cell):
    return next((name for name, cells in SENSORS.items() if cell in cells), "b")


def _moves(cell, action):
    """SPEC §3: 0.8 intended (stay if it leaves the grid), 0.1 / 0.2 sideways."""
    x, y = cell
    dx, dy = MOVES[action]
    inside = lambda c: 0 <= c[0] < N and 0 <= c[1] < N  # noqa: E731
    out = {}
    target = (x + dx, y + dy)
    out[target if inside(target) else cell] = 0.8
    sides = [c for c in ((x + dy, y + dx), (x - dy, y - dx)) if inside(c)]
    for side in sides:
        out[side] = out.get(side, 0.0) + (0.1 if len(sides) == 2 else 0.2)
    return out


def _controller(node, obs):
    """SPEC §3: (action, next node); nodes 0 = n0, 1 = n1 (E-type), 2 = n2 (N-type)."""
    if obs in ("o0", "o1", "o4", "o6"):
        return "E", 1
    if obs in ("o2", "o3", "o5"):
        return "N", 2
    return ("N" if node == 2 else "E"), node


def _chain(alteration):
    """Transient part Q of the product chain over (cell, node) and the one-step absorption
    probabilities into the hazard and the goal."""
    cells = [(x, y) for y in range(N) for x in range(N) if (x, y) not in (GOAL, HAZARD)]
    index = {(c, n): i for i, (c, n) in enumerate((c, n) for c in cells for n in range(3))}
    q = np.zeros((len(index), len(index)))
    to_hazard, to_goal = np.zeros(len(index)), np.zeros(len(index))
    for (cell, node), i in index.items():
        obs = _observation(cell)
        received = alteration.get(obs, obs)
        action, after = _controller(node, received)
        for target, p in _moves(cell, action).items():
            if target == HAZARD:
                to_hazard[i] += p
            elif target == GOAL:
                to_goal[i] += p
            else:
                q[i, index[(target, after)]] += p
    return index, q, to_hazard, to_goal


def _parse(text):
    return {} if text == "none" else dict(part.split(" → ") for part in text.split(", "))


@pytest.mark.parametrize("budget", [0, 1, 2, 4])
def test_heat_map_data_two_ways(results, budget):
    """Visits by a power series over the state distribution; their sum against the expected
    number of steps from a dense backward solve; and the absorbed mass against SPEC §3."""
    folder, _, _ = results
    grid_row = next(r for r in _rows(folder, "grid") if int(r["budget"]) == budget)
    alteration = _parse(grid_row["alteration"])
    assert "o0" not in alteration  # the initial observation is never altered
    index, q, to_hazard, to_goal = _chain(alteration)

    mass = np.zeros(len(index))
    mass[index[((0, 0), 0)]] = 1.0
    visits = np.zeros(len(index))
    for _ in range(100_000):
        visits += mass
        mass = mass @ q
        if mass.sum() < 1e-15:
            break
    else:
        pytest.fail("the chain did not absorb")
    per_cell = {}
    for (cell, _), i in index.items():
        per_cell[cell] = per_cell.get(cell, 0.0) + visits[i]

    written = {
        (int(r["x"]), int(r["y"])): float(r["expected_visits"])
        for r in _rows(folder, "attack_visits")
        if int(r["budget"]) == budget
    }
    assert len(written) == N * N
    for cell, value in written.items():
        assert value == pytest.approx(per_cell.get(cell, 0.0), abs=1e-9), (budget, cell)

    # expected steps to absorption, solved backwards: t = 1 + Q t
    steps = np.linalg.solve(np.eye(len(index)) - q, np.ones(len(index)))
    assert sum(written.values()) == pytest.approx(steps[index[((0, 0), 0)]], rel=1e-9)
    # the visits also carry the right outcome: Pr(hazard) = visits · P(-> hazard) = SPEC value
    assert visits @ to_hazard == pytest.approx(GRID[budget], abs=5e-7)
    assert visits @ to_goal == pytest.approx(1 - GRID[budget], abs=5e-7)
    assert float(grid_row["goal_probability"]) == pytest.approx(1 - GRID[budget], abs=5e-7)


# -- the committed outputs and the README ----------------------------------------------------


def _readme_grid_table():
    """The grid table of docs/benchmarks.md (it was the README's, hence the name)."""
    text = (ROOT / "docs" / "benchmarks.md").read_text(encoding="utf-8")
    section = text.split("## The paper's numbers, reproduced", 1)[1].split("\n## ", 1)[0]
    rows = [
        [cell.strip() for cell in line.strip().strip("|").split("|")]
        for line in section.splitlines()
        if re.match(r"^\| \d", line)
    ]
    assert rows, "no grid table in docs/benchmarks.md's 'The paper's numbers, reproduced'"
    return rows


def _budgets(label):
    low, _, high = label.partition("..")
    return list(range(int(low), int(high or low) + 1))


def test_readme_grid_table_has_spec_values():
    rows = _readme_grid_table()
    covered = []
    for budget_label, probability, printed, _alteration, goal in rows:
        for budget in _budgets(budget_label):
            covered.append(budget)
            assert float(probability) == pytest.approx(GRID[budget], abs=5e-7)
            # every run ends at the goal or the hazard (checked above from the chain)
            assert float(goal) == pytest.approx(1 - GRID[budget], abs=5e-7)
            assert float(printed.split()[0]) == pytest.approx(GRID[budget], abs=1.5e-3)
    assert covered == list(range(8))


def test_readme_and_committed_grid_table_agree():
    committed = {int(r["budget"]): r for r in _rows(ROOT / "docs" / "reproduce", "grid")}
    assert [float(committed[b]["probability"]) for b in range(8)] == pytest.approx(GRID, abs=5e-7)
    for budget_label, probability, _printed, alteration, goal in _readme_grid_table():
        for budget in _budgets(budget_label):
            row = committed[budget]
            assert alteration == row["alteration"], budget
            assert float(probability) == pytest.approx(float(row["probability"]), abs=5e-7)
            assert float(goal) == pytest.approx(float(row["goal_probability"]), abs=5e-7)


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


def test_json_lists_every_file_written(results):
    folder, document, _ = results
    assert document["command"] == "reproduce"
    written = [Path(p) for p in document["written"]]
    assert {"report.md", "grid.csv", "grid.md", "scalability.png"} <= {p.name for p in written}
    assert all(p.parent == folder and p.exists() for p in written)
