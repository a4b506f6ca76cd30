"""The tolerance policy: every comparison of costs, values and bounds in misdirect reads it here.

An exactness tool hides its soundness bugs in tolerances, so there is one place that says how
close is close enough, and why. Every solver, engine and report compares through these names;
none writes a literal. The decision "is this answer optimal?" built on them lives in
:mod:`misdirect.solvers.certification`.
"""

from __future__ import annotations

import numpy as np

BUDGET_SLACK = 1e-9
"""A cost within this of a budget fits it: costs are sums of decimal inputs (0.1 + 0.2)."""

CERTIFY = 1e-9
""""Optimal" means a proven upper bound within this of the exact value of the answer."""

PRUNE = CERTIFY
"""A subtree whose bound is this close to the incumbent cannot beat it by more than a tie."""

NEAR_TIE = CERTIFY
"""Values of low-rank updates this close count as equal: within the updates' rounding error."""

STOCHASTIC = 1e-9
"""A distribution (a model's row, a controller's move) sums to 1 within this."""

TIE = 1e-12
"""Two exact values (or two costs) this close are the same number up to rounding."""

IMPROVE = 1e-12
"""Policy iteration switches a choice only on a gain larger than this (else it may cycle)."""

MISMATCH = 1e-6
"""A solver's claim this far from the exact value of its alteration contradicts the chain."""

GAP = CERTIFY
"""A MILP backend's bound this close to its incumbent proves it (relative above 1)."""

FEASIBILITY = 1e-9
"""A MILP point further than this from feasible gets its claim recomputed with rounded binaries."""


def affordable(cost: float | np.ndarray, budget: float) -> bool | np.ndarray:
    """Whether ``cost`` fits ``budget`` (element-wise on arrays), within :data:`BUDGET_SLACK`."""
    return cost <= budget + BUDGET_SLACK


def proven(value: float, bound: float | None) -> bool:
    """Whether ``bound`` (a proven upper bound) certifies ``value`` as the optimum."""
    return bound is not None and bound - value <= CERTIFY + TIE
