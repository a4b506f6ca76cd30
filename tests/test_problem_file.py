"""Problem files: the issue's example loads as written, files round-trip, JSON equals YAML,
and the published JSON Schema is the one the loader enforces."""

import json
from pathlib import Path

import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from misdirect import decoy_probability, load_problem, write_problem
from misdirect.cli import app
from misdirect.io.problem_file import json_schema
from misdirect.scenarios import knapsack, paper_grid, random_problem

ROOT = Path(__file__).parents[1]
runner = CliRunner()


def same_model(a, b):
    assert a.pomdp.states == b.pomdp.states
    assert a.pomdp.actions == b.pomdp.actions
    assert a.pomdp.observations == b.pomdp.observations
    assert a.pomdp.initial_state == b.pomdp.initial_state
    assert np.array_equal(a.pomdp.observation_of, b.pomdp.observation_of)
    assert np.array_equal(a.pomdp.absorbing, b.pomdp.absorbing)
    assert abs(a.pomdp.transitions - b.pomdp.transitions).max() == 0
    assert np.array_equal(a.controller.action, b.controller.action)
    assert np.array_equal(a.controller.update, b.controller.update)
    assert np.array_equal(a.cost.matrix(), b.cost.matrix())
    assert np.array_equal(a.decoy, b.decoy)
    assert a.budget == b.budget


def test_issue_example_loads_as_written():
    problem = load_problem(ROOT / "examples" / "tiny.yaml")
    pomdp, ctrl = problem.pomdp, problem.controller
    assert pomdp.observations == ("o0", "o1", "o2", "g")
    assert problem.budget == 1
    o = {name: i for i, name in enumerate(pomdp.observations)}
    n = {name: i for i, name in enumerate(ctrl.nodes)}
    a = {name: i for i, name in enumerate(pomdp.actions)}
    # first matching rule wins: (n0, o2) -> (b, n1); everything else -> (a, n0)
    assert ctrl.action[n["n0"], o["o2"]] == a["b"] and ctrl.update[n["n0"], o["o2"]] == n["n1"]
    assert ctrl.action[n["n1"], o["o2"]] == a["a"] and ctrl.update[n["n1"], o["o2"]] == n["n0"]
    assert ctrl.action[n["n1"], o["o1"]] == a["a"] and ctrl.update[n["n1"], o["o1"]] == n["n0"]
    cost = problem.cost.matrix()
    assert cost[o["o1"], o["o2"]] == 3
    assert cost[o["o1"], o["o0"]] == 1
    assert np.isinf(cost[o["o2"], o["o0"]])
    assert np.isinf(cost[o["g"]][[o["o0"], o["o1"], o["o2"]]]).all()
    # absorbing states loop under every action
    goal = pomdp.states.index("goal")
    for action in range(pomdp.n_actions):
        assert pomdp.transition_matrix(action)[goal, goal] == 1.0


@pytest.mark.parametrize(
    "make",
    [
        lambda: paper_grid(5),
        lambda: knapsack([1, 2, 3], [4, 5, 6], 3),
        lambda: random_problem(5),
        lambda: random_problem(17, nodes=3),
    ],
)
@pytest.mark.parametrize("suffix", [".yaml", ".json"])
def test_round_trip(tmp_path, make, suffix):
    problem = make()
    path = tmp_path / f"p{suffix}"
    write_problem(problem, path)
    same_model(problem, load_problem(path))


def test_json_and_yaml_are_the_same_format(tmp_path):
    document = yaml.safe_load((ROOT / "examples" / "tiny.yaml").read_text())
    (tmp_path / "tiny.json").write_text(json.dumps(document))
    same_model(load_problem(ROOT / "examples" / "tiny.yaml"), load_problem(tmp_path / "tiny.json"))


def test_published_schema_is_current():
    published = json.loads((ROOT / "docs" / "problem-format.schema.json").read_text())
    assert published == json_schema(), (
        "regenerate: misdirect schema -o docs/problem-format.schema.json"
    )


def test_examples_validate_against_published_schema():
    jsonschema = pytest.importorskip("jsonschema")
    schema = json.loads((ROOT / "docs" / "problem-format.schema.json").read_text())
    for path in sorted((ROOT / "examples").glob("*.yaml")):
        jsonschema.validate(yaml.safe_load(path.read_text()), schema)


def test_scenario_command_writes_loadable_files(tmp_path):
    grid = tmp_path / "grid.yaml"
    result = runner.invoke(app, ["scenario", "paper-grid", "--size", "5", "-o", str(grid)])
    assert result.exit_code == 0, result.output
    problem = load_problem(grid)
    assert decoy_probability(problem, problem.alteration({"o1": "o3"})) == pytest.approx(
        0.719924, abs=5e-7
    )
    sack = tmp_path / "sack.json"
    result = runner.invoke(
        app,
        [
            "scenario",
            "knapsack",
            "--weights",
            "1,2,3,4,5",
            "--values",
            "20,30,40,50,60",
            "--capacity",
            "7",
            "-o",
            str(sack),
        ],
    )
    assert result.exit_code == 0, result.output
    result = runner.invoke(app, ["solve", str(sack), "--json"])
    assert json.loads(result.stdout)["value"] == pytest.approx(0.25)
    rand = tmp_path / "random.yaml"
    result = runner.invoke(app, ["scenario", "random", "--seed", "3", "-o", str(rand)])
    assert result.exit_code == 0, result.output
    same_model(random_problem(3), load_problem(rand))
