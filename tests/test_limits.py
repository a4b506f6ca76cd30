"""Every command clamps and bounds (issue 29): budgets past what buys everything, memory
estimated before building, deadlines and signals honoured, concurrent solves and writers."""

from __future__ import annotations

import json
from pathlib import Path

from typer.testing import CliRunner

import misdirect
from misdirect.cli import app
from misdirect.io.problem_file import load_problem

runner = CliRunner()
TINY = Path(__file__).parent.parent / "examples" / "tiny.yaml"
# tiny's costs by hand: o1 -> o2 costs 3, o1 -> o0 and o2 -> o1 cost 1, o2 -> o0 is forbidden,
# g is protected, o0 is the initial observation: the most expensive complete alteration costs
# 3 + 1 = 4; within budget 1 both o1 and o2 are alterable, so protecting both costs 2
TINY_CAP = 4.0
TINY_PROTECT_ALL = 2.0


def invoke_json(*args: str) -> dict:
    result = runner.invoke(app, [*args, "--json"])
    assert result.exit_code == 0, result.output
    return json.loads(result.stdout)


# -- budgets past what buys everything --------------------------------------------------------


def test_audit_clamps_a_huge_budget_like_solve():
    payload = invoke_json("audit", str(TINY), "--budget", "1e308")
    assert payload["budget"] == 1e308
    assert payload["budget_clamped_from"] == 1e308 and payload["budget_clamped_to"] == TINY_CAP
    assert [p["budget"] for p in payload["curve"]] == [0, 1, 2, 3, 4, 1e308]
    at_cap = invoke_json("audit", str(TINY), "--budget", "4")
    assert "budget_clamped_from" not in at_cap
    assert payload["probability"] == at_cap["probability"]
    assert payload["sensors"] == at_cap["sensors"]


def test_harden_clamps_huge_protection_and_attacker_budgets():
    payload = invoke_json("harden", str(TINY), "--protect-budget", "1e7")
    assert payload["protect_budget"] == 1e7
    assert payload["protect_budget_clamped_from"] == 1e7
    assert payload["protect_budget_clamped_to"] == TINY_PROTECT_ALL
    assert [p["protect_budget"] for p in payload["curve"]] == [0, 1, 2, 1e7]
    assert payload["curve"][-1]["protection"] == payload["curve"][-2]["protection"]
    assert "budget_clamped_from" not in payload
    huge_b = invoke_json("harden", str(TINY), "--protect-budget", "1", "--budget", "1e300")
    assert huge_b["budget"] == 1e300 and huge_b["budget_clamped_to"] == TINY_CAP


def test_library_audit_and_harden_report_the_clamp():
    problem = load_problem(TINY)
    audited = misdirect.audit(problem, budget=1e12)
    assert (audited.budget_clamped_from, audited.budget_clamped_to) == (1e12, TINY_CAP)
    hardened = misdirect.harden(problem, protect_budget=1e9)
    assert hardened.protect_budget_clamped_to == TINY_PROTECT_ALL
