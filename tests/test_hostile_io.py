"""Hostile input, second round (issue 29): Storm in a child process, names as text, overflow,
alterations given as arrays, a read-only install, signals during imports, atomic writes.

Every case the issue lists is a regression test here. The contract is the CLI's: exit 0 with an
answer, or one line naming the file (or option), the field and the reason with exit code 2 (bad
input) or 1 (an I/O failure); never a crash, a hang or a traceback. Expected values are worked
out by hand from the small models below. No test asserts a duration.
"""

from __future__ import annotations

import errno
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import yaml
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st
from typer.testing import CliRunner

import misdirect
from misdirect.cli import app
from misdirect.errors import ProblemError, WriteError
from misdirect.io import storm_guard
from misdirect.io.problem_file import parse_spec

runner = CliRunner()
ROOT = Path(__file__).resolve().parent.parent
TINY = (
    ROOT / "tests" / "data" / "tiny_hostile.yaml"
)  # the first tiny example, whose values the tests derive
COMMAND = str(Path(sys.executable).parent / "misdirect")


def one_line_error(result, code: int, *fragments: str) -> str:
    """The command failed with ``code`` and exactly one line on stderr holding ``fragments``."""
    assert result.exit_code == code, (result.exit_code, result.output)
    message = result.stderr
    assert message.startswith("error: ") and message.count("\n") == 1, repr(message)
    assert "Traceback" not in result.output and "internal error" not in message
    for fragment in fragments:
        assert fragment in message, message
    return message


# -- models: a 3-state POMDP, by hand Pr(reach decoy) = 0.5 ----------------------------------------

PRISM = """pomdp
observables o endobservables
module m
  s : [0..2] init 0;
  o : [0..1] init 0;
  [a] s=0 -> P1 : (s'=1)&(o'=1) + 0.5 : (s'=2)&(o'=1);
  [a] s>0 -> 1 : true;
endmodule
label "decoy" = s=2;
"""
DRN = """@type: POMDP
@parameters

@reward_models

@nr_states
3
@nr_choices
3
@model
state 0 {0} init
\taction a
\t\t1 : 0.5
\t\t2 : 0.5
state 1 {1} goal
\taction a
\t\t1 : 1
state 2 {OBS} decoy
\taction a
\t\t2 : 1
"""
PROBLEM = """format: misdirect/v1
pomdp: {%s: model.%s}
controller: {nodes: [n], initial: n, rules: [{node: "*", obs: "*", action: a, next: n}]}
deception: {decoy: %s, budget: 1}
"""


def storm_problem(tmp_path: Path, kind: str, model: str, decoy: str = "{label: decoy}") -> Path:
    (tmp_path / f"model.{kind}").write_text(model, encoding="utf-8")
    path = tmp_path / "p.yaml"
    path.write_text(PROBLEM % (kind, kind, decoy), encoding="utf-8")
    return path


def evaluate_json(path: Path):
    return runner.invoke(app, ["evaluate", str(path), "--json"])


# -- 1. Storm never crashes the process ----------------------------------------------------------


@pytest.fixture
def storm():
    return pytest.importorskip("stormpy")


def test_well_formed_models_still_load(tmp_path, storm):
    for kind, text in (("prism", PRISM.replace("P1", "0.5")), ("drn", DRN.replace("OBS", "1"))):
        result = evaluate_json(storm_problem(tmp_path, kind, text))
        assert result.exit_code == 0, result.output
        assert json.loads(result.stdout)["value"] == pytest.approx(0.5, abs=1e-12)


def test_prism_zero_over_zero_is_one_line_not_sigfpe(tmp_path, storm):
    """Storm's parser divides 0/0 as integers: SIGFPE in the child, one line here."""
    path = storm_problem(tmp_path, "prism", PRISM.replace("P1", "0/0"))
    one_line_error(evaluate_json(path), 2, str(path), "pomdp.prism", "model.prism", "SIGFPE")


