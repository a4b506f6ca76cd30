"""Exact reachability analysis of a finite Markov chain (Baier & Katoen, ch. 10).

Graph precomputation first (states that cannot reach the target get 0, states that reach it
almost surely get 1), then one sparse LU solve on the remaining states. Removing the
probability-0 states is what makes the answer the *least* fixed point (SPEC §1) and the
linear system non-singular.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.linalg.lapack import dgbsv
from scipy.sparse.csgraph import connected_components
from scipy.sparse.linalg import SuperLU, splu

from misdirect.model import reachable_from


def _without_rows(matrix: sp.csr_matrix, rows: np.ndarray) -> sp.csr_matrix:
    """Copy of ``matrix`` with the out-edges of the masked rows removed."""
    source = np.repeat(np.arange(matrix.shape[0]), np.diff(matrix.indptr))
    keep = ~rows[source] & (matrix.data != 0)
    indptr = np.concatenate(([0], np.cumsum(np.bincount(source[keep], minlength=rows.size))))
    return sp.csr_matrix((matrix.data[keep], matrix.indices[keep], indptr), shape=matrix.shape)


def prob0_prob1(matrix: sp.csr_matrix, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Masks of states reaching ``target`` with probability exactly 0 and exactly 1."""
    backward = matrix.T.tocsr()
    prob0 = ~reachable_from(backward, np.flatnonzero(target))
    # A state misses the target with positive probability iff it can reach a prob-0 state
    # along a path that does not pass through the target.
    can_miss = reachable_from(_without_rows(matrix, target).T.tocsr(), np.flatnonzero(prob0))
    return prob0, ~can_miss


DIRECT_MAX_STATES = 5_000  # below this one LU of the whole system is fastest
CHUNK_STATES = 1_000  # consecutive components are factorised together up to about this many
BAND_MIN_STATES = 32  # a component this large that is a thin band gets a banded solve ...
BAND_MAX = 8  # ... if no transition reaches further than this in its state order
SEPARATOR_MAX = 512  # cutting a separator only pays when it is small


def factorise(a: sp.spmatrix) -> SuperLU:
    """Sparse LU of ``I - a`` for a substochastic ``a`` from which every state can leave.

    ``I - a`` is then a non-singular M-matrix: Gaussian elimination needs no pivoting (every
    pivot stays positive and every Schur complement stays an M-matrix), so the factorisation
    can use a symmetric fill-reducing ordering on the pattern of ``A + Aᵀ``. On the grid's
    chains that halves the fill of SuperLU's default (COLAMD with partial pivoting) and the
    time with it. Should a pivot vanish all the same, the default is used.
    """
    return _lu((sp.identity(a.shape[0], format="csc") - a).tocsc())


def _lu(system: sp.spmatrix) -> SuperLU:
    system = sp.csc_matrix(system)
    try:
        return splu(
            system,
            permc_spec="MMD_AT_PLUS_A",
            diag_pivot_thresh=0.0,
            options={"SymmetricMode": True},
        )
    except RuntimeError:  # "Factor is exactly singular": let partial pivoting decide
        return splu(system)


def _solve(a: sp.spmatrix, b: np.ndarray, *, transpose: bool = False) -> np.ndarray:
    """Solve ``(I - a) x = b`` (or its transpose) by sparse LU."""
    return factorise(a).solve(b, trans="T" if transpose else "N")


def _rows(matrix: sp.csr_matrix, start: int, stop: int) -> tuple[np.ndarray, ...]:
    """CSR arrays of rows ``start:stop`` without scipy's per-slice checks."""
    first, last = matrix.indptr[start], matrix.indptr[stop]
    return (
        matrix.data[first:last],
        matrix.indices[first:last],
        matrix.indptr[start : stop + 1] - first,
    )


