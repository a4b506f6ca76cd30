"""The command line's conventions (issue 53): one budget flag, help that shows what the source
says, errors in one shape (JSON too, usage errors included), PAYNT's spellings for synthesis,
alterations that travel between commands, and a summary of every file written."""

from __future__ import annotations

import json
import re
import sys
from pathlib import Path

import pytest
import typer.main
import yaml
from typer.testing import CliRunner

import misdirect
from misdirect.cli import app, main
from misdirect.cli.helptext import unescaped
from misdirect.scenarios import paper_grid

runner = CliRunner()


def solved_budgets(*args: str) -> list[float]:
    result = runner.invoke(app, ["solve", "--scenario", "paper-grid", *args, "--json"])
    assert result.exit_code == 0, result.output
    return [point["budget"] for point in json.loads(result.stdout)["curve"]]


# -- A: one budget flag --------------------------------------------------------------------------


@pytest.mark.parametrize("spelling", ["--budget", "--budgets"])
def test_budget_takes_a_number_a_range_or_a_list_under_either_spelling(spelling):
    assert solved_budgets(spelling, "0,2") == [0, 2]
    assert solved_budgets(spelling, "0..2") == [0, 1, 2]
    assert solved_budgets(spelling, "1")[-1] == 1


@pytest.mark.parametrize(
    ("value", "expected"),
    [
        ("lots", "expected a number (2), a range (0..4) or a list (0,1,3), got 'lots'"),
        ("0..x", "expected a range of whole numbers like 0..4, got '0..x'"),
        ("0,x", "expected a list of numbers like 0,1,3, got '0,x'"),
        ("3..1", "0 ≤ low ≤ high"),
        ("0,-1", "non-negative"),
    ],
)
@pytest.mark.parametrize("spelling", ["--budget", "--budgets"])
def test_a_bad_budget_gets_the_message_of_its_own_syntax(spelling, value, expected):
    result = runner.invoke(app, ["solve", "--scenario", "paper-grid", spelling, value, "--json"])
    assert result.exit_code == 2
    error = json.loads(result.stdout)["error"]
    assert expected in error["message"] and error["field"] == "--budget", error


def test_the_library_takes_budget_and_budgets_alike():
    problem = paper_grid(5)
    one = misdirect.solve(problem, budget=1)
    assert one.curve[-1].budget == 1
    assert misdirect.solve(problem, budgets=1).probability == one.probability
    assert [p.budget for p in misdirect.solve(problem, budget=[0, 1]).curve] == [0, 1]
    assert [p.budget for p in misdirect.solve(problem, budgets=range(2)).curve] == [0, 1]
    assert misdirect.solve(problem, budget=1, budgets=[1]).probability == one.probability
    with pytest.raises(TypeError, match="same parameter spelled two ways"):
        misdirect.solve(problem, budget=1, budgets=[0, 1])
    assert misdirect.audit(problem, budgets=1).budget == misdirect.audit(problem, budget=1).budget
    assert misdirect.harden(problem, protect_budget=1, budgets=[1]).budget == 1
    with pytest.raises(TypeError, match="one attacker budget"):
        misdirect.harden(problem, protect_budget=1, budgets=[1, 2])
    with pytest.raises(TypeError, match="same parameter"):
        misdirect.audit(problem, budget=1, budgets=2)


# -- B: help and output consistency --------------------------------------------------------------


def _commands(command=None, path=()):
    command = command or typer.main.get_command(app)
    found = [(path, command)]
    for name, sub in getattr(command, "commands", {}).items():
        found += _commands(sub, (*path, name))
    return found


def _help(path) -> str:
    result = runner.invoke(app, [*path, "--help"], env={"COLUMNS": "250", "TERMINAL_WIDTH": "250"})
    assert result.exit_code == 0, result.output
    return result.stdout


BRACKETED = re.compile(r"\w+\[\w+\]")  # misdirect[cluster], misdirect[storm]


