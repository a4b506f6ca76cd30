"""What the reports say about a monitor (issue 52): simulate counts the alarm as its own kind,
evaluate says where the alarm is raised, audit and harden compare the monitor with protection.

Expected values come from outside the code under test: hand calculation on small problems,
the exact evaluation against the simulation (a binomial bound, a fixed seed), and separate
solves of the problem with and without the monitor.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from typer.testing import CliRunner

import misdirect
from misdirect.cli import app
from misdirect.core.monitor import (
    Monitor,
    Transition,
    _product_controller,
    consistency_monitor,
    with_monitor,
)
from misdirect.core.simulate import simulate
from misdirect.scenarios import paper_grid, random_problem
from watched import WATCHED

runner = CliRunner()

# From s0 the robot plays a into s1 or s2 (1/2 each); it plays a on o0 and g, b on anything
# else. The monitor knows o0 is read only at the start: a later o0 raises the alarm. Altered
# o2 -> o0, the robot in s2 (probability 1/2) reads o0 on its second reading and is caught
# there, in s2; in s1 it reads o1, plays b and reaches the goal.
HAND = WATCHED


def _third_reading(problem):
    """An automaton that raises the alarm on the third reading, whatever it is."""
    return Monitor.from_transitions(
        states=["r0", "r1", "r2", "caught"],
        initial="r0",
        alarm=["caught"],
        transitions=[
            Transition("r0", "*", "r1"),
            Transition("r1", "*", "r2"),
            Transition("r2", "*", "caught"),
        ],
        observations=problem.pomdp.observations,
        actions=problem.pomdp.actions,
    )


# -- simulate -----------------------------------------------------------------------------------


def test_simulate_every_run_caught_on_its_third_reading():
    """On the paper's grid the decoy and the goal are four or more steps from the start: a
    monitor that raises the alarm on the third reading catches every run, on reading 3."""
    problem = paper_grid(5)
    watched = with_monitor(problem, _third_reading(problem))
    runs = simulate(watched, runs=2_000, seed=3)
    assert runs.alarms == 2_000
    assert runs.alarm_mean_step == 3.0
    assert runs.decoy_hits == 0 and sum(runs.absorbed.values()) == 0
    assert "alarm" not in runs.absorbed and runs.alarm_state == "alarm"
    assert math.isnan(runs.mean_steps)  # no run reached a decoy or the goal


def test_simulate_alarms_within_the_binomial_bound_of_the_exact_probability():
    """The consistency monitor on the paper's grid, o1 read as o2: the simulated alarm count
    lies within 4.5 standard deviations of the exact Pr(alarm) (fixed seed); the counts add
    up to the runs."""
    problem = paper_grid(5)
    watched = with_monitor(problem, consistency_monitor(problem))
    alpha = watched.alteration({"o1": "o2"})
    exact = misdirect.evaluate(watched, alpha).alarm_probability
    assert exact == pytest.approx(0.2101947458601, abs=1e-9)
    n = 20_000
    runs = simulate(watched, alpha, runs=n, seed=11)
    spread = 4.5 * math.sqrt(n * exact * (1 - exact))
    assert abs(runs.alarms - n * exact) <= spread
    assert runs.decoy_hits + sum(runs.absorbed.values()) + runs.alarms + runs.unfinished == n
    assert runs.trapped == 0
    # caught no earlier than the second reading: the first reading is never altered
    assert runs.alarm_mean_step > 2


def test_simulate_hand_made_caught_on_the_second_reading():
    problem = misdirect.problem_from_dict(HAND)
    runs = simulate(problem, problem.alteration({"o2": "o0"}), runs=4_000, seed=5)
    assert runs.alarm_mean_step == 2.0  # every caught run: in s2, on its second reading
    assert abs(runs.alarms - 2_000) <= 4.5 * math.sqrt(4_000 * 0.25)
    assert runs.alarms + runs.absorbed["goal"] == 4_000  # the rest reach the goal from s1


def test_simulate_cli_counts_the_alarm_in_json_and_table():
    command = ["simulate", "--scenario", "paper-grid", "--size", "5", "--stealth"]
    command += ["-a", "o1=o3", "--runs", "4000", "--seed", "2"]
    result = runner.invoke(app, [*command, "--json"])
    assert result.exit_code == 0, result.output
    payload = json.loads(result.stdout)
    alarm = payload["totals"]["alarm"]
    assert alarm["kind"] == "alarm" and alarm["state"] is None
    exact = 0.946275  # Pr(alarm) of o1 -> o3 under the consistency monitor (docs/stealth.md)
    assert alarm["interval_95"][0] - 0.01 <= exact <= alarm["interval_95"][1] + 0.01
    assert [o["state"] for o in payload["outcomes"] if o["kind"] == "alarm"] == ["alarm"]
    assert payload["alarm_mean_step"] > 2
    assert sum(t["runs"] for t in payload["totals"].values()) == 4000
    table = runner.invoke(app, command, terminal_width=200)
    assert table.exit_code == 0, table.output
    assert "alarm (monitor)" in table.output and "caught on reading" in table.output
    # an unmonitored problem has no alarm kind
    plain = runner.invoke(app, [*command[:5], "--runs", "100", "--json"])
    assert "alarm" not in json.loads(plain.stdout)["totals"]


# -- evaluate: where the alarm fires ------------------------------------------------------------


def test_evaluate_hand_made_alarm_fires_in_s2_on_o0():
    problem = misdirect.problem_from_dict(HAND)
    report = misdirect.evaluate(problem, {"o2": "o0"})
    assert report.alarm_probability == pytest.approx(0.5, abs=1e-12)
    [source] = report.alarm_sources  # by hand: only in s2, read as o0, half the runs
    assert (source.state, source.observation, source.reading) == ("s2", "o2", "o0")
    assert source.probability == pytest.approx(0.5, abs=1e-12)
    assert report.alarm_readings() == [("o2", "o0", pytest.approx(0.5, abs=1e-12))]
    # o1 -> o0: caught in s1 instead; o1 -> g raises no alarm at all
    [other] = misdirect.evaluate(problem, {"o1": "o0"}).alarm_sources
    assert (other.state, other.reading) == ("s1", "o0")
    assert misdirect.evaluate(problem, {"o1": "g"}).alarm_sources == ()
    payload = misdirect.evaluate(problem, {"o2": "o0"}).to_dict()
    assert payload["alarms"] == [
        {"state": "s2", "observation": "o2", "reading": "o0", "probability": 0.5}
    ]
    plain = misdirect.problem_from_dict({k: v for k, v in HAND.items() if k != "monitor"})
    assert "alarms" not in misdirect.evaluate(plain).to_dict()


def test_evaluate_third_reading_alarm_sources_by_hand():
    """The third-reading monitor on the paper's grid: the alarm fires where the robot is at
    its third reading (after two moves), with the probability of being there, by hand from
    the world's two-step distribution under the controller's first two moves."""
    problem = paper_grid(5)
    watched = with_monitor(problem, _third_reading(problem))
    report = misdirect.evaluate(watched)
    assert report.alarm_probability == pytest.approx(1.0, abs=1e-12)
    # the distribution after two steps, by matrix products of the world and the controller
    pomdp, controller = problem.pomdp, problem.controller
    n_s = pomdp.n_states
    dense = pomdp.transitions.toarray()
    where = {(pomdp.initial_state, controller.initial_node): 1.0}
    for _ in range(2):
        after: dict[tuple[int, int], float] = {}
        for (s, n), p in where.items():
            o = int(pomdp.observation_of[s])
            for a, n2, q in controller.move_table(int(controller.move[n, o])):
                for s2 in np.flatnonzero(dense[a * n_s + s]).tolist():
                    key = (s2, n2)
                    after[key] = after.get(key, 0.0) + p * q * dense[a * n_s + s, s2]
        where = after
    expected: dict[str, float] = {}
    for (s, _), p in where.items():
        expected[pomdp.states[s]] = expected.get(pomdp.states[s], 0.0) + p
    found = {a.state: a.probability for a in report.alarm_sources}
    assert found == pytest.approx(expected, abs=1e-12)
    assert all(a.reading == a.observation for a in report.alarm_sources)  # unaltered


@pytest.mark.parametrize("seed", [3, 17])
def test_alarm_sources_sum_to_the_alarm_probability(seed):
    problem = random_problem(seed)
    watched = with_monitor(problem, consistency_monitor(problem))
    rng = np.random.default_rng(seed)
    n = problem.pomdp.n_observations
    alpha = problem.identity().copy()
    o_init = problem.pomdp.initial_observation
    for o in range(n):
        if o != o_init and rng.random() < 0.5:
            alpha[o] = rng.integers(n)
    report = misdirect.evaluate(watched, alpha)
    total = sum(a.probability for a in report.alarm_sources)
    assert total == pytest.approx(report.alarm_probability, abs=1e-9)


def test_evaluate_cli_lists_where_the_alarm_fires():
    result = runner.invoke(
        app, ["evaluate", "--scenario", "paper-grid", "--stealth", "-a", "o1=o2"]
    )
    assert result.exit_code == 0, result.output
    assert "alarm raised on o1 read as o2" in result.output


# -- the product controller's bisimilar nodes ---------------------------------------------------


def test_merging_bisimilar_nodes_keeps_every_value():
    """with_monitor merges bisimilar (node, monitor state) pairs: fewer nodes than the raw
    product, and the same value and Pr(alarm) as the raw product under every alteration
    tried (the raw product built here from the unmerged entries)."""
    problem = paper_grid(5)
    monitor = consistency_monitor(problem)
    watched = with_monitor(problem, monitor)
    nodes, entries = _product_controller(problem.controller, monitor, problem.pomdp.n_actions)
    assert watched.controller.n_nodes < len(nodes)
    from dataclasses import replace

    from misdirect.core.model import Controller

    n_o = problem.pomdp.n_observations
    cell, action, next_node, probability = entries
    raw = Controller.from_entries(
        nodes=tuple(str(k) for k in nodes),
        initial_node=0,
        n_observations=n_o,
        node=cell // n_o,
        observation=cell % n_o,
        action=action,
        next_node=next_node,
        probability=probability,
    )
    unmerged = replace(watched, controller=raw)
    for changes in ({}, {"o1": "o2"}, {"o1": "o3"}, {"o1": "o2", "o2": "o4"}, {"o3": "b"}):
        merged_report = misdirect.evaluate(watched, changes)
        raw_report = misdirect.evaluate(unmerged, changes)
        assert merged_report.probability == pytest.approx(raw_report.probability, abs=1e-12)
        assert merged_report.alarm_probability == pytest.approx(
            raw_report.alarm_probability, abs=1e-12
        )


# -- audit and harden: the monitor against protection -------------------------------------------


def _protected(problem, sensors):
    """``problem`` with ``sensors`` (names) unalterable, built here from the cost model."""
    from dataclasses import replace

    index = [problem.pomdp.observations.index(o) for o in sensors]
    cost = replace(problem.cost, protected=problem.cost.protected | frozenset(index))
    return replace(problem, cost=cost)


def _optimum(problem, budget):
    result = misdirect.solve(problem, budgets=[budget])
    assert str(result.status) == "optimal"
    return result.probability


@pytest.fixture(scope="module")
def grid_pair():
    """The paper's grid, and the same watched by the consistency monitor; the monitored
    problem is built here and also with_monitor's (they must agree)."""
    problem = paper_grid(5)
    return problem, with_monitor(problem, consistency_monitor(problem))


