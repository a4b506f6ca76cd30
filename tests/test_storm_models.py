"""Models from Storm (PRISM, DRN), PAYNT controllers, and writing models back out for Storm.

The maze and the 3x3 grid are the POMDPs stormpy ships as examples; the probabilities below
are worked out by hand from the PRISM source (comments), and DRN and PRISM are read through two
different Storm paths that must agree.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from misdirect import decoy_probability, load_problem
from misdirect.cli import app

stormpy = pytest.importorskip("stormpy")
SHIPPED = Path(stormpy.__file__).parent / "examples" / "files" / "pomdp"
EXAMPLES = Path(__file__).parent.parent / "examples"
runner = CliRunner()

SOUTH_CONTROLLER = {
    "nodes": ["m"],
    "initial": "m",
    "rules": [
        {"node": "*", "obs": "o=0", "action": "__NOLABEL__", "next": "m"},
        {"node": "*", "obs": "o=7", "action": "done", "next": "m"},
        {"node": "*", "obs": "*", "action": "south", "next": "m"},
    ],
}


def _problem_file(tmp_path, pomdp, controller, decoy, budget=1, name="p.yaml"):
    document = {
        "format": "misdirect/v1",
        "pomdp": pomdp,
        "controller": controller,
        "deception": {"decoy": decoy, "budget": budget},
    }
    path = tmp_path / name
    path.write_text(yaml.safe_dump(document, sort_keys=False))
    return path


def test_maze_by_hand(tmp_path):
    """Always south: from the 13 equally likely starts, only s=2, 6, 9 run down into the
    target s=13 (2->6->9->13); every other column ends against a wall. So 3/13."""
    path = _problem_file(
        tmp_path, {"prism": str(SHIPPED / "maze_2.prism")}, SOUTH_CONTROLLER, {"label": "goal"}
    )
    problem = load_problem(path)
    assert problem.pomdp.n_states == 15
    assert decoy_probability(problem, problem.identity()) == pytest.approx(3 / 13, abs=1e-12)
    # reading the target's o=7 everywhere makes the robot play `done`, which Storm enables
    # only at the target: by default (`stay`) it then never moves, so 0
    alpha = problem.alteration(
        {"o=5": "o=7", "o=1": "o=7", "o=2": "o=7", "o=3": "o=7", "o=4": "o=7", "o=6": "o=7"}
    )
    assert decoy_probability(problem, alpha) == pytest.approx(0.0, abs=1e-12)


def test_prism_and_drn_of_the_maze_agree():
    from misdirect.io.storm import load_storm_pomdp

    prism = load_storm_pomdp(SHIPPED / "maze_2.prism", kind="prism").pomdp
    drn = load_storm_pomdp(SHIPPED / "maze.drn", kind="drn").pomdp
    assert prism.actions == drn.actions
    assert np.array_equal(prism.observation_of, drn.observation_of)
    assert abs(prism.transitions - drn.transitions).max() < 1e-9


def test_disabled_actions_stay_or_forbid(tmp_path):
    """3x3 grid: 'done' is enabled only at the target (o=2). Reading o=1 as o=2 makes the
    robot play 'done' in the grid: with `stay` it stays put, with `forbid` that alteration is
    not allowed."""
    controller = {
        "nodes": ["m"],
        "initial": "m",
        "rules": [
            {"node": "*", "obs": "o=0", "action": "__NOLABEL__", "next": "m"},
            {"node": "*", "obs": "o=2", "action": "done", "next": "m"},
            {"node": "*", "obs": "*", "action": "east", "next": "m"},
        ],
    }
    grid = str(SHIPPED / "3x3grid.prism")
    stay = load_problem(_problem_file(tmp_path, {"prism": grid}, controller, {"label": "goal"}))
    o1, o2 = stay.pomdp.observations.index("o=1"), stay.pomdp.observations.index("o=2")
    assert np.isfinite(stay.cost.row(o1)[o2])
    # east forever: the target (2,0) is reached only from the bottom row starts (0,0), (1,0):
    # 2 of the 8 equally likely starts
    assert decoy_probability(stay, stay.identity()) == pytest.approx(2 / 8, abs=1e-12)
    altered = stay.identity()
    altered[o1] = o2  # the robot now "finishes" everywhere and never moves
    assert decoy_probability(stay, altered) == pytest.approx(0.0, abs=1e-12)

    forbid = load_problem(
        _problem_file(
            tmp_path,
            {"prism": grid, "disabled_action": "forbid"},
            controller,
            {"label": "goal"},
            name="f.yaml",
        )
    )
    assert not np.isfinite(forbid.cost.row(o1)[o2])


def test_paynt_controller_round_trip(tmp_path):
    source = _problem_file(
        tmp_path, {"prism": str(SHIPPED / "maze_2.prism")}, SOUTH_CONTROLLER, {"label": "goal"}
    )
    fsc = tmp_path / "robot.fsc.json"
    result = runner.invoke(app, ["export-fsc", str(source), "-o", str(fsc)])
    assert result.exit_code == 0, result.output
    exported = json.loads(fsc.read_text())
    assert exported["action_labels"][exported["action_function"][0][0]] in (
        "south",
        "done",
        "__NOLABEL__",
    )
    # PAYNT writes observation labels as Storm valuations: "[o=3]"
    exported["observation_labels"] = [f"[{name}]" for name in exported["observation_labels"]]
    fsc.write_text(json.dumps(exported))
    again = load_problem(
        _problem_file(
            tmp_path,
            {"prism": str(SHIPPED / "maze_2.prism")},
            {"paynt": "robot.fsc.json"},
            {"label": "goal"},
            name="q.yaml",
        )
    )
    original = load_problem(source)
    assert np.array_equal(again.controller.action, original.controller.action)
    assert np.array_equal(again.controller.update, original.controller.update)


@pytest.mark.parametrize("target", ["prism", "drn"])
def test_convert_round_trip_through_storm(tmp_path, target):
    """Our model written out, read back by Storm, evaluates to the same probabilities."""
    out = tmp_path / f"trap.{target}"
    result = runner.invoke(
        app, ["convert", str(EXAMPLES / "trap.yaml"), "--to", target, "-o", str(out)]
    )
    assert result.exit_code == 0, result.output
    original = load_problem(EXAMPLES / "trap.yaml")
    names = dict(enumerate(original.pomdp.observations))
    # the file's header keeps our names, which Storm alone would give back as o=k / obs<k>
    obs_name = original.pomdp.observations.__getitem__
    rules = []
    for k, name in names.items():
        o = original.pomdp.observations.index(name)
        rules.append(
            {
                "node": "*",
                "obs": obs_name(k),
                "action": original.pomdp.actions[original.controller.action[0, o]],
                "next": "m",
            }
        )
    path = _problem_file(
        tmp_path,
        {target: out.name},
        {"nodes": ["m"], "initial": "m", "rules": rules},
        {"label": "decoy"},
    )
    back = load_problem(path)
    for change in ({}, {"o1": "o0"}):
        alpha = original.alteration(change)
        mapped = back.identity()
        for o, t in enumerate(alpha):
            mapped[back.pomdp.observations.index(obs_name(o))] = back.pomdp.observations.index(
                obs_name(int(t))
            )
        assert decoy_probability(back, mapped) == pytest.approx(
            decoy_probability(original, alpha), abs=1e-12
        )


@pytest.mark.parametrize(
    ("pomdp", "decoy", "field", "words"),
    [
        (
            {"prism": "broken.prism"},
            {"label": "goal"},
            "pomdp.prism, line 4, column 13",
            "expecting <update list>",
        ),
        ({"prism": "missing.prism"}, {"label": "goal"}, "pomdp.prism", "not found"),
        (
            {"prism": str(SHIPPED / "maze_2.prism")},
            {"label": "lava"},
            "deception.decoy.label",
            "no state label 'lava'",
        ),
        (
            {"prism": str(SHIPPED / "maze_2.prism"), "constnats": "N=1"},
            {"label": "goal"},
            "pomdp.constnats",
            "unknown field",
        ),
        (
            {"prism": str(SHIPPED / "maze_2.prism")},
            {"lable": "goal"},
            "deception.decoy.label",
            "Field required",
        ),
        (
            {"prism": str(SHIPPED / "maze_2_par.prism")},
            {"label": "goal"},
            "pomdp.constants",
            "constants without a value",
        ),
    ],
)
def test_storm_errors(tmp_path, pomdp, decoy, field, words):
    (tmp_path / "broken.prism").write_text(
        "pomdp\nmodule m\n  x : [0..1] init 0;\n  [a] x=0 -> ;\nendmodule\n"
    )
    path = _problem_file(tmp_path, pomdp, SOUTH_CONTROLLER, decoy)
    result = runner.invoke(app, ["evaluate", str(path), "--json"])
    assert result.exit_code == 2, result.output
    error = json.loads(result.stdout)["error"]
    assert error["field"] == field
    assert words in error["message"]


# -- PRISM constants -------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("model", "constants", "words"),
    [
        ("maze_2.prism", "N=5", "unknown undefined constant 'N'"),
        ("maze_2_par.prism", "i5", "syntax error"),
        ("maze_2_par.prism", "i=abc", "'abc'"),
        ("maze_2_par.prism", "N=5", "constants to set: i"),
    ],
)
def test_bad_constants_name_pomdp_constants(tmp_path, model, constants, words):
    path = _problem_file(
        tmp_path,
        {"prism": str(SHIPPED / model), "constants": constants},
        SOUTH_CONTROLLER,
        {"label": "goal"},
    )
    result = runner.invoke(app, ["evaluate", str(path), "--json"])
    assert result.exit_code == 2, result.output
    error = json.loads(result.stdout)["error"]
    assert error["field"] == "pomdp.constants"
    assert words in error["message"]
    assert "\n" not in error["message"]


# -- PAYNT controllers of a model with two observable variables -------------------------------

TWO_VARIABLES = """\
pomdp

