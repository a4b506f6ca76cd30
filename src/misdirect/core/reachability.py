"""Exact reachability analysis of a finite Markov chain (Baier & Katoen, ch. 10).

Graph precomputation first (states that cannot reach the target get 0, states that reach it
almost surely get 1), then one linear solve on the remaining states. Removing the
probability-0 states is what makes the answer the *least* fixed point (SPEC §1) and the
linear system non-singular.

The solve is direct (sparse LU, split by components, bands and separators) except on wide
chains, where LU fill explodes: there Krylov iterations run and the answer carries a proven
error bound (:func:`solve_certified`), accepted only when that bound is small relative to the
answer (:data:`misdirect.core.tolerance.EXACT`); else the direct solve runs after all.

The values a person reads (:func:`reach_probability_bounded`, :func:`occupation`) carry a
proven error bound on every route, on the chain as given (its doubles taken as exact): a
direct solve is proven by its residual and a proven bound on the time to absorption, and on
an ill-conditioned chain (absorbed after 10^9 steps, where double precision loses digits) it
is refined in extended precision (:mod:`misdirect.core.residual`) until the bound is at most
:data:`EXACT_TOL`. :func:`reach_probabilities`, the solvers' inner loop, stays unproven.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple, cast

import numpy as np
import scipy.sparse as sp
from scipy.linalg.lapack import dgbsv
from scipy.sparse.csgraph import connected_components
from scipy.sparse.linalg import SuperLU, splu

from misdirect.core import elimination, residual, tolerance
from misdirect.core.lu_solve import MANY_COLUMNS, solve_many
from misdirect.core.model import reachable_from
from misdirect.errors import SolverError


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


DENSE_MAX_STATES = 200  # up to this many states, dense arrays beat sparse ones' overhead
DIRECT_MAX_STATES = 5_000  # below this one LU of the whole system is fastest
CHUNK_STATES = 1_000  # consecutive components are factorised together up to about this many
BAND_MIN_STATES = 32  # a component this large that is a thin band gets a banded solve ...
BAND_MAX = 8  # ... if no transition reaches further than this in its state order
SEPARATOR_MAX = 512  # cutting a separator only pays when it is small
ITERATIVE_MIN_STATES = 20_000  # below this even a wide component's LU is quick
WIDE_LEVEL = 1_000  # a breadth-first level this wide: LU fronts of about that size, cubed
# the iterative route's answer is accepted with a proven error of at most tolerance.EXACT
# relative to it, and, on expected visits, tolerance.CERTIFY relative to max(1, visits) (a
# count of steps: one visit is its natural unit, so fewer than one visit counts as one)
# Refinement stops once the proven error is this small (core.tolerance) ...
REFINE_TARGET = tolerance.REFINE_TARGET
REFINE_ROUNDS = 5  # ... after this many rounds, or when the residual stops falling
KRYLOV_RTOL = tolerance.KRYLOV_RTOL  # the first round's inner solve shrinks the residual this much
KRYLOV_MAX_ITER = 2_000
UNIT_ROUNDOFF = residual.UNIT_ROUNDOFF
# A value's proven error must be this small relative to it (core.tolerance) ...
EXACT_TOL = tolerance.EXACT
EXACT_ROUNDS = 8  # ... after at most this many rounds of refinement in extended precision
# From a state whose runs last this many steps, a correction solved with double-precision
# factors is off by more than itself, so refinement cannot converge and no proof comes of an
# LU (docs/benchmarks.md counts where proofs stop on the drone's chains): given an elimination
# order, the jump chain's value is then returned, unproven, without one.
NO_PROOF_STEPS = 1e17


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
    """Solve ``(I - a) x = b`` (or its transpose) by sparse LU; many columns at once through
    :func:`~misdirect.core.lu_solve.solve_many`."""
    if transpose:
        return cast(np.ndarray, factorise(a).solve(b, trans="T"))
    return solve_many(factorise(a), b)


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
    entry_from = before.indptr[bounds].tolist()  # each chunk's share of those entries

    x = np.asarray(rhs, dtype=np.float64)[order]  # the right-hand side, overwritten by x
    single = x.ndim == 1
    if single:
        x = x[:, None]
    x = np.ascontiguousarray(x)
    for k in range(bounds.size - 1):
        start, stop = int(bounds[k]), int(bounds[k + 1])
        if entry_from[k + 1] > entry_from[k]:  # subtract what the chunks solved so far give
            # one sparse product: compiled, with no temporary per entry and column (those
            # dominated base solves of thousands of columns)
            earlier = sp.csr_matrix(_rows(before, start, stop), shape=(stop - start, n))
            x[start:stop] -= earlier @ x
        if is_band[k]:
            _, _, solved, info = dgbsv(kl, ku, band[:, start:stop], x[start:stop])
            if info != 0:
                return None
        else:
            size = stop - start
            data, indices, indptr = _rows(diagonal, start, stop)
            if x.shape[1] >= MANY_COLUMNS:  # the compiled loop over its factors, on threads
                chunk = sp.csr_matrix((data, indices - start, indptr), shape=(size, size))
                solved = solve_many(_lu(chunk.tocsc()), x[start:stop])
            else:  # its rows in CSR are its transpose in CSC: factorise that, solve transposed
                chunk_t = sp.csc_matrix((data, indices - start, indptr), shape=(size, size))
                solved = _lu(chunk_t).solve(x[start:stop], trans="T")
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
    if not separator.any() or separator.sum() > SEPARATOR_MAX or separator.all():
        return None  # nothing to cut (a memoryless controller): the caller splits as it is
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


def _structured(a: sp.spmatrix, b: np.ndarray, labels: np.ndarray | None) -> np.ndarray | None:
    """The separator, then the component route; ``None`` when both decline."""
    solved = None if labels is None else solve_with_separator(a, b, labels)
    if solved is None:
        system = sp.identity(a.shape[0], format="csr") - sp.csr_matrix(a)
        solved = solve_topological(system, b)
    return solved


def solve_chain(a: sp.spmatrix, b: np.ndarray, labels: np.ndarray | None = None) -> np.ndarray:
    """Solve ``(I - a) x = b`` by the fastest exact route for the chain's shape.

    Large chains are cut along ``labels`` first (:func:`solve_with_separator`: the separator is
    cheap to find and, where it is small, the rest falls apart), else solved by components as
    they are (:func:`solve_topological`). A chain that stays one big, wide component (a drone
    among moving agents: LU fill grows like the cube of its separators) gets the certified
    iterative solve (:func:`solve_certified`; ``b`` one column). One sparse LU is the fallback
    and the route for small systems. ``b`` may hold several columns.
    """
    if a.shape[0] >= DIRECT_MAX_STATES:
        solved = _structured(a, b, labels)
        if solved is not None:
            return solved
        if np.ndim(b) == 1 and lu_would_fill(a):
            certified = solve_certified(a, b)
            if certified is not None and certified.state_error().max() <= tolerance.slack(
                np.abs(certified.x).max(initial=0.0), rel=tolerance.EXACT
            ):
                return certified.x
    return _solve(a, b)


def steps_bound(a: sp.spmatrix, t: np.ndarray) -> float:
    """A proven bound on the largest expected number of steps before leaving, ``max (I - a)⁻¹
    1``, from an approximate solution ``t`` of ``(I - a) t = 1``; ``inf`` when it cannot be
    proven. It bounds the condition number of ``I - a`` (at most twice it, in the ∞-norm),
    so how many digits a double solve of the chain may lose (:func:`_time_bound_at`)."""
    if not t.size:
        return 0.0
    if not np.isfinite(t).all():
        return np.inf
    csr = sp.csr_matrix(a)
    return float(_time_bound_at(csr, t, _rounding(csr), int(np.argmax(t))))


def _neighbours(matrix: sp.csr_matrix, rows: np.ndarray) -> np.ndarray:
    """Column indices of the entries in ``rows`` (with repeats), without slicing the matrix."""
    starts, stops = matrix.indptr[rows], matrix.indptr[rows + 1]
    counts = stops - starts
    offsets = np.repeat(starts - np.cumsum(counts) + counts, counts)
    return cast(np.ndarray, matrix.indices[offsets + np.arange(counts.sum())])


def lu_would_fill(a: sp.spmatrix) -> bool:
    """Whether a sparse LU of ``I - a`` would drown in fill: many states, wide breadth-first levels.

    Each breadth-first level separates the states before it from those after it, and an LU's
    dense fronts are about as wide as the separators its ordering finds, so their cube is the
    cost. Grid-like chains (the robot's grid, corridors) have levels of a few hundred states;
    a drone among moving agents has levels of thousands (at 5·10^4 states SuperLU fills 10^8
    entries in a minute), while runs there end within a few hundred steps, which is what
    makes Krylov iterations converge fast.
    """
    n = a.shape[0]
    if n < ITERATIVE_MIN_STATES:
        return False
    matrix = sp.csr_matrix(a)
    seen = np.zeros(n, dtype=bool)
    frontier = np.array([0])
    seen[0] = True
    while frontier.size:
        reached = _neighbours(matrix, frontier)
        frontier = np.unique(reached[~seen[reached]])
        if frontier.size > WIDE_LEVEL:
            return True
        seen[frontier] = True
    return False


def _dot(u: np.ndarray, v: np.ndarray) -> float:
    """``u · v`` in one pass without BLAS, whose threads stall on a busy machine."""
    return float(np.einsum("i,i->", u, v))


def _bicgstab(op: sp.csr_matrix, b: np.ndarray, rtol: float, max_iter: int) -> np.ndarray | None:
    """BiCGSTAB for ``op x = b``, right-preconditioned by the diagonal (folded into ``op``).

    ``None`` on breakdown, or as soon as the pace so far says the residual will not fall by
    ``rtol`` within ``max_iter`` iterations (the caller then takes the direct route). Vector
    updates run in place and without BLAS: at 10^5 states they cost as much as the products,
    and BLAS's threads, spinning while other processes hold the cores, made them 100 times
    slower on a busy 2-core machine.
    """
    norm_b = np.sqrt(_dot(b, b))
    x = np.zeros_like(b)
    if norm_b == 0.0:
        return x
    if not np.isfinite(norm_b):
        return None
    target = rtol * norm_b
    inv_diag = 1.0 / op.diagonal()
    if (inv_diag == 1.0).all():  # no self-loops: nothing to scale
        scaled, inv_diag = op, np.ones(1)
    else:  # solve (op D⁻¹) z = b, then x = D⁻¹ z
        scaled = op @ sp.diags(inv_diag, format="csr")
    r = b.copy()
    # the shadow residual: b alone breaks down on sparse right-hand sides (a unit vector)
    r_hat = b + np.random.default_rng(0).random(b.size) * (norm_b / np.sqrt(b.size))
    p = np.zeros_like(b)
    v = np.zeros_like(b)
    scratch = np.empty_like(b)
    rho = alpha = omega = 1.0
    best = norm_b

    def axpy(a: float, u: np.ndarray, out: np.ndarray) -> None:  # out += a u
        np.multiply(u, a, out=scratch)
        out += scratch

    for k in range(1, max_iter + 1):
        rho_next = _dot(r_hat, r)
        if rho_next == 0.0 or omega == 0.0:
            return None
        beta = (rho_next / rho) * (alpha / omega)
        rho = rho_next
        axpy(-omega, v, p)  # p = r + beta (p - omega v)
        p *= beta
        p += r
        v = scaled @ p
        denominator = _dot(r_hat, v)
        if denominator == 0.0:
            return None
        alpha = rho / denominator
        axpy(alpha, p, x)
        axpy(-alpha, v, r)  # r is now s
        t = scaled @ r
        tt = _dot(t, t)
        if tt == 0.0:  # s = 0: solved at the half step
            return cast(np.ndarray, x * inv_diag)
        omega = _dot(t, r) / tt
        axpy(omega, r, x)
        axpy(-omega, t, r)
        residual = np.sqrt(_dot(r, r))
        if residual <= target:
            return cast(np.ndarray, x * inv_diag)
        if not np.isfinite(residual):
            return None
        best = min(best, residual)
        if k % 25 == 0 and k >= 100:  # judge the pace: give up early on slow chains
            pace = np.log(best / norm_b) / k
            if pace >= 0 or np.log(rtol) / pace > max_iter:
                return None
    return None


def _rounding(op: sp.csr_matrix) -> np.ndarray:
    """``γ`` per row: ``|fl(b - op x) - (b - op x)| <= γ (|b| + |op| |x|)`` (Higham's bound for
    a dot product of the row's length, plus the subtraction)."""
    return cast(np.ndarray, 1.01 * (np.diff(op.indptr) + 2) * UNIT_ROUNDOFF)


def _time_bound(system: sp.csr_matrix) -> np.ndarray | None:
    """A proven ``y >= (I - Q)⁻¹ 1`` (expected steps before leaving the system, from each state).

    Any ``y`` with ``(I - Q) y >= 1`` is one, because ``(I - Q)⁻¹ >= 0`` (an M-matrix). A rough
    Krylov solution of ``(I - Q) t = 1`` is scaled by the least lower bound of ``(I - Q) t``
    (rounding of the product accounted for), then checked again.
    """
    n = system.shape[0]
    magnitude = abs(system)
    gamma = _rounding(system)
    # Krylov's relative residuals, then a relative margin on the scaling: both scale-free
    for rtol in tolerance.TIME_BOUND_RTOLS:
        t = _bicgstab(system, np.ones(n), rtol, KRYLOV_MAX_ITER)
        if t is None:
            return None
        low = (system @ t - gamma * (magnitude @ np.abs(t))).min()
        if low <= 0:
            continue
        y = t * ((1 + tolerance.BOUND_MARGIN) / low)
        if (y >= 0).all() and (system @ y - gamma * (magnitude @ y)).min() >= 1.0:
            return cast(np.ndarray, y)
    return None


@dataclass(frozen=True)
class Certified:
    """An iterative solution of ``op x = b`` with a proven bound on its error.

    ``op`` is ``I - Q`` or its transpose, ``Q`` substochastic and leaking from every state, so
    ``(I - Q)⁻¹ >= 0`` and the error ``(I - Q)⁻¹ r`` (resp. ``(I - Q)⁻ᵀ r``) is bounded by the
    residual ``r`` alone. ``residual`` bounds ``|b - op x|`` entry by entry in exact arithmetic
    (the rounding of computing it included).
    """

    x: np.ndarray
    residual: np.ndarray
    time_bound: np.ndarray | None  # y >= (I - Q)⁻¹ 1, proven; None when not computed
    transpose: bool

    def state_error(self) -> np.ndarray:
        """Proven bound on ``|x - x*|`` per state (needs ``time_bound``).

        Forward: ``(I - Q)⁻¹ |r| <= max|r| y``. Transposed: entry ``s`` is ``Σ_j |r_j| G_js``
        with ``G = (I - Q)⁻¹``, and ``G_js <= G_ss <= y_s`` (visits to ``s`` from ``j`` are at
        most those from ``s``, which are at most all steps from ``s``): ``Σ|r| y_s``.
        """
        if self.time_bound is None:
            return np.full(self.x.size, np.inf)
        scale = self.residual.sum() if self.transpose else self.residual.max(initial=0.0)
        return cast(np.ndarray, scale * self.time_bound)

    def functional_error(self) -> float:
        """Proven bound on the error of ``cᵀx`` (a transposed solve) for every ``c >= 0`` with
        ``G c <= 1``, ``G = (I - Q)⁻¹``: probabilities of leaving into some set of states.

        The error of ``x`` is ``Gᵀ r``, so that of ``cᵀx`` is ``rᵀ G c``, at most ``Σ|r|``.
        """
        return float(self.residual.sum())


def solve_certified(
    a: sp.spmatrix, b: np.ndarray, *, transpose: bool = False, states: bool = True
) -> Certified | None:
    """Solve ``(I - a) x = b`` (or the transpose) iteratively, with a proven error bound.

    Iterative refinement: the residual is recomputed in full, a Krylov solve (BiCGSTAB,
    :data:`KRYLOV_RTOL`) corrects ``x``, until the proven error is below
    :data:`REFINE_TARGET` or stops falling. ``states`` also proves the per-state bound
    (:meth:`Certified.state_error`, one rough extra solve); a transposed solve whose caller
    only needs absorption probabilities does without. ``None`` when Krylov breaks down or
    would be too slow: the caller then factorises.
    """
    n = a.shape[0]
    system = (sp.identity(n, format="csr") - sp.csr_matrix(a)).tocsr()
    op = system.T.tocsr() if transpose else system
    time_bound = _time_bound(system) if states else None
    if states and time_bound is None:
        return None
    magnitude = abs(op)
    gamma = _rounding(op)
    b = np.asarray(b, dtype=np.float64)
    x = np.zeros(n)
    best: tuple[float, np.ndarray, np.ndarray] | None = None
    weight = 1.0 if time_bound is None else max(1.0, float(time_bound.max()))
    for round_ in range(REFINE_ROUNDS + 1):
        r = b - op @ x
        floor = gamma * (np.abs(b) + magnitude @ np.abs(x))  # what rounding alone may hide
        bound = np.abs(r) + floor
        size = (bound.sum() if transpose else bound.max(initial=0.0)) * weight
        if best is None or size < best[0]:
            best = (size, x, bound)
        if size <= REFINE_TARGET or round_ == REFINE_ROUNDS or np.abs(r).sum() <= floor.sum():
            break  # proven small enough, or at the rounding floor: another round cannot help
        # aim at the rounding floor: shrinking the residual further proves nothing more
        ratio = np.sqrt(_dot(floor, floor) / max(_dot(r, r), tolerance.DENOMINATOR_FLOOR))
        rtol = max(KRYLOV_RTOL, min(0.1, 0.3 * ratio))
        correction = _bicgstab(op, r, rtol, KRYLOV_MAX_ITER)
        if correction is None:
            if round_ == 0:
                return None
            break
        x = x + correction
    assert best is not None  # the first round always sets it
    _, x, bound = best
    return Certified(x=x, residual=bound, time_bound=time_bound, transpose=transpose)


def _scores(target: np.ndarray, value: np.ndarray | None) -> tuple[float, np.ndarray | None]:
    """``value`` scaled into ``[0, 1]`` and the scale, or ``None`` when every target state is
    worth the same (plain reachability, times that worth).

    Scaling keeps every error argument below (stated for probabilities) valid as it is: the
    weighted problem is the same linear system with a right-hand side in ``[0, 1]``.
    """
    target = np.asarray(target, dtype=bool)
    if value is None or not target.any():
        return 1.0, None
    worth = np.asarray(value, dtype=np.float64)[target]
    top = float(worth.max())
    if top <= 0.0 or np.all(worth == top):
        return top, None
    scaled = np.where(target, np.asarray(value, dtype=np.float64) / top, 0.0)
    return top, scaled


class Bounded(NamedTuple):
    """A value and a proven bound on its error (``inf``: none could be proven)."""

    value: float
    error: float


def reach_probability(
    matrix: sp.csr_matrix,
    target: np.ndarray,
    initial: int,
    blocks: np.ndarray | None = None,
    value: np.ndarray | None = None,
) -> float:
    """Probability of ever reaching ``target`` from ``initial`` alone (least fixed point).

    With ``value`` (a score per target state), the expected score of the first target state
    entered instead (:mod:`misdirect.core.objective`). :func:`reach_probability_bounded`
    gives the proven error bound with it.
    """
    return reach_probability_bounded(matrix, target, initial, blocks, value).value


def reach_probability_bounded(
    matrix: sp.csr_matrix,
    target: np.ndarray,
    initial: int,
    blocks: np.ndarray | None = None,
    value: np.ndarray | None = None,
    *,
    extended_jump: bool = True,
    elimination_rank: np.ndarray | None = None,
) -> Bounded:
    """:func:`reach_probability` and a proven bound on its error, on the chain as given.

    The unknowns are the states whose value is not known from the graph alone; a run from
    them leaves that set almost surely. The direct solve's answer is proven by its residual
    and a proven bound on the expected time to leave (:func:`_prove_forward`), and refined
    in extended precision until the bound is at most :data:`EXACT_TOL`. Where the chain is
    one wide component, one transposed Krylov solve gives the occupation measure from
    ``initial``, whose error bound on the value needs no second solve
    (:meth:`Certified.functional_error`).

    Where nothing can be proven, the jump chain's value is computed in double-double
    (``extended_jump``) or, for a search that only ranks alterations by it, in doubles: the
    same elimination without subtraction, several times faster (:func:`_jump_chain_value`).
    With ``elimination_rank`` (each state's place in a fill-reducing order, from
    :func:`~misdirect.core.elimination.fill_reducing_rank`, for a caller that expects such
    chains), the jump chain is eliminated first, and where its runs last at least
    :data:`NO_PROOF_STEPS` steps its value is returned at once, unproven: no LU is tried.
    """
    if value is not None:
        target = _without_worthless_sinks(matrix, target, value)
    scale, scaled = _scores(target, value)
    if scale == 0.0:
        return Bounded(0.0, 0.0)
    target = np.asarray(target, dtype=bool)
    # the value of a run on entering a state known in advance, and the unknown states
    known = target.astype(np.float64) if scaled is None else scaled
    dense = None
    if matrix.shape[0] <= DENSE_MAX_STATES:
        dense = matrix.toarray()
        unknown = np.flatnonzero(_can_reach_dense(dense, target) & ~target)
    elif scaled is None:
        prob0, prob1 = prob0_prob1(matrix, target)
        known = prob1.astype(np.float64)
        unknown = np.flatnonzero(~prob0 & ~prob1)
    else:
        unknown = np.flatnonzero(reachable_from(matrix.T.tocsr(), np.flatnonzero(target)) & ~target)
    k = int(np.searchsorted(unknown, initial))
    if k < unknown.size and unknown[k] == initial:
        labels = None if blocks is None else blocks[unknown]
        found = _unknown_value(
            matrix, dense, unknown, known, k, labels, extended_jump, elimination_rank
        )
    else:
        found = Bounded(float(known[initial]), 0.0)
    result = scale * min(max(found.value, 0.0), 1.0)
    # scaling the scores rounds each by u at most, and so their expectation; so does `scale *`
    rounding = (0.0 if scaled is None else 2 * UNIT_ROUNDOFF * scale) + UNIT_ROUNDOFF * result
    return Bounded(float(result), float(scale * found.error + rounding))


def _without_worthless_sinks(
    matrix: sp.csr_matrix, target: np.ndarray, value: np.ndarray
) -> np.ndarray:
    """``target`` without its states worth 0 that never leave (a monitor's alarm sink, a
    stopping state of weight 0): a run there scores 0 as a target or not, and left out they
    let the value be a plain reachability (:func:`prob0_prob1`: fewer unknowns)."""
    target = np.asarray(target, dtype=bool)
    worthless = target & (np.asarray(value, dtype=np.float64) == 0.0)
    if not worthless.any():
        return target
    states = np.flatnonzero(worthless)
    stays = matrix.diagonal()[states] == 1.0
    if not stays.any():
        return target
    kept = target.copy()
    kept[states[stays]] = False
    return kept


def _can_reach_dense(dense: np.ndarray, target: np.ndarray) -> np.ndarray:
    """States from which ``target`` is reachable (backward search over the dense edge mask)."""
    edges = dense > 0
    reach, frontier = target.copy(), target.copy()
    while frontier.any():
        frontier = edges[:, frontier].any(axis=1) & ~reach
        reach |= frontier
    return reach


def _unknown_value(
    matrix: sp.csr_matrix,
    dense: np.ndarray | None,
    unknown: np.ndarray,
    known: np.ndarray,
    k: int,
    labels: np.ndarray | None,
    extended_jump: bool = True,
    elimination_rank: np.ndarray | None = None,
) -> Bounded:
    """Value of unknown state ``unknown[k]``: ``x = Q x + R known`` on the unknown states.

    The forward system is solved for the values and for the expected time to leave at once
    (two right-hand sides, one factorisation), then :func:`_prove_forward` bounds the error.
    """
    m = unknown.size
    if dense is not None:
        rows_dense = dense[unknown]
        q_dense = rows_dense[:, unknown]
        system = np.eye(m) - q_dense
        rhs = np.column_stack([rows_dense @ known, np.ones(m)])
        # LAPACK's gesv again for each correction: tiny, and scipy's lu_solve stalls on BLAS
        # threads on a busy machine, however small the solve
        try:
            first = np.linalg.solve(system, rhs)
        except np.linalg.LinAlgError:
            return _singular_value(q_dense, rows_dense, unknown, known, k, extended_jump)
        return _prove_forward(
            q_dense,
            rows_dense,
            unknown,
            known,
            first,
            lambda r: np.linalg.solve(system, r),
            k,
            extended_jump,
        )
    rows = matrix[unknown]
    a = rows[:, unknown]
    if elimination_rank is not None:
        ranked = np.argsort(elimination_rank[unknown], kind="stable")
        lingering = _jump_chain_value(
            a, rows, unknown, known, k, extended_jump, ranked, min_steps=NO_PROOF_STEPS
        )
        if lingering is not None:
            return Bounded(lingering, np.inf)
    rhs = np.ones((m, 2), order="F")  # SuperLU's layout: no copy
    rhs[:, 0] = rows @ known
    solved: np.ndarray | None = None
    solve: Callable[[np.ndarray], np.ndarray | None] | None = None
    if m >= DIRECT_MAX_STATES:
        solved = _structured(a, rhs, labels)
        if solved is not None:
            solve = lambda r: _structured(a, r, labels)  # noqa: E731 (it accepted ``a``)
        elif lu_would_fill(a):
            start = np.zeros(m)
            start[k] = 1.0
            certified = solve_certified(a, start, transpose=True, states=False)
            if certified is not None:
                value = _dot(certified.x, rhs[:, 0])
                # rounding of the dot product and of each b_s (a row's sum), both at most 1
                longest = int(np.diff(rows.indptr).max(initial=0))
                error = certified.functional_error() + (m + longest) * UNIT_ROUNDOFF
                if tolerance.exact_enough(error, value):  # relative: a 1e-10 value too
                    return Bounded(value, error)
    order: np.ndarray | None = None
    if solved is None or solve is None:
        try:
            lu = factorise(a)
        except RuntimeError:  # exactly singular in doubles
            return _singular_value(a, rows, unknown, known, k, extended_jump)
        solved = lu.solve(rhs)
        solve = lu.solve
        order = _elimination_order(lu)
    return _prove_forward(a, rows, unknown, known, solved, solve, k, extended_jump, order)


def _singular_value(
    q: sp.spmatrix | np.ndarray,
    rows: sp.spmatrix | np.ndarray,
    unknown: np.ndarray,
    known: np.ndarray,
    k: int,
    extended: bool,
) -> Bounded:
    """``x[k]`` where ``I - Q`` is singular in doubles although every unknown state reaches
    the known ones: a row whose way out is below the doubles' resolution next to 1 (a
    self-loop of 1 - 5e-324 reads 1.0). The jump chain's value, unproven
    (:func:`_jump_chain_value`); a clear error where even that is not defined."""
    value = _jump_chain_value(sp.csr_matrix(q), rows, unknown, known, k, extended)
    if value is None:
        raise SolverError(
            "the chain's system is singular in double precision (a state leaves its "
            "cycle with a probability below the doubles' resolution next to 1); "
            "scale the model's probabilities"
        )
    return Bounded(value, np.inf)


def _elimination_order(lu: SuperLU) -> np.ndarray | None:
    """The states in the order the LU eliminated them, where it kept to one symmetric
    fill-reducing order (:func:`factorise`'s first choice): elimination without subtraction
    then fills about as little, far less than in the states' own order (docs/benchmarks.md)."""
    if not np.array_equal(lu.perm_r, lu.perm_c):
        return None
    return np.argsort(lu.perm_c)


def _prove_forward(
    q: sp.spmatrix | np.ndarray,
    rows: sp.spmatrix | np.ndarray,
    unknown: np.ndarray,
    known: np.ndarray,
    solved: np.ndarray,
    solve: Callable[[np.ndarray], np.ndarray | None],
    k: int,
    extended_jump: bool = True,
    order: np.ndarray | None = None,
) -> Bounded:
    """Proven error bound on ``x[k]``, refining ``x`` until it is at most :data:`EXACT_TOL`.

    ``solved`` holds ``x`` and ``t``, approximate solutions of ``(I - Q) x = R known`` and
    ``(I - Q) t = 1``; ``rows`` are the unknown states' full rows ``[Q R]`` (``q`` is ``Q``).
    With ``T`` a proven bound on the expected time to leave from ``k`` (:func:`_time_bound_at`,
    which also proves ``(I - Q)⁻¹ >= 0``), the error ``((I - Q)⁻¹ r)_k`` of ``x[k]`` is at most
    ``max|r| T``, with the residual ``r = rows @ z - x`` (``z``: ``known`` with ``x`` in place)
    bounded in exact arithmetic. The residual of a double ``x`` is no smaller than about ``u``,
    so on a chain absorbed after ``10^9`` steps the bound cannot get below about ``10^-7``:
    then ``x`` is refined (:func:`_refine`) as a double-double, residuals computed exactly
    (:mod:`misdirect.core.residual`) and corrections solved with the same factorisation, until
    the bound is small enough or stops falling (each round gains about a factor ``cond · u``).
    """
    x, t = solved[:, 0], solved[:, 1]
    if isinstance(rows, np.ndarray):
        gamma: np.ndarray | float = 1.01 * (rows.shape[1] + 2) * UNIT_ROUNDOFF
        lowest = rows.min(initial=0.0)
    else:
        gamma = 1.01 * (np.diff(rows.indptr) + 2) * UNIT_ROUNDOFF
        lowest = rows.data.min(initial=0.0)
    # γ per row: |fl(rows @ z - w) - (rows @ z - w)| <= γ (rows @ |z| + |w|) (Higham's bound
    # for a dot product of the row's length, in any order, plus one); Q's rows are shorter
    steps = np.inf if lowest < 0 else _time_bound_at(q, t, gamma, k)
    if not np.isfinite(steps):
        jump = _jump_chain_value(q, rows, unknown, known, k, extended_jump, order)
        return Bounded(float(x[k]) if jump is None else jump, np.inf)
    z = known.copy()
    z[unknown] = x
    rz = rows @ z
    floor = gamma * ((rz if (z >= 0).all() else rows @ np.abs(z)) + np.abs(x))
    error = float((np.abs(rz - x) + floor).max(initial=0.0) * steps)
    best = Bounded(float(x[k]), error)
    # small enough relative to the value itself: a decoy reached through a 1e-10 branch has
    # a value of 1e-10 and needs an error far below 1e-10 to be certified
    if tolerance.exact_enough(error, x[k]) or not np.isfinite(error):
        return best
    csr = sp.csr_matrix(rows)
    z_lo = np.zeros(known.size)

    def proven(hi: np.ndarray, lo: np.ndarray) -> tuple[np.ndarray, float]:
        z[unknown], z_lo[unknown] = hi, lo
        r, bound = residual.residual(csr, z, z_lo, unknown)
        return r, float(bound.max(initial=0.0) * steps + UNIT_ROUNDOFF * abs(hi[k] + lo[k]))

    refined, hi, lo = _refine(x, proven, solve, lambda hi, lo: float(hi[k] + lo[k]))
    best = best if best.error <= refined else Bounded(float(hi[k] + lo[k]), refined)
    if np.isfinite(best.error):
        return best
    jump = _jump_chain_value(q, rows, unknown, known, k, extended_jump, order)
    return best if jump is None else Bounded(jump, np.inf)


def _jump_chain_value(
    q: sp.spmatrix | np.ndarray,
    rows: sp.spmatrix | np.ndarray,
    unknown: np.ndarray,
    known: np.ndarray,
    k: int,
    extended: bool = True,
    order: np.ndarray | None = None,
    *,
    min_steps: float = 0.0,
) -> float | None:
    """``x[k]`` where nothing can be proven (a chain absorbed after more than about 10^14
    steps: LU's answer may be off in its first digit), by elimination without subtraction
    (:class:`~misdirect.core.elimination.Elimination`, double-double) on the *jump chain*:
    each state leaves by its other entries, its self-loop taken as what they leave. At that
    conditioning the doubles as loaded no longer fix the value (their rows sum to 1 within
    10^-16, which moves it by 0.1 on a chain absorbed after 10^15 steps), while the jump chain
    moves by a few units of roundoff per state when its entries do, so this is the value of
    the model whose probabilities the doubles round (on a drone, Storm's exact answer to all
    16 digits where LU said 1.0). Not proven: the caller keeps the error bound infinite. None
    where the chain is too large for the elimination, has a closed class or a negative
    entry. ``order``: the states in the order to eliminate them (a fill-reducing one saves
    work); ``min_steps``: None also where the jump chain's runs from ``unknown[k]`` take
    fewer steps on average (its expected time, from the same factors, without cancellation
    either). In doubles
    (``extended`` False) the same elimination rounds once per operation instead of about
    10^-32: it agrees to a few units of roundoff and runs several times faster."""
    m = unknown.size
    if not 0 < m <= elimination.MAX_STATES:
        return None
    csr = sp.csr_matrix(rows)
    if csr.data.min(initial=0.0) < 0:  # not a chain: no jump chain either
        return None
    outside = np.ones(csr.shape[1])
    outside[unknown] = 0.0
    leak = elimination.row_products(csr, outside)
    solver = elimination.Elimination(q, leak, extended=extended, order=order)
    if not solver.proper:
        return None
    if min_steps > 0:
        steps, steps_low = solver.solve((np.ones(m), np.zeros(m)))
        if not steps[k] + steps_low[k] >= min_steps:
            return None
    high, low = solver.solve(elimination.row_products(csr, known * outside))
    value = float(high[k] + low[k])
    return value if np.isfinite(value) else None


def _refine(
    x: np.ndarray,
    proven: Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, float]],
    solve: Callable[[np.ndarray], np.ndarray | None],
    value: Callable[[np.ndarray, np.ndarray], float] | None = None,
) -> tuple[float, np.ndarray, np.ndarray]:
    """Iterative refinement of ``x`` as a double-double ``hi + lo``: ``proven(hi, lo)`` gives
    the residual (computed exactly enough) and the error bound it proves, ``solve`` the
    correction. Stops once the bound is small enough (relative to ``value(hi, lo)``, by
    :func:`~misdirect.core.tolerance.exact_enough`; without ``value``, at most
    :data:`EXACT_TOL`), or when it no longer halves (``cond · u`` near 1), and returns the
    best bound with its ``hi`` and ``lo``."""
    hi, lo = x.copy(), np.zeros_like(x)
    best = (np.inf, hi, lo)
    previous = np.inf
    for _ in range(EXACT_ROUNDS):
        r, error = proven(hi, lo)
        if error < best[0]:
            best = (error, hi, lo)
        enough = (
            error <= EXACT_TOL if value is None else tolerance.exact_enough(error, value(hi, lo))
        )
        if enough or not error < 0.5 * previous:
            break
        previous = error
        correction = solve(r)
        if correction is None or not np.isfinite(correction).all():
            break
        hi, lo = residual.add(hi, lo, np.asarray(correction).reshape(hi.shape))
    return best


