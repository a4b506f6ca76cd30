"""Hostile input, third round (issue 51): regressions for what evaluate printed beside a proven
value, and for chains singular in double precision."""

from __future__ import annotations

import textwrap

import pytest
from typer.testing import CliRunner

from misdirect import evaluate, load_problem, solve
from misdirect.cli import app

runner = CliRunner()


def _leaking_loop(tmp_path, stay: str, leak: str, goal: str | None = None):
    """start -> loop; loop stays with ``stay`` and leaks into the decoy ``trap`` with ``leak``
    (and into ``goal`` with ``goal``). With nothing else, every run ends in the trap: value 1
    by hand, whatever the leak's size."""
    extra = f"\n    - [loop, a, goal, {goal}]" if goal else ""
    path = tmp_path / "leak.yaml"
    path.write_text(
        textwrap.dedent(
            f"""\
            format: misdirect/v1
            name: leaking loop
            pomdp:
              states: [start, loop, trap, goal]
              actions: [a]
              initial: start
              observe: {{start: o0, loop: o1, trap: g, goal: g}}
              transitions:
                - [start, a, loop, 1.0]
                - [loop, a, loop, {stay}]
                - [loop, a, trap, {leak}]"""
        )
        + extra
        + textwrap.dedent(
            """
            absorbing: [trap, goal]
            controller:
              nodes: [m]
              initial: m
              rules:
                - {node: "*", obs: "*", action: a, next: m}
            deception:
              decoy: [trap]
              budget: 0
            """
        ).replace("\nabsorbing", "\n  absorbing")
    )
    return path


def test_a_subnormal_way_out_is_valued_not_an_internal_error(tmp_path):
    """Item 9: {loop: 1 - 5e-324, trap: 5e-324} reads 1.0 and 5e-324 in doubles, and I - Q
    was exactly singular (an internal RuntimeError). The run leaves the loop surely: 1."""
    path = _leaking_loop(tmp_path, "1.0", "5.0e-324")
    report = evaluate(load_problem(path))
    assert report.probability == pytest.approx(1.0, rel=1e-12)
    assert report.outcomes == {}  # left out, and said so
    assert any("left out" in note for note in report.notes)
    point = solve(load_problem(path)).curve[0]
    assert point.probability == pytest.approx(1.0, rel=1e-12)
    result = runner.invoke(app, ["evaluate", str(path)])
    assert result.exit_code == 0 and "internal error" not in result.output


def test_outcomes_that_contradict_the_proven_value_are_left_out(tmp_path):
    """Item 4: a loop that leaks 1e-16 a step ends in the trap surely (value 1, by hand), but
    its first-entry solve read 0.9007 for the trap: printed beside Pr 1.0. Now every
    outcome shown is a distribution that agrees with the value, or none is shown, with a
    note."""
    path = _leaking_loop(tmp_path, "0.9999999999999999", "1.0e-16")
    report = evaluate(load_problem(path))
    assert report.probability == pytest.approx(1.0, rel=1e-9)
    if report.outcomes:
        assert report.outcomes.get("trap", 0.0) == pytest.approx(report.probability, rel=1e-9)
    else:
        assert any("left out" in note for note in report.notes)


def test_rows_a_little_over_one_never_print_an_outcome_over_one(tmp_path):
    """Item 4: rows whose doubles sum to 1 + 5e-11 are accepted as distributions (within
    1e-9); whatever is shown is within [0, 1] and sums to 1 with the trapped runs. By hand:
    the loop leaks to the trap with 0.3 and to the goal with 0.1 of each step's way out, so
    the trap takes 3/4."""
    path = _leaking_loop(tmp_path, "0.60000000005", "0.3", goal="0.1")
    report = evaluate(load_problem(path))
    assert report.probability == pytest.approx(0.75, rel=1e-9)
    shown = list(report.outcomes.values())
    assert all(0.0 <= p <= 1.0 for p in shown)
    if shown:
        assert sum(shown) + report.never_absorbed == pytest.approx(1.0, abs=1e-9)
        assert report.outcomes["trap"] == pytest.approx(0.75, rel=1e-9)


@pytest.mark.parametrize(
    ("args", "flag"),
    [
        (["scenario", "paper-grid", "--size", "2000"], "--size"),
        (["scenario", "sensor-grid", "--size", "1000"], "--size"),
        (["scenario", "drone", "--agents", "3", "--size", "8"], "--size"),
        (["scenario", "random", "--observations", "10000", "--states", "2"], "--observations"),
    ],
)
def test_scenarios_too_big_for_the_memory_limit_are_refused_before_building(tmp_path, args, flag):
    """Item 10: these passed 6 to 10 GB (and up to 284 s) under --memory-limit 3G; each is
    estimated first and refused in one line naming its flag, exit 2, nothing written."""
    import time

    out = tmp_path / "x.yaml"
    began = time.monotonic()
    result = runner.invoke(app, ["--memory-limit", "1G", *args, "-o", str(out)])
    assert result.exit_code == 2, result.output
    assert time.monotonic() - began < 10
    assert flag in result.output and "memory" in result.output
    assert not out.exists()


