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

:func:`entry_gains` counts every entry (one solve of the base chain);
:func:`first_entry_gains` counts each region's first entry only, which is tighter where runs
circle back and costs one factorisation per region. :func:`floor_filter` drops, from an
enumeration's block, the alterations whose bound cannot reach a value already reached.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components
from scipy.sparse.linalg import SuperLU

from misdirect.core import residual, tolerance
from misdirect.core.alterations import AlteredEntries
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

    def also_altering(self, regions: np.ndarray) -> EntryGains:
        """The bound for alterations that alter ``regions`` too: the same gains on a value
        raised by theirs (a search's root gains serve a block whose base altered them)."""
        raised = self.bounds(np.zeros(regions.size, dtype=np.int64), regions, 1)[0]
        return EntryGains(float(raised), self.gains)


GainsOf = Callable[
    [sp.csr_matrix, np.ndarray, np.ndarray, int, np.ndarray, int, float], EntryGains
]  # entry_gains or first_entry_gains


class _Classes(NamedTuple):
    """A chain's strongly connected components, and which states lie in closed ones."""

    matrix: sp.csr_matrix  # the chain with the targets' rows emptied (they end runs)
    component: np.ndarray  # per state
    open_class: np.ndarray  # per component: whether a run can leave it
    closed: np.ndarray  # per state: in a closed class (the targets too)
    region: np.ndarray  # per state, its region (-1 for none and for the targets)
    traps: np.ndarray  # (closed class of no value, region it meets) pairs, distinct


class _Solved(NamedTuple):
    """The base chain solved on its transient states, with proven error bounds."""

    transient: np.ndarray  # the states in no closed class, ascending
    rows: sp.csr_matrix  # their rows (all columns)
    inner: sp.csr_matrix  # their rows among themselves
    values: np.ndarray  # per transient state, its value (rounded)
    value_error: float  # a proven bound on every value's error
    steps: float  # a proven bound on the expected steps before a run leaves them
    lu: SuperLU  # the factorisation of I - inner


def _classes(given: sp.csr_matrix, target: np.ndarray, region: np.ndarray) -> _Classes:
    matrix = sp.csr_matrix(sp.diags((~target).astype(np.float64)) @ given)  # targets end runs
    matrix.eliminate_zeros()
    _, component = connected_components(matrix, directed=True, connection="strong")
    edges = matrix.tocoo()
    leaving = component[edges.row] != component[edges.col]
    open_class = np.zeros(int(component.max(initial=-1)) + 1, dtype=bool)
    open_class[component[edges.row[leaving]]] = True
    closed = ~open_class[component]  # the targets too: nothing leaves them
    closed[np.flatnonzero(target)] = True
    region = np.where(target, -1, region)
    met = (closed & ~target) & (region >= 0)
    traps = np.unique(np.stack([component[met], region[met]], axis=1), axis=0)
    return _Classes(matrix, component, open_class, closed, region, traps)


def _solved(classes: _Classes, target: np.ndarray, target_value: np.ndarray) -> _Solved:
    """Values of the transient states, errors bounded from residuals computed exactly
    (:mod:`misdirect.core.residual`) and a proven bound on the expected steps."""
    stops = np.flatnonzero(target)
    transient = np.flatnonzero(~classes.closed)
    rows = classes.matrix[transient]
    inner = sp.csr_matrix(rows[:, transient])
    reward = np.asarray(rows[:, stops] @ target_value[stops]).ravel()
    lu = factorise(inner)
    values = lu.solve(reward)
    steps = steps_bound(inner, lu.solve(np.ones(transient.size)))
    own = np.arange(transient.size)
    _, value_residual = residual.residual(inner, values, np.zeros_like(values), own, reward)
    # errors (I - Q)^-1 r: at most max|r| times the steps
    value_error = float(value_residual.max(initial=0.0)) * steps * (1 + tolerance.BOUND_MARGIN)
    return _Solved(transient, rows, inner, values, value_error, steps, lu)


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
    return _entry_gains(
        sp.csr_matrix(transitions), target, target_value, initial, region, n_regions, top
    )[0]


