"""Scenario families with cycles (issue 27): the sensor grid whose goal is inside
(``sensor_grid(..., goal="inside")``, docs/sensor-grid.md "Robots that turn back") and the small
drone configurations shaped like PAYNT's drone benchmarks. What each promises, checked on the
arrays it builds, by hand where a value is needed, and against Storm's exact engine."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
from typer.testing import CliRunner

from misdirect import evaluate, load_problem
from misdirect.cli import app
from misdirect.core.attack import prepare
from misdirect.errors import ProblemError
from misdirect.scenarios import drone, sensor_grid
from prism_product import storm_probability

runner = CliRunner()
N, E, S, W = 0, 1, 2, 3  # action indices of the grid: N, E, S, W
STEP = {N: (0, 1), E: (1, 0), S: (0, -1), W: (-1, 0)}


def _cells_of(problem, sensor: int) -> np.ndarray:
    return np.flatnonzero(problem.pomdp.observation_of == sensor)


@pytest.mark.parametrize(("n", "k", "seed"), [(7, 5, 0), (10, 8, 1), (16, 24, 2)])
def test_what_the_inside_family_promises(n, k, seed):
    problem = sensor_grid(n, k, seed=seed, goal="inside")
    pomdp, controller = problem.pomdp, problem.controller
    obs = pomdp.observation_of
    assert pomdp.observations[:k] == tuple(f"s{i}" for i in range(k))
    assert pomdp.observations[k:] == ("b", "start") and obs[0] == k + 1
    centre = (n // 2) * n + n // 2
    decoy = int(np.flatnonzero(problem.decoy)[0])
    assert np.flatnonzero(pomdp.absorbing).tolist() == sorted([centre, decoy])
    assert obs[centre] == k and obs[decoy] == k  # goal and decoy read blank
    # a blank cell has no sensor to spoof: its reading cannot be altered; a sensor's can
    assert np.isinf(np.delete(problem.cost.row(k), k)).all()
    assert problem.cost.row(0)[k] == 1 and problem.cost.row(0)[1] == 1
    x, y = decoy % n, decoy // n
    assert n // 4 <= x <= n - 1 - n // 4 and n // 4 <= y <= n - 1 - n // 4
    cells = np.arange(n * n)
    cx, cy = cells % n, cells // n
    for edge in (cy == n - 1, cx == n - 1, cy == 0, cx == 0):  # a sensor on every edge
        assert (obs[edge] < k).any()
    # four memory nodes, one per heading N, E, S, W; a blank cell keeps node and heading
    assert controller.n_nodes == 4
    assert controller.action[:, k].tolist() == [N, E, S, W]
    assert controller.update[:, k].tolist() == [0, 1, 2, 3]
    # a sensor moves the memory to its own heading's node, whatever the node was
    for s in range(k):
        heading = controller.action[0, s]
        assert (controller.action[:, s] == heading).all()
        assert (controller.update[:, s] == heading).all()
    # the start (0, 0) sees the goal (n//2, n//2) as far East as North: a tie goes East
    assert (controller.action[:, k + 1] == E).all()


@pytest.mark.parametrize(("n", "k", "seed"), [(9, 8, 0), (12, 14, 3), (20, 40, 5)])
def test_every_sensor_points_towards_the_goal(n, k, seed):
    """From its blob's mean cell, one step of a sensor's heading shrinks the larger of the two
    distances to the goal (East/West when they are equal); computed here cell by cell."""
    problem = sensor_grid(n, k, seed=seed, goal="inside")
    goal = n // 2
    for s in range(k):
        mine = _cells_of(problem, s)
        mx, my = (mine % n).mean(), (mine // n).mean()
        dx, dy = goal - mx, goal - my
        heading = int(problem.controller.action[0, s])
        step_x, step_y = STEP[heading]
        if abs(dx) >= abs(dy):
            assert step_y == 0 and step_x * dx >= 0, (s, dx, dy, heading)
            assert abs(dx - step_x) < abs(dx) or dx == 0
        else:
            assert step_x == 0 and step_y * dy > 0, (s, dx, dy, heading)


def test_headings_by_hand():
    """Single-cell sensors of one layout, their headings worked out by hand (goal (4, 4))."""
    problem = sensor_grid(9, 8, seed=0, goal="inside")
    singles = {
        int(_cells_of(problem, s)[0]): int(problem.controller.action[0, s])
        for s in range(8)
        if _cells_of(problem, s).size == 1
    }
    assert singles, "the layout has no single-cell sensor to check"
    for cell, heading in singles.items():
        x, y = cell % 9, cell // 9
        # goal (4, 4): East/West when it is at least as far across as up or down, else N/S
        across, along = (E if x <= 4 else W), (N if y < 4 else S)
        expected = across if abs(4 - x) >= abs(4 - y) else along
        assert heading == expected, (x, y)


def test_more_memory_more_nodes_per_heading():
    problem = sensor_grid(10, 8, seed=1, goal="inside", memory=9)
    controller = problem.controller
    assert controller.n_nodes == 9
    assert controller.action[:, 8].tolist() == [N, E, S, W, N, E, S, W, N]  # node j: j mod 4
    for s in range(8):  # the node a sensor moves to has the sensor's heading
        assert controller.update[0, s] % 4 == controller.action[0, s]


@pytest.mark.parametrize(("n", "k", "seed"), [(6, 4, 0), (8, 6, 1), (10, 8, 2), (14, 20, 3)])
def test_cycles_in_the_attackers_product_and_none_without_attack(n, k, seed):
    problem = sensor_grid(n, k, seed=seed, goal="inside")
    assert prepare(problem, 2).cycling.any()
    report = evaluate(problem, problem.identity())
    goal, decoy = (
        f"({n // 2},{n // 2})",
        problem.pomdp.states[int(np.flatnonzero(problem.decoy)[0])],
    )
    assert set(report.outcomes) <= {goal, decoy}
    assert report.outcomes[goal] + report.outcomes[decoy] == pytest.approx(1.0, abs=1e-9)
    assert report.never_absorbed == pytest.approx(0.0, abs=1e-9)
    assert 0 < report.probability < 0.5


def test_blind_sensors_let_the_robot_wander_forever():
    """Every sensor altered to blank: the robot keeps its first heading (East), never turns
    West again once past the goal's column, and can slide along the right edge forever."""
    problem = sensor_grid(10, 8, seed=2, goal="inside")
    blank = problem.pomdp.observations.index("b")
    alteration = problem.identity()
    alteration[:8] = blank
    assert evaluate(problem, alteration).never_absorbed > 0.01