def _time_bound_at(
    q: sp.spmatrix | np.ndarray, t: np.ndarray, gamma: np.ndarray | float, k: int
) -> float:
    """A proven bound on ``((I - Q)⁻¹ 1)_k`` (expected steps before leaving, from ``k``) for a
    nonnegative ``Q``, from an approximate ``t``; ``inf`` when it cannot be proven.

    If ``t >= 0`` and ``(I - Q) t >= low > 0`` in exact arithmetic, ``I - Q`` is a non-singular
    M-matrix (so ``(I - Q)⁻¹ >= 0``), and ``t >= low (I - Q)⁻¹ 1``: the bound is ``t_k / low``.
    ``low`` is the least computed ``(I - Q) t`` less its rounding (``gamma`` per row, which
    covers ``Q``'s rows); the last factor covers the rounding of ``low`` and of the division.
    """
    if not (t >= 0).all():
        return np.inf
    qt = q @ t
    low = float((t - qt - gamma * (t + qt)).min(initial=np.inf))
    if not low > 0 or not np.isfinite(low):
        return np.inf
    return float(t[k] / low * (1 + tolerance.BOUND_MARGIN))  # a relative margin: scale-free


def reach_probabilities(
    matrix: sp.csr_matrix,
    target: np.ndarray,
    blocks: np.ndarray | None = None,
    value: np.ndarray | None = None,
) -> np.ndarray:
    """Probability of ever reaching ``target`` from every state (least fixed point).

    With ``value`` (a score per target state), the expected score of the first target state
    entered. ``blocks`` (e.g. the memory node of each product state) offers
    :func:`solve_chain` a separator to cut along.
    """
    scale, scaled = _scores(target, value)
    if scale == 0.0:
        return np.zeros(matrix.shape[0])
    if scaled is not None:
        return scale * _expected_scores(matrix, np.asarray(target, dtype=bool), scaled, blocks)
    return scale * _reach_all(matrix, target, blocks)