def _check_rows(comparison, plain, watched, budget, protection, both):
    rows = {row.defence: row for row in comparison.rows}
    assert list(rows) == ["nothing", "monitor", "protection", "monitor and protection"]
    expected = {
        "nothing": _optimum(plain, budget),
        "monitor": _optimum(watched, budget),
        "protection": _optimum(_protected(plain, protection), budget),
        "monitor and protection": _optimum(_protected(watched, both), budget),
    }
    for defence, value in expected.items():
        row = rows[defence]
        assert row.probability == pytest.approx(value, abs=1e-9), defence
        assert row.status == "optimal"
        # how often the monitor catches the reply: evaluated here on the monitored problem
        caught = misdirect.evaluate(watched, row.alteration).alarm_probability
        assert row.alarm_probability == pytest.approx(caught, abs=1e-9), defence
    assert rows["protection"].protection == protection
    assert rows["monitor and protection"].protection == both
    assert rows["monitor"].monitor == "consistency" and rows["nothing"].monitor is None
    return rows


def test_audit_compares_the_monitor_with_protecting_the_most_critical_sensor(grid_pair):
    plain, watched = grid_pair
    report = misdirect.audit(watched, budget=1)
    comparison = report.monitor_comparison
    assert comparison is not None and comparison.budget == 1
    # the sensor to protect: the one whose protection lowers the unmonitored optimum the
    # most, found here by solving every single protection
    sensors = list(plain.pomdp.observations)
    drops = {o: _optimum(_protected(plain, [o]), 1) for o in sensors}
    best = min(drops, key=lambda o: (drops[o], o))
    rows = _check_rows(comparison, plain, watched, 1, [best], [best])
    assert rows["protection"].probability == pytest.approx(drops[best], abs=1e-9)
    assert rows["monitor"].probability == pytest.approx(report.probability, abs=1e-12)
    assert misdirect.audit(plain, budget=1).monitor_comparison is None


