"""The MILP solver: exact on every model, the SPEC numbers on every backend, limits honoured.

Oracles: the exhaustive solver (itself checked against brute force over all Ω -> Ω in
test_exhaustive.py), SPEC §3/§4 values, and hand calculations on examples/trap.yaml.
"""

from __future__ import annotations

import json
from pathlib import Path

import highspy
import numpy as np
import pytest
from typer.testing import CliRunner

from misdirect import decoy_probability, load_problem, solve
from misdirect.cli import app
from misdirect.errors import SolverError
from misdirect.scenarios import knapsack, paper_grid, random_problem
from misdirect.solvers.milp import build_formulation

EXAMPLES = Path(__file__).parent.parent / "examples"
GRID_OPTIMA = [0.084957, 0.719924, 0.860130, 0.862442, 0.863622]  # SPEC §3, budgets 0..4
runner = CliRunner()


# -- exactness against the oracle ------------------------------------------------------------

CHUNKS, PER_CHUNK = 12, 25  # 300 random models


def _random_model(seed: int):
    rng = np.random.default_rng(10_000 + seed)
    return random_problem(
        seed,
        states=int(rng.integers(3, 9)),
        actions=int(rng.integers(1, 4)),
        observations=int(rng.integers(2, 5)),
        nodes=int(rng.integers(1, 4)),
    )


@pytest.mark.parametrize("chunk", range(CHUNKS))
def test_compact_milp_equals_exhaustive_on_random_models(chunk):
    budgets = [0.0, 1.0, 2.5, 4.0]
    for seed in range(chunk * PER_CHUNK, (chunk + 1) * PER_CHUNK):
        problem = _random_model(seed)
        oracle = solve(problem, method="exhaustive", budgets=budgets)
        result = solve(problem, method="milp", budgets=budgets)
        assert not result.warnings, (seed, result.warnings)
        for mine, best in zip(result.curve, oracle.curve, strict=True):
            context = (seed, mine.budget, mine.alteration)
            assert mine.status == "optimal", context
            assert mine.probability == pytest.approx(best.probability, abs=1e-7), context
            assert mine.cost <= mine.budget + 1e-9, context
            alpha = problem.alteration(mine.alteration)
            assert decoy_probability(problem, alpha) == pytest.approx(mine.probability, abs=1e-12)
            assert mine.solver_probability == pytest.approx(mine.probability, abs=1e-6), context


def test_random_models_exercise_the_witness_rows():
    """The models above must include ones that can cycle, or the witness rows go untested."""
    cycling = sum(
        build_formulation(_random_model(seed), "compact", 4.0).notes["end_component_states"] > 0
        for seed in range(CHUNKS * PER_CHUNK)
    )
    assert cycling >= 30


def test_witness_rows_are_what_makes_it_exact(monkeypatch):
    """Without them, maximising the Bellman inequalities overshoots on models that can cycle."""
    import misdirect.milp.compact as compact

    monkeypatch.setattr(
        compact, "end_component_states", lambda group_state, transitions, live: live & False
    )
    wrong = 0
    for seed in range(60):
        result = solve(_random_model(seed), method="milp", budgets=[0.0, 2.0])
        wrong += bool(result.warnings)
    assert wrong > 0


def test_trap_example_by_hand():
    """examples/trap.yaml: 0.4·0.25 = 0.1 unaltered; o1 -> o0 adds 0.6·0.5 = 0.3."""
    problem = load_problem(EXAMPLES / "trap.yaml")
    result = solve(problem, method="milp", budgets=[0, 1])
    assert [p.probability for p in result.curve] == pytest.approx([0.1, 0.4], abs=1e-12)
    assert result.curve[1].alteration == {"o1": "o0"}
    assert result.stats["end_component_states"] >= 1  # the loop state needs a witness


def test_no_witness_rows_on_the_grid():
    model = build_formulation(paper_grid(5), "compact", 4)
    assert model.notes["end_component_states"] == 0
    assert set(model.column_blocks) == {"alteration", "probability"}


# -- SPEC values on every backend ------------------------------------------------------------


def _backend_or_skip(name: str):
    if name == "gurobi":
        pytest.importorskip("gurobipy")
    if name == "scip":
        pytest.importorskip("pyscipopt")


@pytest.mark.parametrize("backend", ["highs", "scip", "gurobi"])
def test_grid_table_on_each_backend(backend):
    _backend_or_skip(backend)
    try:
        result = solve(paper_grid(5), method="milp", budgets=range(5), solver=backend)
    except SolverError as error:  # e.g. no Gurobi licence
        pytest.skip(str(error))
    assert [p.probability for p in result.curve] == pytest.approx(GRID_OPTIMA, abs=5e-7)
    assert all(p.status == "optimal" for p in result.curve)
    assert not result.warnings


