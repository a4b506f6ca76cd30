"""Every command's ``--json`` output follows the one shipped schema (misdirect-result/1), one
concept has one name across commands, and MILP-only flags mean what they say.

Expected values come from hand calculations (examples/trap.yaml, see its description) and the
paper's 5x5 grid optima (SPEC §3, also checked in test_paper_values)."""

from __future__ import annotations

import dataclasses
import fnmatch
import json
import re
import textwrap
import tomllib
from pathlib import Path

import pytest
from jsonschema import Draft202012Validator
from typer.testing import CliRunner

import misdirect
from misdirect.cli import app
from misdirect.report.json_output import SCHEMA, SCHEMA_FILE, result_schema
from misdirect.scenarios import paper_grid
from result_schema import VALIDATOR, checked

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = ROOT / "examples"
GRID = [0.084957, 0.719924, 0.860130]  # SPEC §3: the 5x5 grid's optima at budgets 0, 1, 2
runner = CliRunner()


def run(*args: str, code: int = 0) -> dict:
    result = runner.invoke(app, [*args, "--json"])
    assert result.exit_code == code, result.output
    document = checked(result.stdout)
    assert document["schema"] == SCHEMA
    return document


# -- the schema itself --------------------------------------------------------------------------


def test_schema_is_valid_and_shipped_as_package_data():
    Draft202012Validator.check_schema(result_schema())
    assert result_schema()["properties"]["schema"]["const"] == SCHEMA
    pyproject = tomllib.loads((ROOT / "pyproject.toml").read_text())
    globs = pyproject["tool"]["setuptools"]["package-data"]["misdirect"]
    assert any(fnmatch.fnmatch(f"schema/{SCHEMA_FILE}", g) for g in globs)
    # `misdirect schema --result` prints the same schema
    printed = runner.invoke(app, ["schema", "--result"])
    assert printed.exit_code == 0 and json.loads(printed.stdout) == result_schema()


def test_schema_refuses_old_names():
    """The schema is strict: a document with a pre-1 field name does not validate."""
    solve = run("solve", "--scenario", "paper-grid", "--budget", "1")
    for old, new in (("probability", "value"), ("baseline_probability", "baseline_value")):
        renamed = {(old if k == new else k): v for k, v in solve.items()}
        assert not VALIDATOR.is_valid(renamed), old
    harden = run("harden", "--scenario", "paper-grid", "--budget", "1", "--protect-budget", "0")
    for old, new in (("value_after", "value"), ("best_reply", "alteration")):
        renamed = {(old if k == new else k): v for k, v in harden.items()}
        assert not VALIDATOR.is_valid(renamed), old
    point = dict(harden["curve"][0])
    point["attack"] = point.pop("alteration")
    assert not VALIDATOR.is_valid({**harden, "curve": [point]})


def test_docs_describe_every_field():
    """docs/json-schema.md names every property the schema declares."""
    text = (ROOT / "docs" / "json-schema.md").read_text()
    names: set[str] = set()

    def collect(node: object) -> None:
        if isinstance(node, dict):
            names.update(node.get("properties", {}))
            for value in node.values():
                collect(value)
        elif isinstance(node, list):
            for value in node:
                collect(value)

    collect(result_schema())
    missing = sorted(n for n in names if f"`{n}`" not in text)
    assert not missing, missing


# -- every command ------------------------------------------------------------------------------


def test_evaluate_outcomes_by_hand():
    """trap.yaml unaltered: 0.6 of the runs cycle in `loop` forever, 0.4 reach `exit`, then a
    quarter of those the decoy: decoy 0.1, goal 0.3, trapped 0.6."""
    document = run("evaluate", str(EXAMPLES / "trap.yaml"))
    assert document["command"] == "evaluate"
    assert document["value"] == pytest.approx(0.1, abs=1e-12)
    assert document["baseline_value"] == pytest.approx(0.1, abs=1e-12)
    ends = {(o["kind"], o["state"]): o["probability"] for o in document["outcomes"]}
    assert ends == pytest.approx(
        {("decoy", "decoy"): 0.1, ("goal", "goal"): 0.3, ("trapped", None): 0.6}, abs=1e-12
    )
    altered = run("evaluate", str(EXAMPLES / "trap.yaml"), "--alter", "o1=o0")
    assert altered["value"] == pytest.approx(0.4, abs=1e-12)  # 0.6·0.5 + 0.4·0.25
    assert altered["alteration"] == {"o1": "o0"} and altered["written"] == []


