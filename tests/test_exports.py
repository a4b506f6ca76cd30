"""export-milp's column map and `misdirect decode` of another solver's solution; export-chain
model-checked by Storm. Expected values: tiny.yaml by hand (its description: 0.2 unattacked,
0.6 with o2 -> o1, 1 with o1 -> o2 and o2 -> o1), and an independent linear solve of the
written chain."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from typer.testing import CliRunner

from misdirect import evaluate, load_problem, write_problem
from misdirect.cli import app
from misdirect.io.solution import read_solution
from misdirect.scenarios import paper_grid
from result_schema import checked
from scale_model import scale_model_text

EXAMPLES = Path(__file__).parents[1] / "examples"
TINY = EXAMPLES / "tiny.yaml"
runner = CliRunner()


def _run(*args: str):
    return runner.invoke(app, [*map(str, args)])


def _columns(mapping: dict, changes: dict[str, str]) -> list[str]:
    """The columns of ``mapping`` that choose ``changes`` (identity elsewhere)."""
    chosen = []
    for entry in mapping["alteration_columns"]:
        o, t = entry["observation"], entry["target"]
        if changes.get(o, o) == t:
            chosen.append(entry["column"])
    return chosen


# -- export-milp + decode -----------------------------------------------------------------------


def test_highs_solution_of_the_exported_model_decodes(tmp_path):
    highspy = pytest.importorskip("highspy")
    model = tmp_path / "m.mps"
    result = _run("export-milp", TINY, "-o", model, "--json")
    assert result.exit_code == 0, result.output
    written = json.loads(result.stdout)["written"]
    assert written == [str(model), str(tmp_path / "m.columns.json")]
    mapping = json.loads((tmp_path / "m.columns.json").read_text())
    assert mapping["schema"] == "misdirect-milp-columns/1"
    # every entry names a real column of the model, with its cost from the file
    assert all(entry["column"] == f"c{entry['index']}" for entry in mapping["alteration_columns"])
    o2_o1 = [
        e for e in mapping["alteration_columns"] if (e["observation"], e["target"]) == ("o2", "o1")
    ]
    assert o2_o1 and o2_o1[0]["cost"] == 1.0
    solver = highspy.Highs()
    solver.setOptionValue("output_flag", False)
    solver.readModel(str(model))
    solver.run()
    solution = tmp_path / "m.sol"
    solver.writeSolution(str(solution), 0)
    result = _run("decode", model, solution, "--json")
    assert result.exit_code == 0, result.output
    payload = checked(result.stdout)
    assert payload["schema"] == "misdirect-result/1" and payload["within_budget"] is True
    assert payload["value"] == pytest.approx(0.6, abs=1e-12)  # by hand
    assert payload["alteration"] in ({"o2": "o1"}, {"o2": "g"})  # both reach 0.6
    assert payload["warnings"] == []


@pytest.mark.parametrize("style", ["gurobi", "scip"])
def test_hand_written_solutions_decode(tmp_path, style):
    """The paper formulation at budget 4: a solution choosing o1 -> o2 and o2 -> o1, written
    as Gurobi (every column, a '# Objective value' line) or SCIP (zeros left out, '(obj:..)')."""
    model = tmp_path / "p.lp"
    result = _run("export-milp", TINY, "-o", model, "--formulation", "paper", "--budget", "4")
    assert result.exit_code == 0, result.output
    mapping = json.loads((tmp_path / "p.columns.json").read_text())
    ones = set(_columns(mapping, {"o1": "o2", "o2": "o1"}))
    if style == "gurobi":
        lines = ["# Objective value = 1"] + [
            f"{e['column']} {1 if e['column'] in ones else 0}"
            for e in mapping["alteration_columns"]
        ]
    else:
        lines = ["solution status: optimal solution found", "objective value: 1"]
        lines += [f"{name} 1 \t(obj:0)" for name in sorted(ones)]
    solution = tmp_path / "p.sol"
    solution.write_text("\n".join(lines) + "\n")
    result = _run("decode", model, solution, "--json")
    assert result.exit_code == 0, result.output
    payload = checked(result.stdout)
    assert payload["alteration"] == {"o1": "o2", "o2": "o1"}
    assert payload["value"] == pytest.approx(1.0, abs=1e-12) and payload["cost"] == 4
    assert payload["within_budget"] is True and payload["claimed"] == 1


def test_over_budget_is_not_verified(tmp_path):
    """Decoded against the problem file itself (the model built again) at budget 1: the
    cost-4 alteration is over budget, exit 1; a wrong claimed objective is a warning."""
    built = tmp_path / "p.lp"
    _run("export-milp", TINY, "-o", built, "--formulation", "paper", "--budget", "4")
    mapping = json.loads((tmp_path / "p.columns.json").read_text())
    solution = tmp_path / "p.sol"
    solution.write_text(
        "Objective 0.9\n" + "".join(f"{c} 1\n" for c in _columns(mapping, {"o1": "o2", "o2": "o1"}))
    )
    result = _run("decode", TINY, solution, "--formulation", "paper", "--budget", "1", "--json")
    assert result.exit_code == 1
    payload = checked(result.stdout)
    assert payload["within_budget"] is False and payload["value"] == pytest.approx(1.0)
    assert any("0.9" in text for text in payload["warnings"])


def test_two_targets_for_one_observation_is_refused(tmp_path):
    model = tmp_path / "p.lp"
    _run("export-milp", TINY, "-o", model, "--formulation", "paper", "--budget", "4")
    mapping = json.loads((tmp_path / "p.columns.json").read_text())
    both = _columns(mapping, {"o2": "o1"}) + _columns(mapping, {"o2": "g"})
    solution = tmp_path / "p.sol"
    solution.write_text("".join(f"{c} 1\n" for c in both))
    result = _run("decode", model, solution)
    assert result.exit_code == 2
    assert "both" in result.stderr and str(solution) in result.stderr


def test_a_model_without_its_map_is_a_clear_error(tmp_path):
    model = tmp_path / "m.mps"
    _run("export-milp", TINY, "-o", model)
    (tmp_path / "m.columns.json").unlink()
    solution = tmp_path / "m.sol"
    solution.write_text("c0 1\n")
    result = _run("decode", model, solution)
    assert result.exit_code == 2 and "column map" in result.stderr


def test_highs_dual_values_are_not_read(tmp_path):
    path = tmp_path / "h.sol"
    path.write_text(
        "Model status\nOptimal\n\n# Primal solution values\nFeasible\nObjective 0.5\n"
        "# Columns 2\nc0 1\nc1 0\n# Rows 1\nr0 1\n\n# Dual solution values\nFeasible\n"
        "# Columns 2\nc0 7\nc1 9\n"
    )
    solution = read_solution(path)
    assert solution.values == {"c0": 1.0, "c1": 0.0, "r0": 1.0}
    assert solution.objective == 0.5


# -- export-chain -------------------------------------------------------------------------------


def test_chain_for_storm_has_evaluates_value(tmp_path):
    stormpy = pytest.importorskip("stormpy")
    chain = tmp_path / "c.drn"
    result = _run("export-chain", TINY, "--alter", "o2=o1", "-o", chain, "--json")
    assert result.exit_code == 0, result.output
    payload = checked(result.stdout)
    assert payload["value"] == pytest.approx(0.6, abs=1e-12)  # by hand
    model = stormpy.build_model_from_drn(str(chain))
    formula = stormpy.parse_properties('P=? [F "decoy"]')
    storm = stormpy.model_checking(model, formula[0]).get_value(model.initial_states[0])
    assert storm == pytest.approx(0.6, abs=1e-9)


def test_paper_grid_chain_for_storm(tmp_path):
    """The paper grid under the alteration o1 -> o2, o2 -> o1 (expected: evaluate's value of
    it, a different route: no file, no Storm)."""
    stormpy = pytest.importorskip("stormpy")
    problem = paper_grid(5, budget=2)
    source = tmp_path / "grid.yaml"
    write_problem(problem, source)
    alteration = {"o1": "o2", "o2": "o1"}
    chain = tmp_path / "g.drn"
    args = ["export-chain", source, "-o", chain]
    for o, t in alteration.items():
        args += ["--alter", f"{o}={t}"]
    result = _run(*args)
    assert result.exit_code == 0, result.output
    expected = evaluate(problem, problem.alteration(alteration)).probability
    model = stormpy.build_model_from_drn(str(chain))
    formula = stormpy.parse_properties('P=? [F "decoy"]')
    storm = stormpy.model_checking(model, formula[0]).get_value(model.initial_states[0])
    assert storm == pytest.approx(expected, abs=1e-9)


def test_prism_explicit_chain_solved_independently(tmp_path):
    """The .tra/.lab pair read here by hand and solved with scipy: x = P x on the states that
    are not decoys, 1 on decoys, from the state labelled init."""
    tra = tmp_path / "c.tra"
    result = _run("export-chain", TINY, "--alter", "o2=o1", "-o", tra)
    assert result.exit_code == 0, result.output
    rows = tra.read_text().split("\n")
    n, nnz = map(int, rows[0].split())
    entries = np.array([row.split() for row in rows[1 : 1 + nnz]], dtype=float)
    matrix = sp.csr_matrix((entries[:, 2], (entries[:, 0], entries[:, 1])), shape=(n, n))
    lab = (tmp_path / "c.lab").read_text().split("\n")
    names = dict(item.split("=") for item in lab[0].split())
    index = {name.strip('"'): int(k) for k, name in names.items()}
    members: dict[int, set[int]] = {}
    for line in filter(None, lab[1:]):
        state, labels = line.split(":")
        members[int(state)] = {int(k) for k in labels.split()}
    decoy = np.array([index["decoy"] in members.get(q, set()) for q in range(n)])
    init = next(q for q in range(n) if index["init"] in members.get(q, set()))
    # states that never reach a decoy: 0; solve (I - P) x = P·decoy on the rest
    reach = decoy.copy()
    for _ in range(n):
        reach |= (matrix @ reach.astype(float)) > 0
    rest = np.flatnonzero(reach & ~decoy)
    a = sp.identity(rest.size) - matrix[rest][:, rest]
    b = matrix[rest][:, np.flatnonzero(decoy)].sum(axis=1).A1
    x = np.zeros(n)
    x[decoy] = 1.0
    x[rest] = spla.spsolve(a.tocsc(), b)
    assert x[init] == pytest.approx(0.6, abs=1e-12)
    problem = load_problem(TINY)
    assert x[init] == pytest.approx(evaluate(problem, problem.alteration({"o2": "o1"})).probability)


def test_export_chain_refuses_other_suffixes(tmp_path):
    result = _run("export-chain", TINY, "-o", tmp_path / "c.txt")
    assert result.exit_code == 2 and "-o" in result.stderr


def test_exported_model_of_tiny_values_is_scaled_and_decodes(tmp_path):
    """A decoy behind a branch of 1e-12: o1 -> o0 makes s1 play a, worth 1e-12 x 0.8 = 8e-13
    (by hand) against 2e-13. The model is written scaled as the solve scales it (unscaled,
    its Bellman coefficients of 1e-12 x 1000 were at HiGHS' drop threshold and HiGHS solved
    another model): HiGHS' solution of the file decodes to o1 -> o0, and the map's
    value_unit turns the file's objective back into the value."""
    highspy = pytest.importorskip("highspy")
    problem = tmp_path / "p.yaml"
    problem.write_text(scale_model_text(p=1e-12))
    model = tmp_path / "p.mps"
    result = _run("export-milp", problem, "-o", model)
    assert result.exit_code == 0, result.output
    mapping = json.loads((tmp_path / "p.columns.json").read_text())
    unit = mapping["value_unit"]
    assert 2.0**-45 <= unit <= 2.0**-35  # a power of two about the 8e-13 optimum
    assert np.log2(unit) == int(np.log2(unit))
    solver = highspy.Highs()
    solver.setOptionValue("output_flag", False)
    solver.readModel(str(model))
    solver.run()
    objective = solver.getInfo().objective_function_value
    assert (objective + mapping["objective_offset"]) * unit == pytest.approx(8e-13, rel=1e-6)
    solution = tmp_path / "p.sol"
    solver.writeSolution(str(solution), 0)
    result = _run("decode", model, solution, "--json")
    assert result.exit_code == 0, result.output
    payload = checked(result.stdout)
    assert payload["alteration"] == {"o1": "o0"}
    assert payload["value"] == pytest.approx(8e-13, rel=1e-12)