def test_help_shows_brackets_as_the_source_writes_them():
    seen = set()
    for path, command in _commands():
        shown = " ".join(_help(path).split())
        texts = [command.help or ""] + [getattr(p, "help", None) or "" for p in command.params]
        for text in texts:
            for word in BRACKETED.findall(unescaped(text)):
                assert word in shown, (path, word)
                seen.add(word)
    assert {"misdirect[cluster]", "misdirect[storm]"} <= seen
    assert "\\[" not in _help(("solve",))


def test_flags_are_shown_as_flags():
    for path, _command in _commands():
        assert "<bool>" not in _help(path), path
    lines = [line for line in _help(("solve",)).splitlines() if "│ --json " in line]
    assert lines and all("<" not in line for line in lines)


def _main(monkeypatch, capsys, *args: str):
    monkeypatch.setattr(sys, "argv", ["misdirect", *args])
    with pytest.raises(SystemExit) as exit_:
        main()
    captured = capsys.readouterr()
    return exit_.value.code, captured.out, captured.err


@pytest.mark.parametrize(
    ("args", "command", "field"),
    [
        (["solve", "--scenario", "paper-grid", "--bogus", "--json"], "solve", "--bogus"),
        (["solve", "--json", "--seed", "abc"], "solve", "--seed"),
        (["scenario", "knapsack", "--json", "--nope"], "scenario knapsack", "--nope"),
        (["solvx", "--json"], None, None),
        (["solve", "--json", "--scenario", "paper-grid", "true"], "solve", None),
    ],
)
def test_usage_errors_in_json_mode_are_json(monkeypatch, capsys, args, command, field):
    code, stdout, stderr = _main(monkeypatch, capsys, *args)
    assert code == 2
    document = json.loads(stdout)
    assert document["command"] == command
    assert set(document["error"]) == {"message", "field", "source"}
    assert document["error"]["field"] == field and document["error"]["source"] is None
    assert stderr.startswith("error: ") and stderr.count("\n") == 1


def test_usage_errors_without_json_print_no_json(monkeypatch, capsys):
    code, stdout, stderr = _main(monkeypatch, capsys, "solve", "--bogus")
    assert code == 2 and stdout == "" and "--bogus" in stderr


def test_every_error_has_one_shape(tmp_path):
    bad_alter = runner.invoke(
        app, ["evaluate", "--scenario", "paper-grid", "--alter", "o9=o1", "--json"]
    )
    bad_budget = runner.invoke(
        app, ["solve", "--scenario", "paper-grid", "--budget", "x", "--json"]
    )
    missing = runner.invoke(app, ["evaluate", str(tmp_path / "nope.yaml"), "--json"])
    errors = [json.loads(r.stdout)["error"] for r in (bad_alter, bad_budget, missing)]
    for error in errors:
        assert set(error) == {"message", "field", "source"}, error
    assert errors[0]["field"] == "--alter" and errors[0]["source"] is None
    assert "o9=o1" in errors[0]["message"] and "unknown observation 'o9'" in errors[0]["message"]
    assert errors[1]["field"] == "--budget" and errors[1]["source"] is None
    assert errors[2]["source"] == str(tmp_path / "nope.yaml")


WRITING = {
    ("show",): "--output",
    ("convert",): "--output",
    ("export-fsc",): "--output",
    ("export-milp",): "--output",
    ("export-chain",): "--output",
    ("audit",): "--output",
    ("harden",): "--output",
    ("reproduce",): "--out",
    ("sweep",): "--out",
    ("simulate",): "--trajectories",
    ("controller", "synthesize"): "--output",
    **{("scenario", name): "--output" for name in ("paper-grid", "knapsack", "random")},
}


def test_every_command_that_writes_files_takes_o_beside_its_old_name():
    commands = dict(_commands())
    for path, old in WRITING.items():
        names = [name for param in commands[path].params for name in param.opts]
        assert "-o" in names and old in names, path
        assert next(p for p in commands[path].params if "-o" in p.opts) is next(
            p for p in commands[path].params if old in p.opts
        ), path


# -- C: PAYNT's conventions for controller synthesize -------------------------------------------

GRID = Path(__file__).parent / "data" / "grid_avoid.prism"


def _synthesize(tmp_path, *args: str):
    output = tmp_path / "robot.fsc.json"
    command = ["controller", "synthesize", str(GRID), "--constants", "N=3", "-o", str(output)]
    return runner.invoke(app, [*command, *args, "--json"])