def test_goal_and_decoy_probabilities_agree_with_storm(tmp_path):
    """Storm's exact engine on its own PRISM product: Pr(F decoy) as ours, and Pr(F decoy)
    plus Pr(F goal) (the goal taken as the decoy) is 1: the unattacked chain is absorbed."""
    pytest.importorskip("stormpy")
    problem = sensor_grid(6, 4, seed=0, goal="inside")
    identity = problem.identity()
    decoy_storm = storm_probability(tmp_path, problem, identity)
    assert evaluate(problem, identity).probability == pytest.approx(decoy_storm, abs=1e-9)
    goal_mask = np.zeros_like(problem.decoy)
    goal_mask[3 * 6 + 3] = True
    as_goal = dataclasses.replace(problem, decoy=goal_mask)
    goal_storm = storm_probability(tmp_path, as_goal, identity)
    assert 0 < decoy_storm < 0.5
    assert decoy_storm + goal_storm == pytest.approx(1.0, abs=1e-12)


def test_same_seed_same_problem_other_seed_other_problem():
    one, two = (sensor_grid(12, 10, seed=5, goal="inside") for _ in range(2))
    other = sensor_grid(12, 10, seed=6, goal="inside")
    assert np.array_equal(one.pomdp.observation_of, two.pomdp.observation_of)
    assert np.array_equal(one.decoy, two.decoy)
    assert np.array_equal(one.controller.update, two.controller.update)
    assert np.array_equal(one.cost.matrix(), two.cost.matrix())
    assert not np.array_equal(one.pomdp.observation_of, other.pomdp.observation_of)


def test_the_corner_family_is_the_default():
    made = sensor_grid(10, 8, seed=3)
    corner = sensor_grid(10, 8, seed=3, goal="corner", memory=3)
    assert np.array_equal(made.pomdp.observation_of, corner.pomdp.observation_of)
    assert np.array_equal(made.controller.update, corner.controller.update)
    assert made.pomdp.absorbing[99] and made.controller.n_nodes == 3


