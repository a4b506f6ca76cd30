"""Monitors and stealth (issue 52, first slice): Pr(reach a decoy before the alarm).

Every expected value comes from outside :mod:`misdirect.core.monitor`: worked out by hand, or
from :func:`reference`, a product of world, controller and monitor coded here (explicit
``(state, node, monitor state)`` triples, the monitor a Python function, the consistency
monitor's supports computed as frozensets), solved densely; brute force enumerates every
alteration the budget affords.
"""

from __future__ import annotations

import itertools
import json
from pathlib import Path

import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

import misdirect
from misdirect.cli import app
from misdirect.core.monitor import (
    Monitor,
    Transition,
    consistency_monitor,
    with_monitor,
)
from misdirect.errors import ProblemError
from misdirect.scenarios import paper_grid, random_problem
from watched import HAND, HAND_MONITOR

runner = CliRunner()
ALARM = object()

# -- a hand-made problem: tests/watched.py (HAND, HAND_MONITOR) -----------------------------


def _hand_step(m, o, a):  # HAND_MONITOR, coded again
    if m == "start":
        return "run"
    return ALARM if o == "o0" else "run"


# -- the reference: an independent product ------------------------------------------------------


def reference(problem, alpha, step, m0):
    """(Pr(decoy before alarm), Pr(alarm first)) of ``problem`` (unmonitored) under ``alpha``
    watched by ``step(m, reading name, action name) -> m' | ALARM``, from ``m0``."""
    pomdp, controller = problem.pomdp, problem.controller
    n_s = pomdp.n_states
    dense = pomdp.transitions.toarray()
    successors = [np.flatnonzero(row).tolist() for row in dense]
    obs, acts = pomdp.observations, pomdp.actions
    start = (pomdp.initial_state, controller.initial_node, m0)
    index, order, rows, alarm = {start: 0}, [start], [], []
    i = 0
    while i < len(order):
        s, n, m = order[i]
        i += 1
        row: dict[int, float] = {}
        caught = 0.0
        if not (problem.decoy[s] or pomdp.absorbing[s]):
            o = int(alpha[pomdp.observation_of[s]])
            for a, n2, p in controller.move_table(int(controller.move[n, o])):
                m2 = step(m, obs[o], acts[a])
                if m2 is ALARM:
                    caught += p
                    continue
                for s2 in successors[a * n_s + s]:
                    key = (s2, n2, m2)
                    if key not in index:
                        index[key] = len(order)
                        order.append(key)
                    row[index[key]] = row.get(index[key], 0.0) + p * dense[a * n_s + s, s2]
        rows.append(row)
        alarm.append(caught)
    q = len(order)
    matrix = np.zeros((q, q))
    for k, row in enumerate(rows):
        for j, p in row.items():
            matrix[k, j] += p
    decoy = np.array([bool(problem.decoy[s]) for s, _, _ in order])
    return _reach(matrix, decoy.astype(float)), _reach(matrix, np.array(alarm))


def _reach(matrix, gain):
    """Least solution of x = matrix x + gain (gain: mass leaving to the target): 0 on states
    that cannot collect any gain, a direct solve on the rest."""
    q = matrix.shape[0]
    can = gain > 0
    changed = True
    while changed:
        more = can | ((matrix[:, can] > 0).any(axis=1))
        changed = bool((more != can).any())
        can = more
    # a decoy state collects its own 1 and stops: it is a row of the system with no successor
    x = np.zeros(q)
    live = np.flatnonzero(can)
    if live.size:
        sub = matrix[np.ix_(live, live)]
        x[live] = np.linalg.solve(np.eye(live.size) - sub, gain[live])
    return float(x[0])