def test_solve_keeps_per_point_and_whole_run_stats_apart():
    document = run("solve", "--scenario", "paper-grid", "--budget", "0..2")
    assert [p["value"] for p in document["curve"]] == pytest.approx(GRID, abs=5e-7)
    assert document["value"] == pytest.approx(GRID[2], abs=5e-7)
    # one enumeration answers every budget: its counters once, at the top level
    assert document["stats"] and all("stats" not in p for p in document["curve"])
    assert document["certified_by"] == document["curve"][-1]["certified_by"]
    # the MILP solves each budget on its own: a record per point, none copied to the top
    milp = run("solve", "--scenario", "paper-grid", "--budgets", "1,2", "--method", "milp")
    assert [p["value"] for p in milp["curve"]] == pytest.approx(GRID[1:], abs=5e-7)
    assert all(p["stats"]["formulation"] == "compact" for p in milp["curve"])
    assert "formulation" not in milp["stats"]


def test_simulate_and_files_written(tmp_path):
    trajectories = tmp_path / "runs.csv"
    document = run(
        "simulate",
        str(EXAMPLES / "trap.yaml"),
        "--runs",
        "4000",
        "--trajectories",
        str(trajectories),
    )
    assert document["written"] == [str(trajectories)] and trajectories.exists()
    assert document["value"] == pytest.approx(0.1, abs=1e-12)
    assert sum(t["runs"] for t in document["totals"].values()) == 4000
    assert {o["kind"] for o in document["outcomes"]} <= {"decoy", "goal"}


@pytest.mark.parametrize(
    "args",
    [
        ["show", str(EXAMPLES / "trap.yaml"), "-o", "{tmp}/trap.dot"],
        ["convert", str(EXAMPLES / "trap.yaml"), "--to", "drn", "-o", "{tmp}/trap.drn"],
        ["export-fsc", str(EXAMPLES / "trap.yaml"), "-o", "{tmp}/trap.fsc.json"],
        ["export-milp", str(EXAMPLES / "trap.yaml"), "-o", "{tmp}/trap.lp"],
        ["schema", "-o", "{tmp}/problem.schema.json"],
        ["scenario", "paper-grid", "-o", "{tmp}/grid.yaml"],
        [
            "scenario",
            "knapsack",
            "--weights",
            "1,2",
            "--values",
            "3,4",
            "--capacity",
            "2",
            "-o",
            "{tmp}/k.yaml",
        ],
        ["scenario", "sensor-grid", "--size", "6", "--sensors", "3", "-o", "{tmp}/s.yaml"],
        ["scenario", "drone", "--agents", "1", "--rows", "2", "-o", "{tmp}/d.yaml"],
        ["scenario", "random", "-o", "{tmp}/r.yaml"],
    ],
    ids=lambda args: " ".join(a for a in args[:2] if not a.startswith(("/", "{"))),
)
def test_commands_that_write_a_file_name_it_in_a_list(tmp_path, args):
    args = [a.format(tmp=tmp_path) for a in args]
    document = run(*args)
    command = " ".join(args[:2]) if args[0] == "scenario" else args[0]
    assert document["command"] == command
    output = args[args.index("-o") + 1]
    expected = [output]
    if command == "export-milp":  # the model, then the column map beside it
        expected.append(str(Path(output).with_suffix(".columns.json")))
    assert sorted(document["written"]) == sorted(expected)
    assert all(Path(path).exists() for path in document["written"])


@pytest.mark.parametrize("command", ["convert", "export-fsc", "schema"])
def test_text_to_stdout_is_content_with_nothing_written(command):
    args = [command] if command == "schema" else [command, str(EXAMPLES / "trap.yaml")]
    if command == "convert":
        args += ["--to", "prism"]
    document = run(*args)
    assert document["written"] == [] and document["content"]
    plain = runner.invoke(app, args)
    assert plain.stdout == document["content"]


