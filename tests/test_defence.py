"""The defender's view (docs/defence.md): audit, hardening and the online attacker, checked
against brute force, Storm and values computed by hand — never against the program itself."""

from __future__ import annotations

import itertools
import json
from dataclasses import replace
from fractions import Fraction

import numpy as np
import pytest
from typer.testing import CliRunner

import misdirect
from misdirect.cli import app
from misdirect.core.evaluate import decoy_probability
from misdirect.core.model import Controller, CostModel, Pomdp, Problem
from misdirect.io.problem_file import write_problem
from misdirect.scenarios import paper_grid, random_problem
from prism_product import world_module
from stress_model import stress_model

runner = CliRunner()


# -- brute force ------------------------------------------------------------------------------


def all_alterations(problem: Problem, observations=None):
    """Every alteration function over ``observations`` (default: all) that the cost model
    allows: (alpha, cost, set of altered observations). The initial observation stays."""
    n = problem.pomdp.n_observations
    observations = range(n) if observations is None else observations
    o_init = problem.pomdp.initial_observation
    choices = []
    for o in observations:
        row = problem.cost.row(o)
        targets = [o] if o == o_init else [t for t in range(n) if np.isfinite(row[t])]
        choices.append([(o, t, row[t]) for t in targets])
    for picked in itertools.product(*choices):
        alpha = np.arange(n)
        cost, changed = 0.0, set()
        for o, t, c in picked:
            alpha[o] = t
            if t != o:
                cost += c
                changed.add(o)
        yield alpha, cost, frozenset(changed)


def brute_values(problem: Problem, budget: float, observations=None):
    """(value, altered set) of every allowed alteration within ``budget``."""
    return [
        (decoy_probability(problem, alpha), changed)
        for alpha, cost, changed in all_alterations(problem, observations)
        if cost <= budget + 1e-9
    ]


def small_random(seed: int, budget: float) -> Problem:
    return random_problem(seed, states=5, observations=3, nodes=2, budget=budget)


# -- hardening ---------------------------------------------------------------------------------


@pytest.mark.parametrize("seed", range(10))
def test_harden_matches_brute_force(seed):
    """The min–max against the minimum over *every* protection set of the maximum over
    *every* alteration function avoiding it (random models: forbidden pairs, traps)."""
    rng = np.random.default_rng(100 + seed)
    budget = float(rng.integers(1, 4))
    problem = small_random(seed, budget)
    names = problem.pomdp.observations
    n = len(names)
    protect_costs = {name: float(rng.choice([1.0, 2.0])) for name in names}
    costs = np.array([protect_costs[name] for name in names])
    attacks = brute_values(problem, budget)

    def f(protection: frozenset) -> float:
        return max(v for v, changed in attacks if not changed & protection)

    for d in (0.0, 1.0, 2.0, 3.0):
        best = min(
            f(frozenset(q))
            for k in range(n + 1)
            for q in itertools.combinations(range(n), k)
            if costs[list(q)].sum() <= d + 1e-9
        )
        result = misdirect.harden(
            problem, protect_budget=d, budget=budget, protect_costs=protect_costs
        )
        assert result.status == "optimal"
        assert result.value_after == pytest.approx(best, abs=1e-9), (seed, d)
        chosen = frozenset(names.index(o) for o in result.protection)
        assert costs[list(chosen)].sum() <= d + 1e-9
        assert f(chosen) == pytest.approx(result.value_after, abs=1e-9)
        assert result.value_before == pytest.approx(f(frozenset()), abs=1e-9)
        # the whole trade-off curve, level by level
        for point in result.curve:
            level = min(
                f(frozenset(q))
                for k in range(n + 1)
                for q in itertools.combinations(range(n), k)
                if costs[list(q)].sum() <= point.protect_budget + 1e-9
            )
            assert point.probability == pytest.approx(level, abs=1e-9)
            assert point.lower_bound == pytest.approx(level, abs=1e-9)