def test_deeply_nested_prism_is_refused_before_storm(tmp_path, storm):
    deep = "(" * 2000 + "0.5" + ")" * 2000
    path = storm_problem(tmp_path, "prism", PRISM.replace("P1", deep))
    one_line_error(evaluate_json(path), 2, str(path), "model.prism", "2,000 deep", "200")


def test_nesting_just_within_the_limit_is_read(tmp_path, storm):
    limit = storm_guard.MAX_NESTING
    text = PRISM.replace("P1", "(" * (limit - 1) + "0.5" + ")" * (limit - 1))
    result = evaluate_json(storm_problem(tmp_path, "prism", text))
    assert result.exit_code == 0, result.output
    assert json.loads(result.stdout)["value"] == pytest.approx(0.5, abs=1e-12)


def test_deep_drn_label_expression_is_refused(tmp_path, storm):
    decoy = '{expression: "' + "(" * 5000 + "decoy" + ")" * 5000 + '"}'
    path = storm_problem(tmp_path, "drn", DRN.replace("OBS", "1"), decoy)
    one_line_error(evaluate_json(path), 2, str(path), "deception.decoy", "5,000 deep")


@pytest.mark.parametrize("negations, expected", [(50_000, 0.5), (50_001, 0.5)])
def test_long_negation_chains_are_counted_not_recursed(tmp_path, storm, negations, expected):
    """``!!…!decoy``: an even count is the decoy (state 2, reached with 0.5); an odd count is
    states 0 and 1, and state 0 is the start (Pr = 1 at once)... so compare with by-hand sets."""
    decoy = '{expression: "' + "!" * negations + 'decoy"}'
    path = storm_problem(tmp_path, "drn", DRN.replace("OBS", "1"), decoy)
    result = evaluate_json(path)
    if negations % 2:  # the decoy set holds the initial state: refused or 1, never a crash
        assert result.exit_code in (0, 2), result.output
        if result.exit_code == 0:
            assert json.loads(result.stdout)["value"] == pytest.approx(1.0)
        return
    assert result.exit_code == 0, result.output
    assert json.loads(result.stdout)["value"] == pytest.approx(expected, abs=1e-12)


@pytest.mark.parametrize(
    "observation", ["100000000", "-1", "99999999999999999999999", "1024"], ids=str
)
def test_drn_observation_ids_are_range_checked_first(tmp_path, storm, observation):
    path = storm_problem(tmp_path, "drn", DRN.replace("OBS", observation))
    one_line_error(evaluate_json(path), 2, str(path), "model.drn", "state 2", "observation")


def test_drn_observation_ids_with_gaps_are_read(tmp_path, storm):
    """Ids 0, 1, 7 in a 3-state file: gaps are allowed, within a few per state."""
    result = evaluate_json(storm_problem(tmp_path, "drn", DRN.replace("OBS", "7")))
    assert result.exit_code == 0, result.output
    assert json.loads(result.stdout)["value"] == pytest.approx(0.5, abs=1e-12)


def test_drn_state_count_beyond_the_file_is_refused(tmp_path, storm):
    text = DRN.replace("OBS", "1").replace("@nr_states\n3", "@nr_states\n1000000000")
    path = storm_problem(tmp_path, "drn", text)
    one_line_error(evaluate_json(path), 2, str(path), "@nr_states", "1000000000", "3 states")


def test_synthesize_with_a_crashing_program_is_one_line(tmp_path, storm):
    pytest.importorskip("paynt")
    model = tmp_path / "model.prism"
    model.write_text(PRISM.replace("P1", "0/0"))
    args = ["controller", "synthesize", str(model), "-o", str(tmp_path / "c.json")]
    result = runner.invoke(app, [*args, "--props", 'Pmax=? [F "decoy"]'])
    one_line_error(result, 2, "model.prism", "SIGFPE")
    assert not (tmp_path / "c.json").exists()


