"""PRISM first (issue 53): a PRISM or DRN model on the command line, without a problem file.

``misdirect evaluate model.prism --controller c.fsc.json --decoy bad ...`` must build the
problem the equivalent problem file builds: each test writes that file by hand (not with
``convert``) and compares the two routes' values and answers. Values are also checked
against Storm: the flag route's ``export-chain`` model checked by stormpy, and an
independently written PRISM product (tests/prism_product.py) built and checked by Storm in
exact arithmetic. The models and controllers are our own (tests/data, examples).
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml
from typer.testing import CliRunner

from misdirect import evaluate, load_problem, write_problem
from misdirect.cli import app
from misdirect.errors import ProblemError
from misdirect.io.model_problem import problem_from_model, with_controller
from misdirect.io.paynt import controller_to_paynt
from misdirect.scenarios import paper_grid
from result_schema import checked

stormpy = pytest.importorskip("stormpy")
from prism_product import storm_probability  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "tests" / "data"
MAZE = DATA / "maze.prism"
MAZE_FSC = DATA / "maze.fsc.json"
GRID = DATA / "grid_avoid.prism"
PAYNT_PROPERTY = 'Pmax=? [F "goal"]'
# the maze at c=2 reads "east-west" and at c=4 "east-west-south": node 0 walks into the dead
# end c=10 (tests/test_storm_terminal.py, by hand): 1 instead of 0
MAZE_CHANGES = {"clk=0,!n,e,s,w": "clk=0,!n,e,!s,w", "clk=0,!n,!e,s,w": "clk=0,!n,e,s,w"}
MAZE_ALTER = [f"{o}={t}" for o, t in MAZE_CHANGES.items()]
runner = CliRunner()

# grid_avoid at N=3 (cells x 0..2, rows y 0..2, the trap "bad" at (1, 1)): start, then north
# until the top row, then east. Starting at x=1 the first north step enters the trap (0.8).
GRID_OBS_START = "!started,y=0,!wall,!crashed"
GRID_OBS_TOP = "started,y=2,!wall,!crashed"
GRID_RULES = {
    "nodes": ["m"],
    "initial": "m",
    "rules": [
        {"node": "*", "obs": GRID_OBS_START, "action": "__NOLABEL__", "next": "m"},
        {"node": "*", "obs": GRID_OBS_TOP, "action": "east", "next": "m"},
        {"node": "*", "obs": "*", "action": "north", "next": "m"},
    ],
}


def _run(*args: object):
    return runner.invoke(app, [str(a) for a in args])


def _json(*args: object) -> dict:
    result = _run(*args, "--json")
    assert result.exit_code == 0, result.output
    return checked(result.stdout)


def _write_yaml(path: Path, document: dict) -> Path:
    path.write_text(yaml.safe_dump(document, sort_keys=False))
    return path


def _maze_yaml(tmp_path: Path, budget: float = 2) -> Path:
    """The problem file the maze flags below stand for, written by hand."""
    return _write_yaml(
        tmp_path / "maze.yaml",
        {
            "format": "misdirect/v1",
            "pomdp": {"prism": str(MAZE), "terminal_from": PAYNT_PROPERTY},
            "controller": {"paynt": str(MAZE_FSC)},
            "deception": {"decoy": {"label": "bad"}, "budget": budget},
        },
    )


MAZE_FLAGS = ["--controller", MAZE_FSC, "--decoy", "bad", "--terminal-from", PAYNT_PROPERTY]


def _grid_files(tmp_path: Path) -> tuple[Path, Path]:
    controller = _write_yaml(tmp_path / "grid-controller.yaml", GRID_RULES)
    problem = _write_yaml(
        tmp_path / "grid.yaml",
        {
            "format": "misdirect/v1",
            "pomdp": {"prism": str(GRID), "constants": "N=3", "terminal": "goal"},
            "controller": GRID_RULES,
            "deception": {"decoy": {"expression": "x = 1 & y = 1"}, "budget": 1},
        },
    )
    return controller, problem


def _grid_flags(controller: Path) -> list[object]:
    return [
        *("--controller", controller, "--decoy", "x = 1 & y = 1"),
        *("--constants", "N=3", "--goal", "goal"),
    ]


def _storm_chain_value(tmp_path: Path, *args: object) -> tuple[float, float]:
    """export-chain's value and Storm's check of the chain it wrote."""
    chain = tmp_path / "chain.drn"
    payload = _json("export-chain", *args, "-o", chain)
    model = stormpy.build_model_from_drn(str(chain))
    formula = stormpy.parse_properties('P=? [F "decoy"]')[0]
    storm = stormpy.model_checking(model, formula).get_value(model.initial_states[0])
    return payload["value"], storm


# -- the flag route is the problem file's route ------------------------------------------------


def test_maze_evaluate_flags_equal_yaml_and_storm(tmp_path):
    alters = [arg for pair in MAZE_ALTER for arg in ("--alter", pair)]
    by_flags = _json("evaluate", MAZE, *MAZE_FLAGS, *alters)
    by_file = _json("evaluate", _maze_yaml(tmp_path), *alters)
    assert by_flags["value"] == by_file["value"]
    assert by_flags["value"] == pytest.approx(1.0, abs=1e-9)  # by hand, see MAZE_ALTER
    assert by_flags["baseline_value"] == by_file["baseline_value"]
    value, storm = _storm_chain_value(tmp_path, MAZE, *MAZE_FLAGS, *alters)
    assert value == pytest.approx(by_flags["value"], abs=1e-12)
    assert storm == pytest.approx(value, abs=1e-9)


def test_maze_solve_flags_equal_yaml(tmp_path):
    by_flags = _json("solve", MAZE, *MAZE_FLAGS, "--budget", "2")
    by_file = _json("solve", _maze_yaml(tmp_path))
    assert by_flags["status"] == by_file["status"] == "optimal"
    assert by_flags["value"] == by_file["value"]
    assert by_flags["alteration"] == by_file["alteration"]
    assert by_flags["value"] == pytest.approx(1.0, abs=1e-9)


def test_constants_and_goal_flags_equal_yaml_and_exact_storm(tmp_path):
    """grid_avoid (const int N) with a controller of rules, a decoy expression and a goal."""
    controller, problem_file = _grid_files(tmp_path)
    flags = _grid_flags(controller)
    assert _json("evaluate", GRID, *flags)["value"] == pytest.approx(
        _json("evaluate", problem_file)["value"], abs=0
    )
    by_flags = _json("solve", GRID, *flags, "--budget", "1")
    by_file = _json("solve", problem_file)
    assert (by_flags["value"], by_flags["alteration"]) == (by_file["value"], by_file["alteration"])
    baseline = by_flags["baseline_value"]
    # by hand: from (1,0) the first north step enters the trap (0.8), slips east out of its
    # column (0.1) or stays to try again (0.1): 8/9. From (0,0): north to (0,1) (0.8) or a
    # slip to (1,0) (0.1), and from (0,1) a slip east into the trap (0.1) before the top row
    # (0.8): 1/9; so (0.8/9 + 0.1 * 8/9) / 0.9 = 16/81. Each start is equally likely: 44/81
    assert baseline == pytest.approx(44 / 81, abs=1e-12)
    assert by_flags["value"] > baseline  # an alteration helps
    problem = problem_from_model(
        GRID, controller=controller, decoy="x = 1 & y = 1", constants="N=3", goal="goal"
    )
    alteration = problem.alteration(by_flags["alteration"])
    exact = storm_probability(tmp_path, problem, alteration)
    assert exact == pytest.approx(by_flags["value"], abs=1e-9)
    value, storm = _storm_chain_value(
        tmp_path,
        GRID,
        *flags,
        *[a for o, t in by_flags["alteration"].items() for a in ("--alter", f"{o}={t}")],
    )
    assert storm == pytest.approx(value, abs=1e-9)
    assert value == pytest.approx(by_flags["value"], abs=1e-12)


def test_drn_model_with_the_controller_of_a_problem_file(tmp_path):
    """A DRN file (the trap corridor, written by convert) with the trap's own controller:
    the trap's values by hand, 0.1 unaltered and 0.4 with o1 -> o0."""
    trap = ROOT / "examples" / "trap.yaml"
    drn = tmp_path / "trap.drn"
    assert _run("convert", trap, "--to", "drn", "-o", drn).exit_code == 0
    flags = ["--controller", trap, "--decoy", "decoy"]
    assert _json("evaluate", drn, *flags)["value"] == pytest.approx(0.1, abs=1e-12)
    altered = _json("evaluate", drn, *flags, "--alter", "o1=o0")
    assert altered["value"] == pytest.approx(0.4, abs=1e-12)
    solved = _json("solve", drn, *flags, "--budget", "1")
    assert solved["alteration"] == {"o1": "o0"}
    assert solved["value"] == pytest.approx(0.4, abs=1e-12)