def test_harden_lower_bound_is_valid_when_cut_short():
    """With a tiny time limit the reported lower bound may be loose, but never above the true
    min–max (brute force), and the protection's reported upper bound never below it."""
    cut = 0
    for seed in range(6):
        problem = random_problem(seed, states=6, observations=4, nodes=2, budget=2)
        n = problem.pomdp.n_observations
        result = misdirect.harden(problem, protect_budget=2, budget=2, time_limit=1e-4)
        cut += result.status == "time_limit"
        attacks = brute_values(problem, 2.0)
        best = min(
            max(v for v, changed in attacks if not changed & frozenset(q))
            for k in range(3)
            for q in itertools.combinations(range(n), k)
        )
        assert result.lower_bound <= best + 1e-9, seed
        assert result.value_after_upper >= best - 1e-9, seed
    assert cut >= 3  # the time limit did cut the search short


# -- the online attacker ----------------------------------------------------------------------


def test_online_value_bounds_offline_optimum():
    """An alteration is one strategy of the online attacker (same choice in every state and
    node reading the same observation), so the online value is at least the offline optimum at
    any budget; the offline side is brute force over all alteration functions."""
    strict = 0
    for seed in range(25):
        problem = small_random(seed, 0)
        online = misdirect.online_attack_value(problem).probability
        offline = max(v for v, _ in brute_values(problem, np.inf))
        assert online >= offline - 1e-9, seed
        strict += online > offline + 1e-6
    assert strict >= 1  # not always tight: memory and shared sensors matter (also the grid)


@pytest.mark.parametrize("seed", [0, 23, 25, 31])
def test_online_bound_lies_above_the_offline_optimum_where_doubles_round(seed):
    """On models with probabilities down to 1e-12, policy iteration's online value lay below
    the exhaustive offline optimum (seed 0: 0.9999980240 against 0.9999998733), which the
    online value bounds by a theorem; the proven bound does not. Budget 3 lets the offline
    attacker alter all three alterable sensors."""
    problem = stress_model(seed)
    offline = misdirect.solve(problem, method="exhaustive", budgets=[3.0]).curve[0]
    online = misdirect.online_attack_value(problem)
    assert offline.error_bound is not None
    floor = Fraction(offline.probability) - Fraction(offline.error_bound)
    assert Fraction(online.unlimited_bound) >= floor
    assert online.unlimited_bound >= online.unlimited_probability


@pytest.mark.parametrize("seed", range(8))
def test_online_equals_offline_when_states_are_observed_and_controller_memoryless(seed):
    """Equal when the controller has one memory node and every observation is emitted by one
    state, with an unlimited budget: the product state is then the world state, which the
    observation names, so a state-and-memory-dependent choice is a function of the observation
    alone — an alteration. Memoryless deterministic strategies are optimal for maximal
    reachability in an MDP, so history does not help the online attacker either."""
    problem = random_problem(seed, states=4, observations=3, nodes=1)
    n_s = problem.pomdp.n_states
    names = (*(f"o{s}" for s in range(n_s)), "ghost")
    pomdp = replace(problem.pomdp, observations=names, observation_of=np.arange(n_s))
    n_o = len(names)
    rng = np.random.default_rng(seed)
    controller = Controller(
        nodes=("n0",),
        initial_node=0,
        action=rng.integers(0, pomdp.n_actions, size=(1, n_o)),
        update=np.zeros((1, n_o), dtype=np.int64),
    )
    forbidden = {(1, int(t)): np.inf for t in rng.choice(n_o, size=2, replace=False) if t != 1}
    cost = CostModel(n_observations=n_o, default=1.0, pairs=forbidden)
    problem = replace(problem, pomdp=pomdp, controller=controller, cost=cost)
    # observations of absorbing states (self-loops whatever the robot does) and the ghost
    # (emitted by nobody) cannot change anything: brute force over the others
    movable = [s for s in range(n_s) if not pomdp.absorbing[s]]
    offline = max(v for v, _ in brute_values(problem, np.inf, observations=movable))
    online = misdirect.online_attack_value(problem).probability
    assert online == pytest.approx(offline, abs=1e-9)


