"""Every command clamps and bounds (issue 29): budgets past what buys everything, memory
estimated before building, deadlines and signals honoured, concurrent solves and writers."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

import misdirect
from misdirect.cli import app
from misdirect.core.alterations import alteration_space, options_bound
from misdirect.core.memory import MEMORY_LIMIT_ENV
from misdirect.core.model import Controller, CostModel, Pomdp, Problem
from misdirect.errors import ProblemError
from misdirect.io.problem_file import load_problem, write_problem
from misdirect.scenarios import paper_grid, random_problem, sensor_grid
from misdirect.solvers.deadline import CancelToken, Deadline, DeadlineExpiredError
from misdirect.solvers.milp.model import BUILD_BYTES_PER_NONZERO
from misdirect.solvers.milp.paper import build_paper, paper_size

runner = CliRunner()
TINY = Path(__file__).parent.parent / "examples" / "tiny.yaml"
# tiny's costs by hand: o1 -> o2 costs 3, o1 -> o0 and o2 -> o1 cost 1, o2 -> o0 is forbidden,
# g is protected, o0 is the initial observation: the most expensive complete alteration costs
# 3 + 1 = 4; within budget 1 both o1 and o2 are alterable, so protecting both costs 2
TINY_CAP = 4.0
TINY_PROTECT_ALL = 2.0


def invoke_json(*args: str) -> dict:
    result = runner.invoke(app, [*args, "--json"])
    assert result.exit_code == 0, result.output
    return json.loads(result.stdout)


# -- budgets past what buys everything --------------------------------------------------------


def test_audit_clamps_a_huge_budget_like_solve():
    payload = invoke_json("audit", str(TINY), "--budget", "1e308")
    assert payload["budget"] == 1e308
    assert payload["budget_clamped_from"] == 1e308 and payload["budget_clamped_to"] == TINY_CAP
    assert [p["budget"] for p in payload["curve"]] == [0, 1, 2, 3, 4, 1e308]
    at_cap = invoke_json("audit", str(TINY), "--budget", "4")
    assert at_cap["budget_clamped_from"] is None
    assert payload["value"] == at_cap["value"]
    assert payload["sensors"] == at_cap["sensors"]


def test_harden_clamps_huge_protection_and_attacker_budgets():
    payload = invoke_json("harden", str(TINY), "--protect-budget", "1e7")
    assert payload["protect_budget"] == 1e7
    assert payload["protect_budget_clamped_from"] == 1e7
    assert payload["protect_budget_clamped_to"] == TINY_PROTECT_ALL
    assert [p["protect_budget"] for p in payload["curve"]] == [0, 1, 2, 1e7]
    assert payload["curve"][-1]["protection"] == payload["curve"][-2]["protection"]
    assert payload["budget_clamped_from"] is None
    huge_b = invoke_json("harden", str(TINY), "--protect-budget", "1", "--budget", "1e300")
    assert huge_b["budget"] == 1e300 and huge_b["budget_clamped_to"] == TINY_CAP


def test_library_audit_and_harden_report_the_clamp():
    problem = load_problem(TINY)
    audited = misdirect.audit(problem, budget=1e12)
    assert (audited.budget_clamped_from, audited.budget_clamped_to) == (1e12, TINY_CAP)
    hardened = misdirect.harden(problem, protect_budget=1e9)
    assert hardened.protect_budget_clamped_to == TINY_PROTECT_ALL


# tiny with every cost times 10^9: its costs' unit is 10^9, so the budgets that matter are
# tiny's whole budgets times 10^9 (10^10 whole budgets listed one by one ran out of memory)
GIGA = 1e9


def _tiny_in_billions(tmp_path: Path) -> Path:
    text = TINY.read_text().replace("default: 1 ", f"default: {GIGA:.1e} ")
    text = text.replace("pairs: {o1: {o2: 3}}", f"pairs: {{o1: {{o2: {3 * GIGA:.1e}}}}}")
    path = tmp_path / "billions.yaml"
    path.write_text(text)
    return path


@pytest.mark.parametrize("method", ["exhaustive", "incremental"])
def test_solve_lists_huge_cost_budgets_in_the_costs_unit(tmp_path, method):
    path = _tiny_in_billions(tmp_path)
    payload = invoke_json("solve", str(path), "--method", method, "--budget", "1e10")
    unit = invoke_json("solve", str(TINY), "--method", method, "--budget", "10")
    assert [p["budget"] for p in payload["curve"]] == [b * GIGA for b in (0, 1, 2, 3, 4, 10)]
    assert [p["value"] for p in payload["curve"]] == [p["value"] for p in unit["curve"]]


def test_audit_and_harden_list_huge_cost_budgets_in_the_costs_unit(tmp_path):
    path = _tiny_in_billions(tmp_path)
    payload = invoke_json("audit", str(path), "--budget", "1e10")
    assert [p["budget"] for p in payload["curve"]] == [b * GIGA for b in (0, 1, 2, 3, 4, 10)]
    assert payload["value"] == invoke_json("audit", str(TINY), "--budget", "4")["value"]
    hardened = invoke_json(
        "harden", str(path), "--budget", "1e9", "--protect-budget", "1e10",
        "--protect-cost", f"default={GIGA:.0e}",
    )  # fmt: skip
    # protecting o1 and o2 (each 10^9) protects every sensor alterable within 10^9
    assert [p["protect_budget"] for p in hardened["curve"]] == [0, GIGA, 2 * GIGA, 1e10]


def test_default_budgets_unchanged_for_unit_costs_and_thinned_with_a_note():
    from misdirect.core.tolerance import CostScale
    from misdirect.solvers.run import default_budgets

    unit = CostScale.of([1.0], 5)
    assert default_budgets(999.0, unit) == [float(b) for b in range(1000)]
    assert default_budgets(4.5, unit) == [0.0, 1.0, 2.0, 3.0, 4.0, 4.5]
    # costs 3 and 2: a step of 1, past 1000 budgets every k-th whole one, said so
    notes: list[str] = []
    listed = default_budgets(10_000.0, CostScale.of([3.0, 2.0], 5000), most=1000, notes=notes)
    assert listed == [float(b) for b in range(0, 10_001, 11)] + [10_000.0]
    assert len(notes) == 1 and "every 11 of budget" in notes[0]
    # costs 2.5e9: every alteration costs a multiple of it, none is lost, nothing to say
    notes.clear()
    billions = default_budgets(1e10, CostScale.of([2.5e9], 4), notes=notes)
    assert billions == [0.0, 2.5e9, 5e9, 7.5e9, 1e10] and notes == []


@pytest.mark.parametrize("cost", ["1e308", "inf"])
def test_harden_refuses_protection_costs_past_the_largest_number(cost):
    result = runner.invoke(
        app, ["harden", str(TINY), "--protect-budget", "1", "--protect-cost", f"default={cost}"]
    )
    assert result.exit_code == 2, result.output
    assert "--protect-cost" in result.stderr and "Traceback" not in result.output
    with pytest.raises(ProblemError) as raised:
        misdirect.harden(load_problem(TINY), protect_budget=1, protect_costs={"default": 1e308})
    assert raised.value.field == "protect_costs"


# -- memory estimated before building -----------------------------------------------------------


def classes_problem(k: int, nodes: int = 6, seed: int = 0) -> Problem:
    """``k`` states in a line, each with its own observation, and a random controller on
    ``nodes`` nodes: about one behaviour class per observation, so every observation has
    about ``k`` candidate targets and the choice product about ``k² · nodes`` groups."""
    rng = np.random.default_rng(seed)
    line = np.arange(k)
    nxt = np.where(line + 1 < k, line + 1, k)  # the last state moves on to the goal
    pomdp = Pomdp.from_triplets(
        states=(*(f"s{i}" for i in range(k)), "goal", "decoy"),
        actions=("a0", "a1"),
        observations=tuple(f"o{i}" for i in range(k + 1)),
        initial_state=0,
        observation_of=np.concatenate([line, [k, k]]),
        action=np.repeat([0, 0, 1, 1], k),
        source=np.tile(line, 4),
        target=np.concatenate([nxt, np.full(k, k + 1), nxt, np.full(k, k)]),
        probability=np.repeat([0.9, 0.1, 0.9, 0.1], k),
        absorbing=np.arange(k + 2) >= k,
    )
    controller = Controller(
        nodes=tuple(f"n{i}" for i in range(nodes)),
        initial_node=0,
        action=rng.integers(0, 2, size=(nodes, k + 1)),
        update=rng.integers(0, nodes, size=(nodes, k + 1)),
    )
    return Problem(
        pomdp=pomdp,
        controller=controller,
        cost=CostModel(n_observations=k + 1),
        decoy=np.arange(k + 2) == k + 1,
        budget=1.0,
        name="many classes",
    )


def test_paper_milp_estimate_counts_the_model_it_builds():
    """The estimate is the paper's counting formula; the model built must agree with it."""
    for problem in (load_problem(TINY), sensor_grid(6, 4, seed=1)):
        variables, rows, nonzeros = paper_size(problem)
        model = build_paper(problem)
        assert (variables, rows) == (model.n_columns, model.n_rows)
        assert model.matrix.nnz <= nonzeros <= 1.05 * model.matrix.nnz