def test_a_drn_model_takes_a_step_bounded_property(tmp_path):
    """The trap corridor's decoy is first reached at step 2 (start -> exit -> decoy, 0.4 x
    0.25; with o1 -> o0 also start -> loop -> decoy, 0.6 x 0.5), never sooner: by hand,
    F<=1 is 0 whatever the alteration and F<=2 is the unbounded 0.1, or 0.4 altered."""
    trap = ROOT / "examples" / "trap.yaml"
    drn = tmp_path / "trap.drn"
    assert _run("convert", trap, "--to", "drn", "-o", drn).exit_code == 0
    flags = ["--controller", trap, "--decoy", "decoy", "--budget", "1"]
    within_one = _json("solve", drn, *flags, "--property", 'P=? [F<=1 "decoy"]')
    assert within_one["value"] == pytest.approx(0.0, abs=1e-12)
    within_two = _json("solve", drn, *flags, "--property", 'P=? [F<=2 "decoy"]')
    assert within_two["alteration"] == {"o1": "o0"}
    assert within_two["value"] == pytest.approx(0.4, abs=1e-12)
    plain = _json("evaluate", drn, *flags[:4], "--property", 'P=? [F<=2 "decoy"]')
    assert plain["value"] == pytest.approx(0.1, abs=1e-12)