@pytest.mark.parametrize(
    ("change", "field"),
    [
        (lambda m: m["alteration_columns"].__setitem__(0, 7), "alteration_columns[0]"),
        (lambda m: m["alteration_columns"][0].pop("column"), "column"),
        (lambda m: m.__setitem__("budget", "lots"), "budget"),
        (lambda m: m.__setitem__("budget", -1.0), "budget"),
        (lambda m: m.__setitem__("alteration_columns", {"c0": 1}), "alteration_columns"),
        (lambda m: m["alteration_columns"][0].__setitem__("target", 3), "target"),
    ],
)
def test_a_malformed_column_map_is_one_line_naming_its_field(tmp_path, change, field):
    """Issue 51, item 7: integer entries, a missing column, a budget of "lots" or -1, a
    mapping for the list: exit 2, the map's file and the field named (internal TypeError,
    KeyError or ValueError before; the negative budget was accepted)."""
    model = tmp_path / "p.lp"
    _run("export-milp", TINY, "-o", model, "--formulation", "paper", "--budget", "4")
    path = tmp_path / "p.columns.json"
    mapping = json.loads(path.read_text())
    change(mapping)
    path.write_text(json.dumps(mapping))
    solution = tmp_path / "p.sol"
    solution.write_text("c0 1\n")
    result = _run("decode", model, solution)
    assert result.exit_code == 2, result.output
    assert str(path) in result.stderr and field in result.stderr
    assert "internal error" not in result.stderr and len(result.stderr.strip().splitlines()) == 1


