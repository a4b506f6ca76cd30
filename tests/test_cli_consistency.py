"""The command line's conventions (issue 53): one budget flag, help that shows what the source
says, errors in one shape (JSON too, usage errors included), PAYNT's spellings for synthesis,
alterations that travel between commands, and a summary of every file written."""

from __future__ import annotations

import json

import pytest
from typer.testing import CliRunner

import misdirect
from misdirect.cli import app
from misdirect.scenarios import paper_grid

runner = CliRunner()


def solved_budgets(*args: str) -> list[float]:
    result = runner.invoke(app, ["solve", "--scenario", "paper-grid", *args, "--json"])
    assert result.exit_code == 0, result.output
    return [point["budget"] for point in json.loads(result.stdout)["curve"]]


# -- A: one budget flag --------------------------------------------------------------------------


@pytest.mark.parametrize("spelling", ["--budget", "--budgets"])
def test_budget_takes_a_number_a_range_or_a_list_under_either_spelling(spelling):
    assert solved_budgets(spelling, "0,2") == [0, 2]
    assert solved_budgets(spelling, "0..2") == [0, 1, 2]
    assert solved_budgets(spelling, "1")[-1] == 1


@pytest.mark.parametrize(
    ("value", "expected"),
    [
        ("lots", "expected a number (2), a range (0..4) or a list (0,1,3), got 'lots'"),
        ("0..x", "expected a range of whole numbers like 0..4, got '0..x'"),
        ("0,x", "expected a list of numbers like 0,1,3, got '0,x'"),
        ("3..1", "0 ≤ low ≤ high"),
        ("0,-1", "non-negative"),
    ],
)
@pytest.mark.parametrize("spelling", ["--budget", "--budgets"])
def test_a_bad_budget_gets_the_message_of_its_own_syntax(spelling, value, expected):
    result = runner.invoke(app, ["solve", "--scenario", "paper-grid", spelling, value, "--json"])
    assert result.exit_code == 2
    error = json.loads(result.stdout)["error"]
    assert expected in error["message"] and error["field"] == "--budget", error


def test_the_library_takes_budget_and_budgets_alike():
    problem = paper_grid(5)
    one = misdirect.solve(problem, budget=1)
    assert one.curve[-1].budget == 1
    assert misdirect.solve(problem, budgets=1).probability == one.probability
    assert [p.budget for p in misdirect.solve(problem, budget=[0, 1]).curve] == [0, 1]
    assert [p.budget for p in misdirect.solve(problem, budgets=range(2)).curve] == [0, 1]
    assert misdirect.solve(problem, budget=1, budgets=[1]).probability == one.probability
    with pytest.raises(TypeError, match="same parameter spelled two ways"):
        misdirect.solve(problem, budget=1, budgets=[0, 1])
    assert misdirect.audit(problem, budgets=1).budget == misdirect.audit(problem, budget=1).budget
    assert misdirect.harden(problem, protect_budget=1, budgets=[1]).budget == 1
    with pytest.raises(TypeError, match="one attacker budget"):
        misdirect.harden(problem, protect_budget=1, budgets=[1, 2])
    with pytest.raises(TypeError, match="same parameter"):
        misdirect.audit(problem, budget=1, budgets=2)