@pytest.mark.parametrize("command", ["audit", "harden", "simulate", "show"])
def test_every_problem_command_takes_the_model(tmp_path, command):
    extra = {
        "audit": ["--budget", "1"],
        "harden": ["--budget", "1", "--protect-budget", "1"],
        "simulate": ["--runs", "200"],
        "show": ["-o", tmp_path / "chain.dot"],
    }[command]
    result = _run(command, MAZE, *MAZE_FLAGS, *extra, "--json")
    assert result.exit_code == 0, result.output
    assert checked(result.stdout)["command"] == command


def test_library_route_equals_load_problem(tmp_path):
    by_flags = problem_from_model(
        MAZE, controller=MAZE_FSC, decoy="bad", terminal_from=PAYNT_PROPERTY, budget=2
    )
    by_file = load_problem(_maze_yaml(tmp_path))
    assert by_flags.pomdp.observations == by_file.pomdp.observations
    assert by_flags.budget == by_file.budget == 2
    values = [evaluate(p, p.alteration(MAZE_CHANGES)).probability for p in (by_flags, by_file)]
    assert values[0] == values[1] == pytest.approx(1.0, abs=1e-9)


# -- --controller replaces any problem's controller --------------------------------------------


def _other_grid_controller(tmp_path: Path) -> Path:
    """The paper grid's controller with east instead of its own action at sensor o2."""
    problem = paper_grid(5)
    document = controller_to_paynt(problem.controller, problem.pomdp)
    column = document["observation_labels"].index("o2")
    east = document["action_labels"].index("E")
    for row in document["action_function"]:
        row[column] = east
    path = tmp_path / "mine.fsc.json"
    path.write_text(json.dumps(document))
    return path


