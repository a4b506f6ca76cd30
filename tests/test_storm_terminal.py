"""Storm models at PAYNT's semantics: terminal targets, decoy expressions, validation, names.

The PRISM models and controllers in tests/data are our own. Values are checked against Storm
model checking an independently built product: the PRISM program with a controller module
added (written here from the hand-written .fsc.json and a hand-written table of which cells
emit which observation), built by Storm with the target states terminal, as PAYNT builds.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from misdirect import decoy_probability, load_problem
from misdirect.cli import app

stormpy = pytest.importorskip("stormpy")
DATA = Path(__file__).parent / "data"
runner = CliRunner()

# which states emit which observation, by hand from the PRISM source (our names)
MAZE_CELLS = {
    "!n,e,s,!w": "c = 0",
    "!n,e,!s,w": "(c = 1 | c = 3)",
    "!n,e,s,w": "c = 2",
    "!n,!e,s,w": "c = 4",
    "n,!e,s,!w": "(c >= 5 & c <= 7)",
    "n,!e,!s,!w": "c >= 8",
}
MAZE_OBS = {f"clk={k},{d}": f"clk = {k} & {e}" for k in (0, 1) for d, e in MAZE_CELLS.items()}
GEO_OBS = {"!started,x=2": "!started & x = 2"}
GEO_OBS |= {f"started,x={k}": f"started & x = {k}" for k in range(5)}


def _problem(tmp_path, model, pomdp_extra=None, decoy=None, controller=None, name="p.yaml"):
    document = {
        "format": "misdirect/v1",
        "pomdp": {"prism": str(DATA / f"{model}.prism"), **(pomdp_extra or {})},
        "controller": controller or {"paynt": str(DATA / f"{model}.fsc.json")},
        "deception": {"decoy": decoy or {"label": "bad"}, "budget": 1},
    }
    path = tmp_path / name
    path.write_text(yaml.safe_dump(document, sort_keys=False))
    return path


def _storm_value(
    tmp_path: Path, model: str, table: dict[str, str], changes: dict[str, str], terminal: bool
) -> float:
    """Pr(F "bad") in the PRISM program composed with the controller of ``model``.fsc.json,
    each state reading the observation ``changes`` turns its own into; Storm builds the
    composition (with "goal" terminal when ``terminal``) and model checks it."""
    fsc = json.loads((DATA / f"{model}.fsc.json").read_text())
    source = (DATA / f"{model}.prism").read_text()
    source = re.sub(r"(?m)^\s*observables?\b.*$", "", source).replace("pomdp", "mdp", 1)
    # the world's unlabelled step must synchronise with the controller's memory update
    source = re.sub(r"\[\]", "[tick]", source)
    labels = fsc["observation_labels"]
    reads: dict[str, list[str]] = {label: [] for label in labels}
    for own in labels:
        reads[changes.get(own, own)].append(table[own])
    lines = ["module controller", f"  node : [0..{fsc['num_nodes'] - 1}] init 0;"]
    for n, (actions, updates) in enumerate(
        zip(fsc["action_function"], fsc["update_function"], strict=True)
    ):
        for k, label in enumerate(labels):
            if not reads[label] or actions[k] is None:
                continue
            action = fsc["action_labels"][actions[k]]
            sync = "tick" if action == "__no_label__" else action
            guard = " | ".join(f"({e})" for e in reads[label])
            lines.append(f"  [{sync}] node = {n} & ({guard}) -> (node' = {updates[k]});")
    for action in {*fsc["action_labels"], "tick"} - {"__no_label__"}:
        lines.append(f"  [{action}] false -> true;")
    lines.append("endmodule")
    composed = tmp_path / f"{model}-composed.prism"
    composed.write_text(source + "\n".join(lines) + "\n")
    program = stormpy.parse_prism_program(str(composed))
    target = stormpy.parse_properties('P=? [F "goal"]', program)
    options = stormpy.BuilderOptions(target if terminal else None)
    options.set_build_all_labels()
    mdp = stormpy.build_model(program, options=options)
    values = []
    for direction in ("max", "min"):
        prop = stormpy.parse_properties(f'P{direction}=? [F "bad"]', program)[0]
        result = stormpy.model_checking(mdp, prop)
        values.append(result.get_value(mdp.initial_states[0]))
    assert values[0] == pytest.approx(values[1], abs=1e-12)  # the controller is deterministic
    return values[0]


MAZE_CASES = [{}, {"clk=0,!n,e,s,w": "clk=0,!n,!e,s,w"}, {"clk=0,n,!e,s,!w": "clk=0,n,!e,!s,!w"}]
# at c=2 read "east-west" (go east), at c=4 read "east-west-south" (go south): node 0 then
# walks down the right corridor into the dead end c=10 before it ever sees the goal: 1
MAZE_CASES.append({"clk=0,!n,e,s,w": "clk=0,!n,e,!s,w", "clk=0,!n,!e,s,w": "clk=0,!n,e,s,w"})


@pytest.mark.parametrize("changes", MAZE_CASES)
def test_maze_terminal_matches_storm(tmp_path, changes):
    problem = load_problem(_problem(tmp_path, "maze", {"terminal": "goal"}))
    value = decoy_probability(problem, problem.alteration(changes))
    expected = _storm_value(tmp_path, "maze", MAZE_OBS, changes, True)
    assert value == pytest.approx(expected, abs=1e-9)
    assert expected == pytest.approx(1.0 if changes == MAZE_CASES[-1] else 0.0, abs=1e-9)


def test_maze_as_written_differs(tmp_path):
    """By hand: with the goal terminal the robot stops at c=9 and never reaches a dead end
    (0). As written it reads N at the goal, turns back (node 1), walks east to c=4 and down
    the right corridor into c=10 (1)."""
    terminal = load_problem(_problem(tmp_path, "maze", {"terminal": '"goal"'}))
    written = load_problem(_problem(tmp_path, "maze", name="w.yaml"))
    assert decoy_probability(terminal, terminal.identity()) == pytest.approx(0.0, abs=1e-12)
    assert decoy_probability(written, written.identity()) == pytest.approx(1.0, abs=1e-9)
    assert _storm_value(tmp_path, "maze", MAZE_OBS, {}, False) == pytest.approx(1.0, abs=1e-9)
    assert _storm_value(tmp_path, "maze", MAZE_OBS, {}, True) == pytest.approx(0.0, abs=1e-12)
    # the robot enters the goal at clk=1; Storm builds that state terminal (a self-loop) and
    # never explores past it, so the goal at clk=0 exists only as written: 21 states, not 22
    states, absorbing = terminal.pomdp.states, terminal.pomdp.absorbing
    assert absorbing[states.index("c=9,clk=1")] and "c=9,clk=0" not in states
    assert (terminal.pomdp.n_states, written.pomdp.n_states) == (21, 22)
    assert not written.pomdp.absorbing[written.pomdp.states.index("c=9,clk=1")]


GEO_CASES = [({}, 0.5, 1.0), ({"started,x=1": "started,x=0"}, 0.5, 0.5)]


@pytest.mark.parametrize(("changes", "terminal_value", "written_value"), GEO_CASES)
def test_geo_terminal_and_as_written(tmp_path, changes, terminal_value, written_value):
    """By hand: node 0 walks left to x=0 (bad if the target is at x=4, t=1, else the goal);
    node 1 then walks right to x=4. Terminal: 0.5. As written: when t=0 the robot walks on
    from the goal to x=4, bad: 1. Reading x=1 as x=0 turns it round at x=1, so it ends at
    x=4 either way: bad when t=0, 0.5, terminal or not."""
    for extra, expected, terminal in (
        ({"terminal_from": 'P=? [F "goal"]'}, terminal_value, True),
        ({}, written_value, False),
    ):
        problem = load_problem(_problem(tmp_path, "geo", extra))
        value = decoy_probability(problem, problem.alteration(changes))
        assert value == pytest.approx(expected, abs=1e-9)
        assert _storm_value(tmp_path, "geo", GEO_OBS, changes, terminal) == pytest.approx(
            expected, abs=1e-9
        )


def test_drn_terminal_and_label_expressions(tmp_path):
    """The geo model exported by Storm as DRN: terminal and decoy as label expressions give
    the PRISM model's values (0.5 terminal, 1 as written)."""
    program = stormpy.parse_prism_program(str(DATA / "geo.prism"))
    options = stormpy.BuilderOptions()
    options.set_build_all_labels()
    options.set_build_choice_labels()
    stormpy.io.export_to_drn(
        stormpy.build_model(program, options=options), str(tmp_path / "geo.drn")
    )
    prism = load_problem(_problem(tmp_path, "geo"))
    rules = {
        "nodes": ["n0", "n1"],
        "initial": "n0",
        "rules": [],
    }
    # the same controller over the DRN's observation names obs<k>: same numbering as PRISM's
    for o in range(prism.pomdp.n_observations):
        for n, node in enumerate(rules["nodes"]):
            rules["rules"].append(
                {
                    "node": node,
                    "obs": f"obs{o}",
                    "action": prism.pomdp.actions[prism.controller.action[n, o]],
                    "next": rules["nodes"][prism.controller.update[n, o]],
                }
            )
    for extra, decoy, expected in (
        ({"terminal": "goal & !bad"}, {"expression": "bad & !(goal)"}, 0.5),
        ({"terminal_from": 'P=? [F "goal"]'}, {"label": "bad"}, 0.5),
        ({}, {"expression": "bad"}, 1.0),
    ):
        document = {
            "format": "misdirect/v1",
            "pomdp": {"drn": "geo.drn", **extra},
            "controller": rules,
            "deception": {"decoy": decoy, "budget": 1},
        }
        (tmp_path / "d.yaml").write_text(yaml.safe_dump(document))
        drn = load_problem(tmp_path / "d.yaml")
        assert decoy_probability(drn, drn.identity()) == pytest.approx(expected, abs=1e-9)