def consistency_step(problem):
    """The consistency monitor, coded here: the predicted support as a frozenset."""
    pomdp = problem.pomdp
    n_s = pomdp.n_states
    dense = pomdp.transitions.toarray()
    emits = {
        o: {s for s in range(n_s) if pomdp.observations[pomdp.observation_of[s]] == o}
        for o in pomdp.observations
    }
    action = {a: k for k, a in enumerate(pomdp.actions)}
    seen: dict = {}

    def step(support, o, a):
        key = (support, o, a)
        if key not in seen:
            here = support & emits[o]
            k = action[a]
            seen[key] = (
                frozenset(int(t) for s in here for t in np.flatnonzero(dense[k * n_s + s]))
                if here
                else ALARM
            )
        return seen[key]

    return step, frozenset({pomdp.initial_state})


def affordable(problem, budget):
    """Every alteration whose cost fits ``budget`` (the initial observation never altered),
    by how many observations it alters: none, one, two, ... while the cheapest change fits."""
    n = problem.pomdp.n_observations
    o_init = problem.pomdp.initial_observation
    rows = {o: problem.cost.row(o) for o in range(n) if o != o_init}
    cheapest = min(float(np.delete(row, o).min()) for o, row in rows.items())
    for size in range(len(rows) + 1):
        if size and size * cheapest > budget:
            return
        for changed in itertools.combinations(sorted(rows), size):
            targets = [[t for t in range(n) if t != o] for o in changed]
            for chosen in itertools.product(*targets):
                alpha = np.arange(n, dtype=np.int64)
                alpha[list(changed)] = chosen
                if problem.cost.fits(alpha, budget):
                    yield alpha


# -- (a) the hand-made problem ------------------------------------------------------------------


def _hand(**monitor):
    document = dict(HAND)
    if monitor:
        document["monitor"] = monitor
    return misdirect.problem_from_dict(document)


def test_hand_made_unconstrained_attack_is_caught_and_the_stealthy_one_differs():
    plain, watched = _hand(), _hand(**HAND_MONITOR)
    best = misdirect.solve(plain, budgets=[1])
    assert best.probability == pytest.approx(0.5, abs=1e-12)  # by hand
    assert best.alteration == {"o2": "o0"}
    caught = misdirect.evaluate(watched, {"o2": "o0"})
    assert caught.probability == pytest.approx(0.0, abs=1e-12)  # caught before it falls
    assert caught.alarm_probability == pytest.approx(0.5, abs=1e-12)
    assert {row["kind"] for row in caught.outcome_list()} == {"goal", "alarm"}
    stealthy = misdirect.solve(watched, budgets=[1])
    assert stealthy.probability == pytest.approx(0.15, abs=1e-12)  # 0.5 * 0.3, by hand
    assert stealthy.alteration == {"o1": "g"}
    assert str(stealthy.status) == "optimal"
    assert misdirect.evaluate(watched, {"o1": "g"}).alarm_probability == 0.0


def test_hand_made_every_alteration_against_the_reference():
    plain, watched = _hand(), _hand(**HAND_MONITOR)
    values = []
    for alpha in affordable(plain, 3.0):
        value, alarm = reference(plain, alpha, _hand_step, "start")
        report = misdirect.evaluate(watched, alpha)
        assert report.probability == pytest.approx(value, abs=1e-12)
        assert report.alarm_probability == pytest.approx(alarm, abs=1e-12)
        values.append((plain.cost.cost(alpha), value))
    for budget in (0, 1, 2, 3):
        brute = max(v for c, v in values if c <= budget)
        result = misdirect.solve(watched, budgets=[budget], method="exhaustive")
        assert result.probability == pytest.approx(brute, abs=1e-12)