def test_audit_and_harden_use_solve_names(tmp_path):
    """The attacker's optimum is `value` with its `alteration` whichever command reports it:
    harden with nothing to spend on protection, audit and solve agree at the grid's B = 2."""
    grid = ("--scenario", "paper-grid", "--budget", "2")
    solve = run("solve", *grid)
    audit = run("audit", *grid, "-o", str(tmp_path / "audit"))
    harden = run("harden", *grid, "--protect-budget", "0")
    for document in (solve, audit, harden):
        assert document["value"] == pytest.approx(GRID[2], abs=5e-7)
        assert document["alteration"] == solve["alteration"]
        assert document["objective"] == "probability" and document["status"] == "optimal"
        assert isinstance(document["time_s"], float)
    assert harden["curve"][0]["value"] == harden["value"]
    assert harden["curve"][0]["alteration"] == harden["alteration"]
    assert harden["value_unprotected"] == pytest.approx(GRID[2], abs=5e-7)
    assert set(harden["stats"]) == {"solves", "nodes", "pruned"}
    assert "report.md" in {Path(p).name for p in audit["written"]}
    assert audit["baseline_value"] == solve["baseline_value"]
    # protecting one sensor: the attacker's reply is again `value`/`alteration`, and worse
    protected = run("harden", *grid, "--protect-budget", "1")
    assert protected["value"] < harden["value"]
    assert not set(protected["alteration"]) & set(protected["protection"])


# -- the library writes the same names -----------------------------------------------------------


def _without_runtime(document: dict) -> dict:
    """A document's fields that do not depend on the run's timing or files written."""
    timing = {"time_s", "written", "schema", "command"}
    return {k: v for k, v in document.items() if k not in timing}


def test_library_to_dict_follows_the_result_schema():
    """Each result type's to_dict() is its command's JSON, field for field: it validates
    against that part of the schema, and the values are the CLI's for the same question
    (the grid's optimum at B = 1 from SPEC §3)."""
    problem = paper_grid(5)
    solved = misdirect.solve(problem, budgets=[0, 1])
    baseline = misdirect.evaluate(problem).probability
    evaluated = misdirect.evaluate(problem, problem.alteration({"o1": "o2"}))
    audited = misdirect.audit(problem, budget=1)
    hardened = misdirect.harden(problem, protect_budget=1, budget=1)
    library = {
        "solve": solved.to_dict(),
        "evaluate": dataclasses.replace(evaluated, baseline_value=baseline).to_dict(),
        "audit": audited.to_dict(),
        "harden": hardened.to_dict(),
    }
    for command, fields in library.items():
        checked(json.dumps({"schema": SCHEMA, "command": command, "written": [], **fields}))
    for command in ("solve", "evaluate", "audit"):  # harden's value is under protection
        assert library[command]["value"] == pytest.approx(GRID[1], abs=5e-7)
    point = Draft202012Validator({"$ref": "#/$defs/point", "$defs": result_schema()["$defs"]})
    for budget_point in solved.curve:
        assert not list(point.iter_errors(budget_point.to_dict()))
    assert [p["value"] for p in library["solve"]["curve"]] == pytest.approx(GRID[:2], abs=5e-7)
    # the CLI prints the library's fields: the same keys, and the same values but for timing
    grid = ("--scenario", "paper-grid")
    cli = {
        "solve": run("solve", *grid, "--budget", "1"),
        "audit": run("audit", *grid, "--budget", "1"),
        "harden": run("harden", *grid, "--budget", "1", "--protect-budget", "1"),
    }
    for command, document in cli.items():
        ours = _without_runtime(library[command])
        assert set(_without_runtime(document)) == set(ours), command
        assert document["value"] == ours["value"] and document["alteration"] == ours["alteration"]


def test_defence_results_read_by_the_json_names():
    """HardenResult, its curve points and AuditResult also answer to the JSON's names
    (`value`, `alteration`, ...): read-only aliases of the old fields, equal to to_dict()'s."""
    problem = paper_grid(5)
    hardened = misdirect.harden(problem, protect_budget=2, budget=2)
    document = hardened.to_dict()
    aliases = {
        "value": "value_after",
        "alteration": "best_reply",
        "upper_bound": "value_after_upper",
        "value_unprotected": "value_before",
    }
    for alias, old in aliases.items():
        assert getattr(hardened, alias) == getattr(hardened, old) == document[alias], alias
    assert hardened.value < hardened.value_unprotected
    for point, written in zip(hardened.curve, document["curve"], strict=True):
        assert point.value == point.probability == written["value"]
        assert point.alteration == point.attack == written["alteration"]
    with pytest.raises(AttributeError):  # read-only
        hardened.value = 0.0  # type: ignore[misc]
    audited = misdirect.audit(problem, budget=1)
    assert audited.value == audited.probability == audited.to_dict()["value"]