def test_decoy_expression_equals_label(tmp_path):
    by_label = load_problem(_problem(tmp_path, "maze", {"terminal": "goal"}))
    for text in ("c = 8 | c = 10", '"bad"', "bad & !goal", "c >= 8 & c != 9"):
        by_expression = load_problem(
            _problem(tmp_path, "maze", {"terminal": "goal"}, {"expression": text}, name="e.yaml")
        )
        assert np.array_equal(by_expression.decoy, by_label.decoy), text
    assert by_label.decoy.sum() == 4  # c = 8 and c = 10, each at clk 0 and 1


# -- errors: one line naming file, field and reason ----------------------------------------------


def _one_action_problem(tmp_path, pomdp: dict) -> Path:
    """p.yaml: the model ``pomdp``, a one-node controller playing ``a``, decoy label ``bad``."""
    document = {
        "format": "misdirect/v1",
        "pomdp": pomdp,
        "controller": {
            "nodes": ["m"],
            "initial": "m",
            "rules": [{"node": "*", "obs": "*", "action": "a", "next": "m"}],
        },
        "deception": {"decoy": {"label": "bad"}, "budget": 1},
    }
    path = tmp_path / "p.yaml"
    path.write_text(yaml.safe_dump(document))
    return path


def _error(path):
    result = runner.invoke(app, ["evaluate", str(path), "--json"])
    assert result.exit_code == 2, result.output
    assert "Traceback" not in result.output and "internal error" not in result.output
    error = json.loads(result.stdout)["error"]
    assert "\n" not in error["message"]
    plain = runner.invoke(app, ["evaluate", str(path)])
    assert plain.exit_code == 2 and plain.stderr.count("\n") == 1
    return error


