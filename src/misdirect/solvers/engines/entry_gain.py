"""The first-entry gain bound: how much altering more sensors can add to a base chain's value.

A run that never enters the region of an altered sensor behaves as it would without that
alteration. So for a base chain ``b`` and a set ``R`` of regions whose rows change on top of it,

    V(b + R) <= V(b) + sum over s in R of g_s,
    g_s = sum over x in s of E_b[entries into s at x] (M - V_b(x))
          + M P_b(absorbed in a closed class that meets s),

with ``M`` the largest decoy weight: the value can change only from the first entry into a
region of ``R`` on, and from there it is at most ``M``. An enumeration that knows a value some
alteration reaches need not value those whose bound is below it (the share left is measured by
``bench/entry_gain.py``: about one in eight on the drones among patrolling agents).

Everything here is proven, as the values are (docs/exactness.md): ``V_b`` from below and the
expected entries from above, from residuals bounded in exact arithmetic
(:func:`misdirect.core.residual.residual`) and a proven bound on the expected steps. A base
chain too ill-conditioned for doubles gets loose gains, never wrong ones.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from misdirect.core import residual
from misdirect.core.reachability import factorise, steps_bound

UNIT_ROUNDOFF = residual.UNIT_ROUNDOFF


@dataclass(frozen=True)
class EntryGains:
    """A base chain's proven value (from above) and each region's proven gain (``inf`` where
    nothing could be proven)."""

    value: float
    gains: np.ndarray  # (regions,)

    def bounds(self, owner: np.ndarray, region: np.ndarray, count: int) -> np.ndarray:
        """Upper bounds on the value of ``count`` alterations, each altering the regions
        listed for it (``region[e]`` for the entries ``e`` with ``owner[e]`` its index) on top
        of the base."""
        added = np.bincount(owner, weights=self.gains[region], minlength=count).astype(float)
        # a sum of nonnegative terms: its rounding is relative, at most (terms + 1) u
        most = int(np.bincount(owner, minlength=count).max(initial=0))
        total = self.value + added * (1 + 2.02 * (most + 2) * UNIT_ROUNDOFF)
        return total * (1 + 4 * UNIT_ROUNDOFF)


def entry_gains(
    transitions: sp.csr_matrix,
    target: np.ndarray,
    target_value: np.ndarray,
    initial: int,
    region: np.ndarray,
    n_regions: int,
    top: float,
) -> EntryGains:
    """:class:`EntryGains` of the chain ``transitions`` (a stochastic matrix over its states;
    the ``target`` states end a run with their ``target_value``) from ``initial``, for the
    regions ``region[x]`` (-1: a state in none; a target state's row never matters); ``top``
    is the most a run can score (the largest decoy weight, whether or not this chain reaches
    a decoy)."""
    n = transitions.shape[0]
    given = sp.csr_matrix(transitions)
    stops = np.flatnonzero(target)
    matrix = sp.csr_matrix(sp.diags((~target).astype(np.float64)) @ given)  # targets end runs
    matrix.eliminate_zeros()
    _, component = connected_components(matrix, directed=True, connection="strong")
    edges = matrix.tocoo()
    leaving = component[edges.row] != component[edges.col]
    open_class = np.zeros(int(component.max(initial=-1)) + 1, dtype=bool)
    open_class[component[edges.row[leaving]]] = True
    closed = ~open_class[component]  # the targets too: nothing leaves them
    closed[stops] = True
    region = np.where(target, -1, region)
    nothing = EntryGains(0.0, np.zeros(n_regions))
    if closed[initial]:  # the run never moves on: only its own class may change
        if target[initial]:
            return EntryGains(float(target_value[initial]), np.zeros(n_regions))
        gains = np.zeros(n_regions)
        met = np.unique(region[(component == component[initial]) & (region >= 0)])
        gains[met] = top
        return EntryGains(0.0, gains) if met.size else nothing
    transient = np.flatnonzero(~closed)
    position = np.searchsorted(transient, initial)
    rows = matrix[transient]
    inner = sp.csr_matrix(rows[:, transient])
    reward = np.asarray(rows[:, stops] @ target_value[stops]).ravel()
    lu = factorise(inner)
    values = lu.solve(reward)
    start = np.zeros(transient.size)
    start[position] = 1.0
    visits = lu.solve(start, trans="T")
    steps = steps_bound(inner, lu.solve(np.ones(transient.size)))
    own = np.arange(transient.size)
    _, value_residual = residual.residual(inner, values, np.zeros_like(values), own, reward)
    transposed = sp.csr_matrix(inner.T)
    _, visit_residual = residual.residual(transposed, visits, np.zeros_like(visits), own, start)
    # errors (I - Q)^-1 r: forward at most max|r| steps; transposed at most sum|r| steps
    # per state (visits to x from anywhere are at most those from x, at most its steps)
    value_error = float(value_residual.max(initial=0.0)) * steps * (1 + 1e-9)
    visit_error = float(visit_residual.sum()) * steps * (1 + 1e-9)
    if not (np.isfinite(value_error) and np.isfinite(visit_error)):
        return EntryGains(top, np.full(n_regions, np.inf))
    value_up = min(float(values[position]) + value_error, top)
    low = np.zeros(n)
    low[transient] = np.clip(values - value_error, 0.0, top)
    visits_up = np.zeros(n)
    visits_up[transient] = np.maximum(visits, 0.0) + visit_error
    # entries: moves y -> x from outside x's region, each weighted by the visits to y
    flow = (sp.diags(visits_up) @ given).tocoo()
    moving = ~closed[flow.row]
    entry = moving & (region[flow.row] != region[flow.col]) & (region[flow.col] >= 0)
    into = entry & ~closed[flow.col]
    gains = np.bincount(  # (float: numpy counts in integers when nothing is counted)
        region[flow.col[into]],
        weights=flow.data[into] * (top - low[flow.col[into]]),
        minlength=n_regions,
    ).astype(np.float64)
    # a closed class of no value that meets a region: all the mass it takes may gain M
    trapped_in = moving & closed[flow.col] & ~target[flow.col]
    absorbed = np.bincount(
        component[flow.col[trapped_in]],
        weights=flow.data[trapped_in],
        minlength=open_class.size,
    ).astype(np.float64)
    met = (closed & ~target) & (region >= 0)
    if met.any():
        pairs = np.unique(np.stack([component[met], region[met]], axis=1), axis=0)
        np.add.at(gains, pairs[:, 1], absorbed[pairs[:, 0]] * top)
    # the sums above round by at most (terms + 2) u, relative: the largest row counts
    terms = int(np.diff(given.indptr).max(initial=0)) * n + 2
    return EntryGains(value_up, gains * (1 + 2.02 * terms * UNIT_ROUNDOFF))