def _expected_scores(
    matrix: sp.csr_matrix, target: np.ndarray, scaled: np.ndarray, blocks: np.ndarray | None
) -> np.ndarray:
    """Expected score in ``[0, 1]`` of the first target state entered, from every state.

    Scores differ, so no state is known in advance to score 1: the unknowns are every state
    that can reach the target, outside it. From each of them the target stays reachable, so
    ``I - Q`` on them is non-singular and its solution is the least fixed point.
    """
    if matrix.shape[0] <= DENSE_MAX_STATES:
        return _reach_dense(matrix, target, scaled)
    values = scaled.copy()
    can_reach = reachable_from(matrix.T.tocsr(), np.flatnonzero(target))
    maybe = np.flatnonzero(can_reach & ~target)
    if maybe.size:
        rows = matrix[maybe]
        labels = None if blocks is None else blocks[maybe]
        values[maybe] = solve_chain(rows[:, maybe], rows @ scaled, labels)
    return cast(np.ndarray, np.clip(values, 0.0, 1.0))


def _reach_all(matrix: sp.csr_matrix, target: np.ndarray, blocks: np.ndarray | None) -> np.ndarray:
    if matrix.shape[0] <= DENSE_MAX_STATES:
        return _reach_dense(matrix, target)
    prob0, prob1 = prob0_prob1(matrix, target)
    values = prob1.astype(np.float64)
    maybe = np.flatnonzero(~prob0 & ~prob1)
    if maybe.size:
        rows = matrix[maybe]
        b = rows @ prob1.astype(np.float64)  # one step into the almost-sure states
        labels = None if blocks is None else blocks[maybe]
        values[maybe] = solve_chain(rows[:, maybe], b, labels)
    return np.clip(values, 0.0, 1.0)