def solve_topological(system: sp.spmatrix, rhs: np.ndarray) -> np.ndarray | None:
    """Solve ``system @ x = rhs`` by block substitution over strongly connected components.

    A chain that mostly moves forward (the grid robot's E and N moves) splits into many small
    strongly connected components. Ordered so that every component comes after the ones it
    leads to, the system is block lower triangular, and it is solved chunk by chunk, each
    chunk once the chunks it leads to are known (Storm's topological solver, with direct
    solves inside):

    * a component of at least ``BAND_MIN_STATES`` states that is a thin band in its own state
      order (a corridor, a grid column: bandwidth at most ``BAND_MAX``) is one chunk, solved
      by LAPACK's banded LU in time linear in its size;
    * other components are grouped, in order, into chunks of about ``CHUNK_STATES`` states,
      each factorised by sparse LU alone (its fill cannot leave the chunk).

    ``rhs`` may hold several columns. ``None`` when one component holds most of the states:
    one LU of the whole system is then better. ``system`` must be a non-singular M-matrix
    (every diagonal block of one is one too).
    """
    system = sp.csr_matrix(system)
    n = system.shape[0]
    count, component = connected_components(system, directed=True, connection="strong")
    sizes = np.bincount(component, minlength=count)
    if sizes.max() > n // 2:
        return None
    coo = system.tocoo()
    # SciPy numbers components in the order it completes them: successors first. Check it,
    # since the substitution below is only right in that order.
    if np.any(component[coo.row] < component[coo.col]):
        return None
    order = np.argsort(component, kind="stable")
    position = np.empty(n, dtype=np.int64)
    position[order] = np.arange(n)
    row, col = position[coo.row], position[coo.col]

    # Bandwidths of each component in its own state order, and which get a banded solve.
    ends = np.cumsum(sizes)
    starts = ends - sizes
    same = component[coo.row] == component[coo.col]
    lower = np.zeros(count, dtype=np.int64)
    upper = np.zeros(count, dtype=np.int64)
    np.maximum.at(lower, component[coo.row[same]], (row - col)[same])
    np.maximum.at(upper, component[coo.row[same]], (col - row)[same])
    banded = (sizes >= BAND_MIN_STATES) & (lower <= BAND_MAX) & (upper <= BAND_MAX)
    cuts = ends[np.flatnonzero(np.diff(ends // CHUNK_STATES, prepend=0) > 0)]
    bounds = np.unique(np.concatenate(([0, n], cuts, starts[banded], ends[banded])))
    is_band = np.zeros(bounds.size, dtype=bool)
    is_band[np.searchsorted(bounds, starts[banded])] = True

    # Entries inside a chunk form its diagonal block; the rest point to chunks solved earlier.
    chunk = np.searchsorted(bounds, np.arange(n), side="right") - 1
    in_band = is_band[chunk]
    inside = chunk[row] == chunk[col]
    sparse_part = inside & ~in_band[row]
    diagonal = sp.csr_matrix(
        (coo.data[sparse_part], (row[sparse_part], col[sparse_part])), shape=(n, n)
    )
    kl = int(lower[banded].max(initial=0))
    ku = int(upper[banded].max(initial=0))
    band = np.zeros((2 * kl + ku + 1, n), order="F")  # LAPACK's band storage, room to pivot
    band_part = inside & in_band[row]
    band[kl + ku + row[band_part] - col[band_part], col[band_part]] = coo.data[band_part]
    before = sp.csr_matrix((coo.data[~inside], (row[~inside], col[~inside])), shape=(n, n))
    # Rows with transitions to earlier chunks, where their terms start, and each chunk's share.
    depends = np.flatnonzero(np.diff(before.indptr) > 0)
    term_start = before.indptr[depends]
    depends_from = np.searchsorted(depends, bounds).tolist()
    entry_from = before.indptr[bounds].tolist()

    x = np.asarray(rhs, dtype=np.float64)[order]  # the right-hand side, overwritten by x
    single = x.ndim == 1
    if single:
        x = x[:, None]
    x = np.ascontiguousarray(x)
    data, indices = before.data, before.indices
    for k in range(bounds.size - 1):
        start, stop = int(bounds[k]), int(bounds[k + 1])
        first, last = entry_from[k], entry_from[k + 1]
        if last > first:  # subtract what the chunks solved so far contribute, row by row
            rows = depends[depends_from[k] : depends_from[k + 1]]
            terms = data[first:last, None] * x[indices[first:last]]
            x[rows] -= np.add.reduceat(
                terms, term_start[depends_from[k] : depends_from[k + 1]] - first
            )
        if is_band[k]:
            _, _, solved, info = dgbsv(kl, ku, band[:, start:stop], x[start:stop])
            if info != 0:
                return None
        else:
            size = stop - start
            block = _rows(diagonal, start, stop)
            # The chunk's rows in CSR are its transpose in CSC: factorise that, solve transposed.
            block_t = sp.csc_matrix((block[0], block[1] - start, block[2]), shape=(size, size))
            solved = _lu(block_t).solve(x[start:stop], trans="T")
        x[start:stop] = solved
    x = x[position]
    return x[:, 0] if single else x


def solve_with_separator(a: sp.spmatrix, b: np.ndarray, labels: np.ndarray) -> np.ndarray | None:
    """Solve ``(I - a) x = b`` by cutting the states whose edges cross between ``labels``.

    The product chain of a controller that rarely changes its memory node splits by node: only
    the states that read a memory-changing observation have transitions into another node's
    part. Those states form the separator ``S``; without them the chain falls apart into the
    small components :func:`solve_topological` is fast on. The interior ``I`` is solved for
    ``b_I`` and for the coupling columns at once, the small dense Schur complement on ``S``
    gives ``x_S``, and back-substitution the rest. Every principal submatrix and Schur
    complement of the non-singular M-matrix ``I - a`` is again one, so no step can break
    down. ``None`` when the cut would not pay.
    """
    n = a.shape[0]
    coo = sp.coo_matrix(a)
    separator = np.zeros(n, dtype=bool)
    separator[coo.row[labels[coo.row] != labels[coo.col]]] = True  # every crossing edge
    if separator.sum() > SEPARATOR_MAX or separator.all():
        return None
    system = (sp.identity(n, format="csr") - sp.csr_matrix(a)).tocsr()
    border, interior = np.flatnonzero(separator), np.flatnonzero(~separator)
    interior_rows, border_rows = system[interior], system[border]
    rhs = b.reshape(n, -1)
    columns = rhs.shape[1]
    coupling = interior_rows[:, border].toarray()
    solved = solve_topological(
        interior_rows[:, interior], np.column_stack([rhs[interior], coupling])
    )
    if solved is None:
        return None
    y, y_coupling = solved[:, :columns], solved[:, columns:]
    to_interior = border_rows[:, interior]
    schur = border_rows[:, border].toarray() - to_interior @ y_coupling
    x_border = np.linalg.solve(schur, rhs[border] - to_interior @ y)
    x = np.empty((n, columns))
    x[border] = x_border
    x[interior] = y - y_coupling @ x_border
    return x.reshape(b.shape)


def solve_chain(a: sp.spmatrix, b: np.ndarray, labels: np.ndarray | None = None) -> np.ndarray:
    """Solve ``(I - a) x = b`` by the fastest exact route for the chain's shape.

    Large chains are cut along ``labels`` first (:func:`solve_with_separator`: the separator is
    cheap to find and, where it is small, the rest falls apart), else solved by components as
    they are (:func:`solve_topological`); one sparse LU is the fallback and the route for small
    systems. ``b`` may hold several columns.
    """
    if a.shape[0] >= DIRECT_MAX_STATES:
        solved = None if labels is None else solve_with_separator(a, b, labels)
        if solved is None:
            system = sp.identity(a.shape[0], format="csr") - sp.csr_matrix(a)
            solved = solve_topological(system, b)
        if solved is not None:
            return solved
    return _solve(a, b)


def reach_probabilities(
    matrix: sp.csr_matrix, target: np.ndarray, blocks: np.ndarray | None = None
) -> np.ndarray:
    """Probability of ever reaching ``target`` from every state (least fixed point).

    ``blocks`` (e.g. the memory node of each product state) offers :func:`solve_chain` a
    separator to cut along.
    """
    prob0, prob1 = prob0_prob1(matrix, target)
    values = prob1.astype(np.float64)
    maybe = np.flatnonzero(~prob0 & ~prob1)
    if maybe.size:
        rows = matrix[maybe]
        b = rows @ prob1.astype(np.float64)  # one step into the almost-sure states
        labels = None if blocks is None else blocks[maybe]
        values[maybe] = solve_chain(rows[:, maybe], b, labels)
    return np.clip(values, 0.0, 1.0)


@dataclass(frozen=True)
class Occupation:
    """Where a run from one state goes: expected visits and first terminal state entered.

    ``visits[q]``: expected number of steps spent in transient state ``q`` before the run enters
    a terminal state or a trapped region. ``entered[q]``: probability that the first
    non-transient state the run enters is ``q`` (terminal or trapped). Trapped states are those
    from which no terminal state is reachable.
    """

    visits: np.ndarray
    entered: np.ndarray
    transient: np.ndarray  # mask
    trapped: np.ndarray  # mask


def occupation(matrix: sp.csr_matrix, terminal: np.ndarray, initial: int) -> Occupation:
    """Expected visits and first-entry distribution from ``initial`` (one transposed LU solve)."""
    n = matrix.shape[0]
    can_reach = reachable_from(matrix.T.tocsr(), np.flatnonzero(terminal))
    transient = can_reach & ~terminal
    trapped = ~can_reach
    visits = np.zeros(n)
    entered = np.zeros(n)
    if not transient[initial]:
        entered[initial] = 1.0
        return Occupation(visits, entered, transient, trapped)
    inner = np.flatnonzero(transient)
    rows = matrix[inner]
    start = np.zeros(inner.size)
    start[np.searchsorted(inner, initial)] = 1.0
    y = np.maximum(_solve(rows[:, inner], start, transpose=True), 0.0)
    visits[inner] = y
    entered = np.asarray(rows.T @ y).ravel()
    entered[inner] = 0.0
    return Occupation(visits, entered, transient, trapped)