def test_harden_compares_the_monitor_with_the_best_protection(grid_pair):
    plain, watched = grid_pair
    plan = misdirect.harden(watched, protect_budget=1, budget=1)
    comparison = plan.monitor_comparison
    assert comparison is not None
    # the best single protection with and without the monitor, by solving every one here
    sensors = list(plain.pomdp.observations)
    alone = {o: _optimum(_protected(plain, [o]), 1) for o in sensors}
    watched_alone = {o: _optimum(_protected(watched, [o]), 1) for o in sensors}
    rows = _check_rows(
        comparison, plain, watched, 1, plan_protection(comparison, "protection"), plan.protection
    )
    assert rows["protection"].probability == pytest.approx(min(alone.values()), abs=1e-9)
    assert rows["monitor and protection"].probability == pytest.approx(
        min(watched_alone.values()), abs=1e-9
    )
    assert rows["monitor and protection"].probability == pytest.approx(plan.value, abs=1e-12)


def plan_protection(comparison, defence):
    return comparison.row(defence).protection


def test_audit_and_harden_cli_show_the_comparison(tmp_path):
    from result_schema import checked

    base = ["--scenario", "paper-grid", "--budget", "1", "--stealth"]
    audit = runner.invoke(app, ["audit", *base, "--json"])
    assert audit.exit_code == 0, audit.output
    document = checked(audit.stdout)
    rows = document["monitor_comparison"]["rows"]
    assert [r["defence"] for r in rows][:2] == ["nothing", "monitor"]
    assert rows[0]["value"] == pytest.approx(0.719924, abs=1e-6)  # the paper's budget-1 optimum
    assert rows[1]["value"] == pytest.approx(0.6479029686743, abs=1e-9)  # docs/stealth.md
    harden = runner.invoke(
        app, ["harden", *base, "--protect-budget", "1", "-o", str(tmp_path / "h")]
    )
    assert harden.exit_code == 0, harden.output
    as_json = runner.invoke(app, ["harden", *base, "--protect-budget", "1", "--json"])
    assert as_json.exit_code == 0, as_json.output
    rows = checked(as_json.stdout)["monitor_comparison"]["rows"]
    assert rows[-1]["defence"] == "monitor and protection" and rows[-1]["protection"] == ["o1"]
    assert "add the monitor (consistency) or protect sensors?" in " ".join(harden.output.split())
    assert "The monitor against protection" in (tmp_path / "h" / "report.md").read_text()
    plain = runner.invoke(
        app,
        ["harden", "--scenario", "paper-grid", "--budget", "1", "--protect-budget", "0", "--json"],
    )
    assert checked(plain.stdout)["monitor_comparison"] is None