def _reach_dense(
    matrix: sp.spmatrix, target: np.ndarray, scaled: np.ndarray | None = None
) -> np.ndarray:
    """:func:`reach_probabilities` for a tiny chain, with dense arrays (one LU, LAPACK).

    The states that can reach ``target`` (backward search over the dense edge mask) are
    exactly those with a positive value, and ``I - P`` restricted to them is non-singular:
    from each of them the target stays reachable, so no probability mass stays there forever.
    So no prob-1 search is needed, and the solve gives the least fixed point directly.
    """
    dense = matrix.toarray()
    target = np.asarray(target, dtype=bool)
    reach = _can_reach_dense(dense, target)
    values = target.astype(np.float64) if scaled is None else scaled.copy()
    maybe = np.flatnonzero(reach & ~target)
    if maybe.size:
        system = np.eye(maybe.size) - dense[np.ix_(maybe, maybe)]
        values[maybe] = np.linalg.solve(system, dense[maybe][:, target] @ values[target])
    return cast(np.ndarray, np.clip(values, 0.0, 1.0))


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
    # Proven bound on the error of every entry of ``entered`` and of any sum of them (``inf``
    # when none could be proven; ``0`` when nothing was solved). The visits are proven (to
    # VISITS_TOL relative to max(1, visits)) only when the iterative route solved it.
    error_bound: float = 0.0
    iterative: bool = False  # the certified iterative route solved it