def hand_model() -> Problem:
    """s0 (reads i) → s1 or s2 with 1/2 each; in s1 (reads a) action L reaches the decoy with
    0.6 (goal 0.4), in s2 (reads b) with 0.3 (goal 0.7); action R always reaches the goal. The
    controller (one node) plays R on every reading except x, which no state emits, where it
    plays L. Every alteration costs 1; g is read only in the absorbing goal and decoy."""
    states = ("s0", "s1", "s2", "goal", "decoy")
    entries = [  # (action, source, target, probability); actions L=0, R=1
        (0, 0, 1, 0.5), (0, 0, 2, 0.5), (1, 0, 1, 0.5), (1, 0, 2, 0.5),
        (0, 1, 4, 0.6), (0, 1, 3, 0.4), (1, 1, 3, 1.0),
        (0, 2, 4, 0.3), (0, 2, 3, 0.7), (1, 2, 3, 1.0),
    ]  # fmt: skip
    a, s, t, p = (np.array(column) for column in zip(*entries, strict=True))
    pomdp = Pomdp.from_triplets(
        states=states,
        actions=("L", "R"),
        observations=("i", "a", "b", "g", "x"),
        initial_state=0,
        observation_of=np.array([0, 1, 2, 3, 3]),
        action=a,
        source=s,
        target=t,
        probability=p.astype(float),
        absorbing=np.array([False, False, False, True, True]),
    )
    controller = Controller(
        nodes=("n0",),
        initial_node=0,
        action=np.array([[1, 1, 1, 1, 0]]),
        update=np.zeros((1, 5), dtype=np.int64),
    )
    decoy = np.array([False, False, False, False, True])
    return Problem(pomdp, controller, CostModel(5, default=1.0), decoy, budget=1.0, name="hand")


def test_criticality_by_hand():
    """Altering a to x (or to nothing the controller treats like x — only x plays L) makes s1
    play L: 1/2 · 0.6 = 0.3; altering b: 1/2 · 0.3 = 0.15; both: 0.45. Without: 0.
    Budget 1: the optimum alters a (0.3). Protecting a leaves b: 0.15, so criticality(a) =
    0.3 - 0.15 = 0.15; b is not in the optimal attack: criticality 0. Single values: a 0.3,
    b 0.15. Budget 2: optimum 0.45; protecting a leaves 0.15 (criticality 0.30), protecting b
    leaves 0.3 (criticality 0.15)."""
    problem = hand_model()
    one = misdirect.audit(problem, budget=1)
    assert one.probability == pytest.approx(0.3, abs=1e-12)
    rows = {s.observation: s for s in one.sensors}
    assert set(rows) == {"a", "b"}  # i is the initial reading, g only the absorbing states'
    assert rows["a"].criticality == pytest.approx(0.15, abs=1e-12)
    assert rows["a"].protected_probability == pytest.approx(0.15, abs=1e-12)
    assert rows["b"].criticality == 0.0 and not rows["b"].in_optimal_attack
    assert rows["a"].single_probability == pytest.approx(0.3, abs=1e-12)
    assert rows["b"].single_probability == pytest.approx(0.15, abs=1e-12)
    assert one.certified
    two = misdirect.audit(problem, budget=2)
    rows = {s.observation: s for s in two.sensors}
    assert two.probability == pytest.approx(0.45, abs=1e-12)
    assert rows["a"].criticality == pytest.approx(0.30, abs=1e-12)
    assert rows["b"].criticality == pytest.approx(0.15, abs=1e-12)
    assert [p.probability for p in two.curve] == pytest.approx([0.0, 0.3, 0.45], abs=1e-12)
    # hardening with D = 1 against B = 2: protect a (attacker left with 0.15), not b (0.3)
    hardened = misdirect.harden(problem, protect_budget=1, budget=2)
    assert hardened.protection == ["a"]
    assert hardened.value_after == pytest.approx(0.15, abs=1e-12)