def test_the_monitor_reads_the_altered_reading_and_the_alteration_space_is_unchanged():
    plain, watched = _hand(), _hand(**HAND_MONITOR)
    # the same observations and cost model: an alteration of one is one of the other
    assert watched.pomdp.observations == plain.pomdp.observations
    assert np.array_equal(watched.cost.matrix(), plain.cost.matrix())
    assert with_monitor(plain, consistency_monitor(plain)).cost is plain.cost
    assert np.array_equal(watched.relevant_observations, plain.relevant_observations)
    sink = watched.alarm_state
    assert watched.pomdp.states[sink] == "alarm"
    assert watched.pomdp.absorbing[sink] and not watched.decoy[sink]
    # the sink emits the initial observation, which is never altered
    assert watched.pomdp.observation_of[sink] == plain.pomdp.initial_observation
    with pytest.raises(ProblemError, match="never altered"):
        watched.alteration({"o0": "o1"})
    # the unaltered run reads o0 once: no alarm; reading o0 later (altered) raises it
    assert misdirect.evaluate(watched).alarm_probability == 0.0
    assert misdirect.evaluate(watched, {"o1": "o0"}).alarm_probability == pytest.approx(0.5)


def test_an_action_guard():
    """A monitor that raises the alarm on the action a read with g (what o1 -> g does at s1,
    1/2 of the runs), and lets b pass."""
    monitor = {
        "states": ["ok", "bad"],
        "initial": "ok",
        "alarm": ["bad"],
        "transitions": [
            {"state": "ok", "reading": "g", "action": "a", "next": "bad"},
            {"state": "ok", "reading": "*", "next": "ok"},
        ],
    }
    watched = _hand(**monitor)
    report = misdirect.evaluate(watched, {"o1": "g"})
    assert report.probability == 0.0 and report.alarm_probability == pytest.approx(0.5)
    # o2 -> o0 is not seen: the alarm waits for g, read only in goal and trap (the run has
    # ended there)
    report = misdirect.evaluate(watched, {"o2": "o0"})
    assert report.probability == pytest.approx(0.5) and report.alarm_probability == 0.0


# -- random problems, random monitors: brute force against the reference -----------------------


def _random_monitor(problem, rng, size):
    obs, acts = problem.pomdp.observations, problem.pomdp.actions
    table = {}
    transitions = []
    for m in range(size - 1):  # the last state raises the alarm
        for o in obs:
            for a in acts:
                nxt = int(rng.integers(size)) if rng.random() < 0.3 else int(rng.integers(size - 1))
                table[(f"m{m}", o, a)] = f"m{nxt}"
                transitions.append(Transition(state=f"m{m}", reading=o, action=a, next=f"m{nxt}"))
    monitor = Monitor.from_transitions(
        states=[f"m{k}" for k in range(size)],
        initial="m0",
        alarm=[f"m{size - 1}"],
        transitions=transitions,
        observations=obs,
        actions=acts,
    )

    def step(m, o, a):
        nxt = table[(m, o, a)]
        return ALARM if nxt == f"m{size - 1}" else nxt

    return monitor, step


@pytest.mark.parametrize("seed", range(8))
def test_random_problems_and_monitors_brute_force(seed):
    rng = np.random.default_rng(seed)
    problem = random_problem(seed, randomized=seed % 2 == 1)
    monitor, step = _random_monitor(problem, rng, 3)
    watched = with_monitor(problem, monitor)
    budget = problem.budget
    best = 0.0
    for alpha in affordable(problem, budget):
        value, alarm = reference(problem, alpha, step, "m0")
        report = misdirect.evaluate(watched, alpha)
        assert report.probability == pytest.approx(value, abs=1e-10)
        assert (report.alarm_probability or 0.0) == pytest.approx(alarm, abs=1e-10)
        # a monitor only takes runs away (auto bounds the monitored optimum by the plain one)
        assert value <= misdirect.evaluate(problem, alpha).probability + 1e-12
        best = max(best, value)
    for method in ("exhaustive", "auto"):
        result = misdirect.solve(watched, budgets=[budget], method=method)
        assert result.probability == pytest.approx(best, abs=1e-10)
        assert str(result.status) == "optimal"


