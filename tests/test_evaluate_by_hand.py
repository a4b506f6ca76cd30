"""Evaluator values worked out by hand on models small enough to follow on paper."""

import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from misdirect import evaluate, load_problem, solve, write_problem
from misdirect.cli import app
from misdirect.core.simulate import simulate
from misdirect.scenarios import paper_grid

runner = CliRunner()

EXAMPLES = Path(__file__).parents[1] / "examples"


def test_trap_cycle_gets_zero_not_a_spurious_fixed_point():
    """In `loop` the robot stays forever: x_loop = x_loop admits any value, the least is 0.

    Unaltered: 0.6 * 0 (trapped) + 0.4 * 0.25 (exit, stay) = 0.1; 60 % never absorbed.
    """
    problem = load_problem(EXAMPLES / "trap.yaml")
    report = evaluate(problem)
    assert report.probability == pytest.approx(0.1, abs=1e-12)
    assert report.never_absorbed == pytest.approx(0.6, abs=1e-12)
    assert report.outcomes == pytest.approx({"goal": 0.3, "decoy": 0.1}, abs=1e-12)


def test_trap_cycle_altered_out():
    """o1 -> o0 makes the robot `go` in `loop`: 0.6 * 0.5 + 0.4 * 0.25 = 0.4.
    o2 -> o0 makes it `go` at `exit`: 0.4 * 0 = 0 extra, worse. Optimum at budget 1: 0.4."""
    problem = load_problem(EXAMPLES / "trap.yaml")
    assert evaluate(problem, problem.alteration({"o1": "o0"})).probability == pytest.approx(0.4)
    result = solve(problem, method="exhaustive")
    assert result.probability == pytest.approx(0.4, abs=1e-12)
    assert result.alteration == {"o1": "o0"}  # o1 -> o2 keeps `stay`; o2 -> o0 is worse


def test_issue_example_by_hand(tmp_path):
    """s0 -a-> s1|s2 (1/2 each); at s1 the robot reads o1 and plays a (goal 0.8, trap 0.2); at
    s2 it reads o2 in node n0 and steps back to s1 with b: 0.2. Altering o2 -> o1 makes it
    play a at s2, into the trap: 0.5 * 0.2 + 0.5 * 1 = 0.6. Altering o1 -> o0 keeps a: 0.2."""
    problem = load_problem(EXAMPLES / "tiny.yaml")
    assert evaluate(problem).probability == pytest.approx(0.2, abs=1e-15)
    assert evaluate(problem, problem.alteration({"o2": "o1"})).probability == pytest.approx(0.6)
    assert evaluate(problem, problem.alteration({"o1": "o0"})).probability == pytest.approx(0.2)


def test_first_step_of_grid_by_hand():
    """From (0,0) under E: 0.8 to (1,0), 0.2 to (0,1) (the only orthogonal cell inside)."""
    pomdp = paper_grid(5).pomdp
    east = pomdp.transition_matrix(pomdp.actions.index("E"))
    row = dict(zip((pomdp.states[i] for i in east[0].indices), east[0].data, strict=True))
    assert row == pytest.approx({"(1,0)": 0.8, "(0,1)": 0.2})
    north = pomdp.transition_matrix(pomdp.actions.index("N"))
    middle = pomdp.states.index("(2,1)")
    row = dict(
        zip((pomdp.states[i] for i in north[middle].indices), north[middle].data, strict=True)
    )
    assert row == pytest.approx({"(2,2)": 0.8, "(1,1)": 0.1, "(3,1)": 0.1})
    # (4,3) under E: the intended move would leave the grid, so the robot stays with 0.8;
    # both orthogonal cells (4,4) and (4,2) are inside.
    top_right = pomdp.states.index("(4,3)")
    east_row = east[top_right]
    got = dict(zip((pomdp.states[i] for i in east_row.indices), east_row.data, strict=True))
    assert got == pytest.approx({"(4,3)": 0.8, "(4,4)": 0.1, "(4,2)": 0.1})


def test_sensor_layout_n5_matches_paper_figure():
    problem = paper_grid(5)
    pomdp = problem.pomdp
    by_obs = {}
    for s, o in enumerate(pomdp.observation_of):
        by_obs.setdefault(pomdp.observations[o], set()).add(pomdp.states[s])
    assert by_obs["o0"] == {"(0,0)"}
    assert by_obs["o1"] == {"(2,0)", "(2,1)"}
    assert by_obs["o2"] == {"(0,2)", "(1,2)"}
    assert by_obs["o3"] == {"(4,0)", "(4,1)"}
    assert by_obs["o4"] == {"(0,4)", "(1,4)"}
    assert by_obs["o5"] == {"(4,3)"}
    assert by_obs["o6"] == {"(3,4)"}
    assert len(by_obs["b"]) == 25 - 11
    assert [pomdp.states[s] for s in np.flatnonzero(problem.decoy)] == ["(2,2)"]
    assert {pomdp.states[s] for s in np.flatnonzero(pomdp.absorbing)} == {"(2,2)", "(4,4)"}


