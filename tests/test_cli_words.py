"""Issue 53, the budget flag: audit/harden --budget written as solve's (a number, range or
list), a range or list of several budgets refused by name."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from typer.testing import CliRunner

from misdirect.cli import app

runner = CliRunner()
TINY = str(Path(__file__).resolve().parents[1] / "examples" / "tiny.yaml")


@pytest.mark.parametrize("command", [["audit"], ["harden", "--protect-budget", "1"]])
@pytest.mark.parametrize("spelling", ["--budget", "--budgets"])
def test_audit_and_harden_read_budget_as_solve_does(command, spelling):
    for text in ("1", "1..1", "1,1"):
        result = runner.invoke(app, [*command, TINY, spelling, text, "--json"])
        assert result.exit_code == 0, (text, result.output)
        assert json.loads(result.stdout)["budget"] == 1


@pytest.mark.parametrize("command", [["audit"], ["harden", "--protect-budget", "1"]])
@pytest.mark.parametrize("text", ["0..2", "0,1,3", "0..1000000000"])
def test_audit_and_harden_refuse_several_budgets_by_name(command, text):
    result = runner.invoke(app, [*command, TINY, "--budget", text, "--json"])
    assert result.exit_code == 2, result.output
    error = json.loads(result.stdout)["error"]
    assert error["field"] == "--budget"
    assert f"{command[0]} answers one budget" in error["message"]
    assert "give one number" in error["message"]


@pytest.mark.parametrize("text", ["lots", "0..x", "-1"])
def test_audit_budget_syntax_errors_are_solves(text):
    result = runner.invoke(app, ["audit", TINY, "--budget", text, "--json"])
    assert result.exit_code == 2, result.output
    assert json.loads(result.stdout)["error"]["field"] == "--budget"
