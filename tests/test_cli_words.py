"""Issue 53, item 9 and the budget flag: solve's footer in words a user understands,
--verbose shown as one flag, and audit/harden --budget written as solve's (a number, range or
list) with a range or list of several budgets refused by name."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest
from typer.testing import CliRunner

from misdirect.cli import app

runner = CliRunner()
TINY = str(Path(__file__).resolve().parents[1] / "examples" / "tiny.yaml")


def test_solve_footer_explains_its_counts():
    result = runner.invoke(app, ["solve", TINY, "--budget", "0..2", "--method", "incremental"])
    assert result.exit_code == 0, result.output
    footer = " ".join(result.stdout.split())  # rich wraps the line
    for jargon in ("inner observations", "outer observations", "factorisations"):
        assert jargon not in footer
    assert "sensors valued by low-rank updates of a base chain 1" in footer
    assert "base chains solved 1" in footer and "alterations valued 2" in footer
    # --json keeps the counters' own names
    document = runner.invoke(app, ["solve", TINY, "--method", "incremental", "--json"])
    stats = json.loads(document.stdout)["stats"]
    assert {"factorisations", "inner_observations", "outer_observations"} <= set(stats)


def test_verbose_is_one_flag_in_help():
    result = runner.invoke(app, ["solve", "--help"], env={"COLUMNS": "200"})
    assert result.exit_code == 0
    assert "--no-verbose" not in result.stdout
    assert re.search(r"--verbose\s+MILP: show the solver's log", result.stdout)


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


def test_a_footer_leaves_out_what_the_run_did_not_do():
    """Branch-and-bound on the paper's grid (no end components: no covers, no collapsed
    proofs) shows its nodes but not the counters of the covers it never tried; --json keeps
    them, at 0."""
    args = ["solve", "--scenario", "paper-grid", "--budget", "1", "--method", "branch-and-bound"]
    result = runner.invoke(app, args)
    assert result.exit_code == 0, result.output
    footer = " ".join(result.stdout.split())
    assert "nodes" in footer
    for quiet in ("cover", "collapsed"):
        assert quiet not in footer
    stats = json.loads(runner.invoke(app, [*args, "--json"]).stdout)["stats"]
    assert stats["covers"] == 0 and stats["collapsed_proofs"] == 0