def test_paper_milp_too_large_is_refused_before_building(monkeypatch):
    monkeypatch.setenv(MEMORY_LIMIT_ENV, "1M")
    problem = sensor_grid(6, 4, seed=1)
    _, _, nonzeros = paper_size(problem)
    assert nonzeros * BUILD_BYTES_PER_NONZERO > 1024**2  # the limit is certainly exceeded
    with pytest.raises(ProblemError, match=r"paper's MILP .* needs about .* than the limit of"):
        misdirect.solve(problem, method="milp", formulation="paper", time_limit=5)


def test_memory_limit_option_refuses_and_does_not_leak(tmp_path):
    grid = tmp_path / "grid.yaml"
    write_problem(sensor_grid(6, 4, seed=1), grid)
    args = ["solve", str(grid), "--method", "milp", "--formulation", "paper"]
    result = runner.invoke(app, ["--memory-limit", "1M", *args, "--json"])
    assert result.exit_code == 2, result.output
    message = json.loads(result.stdout)["error"]["message"]
    assert "paper's MILP" in message and "limit of 0.00098 GiB" in message  # 1 MiB
    assert MEMORY_LIMIT_ENV not in os.environ  # restored after the command
    bad = runner.invoke(app, ["--memory-limit", "lots", "solve", str(TINY)])
    assert bad.exit_code == 2 and "--memory-limit" in bad.output and "Traceback" not in bad.output