def test_errors_name_their_command(tmp_path):
    missing = run("solve", str(tmp_path / "nothing.yaml"), code=2)
    assert missing["command"] == "solve" and "not found" in missing["error"]["message"]
    bad = run(
        "scenario",
        "knapsack",
        "--weights",
        "x",
        "--values",
        "1",
        "--capacity",
        "1",
        "-o",
        str(tmp_path / "k.yaml"),
        code=2,
    )
    assert bad["command"] == "scenario knapsack" and bad["error"]["field"] == "--weights"


def test_every_command_is_covered():
    """Every registered command has a branch in the schema (a new one needs its own)."""
    import typer.main

    group = typer.main.get_command(app)
    names = []
    for name, command in group.commands.items():  # type: ignore[attr-defined]
        subcommands = getattr(command, "commands", None)
        names += [f"{name} {sub}" for sub in subcommands] if subcommands else [name]
    assert set(names) == set(result_schema()["else"]["properties"]["command"]["enum"])


# -- MILP-only flags ----------------------------------------------------------------------------


@pytest.mark.parametrize(
    "flag", [["--formulation", "compact"], ["--solver", "highs"], ["--mip-gap", "1e-9"]]
)
def test_milp_flags_imply_the_milp(flag):
    document = run("solve", "--scenario", "paper-grid", "--budget", "1", *flag)
    assert document["method"] == "milp"
    assert sum("implies --method milp" in note for note in document["notes"]) == 1
    assert document["value"] == pytest.approx(GRID[1], abs=5e-7)
    assert document["stats"]["formulation"] == "compact"
    plain = run("solve", "--scenario", "paper-grid", "--budget", "1")
    assert plain["method"] == "auto" and plain["notes"] == []
    shown = runner.invoke(app, ["solve", "--scenario", "paper-grid", "--budget", "1", *flag])
    assert shown.exit_code == 0, shown.output
    assert shown.stderr.count("implies --method milp") == 1  # the note once, not twice


def test_milp_options_imply_the_milp_in_the_library():
    """The library applies the CLI's rule: under method="auto" (the default) a MILP-only
    option runs the MILP, and the result says so in a note (it ran auto's exact search,
    certified by incremental, with no word)."""
    problem = paper_grid(5)
    result = misdirect.solve(problem, budgets=[1], formulation="paper", time_limit=5)
    assert result.method == "milp"
    assert result.final.stats.formulation == "paper"  # type: ignore[attr-defined]
    assert any("formulation implies method milp" in note for note in result.notes)
    plain = misdirect.solve(problem, budgets=[1])
    assert plain.method == "auto" and not any("implies" in note for note in plain.notes)
    named = misdirect.solve(problem, budgets=[1], method="milp", formulation="compact")
    assert named.method == "milp" and not any("implies" in note for note in named.notes)


def test_scip_without_a_method_runs_the_milp():
    pytest.importorskip("pyscipopt")
    result = misdirect.solve(paper_grid(5), budgets=[1], solver="scip")
    assert result.method == "milp" and result.final.certified_by == "milp"
    assert result.final.stats.solver == "scip"  # type: ignore[attr-defined]
    assert result.probability == pytest.approx(GRID[1], abs=5e-7)


def test_implied_method_is_the_one_rule():
    from misdirect.solvers.options import MILP_OPTIONS, implied_method

    for name in MILP_OPTIONS:
        assert implied_method("auto", ["time_limit", name]) == ("milp", [name])
        assert implied_method("exhaustive", [name]) == ("exhaustive", [])  # then refused
    assert implied_method("auto", ["time_limit", "threads", "pool"]) == ("auto", [])
    assert implied_method("milp", ["solver"]) == ("milp", [])