@pytest.mark.parametrize("budget", ["nan", "inf", "-1"])
def test_sensor_grid_refuses_a_budget_that_is_no_budget(tmp_path, budget):
    """Item 12: NaN, inf and -1 were written into the file."""
    out = tmp_path / "x.yaml"
    result = runner.invoke(app, ["scenario", "sensor-grid", f"--budget={budget}", "-o", str(out)])
    assert result.exit_code == 2 and "--budget" in result.output
    assert not out.exists()


def test_sensor_grid_checks_its_output_before_building(tmp_path):
    """Item 12: -o in a missing folder was found only after the grid was built (85 s)."""
    import time

    began = time.monotonic()
    target = tmp_path / "missing" / "x.yaml"
    result = runner.invoke(app, ["scenario", "sensor-grid", "--size", "1000", "-o", str(target)])
    assert result.exit_code == 2 and "-o" in result.output
    assert time.monotonic() - began < 10


def test_solve_with_no_budget_is_an_option_error():
    """Item 12: solve(problem, budgets=[]) raised a bare ValueError."""
    from misdirect import OptionError
    from misdirect.scenarios import paper_grid

    with pytest.raises(OptionError, match="budget"):
        solve(paper_grid(5), budgets=[])


@pytest.mark.parametrize("command", ["audit", "harden"])
def test_a_report_folder_is_not_created_for_an_input_that_does_not_load(tmp_path, command):
    """Issue 51 (questionable, decided): `audit -o DIR` created DIR before reading its input;
    an input that does not load now leaves nothing behind."""
    folder = tmp_path / "report"
    result = runner.invoke(app, [command, str(tmp_path / "missing.yaml"), "-o", str(folder)])
    assert result.exit_code == 2
    assert not folder.exists()


@pytest.mark.parametrize("columns", ["0", "abc"])
def test_a_terminal_width_that_is_no_width_still_prints(columns):
    """Item 12: COLUMNS=0 printed nothing at all (rich's width 0)."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    trap = Path(__file__).resolve().parent.parent / "examples" / "trap.yaml"
    env = {**os.environ, "COLUMNS": columns}
    done = subprocess.run(
        [sys.executable, "-m", "misdirect", "evaluate", str(trap)],
        capture_output=True,
        text=True,
        env=env,
        timeout=120,
    )
    assert done.returncode == 0, done.stderr
    assert "0.100000" in done.stdout  # the corridor unaltered: 0.4 x 0.25, by hand


def test_too_little_address_space_is_one_line_not_an_import_traceback(tmp_path):
    """Item 12: under a 400 MB address-space limit, numba's compiler (llvmlite) cannot load
    while the command imports: a traceback from deep in an import. Now one line and exit 1
    (or, where the libraries fit, the command runs)."""
    import resource
    import subprocess
    import sys

    def limit() -> None:
        resource.setrlimit(resource.RLIMIT_AS, (400 * 1024**2, 400 * 1024**2))

    done = subprocess.run(
        [sys.executable, "-m", "misdirect", "scenario", "random", "-o", str(tmp_path / "r.yaml")],
        capture_output=True,
        text=True,
        preexec_fn=limit,
        timeout=120,
    )
    assert "Traceback" not in done.stderr
    if done.returncode != 0:
        assert done.returncode == 1
        assert done.stderr.startswith("error: misdirect could not start")
        assert len(done.stderr.strip().splitlines()) == 1


def test_a_thread_that_cannot_start_is_one_line_not_an_internal_error(tmp_path, monkeypatch):
    """Under the same address-space limit, a command that got past its imports failed to
    start a thread (its stack did not fit) and said "internal error: RuntimeError: can't
    start new thread". It is the same want of resources as at import: said so, exit 1; any
    other RuntimeError is still an internal error."""
    from typer.testing import CliRunner

    import misdirect.cli.models as models
    from misdirect.cli import app

    def no_thread(*args, **kwargs):
        raise RuntimeError("can't start new thread")

    monkeypatch.setattr(models, "random_problem", no_thread)
    result = CliRunner().invoke(app, ["scenario", "random", "-o", str(tmp_path / "r.yaml")])
    assert result.exit_code == 1
    assert "misdirect could not start a thread" in result.output
    assert "internal error" not in result.output and "ulimit -v" in result.output

    def a_bug(*args, **kwargs):
        raise RuntimeError("something else")

    monkeypatch.setattr(models, "random_problem", a_bug)
    result = CliRunner().invoke(app, ["scenario", "random", "-o", str(tmp_path / "r.yaml")])
    assert result.exit_code == 1 and "internal error: RuntimeError: something else" in result.output
