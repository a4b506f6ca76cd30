"""Enumeration with low-rank (Woodbury) updates agrees with plain enumeration everywhere it
applies, and refuses models that can cycle without reaching the decoy."""

from pathlib import Path

import numpy as np
import pytest

from misdirect import load_problem, solve
from misdirect.scenarios import paper_grid, random_problem
from misdirect.solvers.incremental import IncrementalSolver, NotApplicableError

EXAMPLES = Path(__file__).parent.parent / "examples"


@pytest.mark.parametrize("n", [5, 7, 9, 15])
def test_grid_curve_equals_exhaustive(n):
    budgets = list(range(8))
    mine = solve(paper_grid(n), method="incremental", budgets=budgets)
    oracle = solve(paper_grid(n), method="exhaustive", budgets=budgets)
    assert not mine.warnings
    for a, b in zip(mine.curve, oracle.curve, strict=True):
        assert a.probability == pytest.approx(b.probability, abs=1e-9)
        assert a.solver_probability == pytest.approx(a.probability, abs=1e-9)
        assert a.cost <= a.budget


def test_random_models_equal_exhaustive():
    applicable = 0
    for seed in range(200):
        rng = np.random.default_rng(50_000 + seed)
        problem = random_problem(
            seed + 1000,
            states=int(rng.integers(3, 9)),
            actions=int(rng.integers(1, 4)),
            observations=int(rng.integers(2, 5)),
            nodes=int(rng.integers(1, 4)),
        )
        budgets = [0.0, 1.0, 2.5, 4.0]
        try:
            mine = solve(problem, method="incremental", budgets=budgets)
        except NotApplicableError:
            continue
        applicable += 1
        oracle = solve(problem, method="exhaustive", budgets=budgets)
        for a, b in zip(mine.curve, oracle.curve, strict=True):
            assert a.probability == pytest.approx(b.probability, abs=1e-9), (seed, a.budget)
            # the updated value it claimed is the exact value of what it returned
            assert a.solver_probability == pytest.approx(a.probability, abs=1e-9), seed
    assert applicable >= 40


def test_models_that_can_cycle_are_refused_and_auto_falls_back():
    trap = load_problem(EXAMPLES / "trap.yaml")
    with pytest.raises(NotApplicableError):
        IncrementalSolver().solve(trap, [1.0])
    result = solve(trap, budgets=[0, 1])
    assert result.certified_by == "exhaustive"
    assert "no low-rank updates" in result.stats["auto_reason"]
    assert [p.probability for p in result.curve] == pytest.approx([0.1, 0.4], abs=1e-12)


def test_auto_uses_updates_on_the_grid():
    result = solve(paper_grid(25), budgets=range(8))
    assert result.certified_by == "incremental"
    assert result.stats["factorisations"] == 3  # one per choice for the blank reading


def test_both_ways_of_batching_the_corrections_agree(monkeypatch):
    """Padded full-size systems and per-pattern systems are the same algebra."""
    import misdirect.solvers.incremental as incremental

    problems = [paper_grid(7), paper_grid(9)] + [
        random_problem(seed, states=8) for seed in range(20)
    ]
    padded = []
    for problem in problems:
        try:
            padded.append(solve(problem, method="incremental", budgets=[0, 1, 2, 3]))
        except NotApplicableError:
            padded.append(None)
    monkeypatch.setattr(incremental, "PADDED_ROWS", 0)
    for problem, before in zip(problems, padded, strict=True):
        if before is None:
            continue
        after = solve(problem, method="incremental", budgets=[0, 1, 2, 3])
        for a, b in zip(after.curve, before.curve, strict=True):
            assert a.solver_probability == pytest.approx(b.solver_probability, abs=1e-12)
