"""The public API as a user meets it: names, reprs, conversions, keyword errors.

Expected values: the trap example by hand (from ``start`` 0.4 reaches ``exit``, whose ``stay``
ends in the decoy with 0.25: 0.1 unaltered; reading the loop's ``o1`` as ``o0`` sends the 0.6
in the loop on, half into the decoy: 0.1 + 0.3 = 0.4); the paper's grid from the paper (0.720
at budget 1 with o1 → o3).
"""

from __future__ import annotations

import builtins
import pickle
from pathlib import Path

import numpy as np
import pytest
import yaml

import misdirect
from misdirect.scenarios import paper_grid

ROOT = Path(__file__).resolve().parents[1]
TRAP = ROOT / "examples" / "trap.yaml"


def test_every_public_name_is_importable():
    for name in misdirect.__all__:
        assert getattr(misdirect, name) is not None, name


# -- Alteration ------------------------------------------------------------------------------


def test_alteration_names_its_observations():
    problem = paper_grid(5)
    alteration = problem.alteration({"o1": "o3", "o2": "o0"})
    assert isinstance(alteration, misdirect.Alteration)
    assert alteration.observations == problem.pomdp.observations
    assert alteration.changes == {"o1": "o3", "o2": "o0"}
    assert alteration["o1"] == "o3" and alteration["o4"] == "o4"
    assert repr(alteration) == "Alteration({'o1': 'o3', 'o2': 'o0'})"
    assert str(alteration) == "o1 → o3, o2 → o0"
    with pytest.raises(KeyError, match="unknown observation 'o9'"):
        alteration["o9"]


def test_alteration_is_still_the_integer_array():
    """Existing callers: the plain array, comparisons as masks, indexing as integers."""
    problem = paper_grid(5)
    alteration = problem.alteration({"o1": "o3"})
    names = problem.pomdp.observations
    expected = [names.index(n) for n in names]
    expected[names.index("o1")] = names.index("o3")
    plain = np.asarray(alteration)
    assert type(plain) is np.ndarray and plain.tolist() == expected
    mask = alteration != problem.identity()
    assert type(mask) is np.ndarray and mask.tolist() == [n == "o1" for n in names]
    assert int(alteration[names.index("o1")]) == names.index("o3")
    assert type(alteration[1:3]) is np.ndarray
    copy = alteration.copy()
    copy[names.index("o2")] = names.index("o0")
    assert copy.changes == {"o1": "o3", "o2": "o0"} and alteration.changes == {"o1": "o3"}
    again = pickle.loads(pickle.dumps(alteration))
    assert again.changes == {"o1": "o3"} and again.observations == names


def test_alteration_is_taken_wherever_an_array_was():
    problem = paper_grid(5)
    alteration = problem.alteration({"o1": "o3"})
    assert misdirect.evaluate(problem, alteration).probability == pytest.approx(0.72, abs=5e-4)
    assert misdirect.decoy_probability(problem, alteration) == pytest.approx(0.72, abs=5e-4)


def test_alteration_refuses_a_wrong_length():
    with pytest.raises(ValueError, match="one entry per observation"):
        misdirect.Alteration([0, 1], ("a", "b", "c"))


def test_solve_result_carries_a_named_alteration():
    problem = misdirect.load_problem(TRAP)
    result = misdirect.solve(problem)
    assert result.alteration == {"o1": "o0"}
    assert result.alteration_array.changes == {"o1": "o0"}
    assert result.probability == pytest.approx(0.4, abs=1e-12)


# -- reprs -----------------------------------------------------------------------------------


def test_reprs_are_short_and_have_no_arrays():
    problem = paper_grid(15)  # 225 states: a dataclass repr would run to thousands of chars
    result = misdirect.solve(problem, budgets=range(3))
    for text in (repr(problem), repr(problem.pomdp), repr(problem.controller), repr(result)):
        assert len(text) < 300, text
        assert "array(" not in text and "\n" not in text
    assert "225 states" in repr(problem)
    assert "curve=3 points" in repr(result) and "status=optimal" in repr(result)
    assert len(repr(result.curve[0])) < 200


def test_defence_reprs_are_short():
    problem = paper_grid(5)
    audit = misdirect.audit(problem, budget=2)
    plan = misdirect.harden(problem, protect_budget=1, budget=2)
    assert len(repr(audit)) < 300 and "sensors=" in repr(audit)
    assert len(repr(plan)) < 300 and "protection=['o1']" in repr(plan)


# -- problem_from_dict -----------------------------------------------------------------------


def _same_problem(a: misdirect.Problem, b: misdirect.Problem) -> None:
    assert a.pomdp.states == b.pomdp.states
    assert a.pomdp.observations == b.pomdp.observations
    assert np.array_equal(a.pomdp.observation_of, b.pomdp.observation_of)
    assert (a.pomdp.transitions != b.pomdp.transitions).nnz == 0
    assert np.array_equal(a.decoy, b.decoy) and a.budget == b.budget and a.name == b.name
    assert np.array_equal(a.cost.matrix(), b.cost.matrix())
    assert np.array_equal(a.controller.move, b.controller.move)


@pytest.mark.parametrize("name", ["trap.yaml", "tiny.yaml", "paper-grid-map.yaml"])
def test_problem_from_dict_is_load_problem_of_the_same_yaml(name: str):
    path = ROOT / "examples" / name
    document = yaml.safe_load(path.read_text(encoding="utf-8"))
    from_dict = misdirect.problem_from_dict(document)
    _same_problem(from_dict, misdirect.load_problem(path))