@pytest.mark.parametrize(
    ("decoy", "words"),
    [
        ({"expression": "c >"}, "Storm cannot parse it"),
        ({"expression": '"lava"'}, "no label 'lava'"),
        ({"expression": "c + 1"}, "boolean"),
        ({"expression": "c = 99"}, "no state satisfies"),
        ({"expression": "c = 1; label"}, "no ';'"),
    ],
)
def test_bad_decoy_expression(tmp_path, decoy, words):
    error = _error(_problem(tmp_path, "maze", decoy=decoy))
    assert error["field"] == "deception.decoy.expression"
    assert words in error["message"], error["message"]


def test_bad_terminal(tmp_path):
    error = _error(_problem(tmp_path, "maze", {"terminal": "nosuch | goal"}))
    assert error["field"] == "pomdp.terminal" and "Storm cannot parse it" in error["message"]
    error = _error(_problem(tmp_path, "maze", {"terminal_from": "P=? [F"}, name="q.yaml"))
    assert error["field"] == "pomdp.terminal_from"


DRN_HEAD = "@type: POMDP\n@parameters\n\n@reward_models\n\n@nr_states\n3\n@nr_choices\n3\n@model\n"


def _drn(first: str, second: str, init0: str = " init", init1: str = "") -> str:
    return DRN_HEAD + (
        f"state 0 {{0}}{init0}\n\taction a\n\t\t1 : {first}\n\t\t2 : {second}\n"
        f"state 1 {{1}}{init1}\n\taction a\n\t\t1 : 1\n"
        "state 2 {1} bad\n\taction a\n\t\t2 : 1\n"
    )