def test_export_milp_writes_both_files_or_neither(tmp_path, monkeypatch):
    """Issue 51 (questionable, decided): the model was replaced and then its column map
    failed to be written, a mismatched pair. Now a map that cannot be written leaves the
    earlier pair as it was, and no staged file behind."""
    from misdirect.errors import WriteError

    model = tmp_path / "m.mps"
    assert _run("export-milp", TINY, "-o", model, "--budget", "1").exit_code == 0
    before = model.read_bytes(), (tmp_path / "m.columns.json").read_text()

    import misdirect.cli.models as models

    def full_disk(path, *args, **kwargs):
        raise WriteError(f"cannot write {path}: No space left on device")

    monkeypatch.setattr(models, "write_output", full_disk)
    result = _run("export-milp", TINY, "-o", model, "--budget", "2")
    assert result.exit_code != 0
    assert (model.read_bytes(), (tmp_path / "m.columns.json").read_text()) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.columns.json", "m.mps"]


def test_a_solution_claiming_nan_decodes_to_strict_json(tmp_path):
    """Issue 51, item 8: a solution file whose objective reads "nan" made `decode --json`
    write a bare NaN; JSON has none: the claim is null."""
    model = tmp_path / "p.lp"
    _run("export-milp", TINY, "-o", model, "--formulation", "paper", "--budget", "4")
    solution = tmp_path / "p.sol"
    solution.write_text("# Objective value = nan\nc0 0\n")
    result = _run("decode", model, solution, "--json")

    def refuse(constant):
        raise AssertionError(f"not JSON: {constant}")

    payload = json.loads(result.stdout, parse_constant=refuse)
    assert payload["claimed"] is None
