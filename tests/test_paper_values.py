"""SPEC §3 (grid case study) and SPEC §4 (knapsack reduction), through library and CLI.

Expected values: the paper's Section VII, corrected to six decimals by the specification
(exhaustive enumeration and solving the chain; independently re-checked against Storm in
test_storm_agreement.py).
"""

import json

import pytest
from typer.testing import CliRunner

from misdirect import decoy_probability, evaluate, solve
from misdirect.cli import app
from misdirect.scenarios import knapsack, paper_grid

# budget -> (max Pr(reach hazard), one optimal alteration), SPEC §3 table for n = 5
GRID_OPTIMA = {
    0: (0.084957, {}),
    1: (0.719924, {"o1": "o3"}),
    2: (0.860130, {"o1": "o5", "o2": "o0"}),
    3: (0.862442, {"o1": "o5", "o2": "o0", "o6": "o2"}),
    4: (0.863622, {"o2": "o6", "o5": "o1", "o1": "o2", "o6": "o3"}),
}
runner = CliRunner()


@pytest.mark.parametrize("budget", GRID_OPTIMA)
def test_listed_alterations_evaluate_to_spec(budget):
    problem = paper_grid(5)
    value, changes = GRID_OPTIMA[budget]
    assert decoy_probability(problem, problem.alteration(changes)) == pytest.approx(value, abs=5e-7)


def test_baseline_goal_probability():
    report = evaluate(paper_grid(5))
    assert report.outcomes["(4,4)"] == pytest.approx(0.915043, abs=5e-7)
    assert report.outcomes["(2,2)"] == pytest.approx(0.084957, abs=5e-7)
    assert report.never_absorbed == pytest.approx(0.0, abs=1e-12)


def test_exhaustive_reproduces_budget_curve():
    result = solve(paper_grid(5).with_budget(7), method="exhaustive")
    values = {point.budget: point.probability for point in result.curve}
    for budget in range(8):
        expected = GRID_OPTIMA[min(budget, 4)][0]
        assert values[budget] == pytest.approx(expected, abs=5e-7), budget
    for point in result.curve:
        assert point.cost <= point.budget
        assert point.status == "optimal"


@pytest.mark.parametrize("budget", GRID_OPTIMA)
def test_cli_evaluate_matches_spec(budget):
    value, changes = GRID_OPTIMA[budget]
    args = ["evaluate", "--scenario", "paper-grid", "--size", "5", "--json"]
    for original, received in changes.items():
        args += ["--alter", f"{original}={received}"]
    result = runner.invoke(app, args)
    assert result.exit_code == 0, result.output
    payload = json.loads(result.stdout)
    assert payload["value"] == pytest.approx(value, abs=5e-7)
    assert payload["baseline_value"] == pytest.approx(0.084957, abs=5e-7)
    assert payload["cost"] == len(changes)


def test_cli_solve_curve_matches_spec():
    result = runner.invoke(
        app,
        [
            "solve",
            "--scenario",
            "paper-grid",
            "--budget",
            "0..4",
            "--method",
            "exhaustive",
            "--json",
        ],
    )
    assert result.exit_code == 0, result.output
    payload = json.loads(result.stdout)
    assert payload["status"] == "optimal"
    assert payload["budget"] == 4
    assert payload["value"] == pytest.approx(0.863622, abs=5e-7)
    assert payload["baseline_value"] == pytest.approx(0.084957, abs=5e-7)
    assert [p["budget"] for p in payload["curve"]] == [0, 1, 2, 3, 4]
    for point in payload["curve"]:
        assert point["value"] == pytest.approx(GRID_OPTIMA[point["budget"]][0], abs=5e-7)
    assert len(payload["alteration"]) == payload["cost"] <= 4
    assert {"method", "time_s", "cost", "alteration"} <= payload.keys()


def test_knapsack_reduction_optimum():
    problem = knapsack([1, 2, 3, 4, 5], [20, 30, 40, 50, 60], 7)
    result = solve(problem, method="exhaustive")
    assert result.probability == pytest.approx(0.25, abs=1e-12)
    assert result.alteration == {"o1": "o_club", "o2": "o_club", "o4": "o_club"}
    assert result.cost == 7


def test_cli_knapsack_solve():
    result = runner.invoke(
        app,
        [
            "solve",
            "--scenario",
            "knapsack",
            "--weights",
            "1,2,3,4,5",
            "--values",
            "20,30,40,50,60",
            "--capacity",
            "7",
            "--json",
        ],
    )
    assert result.exit_code == 0, result.output
    payload = json.loads(result.stdout)
    assert payload["value"] == pytest.approx(0.25, abs=1e-12)
    assert payload["alteration"] == {"o1": "o_club", "o2": "o_club", "o4": "o_club"}
