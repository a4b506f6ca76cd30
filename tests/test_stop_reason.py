"""Every method says how its work on a budget ended (``stop_reason``), apart from ``status``:
finished, cut by time, by a node limit, by the MILP's gap, or cancelled. Only certification
says ``optimal``; the stop reason is the method's own word, carried to the ``--json``."""

from __future__ import annotations

import json

import pytest
from typer.testing import CliRunner

from misdirect import solve
from misdirect.cli import app
from misdirect.scenarios import paper_grid
from misdirect.solvers.branch_and_bound import BranchAndBoundSolver
from misdirect.solvers.deadline import CancelToken, Deadline
from misdirect.solvers.exhaustive import ExhaustiveSolver
from misdirect.solvers.incremental import IncrementalSolver
from misdirect.solvers.status import Status, StopReason
from result_schema import VALIDATOR, checked
from test_branch_and_bound import trap_grid

runner = CliRunner()


def test_the_stop_reason_of_each_status():
    assert StopReason.of(Status.OPTIMAL, cancelled=False) == StopReason.FINISHED
    assert StopReason.of(Status.FEASIBLE, cancelled=False) == StopReason.NODES
    assert StopReason.of(Status.GAP_LIMIT, cancelled=False) == StopReason.GAP
    assert StopReason.of(Status.TIME_LIMIT, cancelled=False) == StopReason.TIME
    assert StopReason.of(Status.TIME_LIMIT, cancelled=True) == StopReason.CANCELLED
    assert StopReason.of(Status.INTERRUPTED, cancelled=False) == StopReason.CANCELLED


@pytest.mark.parametrize("method", ["exhaustive", "incremental", "branch-and-bound", "auto"])
def test_a_finished_run_says_finished(method):
    result = solve(paper_grid(5), method=method, budgets=[0, 1, 2])
    assert [p.status for p in result.curve] == ["optimal"] * 3
    assert [p.stop_reason for p in result.curve] == ["finished"] * 3
    shown = result.to_dict()
    assert [p["stop_reason"] for p in shown["curve"]] == ["finished"] * 3
    assert shown["stop_reason"] == "finished"


def test_the_milp_finished_and_the_milp_stopped_by_its_gap():
    proven = solve(paper_grid(5), method="milp", budgets=[1]).curve[0]
    assert proven.stop_reason == StopReason.FINISHED
    gapped = solve(paper_grid(5), method="milp", budgets=[1], mip_gap=0.5).curve[0]
    assert gapped.status == "gap_limit"
    assert gapped.stop_reason == StopReason.GAP


def test_a_tiny_time_limit_on_a_big_map_says_time():
    """Thousands of exact evaluations do not fit 50 ms: the budgets past 0 stop by time."""
    result = solve(paper_grid(9), method="exhaustive", budgets=[0, 1, 2, 3], time_limit=0.05)
    assert not result.interrupted
    assert result.curve[-1].status == "time_limit"
    assert result.curve[-1].stop_reason == StopReason.TIME
    assert result.to_dict()["curve"][-1]["stop_reason"] == "time"


def test_an_incremental_run_cut_by_its_deadline_says_time():
    solver = IncrementalSolver()
    answers = solver.solve(paper_grid(9), [0.0, 3.0], deadline=Deadline(0.0))
    assert answers[-1].status == Status.TIME_LIMIT
    assert answers[-1].stop_reason == StopReason.TIME


def test_a_cancelled_run_says_cancelled():
    token = CancelToken()
    token.cancel()
    result = solve(paper_grid(9), method="exhaustive", budgets=[0, 1, 2, 3], cancel=token)
    assert result.interrupted
    # the method was stopped before it began, at every budget; certification still proves
    # budget 0 (it affords "alter nothing" only): the stop and the status are apart
    assert {p.stop_reason for p in result.curve} == {StopReason.CANCELLED}
    assert result.curve[0].status == "optimal"
    assert {p.status for p in result.curve[1:]} == {"interrupted"}
    assert {p["stop_reason"] for p in result.to_dict()["curve"]} == {"cancelled"}


def test_a_run_cancelled_while_it_searches_says_cancelled():
    """Cancelled from its progress callback, mid-search: the budget it did not finish says
    cancelled, not time (it has no time limit), though its status is the method's
    ``time_limit`` until the front door says ``interrupted``; the budget it finished says so."""
    token = CancelToken()

    def progress(done, total, **_):
        if done >= 50:
            token.cancel()

    answers = ExhaustiveSolver().solve(
        paper_grid(9), [0.0, 3.0], progress=progress, deadline=Deadline(cancel=token)
    )
    assert answers[-1].stats["evaluations"] < answers[-1].stats["alterations_within_budget"]
    assert answers[0].stop_reason == StopReason.FINISHED  # "alter nothing" came first
    assert answers[-1].stop_reason == StopReason.CANCELLED
    assert answers[-1].status == Status.TIME_LIMIT


def test_a_node_limited_search_says_nodes():
    problem = trap_grid(9, budget=2)
    (answer,) = BranchAndBoundSolver(max_nodes=2).solve(problem, [2.0])
    assert answer.status == Status.FEASIBLE
    assert answer.stop_reason == StopReason.NODES


def test_an_exhaustive_method_called_on_its_own_reports_its_stop():
    """A method called without the front door builds its deadline from its own options."""
    from misdirect.solvers.options import SolveOptions

    solver = ExhaustiveSolver(SolveOptions(time_limit=0.05))
    answers = solver.solve(paper_grid(9), [0.0, 3.0])
    assert answers[0].stop_reason == StopReason.FINISHED
    assert answers[-1].stop_reason == StopReason.TIME
    finished = ExhaustiveSolver().solve(paper_grid(5), [0.0, 2.0])
    assert {a.stop_reason for a in finished} == {StopReason.FINISHED}


def test_the_json_of_solve_carries_the_stop_reason_and_the_schema_checks_it():
    printed = runner.invoke(app, ["solve", "--scenario", "paper-grid", "--budget", "2", "--json"])
    assert printed.exit_code == 0, printed.output
    document = checked(printed.stdout)
    assert document["stop_reason"] == "finished"
    assert {p["stop_reason"] for p in document["curve"]} == {"finished"}
    # a value outside the enum is refused; the field may be left out (an older document)
    point = document["curve"][0]
    assert not VALIDATOR.is_valid({**document, "curve": [{**point, "stop_reason": "tired"}]})
    older = {k: v for k, v in point.items() if k != "stop_reason"}
    assert VALIDATOR.is_valid({**document, "curve": [older]})
    json.dumps(document)