@pytest.mark.parametrize(
    ("args", "field"),
    [
        (dict(goal="middle"), "goal"),
        (dict(goal="inside", memory=3), "memory"),
        (dict(goal="inside", sensors=3), "sensors"),
    ],
)
def test_bad_arguments(args, field):
    sensors = args.pop("sensors", 6)
    with pytest.raises(ProblemError) as raised:
        sensor_grid(8, sensors, **args)
    assert raised.value.field == field


def test_cli_writes_an_inside_grid_that_loads_to_the_same_problem(tmp_path):
    path = tmp_path / "turn.yaml"
    result = runner.invoke(
        app,
        [
            *("scenario", "sensor-grid", "--size", "9", "--sensors", "8", "--seed", "1"),
            *("--goal", "inside", "-o", str(path), "--json"),
        ],
    )
    assert result.exit_code == 0, result.output
    assert json.loads(result.stdout)["states"] == 81
    loaded, made = load_problem(path), sensor_grid(9, 8, seed=1, goal="inside")
    assert np.array_equal(loaded.pomdp.observation_of, made.pomdp.observation_of)
    assert np.array_equal(loaded.controller.action, made.controller.action)
    assert np.array_equal(loaded.controller.update, made.controller.update)
    assert np.array_equal(loaded.cost.matrix(), made.cost.matrix())  # b stays protected
    assert prepare(loaded, 2).cycling.any()
    assert evaluate(loaded).probability == pytest.approx(evaluate(made).probability, abs=1e-12)


def test_cli_names_the_flag_of_a_bad_goal_option(tmp_path):
    result = runner.invoke(
        app,
        [
            "scenario",
            "sensor-grid",
            "--goal",
            "inside",
            "--memory",
            "2",
            "-o",
            str(tmp_path / "x.yaml"),
        ],
    )
    assert result.exit_code == 2
    assert "--memory" in result.output and "Traceback" not in result.output


# -- the drone among patrolling agents: the C2 shape ----------------------------------------


@pytest.mark.parametrize(
    "kwargs", [dict(n=7, agents=2, rows=1), dict(n=8, agents=1, rows=2)], ids=["7-2-1", "8-1-2"]
)
def test_small_drones_have_the_shape_of_paynts_drone_benchmarks(kwargs):
    """1-3k product states, hundreds of observations that matter, end components."""
    problem = drone(**kwargs, budget=3)
    report = evaluate(problem)
    assert 1_000 <= report.product_states <= 3_000
    instance = prepare(problem, 3)
    assert (instance.live_states_per_observation > 0).sum() >= 100
    assert instance.cycling.any()
    assert problem.controller.n_nodes == 1  # memoryless, as PAYNT's drone controllers
    # the drone is absorbed (goal, pad or a crash) with probability 1 without attack
    assert report.never_absorbed == pytest.approx(0.0, abs=1e-9)
    assert sum(report.outcomes.values()) == pytest.approx(1.0, abs=1e-9)


def test_cli_writes_a_drone_that_loads(tmp_path):
    path = tmp_path / "drone.yaml"
    result = runner.invoke(
        app,
        [
            *("scenario", "drone", "--size", "5", "--agents", "1", "--rows", "2"),
            *("--budget", "3", "-o", str(path), "--json"),
        ],
    )
    assert result.exit_code == 0, result.output
    made = drone(5, agents=1, rows=2, budget=3)
    assert json.loads(result.stdout)["states"] == made.pomdp.n_states
    loaded = load_problem(path)
    assert loaded.budget == 3
    assert np.array_equal(loaded.controller.action, made.controller.action)
    assert evaluate(loaded).probability == pytest.approx(evaluate(made).probability, abs=1e-12)


@pytest.mark.parametrize(
    ("flags", "flag"),
    [
        (["--size", "3"], "--size"),
        (["--agents", "4"], "--agents"),
        (["--rows", "0"], "--rows"),
        (["--slip", "1.5"], "--slip"),
        (["--size", "12", "--agents", "3"], "--size"),  # too many states: refused up front
    ],
)
def test_drone_cli_refuses_bad_options_naming_the_flag(tmp_path, flags, flag):
    result = runner.invoke(app, ["scenario", "drone", *flags, "-o", str(tmp_path / "d.yaml")])
    assert result.exit_code == 2, result.output
    assert flag in result.output and "Traceback" not in result.output
    assert not (tmp_path / "d.yaml").exists()
