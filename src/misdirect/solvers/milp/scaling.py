"""Per-state scales of the MILP's value columns, so that a backend sees values near 1.

A decoy behind a branch of 1e-10 gives the states before it values of 1e-10: below HiGHS's
absolute feasibility tolerance (1e-7), with Bellman coefficients below the size under which it
drops a matrix entry (1e-9). HiGHS then read the value as 0 and proved a bound of 0. Dividing the
objective by its scale (:func:`misdirect.solvers.milp.solver._scaled`) does not help: the
columns themselves stay at 1e-10.

So each value column ``z_q`` becomes ``y_q = z_q / u_q``, with ``u_q`` a power of two at least the
largest value ``q`` has under any alteration; ``y_q`` lies in ``[0, 1]`` and every big-M that was
1 (the bound of ``z_q``) becomes ``u_q``. Divided by ``u_q`` (exact: a power of two), the rows
read as they did, with Bellman coefficients ``P(q, q') u_q' / u_q``: at most 1, as ``u_q``
bounds ``P(q, q') u_q'`` (below). A state whose bound is near 1 (at least :data:`NEAR_ONE`)
keeps ``u_q = 1``, so a model of normal scale goes to the backend exactly as it was built.

The bound must be proven, or the MILP would cut off the optimum: ``u`` is a super-solution of
the Bellman operator over every choice of the choice product (``u_q ≥ max_g b_g + P_g u``
wherever ``u_q < 1``), hence at least its least fixed point, the largest value. The per-state
relaxation's values (policy iteration, exact only up to its tolerances) are only the start;
:func:`value_scales` raises the bound where the check fails, and gives up (all 1) if it does
not settle.
"""

from __future__ import annotations

from typing import cast

import numpy as np

from misdirect.core.choice_product import ChoiceProduct

NEAR_ONE = 2.0**-10
"""A bound at least this is 1: the column and its rows stay as built."""

FLOOR = 2.0**-1000
"""No bound below this (so ``1 / u`` stays finite)."""

MARGIN = 2.0**-30
"""How much (relative) a float ``b + P u`` may lie below its exact value: its rounding."""

ROUNDS = 64
"""Raises of the bounds tried before giving up on scaling (bounds of 1 are always valid)."""


def value_scales(
    chain: ChoiceProduct, live: np.ndarray, start: np.ndarray | None, top: float
) -> np.ndarray:
    """``u`` per state of ``chain``: a power of two at least the largest value (divided by the
    objective's largest value ``top``) of every ``live`` state, 1 where that is near 1; 1 on
    every other state, and everywhere when ``start`` (values of the states, in the objective's
    units, e.g. the per-state relaxation's) is None or the bounds cannot be proven."""
    ones = np.ones(chain.n_states)
    if start is None or start.shape != (chain.n_states,) or not live.any() or not top > 0:
        return ones
    scales = ones.copy()
    scales[live] = _power_at_or_above(2.0 * np.abs(start[live]) / top)
    scales[scales >= NEAR_ONE] = 1.0
    if np.all(scales == 1.0):
        return ones
    reward = chain.one_step() / top  # the decoys' part of every choice, in units of ``top``
    for _ in range(ROUNDS):
        inside = np.where(live, scales, 0.0)  # a state that cannot reach the decoy: 0
        best = np.zeros(chain.n_states)
        np.maximum.at(best, chain.group_state, reward + chain.transitions @ inside)
        best *= 1.0 + MARGIN
        short = live & (scales < 1.0) & (best > scales)
        if not short.any():
            return scales
        scales[short] = _power_at_or_above(2.0 * best[short])
        scales[scales >= NEAR_ONE] = 1.0
    return ones


def _power_at_or_above(x: np.ndarray) -> np.ndarray:
    """The least power of two at or above each of ``x``, within ``[FLOOR, 1]``."""
    mantissa, exponent = np.frexp(np.clip(x, FLOOR, 1.0))  # x = mantissa 2^exponent
    return cast(np.ndarray, np.ldexp(1.0, exponent - (mantissa == 0.5)))