def test_controller_flag_on_a_scenario_equals_yaml_with_that_controller(tmp_path):
    mine = _other_grid_controller(tmp_path)
    grid_file = tmp_path / "grid.yaml"
    write_problem(paper_grid(5, budget=2), grid_file)
    explicit = yaml.safe_load(grid_file.read_text())
    explicit["controller"] = {"paynt": str(mine)}
    with_mine = _write_yaml(tmp_path / "with-mine.yaml", explicit)

    by_flag = _json("solve", "--scenario", "paper-grid", "--controller", mine, "--budget", "2")
    by_file = _json("solve", with_mine)
    own = _json("solve", "--scenario", "paper-grid", "--budget", "2")
    assert (by_flag["value"], by_flag["alteration"]) == (by_file["value"], by_file["alteration"])
    assert by_flag["baseline_value"] == by_file["baseline_value"]
    assert by_flag["value"] != pytest.approx(own["value"], abs=1e-6)  # another robot
    # and on the problem file of the scenario: its own controller replaced
    on_file = _json("solve", grid_file, "--controller", mine)
    assert (on_file["value"], on_file["alteration"]) == (by_file["value"], by_file["alteration"])


def test_controller_flag_on_a_problem_file_with_rules(tmp_path):
    """trap.yaml whose robot always plays go: from the loop half the runs end in the decoy
    unaltered (0.6 * 0.5 = 0.3), from the exit none."""
    rules = {
        "nodes": ["m"],
        "initial": "m",
        "rules": [{"node": "*", "obs": "*", "action": "go", "next": "m"}],
    }
    controller = _write_yaml(tmp_path / "go.yaml", rules)
    trap = ROOT / "examples" / "trap.yaml"
    value = _json("evaluate", trap, "--controller", controller)["value"]
    assert value == pytest.approx(0.3, abs=1e-12)
    inline = yaml.safe_load(trap.read_text()) | {"controller": rules}
    by_file = _json("evaluate", _write_yaml(tmp_path / "go-trap.yaml", inline))
    assert by_file["value"] == value
    problem = with_controller(load_problem(trap), controller)
    assert evaluate(problem).probability == value


# -- convert writes the problem file of the flags ----------------------------------------------


def test_convert_writes_the_problem_file_of_the_flags(tmp_path):
    out = tmp_path / "sub" / "maze.yaml"
    out.parent.mkdir()
    result = _run("convert", MAZE, *MAZE_FLAGS, "--budget", "2", "-o", out)
    assert result.exit_code == 0, result.output
    document = yaml.safe_load(out.read_text())
    assert set(document["pomdp"]) == {"prism", "terminal_from"}
    assert document["pomdp"]["terminal_from"] == PAYNT_PROPERTY
    assert not Path(document["pomdp"]["prism"]).is_absolute()  # relative to the file
    assert (out.parent / document["pomdp"]["prism"]).resolve() == MAZE.resolve()
    assert (out.parent / document["controller"]["paynt"]).resolve() == MAZE_FSC.resolve()
    assert document["deception"] == {"decoy": {"label": "bad"}, "budget": 2.0}
    by_flags = _json("solve", MAZE, *MAZE_FLAGS, "--budget", "2")
    by_file = _json("solve", out)
    assert (by_flags["value"], by_flags["alteration"]) == (by_file["value"], by_file["alteration"])


def test_convert_expression_decoy_and_json(tmp_path):
    out = tmp_path / "maze.json"
    flags = ["--controller", MAZE_FSC, "--decoy", "c = 8 | c = 10", "--goal", '"goal"']
    assert _run("convert", MAZE, *flags, "-o", out).exit_code == 0
    document = json.loads(out.read_text())
    assert document["deception"] == {"decoy": {"expression": "c = 8 | c = 10"}}
    assert document["pomdp"]["terminal"] == '"goal"'
    assert (
        load_problem(out).decoy.sum()
        == problem_from_model(MAZE, controller=MAZE_FSC, decoy="bad", goal="goal").decoy.sum()
    )


# -- errors ------------------------------------------------------------------------------------


def _error(*args: object) -> dict:
    result = _run(*args, "--json")
    assert result.exit_code == 2, result.output
    return checked(result.stdout)["error"]