observables x, y endobservables

module robot
  x : [0..2] init 0;
  y : [0..1] init 0;
  [east]  x<2 & y=0 -> 0.8 : (x'=x+1) + 0.2 : (y'=1);
  [north] x<2 & y=0 -> (y'=1);
  [stop]  x=2 | y=1 -> true;
endmodule

label "bad" = y=1;
"""


def test_paynt_labels_of_two_observable_variables(tmp_path):
    """Storm names the observation (x=1, y=0) `[x=1\\t& y=0]`, and so does PAYNT; it must
    match our observation `x=1,y=0`.

    Robot: east while y=0 (0.8 ahead, 0.2 up into y=1, the decoy `bad`), stop at x=2 (goal).
    By hand: Pr(bad) = 0.2 + 0.8 * 0.2 = 0.36. Reading (1,0) as (1,1) makes it play `north`
    there (the controller's choice for (1,1)): 0.2 + 0.8 * 1 = 1. Reading (1,0) as (0,1) makes
    it play `stop`, not enabled at (1,0): it stays there forever (`stay`), so 0.2."""
    (tmp_path / "two.prism").write_text(TWO_VARIABLES)
    storm = "[x={}\t& y={}]"
    chosen = {(0, 0): "east", (1, 0): "east", (2, 0): "stop", (0, 1): "stop", (1, 1): "north"}
    cells = [(1, 1), (2, 0), (0, 0), (0, 1), (1, 0)]  # not in Storm's order: matched by name
    labels = ["north", "stop", "east"]
    fsc = {
        "num_nodes": 1,
        "num_observations": len(cells),
        "action_function": [[labels.index(chosen[c]) for c in cells]],
        "update_function": [[0] * len(cells)],
        "action_labels": labels,
        "observation_labels": [storm.format(*c) for c in cells],
    }
    (tmp_path / "robot.fsc.json").write_text(json.dumps(fsc))
    problem = load_problem(
        _problem_file(
            tmp_path,
            {"prism": "two.prism"},
            {"paynt": "robot.fsc.json"},
            {"label": "bad"},
        )
    )
    pomdp = problem.pomdp
    assert sorted(pomdp.observations) == sorted(f"x={x},y={y}" for x, y in cells)
    for cell, action in chosen.items():
        o = pomdp.observations.index("x={},y={}".format(*cell))
        assert pomdp.actions[problem.controller.action[0, o]] == action
    assert decoy_probability(problem, problem.identity()) == pytest.approx(0.36, abs=1e-12)
    up = problem.alteration({"x=1,y=0": "x=1,y=1"})
    assert decoy_probability(problem, up) == pytest.approx(1.0, abs=1e-12)
    stuck = problem.alteration({"x=1,y=0": "x=0,y=1"})
    assert decoy_probability(problem, stuck) == pytest.approx(0.2, abs=1e-12)


# -- disabled_action: stay vs forbid ----------------------------------------------------------

FORK = """\
pomdp

observables o endobservables

module fork
  s : [0..4] init 0;
  o : [0..3] init 0;
  [go] s=0 -> 0.6 : (s'=1) & (o'=1) + 0.4 : (s'=2) & (o'=2);
  [a]  s=1 -> (s'=3) & (o'=3);
  [b]  s=1 -> (s'=4) & (o'=3);
  [a]  s=2 -> (s'=4) & (o'=3);
  [c]  s=2 -> (s'=4) & (o'=3);
  [done] s=3 | s=4 -> true;
endmodule

label "bad" = s=3;
"""
# Node n0 plays c on o=2 and moves to n1, where o=2 means a. In s=1, reading o=1 plays b (goal).
# The controller plays b on o=3, which only the decoy s=3 and the goal s=4 emit, where b is not
# enabled: the run has ended there, so `forbid` must not hold that against it.
FORK_CONTROLLER = {
    "nodes": ["n0", "n1"],
    "initial": "n0",
    "rules": [
        {"node": "*", "obs": "o=0", "action": "go", "next": "n0"},
        {"node": "*", "obs": "o=1", "action": "b", "next": "n0"},
        {"node": "n0", "obs": "o=2", "action": "c", "next": "n1"},
        {"node": "n1", "obs": "o=2", "action": "a", "next": "n1"},
        {"node": "*", "obs": "o=3", "action": "b", "next": "n0"},
    ],
}


def test_stay_and_forbid_solve_differently(tmp_path):
    """Budget 1, every alteration costs 1. By hand:

    stay: reading o=1 as o=2 in s=1 (probability 0.6), node n0 plays c, which s=1 does not
    enable: the robot stays and its memory moves to n1; there it reads o=2 again and plays a,
    into the decoy. The other branch (s=2, 0.4) ends in the goal. So 0.6, and no other single
    alteration reaches the decoy (each makes the robot play a disabled action forever, or b).
    forbid: o=1 -> o=2 is forbidden (c is not enabled in s=1); o=1 -> o=3 plays b (allowed,
    goal); every alteration of o=2 plays go or b, not enabled in s=2. So 0.
    """
    from misdirect import solve

    (tmp_path / "fork.prism").write_text(FORK)
    stay = load_problem(
        _problem_file(tmp_path, {"prism": "fork.prism"}, FORK_CONTROLLER, {"label": "bad"})
    )
    forbid = load_problem(
        _problem_file(
            tmp_path,
            {"prism": "fork.prism", "disabled_action": "forbid"},
            FORK_CONTROLLER,
            {"label": "bad"},
            name="forbid.yaml",
        )
    )
    assert decoy_probability(stay, stay.identity()) == pytest.approx(0.0, abs=1e-12)
    answer = solve(stay, method="exhaustive")
    assert answer.probability == pytest.approx(0.6, abs=1e-12)
    assert answer.alteration == {"o=1": "o=2"}
    answer = solve(forbid, method="exhaustive")
    assert answer.probability == pytest.approx(0.0, abs=1e-12)
    obs = forbid.pomdp.observations
    o1, o2, o3 = (obs.index(f"o={k}") for k in (1, 2, 3))
    assert np.isinf(forbid.cost.row(o1)[o2]) and np.isfinite(forbid.cost.row(o1)[o3])
    assert np.isinf(forbid.cost.row(o2)[[o1, o3]]).all()
    # the decoy and the goal are absorbing in Storm (only a self-loop is enabled there)
    assert forbid.pomdp.absorbing.sum() == 2


def test_forbid_still_checks_the_controllers_own_choices(tmp_path):
    """In s=2 (o=2) node n1 would play b, which s=2 does not enable: refused, naming it."""
    (tmp_path / "fork.prism").write_text(FORK)
    controller = json.loads(json.dumps(FORK_CONTROLLER))
    controller["rules"][3]["action"] = "b"
    path = _problem_file(
        tmp_path, {"prism": "fork.prism", "disabled_action": "forbid"}, controller, {"label": "bad"}
    )
    result = runner.invoke(app, ["evaluate", str(path), "--json"])
    assert result.exit_code == 2, result.output
    error = json.loads(result.stdout)["error"]
    assert error["field"] == "pomdp.disabled_action"
    assert "'b' in state 's=2,o=2'" in error["message"] and "'n1'" in error["message"]


# -- stormpy's shipped maze: round trip and DRN ------------------------------------------------

# A controller written for the maze (PRISM maze_2.prism; o=k are its observations):
# o=1 (s0) east, o=2 (s1, s3) east, o=3 (s2) south, o=4 (s4) west, o=5 south, o=6 north.
MAZE_CHOICE = {0: "__NOLABEL__", 1: "east", 2: "east", 3: "south", 4: "west", 5: "south"}
MAZE_CHOICE |= {6: "north", 7: "done"}
# By hand, from the 13 equally likely starts (target s13 below s9):
#   s0 -> s1 -> s2 -> s6 -> s9 -> s13, and s1, s2, s6, s9 on that path: 5 reach it; s3 <-> s4
#   loop (east, west), s5/s8/s11 and s7/s10/s12 shuttle at the dead ends (south, north).
#   o=3 read as o=2: s2 goes east into the s3/s4 loop, so s0, s1, s2 fail: 2 (s6, s9).
#   o=1 read as o=5: s0 goes south into the left dead end: 4.
#   o=5 read as o=7: `done` is not enabled in s5..s10, the robot stays: 0.
MAZE_CASES = [({}, 5 / 13), ({"o=3": "o=2"}, 2 / 13), ({"o=1": "o=5"}, 4 / 13)]
MAZE_CASES.append(({"o=5": "o=7"}, 0.0))


def _maze_paynt(tmp_path) -> Path:
    labels = sorted(set(MAZE_CHOICE.values()))
    fsc = {
        "action_function": [[labels.index(MAZE_CHOICE[k]) for k in range(8)]],
        "update_function": [[0] * 8],
        "action_labels": labels,
        "observation_labels": [f"[o={k}]" for k in range(8)],
    }
    path = tmp_path / "maze.fsc.json"
    path.write_text(json.dumps(fsc))
    return path


def _rules(problem, obs_name) -> dict:
    """The problem's one-node controller as rules over the observation names ``obs_name(k)``
    (k: the problem's own observation index)."""
    return {
        "nodes": ["m"],
        "initial": "m",
        "rules": [
            {
                "node": "*",
                "obs": obs_name(k),
                "action": problem.pomdp.actions[problem.controller.action[0, k]],
                "next": "m",
            }
            for k in range(problem.pomdp.n_observations)
        ],
    }


def _mapped(problem, back, obs_name, changes):
    """``changes`` (names of ``problem``) as an alteration of ``back``."""
    alpha = problem.alteration(changes)
    mapped = back.identity()
    index = {name: i for i, name in enumerate(back.pomdp.observations)}
    for o, t in enumerate(alpha):
        mapped[index[obs_name(o)]] = index[obs_name(int(t))]
    return mapped


@pytest.mark.parametrize("target", ["prism", "drn"])
def test_shipped_maze_round_trip_through_storm(tmp_path, target):
    _maze_paynt(tmp_path)
    source = _problem_file(
        tmp_path,
        {"prism": str(SHIPPED / "maze_2.prism")},
        {"paynt": "maze.fsc.json"},
        {"label": "goal"},
    )
    original = load_problem(source)
    for changes, expected in MAZE_CASES:
        alpha = original.alteration(changes)
        assert decoy_probability(original, alpha) == pytest.approx(expected, abs=1e-12)
    out = tmp_path / f"maze.{target}"
    result = runner.invoke(app, ["convert", str(source), "--to", target, "-o", str(out)])
    assert result.exit_code == 0, result.output
    obs_name = original.pomdp.observations.__getitem__  # kept by the file's header
    back = load_problem(
        _problem_file(
            tmp_path,
            {target: out.name},
            _rules(original, obs_name),
            {"label": "decoy"},
            name="b.yaml",
        )
    )
    assert back.pomdp.n_states == original.pomdp.n_states
    for changes, expected in MAZE_CASES:
        mapped = _mapped(original, back, obs_name, changes)
        assert decoy_probability(back, mapped) == pytest.approx(expected, abs=1e-12)


def test_shipped_maze_drn_evaluates_like_the_prism_maze(tmp_path):
    """maze.drn is Storm's export of the maze (probabilities 1/13 rounded to 0.07692307692): the
    same hand values, within that rounding, with observation obs<k> of the DRN being
    observation k of the PRISM build."""
    prism = load_problem(
        _problem_file(
            tmp_path,
            {"prism": str(SHIPPED / "maze_2.prism")},
            {"paynt": str(_maze_paynt(tmp_path))},
            {"label": "goal"},
        )
    )
    drn = load_problem(
        _problem_file(
            tmp_path,
            {"drn": str(SHIPPED / "maze.drn")},
            _rules(prism, lambda k: f"obs{k}"),
            {"label": "goal"},
            name="drn.yaml",
        )
    )
    for changes, expected in MAZE_CASES:
        mapped = _mapped(prism, drn, lambda k: f"obs{k}", changes)
        assert decoy_probability(drn, mapped) == pytest.approx(expected, abs=1e-9)


def test_simulate_storm_maze_stops_runs_at_dead_ends(tmp_path):
    """Always south in the maze: 3 of the 13 starts (s2, s6, s9) reach the target, 4, 3 and 2
    steps after the initial state (mean 3); the other 10 end against a wall, where south is
    a self-loop: trapped, not run to --max-steps."""
    path = _problem_file(
        tmp_path, {"prism": str(SHIPPED / "maze_2.prism")}, SOUTH_CONTROLLER, {"label": "goal"}
    )
    result = runner.invoke(app, ["simulate", str(path), "--runs", "26000", "--json"])
    assert result.exit_code == 0, result.output
    payload = json.loads(result.stdout)
    totals = payload["totals"]
    for name, expected in (("decoy", 3 / 13), ("trapped", 10 / 13)):
        low, high = totals[name]["interval_95"]
        assert low <= expected <= high, (name, totals[name])
    assert [o["state"] for o in payload["outcomes"] if o["kind"] == "decoy"] == ["s=13,o=7"]
    assert totals["goal"]["runs"] == 0 and totals["unfinished"]["runs"] == 0
    assert payload["mean_steps_finished"] == pytest.approx(3.0, abs=0.05)


@pytest.mark.parametrize("target", ["prism", "drn", "yaml", "json"])
def test_convert_without_output_writes_to_stdout(tmp_path, target):
    """`misdirect convert FILE --to prism` (no -o), as the README writes it: the text on stdout
    reads back (through Storm for PRISM and DRN) to the same decoy probability, 0.4 by hand."""
    result = runner.invoke(app, ["convert", str(EXAMPLES / "trap.yaml"), "--to", target])
    assert result.exit_code == 0, result.output
    out = tmp_path / f"trap.{target}"
    out.write_text(result.stdout)
    if target in ("yaml", "json"):
        back = load_problem(out)
        alpha = back.alteration({"o1": "o0"})
    else:
        original = load_problem(EXAMPLES / "trap.yaml")
        obs = original.pomdp.observations.__getitem__  # kept by the file's header
        back = load_problem(
            _problem_file(tmp_path, {target: out.name}, _rules(original, obs), {"label": "decoy"})
        )
        alpha = _mapped(original, back, obs, {"o1": "o0"})
    assert decoy_probability(back, alpha) == pytest.approx(0.4, abs=1e-12)
    result = runner.invoke(app, ["convert", str(EXAMPLES / "trap.yaml"), "--to", target, "--json"])
    assert json.loads(result.stdout)["content"] == out.read_text()


BIG_PRISM = """pomdp
observables o endobservables
module m
  x : [0..100000] init 0;
  y : [0..100000] init 0;
  o : [0..1] init 0;
  [a] true -> 0.5:(x'=min(x+1,100000)) + 0.5:(y'=min(y+1,100000));
endmodule
label "goal" = x=100000;
"""


def test_a_program_too_large_to_build_is_refused_before_storm_builds_it(tmp_path, monkeypatch):
    """x and y each range over 100,001 values: up to 100,001² states (Storm's program keeps
    no range for o, which no command changes), more than the default limit of 10^8, so the
    command refuses in one line with that size instead
    of letting Storm build for minutes; the environment variable lowers or raises the limit."""
    (tmp_path / "big.prism").write_text(BIG_PRISM)
    controller = {
        "nodes": ["m"],
        "initial": "m",
        "rules": [{"node": "*", "obs": "*", "action": "a", "next": "m"}],
    }
    path = _problem_file(tmp_path, {"prism": "big.prism"}, controller, {"label": "goal"})
    result = runner.invoke(app, ["evaluate", str(path)])
    assert result.exit_code == 2
    assert "10,000,200,001 states" in result.stderr and "pomdp.prism" in result.stderr
    assert result.stderr.count("\n") == 1
    monkeypatch.setenv("MISDIRECT_MAX_PRISM_STATES", "1")
    small = _problem_file(
        tmp_path,
        {"prism": str(SHIPPED / "maze_2.prism")},
        SOUTH_CONTROLLER,
        {"label": "goal"},
        name="maze.yaml",
    )
    refused = runner.invoke(app, ["evaluate", str(small)])
    assert refused.exit_code == 2 and "more than the limit of 1 " in refused.stderr


def test_a_storm_model_without_a_path_is_a_clear_error(tmp_path):
    """``prism: null`` and no drn passes the schema; it must be refused naming the field,
    not crash."""
    from misdirect.errors import ProblemError

    path = _problem_file(tmp_path, {"prism": None}, SOUTH_CONTROLLER, {"label": "goal"})
    with pytest.raises(ProblemError, match="prism or a drn") as raised:
        load_problem(path)
    assert raised.value.field == "pomdp"