@pytest.mark.parametrize("seed", range(4))
def test_random_problems_consistency_brute_force(seed):
    problem = random_problem(seed, randomized=seed % 2 == 1)
    step, m0 = consistency_step(problem)
    watched = with_monitor(problem, consistency_monitor(problem))
    # the robot's model is right: without an alteration, nothing is ever impossible
    assert (misdirect.evaluate(watched).alarm_probability or 0.0) == 0.0
    best = 0.0
    for alpha in affordable(problem, problem.budget):
        value, alarm = reference(problem, alpha, step, m0)
        report = misdirect.evaluate(watched, alpha)
        assert report.probability == pytest.approx(value, abs=1e-10)
        assert (report.alarm_probability or 0.0) == pytest.approx(alarm, abs=1e-10)
        best = max(best, value)
    result = misdirect.solve(watched, budgets=[problem.budget], method="exhaustive")
    assert result.probability == pytest.approx(best, abs=1e-10)


# -- (b) the consistency monitor on the paper grid ----------------------------------------------


def test_paper_grid_consistency_catches_the_budget_one_attacks():
    """The budget-1 optima of the paper (o1 read as o2 or as o3: 0.719924,
    tests/test_paper_values.py) make the robot read a region it cannot be in; the
    consistency monitor catches them (o1 -> o2 with 0.21, o1 -> o3 with 0.95)."""
    problem = paper_grid(5)
    step, m0 = consistency_step(problem)
    watched = with_monitor(problem, consistency_monitor(problem))
    for changes in ({"o1": "o2"}, {"o1": "o3"}):
        alpha = problem.alteration(changes)
        assert misdirect.evaluate(problem, alpha).probability == pytest.approx(0.719924, abs=1e-6)
        value, alarm = reference(problem, alpha, step, m0)
        report = misdirect.evaluate(watched, alpha)
        assert alarm > 0.2
        assert report.alarm_probability == pytest.approx(alarm, abs=1e-10)
        assert report.probability == pytest.approx(value, abs=1e-10)
        assert report.probability < 0.719924 - 0.05


def test_paper_grid_stealth_cli_against_brute_force():
    problem = paper_grid(5)
    step, m0 = consistency_step(problem)
    brute = max(reference(problem, alpha, step, m0)[0] for alpha in affordable(problem, 1.0))
    result = runner.invoke(
        app, ["solve", "--scenario", "paper-grid", "--budget", "1", "--stealth", "--json"]
    )
    assert result.exit_code == 0, result.output
    payload = json.loads(result.stdout)
    assert payload["status"] == "optimal"
    assert payload["value"] == pytest.approx(brute, abs=1e-10)
    assert payload["value"] <= 0.719924 + 1e-6
    assert payload["value"] == pytest.approx(0.6479029686743, abs=1e-9)
    assert any("before the alarm" in note for note in payload["notes"])
    # --monitor consistency says the same
    same = runner.invoke(
        app,
        [
            "solve",
            "--scenario",
            "paper-grid",
            "--budget",
            "1",
            "--monitor",
            "consistency",
            "--json",
        ],
    )
    assert json.loads(same.stdout)["value"] == payload["value"]


def test_evaluate_reports_the_alarm_outcome():
    result = runner.invoke(
        app,
        ["evaluate", "--scenario", "paper-grid", "--stealth", "-a", "o1=o2", "--json"],
    )
    assert result.exit_code == 0, result.output
    outcomes = json.loads(result.stdout)["outcomes"]
    alarm = [row for row in outcomes if row["kind"] == "alarm"]
    assert [row["state"] for row in alarm] == ["alarm"]
    assert alarm[0]["probability"] == pytest.approx(0.2101947458601, abs=1e-9)


@pytest.mark.parametrize("command", ["simulate", "audit", "harden", "export-chain", "solve"])
def test_every_problem_command_takes_monitor_and_stealth(command):
    result = runner.invoke(app, [command, "--help"], terminal_width=200)
    assert "--monitor" in result.output and "--stealth" in result.output


# -- (c) export-chain against Storm -------------------------------------------------------------