def test_online_by_hand():
    """Hand model: memoryless, a and b each read in one state, so unlimited online = offline
    unlimited = 0.45. Paying per reading with budget 1, the online attacker alters whichever
    of s1, s2 the run meets (each run meets one): 0.45 as well — above the offline optimum at
    budget 1 (0.3), because the offline attacker must commit to one sensor in advance. Budget
    0: nothing to alter, 0."""
    problem = hand_model()
    assert misdirect.online_attack_value(problem).probability == pytest.approx(0.45, abs=1e-12)
    assert misdirect.online_attack_value(problem, 1).probability == pytest.approx(0.45, abs=1e-12)
    assert misdirect.online_attack_value(problem, 0).probability == pytest.approx(0.0, abs=1e-12)


def test_budgeted_online_refuses_costs_without_a_common_unit():
    problem = hand_model()
    cost = CostModel(5, default=1.0, pairs={(1, 4): float(np.sqrt(2))})
    problem = replace(problem, cost=cost)
    with pytest.raises(misdirect.ProblemError, match="common unit"):
        misdirect.online_attack_value(problem, 2)
    # the unlimited variant needs no unit
    assert misdirect.online_attack_value(problem).probability == pytest.approx(0.45, abs=1e-12)


# -- Storm: the attacker's product MDP written out independently ------------------------------


def prism_attacker_mdp(problem: Problem, budget: float | None, unit: float = 0.5) -> str:
    """World and controller synchronise on action labels; in state s, node n the attacker
    picks any received observation t that the cost model allows for O(s) (the initial
    observation never altered), which enables the controller's command for (n, t) — one
    nondeterministic choice per t. With a budget, a module-level counter r of remaining cost
    units is decreased by the cost of each altered reading."""
    pomdp, ctrl = problem.pomdp, problem.controller
    lines = ["mdp", *world_module(pomdp)]
    lines += [
        "module controller",
        f"  n : [0..{ctrl.n_nodes - 1}] init {ctrl.initial_node};",
    ]
    levels = None if budget is None else round(budget / unit)
    if levels is not None:
        lines.append(f"  r : [0..{levels}] init {levels};")
    lines += [f"  [act{a}] false -> true;" for a in range(pomdp.n_actions)]
    o_init = pomdp.initial_observation
    for s in range(pomdp.n_states):
        o = int(pomdp.observation_of[s])
        row = problem.cost.row(o)
        targets = (
            [o] if o == o_init else [t for t in range(pomdp.n_observations) if np.isfinite(row[t])]
        )
        for n in range(ctrl.n_nodes):
            for t in targets:
                a, nxt = int(ctrl.action[n, t]), int(ctrl.update[n, t])
                if levels is None or t == o:
                    lines.append(f"  [act{a}] n={n} & s={s} -> (n'={nxt});")
                else:
                    k = round(row[t] / unit)
                    lines.append(f"  [act{a}] n={n} & s={s} & r>={k} -> (n'={nxt}) & (r'=r-{k});")
    lines.append("endmodule")
    decoys = " | ".join(f"s={int(s)}" for s in np.flatnonzero(problem.decoy))
    lines.append(f'label "decoy" = {decoys};')
    return "\n".join(lines) + "\n"


def storm_pmax(tmp_path, text: str) -> float:
    """Storm's Pmax [F decoy] in exact rational arithmetic (skips without stormpy)."""
    stormpy = pytest.importorskip("stormpy")
    path = tmp_path / "attacker.prism"
    path.write_text(text)
    program = stormpy.parse_prism_program(str(path))
    formula = stormpy.parse_properties('Pmax=? [F "decoy"]', program)
    model = stormpy.build_model[stormpy.Rational](program, formula)
    result = stormpy.model_checking(model, formula[0], environment=stormpy.environments.exact())
    return float(result.get_value(model.initial_states[0]))


