"""The sensor-grid family (docs/sensor-grid.md): what the generator promises, checked on the
arrays it builds, and every method against the exhaustive solver on small networks, with
uniform, random and partly forbidden costs."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
from typer.testing import CliRunner

from misdirect import decoy_probability, load_problem, solve
from misdirect.cli import app
from misdirect.core.model import CostModel
from misdirect.errors import ProblemError
from misdirect.scenarios import sensor_grid
from misdirect.solvers.incremental import NotApplicableError

runner = CliRunner()
E, N = 1, 0  # action indices of the paper grid: N, E, S, W


@pytest.mark.parametrize(("n", "k", "seed"), [(10, 8, 0), (20, 32, 1), (20, 128, 2)])
def test_what_the_generator_promises(n, k, seed):
    problem = sensor_grid(n, k, seed=seed)
    pomdp, controller = problem.pomdp, problem.controller
    obs = pomdp.observation_of
    names = pomdp.observations
    assert names[:k] == tuple(f"s{i}" for i in range(k)) and names[k:] == ("b", "start")
    sizes = np.bincount(obs[obs < k], minlength=k)
    assert sizes.min() >= 1 and sizes.max() <= 6  # every sensor covers 1..6 cells
    assert sizes.sum() <= 0.6 * (n * n - 2)
    assert obs[0] == k + 1 and (obs == k + 1).sum() == 1  # the start's own reading
    goal = n * n - 1
    decoy = int(np.flatnonzero(problem.decoy)[0])
    assert problem.decoy.sum() == 1 and pomdp.absorbing[[goal, decoy]].all()
    assert pomdp.absorbing.sum() == 2 and obs[decoy] == k  # the decoy is a blank cell
    x, y = decoy % n, decoy // n
    assert n // 4 <= x <= n - 1 - n // 4 and n // 4 <= y <= n - 1 - n // 4
    assert 0 < decoy_probability(problem, problem.identity()) < 0.5
    # the paper's controller, generalised (memory 3): direction by the blob's mean cell
    cells = np.arange(n * n)
    for s in range(k):
        mine = cells[obs == s]
        east = (mine % n).mean() <= (mine // n).mean()
        assert (controller.action[:, s] == (E if east else N)).all()
        assert (controller.update[:, s] == (1 if east else 2)).all()
    assert controller.action[:, k].tolist() == [E, E, N]  # blank: the node's heading
    assert controller.update[:, k].tolist() == [0, 1, 2]


def test_same_seed_same_problem_other_seed_other_problem():
    one, two, other = (
        sensor_grid(12, 10, seed=5),
        sensor_grid(12, 10, seed=5),
        sensor_grid(12, 10, seed=6),
    )
    assert np.array_equal(one.pomdp.observation_of, two.pomdp.observation_of)
    assert np.array_equal(one.decoy, two.decoy)
    assert np.array_equal(one.controller.update, two.controller.update)
    assert not np.array_equal(one.pomdp.observation_of, other.pomdp.observation_of)


def test_random_costs_are_per_sensor_from_one_to_three():
    problem = sensor_grid(12, 10, seed=3, costs="random")
    matrix = problem.cost.matrix()
    for s in range(10):
        row = np.delete(matrix[s], s)
        assert np.all(row == row[0]) and row[0] in (1.0, 2.0, 3.0)
    assert len({matrix[s, (s + 1) % 12] for s in range(10)}) > 1


def test_more_memory_more_behaviour_classes():
    three = sensor_grid(12, 10, seed=4, memory=3).controller
    five = sensor_grid(12, 10, seed=4, memory=5).controller
    heading = [E, E, N, E, N]  # node j >= 1: East when odd, North when even
    assert five.action[:, 10].tolist() == heading
    for s in range(10):  # a sensor's node has its direction
        assert heading[five.update[0, s]] == five.action[0, s]
    assert len(np.unique(five.behaviour_class)) > len(np.unique(three.behaviour_class))


@pytest.mark.parametrize(
    ("args", "field"),
    [
        (dict(n=4, sensors=3), "n"),
        (dict(n=6, sensors=0), "sensors"),
        (dict(n=6, sensors=100), "sensors"),
        (dict(n=6, sensors=3, memory=0), "memory"),
        (dict(n=6, sensors=3, costs="free"), "costs"),
    ],
)
def test_bad_arguments(args, field):
    """The library names its parameter; the CLI shows it as the flag (--size for n)."""
    n, sensors = args.pop("n"), args.pop("sensors")
    with pytest.raises(ProblemError) as raised:
        sensor_grid(n, sensors, **args)
    assert raised.value.field == field


def test_cli_writes_a_file_that_loads_to_the_same_problem(tmp_path):
    path = tmp_path / "net.yaml"
    result = runner.invoke(
        app,
        [
            "scenario",
            "sensor-grid",
            "--size",
            "10",
            "--sensors",
            "8",
            "--seed",
            "2",
            "--costs",
            "random",
            "-o",
            str(path),
            "--json",
        ],
    )
    assert result.exit_code == 0, result.output
    assert json.loads(result.stdout)["states"] == 100
    loaded, made = load_problem(path), sensor_grid(10, 8, seed=2, costs="random")
    assert np.array_equal(loaded.pomdp.observation_of, made.pomdp.observation_of)
    assert np.array_equal(loaded.cost.matrix(), made.cost.matrix())
    assert decoy_probability(loaded, loaded.identity()) == pytest.approx(
        decoy_probability(made, made.identity()), abs=1e-12
    )


def _with_forbidden_pairs(problem, seed):
    """Every fourth alteration pair forbidden (the generator itself has none)."""
    rng = np.random.default_rng(seed)
    matrix = problem.cost.matrix()
    n = matrix.shape[0]
    pairs = {
        (o, t): (np.inf if rng.random() < 0.25 else float(matrix[o, t]))
        for o in range(n)
        for t in range(n)
        if o != t
    }
    return dataclasses.replace(problem, cost=CostModel(n_observations=n, default=1.0, pairs=pairs))


SMALL = [  # n, k, seed, memory, costs, forbidden pairs, top budget
    (7, 5, 0, 3, "uniform", False, 3),
    (8, 6, 1, 3, "random", False, 3),
    (8, 7, 2, 4, "uniform", True, 3),
    (9, 8, 3, 3, "random", True, 3),
    (7, 5, 4, 5, "uniform", False, 2),
]


@pytest.mark.parametrize(("n", "k", "seed", "memory", "costs", "forbid", "top"), SMALL)
def test_every_method_agrees_with_exhaustive(n, k, seed, memory, costs, forbid, top):
    problem = sensor_grid(n, k, seed=seed, memory=memory, costs=costs)
    if forbid:
        problem = _with_forbidden_pairs(problem, seed)
    budgets = list(range(top + 1))
    oracle = solve(problem, method="exhaustive", budgets=budgets)
    assert oracle.curve[-1].probability > oracle.baseline_probability + 1e-6  # not trivial
    methods = ["auto", "branch-and-bound", "milp", "incremental"]
    for method in methods:
        try:
            result = solve(problem, method=method, budgets=budgets)
        except NotApplicableError:
            continue
        assert not result.warnings, (method, result.warnings)
        for mine, best in zip(result.curve, oracle.curve, strict=True):
            where = (method, n, k, seed, mine.budget)
            assert mine.status == "optimal", where
            assert mine.probability == pytest.approx(best.probability, abs=1e-9), where
            assert mine.upper_bound - mine.probability <= 1e-9 + 1e-12, where
            assert mine.cost <= mine.budget, where