@pytest.mark.parametrize(
    ("text", "words"),
    [
        (_drn("1.5", "-0.5"), "state 's0', action 'a': probability 1.5 is not in [0, 1]"),
        (_drn("0.7", "0.7"), "state 's0', action 'a': probabilities sum to 1.4, not 1"),
        (_drn("0.5", "0.5", init0=""), "has no initial state"),
        (_drn("0.5", "0.5", init1=" init"), "has 2 initial states (states 0, 1)"),
    ],
)
def test_drn_validation(tmp_path, text, words):
    (tmp_path / "m.drn").write_text(text)
    error = _error(_one_action_problem(tmp_path, {"drn": "m.drn"}))
    assert error["source"] == str(tmp_path / "p.yaml")
    assert error["field"] == "pomdp.drn"
    assert "m.drn" in error["message"] and words in error["message"], error["message"]


def test_prism_probabilities_not_summing_to_one(tmp_path):
    (tmp_path / "bad.prism").write_text(
        "pomdp\nobservables o endobservables\nmodule m\n  s : [0..2] init 0;\n"
        "  o : [0..1] init 0;\n  [a] s=0 -> 0.7 : (s'=1) + 0.7 : (s'=2);\n"
        '  [a] s>0 -> true;\nendmodule\nlabel "bad" = s=2;\n'
    )
    error = _error(_one_action_problem(tmp_path, {"prism": "bad.prism"}))
    assert error["field"] == "pomdp.prism"
    assert "bad.prism: state 's=0" in error["message"]
    assert "action 'a': probabilities sum to 1.4, not 1" in error["message"]


# -- names --------------------------------------------------------------------------------------


def test_observation_names_from_the_states():
    """tests/data/observables.prism, by hand. States (x, y, flag): the start (0, -1, false);
    `go` moves to (x+1, min(y+1, 1), !flag) or only flips h. So the observations are
    x=0: !flag, y=-1 -> sum=-1; x=1: flag, y=0 -> sum=1; x=2: !flag, y=1 -> 3;
    x=3: flag, y=1 -> 4; far is x >= 2. Storm itself prints these as e.g. `x=3,sum=1`."""
    from misdirect.io.storm import load_storm_pomdp

    world = load_storm_pomdp(DATA / "observables.prism", kind="prism")
    pomdp = world.pomdp
    assert sorted(pomdp.observations) == sorted(
        [
            "!flag,x=0,!far,sum=-1",
            "flag,x=1,!far,sum=1",
            "!flag,x=2,far,sum=3",
            "flag,x=3,far,sum=4",
        ]
    )
    for s, name in enumerate(pomdp.states):
        x = int(re.search(r"x=(\d)", name)[1])
        observation = pomdp.observations[pomdp.observation_of[s]]
        assert f"x={x}," in observation
        assert observation.startswith("flag" if x % 2 else "!flag")
    assert pomdp.states[pomdp.initial_state] == "!flag,x=0,y=-1,h=0"


def test_bulk_reading_matches_stormpys_accessors():
    """The UMB route gives the matrix stormpy's per-entry accessors give."""
    from misdirect.io.storm_arrays import read_arrays, read_arrays_slowly

    program = stormpy.parse_prism_program(str(DATA / "drone.prism"))
    program, _ = stormpy.instantiate_constants(program, "N=4,B=6")
    options = stormpy.BuilderOptions()
    options.set_build_choice_labels()
    model = stormpy.build_model(program, options=options)
    fast, slow = read_arrays(stormpy, model), read_arrays_slowly(model)
    assert model.nr_choices > 100
    for name in ("groups", "rows", "target", "probability", "observation_of", "initial"):
        assert np.array_equal(getattr(fast, name), getattr(slow, name)), name
    assert [fast.actions[a] for a in fast.action] == [slow.actions[a] for a in slow.action]


# -- PAYNT null entries ---------------------------------------------------------------------------


def test_paynt_null_entries_are_never_targets(tmp_path):
    """geo: node 1 never sees the start observation. With its entries null, the controller
    loads, the value is unchanged (0.5 terminal), and no observation may be altered into it."""
    fsc = json.loads((DATA / "geo.fsc.json").read_text())
    fsc["action_function"][1][0] = None
    fsc["update_function"][1][0] = None
    (tmp_path / "geo.fsc.json").write_text(json.dumps(fsc))
    problem = load_problem(
        _problem(
            tmp_path,
            "geo",
            {"terminal": "goal"},
            controller={"paynt": str(tmp_path / "geo.fsc.json")},
        )
    )
    assert decoy_probability(problem, problem.identity()) == pytest.approx(0.5, abs=1e-9)
    start = problem.pomdp.observations.index("!started,x=2")
    other = problem.pomdp.observations.index("started,x=1")
    assert np.isinf(problem.cost.row(other)[start])
    assert np.isfinite(problem.cost.row(start)[other])  # it may still be altered itself
    with pytest.raises(Exception, match="forbidden"):
        problem.alteration({"started,x=1": "!started,x=2"})