def test_online_value_agrees_with_storm(tmp_path):
    nontrivial = 0
    for seed in range(20):
        problem = random_problem(seed, states=6, nodes=1 + seed % 3)
        ours = misdirect.online_attack_value(problem).probability
        assert ours == pytest.approx(
            storm_pmax(tmp_path, prism_attacker_mdp(problem, None)), abs=1e-9
        )
        for budget in (1.0, 2.5):
            ours_b = misdirect.online_attack_value(problem, budget).probability
            theirs = storm_pmax(tmp_path, prism_attacker_mdp(problem, budget))
            assert ours_b == pytest.approx(theirs, abs=1e-9), (seed, budget)
            nontrivial += 1e-6 < ours_b < ours - 1e-6  # the budget binds
    assert nontrivial >= 5


def test_online_budgeted_is_not_a_bound_either_way_on_the_grid(tmp_path):
    """Paying per reading, the online attacker does worse than the offline one at budget 1
    (SPEC §3: 0.719924) and better at budget 3 (0.862442); values from Storm."""
    problem = paper_grid(5)
    one = storm_pmax(tmp_path, prism_attacker_mdp(problem, 1.0, unit=1.0))
    three = storm_pmax(tmp_path, prism_attacker_mdp(problem, 3.0, unit=1.0))
    assert one < 0.719924 < 0.862442 < three
    assert misdirect.online_attack_value(problem, 1).probability == pytest.approx(one, abs=1e-9)
    assert misdirect.online_attack_value(problem, 3).probability == pytest.approx(three, abs=1e-9)
    unlimited = storm_pmax(tmp_path, prism_attacker_mdp(problem, None))
    assert misdirect.online_attack_value(problem).probability == pytest.approx(unlimited, abs=1e-9)
    assert unlimited >= 0.863622  # above the offline optimum at every budget (SPEC §3)


# -- command line ------------------------------------------------------------------------------


@pytest.fixture
def hand_file(tmp_path):
    path = tmp_path / "hand.yaml"
    write_problem(hand_model(), path)
    return path


def test_cli_audit_json_and_report(tmp_path, hand_file):
    result = runner.invoke(app, ["audit", str(hand_file), "--budget", "2", "--json"])
    assert result.exit_code == 0, result.output
    data = json.loads(result.stdout)
    assert data["value"] == pytest.approx(0.45, abs=1e-12)
    assert [p["value"] for p in data["curve"]] == pytest.approx([0, 0.3, 0.45], abs=1e-12)
    sensors = {s["observation"]: s for s in data["sensors"]}
    assert sensors["a"]["criticality"] == pytest.approx(0.3, abs=1e-12)
    assert data["online"]["unlimited_value"] == pytest.approx(0.45, abs=1e-12)
    assert data["certified"] is True
    out = tmp_path / "report"
    result = runner.invoke(
        app, ["audit", "--scenario", "paper-grid", "--budget", "2", "-o", str(out)]
    )
    assert result.exit_code == 0, result.output
    for name in ("report.md", "curve.csv", "sensors.csv", "curve.png", "sensors.png", "map.png"):
        assert (out / name).stat().st_size > 0, name
    curve = (out / "curve.csv").read_text().splitlines()
    assert len(curve) == 4 and curve[2].startswith("1,0.719923673")  # SPEC §3, budget 1
    assert "0.860130282" in (out / "report.md").read_text()  # SPEC §3, budget 2


def test_cli_harden_json(hand_file):
    result = runner.invoke(
        app, ["harden", str(hand_file), "--budget", "2", "--protect-budget", "1", "--json"]
    )
    assert result.exit_code == 0, result.output
    data = json.loads(result.stdout)
    assert data["protection"] == ["a"] and data["status"] == "optimal"
    assert data["value_unprotected"] == pytest.approx(0.45, abs=1e-12)
    assert data["value"] == pytest.approx(0.15, abs=1e-12)
    assert [p["value"] for p in data["curve"]] == pytest.approx([0.45, 0.15], abs=1e-12)
    # protecting a costs 2 now: only b is affordable within D = 1 (attacker keeps a: 0.3)
    result = runner.invoke(
        app,
        ["harden", str(hand_file), "--budget", "2", "--protect-budget", "1",
         "--protect-cost", "default=1,a=2", "--json"],
    )  # fmt: skip
    data = json.loads(result.stdout)
    assert data["protection"] == ["b"] and data["value"] == pytest.approx(0.3, abs=1e-12)