def _storm_values(stormpy, path):
    model = stormpy.build_model_from_drn(str(path))
    values = []
    for text in ('P=? [!"alarm" U "decoy"]', 'P=? [F "alarm"]'):
        formula = stormpy.parse_properties(text)
        values.append(stormpy.model_checking(model, formula[0]).get_value(model.initial_states[0]))
    return values


@pytest.mark.parametrize(
    ("name", "alter"),
    [
        ("hand", ["o1=g", "o2=o0"]),
        ("paper-grid", ["o1=o2"]),
        ("tiny", ["o2=g"]),
    ],
)
def test_export_chain_monitored_agrees_with_storm(tmp_path, name, alter):
    stormpy = pytest.importorskip("stormpy")
    if name == "hand":
        source = tmp_path / "hand.yaml"
        source.write_text(yaml.safe_dump({**HAND, "monitor": HAND_MONITOR}))
        args = [str(source)]
    elif name == "paper-grid":
        args = ["--scenario", "paper-grid", "--monitor", "consistency"]
    else:  # the example with a monitor file: g (the goal's and the trap's) read elsewhere
        monitor = tmp_path / "m.yaml"
        monitor.write_text(
            yaml.safe_dump(
                {
                    "states": ["ok", "caught"],
                    "initial": "ok",
                    "alarm": ["caught"],
                    "transitions": [
                        {"state": "ok", "reading": "g", "next": "caught"},
                        {"state": "ok", "reading": "*", "next": "ok"},
                    ],
                }
            )
        )
        tiny = Path(__file__).parent.parent / "examples" / "tiny.yaml"
        args = [str(tiny), "--monitor", str(monitor)]
    chain = tmp_path / "chain.drn"
    flags = [item for pair in (("--alter", a) for a in alter) for item in pair]
    result = runner.invoke(app, ["export-chain", *args, *flags, "-o", str(chain), "--json"])
    assert result.exit_code == 0, result.output
    value = json.loads(result.stdout)["value"]
    evaluated = runner.invoke(app, ["evaluate", *args, *flags, "--json"])
    payload = json.loads(evaluated.stdout)
    alarm = sum(row["probability"] for row in payload["outcomes"] if row["kind"] == "alarm")
    assert payload["value"] == pytest.approx(value, abs=1e-12)
    storm_value, storm_alarm = _storm_values(stormpy, chain)
    # Storm's default engine iterates to a relative 1e-6: its answer is that close
    assert storm_value == pytest.approx(value, abs=1e-6)
    assert storm_alarm == pytest.approx(alarm, abs=1e-6)
    assert alarm > 0  # each of the three is caught sometimes


# -- (d) malformed monitors and the cap ---------------------------------------------------------


BAD_MONITOR = {
    "states": ["start", "run", "half", "caught"],
    "initial": "start",
    "alarm": ["caught", "nowhere"],
    "transitions": [
        {"state": "start", "reading": "*", "next": "run"},
        {"state": "run", "reading": "o0", "next": "caught"},
        {"state": "run", "reading": ["o0", "o1", "o2", "g"], "next": "run"},
        {"state": "start", "reading": "o9", "next": "run"},
        {"state": "half", "reading": ["o1", "o2"], "next": "half"},
    ],
}


def test_a_bad_monitor_file_reports_every_problem_at_once(tmp_path):
    source = tmp_path / "hand.yaml"
    source.write_text(yaml.safe_dump(HAND))
    monitor = tmp_path / "bad.yaml"
    monitor.write_text(yaml.safe_dump(BAD_MONITOR))
    result = runner.invoke(app, ["evaluate", str(source), "--monitor", str(monitor)])
    assert result.exit_code == 2
    lines = [line for line in result.output.splitlines() if line.startswith("error:")]
    assert len(lines) == 4, result.output
    assert all(str(monitor) in line for line in lines)
    text = "\n".join(lines)
    assert "alarm: unknown alarm state 'nowhere'" in text
    assert "transitions[2]: nondeterministic: in state 'run' reading 'o0'" in text
    assert "transitions[3]: unknown reading 'o9'" in text
    assert "transitions: incomplete: no transition of state 'half' reads 'o0'" in text