def test_synthesize_reads_a_paynt_properties_file_under_its_spellings(tmp_path):
    pytest.importorskip("paynt")
    props = tmp_path / "grid.props"
    props.write_text('// what the robot wants\n\nPmax=? [F "goal"];\n')
    new = _synthesize(tmp_path, "--props", str(props), "--memory-nodes", "2", "--time-limit", "30")
    old = _synthesize(tmp_path, "--props", 'Pmax=? [F "goal"]', "--memory", "2", "--timeout", "30")
    written = _synthesize(tmp_path, "--property", 'Pmax=? [F "goal"]', "--memory-nodes", "2")
    reports = [json.loads(result.stdout) for result in (new, old, written)]
    assert all(result.exit_code == 0 for result in (new, old, written)), new.output
    assert {r["property"] for r in reports} == {'Pmax=? [F "goal"]'}
    assert {r["memory"] for r in reports} == {2} and reports[0]["value"] == reports[1]["value"]


@pytest.mark.parametrize(
    ("text", "field", "words"),
    [
        ("Pmax=? [F goal\n", "line 1", "Storm cannot parse it"),
        ('// comment\nP=? [F "goal"]\n', "line 2", "optimizing property"),
        ('Pmax=? [F "goal"]\nPmin=? [F "goal"]\n', None, "2 properties (lines 1, 2)"),
        ("// nothing\n", None, "no property"),
    ],
)
def test_a_bad_properties_file_is_named_not_the_model(tmp_path, text, field, words):
    if field is not None:
        pytest.importorskip("paynt")
    props = tmp_path / "grid.props"
    props.write_text(text)
    result = _synthesize(tmp_path, "--props", str(props))
    assert result.exit_code == 2, result.output
    error = json.loads(result.stdout)["error"]
    assert error["source"] == str(props) and error["field"] == field, error
    assert words in error["message"] and str(GRID) not in error["message"]


def test_a_missing_properties_file_is_named(tmp_path):
    result = _synthesize(tmp_path, "--props", "grid4.props")
    assert result.exit_code == 2
    error = json.loads(result.stdout)["error"]
    assert error["source"] == "grid4.props" and "file not found" in error["message"]


def test_a_property_written_out_is_named_by_its_flag(tmp_path):
    pytest.importorskip("paynt")
    result = _synthesize(tmp_path, "--property", 'P=? [F "goal"]')
    error = json.loads(result.stdout)["error"]
    assert error["field"] == "--property" and error["source"] is None
    both = _synthesize(tmp_path, "--property", 'Pmax=? [F "goal"]', "--props", "x.props")
    assert both.exit_code == 2 and "not both" in json.loads(both.stdout)["error"]["message"]
    none = _synthesize(tmp_path)
    assert (
        none.exit_code == 2 and "--property STRING" in json.loads(none.stdout)["error"]["message"]
    )


@pytest.mark.parametrize(
    ("flag", "field"),
    [
        ("--time-limit", "--time-limit"),
        ("--timeout", "--time-limit"),
        ("--memory-nodes", "--memory-nodes"),
        ("--memory", "--memory-nodes"),
    ],
)
def test_synthesis_limits_are_named_by_their_new_flag(tmp_path, flag, field):
    result = _synthesize(tmp_path, "--property", 'Pmax=? [F "goal"]', flag, "0")
    assert result.exit_code == 2
    assert json.loads(result.stdout)["error"]["field"] == field


# -- D: alterations travel -----------------------------------------------------------------------

ALTERING = ["evaluate", "simulate", "show", "export-chain"]


def _alteration_of(command: str, tmp_path, *args: str) -> dict[str, str]:
    """The alteration ``command`` applied, from its --json output."""
    extra = {
        "simulate": ["--runs", "10"],
        "show": ["-o", str(tmp_path / "map.dot")],
        "export-chain": ["-o", str(tmp_path / "chain.drn")],
    }.get(command, [])
    result = runner.invoke(app, [command, "--scenario", "paper-grid", *args, *extra, "--json"])
    assert result.exit_code == 0, result.output
    if command in ("show", "export-chain"):  # no alteration in their documents: the file's
        return {"written": json.loads(result.stdout)["written"]}  # written means it loaded
    return json.loads(result.stdout)["alteration"]