def test_model_without_decoy_names_the_missing_flags():
    result = _run("evaluate", MAZE)
    assert result.exit_code == 2
    assert "--decoy: is required with the PRISM model" in result.output
    assert "--controller: is required" in result.output
    assert "invalid YAML" not in result.output
    error = _error("solve", MAZE, "--controller", MAZE_FSC)
    assert error["source"] == "--decoy" and "is required" in error["message"]


def test_unknown_label_names_the_decoy_flag():
    error = _error("evaluate", MAZE, "--controller", MAZE_FSC, "--decoy", "nosuch")
    assert error["source"] == "--decoy"
    assert "no state label 'nosuch'" in error["message"] and "bad" in error["message"]
    error = _error("evaluate", MAZE, "--controller", MAZE_FSC, "--decoy", "c = 99")
    assert error["source"] == "--decoy" and "no state satisfies" in error["message"]


@pytest.mark.parametrize("constants", ["N5", "M=3", "N=x"])
def test_bad_constants_name_the_flag(tmp_path, constants):
    controller, _ = _grid_files(tmp_path)
    args = ["--controller", controller, "--decoy", "bad", "--constants", constants]
    error = _error("evaluate", GRID, *args)
    assert error["source"] == "--constants", error
    assert error["message"].startswith("--constants: ")


def test_missing_constants_name_the_flag(tmp_path):
    controller, _ = _grid_files(tmp_path)
    error = _error("evaluate", GRID, "--controller", controller, "--decoy", "bad")
    assert error["source"] == "--constants" and "N" in error["message"]


def test_bad_goal_and_property_name_their_flags():
    error = _error("evaluate", MAZE, "--controller", MAZE_FSC, "--decoy", "bad", "--goal", "nope")
    assert error["source"] == "--goal", error
    error = _error(
        "evaluate", MAZE, "--controller", MAZE_FSC, "--decoy", "bad", "--terminal-from", "P=? [F"
    )
    assert error["source"] == "--terminal-from", error


def test_missing_controller_file_names_the_flag(tmp_path):
    missing = tmp_path / "none.fsc.json"
    error = _error("evaluate", MAZE, "--controller", missing, "--decoy", "bad")
    assert error["source"] == "--controller" and "not found" in error["message"]
    error = _error("evaluate", "--scenario", "paper-grid", "--controller", missing)
    assert error["source"] == "--controller" and "not found" in error["message"]


def test_model_flags_refused_with_a_problem_file_or_scenario():
    error = _error("evaluate", ROOT / "examples" / "trap.yaml", "--decoy", "goal")
    assert error["source"] == "--decoy" and "PRISM or DRN model" in error["message"]
    error = _error("evaluate", "--scenario", "paper-grid", "--constants", "N=3")
    assert error["source"] == "--constants"


def test_load_problem_of_a_prism_file_says_what_it_is():
    with pytest.raises(ProblemError, match="a PRISM program, not a misdirect/v1 problem file"):
        load_problem(MAZE)


def test_prism_text_under_another_name_is_recognised(tmp_path):
    """A PAYNT sketch is often named sketch.templ; any unknown suffix is read by content."""
    copy = tmp_path / "sketch.txt"
    copy.write_text(MAZE.read_text())
    with pytest.raises(ProblemError, match="a PRISM program"):
        load_problem(copy)
    assert _json("evaluate", copy, *MAZE_FLAGS)["value"] == pytest.approx(0.0, abs=1e-12)


def test_exact_on_the_flag_route(tmp_path):
    """--exact rebuilds the model with the flags' settings: geo's controller reaches the bad
    end with probability 1/2 exactly (the target is at either end, equally likely)."""
    geo = ["--controller", DATA / "geo.fsc.json", "--decoy", "bad", "--goal", "goal"]
    payload = _json("evaluate", DATA / "geo.prism", *geo, "--exact")
    assert payload["exact"]["value"] == "1/2"
    assert payload["value"] == pytest.approx(0.5, abs=1e-12)