def occupation(
    matrix: sp.csr_matrix,
    terminal: np.ndarray,
    initial: int,
    blocks: np.ndarray | None = None,
) -> Occupation:
    """Expected visits and first-entry distribution from ``initial``: one transposed solve.

    The occupation measure ``x = (I - Q)⁻ᵀ e_initial`` over the transient states gives both at
    once: ``x`` is the expected visits, and the first-entry probability of a non-transient
    state ``t`` is ``Σ_s x_s P(s, t)``, for every ``t`` together. Only states that can still
    reach a terminal state are transient, so ``I - Q`` is non-singular and states that cycle
    forever without one (trapped) are entered, not visited forever. The transposed system is
    solved like the forward one (:func:`solve_chain`'s routes; ``blocks`` offers a separator).
    """
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
    a = rows[:, inner]
    start = np.zeros(inner.size)
    start[np.searchsorted(inner, initial)] = 1.0
    y, error_bound, iterative = _occupation_measure(
        a, start, None if blocks is None else blocks[inner]
    )
    # visits are never negative: clipping moves each towards the truth, but a sum of them
    # weighted by probabilities may move by up to the mass clipped
    error_bound += float(np.maximum(-y, 0.0).sum())
    y = np.maximum(y, 0.0)
    visits[inner] = y
    entered = np.asarray(rows.T @ y).ravel()
    entered[inner] = 0.0
    return Occupation(visits, entered, transient, trapped, error_bound, iterative)