def test_solve_writes_what_every_altering_command_reads(tmp_path):
    as_json, as_yaml = tmp_path / "answer.json", tmp_path / "answer.yaml"
    for path in (as_json, as_yaml):
        result = runner.invoke(
            app, ["solve", "--scenario", "paper-grid", "--budget", "0..2", "-o", str(path)]
        )
        assert result.exit_code == 0, result.output
        assert f"wrote {path}" in " ".join(result.stdout.split())
    curve = json.loads(as_json.read_text())["curve"]
    assert (
        yaml.safe_load(as_yaml.read_text()) == curve[-1]["alteration"] == {"o1": "o2", "o2": "o0"}
    )
    for command in ALTERING:
        for path in (as_json, as_yaml):
            assert _alteration_of(command, tmp_path, "--alteration", str(path)) == _alteration_of(
                command, tmp_path, "--alter", "o1=o2", "--alter", "o2=o0"
            ), (command, path)
    at_one = _alteration_of("evaluate", tmp_path, "--alteration", str(as_json), "--at-budget", "1")
    assert at_one == curve[1]["alteration"] == {"o1": "o2"}


def test_evaluate_output_and_a_small_mapping_travel_too(tmp_path):
    evaluated = runner.invoke(
        app, ["evaluate", "--scenario", "paper-grid", "--alter", "o1=o3", "--json"]
    )
    (tmp_path / "e.json").write_text(evaluated.stdout)
    (tmp_path / "m.yaml").write_text("o1: o3\n")
    for name in ("e.json", "m.yaml"):
        path = str(tmp_path / name)
        assert _alteration_of("simulate", tmp_path, "--alteration", path) == {"o1": "o3"}


@pytest.mark.parametrize(
    ("args", "field", "words"),
    [
        (["--at-budget", "7"], "--at-budget", "no budget 7 (it has 0, 1)"),
        (["--alter", "o1=o3"], "--alteration", "not both"),
    ],
)
def test_a_bad_alteration_file_or_budget_is_named(tmp_path, args, field, words):
    answer = tmp_path / "answer.json"
    runner.invoke(app, ["solve", "--scenario", "paper-grid", "--budget", "0..1", "-o", str(answer)])
    result = runner.invoke(
        app, ["evaluate", "--scenario", "paper-grid", "--alteration", str(answer), *args, "--json"]
    )
    assert result.exit_code == 2
    error = json.loads(result.stdout)["error"]
    assert error["field"] == field and words in error["message"], error


def test_an_unknown_name_in_an_alteration_file_names_the_file(tmp_path):
    mapping = tmp_path / "m.yaml"
    mapping.write_text("o1: o9\n")
    result = runner.invoke(
        app, ["evaluate", "--scenario", "paper-grid", "--alteration", str(mapping), "--json"]
    )
    error = json.loads(result.stdout)["error"]
    assert error["source"] == str(mapping) and "unknown observation 'o9'" in error["message"]
    alone = runner.invoke(
        app, ["evaluate", "--scenario", "paper-grid", "--at-budget", "1", "--json"]
    )
    assert json.loads(alone.stdout)["error"]["field"] == "--at-budget"


STORM_NAMED = """
format: misdirect/v1
pomdp:
  states: [s0, s1, goal, trap]
  actions: [a, b]
  initial: s0
  observe: {s0: "o=0", s1: "clk=0,!n", goal: "o=2", trap: "o=2"}
  transitions:
    - [s0, a, s1, 0.5]
    - [s0, a, goal, 0.5]
    - [s0, b, s0, 1.0]
    - [s1, a, goal, 1.0]
    - [s1, b, trap, 1.0]
  absorbing: [goal, trap]
controller:
  nodes: [n0]
  initial: n0
  rules:
    - {node: "*", obs: "*", action: a, next: n0}
deception:
  decoy: [trap]
  budget: 1
"""