@pytest.mark.parametrize("backend", ["highs", "scip", "gurobi"])
def test_knapsack_reduction_on_each_backend(backend):
    _backend_or_skip(backend)
    try:
        result = solve(
            knapsack([1, 2, 3, 4, 5], [20, 30, 40, 50, 60], 7), method="milp", solver=backend
        )
    except SolverError as error:
        pytest.skip(str(error))
    assert result.probability == pytest.approx(0.25, abs=1e-12)
    assert result.alteration == {"o1": "o_club", "o2": "o_club", "o4": "o_club"}


def test_missing_backend_is_a_clear_error(monkeypatch):
    import sys

    monkeypatch.setitem(sys.modules, "gurobipy", None)  # import fails as if not installed
    result = runner.invoke(app, ["solve", str(EXAMPLES / "trap.yaml"), "--solver", "gurobi"])
    assert result.exit_code == 1
    assert "pip install 'misdirect[gurobi]'" in result.stderr
    assert "Traceback" not in result.output


@pytest.mark.parametrize(
    ("args", "field"),
    [
        (["--solver", "cplex"], "--solver"),
        (["--formulation", "clever"], "--formulation"),
        (["--method", "exhaustive", "--time-limit", "3"], "--time-limit"),
        (["--time-limit", "-1"], "--time-limit"),
        (["--threads", "0"], "--threads"),
        (["--verbose"], "--verbose"),
    ],
)
def test_bad_milp_options(args, field):
    result = runner.invoke(app, ["solve", str(EXAMPLES / "trap.yaml"), *args, "--json"])
    assert result.exit_code == 2, result.output
    assert json.loads(result.stdout)["error"]["field"] == field


# -- the paper's formulation -----------------------------------------------------------------


def _paper_counts(n: int) -> tuple[int, int]:
    """Closed form for the scaled grid (see misdirect.milp.paper): |Ω| = 8, |N| = 3, and
    E = 4n² - 9 successor pairs (4 per cell; 3 for the three non-goal corners, which can stay
    put and have two neighbours; 1 for the absorbing goal and hazard)."""
    cells, observations, nodes = n * n, 8, 3
    edges = 4 * n * n - 9
    l_vars = edges * observations * nodes * observations
    variables = observations**2 + cells * nodes * observations + l_vars
    rows = 2 + observations + cells * nodes * observations + 4 * l_vars
    return variables, rows


def test_closed_form_matches_spec_at_45():
    variables, rows = _paper_counts(45)
    assert 1_600_000 < variables < 1_700_000  # "just over 1.6 million variables"
    assert 6_200_000 < rows < 6_300_000  # "more than 6.2 million constraints"


@pytest.mark.parametrize("n", [5, 15])
def test_paper_formulation_counts(n):
    model = build_formulation(paper_grid(n), "paper", 4)
    assert (model.n_columns, model.n_rows) == _paper_counts(n)
    assert model.integer.sum() == 64


def test_paper_formulation_is_unsound_on_the_grid():
    """SPEC §2: z_goal = z_goal lets the maximiser claim 1 where the truth is 0.085."""
    result = solve(paper_grid(5), method="milp", budgets=[0], formulation="paper")
    point = result.curve[0]
    assert point.solver_probability == pytest.approx(1.0, abs=1e-6)
    assert point.probability == pytest.approx(GRID_OPTIMA[0], abs=5e-7)
    assert point.status == "unverified" and result.warnings
    assert point.upper_bound is None  # a bound from an unsound model would be a lie


def test_pinning_fixes_the_goal_but_not_a_loop():
    # pinning z = 0 where no alteration reaches the decoy mends the grid ...
    grid = solve(paper_grid(5), method="milp", budgets=[0], formulation="paper-pinned")
    assert grid.curve[0].solver_probability == pytest.approx(GRID_OPTIMA[0], abs=1e-6)
    assert not grid.warnings
    # ... but not the trap: `loop` escapes under o1 -> o0, so it is not pinned, and under the
    # identity z_loop = z_loop is free. Claimed 0.6·1 + 0.4·0.25 = 0.7; true optimum 0.4.
    trap = load_problem(EXAMPLES / "trap.yaml")
    pinned = solve(trap, method="milp", budgets=[1], formulation="paper-pinned")
    assert pinned.curve[0].solver_probability == pytest.approx(0.7, abs=1e-6)
    assert pinned.probability == pytest.approx(0.1, abs=1e-12)  # it even picks the wrong α
    assert pinned.warnings
    assert solve(trap, method="milp", budgets=[1]).probability == pytest.approx(0.4, abs=1e-12)


# -- limits, curve, statistics, export -------------------------------------------------------