def _entry_gains(
    given: sp.csr_matrix,
    target: np.ndarray,
    target_value: np.ndarray,
    initial: int,
    region: np.ndarray,
    n_regions: int,
    top: float,
) -> tuple[EntryGains, _Classes | None, _Solved | None]:
    """:func:`entry_gains`, with the classes and the solve it built (None where it needed
    none)."""
    n = given.shape[0]
    classes = _classes(given, target, region)
    component, open_class, closed = classes.component, classes.open_class, classes.closed
    region = classes.region
    nothing = EntryGains(0.0, np.zeros(n_regions))
    if closed[initial]:  # the run never moves on: only its own class may change
        if target[initial]:
            return EntryGains(float(target_value[initial]), np.zeros(n_regions)), None, None
        gains = np.zeros(n_regions)
        met = np.unique(region[(component == component[initial]) & (region >= 0)])
        gains[met] = top
        return (EntryGains(0.0, gains) if met.size else nothing), None, None
    solved = _solved(classes, target, target_value)
    transient, inner, values, lu = solved.transient, solved.inner, solved.values, solved.lu
    position = np.searchsorted(transient, initial)
    start = np.zeros(transient.size)
    start[position] = 1.0
    visits = lu.solve(start, trans="T")
    own = np.arange(transient.size)
    transposed = sp.csr_matrix(inner.T)
    _, visit_residual = residual.residual(transposed, visits, np.zeros_like(visits), own, start)
    # transposed: at most sum|r| steps per state (visits to x from anywhere are at most
    # those from x, at most its steps)
    value_error = solved.value_error
    visit_error = float(visit_residual.sum()) * solved.steps * (1 + tolerance.BOUND_MARGIN)
    if not (np.isfinite(value_error) and np.isfinite(visit_error)):
        return EntryGains(top, np.full(n_regions, np.inf)), classes, None
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
    pairs = classes.traps
    if pairs.size:
        np.add.at(gains, pairs[:, 1], absorbed[pairs[:, 0]] * top)
    # the sums above round by at most (terms + 2) u, relative: the largest row counts
    terms = int(np.diff(given.indptr).max(initial=0)) * n + 2
    result = EntryGains(value_up, gains * (1 + 2.02 * terms * UNIT_ROUNDOFF))
    return result, classes, solved