def test_paper_formulation_is_run_when_asked():
    """The issue's case: `--formulation paper` ran auto's exact search instead. Now the paper's
    MILP runs (its formulation named in the stats); it is a baseline, not exact, so its claim
    may disagree with the exact chain (a warning, exit code 1)."""
    args = ["solve", "--scenario", "paper-grid", "--budget", "1", "--formulation", "paper"]
    result = runner.invoke(app, [*args, "--time-limit", "5", "--json"])
    assert result.exit_code in (0, 1), result.output
    document = checked(result.stdout)
    assert document["method"] == "milp" and document["stats"]["formulation"] == "paper"


@pytest.mark.parametrize("method", ["auto", "exhaustive", "incremental", "branch-and-bound"])
def test_milp_flags_refused_with_another_method(method):
    result = runner.invoke(
        app, ["solve", "--scenario", "paper-grid", "--method", method, "--solver", "highs"]
    )
    assert result.exit_code == 2
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and re.search(r"--solver: .*--method milp only", lines[0]), lines
    document = run(
        "solve", "--scenario", "paper-grid", "--method", method, "--mip-gap", "0", code=2
    )
    assert document["error"]["field"] == "--mip-gap"


def test_every_problem_of_a_file_is_in_the_error_document(tmp_path):
    """A file with two schema problems: the error document lists both, and validates."""
    bad = tmp_path / "bad.yaml"
    text = (EXAMPLES / "trap.yaml").read_text()
    bad.write_text(
        text.replace("format: misdirect/v1", "format: misdirect/v1\nnonsense: 1\nalso: 2")
    )
    document = run("evaluate", str(bad), code=2)
    problems = document["error"]["problems"]
    assert len(problems) == 2 and any("nonsense" in p for p in problems)
    assert any("also" in p for p in problems)


def test_an_unknown_initial_state_does_not_hide_the_other_problems(tmp_path):
    """An unknown initial state was reported alone; the file's other wrong names (a
    transition's state, a decoy, a rule's action) came out only once it was fixed. Now all
    four are in one error."""
    bad = tmp_path / "names.yaml"
    bad.write_text(
        textwrap.dedent(
            """\
            format: misdirect/v1
            pomdp:
              states: [s0, s1, goal]
              actions: [a]
              initial: s9
              observe: {s0: o0, s1: o1, goal: g}
              transitions:
                - [s0, a, s1, 1.0]
                - [s1, a, goal, 1.0]
                - [s7, a, goal, 1.0]
              absorbing: [goal]
            controller:
              nodes: [n]
              initial: n
              rules:
                - {node: "*", obs: "*", action: b, next: n}
            deception:
              decoy: [goal, nowhere]
              budget: 1
            """
        )
    )
    problems = run("evaluate", str(bad), code=2)["error"]["problems"]
    assert len(problems) == 4, problems
    for where, name in [
        ("pomdp.initial", "s9"),
        ("pomdp.transitions[2]", "s7"),
        ("deception.decoy[1]", "nowhere"),
        ("controller.rules[0].action", "b"),
    ]:
        assert any(where in p and repr(name) in p for p in problems), (where, problems)


def test_controller_robust_follows_the_schema(tmp_path):
    """`controller robust --json` (issue 54) has its own branch: the bounds it proves, the
    rounds, and the controller file it wrote."""
    output = tmp_path / "robust.fsc.json"
    document = run(
        "controller", "robust", str(EXAMPLES / "trap.yaml"), "--budget", "1", "-o", str(output)
    )
    robust = document["robust"]
    assert document["written"] == [str(output)] and output.exists()
    assert robust["lower_bound"] <= robust["upper_bound"]
    assert robust["optimal"] == (robust["gap"] == 0)


def test_controller_robust_randomized_seeds_follow_the_schema(tmp_path):
    """`controller robust --randomized --json`: the seeds it started from (issue 54), each with
    its certified worst case, none better than the controller written."""
    output = tmp_path / "robust.fsc.json"
    document = run(
        "controller", "robust", str(EXAMPLES / "trap.yaml"), "--budget", "1", "--randomized",
        "--restarts", "1", "--baselines", "none", "-o", str(output),
    )  # fmt: skip
    seeds = document["robust"]["seeds"]
    assert "observation-blind" in {s["name"] for s in seeds}
    for seed in seeds:
        assert document["robust"]["worst_case"] <= seed["worst_case"] + 1e-9