def test_a_bad_monitor_section_names_the_problem_file(tmp_path):
    source = tmp_path / "hand.yaml"
    source.write_text(yaml.safe_dump({**HAND, "monitor": BAD_MONITOR}))
    with pytest.raises(ProblemError) as raised:
        misdirect.load_problem(source)
    lines = str(raised.value).splitlines()
    assert len(lines) == 4
    assert all(line.startswith(f"{source}: monitor.") for line in lines)
    # a schema error (not a name) is reported with its field too
    broken = {**HAND, "monitor": {**HAND_MONITOR, "consistency": True, "initial": 3.5}}
    with pytest.raises(ProblemError, match=r"monitor\.initial"):
        misdirect.problem_from_dict(broken)
    with pytest.raises(ProblemError, match="consistency or an automaton, not both"):
        misdirect.problem_from_dict({**HAND, "monitor": {**HAND_MONITOR, "consistency": True}})


def test_the_cap_is_named(tmp_path):
    problem = paper_grid(5)
    with pytest.raises(ProblemError, match=r"more than 10 belief supports \(the cap\)"):
        consistency_monitor(problem, max_states=10)
    source = tmp_path / "hand.yaml"
    source.write_text(yaml.safe_dump({**HAND, "monitor": {"consistency": {"max_states": 2}}}))
    result = runner.invoke(app, ["evaluate", str(source)])
    assert result.exit_code == 2
    (line,) = [line for line in result.output.splitlines() if line.startswith("error:")]
    assert f"{source}: monitor.consistency.max_states: " in line
    assert "more than 2 belief supports (the cap)" in line


def test_one_monitor_at_a_time_and_over_the_problems_names():
    problem = paper_grid(5)
    watched = with_monitor(problem, consistency_monitor(problem))
    with pytest.raises(ProblemError, match="already watched"):
        with_monitor(watched, consistency_monitor(problem))
    other = _hand()
    with pytest.raises(ProblemError, match="other observations"):
        with_monitor(other, consistency_monitor(problem))
    with pytest.raises(ProblemError, match="raises the alarm"):
        Monitor.from_transitions(
            states=["x"],
            initial="x",
            alarm=["x"],
            transitions=[Transition("x", "*", "x")],
            observations=("o",),
            actions=("a",),
        )


def test_the_schema_describes_the_monitor():
    from misdirect.io.problem_file import json_schema

    schema = json_schema()
    assert "monitor" in schema["properties"]
    spec = schema["$defs"]["MonitorSpec"]
    assert {"consistency", "states", "initial", "alarm", "transitions"} <= set(spec["properties"])
    assert spec["additionalProperties"] is False


def test_auto_searches_first_where_the_enumeration_is_mostly_bases(monkeypatch):
    """Auto gives branch-and-bound the first try where the low-rank enumeration would be
    mostly base solves (issue 52's speed: the monitored grid's budget 4 is 3,956 bases); the
    constants are lowered so that budget 2 of the monitored grid (36 bases, 1,079 alterations)
    counts as such, and one exact evaluation (what a base is costed at) is pinned to 10 ms:
    measured, it is a few ms, where 36 bases and 1,079 updates weigh about the same, so which
    won varied from run to run. The curve is the one-by-one exhaustive enumeration's, and
    budget 1 brute force's on the reference product."""
    from misdirect.solvers import auto, schedule

    monkeypatch.setattr(auto, "BASES_SAMPLED_FROM", 2)
    monkeypatch.setattr(schedule, "BASES_FIRST_SECONDS", 0.0)
    monkeypatch.setattr(auto._Facts, "evaluation_s", property(lambda self: 0.01))
    problem = paper_grid(5)
    watched = with_monitor(problem, consistency_monitor(problem))
    notes: list[str] = []
    budgets = [0.0, 1.0, 2.0]
    result = misdirect.solve(
        watched,
        budgets=budgets,
        method="auto",
        progress=lambda d, t, **info: notes.append(info.get("note") or ""),
    )
    # searched first, the enumeration kept for what the search leaves open
    assert any("mostly base solves" in n and "after the search" in n for n in notes)
    oracle = misdirect.solve(watched, budgets=budgets, method="exhaustive")
    for mine, best in zip(result.curve, oracle.curve, strict=True):
        assert str(mine.status) == "optimal"
        assert mine.probability == pytest.approx(best.probability, abs=1e-12)
    step, m0 = consistency_step(problem)
    brute = max(reference(problem, alpha, step, m0)[0] for alpha in affordable(problem, 1.0))
    assert result.curve[1].probability == pytest.approx(brute, abs=1e-10)