def test_bad_memory_limit_variable_is_one_line(monkeypatch):
    monkeypatch.setenv(MEMORY_LIMIT_ENV, "-3G")
    result = runner.invoke(app, ["solve", str(TINY), "--method", "milp", "--json"])
    assert result.exit_code == 2
    assert MEMORY_LIMIT_ENV in json.loads(result.stdout)["error"]["message"]


def test_many_behaviour_classes_are_refused_through_harden(monkeypatch):
    k, nodes = 300, 6
    problem = classes_problem(k, nodes)
    # the behaviour classes counted independently: distinct (action, update) columns
    columns = np.vstack([problem.controller.action, problem.controller.update]).T
    classes = len({tuple(c) for c in columns})
    assert classes > 250
    # o1..o(k-1) are relevant (o0 is the initial observation), each with one candidate per
    # class; every other product state keeps its own reading
    groups = nodes * ((k - 1) * classes + 3)
    monkeypatch.setenv(MEMORY_LIMIT_ENV, "20M")
    with pytest.raises(ProblemError, match=f"choice product .*{groups:,} groups"):
        misdirect.harden(problem, protect_budget=2, time_limit=30)


@pytest.mark.parametrize("seed", range(12))
def test_options_bound_covers_the_alteration_space(seed):
    problem = random_problem(seed, states=7, observations=5, nodes=3, budget=2)
    bound = options_bound(problem)
    sizes = np.zeros_like(bound)
    for choice in alteration_space(problem).choices:
        sizes[choice.observation] = choice.size
    assert np.all(bound >= sizes)
    if problem.cost.default <= problem.budget and not problem.cost.pairs:
        assert np.array_equal(bound[sizes > 0], sizes[sizes > 0])


# -- signals: honoured within about a second at any moment ---------------------------------------

# a solve that never looks at its cancel token (as a long call into numpy or a solver would
# not): the command must still stop soon after SIGTERM or Ctrl-C, with the signal's exit code
STUCK_SOLVE = """
import sys, time
import misdirect.cli.solving as solving
def stuck(*args, **kwargs):
    sys.stderr.write("solving\\n"); sys.stderr.flush()
    end = time.monotonic() + 60
    while time.monotonic() < end:
        time.sleep(0.05)
    raise SystemExit(3)
solving.solve_problem = stuck
sys.argv = ["misdirect", "solve", sys.argv[1], "--json"]
from misdirect.cli import main
main()
"""


