"""Exact reachability analysis of a finite Markov chain (Baier & Katoen, ch. 10).

Graph precomputation first (states that cannot reach the target get 0, states that reach it
almost surely get 1), then one sparse LU solve on the remaining states. Removing the
probability-0 states is what makes the answer the *least* fixed point (SPEC §1) and the
linear system non-singular.
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import SuperLU, splu

from misdirect.model import reachable_from


def _without_rows(matrix: sp.csr_matrix, rows: np.ndarray) -> sp.csr_matrix:
    """Copy of ``matrix`` with the out-edges of the masked rows removed."""
    kept = (sp.diags((~rows).astype(np.float64)) @ matrix).tocsr()
    kept.eliminate_zeros()
    return kept


def prob0_prob1(matrix: sp.csr_matrix, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Masks of states reaching ``target`` with probability exactly 0 and exactly 1."""
    backward = matrix.T.tocsr()
    prob0 = ~reachable_from(backward, np.flatnonzero(target))
    # A state misses the target with positive probability iff it can reach a prob-0 state
    # along a path that does not pass through the target.
    can_miss = reachable_from(_without_rows(matrix, target).T.tocsr(), np.flatnonzero(prob0))
    return prob0, ~can_miss


PARALLEL_MIN_STATES = 5_000  # below this one factorisation is faster than threads
SEPARATOR_MAX = 512  # block elimination only pays with a small separator


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


def solve_by_blocks(a: sp.spmatrix, b: np.ndarray, labels: np.ndarray) -> np.ndarray | None:
    """Solve ``(I - a) x = b`` by block elimination along ``labels``, blocks in parallel.

    The product chain of a controller that rarely changes its memory node splits by node:
    only the states that read a memory-changing observation have transitions into another
    node's block. Those states form the separator ``S``; the rest is block-diagonal by label.
    Each block is factorised in its own thread (SuperLU releases the GIL), then the small
    Schur complement on ``S`` gives ``x_S`` and back-substitution the rest. Every principal
    submatrix and Schur complement of the non-singular M-matrix ``I - a`` is again one, so
    no step can break down. ``None`` when the split would not pay.
    """
    n = a.shape[0]
    coo = sp.coo_matrix(a)
    crossing = labels[coo.row] != labels[coo.col]
    separator = np.zeros(n, dtype=bool)
    separator[coo.row[crossing]] = True  # every edge between blocks starts in S
    interior = [np.flatnonzero(~separator & (labels == k)) for k in np.unique(labels[~separator])]
    if separator.sum() > SEPARATOR_MAX or len(interior) < 2:
        return None
    system = (sp.identity(n, format="csr") - sp.csr_matrix(a)).tocsr()
    border = np.flatnonzero(separator)
    border_rows = system[border]

    def eliminate(block: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        rows = system[block]
        lu = _lu(rows[:, block])
        coupling = rows[:, border].toarray()
        y_coupling = lu.solve(coupling) if border.size else coupling
        return y_coupling, lu.solve(b[block])

    workers = min(len(interior), os.cpu_count() or 1)
    with ThreadPoolExecutor(max_workers=workers) as pool:
        parts = list(pool.map(eliminate, interior))
    schur = border_rows[:, border].toarray()
    rhs = b[border].astype(np.float64)
    for block, (y_coupling, y) in zip(interior, parts, strict=True):
        to_block = border_rows[:, block]
        schur -= to_block @ y_coupling
        rhs -= to_block @ y
    x = np.empty(n)
    x_border = np.linalg.solve(schur, rhs) if border.size else rhs
    x[border] = x_border
    for block, (y_coupling, y) in zip(interior, parts, strict=True):
        x[block] = y - y_coupling @ x_border
    return x


def reach_probabilities(
    matrix: sp.csr_matrix, target: np.ndarray, blocks: np.ndarray | None = None
) -> np.ndarray:
    """Probability of ever reaching ``target`` from every state (least fixed point).

    ``blocks`` (e.g. the memory node of each product state) lets large systems be solved by
    :func:`solve_by_blocks`.
    """
    prob0, prob1 = prob0_prob1(matrix, target)
    values = prob1.astype(np.float64)
    maybe = np.flatnonzero(~prob0 & ~prob1)
    if maybe.size:
        rows = matrix[maybe]
        b = np.asarray(rows[:, np.flatnonzero(prob1)].sum(axis=1)).ravel()
        inner = rows[:, maybe]
        solved = None
        if blocks is not None and maybe.size >= PARALLEL_MIN_STATES:
            solved = solve_by_blocks(inner, b, blocks[maybe])
        values[maybe] = _solve(inner, b) if solved is None else solved
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