def _cell_jump(problem):
    """A drone's GPS check: the alarm when a reading names a cell more than one step (in
    either coordinate) from the cell the previous reading named (readings are "(x,y):...")."""
    observations = problem.pomdp.observations
    cell_of = {o: o.split(":")[0] for o in observations if ":" in o}
    cells = sorted(set(cell_of.values()))
    named = {c: [o for o, at in cell_of.items() if at == c] for c in cells}

    def near(a, b):
        (ax, ay), (bx, by) = (tuple(map(int, c.strip("()").split(","))) for c in (a, b))
        return max(abs(ax - bx), abs(ay - by)) <= 1

    transitions = [Transition(state="start", reading=named[c], next=c) for c in cells]
    transitions.append(Transition(state="start", reading="*", next="start"))
    for c in cells:
        transitions += [Transition(state=c, reading=named[d], next=d) for d in cells if near(c, d)]
        transitions.append(Transition(state=c, reading="*", next="caught"))
    return Monitor.from_transitions(
        states=["start", "caught", *cells],
        initial="start",
        alarm=["caught"],
        transitions=transitions,
        observations=observations,
        actions=problem.pomdp.actions,
    )


def test_the_plain_twin_certifies_an_attack_the_monitor_misses():
    """auto solves a monitored problem's plain twin first. On a small drone under a GPS
    check, the twin's budget-1 attack, (2,1):E read as (0,0):clear, jumps two cells and is
    always caught (worth 0 watched); the same behaviour read from a neighbouring cell is
    not, and is worth the twin's optimum, which bounds every monitored attack. So auto
    certifies it by the twin's bound alone; the exhaustive enumeration of the monitored
    problem agrees."""
    from misdirect.scenarios import drone

    problem = drone(5, agents=1, rows=1)
    watched = with_monitor(problem, _cell_jump(problem))
    plain = misdirect.solve(problem, budgets=[1.0])
    assert str(plain.status) == "optimal"
    caught = problem.alteration({"(2,1):E": "(0,0):clear"})
    assert misdirect.evaluate(problem, caught).probability == pytest.approx(plain.probability)
    assert misdirect.evaluate(watched, caught).probability == 0.0
    result = misdirect.solve(watched, budgets=[1.0])
    point = result.curve[-1]
    assert str(point.status) == "optimal" and point.certified_by == "unmonitored"
    assert point.probability == pytest.approx(plain.probability, rel=1e-12)
    assert point.alarm == 0.0
    ((read, sent),) = point.alteration.items()
    assert read == "(2,1):E"
    assert (
        problem.controller.behaviour_class[problem.pomdp.observations.index(sent)]
        == (problem.controller.behaviour_class[problem.pomdp.observations.index("(0,0):clear")])
    )
    oracle = misdirect.solve(watched, budgets=[1.0], method="exhaustive")
    assert oracle.probability == pytest.approx(point.probability, rel=1e-12)


# -- the consistency monitor along the controller's runs ----------------------------------------


