"""`convert --to drn|prism` plus `export-fsc` of one explicit problem, read back through Storm
({drn:} or {prism:}) with the controller from PAYNT's JSON ({paynt:}), gives the same values.

The expected values of tiny.yaml are the hand calculation in its description; the paper grid's
are the original problem's, evaluated on its own model (a different route: no Storm, no PAYNT
reader)."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml
from typer.testing import CliRunner

from misdirect import evaluate, load_problem, solve
from misdirect.cli import app
from misdirect.errors import ProblemError
from misdirect.io.problem_file import problem_to_document, write_problem
from misdirect.scenarios import paper_grid, random_problem

pytest.importorskip("stormpy")
EXAMPLES = Path(__file__).parents[1] / "examples"
runner = CliRunner()


def _export(tmp_path: Path, source: Path, target: str) -> Path:
    """The problem file that reads ``source``'s exports back."""
    model, fsc = tmp_path / f"world.{target}", tmp_path / "robot.fsc.json"
    for args in (
        ["convert", str(source), "--to", target, "-o", str(model)],
        ["export-fsc", str(source), "-o", str(fsc)],
    ):
        result = runner.invoke(app, args)
        assert result.exit_code == 0, result.output
    deception = problem_to_document(load_problem(source))["deception"]
    deception["decoy"] = {"label": "decoy"}
    document = {
        "format": "misdirect/v1",
        "pomdp": {target: model.name},
        "controller": {"paynt": fsc.name},
        "deception": deception,
    }
    path = tmp_path / "back.yaml"
    path.write_text(yaml.safe_dump(document, sort_keys=False))
    return path


@pytest.mark.parametrize("target", ["drn", "prism"])
def test_tiny_round_trip_by_hand(tmp_path, target):
    back = load_problem(_export(tmp_path, EXAMPLES / "tiny.yaml", target))
    assert evaluate(back).probability == pytest.approx(0.2, abs=1e-12)
    assert evaluate(back, back.alteration({"o2": "o1"})).probability == pytest.approx(0.6)
    result = solve(back, budgets=[0, 1, 4])
    assert [point.probability for point in result.curve] == pytest.approx(
        [0.2, 0.6, 1.0], abs=1e-12
    )


@pytest.mark.parametrize(
    "problem",
    [paper_grid(5, budget=2), random_problem(3, states=7, observations=4, nodes=2)],
    ids=["paper-grid", "random"],
)
def test_round_trip_keeps_names_and_values(tmp_path, problem):
    source = tmp_path / "source.yaml"
    write_problem(problem, source)
    original = load_problem(source)
    back = load_problem(_export(tmp_path, source, "drn"))
    assert back.pomdp.states == original.pomdp.states
    assert set(back.pomdp.observations) == set(original.pomdp.observations)
    budgets = [0, 1, 2]
    want = solve(original, budgets=budgets, method="exhaustive")
    got = solve(back, budgets=budgets, method="exhaustive")
    for a, b in zip(want.curve, got.curve, strict=True):
        assert b.probability == pytest.approx(a.probability, abs=1e-12)
        # the same alteration, by name, has the same value in both
        assert evaluate(back, back.alteration(a.alteration)).probability == pytest.approx(
            a.probability, abs=1e-12
        )


def test_drn_without_names_says_why_not_constants(tmp_path):
    """A DRN file without misdirect's names header (Storm's own export, or an older misdirect)
    numbers its observations; a controller naming them must not get a hint about PAYNT's
    constants, which a DRN file has none of."""
    path = _export(tmp_path, EXAMPLES / "tiny.yaml", "drn")
    drn = tmp_path / "world.drn"
    drn.write_text(
        "".join(
            line
            for line in drn.read_text().splitlines(keepends=True)
            if "misdirect-names" not in line
        )
    )
    with pytest.raises(ProblemError) as caught:
        load_problem(path)
    assert "constants" not in caught.value.reason
    assert "DRN" in caught.value.reason and "'o0'" in caught.value.reason