def _occupation_measure(
    a: sp.csr_matrix, start: np.ndarray, labels: np.ndarray | None
) -> tuple[np.ndarray, float, bool]:
    """``(I - a)⁻ᵀ start``, its proven error bound on absorption probabilities (``inf`` when
    none), and whether the iterative route solved it."""
    a_t = a.T.tocsr()
    solved: np.ndarray | None = None
    solve: Callable[[np.ndarray], np.ndarray | None] | None = None
    if a.shape[0] >= DIRECT_MAX_STATES:
        solved = _structured(a_t, start, labels)
        if solved is not None:
            solve = lambda r: _structured(a_t, r, labels)  # noqa: E731 (it accepted ``a_t``)
        elif lu_would_fill(a):
            certified = solve_certified(a, start, transpose=True, states=True)
            if certified is not None:
                rounding = a.shape[0] * UNIT_ROUNDOFF  # of summing x_s P(s, t), at most 1
                error = certified.functional_error() + rounding
                scale = np.maximum(1.0, np.abs(certified.x))
                # absorption probabilities out of a start of mass 1: their scale is that mass
                mass = float(np.abs(start).sum())
                visits_ok = (certified.state_error() <= tolerance.CERTIFY * scale).all()
                if tolerance.exact_enough(error, mass) and visits_ok:
                    return certified.x, error, True
    if solved is None or solve is None:
        lu = factorise(a)
        solved = cast(np.ndarray, lu.solve(start, trans="T"))
        solve = lambda r: lu.solve(r, trans="T")  # noqa: E731
    x, error = _prove_transposed(a_t, start, solved, solve)
    # summing x_s P(s, t) (at most 1) rounds by m u at most; so does storing hi + lo as x
    return x, error + (a.shape[0] + 2) * UNIT_ROUNDOFF, False