def run_until_started(script: str, *args: str) -> subprocess.Popen:
    env = {**os.environ, "PYTHONPATH": str(Path(misdirect.__file__).parent.parent)}
    process = subprocess.Popen(
        [sys.executable, "-c", script, *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        env=env,
    )
    assert process.stderr is not None
    assert process.stderr.readline() == b"solving\n"  # under way
    return process


@pytest.mark.parametrize(("sig", "code"), [(signal.SIGTERM, 143), (signal.SIGINT, 130)])
def test_a_solve_that_does_not_stop_is_stopped_hard_after_the_grace(sig, code):
    process = run_until_started(STUCK_SOLVE, str(TINY))
    try:
        process.send_signal(sig)
        stdout, stderr = process.communicate(timeout=20)  # far below the stuck 60 s
    finally:
        if process.poll() is None:
            process.kill()
    assert process.returncode == code, stderr
    message = json.loads(stdout)["error"]["message"]
    assert "stopped at once" in message
    assert stderr.decode().count("\n") == 1 and b"Traceback" not in stderr


def test_ctrl_c_under_scip_keeps_the_answers_without_an_lp_error():
    """SCIP's own Ctrl-C handler stopped it inside an LP ("error in LP solver"); the command's
    token stops it now, and the best answers so far are printed."""
    pytest.importorskip("pyscipopt")
    script = """
import sys
import misdirect.solvers.milp.backends as backends
original = backends.ScipBackend.solve
def announced(self, *args, **kwargs):
    sys.stderr.write("solving\\n"); sys.stderr.flush()
    return original(self, *args, **kwargs)
backends.ScipBackend.solve = announced
sys.argv = ["misdirect", "solve", "--scenario", "paper-grid", "--size", "25", "--method",
            "milp", "--solver", "scip", "--budget", "0..7", "--json"]
from misdirect.cli import main
main()
"""
    process = run_until_started(script)
    try:
        process.stderr.readline()  # budget 0 is quick; Ctrl-C lands in a later budget's solve
        process.send_signal(signal.SIGINT)
        stdout, stderr = process.communicate(timeout=60)
    finally:
        if process.poll() is None:
            process.kill()
    assert process.returncode == 130, stderr
    assert b"LP" not in stderr and b"SCIP failed" not in stderr
    payload = json.loads(stdout)
    assert payload["interrupted"] is True and len(payload["curve"]) == 8
    assert {p["status"] for p in payload["curve"]} <= {"optimal", "interrupted"}


# -- concurrency --------------------------------------------------------------------------------

WRITER = """
import sys
from pathlib import Path
from misdirect.io.files import write_output
path, letter = Path(sys.argv[1]), sys.argv[2]
content = letter * 500_000
for _ in range(20):
    write_output(path, content)
"""


def test_two_processes_writing_one_path_never_leave_a_torn_file(tmp_path):
    """Two writers race on one path while it is read over and over: every read is one whole
    file of one writer (500 kB of one letter), never a mix, a prefix or an empty file."""
    path = tmp_path / "out.txt"
    env = {**os.environ, "PYTHONPATH": str(Path(misdirect.__file__).parent.parent)}
    writers = [
        subprocess.Popen([sys.executable, "-c", WRITER, str(path), letter], env=env)
        for letter in "ab"
    ]
    try:
        while any(w.poll() is None for w in writers):
            if path.exists():
                data = path.read_bytes()
                assert len(data) == 500_000 and data.count(data[:1]) == len(data)
        assert [w.wait(timeout=120) for w in writers] == [0, 0]
    finally:
        for w in writers:
            if w.poll() is None:
                w.kill()
    final = path.read_bytes()
    assert final in (b"a" * 500_000, b"b" * 500_000)
    assert not [p for p in tmp_path.iterdir() if p != path]  # no temporary file left behind


# -- time limits: no work started past the deadline ------------------------------------------------


def test_audit_starts_no_solve_once_its_clock_has_expired(monkeypatch):
    """A cancelled audit (its clock expired) used to run every single-sensor and protected
    re-solve anyway, each at least 50 ms with its exact evaluations (5-10 s past the limit on a
    64-sensor network). Now it starts none, and what it reports stays sound: each criticality
    interval holds the value a full audit computes."""
    from misdirect.defence import attack

    problem = sensor_grid(6, 4, seed=1)
    full = misdirect.audit(problem, budget=2)
    calls = []
    original = attack.solve_at  # every solve of the audit goes through it (solve_many)
    monkeypatch.setattr(attack, "solve_at", lambda *a, **k: calls.append(1) or original(*a, **k))
    token = CancelToken()
    token.cancel()
    cut = misdirect.audit(problem, budget=2, cancel=token)
    assert calls == []
    truth = {row.observation: row for row in full.sensors}
    assert {row.observation for row in cut.sensors} == set(truth)
    for row in cut.sensors:
        exact = truth[row.observation]
        assert row.criticality - 1e-9 <= exact.criticality <= row.criticality_upper + 1e-9
        assert row.single_probability <= exact.single_probability + 1e-9
    # the online value is cut too: unknown, not a number (it took 14 s on a 300x300 grid)
    assert cut.online is None and full.online is not None
    assert any("online attacker's value is not computed" in note for note in cut.notes)


def test_a_cancelled_milp_curve_stops_handing_budgets_to_the_backend(monkeypatch):
    from misdirect.solvers.milp import backends

    calls = []
    original = backends.HighsBackend.solve

    def counted(self, *args, **kwargs):
        calls.append(1)
        return original(self, *args, **kwargs)

    monkeypatch.setattr(backends.HighsBackend, "solve", counted)
    token = CancelToken()
    token.cancel()
    result = misdirect.solve(load_problem(TINY), method="milp", budgets=[0, 1, 2, 3], cancel=token)
    assert calls == [] and result.interrupted
    assert all(p.upper_bound is None or p.upper_bound >= p.probability for p in result.curve)


class ExpiresAtLook(Deadline):
    """A deadline without a clock that expires at its ``n``-th look (and stays expired): a cut
    at a chosen point of the work, with no timing."""

    def __init__(self, n: int):
        super().__init__()
        self.left = n

    def expired(self) -> bool:
        self.left -= 1
        return self.left < 0 or super().expired()


def test_the_choice_product_build_stops_at_the_callers_check():
    """core knows no deadline: a caller's plain check, called between the build's stages, stops
    it (a 1000x1000 grid spent 10 s here past a 5 s limit)."""
    from misdirect.core.checkpoint import interruptible
    from misdirect.core.choice_product import build_choice_product

    problem = paper_grid(5)
    space = alteration_space(problem)
    looks: list[int] = []
    with interruptible(lambda: looks.append(1)):
        build_choice_product(problem, space)
    assert len(looks) >= 5  # stages between which it can stop
    deadline = ExpiresAtLook(2)
    with pytest.raises(DeadlineExpiredError), interruptible(deadline.check):
        build_choice_product(problem, space)
    assert deadline.left == -1  # stopped at the third look, not after the last


def test_a_solve_cut_while_building_the_choice_product_reports_the_unaltered_chain(monkeypatch):
    from misdirect.core import choice_product

    built = []
    original = choice_product.ChoiceProduct
    monkeypatch.setattr(
        choice_product, "ChoiceProduct", lambda *a, **k: built.append(1) or original(*a, **k)
    )
    problem = paper_grid(5)
    result = misdirect.solve(problem, budgets=[4], deadline=ExpiresAtLook(0))
    assert built == []  # the build stopped at its first stage
    (point,) = result.curve
    assert point.alteration == {} and point.status == "time_limit"
    # the unaltered chain's value, by the evaluation of one alteration
    assert point.probability == pytest.approx(
        misdirect.evaluate(problem, problem.identity()).probability
    )


def test_the_online_value_honours_its_deadline():
    """The online attacker's value (an MDP over the whole choice product) ran without a deadline:
    14 s of a 10 s audit on a 300x300 grid."""
    problem = paper_grid(5)
    for looks in (0, 3):  # before the build, and inside it
        with pytest.raises(DeadlineExpiredError):
            misdirect.online_attack_value(problem, None, deadline=ExpiresAtLook(looks))
    # the value computed in full is the one without a deadline
    assert misdirect.online_attack_value(
        problem, None, deadline=ExpiresAtLook(10**6)
    ).probability == pytest.approx(misdirect.online_attack_value(problem).probability)


def test_an_audit_whose_online_stage_is_cut_reports_it_as_unknown(tmp_path, monkeypatch):
    """Everything else done, the online value cut: null in --json (valid), "not computed" in the
    report, not a number that was never computed."""
    from misdirect.defence import auditing
    from misdirect.report.defence import write_audit_report
    from misdirect.report.json_output import audit as audit_json
    from result_schema import VALIDATOR

    original = auditing.online_attack_value

    def cut(problem, budget=None, *, deadline=None):  # the clock runs out inside this stage
        return original(problem, budget, deadline=ExpiresAtLook(0))

    monkeypatch.setattr(auditing, "online_attack_value", cut)
    problem = paper_grid(5)
    result = misdirect.audit(problem, budget=2)
    assert result.online is None
    assert result.status == "optimal"  # the other stages are untouched
    document = audit_json(result)
    assert document["online"] is None
    VALIDATOR.validate(json.loads(json.dumps(document)))
    write_audit_report(problem, result, tmp_path)
    report = (tmp_path / "report.md").read_text()
    assert "* not computed (the time limit was reached)." in report  # said once


def test_listing_millions_of_alterations_stops_at_the_callers_check(monkeypatch):
    """A block of 9.5 million alterations took 4 s to list and 2 s more to prepare before its
    first deadline check (sensor_grid(40, 128), `--method incremental --time-limit 5` ran for
    9.3 s): the listing now looks at the caller's check every chunk of rows."""
    from misdirect.core import alterations
    from misdirect.core.checkpoint import interruptible

    monkeypatch.setattr(alterations, "READBACK_CHUNK", 50)
    space = alteration_space(sensor_grid(8, 6, budget=3))
    whole = space.altered_within(3.0)
    looks: list[int] = []
    with interruptible(lambda: looks.append(1)):
        again = space.altered_within(3.0)
    assert whole is not None and again is not None
    assert all(np.array_equal(a, b) for a, b in zip(whole, again, strict=True))
    assert whole.costs.size > 500
    assert len(looks) >= whole.costs.size // 50  # a look per chunk read back
    deadline = ExpiresAtLook(3)
    with pytest.raises(DeadlineExpiredError), interruptible(deadline.check):
        space.altered_within(3.0)
    assert deadline.left == -1  # stopped at the fourth look


def test_an_enumeration_cut_while_listing_its_first_block_keeps_budget_zero(monkeypatch):
    """Cut before a single alteration is valued, the enumeration still proves budget 0 (the
    unaltered chain, valued on its own) and leaves every budget an alteration fits open."""
    from misdirect.core import alterations

    def expired() -> None:
        raise DeadlineExpiredError

    monkeypatch.setattr(alterations, "checkpoint", expired)
    problem = sensor_grid(8, 6, budget=2)
    cut = misdirect.solve(problem, method="incremental", budgets=[0, 1, 2])
    unaltered = misdirect.evaluate(problem, problem.identity())
    assert cut.curve[0].status == "optimal"
    assert cut.curve[0].probability == pytest.approx(unaltered.probability, abs=1e-12)
    assert [p.status for p in cut.curve[1:]] == ["time_limit", "time_limit"]
    monkeypatch.undo()
    full = misdirect.solve(problem, method="exhaustive", budgets=[2])
    assert cut.curve[2].probability < full.final.probability  # there was more to find
    assert all(p.upper_bound >= full.final.probability for p in cut.curve[1:])


def test_alterations_valued_on_their_own_systems_stop_at_the_deadline(monkeypatch):
    """On maps of tiny probabilities most deep alterations are valued on their own systems
    (175,000 of 1.2 million took 30 s past a 28 s share on sensor_grid(40, 16)): a chunk at a
    time now, and those the deadline leaves are unvalued, not wrong."""
    from misdirect.core.attack import prepare
    from misdirect.solvers.engines import lowrank_updates
    from misdirect.solvers.engines.lowrank import LowRankEnumeration

    problem = sensor_grid(20, 10)
    full = LowRankEnumeration(prepare(problem, 3)).run(3.0)
    assert full.complete_for(3.0)
    original = lowrank_updates._direct_corrections
    sizes: list[int] = []

    def two_chunks(alterations, tree, deltas, weight, deadline=None):
        sizes.append(alterations.size)
        return original(alterations, tree, deltas, weight, ExpiresAtLook(2))

    monkeypatch.setattr(lowrank_updates, "DIRECT_CHUNK", 16)
    monkeypatch.setattr(lowrank_updates, "_direct_corrections", two_chunks)
    cut = LowRankEnumeration(prepare(problem, 3)).run(3.0)
    assert sum(sizes) > 32  # more than two chunks' worth came to be valued on their own
    left = ~np.isfinite(cut.costs)
    # two chunks (of one width each, at most 16) valued, the rest left
    assert sum(sizes) - 32 * len(sizes) <= left.sum() < sum(sizes)
    assert not cut.complete_for(3.0)
    valued = ~left
    assert np.array_equal(cut.costs[valued], full.costs[valued])
    assert np.allclose(cut.values[valued], full.values[valued], rtol=1e-9, atol=1e-15)


def test_the_alterations_tree_is_indexed_between_looks_at_the_deadline(monkeypatch):
    """Indexing a block's alterations (28 million entries took 2 s past a 5 s limit on a big
    map) goes a chunk of entries at a time: a deadline that passes between two chunks leaves
    every alteration but the unaltered one unvalued, with the tree never finished."""
    from misdirect.core.attack import prepare
    from misdirect.solvers.engines import lowrank_updates
    from misdirect.solvers.engines.lowrank import LowRankEnumeration

    original = lowrank_updates._Tree.of
    trees: list[object] = []

    def recorded(altered, deltas, expired=None):
        tree = original(altered, deltas, expired)
        trees.append(tree)
        return tree

    monkeypatch.setattr(lowrank_updates, "TREE_CHUNK", 64)
    monkeypatch.setattr(lowrank_updates._Tree, "of", staticmethod(recorded))
    # looks before the tree: one on entry, one after listing; the third is between chunks
    cut = LowRankEnumeration(prepare(sensor_grid(20, 10), 2)).run(2.0, deadline=ExpiresAtLook(3))
    assert trees == [None]
    assert np.isfinite(cut.costs).sum() == 1 and cut.complete_for(0.0)
    assert not cut.complete_for(1.0)


def test_a_staged_runs_first_block_stops_where_its_share_ends():
    """A run with a share (auto, with a search to hand the budget to) always starts its first
    block; the block itself now stops at the share's end, not the solve's: with no share at
    all it values nothing but the unaltered alteration, and hands every budget on."""
    from misdirect.core.attack import prepare
    from misdirect.solvers.engines.lowrank import LowRankEnumeration

    enumeration = LowRankEnumeration(prepare(sensor_grid(20, 10), 3))
    cut = enumeration.run(3.0, share=0.0)
    assert cut.complete_for(0.0) and not cut.complete_for(1.0)
    assert np.isfinite(cut.costs).sum() == 1  # the unaltered alteration
    assert enumeration.run(3.0, share=60.0).complete_for(3.0)


def test_a_deadline_inside_the_exact_revaluation_keeps_the_unaltered_answer(monkeypatch):
    """`solve --scenario paper-grid --size 300 --budget 0..3 --time-limit 10` crashed (a max
    over no candidate): ill-conditioned bases are re-valued exactly, and a deadline passing
    there dropped every candidate, the unaltered one of cost 0 too."""
    from misdirect.solvers.engines import exact_revaluation, lowrank

    original = lowrank.LowRankEnumeration._verified

    def cut(self, found, steps, deadline, floor=None):  # the clock runs out right there
        return original(self, found, steps, ExpiresAtLook(0), floor)

    # every low-rank value counted as possibly off by 1: each may be the best, re-valued
    monkeypatch.setattr(lowrank, "update_error", lambda steps, scale: 1.0)
    monkeypatch.setattr(exact_revaluation, "update_error", lambda steps, scale: 1.0)
    monkeypatch.setattr(lowrank.LowRankEnumeration, "_verified", cut)
    problem = paper_grid(5)
    result = misdirect.solve(problem, method="incremental", budgets=[0, 1, 2])
    baseline = misdirect.evaluate(problem, problem.identity()).probability
    assert result.baseline_probability == pytest.approx(baseline)
    # budget 0 affords only the unaltered alteration: proven without any ranking
    assert result.curve[0].alteration == {} and result.curve[0].status == "optimal"
    # the others are left open with the unaltered alteration, not a guess
    for point in result.curve:
        assert point.alteration == {}
        assert point.probability == pytest.approx(baseline)
    assert [p.status for p in result.curve[1:]] == ["time_limit", "time_limit"]


def test_an_enumeration_with_nothing_valued_falls_back_to_the_unaltered_alteration(monkeypatch):
    """Should a run come back with no alteration valued within a budget, incremental answers
    it with the unaltered alteration, left open, instead of a max over nothing."""
    import dataclasses

    from misdirect.solvers.engines import lowrank

    def none_valued(self, found, steps, deadline, floor=None):
        return dataclasses.replace(found, costs=np.full_like(found.costs, np.inf), unevaluated=0.0)

    monkeypatch.setattr(lowrank.LowRankEnumeration, "_verified", none_valued)
    problem = paper_grid(5)
    result = misdirect.solve(problem, method="incremental", budgets=[0, 2])
    baseline = misdirect.evaluate(problem, problem.identity()).probability
    for point in result.curve:
        assert point.alteration == {} and point.probability == pytest.approx(baseline)
    assert [p.status for p in result.curve] == ["time_limit", "time_limit"]


class ExpiresOnCue(Deadline):
    """A deadline without a clock that expires once told to (and stays expired)."""

    def __init__(self) -> None:
        super().__init__()
        self.over = False

    def expired(self) -> bool:
        return self.over or super().expired()


def test_the_first_blocks_own_value_is_not_started_past_the_deadline(monkeypatch):
    """`solve --scenario paper-grid --size 600 --time-limit 5` reported 11.3 s: the first
    block's base solve ended past the deadline, and the unaltered chain was then solved again
    on its own (as long again). Started past the deadline, that value is now left undone, and
    the unaltered alteration is answered unvalued."""
    from misdirect.core.attack import prepare
    from misdirect.core.checkpoint import interruptible
    from misdirect.solvers.engines import lowrank

    deadline = ExpiresOnCue()
    original = lowrank.LowRankEnumeration._block_base

    def base_then_expire(self, *args, **kwargs):  # the clock runs out during the base solve
        base = original(self, *args, **kwargs)
        deadline.over = True
        return base

    monkeypatch.setattr(lowrank.LowRankEnumeration, "_block_base", base_then_expire)
    problem = paper_grid(5)
    enumeration = lowrank.LowRankEnumeration(prepare(problem, 2))
    # as under solve: listing the block's alterations stops at the deadline's check
    with interruptible(deadline.check):
        found = enumeration.run(2.0, deadline=deadline)
    assert enumeration.exact_evaluations == 0  # no chain solved after the deadline
    assert not np.isfinite(found.costs).any() and not found.complete_for(0.0)
    deadline.over = False
    result = misdirect.solve(problem, method="incremental", budgets=[0, 2], deadline=deadline)
    baseline = misdirect.evaluate(problem, problem.identity()).probability
    for point in result.curve:
        assert point.alteration == {} and point.probability == pytest.approx(baseline)
        assert point.status == "time_limit"


def test_time_s_of_a_search_cut_before_any_answer_leaves_out_the_exact_values(monkeypatch):
    """The 1000x1000 grid at a 5 s limit reported time_s 20.9: its method was cut before any
    answer, and the unaltered chain's exact value (the printed baseline: 14 s on a million
    states) was counted as search time. Exact values come on top of the limit, as after any
    other search. A clock that jumps 100 s on each exact value shows which side it is on."""
    from misdirect.solvers import run as run_module
    from misdirect.solvers.auto import AutoSolver
    from misdirect.solvers.certification import ExactValues

    clock = {"now": 0.0}
    monkeypatch.setattr(run_module.time, "perf_counter", lambda: clock["now"])
    valued = ExactValues.__call__

    def slow_exact(self, alteration):
        clock["now"] += 100.0
        return valued(self, alteration)

    def cut(self, problem, budgets, *, progress=None, deadline=None):
        clock["now"] += 3.0  # the search's own time
        raise DeadlineExpiredError

    monkeypatch.setattr(ExactValues, "__call__", slow_exact)
    monkeypatch.setattr(AutoSolver, "solve", cut)
    result = misdirect.solve(paper_grid(5), budgets=[1.0], time_limit=5)
    assert result.time_s == 3.0
    assert result.final.status.value == "time_limit"
    assert result.final.alteration == {}  # the unaltered chain, valued exactly