def _same_values_along_and_full(problem, alterations):
    """The monitor built along the controller (the default) against the full one (every
    action played on a reading, in any node): the same value and Pr(alarm) under each
    alteration, and no support the full monitor lacks."""
    along = consistency_monitor(problem)
    full = consistency_monitor(problem, along_controller=False)
    assert set(along.supports) <= set(full.supports)
    short, long = with_monitor(problem, along), with_monitor(problem, full)
    for alpha in alterations:
        mine, theirs = misdirect.evaluate(short, alpha), misdirect.evaluate(long, alpha)
        assert mine.probability == pytest.approx(theirs.probability, abs=1e-12)
        assert (mine.alarm_probability or 0.0) == pytest.approx(
            theirs.alarm_probability or 0.0, abs=1e-12
        )
    return along, full


@pytest.mark.parametrize("seed", range(6))
def test_consistency_along_the_controller_equals_the_full_monitor(seed):
    problem = random_problem(seed, randomized=seed % 2 == 1)
    step, m0 = consistency_step(problem)
    along, _ = _same_values_along_and_full(problem, affordable(problem, problem.budget))
    # and the reference product (supports as frozensets) once more, at the optimum
    watched = with_monitor(problem, along)
    best = max(reference(problem, a, step, m0)[0] for a in affordable(problem, problem.budget))
    result = misdirect.solve(watched, budgets=[problem.budget], method="exhaustive")
    assert result.probability == pytest.approx(best, abs=1e-10)


def test_consistency_along_the_controller_on_a_sensor_network():
    """sensor_grid(8, 6): the full monitor has thousands of supports, the controller's runs
    reach a few hundred; every single-sensor alteration gets the same value and alarm."""
    from misdirect.scenarios import sensor_grid

    problem = sensor_grid(8, 6)
    sensors = [o for o in problem.pomdp.observations if o.startswith("s")]
    alterations = [{}] + [{o: t} for o in sensors[:3] for t in ("b", sensors[-1]) if t != o]
    along, full = _same_values_along_and_full(problem, alterations)
    assert 10 * along.n_states < full.n_states


def test_a_consistency_monitor_folds_into_its_own_controller_only():
    import copy
    from dataclasses import replace

    problem = paper_grid(5)
    monitor = consistency_monitor(problem)
    changed = replace(problem, controller=copy.copy(problem.controller))  # another, alike
    with pytest.raises(ProblemError, match="another controller"):
        with_monitor(changed, monitor)
    # the full monitor is exact for any node, so it folds into any controller over its names
    assert consistency_monitor(problem, along_controller=False).controller is None


def test_the_plain_twin_certifies_a_tradeoff_curve_once_solved():
    """Under --max-alarm the twin's bound holds too (the constrained optimum is at most the
    stealthy one), and its lifted attack counts where it is proven feasible: on the small
    drone under the GPS check it is never caught, so every δ's budget 1 is certified by it,
    at the unmonitored optimum. The twin is solved once for the whole curve."""
    from misdirect.scenarios import drone

    problem = drone(5, agents=1, rows=1)
    watched = with_monitor(problem, _cell_jump(problem))
    plain = misdirect.solve(problem, budgets=[1.0])
    notes: list[str] = []
    curves = misdirect.solve_tradeoff(
        watched,
        [0.0, 0.5],
        budgets=[1.0],
        progress=lambda done, total, **info: notes.append(info.get("note") or ""),
    )
    for curve in curves:
        point = curve.curve[-1]
        assert str(point.status) == "optimal" and point.certified_by == "unmonitored"
        assert point.probability == pytest.approx(plain.probability, rel=1e-12)
        assert point.alarm == 0.0
    assert sum("without its monitor first" in note for note in notes) == 1
    oracle = misdirect.solve(watched, budgets=[1.0], method="exhaustive", max_alarm=0.0)
    assert oracle.probability == pytest.approx(plain.probability, rel=1e-12)