@pytest.mark.parametrize(
    ("args", "field"),
    [
        (["harden", "--protect-budget", "-1"], "--protect-budget"),
        (["harden", "--protect-budget", "1", "--protect-cost", "zz=1"], "--protect-cost"),
        (["harden", "--protect-budget", "1", "--protect-cost", "o1"], "--protect-cost"),
        (["harden", "--protect-budget", "1", "--protect-cost", "o1=-2"], "--protect-cost"),
        (["harden", "--protect-budget", "1", "--time-limit", "0"], "--time-limit"),
        (["audit", "--budget", "-1"], "--budget"),
        (["audit", "--time-limit", "-5"], "--time-limit"),
    ],
)
def test_cli_bad_input_is_one_line_and_exit_2(args, field):
    result = runner.invoke(app, [*args, "--scenario", "paper-grid"])
    assert result.exit_code == 2, result.output
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error:") and field in lines[0]
    assert "Traceback" not in result.output


def test_cli_audit_output_folder_that_is_a_file(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    result = runner.invoke(app, ["audit", "--scenario", "paper-grid", "-o", str(blocker)])
    assert result.exit_code == 2


# -- the benchmark's quick mode ------------------------------------------------------------------


def test_defence_benchmark_quick_mode(tmp_path):
    """bench/defence.py --quick: every goal row present, values checked, no timing."""
    import csv
    import subprocess
    import sys
    from pathlib import Path

    script = Path(__file__).parent.parent / "bench" / "defence.py"
    subprocess.run(
        [sys.executable, str(script), "--quick", "--out", str(tmp_path)],
        check=True,
        capture_output=True,
    )
    rows = {r["goal"]: r for r in json.loads((tmp_path / "defence.json").read_text())["rows"]}
    assert set(rows) == {"D1", "D2", "D3"}
    # SPEC §3: the 5x5 grid at budgets 0..2, and at budget 4 (hardening with D = 0)
    curve = [p["probability"] for p in rows["D1"]["detail"]["curve"]]
    assert curve == pytest.approx([0.084957, 0.719924, 0.860130], abs=5e-7)
    harden = rows["D3"]["detail"]["curve"]
    assert harden[0]["protection"] == []
    assert harden[0]["probability"] == pytest.approx(0.863622, abs=5e-7)
    assert harden[1]["probability"] <= harden[0]["probability"]
    # the online attacker bounds the offline optimum (docs/defence.md)
    assert rows["D1"]["detail"]["online_unlimited"] >= curve[-1]
    assert {r["goal"] for r in csv.DictReader((tmp_path / "defence.csv").open())} == set(rows)
    assert "| D3 |" in (tmp_path / "defence.md").read_text()


# -- the audit reuses what it proved ------------------------------------------------------------


class NoProof:
    """A method that proves nothing: the unaltered chain with bound 1, what branch-and-bound
    reported for budget 1 on drone-4-1's cycling chain (issue 27)."""

    name = "no-proof"
    curve_is_free = False
    accepts = ("time_limit",)

    def __init__(self, options=None):
        pass

    def solve(self, problem, budgets, *, progress=None, deadline=None):
        from misdirect.solvers.base import Solution
        from misdirect.solvers.status import Status

        value = decoy_probability(problem, problem.identity())
        return [
            Solution(b, problem.identity(), value, Status.TIME_LIMIT, upper_bound=1.0)
            for b in budgets
        ]


@pytest.fixture
def no_proof(monkeypatch):
    from misdirect.solvers import SOLVERS

    monkeypatch.setitem(SOLVERS, "no-proof", NoProof)
    return "no-proof"


def best_single_sensor(problem: Problem, budget: float) -> float:
    """Brute force: the best value of the unaltered chain and of every alteration of one
    observation (the initial one stays) to any target it may take within ``budget``."""
    best = decoy_probability(problem, problem.identity())
    for o in range(problem.pomdp.n_observations):
        if o == problem.pomdp.initial_observation:
            continue
        row = problem.cost.row(o)
        for t in np.flatnonzero(row <= budget + 1e-9):
            alpha = problem.identity()
            alpha[o] = t
            best = max(best, decoy_probability(problem, alpha))
    return best


def test_audit_proves_budget_one_by_the_single_sensor_optima(no_proof):
    """Issue 27 (drone-4-1, audit at budget 2: every single-sensor value optimal, yet budget 1
    reported open with bound 1). With unit costs budget 1 affords one sensor at most, so its
    optimum is the best single-sensor optimum: proven even when the curve's own solve proves
    nothing. Expected value: brute force over every single-observation alteration of a patrol
    that can turn back; budget 2 (two sensors fit) stays open, bound 1."""
    from turnback import turnback

    problem = turnback(3, nodes=1, budget=2)
    result = misdirect.audit(problem, budget=2, method=no_proof)
    zero, one, two = result.curve
    expected = best_single_sensor(problem, 1.0)
    assert expected > decoy_probability(problem, problem.identity()) + 1e-3
    assert one.status == "optimal"
    assert one.probability == pytest.approx(expected, abs=1e-12)
    assert one.upper_bound - one.probability <= 1e-9
    assert one.certified_by == "single-sensor optima"
    assert "one sensor at most" in one.to_dict()["certification"]["bound_from"]
    assert all(row.single_status == "optimal" for row in result.sensors)
    assert max(row.single_probability for row in result.sensors) == pytest.approx(expected)
    assert zero.status == "optimal" and zero.alteration == {}
    assert two.status != "optimal" and two.upper_bound == 1.0
    assert two.probability >= one.probability


def test_audit_single_sensor_bound_follows_the_costs(no_proof):
    """Costs decide which budgets the single-sensor optima settle. Hand model with altering a
    costing 2 (b costs 1): budget 1 affords only b (0.15), budget 2 only a (0.3: both cost 3),
    both proven by brute force over every alteration. With every alteration at 0.5, budget 1
    affords two sensors, so the singles bound nothing there: the point stays open, its bound
    still at least the brute-force optimum."""
    problem = hand_model()
    costly_a = CostModel(5, default=1.0, pairs={(1, t): 2.0 for t in (0, 2, 3, 4)})
    problem = replace(problem, cost=costly_a)
    result = misdirect.audit(problem, budget=2, method=no_proof)
    for point in result.curve:
        expected = max(v for v, _ in brute_values(problem, point.budget))
        assert point.status == "optimal", point.budget
        assert point.probability == pytest.approx(expected, abs=1e-12)
    assert [p.probability for p in result.curve] == pytest.approx([0.0, 0.15, 0.3], abs=1e-12)

    cheap = replace(problem, cost=CostModel(5, default=0.5))
    result = misdirect.audit(cheap, budget=1, method=no_proof)
    zero, one = result.curve
    assert zero.status == "optimal" and one.status != "optimal"
    assert one.upper_bound >= max(v for v, _ in brute_values(cheap, 1.0)) - 1e-12


def test_an_unattacked_sensor_of_a_certified_optimum_is_exactly_not_critical():
    """Protecting a sensor the optimal alteration leaves alone keeps it feasible, and only
    removes alterations: the optimum is unchanged, a drop of exactly 0, even when the
    certified optimum's bound sits a rounding above its value (a gap of 1e-16 over 0 read as
    unproven, and the whole audit as uncertified). Uncertified, the gap is the honest range."""
    from misdirect.defence.attack import Attack
    from misdirect.defence.auditing import _criticality
    from misdirect.solvers.status import Status

    value = 0.8636215453434299
    certified = Attack(value, value + 1.1e-16, Status.OPTIMAL, {}, frozenset(), 0.0)
    assert _criticality(certified, None) == (0.0, 0.0)
    open_ = Attack(value, 0.9, Status.TIME_LIMIT, {}, frozenset(), 0.0)
    low, high = _criticality(open_, None)
    assert low == 0.0 and high == pytest.approx(0.9 - value)
