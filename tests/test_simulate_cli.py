"""`misdirect simulate`: the empirical frequency brackets the exact value, and the written
trajectories are real runs of the controller."""

import csv
import json
from pathlib import Path

from typer.testing import CliRunner

from misdirect.cli import app
from result_schema import checked

EXAMPLES = Path(__file__).parent.parent / "examples"
runner = CliRunner()


def test_simulate_trap_brackets_hand_value(tmp_path):
    path = tmp_path / "runs.csv"
    result = runner.invoke(
        app,
        [
            "simulate",
            str(EXAMPLES / "trap.yaml"),
            "--alter",
            "o1=o0",
            "--runs",
            "50000",
            "--seed",
            "3",
            "--trajectories",
            str(path),
            "--samples",
            "5",
            "--json",
        ],
    )
    assert result.exit_code == 0, result.output
    payload = checked(result.stdout)
    low, high = payload["totals"]["decoy"]["interval_95"]
    assert low <= 0.4 <= high  # hand value: 0.6·0.5 + 0.4·0.25
    assert payload["value"] == 0.4 or abs(payload["value"] - 0.4) < 1e-12
    assert payload["written"] == [str(path)]
    goal_low, goal_high = payload["totals"]["goal"]["interval_95"]
    assert goal_low <= 0.6 <= goal_high
    rows = list(csv.DictReader(path.open()))
    assert sorted({int(r["run"]) for r in rows}) == [0, 1, 2, 3, 4]
    for run in range(5):
        steps = [r for r in rows if int(r["run"]) == run]
        assert [int(r["step"]) for r in steps] == list(range(len(steps)))
        assert steps[0]["state"] == "start" and steps[0]["action"] == "go"  # reads o0: go
        assert steps[-1]["action"] == "(stopped)"
        assert steps[-1]["state"] in ("goal", "decoy")
        for row in steps[:-1]:  # the altered loop sensor reads o0, so the robot goes
            assert row["action"] == ("stay" if row["received"] == "o2" else "go")


def test_simulate_rejects_bad_counts():
    result = runner.invoke(app, ["simulate", str(EXAMPLES / "trap.yaml"), "--runs", "0", "--json"])
    assert result.exit_code == 2
    assert json.loads(result.stdout)["error"]["field"] == "--runs"


def test_show_grid_picture_and_chain_graph(tmp_path):
    picture = tmp_path / "attack.png"
    result = runner.invoke(
        app, ["show", str(EXAMPLES / "paper-grid-map.yaml"), "-a", "1=3", "-o", str(picture)]
    )
    assert result.exit_code == 0, result.output
    assert picture.stat().st_size > 20_000
    graph = tmp_path / "trap.dot"
    result = runner.invoke(
        app, ["show", str(EXAMPLES / "trap.yaml"), "-a", "o1=o0", "-o", str(graph)]
    )
    assert result.exit_code == 0, result.output
    text = graph.read_text()
    assert text.count("[label=") == 5 + 8  # 5 product states; 8 transitions incl. 2 self-loops
    assert 'q1 -> q4 [label="0.5"]' in text  # the altered loop: go, half into the decoy


def test_show_refuses_what_it_cannot_draw(tmp_path):
    for args in (
        [str(EXAMPLES / "trap.yaml"), "-o", str(tmp_path / "trap.png")],
        ["--scenario", "paper-grid", "--size", "45", "-o", str(tmp_path / "big.dot")],
        [str(EXAMPLES / "trap.yaml"), "-o", str(tmp_path / "trap.txt")],
    ):
        result = runner.invoke(app, ["show", *args, "--json"])
        assert result.exit_code == 2, result.output
        assert json.loads(result.stdout)["error"]["field"] == "-o"


def test_simulate_stops_trapped_runs_and_names_outcomes():
    """trap.yaml unaltered: 0.6 of the runs go to `loop` and stay there forever (trapped), 0.4
    go to `exit`, then 0.25 into the decoy and 0.75 into the goal: decoy 0.1, goal 0.3. Every
    finished run takes exactly two steps. The default --max-steps is 10,000; trapped runs are
    stopped when they enter the loop, not run to it."""
    result = runner.invoke(
        app, ["simulate", str(EXAMPLES / "trap.yaml"), "--runs", "40000", "--seed", "5", "--json"]
    )
    assert result.exit_code == 0, result.output
    payload = checked(result.stdout)
    totals = payload["totals"]
    for name, expected in (("decoy", 0.1), ("goal", 0.3), ("trapped", 0.6)):
        low, high = totals[name]["interval_95"]
        assert low <= expected <= high, (name, totals[name])
    by_state = {(o["kind"], o["state"]): o["runs"] for o in payload["outcomes"]}
    assert by_state == {
        ("decoy", "decoy"): totals["decoy"]["runs"],
        ("goal", "goal"): totals["goal"]["runs"],
    }
    assert totals["unfinished"]["runs"] == 0
    assert sum(row["runs"] for row in totals.values()) == 40000
    assert payload["mean_steps_finished"] == 2.0
    text = runner.invoke(app, ["simulate", str(EXAMPLES / "trap.yaml"), "--runs", "2000"]).stdout
    assert "trapped: never stops" in text and "finished runs" in text
    assert "goal (absorbing, not decoy)" in text and "decoy (attacker's target)" in text


def test_simulate_library_counts_add_up():
    from misdirect import load_problem
    from misdirect.core.simulate import simulate

    problem = load_problem(EXAMPLES / "trap.yaml")
    result = simulate(problem, runs=5000, seed=1, max_steps=1)  # exit runs need 2 steps
    assert result.decoy_hits == 0 and sum(result.absorbed.values()) == 0
    assert result.trapped + result.unfinished == 5000
    assert 0 < result.trapped < 5000  # the loop runs are trapped at step 1, exit runs unfinished


def test_a_mean_over_no_finished_run_is_null_in_strict_json():
    """Issue 51, item 8: with --max-steps 1 no run of the trap corridor finishes (each takes
    two steps, by hand), so the mean over finished runs is undefined: null, and the document
    is strict JSON (it held a bare NaN, which JSON has not)."""
    result = runner.invoke(
        app, ["simulate", str(EXAMPLES / "trap.yaml"), "--runs", "50", "--max-steps", "1", "--json"]
    )
    assert result.exit_code == 0, result.output

    def refuse(constant):
        raise AssertionError(f"not JSON: {constant}")

    payload = json.loads(result.stdout, parse_constant=refuse)
    assert payload["mean_steps_finished"] is None
    assert payload["totals"]["decoy"]["runs"] + payload["totals"]["goal"]["runs"] == 0