def test_problem_from_dict_values_by_hand():
    document = yaml.safe_load(TRAP.read_text(encoding="utf-8"))
    problem = misdirect.problem_from_dict(document)
    assert misdirect.evaluate(problem).probability == pytest.approx(0.1, abs=1e-12)
    altered = misdirect.evaluate(problem, problem.alteration({"o1": "o0"}))
    assert altered.probability == pytest.approx(0.4, abs=1e-12)


def test_problem_from_dict_errors_name_the_source_and_field():
    document = yaml.safe_load(TRAP.read_text(encoding="utf-8"))
    document["deception"]["budget"] = -1
    with pytest.raises(misdirect.ProblemError, match=r"^robot: deception\.budget"):
        misdirect.problem_from_dict(document, source="robot")


# -- keyword errors --------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("call", "typo", "meant"),
    [
        (lambda p: misdirect.solve(p, time_limt=5), "time_limt", "time_limit"),
        (lambda p: misdirect.solve(p, mip_gpa=0.1), "mip_gpa", "mip_gap"),
        (lambda p: misdirect.audit(p, budgte=1), "budgte", "budget"),
        (lambda p: misdirect.harden(p, protect_budget=1, protect_cost={}), "protect_cost", None),
        (lambda p: misdirect.simulate(p, run=10), "run", "runs"),
    ],
)
def test_a_keyword_typo_names_it_and_the_valid_ones(call, typo, meant):
    problem = paper_grid(5)
    with pytest.raises(TypeError) as error:
        call(problem)
    message = str(error.value)
    assert f"unexpected keyword argument {typo!r}" in message
    assert "valid keywords: problem," in message
    assert "MilpSolver" not in message and "__init__" not in message
    if meant is not None:
        assert f"did you mean {meant!r}" in message


def test_the_signature_stays_explicit():
    """help() and the API reference show the keywords, not ``**options``."""
    import inspect

    parameters = inspect.signature(misdirect.solve).parameters
    for name in ("time_limit", "threads", "solver", "formulation", "mip_gap", "progress"):
        assert parameters[name].kind is inspect.Parameter.KEYWORD_ONLY
    assert not any(p.kind is inspect.Parameter.VAR_KEYWORD for p in parameters.values())
    for function in (misdirect.solve, misdirect.evaluate, misdirect.audit, misdirect.harden):
        assert "Parameters\n" in function.__doc__ and "Examples\n" in function.__doc__


# -- certified_by ----------------------------------------------------------------------------


@pytest.mark.parametrize("method", ["milp", "exhaustive", "branch-and-bound"])
def test_certified_by_names_a_single_method_that_proved_its_point(method: str):
    result = misdirect.solve(paper_grid(5), budgets=range(3), method=method)
    assert [p.status for p in result.curve] == ["optimal"] * 3
    assert [p.certified_by for p in result.curve] == [method] * 3
    assert result.to_dict()["certified_by"] == method
    assert [p["certified_by"] for p in result.to_dict()["curve"]] == [method] * 3


def test_certified_by_stays_empty_when_not_proven():
    """The paper's MILP claims 1.0 where the truth is 0.085: unverified, certified by none."""
    result = misdirect.solve(paper_grid(5), budgets=[0], method="milp", formulation="paper")
    assert result.status != "optimal"
    assert result.certified_by is None


# -- to_dict / to_dataframe ------------------------------------------------------------------


def test_to_dataframe_tabulates_the_curve():
    pytest.importorskip("pandas")
    result = misdirect.solve(paper_grid(5), budgets=range(3))
    frame = result.to_dataframe()
    assert list(frame["budget"]) == [0.0, 1.0, 2.0]
    assert list(frame["status"]) == ["optimal"] * 3
    assert frame["value"].round(3).tolist() == [0.085, 0.72, 0.86]
    assert frame["alteration"].iloc[0] == "none"


def test_defence_dataframes():
    pytest.importorskip("pandas")
    problem = paper_grid(5)
    sensors = misdirect.audit(problem, budget=2).to_dataframe()
    assert sensors["observation"].iloc[0] == "o1"
    assert (sensors["criticality"].diff().dropna() <= 0).all()  # most critical first
    curve = misdirect.harden(problem, protect_budget=1, budget=2).to_dataframe()
    assert list(curve["protect_budget"]) == [0.0, 1.0]
    assert curve["protection"].tolist() == ["", "o1"]


def test_to_dataframe_without_pandas_says_how_to_get_it(monkeypatch: pytest.MonkeyPatch):
    real_import = builtins.__import__

    def no_pandas(name, *args, **kwargs):
        if name == "pandas" or name.startswith("pandas."):
            raise ImportError("No module named 'pandas'")
        return real_import(name, *args, **kwargs)

    result = misdirect.solve(paper_grid(5), budgets=[0])
    monkeypatch.setattr(builtins, "__import__", no_pandas)
    with pytest.raises(ImportError, match=r"needs pandas.*pip install pandas"):
        result.to_dataframe()


def test_simulation_to_dict_counts_add_up():
    problem = misdirect.load_problem(TRAP)
    runs = misdirect.simulate(problem, problem.alteration({"o1": "o0"}), runs=4000, seed=1)
    document = runs.to_dict()
    total = document["decoy_hits"] + sum(document["absorbed"].values())
    assert total + document["trapped"] + document["unfinished"] == 4000
    assert document["confidence_interval"] == list(runs.confidence_interval())
    low, high = runs.confidence_interval(z=4.0)  # 1 in 15,000 to miss: a seeded run, not flaky
    assert low < 0.4 < high  # the hand value