def test_paynt_labels_as_storm_prints_them(tmp_path):
    """PAYNT writes Storm's own text of each observation; for `geo` Storm prints a true
    `started` as nothing: `[\\t& x=1]`. Those labels load (where they name one observation)."""
    fsc = json.loads((DATA / "geo.fsc.json").read_text())
    fsc["observation_labels"] = ["[!started\t& x=2]"] + [f"[\t& x={k}]" for k in range(5)]
    (tmp_path / "geo.fsc.json").write_text(json.dumps(fsc))
    problem = load_problem(
        _problem(tmp_path, "geo", {"terminal": "goal"}, controller={"paynt": "geo.fsc.json"})
    )
    assert decoy_probability(problem, problem.identity()) == pytest.approx(0.5, abs=1e-9)


# -- a PAYNT file made for the terminal build, read without terminal -----------------------------

# x=0 -> x=1 (o=1) -> goal x=2 (0.9) or bad x=4 (0.1); past the goal, x=3 reads o=1 again and
# leads to bad. The controller (PAYNT's form, nulls where PAYNT's controller never goes) moves
# to node 1 at o=1: in PAYNT's build, with the goal terminal, node 1 never meets o=1 again.
BEYOND = """pomdp
observables o endobservables
module m
  x : [0..4] init 0;
  o : [0..2] init 0;
  [go] x=0 -> (x'=1) & (o'=1);
  [go] x=1 -> 0.9 : (x'=2) & (o'=2) + 0.1 : (x'=4) & (o'=2);
  [go] x=2 -> (x'=3) & (o'=1);
  [go] x=3 -> (x'=4) & (o'=2);
  [go] x=4 -> true;
endmodule
label "goal" = x=2;
label "bad" = x=4;
"""
BEYOND_FSC = {
    "num_nodes": 2,
    "num_observations": 3,
    "action_function": [[0, 0, None], [None, None, 0]],
    "update_function": [[0, 1, None], [None, None, 1]],
    "action_labels": ["go"],
    "observation_labels": ["o=0", "o=1", "o=2"],
}


def test_paynt_file_of_the_terminal_build_read_without_terminal_warns(tmp_path):
    """By hand: with the goal terminal, Pr(bad) = 0.1 and node 1 never reads o=1. As written,
    the robot walks on from the goal to x=3, reads o=1 in node 1 (null in the file) and ends
    in bad: 1.0. That reading is warned about, naming the label to make terminal."""
    (tmp_path / "beyond.prism").write_text(BEYOND)
    (tmp_path / "beyond.fsc.json").write_text(json.dumps(BEYOND_FSC))

    def problem(extra: dict, name: str):
        document = {
            "format": "misdirect/v1",
            "pomdp": {"prism": "beyond.prism", **extra},
            "controller": {"paynt": "beyond.fsc.json"},
            "deception": {"decoy": {"label": "bad"}, "budget": 1},
        }
        (tmp_path / name).write_text(yaml.safe_dump(document))
        return tmp_path / name

    terminal = load_problem(problem({"terminal_from": 'P=? [F "goal"]'}, "t.yaml"))
    assert terminal.warnings == ()
    assert decoy_probability(terminal, terminal.identity()) == pytest.approx(0.1, abs=1e-12)
    plain_path = problem({}, "p.yaml")
    plain = load_problem(plain_path)
    assert decoy_probability(plain, plain.identity()) == pytest.approx(1.0, abs=1e-12)
    (warning,) = plain.warnings
    assert "'o=1' in node n1" in warning and "labelled 'goal' terminal" in warning
    for command in ("evaluate", "solve"):
        result = runner.invoke(app, [command, str(plain_path), "--json"])
        assert result.exit_code == 1, result.output  # a warning, as elsewhere
        assert json.loads(result.stdout)["warnings"] == [warning]
        assert "warning:" in result.stderr
    result = runner.invoke(app, ["evaluate", str(tmp_path / "t.yaml"), "--json"])
    assert result.exit_code == 0 and json.loads(result.stdout)["warnings"] == []