def first_entry_gains(
    transitions: sp.csr_matrix,
    target: np.ndarray,
    target_value: np.ndarray,
    initial: int,
    region: np.ndarray,
    n_regions: int,
    top: float,
    stop: Callable[[], bool] | None = None,
) -> EntryGains:
    """:class:`EntryGains` as :func:`entry_gains` computes them, each region's gain taken on
    its *first* entry only where that is smaller: ``g_s = E_b[M - V_b(x) at the first entry
    x into s]``, plus ``M`` times the mass absorbed, before that, in a closed class that
    meets ``s``. Where runs circle back through a region, counting every entry counts them
    again and again (on a turn-back grid the largest gain falls from 0.77 to 0.30,
    ``bench/entry_gain.py``). The price is one factorisation per region (its states stop the
    run), so a search computes these once, on its root chain.

    Proven as :func:`entry_gains` is: a region's system is the base chain with the region's
    states stopping runs, whose expected steps are at most the base chain's. Regions go in
    decreasing order of their gains on every entry; once ``stop()`` says so, those not yet
    done keep those gains (a bound still)."""
    given = sp.csr_matrix(transitions)
    base, classes, solved = _entry_gains(
        given, target, target_value, initial, region, n_regions, top
    )
    if classes is None or solved is None:
        return base  # nothing proven, or the run never moves: the first bound stands
    component, closed, region = classes.component, classes.closed, classes.region
    transient, rows, inner = solved.transient, solved.rows, solved.inner
    # what a run gains at most on entering a transient state: M less its proven value
    worth = np.clip(top - (solved.values - solved.value_error), 0.0, top)
    # closed classes of no value that meet a region: per transient row, the mass it sends
    # into each (a run absorbed there enters the region for sure, worth M)
    pairs = classes.traps
    n_classes = classes.open_class.size
    meets = sp.csr_matrix(
        (np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n_classes, n_regions)
    )
    flow = rows.tocoo()
    absorbed = closed[flow.col] & ~target[flow.col]
    into_class = sp.csr_matrix(
        (flow.data[absorbed], (flow.row[absorbed], component[flow.col[absorbed]])),
        shape=(transient.size, n_classes),
    )
    trap_gain = sp.csc_matrix(into_class @ meets) * top  # (transient rows, regions)
    position = int(np.searchsorted(transient, initial))
    # each row's reward below sums at most its entries plus one, each product rounded
    terms = int(np.diff(given.indptr).max(initial=0)) + 2
    raise_by = 1 + 2.02 * terms * UNIT_ROUNDOFF
    gains = base.gains.copy()
    transient_region = region[transient]
    # the largest gains first: they weigh most in a bound's sum
    for s in np.argsort(-base.gains, kind="stable")[: int((base.gains > 0).sum())].tolist():
        if stop is not None and stop():
            break
        inside = transient_region == s
        if inside[position]:
            continue  # the run starts in it (never: the initial observation is never altered)
        outside = np.flatnonzero(~inside)
        into = np.where(inside, worth, 0.0)
        reward = np.asarray(inner @ into).ravel() + trap_gain[:, [s]].toarray().ravel()
        reward = reward[outside] * raise_by
        stay = sp.csr_matrix(inner[outside][:, outside])
        gain = factorise(stay).solve(reward)
        local = np.arange(outside.size)
        _, gain_residual = residual.residual(stay, gain, np.zeros_like(gain), local, reward)
        # runs that stop on entering s take at most as many steps as the base chain's
        error = float(gain_residual.max(initial=0.0)) * solved.steps * (1 + tolerance.BOUND_MARGIN)
        proven = float(gain[int(np.searchsorted(outside, position))]) + error
        if np.isfinite(proven):
            gains[s] = min(gains[s], max(proven, 0.0) * (1 + 4 * UNIT_ROUNDOFF))
    return EntryGains(base.value, gains)


# The floor filter of the low-rank enumeration (misdirect.solvers.engines.lowrank): a block
# with a floor lists at least this many alterations, and this many per live state (the gains
# cost about one solve of its base chain), before the gain bound filters them
FILTER_FROM = 20_000
FILTER_PER_STATE = 4


def worth_filtering(count: int, live_states: int) -> bool:
    """Whether a block of ``count`` alterations on a chain of ``live_states`` is big enough
    for the floor filter: its gains cost about one solve of the block's base chain, which a
    small block would not repay."""
    return count >= max(FILTER_FROM, FILTER_PER_STATE * live_states)


class FloorFiltered(NamedTuple):
    """What the floor filter kept: the alterations (renumbered), which of them may reach the
    floor (the others are kept only as parents), and how many it left out."""

    altered: AlteredEntries
    reaches: np.ndarray
    dropped: int


def floor_filter(altered: AlteredEntries, bound: np.ndarray, floor: float) -> FloorFiltered:
    """``altered`` without the alterations whose gain ``bound`` (per alteration, proven from
    above) cannot reach ``floor``: valuing them could not change the answer, since some
    alteration already reaches the floor. Those within a near-tie of ``floor`` may (the
    cheaper of tied ones wins); every parent of one that may is kept too (the low-rank
    updates build each alteration from its parent), but need not be valued exactly."""
    count = len(altered.costs)
    reaches = bound >= floor - tolerance.slack(floor, rel=tolerance.NEAR_TIE)
    keep = reaches.copy()
    keep[0] = True  # the base itself: every alteration's ancestor
    marked = keep
    while True:  # every ancestor of one kept (as deep as the budget allows)
        parents = altered.parent[marked]
        parents = parents[(parents >= 0) & ~keep[np.maximum(parents, 0)]]
        if not parents.size:
            break
        keep[parents] = True
        marked = np.zeros(count, dtype=bool)
        marked[parents] = True
    dropped = int(count - keep.sum())
    if keep.all():
        return FloorFiltered(altered, reaches, dropped)
    return FloorFiltered(altered.restricted(keep), reaches[keep], dropped)
