"""The evaluator against Storm, which builds the product chain itself from a PRISM encoding."""

import numpy as np
import pytest

from misdirect.core.evaluate import decoy_probability
from misdirect.scenarios import paper_grid, random_problem
from prism_product import random_allowed_alteration, storm_probability

stormpy = pytest.importorskip("stormpy")


def test_random_chains_agree_with_storm(tmp_path):
    rng = np.random.default_rng(2024)
    checked, nontrivial = 0, 0
    for seed in range(60):
        problem = random_problem(
            seed, states=int(rng.integers(3, 9)), nodes=int(rng.integers(1, 4))
        )
        alpha = random_allowed_alteration(problem, rng)
        ours = decoy_probability(problem, alpha)
        theirs = storm_probability(tmp_path, problem, alpha)
        assert ours == pytest.approx(theirs, abs=1e-9), f"seed {seed}"
        checked += 1
        nontrivial += 1e-6 < ours < 1 - 1e-6
    assert checked >= 50
    assert nontrivial >= 15  # the comparison is not only on 0/1 answers


@pytest.mark.parametrize("changes", [{}, {"o1": "o3"}, {"o1": "o5", "o2": "o0", "o6": "o2"}])
def test_paper_grid_agrees_with_storm(tmp_path, changes):
    problem = paper_grid(9)
    alpha = problem.alteration(changes)
    assert decoy_probability(problem, alpha) == pytest.approx(
        storm_probability(tmp_path, problem, alpha), abs=1e-9
    )
