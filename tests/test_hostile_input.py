"""Hostile and extreme input (issue 15): every case found by fuzzing the CLI, as a fixed
regression test. The contract: exit 0 with a valid answer, or one line naming the file (or
option), the field and the reason, with exit code 2 (bad input, bad output path) or 1 (an I/O
failure such as a full disk); never a hang, a traceback or "wrote" for a file not written.
Each test is quick; none asserts a duration."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import yaml
from typer.testing import CliRunner

from misdirect.cli import MAX_GRID_SIZE, MAX_RUNS, Terminated, app
from misdirect.core import memory
from misdirect.core.product import check_product_fits
from misdirect.errors import ProblemError, WriteError
from misdirect.io import files as io_utils
from misdirect.scenarios import paper_grid
from misdirect.solvers.run import solve

runner = CliRunner()
EXAMPLES = Path(__file__).parent.parent / "examples"
TINY = EXAMPLES / "tiny.yaml"


def one_line_error(result, code: int = 2, *fragments: str) -> str:
    """The result failed with ``code`` and exactly one line on stderr, holding ``fragments``."""
    assert result.exit_code == code, (result.exit_code, result.output)
    assert result.exception is None or isinstance(result.exception, SystemExit)
    message = result.stderr
    assert message.startswith("error: "), message
    assert message.count("\n") == 1 and message.endswith("\n"), repr(message)
    assert "Traceback" not in result.output and "internal error" not in message
    assert "wrote" not in result.output
    for fragment in fragments:
        assert fragment in message, message
    return message


def evaluate(path: Path, *args: str):
    return runner.invoke(app, ["evaluate", str(path), *args])


# -- input: size, shape and kind of file --------------------------------------------------------


def billion_laughs() -> str:
    lines = ["format: misdirect/v1", 'a: &a ["lol", "lol", "lol", "lol", "lol", "lol", "lol"]']
    for i in range(1, 10):
        previous, this = chr(ord("a") + i - 1), chr(ord("a") + i)
        lines.append(f"{this}: &{this} [" + ", ".join([f"*{previous}"] * 9) + "]")
    return "\n".join(lines) + "\n"


@pytest.mark.parametrize(
    "name, text, words",
    [
        ("bomb.yaml", billion_laughs(), ["alias bomb", "line 7"]),
        ("brackets.yaml", "[" * 100_000 + "]" * 100_000, ["nested deeper than 64"]),
        ("dashes.yaml", "- " * 100_000 + "x\n", ["nested deeper than 64"]),
        ("maps.yaml", "".join(" " * i + "a:\n" for i in range(2000)), ["nested deeper"]),
        ("deep.json", "[" * 10_000 + "]" * 10_000, ["nested deeper than 64"]),
        ("deep-object.json", '{"a":' * 10_000 + "1" + "}" * 10_000, ["nested deeper"]),
    ],
    ids=["alias bomb", "10^5 brackets", "10^5 dashes", "deep maps", "deep JSON", "deep objects"],
)
def test_bombs_and_deep_nesting_are_refused(tmp_path, name, text, words):
    path = tmp_path / name
    path.write_text(text)
    message = one_line_error(evaluate(path), 2, str(path), *words)
    assert "invalid" in message


def test_duplicate_yaml_key_names_both_lines(tmp_path):
    path = tmp_path / "p.yaml"
    path.write_text(TINY.read_text().replace("deception:\n", "deception:\n  budget: 5\n", 1))
    line = path.read_text().splitlines().index("  budget: 1") + 1
    one_line_error(
        evaluate(path), 2, str(path), "duplicate key 'budget'", "first at line", f"line {line}"
    )


def test_duplicate_yaml_key_in_a_flow_mapping(tmp_path):
    path = tmp_path / "p.yaml"
    path.write_text(TINY.read_text().replace("{o1: {o2: 3}}", "{o1: {o2: 3, o2: 1}}"))
    one_line_error(evaluate(path), 2, "duplicate key 'o2'")


def test_duplicate_json_key_names_both_lines(tmp_path):
    document = yaml.safe_load(TINY.read_text())
    text = json.dumps(document, indent=1).replace('"budget": 1', '"budget": 1,\n  "budget": 9')
    path = tmp_path / "p.json"
    path.write_text(text)
    lines = [i + 1 for i, line in enumerate(text.splitlines()) if '"budget"' in line]
    one_line_error(
        evaluate(path),
        2,
        str(path),
        "duplicate key 'budget'",
        f"first at line {lines[0]}",
        f"line {lines[1]}",
    )


def test_yaml_merge_keys_may_override_and_anchors_still_work(tmp_path):
    text = TINY.read_text().replace(
        "deception:\n  decoy: [trap]\n  budget: 1\n",
        "base: &base {decoy: [trap], budget: 3}\ndeception:\n  <<: *base\n  budget: 1\n",
    )
    path = tmp_path / "p.yaml"
    path.write_text(text)
    # the merge itself is accepted; the extra top-level key is the schema's business
    one_line_error(evaluate(path), 2, "base", "unknown field")


def test_device_directory_and_fifo_are_refused_without_reading(tmp_path):
    one_line_error(evaluate(Path("/dev/zero")), 2, "/dev/zero", "is a device")
    one_line_error(evaluate(tmp_path), 2, str(tmp_path), "is a directory")
    fifo = tmp_path / "pipe.yaml"
    os.mkfifo(fifo)
    done = threading.Event()

    def unblock() -> None:  # should the FIFO ever be opened, end the read instead of hanging
        if not done.wait(30):
            with open(fifo, "w"):
                pass

    threading.Thread(target=unblock, daemon=True).start()
    try:
        one_line_error(evaluate(fifo), 2, str(fifo), "FIFO", "not a regular file")
    finally:
        done.set()


def test_oversized_file_is_refused_with_the_limit(tmp_path, monkeypatch):
    monkeypatch.setenv("MISDIRECT_MAX_FILE_BYTES", "100")
    one_line_error(evaluate(TINY), 2, str(TINY), "larger than the limit of 100 bytes")
    monkeypatch.setenv("MISDIRECT_MAX_FILE_BYTES", "lots")
    one_line_error(evaluate(TINY), 2, "MISDIRECT_MAX_FILE_BYTES")


def test_binary_garbage_is_one_line(tmp_path):
    path = tmp_path / "p.yaml"
    path.write_bytes(b"format: misdirect/v1\n\xff\xfe\x00garbage")
    one_line_error(evaluate(path), 2, str(path), "not UTF-8")


def test_nul_and_control_characters_in_the_file(tmp_path):
    path = tmp_path / "p.yaml"
    path.write_text(TINY.read_text().replace("name: tiny example", "name: tiny\x00\x1b[2J"))
    one_line_error(evaluate(path), 2, str(path))


def test_names_with_newlines_and_controls_stay_on_one_line(tmp_path):
    document = yaml.safe_load(TINY.read_text())
    document["pomdp"]["states"].append("bad\nstate\u2028x\x1b[31m")
    path = tmp_path / "p.json"
    path.write_text(json.dumps(document))
    message = one_line_error(evaluate(path), 2, str(path), "pomdp.observe")
    assert "bad\\nstate\\u2028x\\x1b[31m" in message
    result = runner.invoke(app, ["evaluate", str(TINY), "--alter", "o\n1=o2"])
    one_line_error(result, 2, "--alter", "'o\\n1'")


def test_paynt_controller_that_is_a_fifo(tmp_path):
    fifo = tmp_path / "robot.fsc.json"
    os.mkfifo(fifo)
    text = TINY.read_text()
    start = text.index("controller:")
    end = text.index("deception:")
    path = tmp_path / "p.yaml"
    path.write_text(text[:start] + "controller: {paynt: robot.fsc.json}\n" + text[end:])
    one_line_error(evaluate(path), 2, "controller.paynt", "FIFO")


# -- numbers on the command line ------------------------------------------------------------


@pytest.mark.parametrize(
    "args, option",
    [
        (["evaluate", "--scenario", "random", "--seed", "-1"], "--seed"),
        (["evaluate", "--scenario", "paper-grid", "--size", "1000000"], "--size"),
        (["simulate", str(TINY), "--runs", str(10**8)], "--runs"),
        (["simulate", str(TINY), "--seed", "-1"], "--seed"),
        (["simulate", str(TINY), "--samples", str(10**9)], "--samples"),
        (["solve", str(TINY), "--threads", "0"], "--threads"),
        (["solve", str(TINY), "--time-limit", "nan"], "--time-limit"),
        (["solve", str(TINY), "--budget", "5..2"], "--budget"),
        (["solve", str(TINY), "--budget", "1e999"], "--budget"),
        (["reproduce", "--sizes", "5,100000"], "--sizes"),
    ],
)
def test_numeric_options_are_checked_first(args, option):
    one_line_error(runner.invoke(app, args), 2, option)


def test_scenario_options_are_checked_before_writing(tmp_path):
    output = tmp_path / "p.yaml"
    for args, option in (
        (["random", "--seed", "-1"], "--seed"),
        (["random", "--states", str(10**9)], "--states"),
        (["paper-grid", "--size", str(MAX_GRID_SIZE + 1)], "--size"),
    ):
        one_line_error(runner.invoke(app, ["scenario", *args, "-o", str(output)]), 2, option)
    assert not output.exists()
    assert MAX_RUNS >= 100_000  # the default --runs stays allowed


def test_map_cell_that_is_a_non_ascii_digit(tmp_path):
    path = tmp_path / "map.yaml"
    text = (EXAMPLES / "paper-grid-map.yaml").read_text()
    assert "    . . . . 5" in text
    path.write_text(text.replace("    . . . . 5", "    ² . . . 5", 1))
    one_line_error(evaluate(path), 2, str(path), "grid.map", "'²'")


# -- --alter with observation names that contain "=" ------------------------------------------


def eq_problem(tmp_path, names=("o=0", "o=1", "o=2")) -> Path:
    text = TINY.read_text()
    for old, new in zip(("o0", "o1", "o2"), names, strict=True):
        text = text.replace(old, new)
    path = tmp_path / "eq.yaml"
    path.write_text(text)
    return path


def test_alter_accepts_names_with_equals_signs(tmp_path):
    path = eq_problem(tmp_path)
    result = runner.invoke(app, ["evaluate", str(path), "-a", "o=1=o=2", "--json"])
    assert result.exit_code == 0, result.output
    assert json.loads(result.stdout)["alteration"] == {"o=1": "o=2"}
    one_line_error(evaluate(path, "-a", "o=1=o=9"), 2, "--alter", "unknown observation 'o=9'")


def test_alter_that_reads_two_ways_is_ambiguous(tmp_path):
    path = eq_problem(tmp_path, names=("x", "x=y", "y=z"))
    text = path.read_text().replace("g]", "g, z]", 1)  # declare z too; no state emits it
    text = text.replace("  absorbing:", "  observations: [x, x=y, y=z, g, z]\n  absorbing:")
    path.write_text(text)
    one_line_error(evaluate(path, "-a", "x=y=z"), 2, "--alter", "ambiguous", "'x' -> 'y=z'")


# -- budgets beyond every alteration's cost ---------------------------------------------------


@pytest.mark.parametrize("method", ["exhaustive", "incremental"])
@pytest.mark.parametrize("budget", ["1e9", "0..1000000000", "1e308"])
def test_huge_budgets_are_clamped_not_enumerated(method, budget):
    result = runner.invoke(
        app, ["solve", str(TINY), "--method", method, "--budget", budget, "--json"]
    )
    assert result.exit_code == 0, result.output
    payload = json.loads(result.stdout)
    asked = float(budget.split("..")[-1])
    cap = 4.0  # tiny: o1 at most 3 (o1 -> o2), o2 at most 1
    assert payload["budget"] == asked  # reported at the budget asked for
    assert payload["budget_clamped_from"] == asked and payload["budget_clamped_to"] == cap
    curve = {point["budget"]: point for point in payload["curve"]}
    assert len(curve) <= 6 and asked in curve
    if cap in curve:  # the budget asked for is answered exactly like the cap
        assert curve[asked]["alteration"] == curve[cap]["alteration"]
        assert curve[asked]["value"] == curve[cap]["value"]


def test_huge_budget_in_the_file_is_clamped(tmp_path):
    path = tmp_path / "p.yaml"
    path.write_text(TINY.read_text().replace("budget: 1", "budget: 1e308"))
    result = runner.invoke(app, ["solve", str(path), "--method", "exhaustive", "--json"])
    assert result.exit_code == 0, result.output
    payload = json.loads(result.stdout)
    assert payload["budget"] == 1e308
    assert payload["budget_clamped_from"] == 1e308 and payload["budget_clamped_to"] == 4.0
    assert [point["budget"] for point in payload["curve"]] == [0, 1, 2, 3, 4, 1e308]


def test_clamping_keeps_one_answer_per_budget_asked():
    problem = paper_grid(5, budget=4)
    result = solve(problem, method="exhaustive", budgets=[0, 3, 50, 1e12])
    assert [point.budget for point in result.curve] == [0, 3, 50, 1e12]
    assert result.budget_clamped_to == 7.0 and result.budget_clamped_from == 1e12
    assert result.curve[2].alteration == result.curve[3].alteration
    assert result.curve[3].probability == pytest.approx(0.863622, abs=1e-6)


def test_clamped_range_lists_every_budget_asked():
    """tiny's most expensive alteration costs 4 (above); `--budget 0..7` asks for eight
    budgets and gets eight, those above 4 answered like 4 (it listed 0..4 and 7)."""
    result = runner.invoke(app, ["solve", str(TINY), "--budget", "0..7", "--json"])
    assert result.exit_code == 0, result.output
    payload = json.loads(result.stdout)
    assert payload["budget_clamped_from"] == 7.0 and payload["budget_clamped_to"] == 4.0
    curve = payload["curve"]
    assert [point["budget"] for point in curve] == [0, 1, 2, 3, 4, 5, 6, 7]
    for point in curve[5:]:
        assert point["alteration"] == curve[4]["alteration"]
        assert point["value"] == curve[4]["value"]


def test_budget_within_reach_is_not_clamped():
    result = runner.invoke(app, ["solve", str(TINY), "--budget", "2", "--json"])
    assert result.exit_code == 0, result.output
    payload = json.loads(result.stdout)
    assert payload["budget"] == 2.0 and payload["budget_clamped_from"] is None


# -- memory -------------------------------------------------------------------------------------


def test_product_that_cannot_fit_is_refused_with_its_size(monkeypatch):
    grid = paper_grid(5)  # built first: building it is checked against the memory too
    monkeypatch.setattr(memory, "MEMORY_CHECK_FLOOR", 0)
    monkeypatch.setattr(memory, "available_memory", lambda: 1000)
    with pytest.raises(ProblemError) as caught:
        check_product_fits(grid)
    assert "75 states" in str(caught.value) and "GiB" in str(caught.value)


# -- outputs ------------------------------------------------------------------------------------


@pytest.mark.parametrize("suffix", [".mps", ".lp"])
def test_export_milp_to_a_missing_directory(suffix):
    result = runner.invoke(app, ["export-milp", str(TINY), "-o", f"/nonexistent/dir/x{suffix}"])
    one_line_error(result, 2, "-o", "/nonexistent/dir", "does not exist")


def test_export_milp_writes_and_reports(tmp_path):
    output = tmp_path / "m.lp"
    result = runner.invoke(app, ["export-milp", str(TINY), "-o", str(output)])
    assert result.exit_code == 0, result.output
    assert (
        output.read_text().strip() and "wrote" in result.stdout
    )  # the summary, on stdout (issue 53)
    # the model and its column map, no temporary file left
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.columns.json", "m.lp"]


OUTPUT_COMMANDS = {
    "export-milp": ["export-milp", str(TINY), "-o"],
    "convert": ["convert", "--to", "prism", str(TINY), "-o"],
    "export-fsc": ["export-fsc", str(TINY), "-o"],
    "scenario": ["scenario", "paper-grid", "-o"],
    "schema": ["schema", "-o"],
    "show": ["show", str(TINY), "-o"],
    "simulate": ["simulate", str(TINY), "--runs", "10", "--trajectories"],
}


@pytest.mark.parametrize("command", OUTPUT_COMMANDS)
def test_output_to_a_directory_or_a_missing_folder(tmp_path, command):
    args = OUTPUT_COMMANDS[command]
    one_line_error(runner.invoke(app, [*args, str(tmp_path)]), 2, "is a directory")
    missing = tmp_path / "missing" / ("x.dot" if command == "show" else "x.mps")
    one_line_error(runner.invoke(app, [*args, str(missing)]), 2, "does not exist")


@pytest.mark.skipif(not Path("/dev/full").exists(), reason="needs /dev/full")
@pytest.mark.parametrize("command", ["convert", "export-fsc", "schema", "simulate", "scenario"])
def test_output_to_a_full_disk_is_an_io_error(command):
    result = runner.invoke(app, [*OUTPUT_COMMANDS[command], "/dev/full"])
    one_line_error(result, 1, "/dev/full", "No space left on device")


def test_reproduce_out_that_cannot_be_a_folder(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    result = runner.invoke(app, ["reproduce", "--out", str(blocker / "sub")])
    one_line_error(result, 2, "--out")
    one_line_error(runner.invoke(app, ["reproduce", "--out", str(blocker)]), 2, "--out")


def test_failed_write_leaves_the_old_file_and_no_temporary(tmp_path):
    target = tmp_path / "kept.txt"
    target.write_text("old")

    def broken(path: Path) -> None:
        path.write_text("half")
        raise OSError(28, "No space left on device")

    with pytest.raises(WriteError):
        io_utils.write_output(target, broken)
    assert target.read_text() == "old" and [p.name for p in tmp_path.iterdir()] == ["kept.txt"]
    io_utils.write_output(target, "new")
    assert target.read_text() == "new"


def test_convert_to_prism_escapes_names_it_cannot_hold(tmp_path):
    document = yaml.safe_load(TINY.read_text())
    document["name"] = "evil\nname"
    text = json.dumps(document).replace('"s1"', '"s\\n1"').replace('"b"', '"go left"')
    path = tmp_path / "p.json"
    path.write_text(text)
    output = tmp_path / "p.prism"
    result = runner.invoke(app, ["convert", "--to", "prism", str(path), "-o", str(output)])
    assert result.exit_code == 0, result.output
    assert "escaped" in result.stderr and "'go left' -> a1" in result.stderr
    prism = output.read_text()
    assert "evil\\nname" in prism and "1=s\\n1" in prism
    assert all(line.startswith("//") for line in prism.splitlines()[:5])
    stormpy = pytest.importorskip("stormpy")
    assert stormpy.parse_prism_program(str(output)).nr_modules == 1
    drn = tmp_path / "p.drn"
    result = runner.invoke(app, ["convert", "--to", "drn", str(path), "-o", str(drn)])
    assert result.exit_code == 0, result.output
    assert stormpy.build_model_from_drn(str(drn)).nr_states == 5


# -- Storm route (validated in storm_models.py): regression tests ------------------------------

STORM_PROBLEM = """format: misdirect/v1
pomdp: {%s}
controller: {nodes: [n], initial: n, rules: [{node: "*", obs: "*", action: a, next: n}]}
deception: {decoy: {label: decoy}, budget: 1}
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
\t\t1 : P1
\t\t2 : P2
state 1 {1} goal
\taction a
\t\t1 : 1
state 2 {1} decoy
\taction a
\t\t2 : 1
"""
PRISM = """pomdp
observables o endobservables
module m
  s : [0..2] init 0;
  o : [0..1] init 0;
  [a] s=0 -> 0.7 : (s'=1)&(o'=1) + 0.7 : (s'=2)&(o'=1);
  [a] s>0 -> 1 : true;