def _prove_transposed(
    a_t: sp.csr_matrix,
    start: np.ndarray,
    x: np.ndarray,
    solve: Callable[[np.ndarray], np.ndarray | None],
) -> tuple[np.ndarray, float]:
    """Proven bound on the absorption probabilities read off the occupation measure ``x``,
    refining ``x`` until it is at most :data:`EXACT_TOL`.

    With ``r = start - (I - Q)ᵀ x`` bounded in exact arithmetic, the error of ``cᵀx`` is
    ``rᵀ (I - Q)⁻¹ c``, at most ``Σ|r|`` for the ``c`` that matter (probabilities of leaving
    into a set of states; :meth:`Certified.functional_error`): no time bound is needed.
    Refined by :func:`_refine`, as the forward solve is.
    """
    gamma = 1.01 * (np.diff(a_t.indptr) + 2) * UNIT_ROUNDOFF  # as in _prove_forward
    magnitude = np.abs(x)
    r = start - x + a_t @ x
    floor = gamma * (np.abs(start) + magnitude + abs(a_t) @ magnitude)
    error = float((np.abs(r) + floor).sum())
    if error <= EXACT_TOL or not np.isfinite(error):
        return x, error
    own = np.arange(x.size)

    def proven(hi: np.ndarray, lo: np.ndarray) -> tuple[np.ndarray, float]:
        r, bound = residual.residual(a_t, hi, lo, own, start)
        return r, float(bound.sum())

    refined, hi, lo = _refine(x, proven, solve)
    return (x, error) if error <= refined else (hi + lo, refined)