def test_storm_names_are_accepted_and_names_with_separators_quoted(tmp_path):
    path = tmp_path / "storm.yaml"
    path.write_text(STORM_NAMED)
    for pair in ["[clk=0\t& !n]=[o=2]", "clk=0,!n=o=2", "[clk=0 & !n]=o=2"]:
        result = runner.invoke(app, ["evaluate", str(path), "--alter", pair, "--json"])
        assert result.exit_code == 0, (pair, result.output)
        assert json.loads(result.stdout)["alteration"] == {"clk=0,!n": "o=2"}, pair
    shown = runner.invoke(
        app, ["evaluate", str(path), "--alter", "[clk=0 & !n]=[o=2]"], env={"COLUMNS": "200"}
    )
    assert '"clk=0,!n" → "o=2"' in shown.stdout, shown.stdout
    mapping = tmp_path / "m.yaml"
    mapping.write_text('"[clk=0\\t& !n]": "[o=2]"\n')
    result = runner.invoke(app, ["evaluate", str(path), "--alteration", str(mapping), "--json"])
    assert json.loads(result.stdout)["alteration"] == {"clk=0,!n": "o=2"}


# -- E: small surprises --------------------------------------------------------------------------

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def test_audit_and_harden_with_o_print_a_summary_on_stdout(tmp_path):
    audit = runner.invoke(
        app, ["audit", "--scenario", "paper-grid", "--budget", "1", "-o", str(tmp_path / "a")]
    )
    assert audit.exit_code == 0, audit.output
    shown = " ".join(audit.stdout.split())
    assert f"wrote {len(list((tmp_path / 'a').iterdir()))} files to {tmp_path / 'a'}/" in shown
    assert "report.md" in shown and "criticality" in shown  # the table too, as without -o
    harden = runner.invoke(
        app,
        [
            *("harden", "--scenario", "paper-grid", "--budget", "1", "--protect-budget", "1"),
            *("-o", str(tmp_path / "h")),
        ],
    )
    assert harden.exit_code == 0, harden.output
    assert f"files to {tmp_path / 'h'}/" in " ".join(harden.stdout.split())


@pytest.mark.parametrize(
    ("args", "written"),
    [
        (["convert", "--scenario", "paper-grid", "--to", "yaml", "-o", "p.yaml"], "p.yaml"),
        (["show", "--scenario", "paper-grid", "-o", "p.dot"], "p.dot"),
        (["export-chain", "--scenario", "paper-grid", "-o", "c.drn"], "c.drn"),
        (["scenario", "paper-grid", "-o", "g.yaml"], "g.yaml"),
        (["simulate", "--scenario", "paper-grid", "--runs", "5", "-o", "t.csv"], "t.csv"),
        (["solve", "--scenario", "paper-grid", "--budget", "1", "-o", "a.yaml"], "a.yaml"),
    ],
)
def test_every_command_that_writes_files_says_so_on_stdout(tmp_path, monkeypatch, args, written):
    monkeypatch.chdir(tmp_path)
    result = runner.invoke(app, args)
    assert result.exit_code == 0, result.output
    assert (tmp_path / written).exists() and f"wrote {written}" in result.stdout, result.stdout


def test_solve_of_a_file_says_when_it_answered_its_budget_alone():
    """trap.yaml has budget 1: the help promised every smaller budget, the table had one row.
    The help says when smaller budgets come (for free, else a range), and a note says how."""
    help_text = " ".join(_help(("solve",)).split())
    assert "every smaller budget" not in help_text and "--budget 0..B" in help_text
    result = runner.invoke(app, ["solve", str(EXAMPLES / "trap.yaml")])
    table = [line for line in result.stdout.splitlines() if "optimal" in line and "│" in line]
    assert len(table) == 1 and "note: budget 1 alone was solved" in result.stderr
    assert "--budget 0..1 answers each budget" in result.stderr
    ranged = runner.invoke(app, ["solve", str(EXAMPLES / "trap.yaml"), "--budget", "0..1"])
    assert ranged.exit_code == 0 and "alone was solved" not in ranged.output
    table = [line for line in ranged.stdout.splitlines() if "optimal" in line and "│" in line]
    assert len(table) == 2, ranged.stdout