endmodule
label "decoy" = s=2;
"""


@pytest.mark.parametrize(
    "model, text, words",
    [
        ("bad.drn", DRN.replace("P1", "1.5").replace("P2", "-0.5"), ["1.5", "not in [0, 1]"]),
        (
            "noinit.drn",
            DRN.replace("P1", "0.5").replace("P2", "0.5").replace(" init\n", "\n"),
            ["no initial state"],
        ),
        ("bad.prism", PRISM, ["sum to 1.4"]),
    ],
)
def test_storm_models_are_validated(tmp_path, model, text, words):
    pytest.importorskip("stormpy")
    (tmp_path / model).write_text(text)
    kind = model.rsplit(".", 1)[1]
    path = tmp_path / "p.yaml"
    path.write_text(STORM_PROBLEM % f"{kind}: {model}")
    one_line_error(evaluate(path), 2, str(path), f"pomdp.{kind}", *words)


# -- signals ------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "raised, code, words", [(KeyboardInterrupt, 130, "interrupted"), (Terminated, 143, "SIGTERM")]
)
def test_interrupt_is_one_line_and_exit_code(monkeypatch, raised, code, words):
    def interrupted(*args, **kwargs):
        raise raised

    monkeypatch.setattr("misdirect.cli.solving.solve_problem", interrupted)
    result = runner.invoke(app, ["solve", str(TINY)])
    assert result.exit_code == code
    assert result.stderr == f"error: {'interrupted' if code == 130 else 'terminated (SIGTERM)'}\n"
    assert words in result.stderr


def _children(pid: int) -> list[int]:
    try:
        text = Path(f"/proc/{pid}/task/{pid}/children").read_text()
    except OSError:
        return []
    return [int(child) for child in text.split()]


@pytest.mark.skipif(not Path("/proc/self/task").exists(), reason="needs Linux /proc")
@pytest.mark.parametrize("sig, code", [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
def test_ctrl_c_during_a_highs_solve(sig, code):
    """Ctrl-C reaches the whole process group, HiGHS' worker included: one line, no traceback
    from either process, and the worker is gone."""
    command = [str(Path(sys.executable).parent / "misdirect"), "solve", "--scenario", "paper-grid"]
    command += ["--size", "25", "--method", "milp", "--budget", "0..7", "-q"]
    process = subprocess.Popen(
        command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, start_new_session=True
    )
    try:
        for _ in range(600):  # wait until the HiGHS worker runs (or the command ended)
            if _children(process.pid) or process.poll() is not None:
                break
            time.sleep(0.1)
        workers = _children(process.pid)
        assert workers, "the HiGHS worker never started"
        os.killpg(process.pid, sig)
        _, stderr = process.communicate(timeout=60)
    finally:
        if process.poll() is None:
            process.kill()
    assert process.returncode == code, stderr
    assert b"Traceback" not in stderr and stderr.count(b"\n") == 1, stderr
    for worker in workers:
        assert (
            not Path(f"/proc/{worker}").exists()
            or "Z" in Path(f"/proc/{worker}/stat").read_text().split()[2]
        )


@pytest.mark.parametrize(
    "args",
    [["solve", "--scenario", "paper-grid", "--seed", "abc"], ["solvx"], ["solve", "--nope"]],
)
def test_usage_errors_of_the_installed_command_are_one_line(args):
    """click's own usage errors (an option that does not parse, an unknown command or option)
    go through the console entry point: one line, exit 2, no usage block."""
    command = [str(Path(sys.executable).parent / "misdirect"), *args]
    done = subprocess.run(command, capture_output=True, text=True, timeout=60)
    assert done.returncode == 2
    assert done.stderr.startswith("error: misdirect") and done.stderr.count("\n") == 1
    assert "Usage" not in done.stderr and "Traceback" not in done.stderr