def test_time_limit_returns_a_verified_incumbent():
    problem = paper_grid(45)
    result = solve(problem, method="milp", budgets=[3], time_limit=1.0)
    point = result.curve[0]
    assert point.status == "time_limit"
    assert point.cost <= 3
    assert point.probability == pytest.approx(
        decoy_probability(problem, problem.alteration(point.alteration)), abs=1e-12
    )
    assert point.upper_bound is not None and point.upper_bound >= point.probability - 1e-9
    assert point.gap == pytest.approx(point.upper_bound - point.probability)
    assert point.stats["solve_time_s"] < 30  # the limit was honoured, loosely


def test_cli_time_limit_json():
    result = runner.invoke(
        app,
        [
            "solve",
            "--scenario",
            "paper-grid",
            "--size",
            "45",
            "--budget",
            "3",
            "--time-limit",
            "1",
            "--method",
            "milp",
            "--json",
        ],
    )
    assert result.exit_code == 0, result.output
    payload = json.loads(result.stdout)
    assert payload["status"] == "time_limit"
    assert payload["upper_bound"] >= payload["probability"]
    assert payload["gap"] >= 0


def test_cli_curve_with_stats():
    result = runner.invoke(
        app, ["solve", "--scenario", "paper-grid", "--budget", "0..4", "--method", "milp", "--json"]
    )
    assert result.exit_code == 0, result.output
    payload = json.loads(result.stdout)
    assert [p["probability"] for p in payload["curve"]] == pytest.approx(GRID_OPTIMA, abs=5e-7)
    for point in payload["curve"]:
        stats = point["stats"]
        assert {
            "variables",
            "binaries",
            "rows",
            "nonzeros",
            "build_time_s",
            "solve_time_s",
            "status",
            "bound",
            "nodes",
        } <= stats.keys()
        assert stats["status"] == "optimal"
    assert payload["method"] == "milp"


def test_cli_budgets_list():
    result = runner.invoke(
        app, ["solve", "--scenario", "paper-grid", "--budgets", "2,0", "--method", "milp", "--json"]
    )
    payload = json.loads(result.stdout)
    assert [p["budget"] for p in payload["curve"]] == [0, 2]
    assert payload["probability"] == pytest.approx(GRID_OPTIMA[2], abs=5e-7)


@pytest.mark.parametrize("suffix", [".mps", ".lp"])
def test_exported_model_solves_to_the_spec_value(tmp_path, suffix):
    """Another reader of the file (HiGHS' own parser) finds the SPEC optimum for budget 1."""
    path = tmp_path / f"grid{suffix}"
    result = runner.invoke(
        app, ["export-milp", "--scenario", "paper-grid", "--budget", "1", "-o", str(path)]
    )
    assert result.exit_code == 0, result.output
    highs = highspy.Highs()
    highs.setOptionValue("output_flag", False)
    highs.readModel(str(path))
    highs.run()
    assert highs.getInfo().objective_function_value == pytest.approx(GRID_OPTIMA[1], abs=1e-6)


def test_export_rejects_unknown_suffix(tmp_path):
    result = runner.invoke(
        app, ["export-milp", "--scenario", "paper-grid", "-o", str(tmp_path / "m.txt"), "--json"]
    )
    assert result.exit_code == 2
    assert json.loads(result.stdout)["error"]["field"] == "-o"


# -- a crashing solver must not take the session with it -------------------------------------


def test_highs_crash_is_retried_in_a_fresh_worker(monkeypatch):
    import os

    import misdirect.milp.backends as backends

    real = backends.run_highs

    def crash_on_first_seed(arrays, options, start, seed=0):
        if seed == 0:
            os._exit(139)  # what a segmentation fault in HiGHS looks like from outside
        return real(arrays, options, start, seed)

    monkeypatch.setattr(backends, "run_highs", crash_on_first_seed)
    result = solve(paper_grid(5), method="milp", budgets=[1])
    assert result.probability == pytest.approx(GRID_OPTIMA[1], abs=5e-7)
    assert result.curve[0].stats["highs_crashes"] == 1


def test_highs_crashing_every_time_is_a_clear_error(monkeypatch):
    import os

    import misdirect.milp.backends as backends

    monkeypatch.setattr(backends, "run_highs", lambda *args, **kwargs: os._exit(139))
    result = runner.invoke(app, ["solve", str(EXAMPLES / "trap.yaml"), "--method", "milp"])
    assert result.exit_code == 1
    assert "HiGHS crashed 2 times" in result.stderr and "--solver scip" in result.stderr
    assert "Traceback" not in result.output


def _knapsack_in_a_pool_worker(_: int) -> float:
    problem = knapsack([1, 2, 3, 4, 5], [20, 30, 40, 50, 60], 7)
    return solve(problem, method="milp").probability


def test_milp_inside_a_multiprocessing_pool():
    """A pool worker is daemonic and may not start the HiGHS worker process: still solves."""
    import multiprocessing

    with multiprocessing.get_context("spawn").Pool(1) as pool:
        assert pool.map(_knapsack_in_a_pool_worker, [0]) == [pytest.approx(0.25, abs=1e-12)]