# the child process itself: crash, error, time and memory


def _segfault() -> None:
    os.kill(os.getpid(), signal.SIGSEGV)


def _refuse() -> None:
    raise ProblemError("no such label", source="m.yaml", field="deception.decoy")


def _sleep() -> None:
    time.sleep(30)


def _allocate() -> int:
    return int(np.ones(2 * 1024**3 // 8).sum())  # 2 GiB


def _arrays() -> dict:
    return {"a": np.arange(5), "b": (1.5, "x")}


isolated = pytest.mark.skipif(not storm_guard.isolation_enabled(), reason="needs Linux fork")


@isolated
def test_the_child_returns_plain_data():
    answer = storm_guard.run_isolated(_arrays, name="m", field="f")
    assert np.array_equal(answer["a"], np.arange(5)) and answer["b"] == (1.5, "x")


@isolated
def test_a_crash_in_the_child_is_a_problem_error():
    with pytest.raises(ProblemError, match=r"crashed reading m.prism \(SIGSEGV") as raised:
        storm_guard.run_isolated(_segfault, name="m.prism", field="pomdp.prism")
    assert raised.value.field == "pomdp.prism"


@isolated
def test_the_childs_problem_error_keeps_its_place():
    with pytest.raises(ProblemError) as raised:
        storm_guard.run_isolated(_refuse, name="m", field="f")
    error = raised.value
    assert (error.reason, error.source, error.field) == (
        "no such label",
        "m.yaml",
        "deception.decoy",
    )


@isolated
def test_the_child_is_stopped_at_the_time_limit(monkeypatch):
    monkeypatch.setenv(storm_guard.TIME_LIMIT_ENV, "0.5")
    with pytest.raises(ProblemError, match=r"did not finish reading m within 0\.5 s"):
        storm_guard.run_isolated(_sleep, name="m", field="f")


@isolated
def test_the_child_runs_out_of_memory_at_its_limit(monkeypatch):
    monkeypatch.setenv(storm_guard.MEMORY_ENV, str(256 * 1024**2))
    with pytest.raises(ProblemError, match="ran out of memory reading m"):
        storm_guard.run_isolated(_allocate, name="m", field="f")


@pytest.mark.parametrize("value", ["abc", "-1", "inf"])
def test_bad_limits_in_the_environment_are_one_line(monkeypatch, value):
    monkeypatch.setenv(storm_guard.TIME_LIMIT_ENV, value)
    with pytest.raises(ProblemError, match=storm_guard.TIME_LIMIT_ENV):
        storm_guard.run_isolated(_arrays, name="m", field="f")


def test_nesting_depth_counts_parentheses():
    assert storm_guard.nesting_depth("") == 0
    assert storm_guard.nesting_depth("(a) + ((b) * (c))") == 2
    assert storm_guard.nesting_depth(")))(") == 1  # stray ")" do not hide a "(" after them
    assert storm_guard.nesting_depth(")" * 500 + "(" * 300) == 300


# PRISM/DRN text mutations, read in the sandboxed child: an answer or one line, never a crash

NASTY = [
    "0/0",
    "(" * 300,
    ")",
    "{",
    "}",
    "-1",
    "1e308",
    "99999999999",
    "\x00",
    "[",
    ";",
    "'",
    ":",
    "/",
]


@st.composite
def mutated_model(draw) -> tuple[str, str]:
    kind = draw(st.sampled_from(["prism", "drn"]))
    text = PRISM.replace("P1", "0.5") if kind == "prism" else DRN.replace("OBS", "1")
    for _ in range(draw(st.integers(1, 3))):
        at = draw(st.integers(0, len(text) - 1))
        how = draw(st.sampled_from(["insert", "replace", "delete"]))
        fragment = draw(st.sampled_from(NASTY) | st.text(max_size=3))
        if how == "insert":
            text = text[:at] + fragment + text[at:]
        elif how == "replace":
            text = text[:at] + fragment + text[at + len(fragment) :]
        else:
            text = text[:at] + text[at + draw(st.integers(1, 6)) :]
    return kind, text


@settings(
    max_examples=40,
    deadline=None,
    derandomize=True,
    database=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)
@given(mutated_model())
def test_mutated_storm_models_answer_or_fail_in_one_line(tmp_path, storm, case):
    kind, text = case
    path = storm_problem(tmp_path, kind, text)
    result = evaluate_json(path)
    assert "Traceback" not in result.output
    if result.exit_code == 0:
        probability = json.loads(result.stdout)["value"]
        assert 0 <= probability <= 1 + 1e-9
    else:
        one_line_error(result, 2, str(path))


# -- 2. names are text -----------------------------------------------------------------------------


def _tiny(**changes) -> dict:
    document = yaml.safe_load(TINY.read_text())
    for key, value in changes.items():
        document[key] = value
    return document


def test_a_name_written_010_is_read_as_written_and_kept_apart_from_8(tmp_path):
    text = TINY.read_text().replace("s1: o1", "s1: 010").replace("s2: o2", "s2: 8")
    text = text.replace("obs: o1", "obs: 010").replace(
        "pairs: {o1: {o2: 3}}", "pairs: {010: {8: 3}}"
    )
    text = text.replace("forbidden: [[o2, o0]]", "forbidden: [[8, o0]]")
    path = tmp_path / "p.yaml"
    path.write_text(text)
    problem = misdirect.load_problem(path)
    observations = problem.pomdp.observations
    assert "010" in observations and "8" in observations
    o10, o8 = observations.index("010"), observations.index("8")
    assert problem.pomdp.observation_of[problem.pomdp.states.index("s1")] == o10
    assert problem.pomdp.observation_of[problem.pomdp.states.index("s2")] == o8
    assert problem.cost.row(o10)[o8] == 3  # the pair 010 -> 8 of the file


def test_keys_1_and_quoted_1_are_one_key_reported_twice(tmp_path):
    path = tmp_path / "p.yaml"
    path.write_text(
        TINY.read_text().replace("pairs: {o1: {o2: 3}}", 'pairs: {1: {o2: 3}, "1": {o2: 1}}')
    )
    one_line_error(runner.invoke(app, ["evaluate", str(path)]), 2, str(path), "duplicate key '1'")


def test_a_python_mapping_whose_keys_collide_as_names_is_refused():
    document = _tiny()
    document["deception"]["cost"]["pairs"] = {"o1": {"o2": 3, 1: 2, "1": 4}}
    with pytest.raises(ProblemError, match="keys 1 and '1' are the same name") as raised:
        parse_spec(document)
    assert raised.value.field == "deception.cost.pairs.o1"


# -- 3. overflow and non-finite values -------------------------------------------------------------


@pytest.mark.parametrize(
    "weights, values, option",
    [("1,1", "1e308,1e308", "--values"), ("1e308,1e308", "1,1", "--weights")],
)
def test_knapsack_sums_that_overflow_are_refused(tmp_path, weights, values, option):
    output = tmp_path / "k.yaml"
    args = ["scenario", "knapsack", "-o", str(output), "--weights", weights, "--values", values]
    one_line_error(runner.invoke(app, [*args, "--capacity", "1"]), 2, option, "sum")
    assert not output.exists()


@pytest.mark.parametrize("command", [["solve"], ["audit"], ["harden", "--protect-budget", "1"]])
def test_costs_whose_complete_alteration_overflows_are_refused(tmp_path, command):
    """o1 and o2 alterable at 1e308 each: a complete alteration costs 2e308, past the largest
    float (an OverflowError inside every command before)."""
    document = _tiny()
    document["deception"]["cost"] = {"default": 1.0e308, "forbidden": [["o2", "o0"]]}
    path = tmp_path / "p.yaml"
    path.write_text(yaml.safe_dump(document))
    result = runner.invoke(app, [command[0], str(path), *command[1:]])
    one_line_error(result, 2, str(path), "deception.cost", "largest number")
    with pytest.raises(ProblemError, match="largest number"):
        misdirect.problem_from_dict(document)
    # one sensor alterable at 1e308 sums to 1e308: a valid model
    document["deception"]["cost"]["protected"] = ["g", "o1"]
    assert misdirect.problem_from_dict(document).cost.default == 1e308


def test_a_problem_built_in_code_with_overflowing_costs_is_refused_by_solve():
    import dataclasses

    from misdirect.core.alterations import max_alteration_cost
    from misdirect.core.model import CostModel

    problem = misdirect.load_problem(TINY)
    huge = CostModel(
        problem.pomdp.n_observations, default=1.0e308, protected=problem.cost.protected
    )
    built = dataclasses.replace(problem, cost=huge)
    with pytest.raises(ProblemError, match="largest number") as raised:
        max_alteration_cost(built)
    assert raised.value.field == "deception.cost"
    with pytest.raises(ProblemError, match="largest number"):
        misdirect.solve(built)


def test_mip_gap_must_be_finite():
    result = runner.invoke(app, ["solve", str(TINY), "--method", "milp", "--mip-gap", "1e999"])
    one_line_error(result, 2, "--mip-gap", "finite")


def test_scip_parameters_out_of_range():
    pytest.importorskip("pyscipopt")
    base = ["solve", str(TINY), "--method", "milp", "--solver", "scip", "--json"]
    one_line_error(runner.invoke(app, [*base, "--threads", "1000"]), 2, "--threads", "64")
    result = runner.invoke(app, [*base, "--time-limit", "1e30"])  # SCIP's 1e20 s: no limit
    assert result.exit_code == 0, result.output
    assert json.loads(result.stdout)["value"] == pytest.approx(0.5, abs=1e-9)


@pytest.mark.parametrize("suffix", [".yaml", ".json"])
def test_an_integer_too_long_for_python_is_one_line(tmp_path, suffix):
    document = _tiny()
    text = json.dumps(document) if suffix == ".json" else TINY.read_text()
    text = text.replace('"budget": 1', '"budget": 1' + "0" * 5000)
    text = text.replace("budget: 1", "budget: 1" + "0" * 5000)
    path = tmp_path / f"p{suffix}"
    path.write_text(text)
    one_line_error(runner.invoke(app, ["evaluate", str(path)]), 2, str(path), "too long")


def test_a_lone_surrogate_in_a_name_is_one_line(tmp_path):
    text = json.dumps(_tiny()).replace('"o1"', '"o\\ud8001"')
    path = tmp_path / "p.json"
    path.write_text(text)
    message = one_line_error(runner.invoke(app, ["solve", str(path)]), 2, str(path), "surrogate")
    assert "\\ud800" in message


@pytest.mark.skipif(not Path("/dev/full").exists(), reason="needs /dev/full")
@pytest.mark.parametrize("problem", [str(TINY), "missing.yaml"], ids=["answer", "error"])
def test_json_to_a_full_stdout_is_one_line(problem):
    with open("/dev/full", "w") as full:
        done = subprocess.run(
            [COMMAND, "evaluate", problem, "--json"],
            stdout=full,
            stderr=subprocess.PIPE,
            text=True,
            timeout=120,
        )
    assert done.returncode != 0
    assert "Traceback" not in done.stderr and done.stderr.count("\n") == 1, done.stderr
    assert done.stderr.startswith("error: ")


# -- 4. alterations given as arrays to the library -------------------------------------------------


@pytest.mark.parametrize(
    "alteration, words",
    [
        ([0, -4, 2, 3], "sent to -4"),
        ([0, 0.9, 2, 3], "integer"),
        ([1, 1, 2, 3], "initial observation 'o0'"),
        ([0, 1, 2], "one observation index per observation (4)"),
        ([0, 1, 2, 4], "sent to 4"),
    ],
)
def test_array_alterations_are_checked(alteration, words):
    problem = misdirect.load_problem(TINY)
    for call in (misdirect.evaluate, misdirect.decoy_probability):
        with pytest.raises(ProblemError) as raised:
            call(problem, alteration)
        assert words in str(raised.value)


def test_a_valid_array_alteration_is_evaluated():
    """tiny.yaml by hand: s0 goes to s1 or s2 (1/2 each); s2 reads o2 and walks into the trap
    (the decoy); o1 -> o2 makes s1 read o2, whose rule also takes action a (to goal): 0.5."""
    problem = misdirect.load_problem(TINY)
    for alteration in ([0, 2, 2, 3], np.array([0, 2, 2, 3], dtype=np.int32)):
        assert misdirect.evaluate(problem, alteration).probability == pytest.approx(0.5)
        assert misdirect.decoy_probability(problem, alteration) == pytest.approx(0.5)


# -- 5. a read-only install, a read-only HOME, signals while importing ----------------------------


def _read_only_runner() -> list[str] | None:
    """How to run a command with /tmp-copies of the package and HOME read-only: a private
    mount namespace as root, file modes otherwise; None where neither works."""
    if os.geteuid() != 0:
        return []
    if shutil.which("unshare") is None:
        return None
    probe = subprocess.run(["unshare", "-m", "true"], capture_output=True)
    return ["unshare", "-m"] if probe.returncode == 0 else None


def test_a_read_only_install_and_home_still_run(tmp_path):
    wrapper = _read_only_runner()
    if wrapper is None:
        pytest.skip("cannot make a folder read-only here")
    sandbox = tmp_path / "ro"
    shutil.copytree(
        ROOT / "src" / "misdirect",
        sandbox / "src" / "misdirect",
        ignore=shutil.ignore_patterns("__pycache__"),
    )
    (sandbox / "home").mkdir()
    env = dict(os.environ, HOME=str(sandbox / "home"), PYTHONPATH=str(sandbox / "src"))
    env.pop("NUMBA_CACHE_DIR", None)
    env.pop("XDG_CACHE_HOME", None)
    env["TMPDIR"] = str(tmp_path / "tmp")
    (tmp_path / "tmp").mkdir()
    program = "from misdirect.cli import main; main()"
    solve = [sys.executable, "-c", program, "solve", "--scenario", "paper-grid", "--size", "5"]
    solve += ["--method", "exhaustive", "--json"]
    if wrapper:
        script = f'mount --bind -o ro {sandbox} {sandbox} && exec "$@"'
        command = [*wrapper, "sh", "-c", script, "sh", *solve]
    else:
        for folder, _, _ in os.walk(sandbox):
            os.chmod(folder, 0o555)
        command = solve
    try:
        done = subprocess.run(command, capture_output=True, text=True, env=env, timeout=300)
    finally:
        for folder, _, _ in os.walk(sandbox):
            os.chmod(folder, 0o755)
    assert done.returncode == 0, done.stderr
    assert "Traceback" not in done.stderr
    payload = json.loads(done.stdout)
    assert 0 <= payload["value"] <= 1


READ_ONLY_HOME_COMMANDS = [
    ["evaluate", "--scenario", "paper-grid", "--size", "5", "--json"],
    ["solve", "--scenario", "paper-grid", "--size", "6", "--budget", "0..2", "--json"],
    ["audit", "--scenario", "paper-grid", "--size", "5", "--budget", "1", "--json"],
    ["scenario", "random", "--seed", "3", "-o", "random.yaml"],
]


@settings(
    max_examples=4,
    deadline=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.function_scoped_fixture],
)
@given(
    argv=st.sampled_from(READ_ONLY_HOME_COMMANDS),
    cache_dir_set=st.booleans(),
)
def test_commands_under_a_read_only_home(tmp_path, argv, cache_dir_set):
    """The campaign's read-only HOME: any command, with or without XDG_CACHE_HOME pointing
    into it, runs to its normal end (numba's cache falls back), with no traceback."""
    wrapper = _read_only_runner()
    if not wrapper:  # as root only a read-only mount stops writes
        pytest.skip("cannot mount a folder read-only here")
    home, work = tmp_path / "home", tmp_path / "work"  # files are written in work
    home.mkdir(exist_ok=True)
    work.mkdir(exist_ok=True)
    env = dict(os.environ, HOME=str(home), PYTHONPATH=str(ROOT / "src"))
    env.pop("NUMBA_CACHE_DIR", None)
    env.pop("XDG_CACHE_HOME", None)
    if cache_dir_set:
        env["XDG_CACHE_HOME"] = str(home / ".cache")
    program = [sys.executable, "-c", "from misdirect.cli import main; main()", *argv]
    script = f'mount --bind -o ro {home} {home} && exec "$@"'
    done = subprocess.run(
        [*wrapper, "sh", "-c", script, "sh", *program],
        capture_output=True,
        text=True,
        env=env,
        timeout=300,
        cwd=work,
    )
    assert done.returncode == 0, done.stderr
    assert "Traceback" not in done.stderr, done.stderr
    assert not any(home.iterdir())  # nothing could be written there


@pytest.mark.skipif(sys.platform == "win32", reason="POSIX signals")
@pytest.mark.parametrize(
    "sig, code, words", [(signal.SIGINT, 130, "interrupted"), (signal.SIGTERM, 143, "SIGTERM")]
)
@pytest.mark.parametrize("launcher", ["script", "python -m"])
@pytest.mark.parametrize("moment", [0.15, 0.3])
def test_a_signal_while_importing_is_one_line(sig, code, words, launcher, moment):
    """0.15 to 0.3 s after start the command is importing its modules (numpy, scipy, numba,
    ...). ``python -m misdirect`` printed a traceback at any such moment: its ``__main__`` is
    not yet the package's while the package imports."""
    command = [COMMAND] if launcher == "script" else [sys.executable, "-m", "misdirect"]
    solve = ["solve", "--scenario", "paper-grid", "--size", "25", "--budget", "0..7", "-q"]
    returncode, stderr = _signalled([*command, *solve], sig, moment)
    assert returncode == code, stderr
    assert "Traceback" not in stderr and stderr.count("\n") == 1 and words in stderr, stderr


@pytest.mark.skipif(sys.platform == "win32", reason="POSIX signals")
@settings(max_examples=5, deadline=None, derandomize=True)
@given(
    moment=st.floats(0.05, 4.0),
    case=st.sampled_from([(signal.SIGINT, 130, "interrupted"), (signal.SIGTERM, 143, "SIGTERM")]),
)
def test_a_signal_at_any_moment_is_one_line(moment, case):
    """The campaign's signals at random moments: while importing, building, solving or
    printing, Ctrl-C and SIGTERM end the command with their exit code and words, or it had
    already finished (exit 0); never a traceback. Found by it: a signal during the
    interpreter's shutdown ends the process by that signal (the answer already printed)."""
    sig, code, words = case
    solve = ["solve", "--scenario", "paper-grid", "--size", "12", "--budget", "0..5", "-q"]
    returncode, stderr = _signalled([COMMAND, *solve], sig, moment)
    # a signal that came while CPython itself was starting (importing its site module, on a
    # loaded machine later than 0.05 s) came before any line of misdirect ran: not ours
    assume(not stderr.startswith("Fatal Python error: init_import_site"))
    # -sig: the signal came as the interpreter shut down, after the answer was printed and
    # the handlers were gone; a shell shows it as the same code (128 + sig)
    assert returncode in (0, code, -sig), stderr
    assert "Traceback" not in stderr, stderr
    if returncode == code:
        assert words in stderr, stderr


def _signalled(argv: list[str], sig: int, moment: float) -> tuple[int, str]:
    """(exit code, standard error) of ``argv`` sent ``sig`` ``moment`` seconds after start."""
    env = {**os.environ, "PYTHONPATH": str(ROOT / "src")}
    process = subprocess.Popen(
        argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env
    )
    try:
        time.sleep(moment)
        process.send_signal(sig)
        _, stderr = process.communicate(timeout=120)
    finally:
        if process.poll() is None:
            process.kill()
    return process.returncode, stderr


@pytest.mark.parametrize(
    "argv, main_file, ours",
    [
        (["python", "-m", "misdirect", "solve"], None, True),
        (["python", "-X", "dev", "-m", "misdirect.cli", "solve"], None, True),
        (["python", "-mmisdirect", "solve"], None, True),
        (["python", "-m", "pytest", "-q"], None, False),
        (["python", "script.py", "-m", "misdirect"], "/x/script.py", False),
        (["python", "-c", "import misdirect"], None, False),
        (["/venv/bin/python", "/venv/bin/misdirect", "solve"], "/venv/bin/misdirect", True),
    ],
)
def test_the_command_line_is_told_from_a_library_user(monkeypatch, argv, main_file, ours):
    """Only the command itself (its script, or ``python -m misdirect``) takes over Ctrl-C
    while importing; a program that imports misdirect keeps its own signals."""
    import types

    from misdirect import startup

    main = types.ModuleType("__main__")
    if main_file is not None:
        main.__file__ = main_file
    monkeypatch.setitem(sys.modules, "__main__", main)
    monkeypatch.setattr(sys, "orig_argv", argv, raising=False)
    assert startup._is_command_line() is ours


# -- 6. writes stay atomic ------------------------------------------------------------------------


def _disk_full(*args, **kwargs):
    raise OSError(errno.ENOSPC, "No space left on device")


def test_reproduce_tables_keep_the_earlier_file_on_a_full_disk(tmp_path, monkeypatch):
    from misdirect.report.reproduce import Table

    table = Table("t", "T", ["a"], [{"a": 1}])
    table.write(tmp_path)
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    monkeypatch.setattr(os, "fsync", _disk_full)
    with pytest.raises(WriteError, match="No space left"):
        Table("t", "T", ["a"], [{"a": 2}]).write(tmp_path)
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before  # and no temporary


def test_figures_keep_the_earlier_picture_on_a_full_disk(tmp_path, monkeypatch):
    import matplotlib.pyplot as plt

    from misdirect.report import figures

    stem = tmp_path / "fig"
    figures.save(plt.figure(), stem, formats=(".png",))
    before = (tmp_path / "fig.png").read_bytes()
    monkeypatch.setattr(plt.Figure, "savefig", _disk_full)
    with pytest.raises(WriteError):
        figures.save(plt.figure(), stem, formats=(".png",))
    assert (tmp_path / "fig.png").read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["fig.png"]


def test_a_model_highs_cuts_off_never_replaces_a_complete_one(tmp_path, monkeypatch):
    highspy = pytest.importorskip("highspy")
    output = tmp_path / "m.mps"
    assert runner.invoke(app, ["export-milp", str(TINY), "-o", str(output)]).exit_code == 0
    before = output.read_bytes()
    assert before.split()[-1] == b"ENDATA"

    def cut_off(self, path):  # what HiGHS does on a full disk: a partial file, and success
        Path(path).write_bytes(before[: len(before) // 2])
        return highspy.HighsStatus.kOk

    monkeypatch.setattr(highspy.Highs, "writeModel", cut_off)
    result = runner.invoke(app, ["export-milp", str(TINY), "-o", str(output)])
    one_line_error(result, 1, "incomplete")
    assert output.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.columns.json", "m.mps"]