@pytest.mark.parametrize("n", [5, 6, 7, 8, 11, 45])
def test_scaled_grid_is_stochastic_and_sensors_keep_their_sizes(n):
    problem = paper_grid(n)
    sums = np.asarray(problem.pomdp.transitions.sum(axis=1)).ravel()
    assert np.allclose(sums, 1.0, atol=1e-12)
    counts = np.bincount(problem.pomdp.observation_of, minlength=8)
    assert counts[:7].tolist() == [1, 2, 2, 2, 2, 1, 1]


@pytest.mark.parametrize(
    ("changes", "seed"), [({}, 1), ({"o1": "o3"}, 2), ({"o1": "o5", "o2": "o0"}, 3)]
)
def test_monte_carlo_agrees_with_exact_value(changes, seed):
    """The simulator walks the POMDP and controller directly, without the product chain."""
    problem = paper_grid(5)
    alpha = problem.alteration(changes)
    exact = evaluate(problem, alpha).probability
    sim = simulate(problem, alpha, runs=100_000, seed=seed)
    low, high = sim.confidence_interval(z=3.29)  # 99.9 %: a seeded run, far from the edge
    assert sim.unfinished == 0
    assert low <= exact <= high


def test_expected_visits_two_ways():
    """Expected visits per cell from the LU solve against a Monte-Carlo-free power series:
    visits = Σ_k e0ᵀ A^k over the transient block, summed to convergence."""
    from misdirect.core.product import build_product

    problem = paper_grid(5)
    alpha = problem.alteration({"o1": "o3"})
    report = evaluate(problem, alpha)
    chain = build_product(problem, alpha)
    stop = problem.decoy[chain.world_state] | problem.pomdp.absorbing[chain.world_state]
    a = chain.matrix.toarray()
    a[stop] = 0.0  # runs end there
    a[:, stop] = 0.0
    vector = np.zeros(chain.n_states)
    vector[chain.initial] = 1.0
    total = np.zeros(chain.n_states)
    for _ in range(5000):
        total += vector
        vector = vector @ a
    per_cell = np.bincount(chain.world_state, weights=total, minlength=problem.pomdp.n_states)
    assert np.allclose(report.expected_visits, per_cell, atol=1e-9)


def test_initial_state_in_the_decoy_is_noted(tmp_path):
    """A robot that starts in a decoy state scores 1 at once (by hand, whatever it reads):
    evaluate and solve say why every alteration is worth 1, as a note (exit code 0)."""
    from misdirect.io.problem_file import compile_problem, parse_spec

    document = {
        "format": "misdirect/v1",
        "pomdp": {
            "states": ["start", "next", "goal"],
            "actions": ["a"],
            "initial": "start",
            "observe": {"start": "o0", "next": "o1", "goal": "o2"},
            "transitions": [["start", "a", "next", 1.0], ["next", "a", "goal", 1.0]],
            "absorbing": ["goal"],
        },
        "controller": {
            "nodes": ["m"],
            "initial": "m",
            "rules": [{"node": "*", "obs": "*", "action": "a", "next": "m"}],
        },
        "deception": {"decoy": ["start"], "budget": 1},
    }
    problem = compile_problem(parse_spec(document))
    (note,) = problem.notes
    assert "initial state 'start' is a decoy" in note
    assert evaluate(problem).notes == (note,)
    result = solve(problem, budgets=[0, 1])
    assert result.notes == [note] and result.warnings == []
    assert [p.probability for p in result.curve] == [1.0, 1.0]
    document["deception"]["decoy"] = ["goal"]
    assert compile_problem(parse_spec(document)).notes == ()
    write_problem(problem, tmp_path / "p.yaml")
    for command in ("evaluate", "solve"):
        shown = runner.invoke(app, [command, str(tmp_path / "p.yaml"), "--json"])
        assert shown.exit_code == 0, shown.output
        assert json.loads(shown.stdout)["notes"] == [note]
    shown = runner.invoke(app, ["solve", str(tmp_path / "p.yaml")])
    assert shown.exit_code == 0 and "note: the initial state 'start' is a decoy" in shown.stderr
