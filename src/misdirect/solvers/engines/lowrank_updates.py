"""Low-rank updates of one base chain: the Woodbury machinery of the enumeration.

A base chain (every inner sensor unaltered) is solved once for its value ``x0`` and for
``W = A⁻¹ E_R`` on the rows ``R`` that inner sensors may change (:func:`base_solve`). An
alteration replaces a few rows, and Sherman–Morrison–Woodbury gives its value at the start
from a system as small as the rows it changes:

    x'(q0) = x0(q0) + W(q0, C) (I − D W_C)⁻¹ (D x0 + Δb)

where ``D`` holds the row differences and ``Δb`` the differences in one-step decoy mass
(:class:`RowDeltas`). An alteration with several sensors borders the system of its parent
(itself without its last sensor), so it solves only the Schur complement on its last sensor's
rows (:func:`add_corrections`, a compiled loop that releases the GIL). :class:`Basis` keeps a
base with every option's row differences, so a subtree that fixes some sensors needs no solve.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import NamedTuple, cast

import numpy as np
import scipy.sparse as sp

from misdirect.core import tolerance
from misdirect.core.alterations import AlteredEntries, rank_in_group
from misdirect.core.blas import one_blas_thread
from misdirect.core.choice_product import ChoiceProduct
from misdirect.core.jit import njit
from misdirect.core.reachability import solve_chain, steps_bound
from misdirect.solvers.deadline import Deadline

BATCH_ENTRIES = 4_000_000  # numbers per batch of parents when threads share the batches
CACHED_BATCH_ENTRIES = 250_000  # ... and on one thread: a batch's gathers stay in cache while
# its children read them (on two threads the pool's overhead per batch outweighs that)
WIDEST_ENTRY = 16  # rows of one sensor's option, for sizing batches (1-18 on sensor grids)
DIRECT_CHUNK = 4096  # alterations valued on their whole systems between looks at the deadline
TREE_CHUNK = 4_000_000  # entries indexed between two looks at the deadline (about 0.3 s)


def base_solve(
    inside: sp.csr_matrix,
    to_target: np.ndarray,
    base_groups: np.ndarray,
    local: np.ndarray,
    live_node: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, float]:
    """``x0`` and ``W`` (the base chain's solution for ``b`` and for a unit column per inner
    row ``local``), as contiguous arrays (sparse @ dense copies a strided operand per call),
    and a proven bound on the chain's expected steps before leaving (its conditioning: how
    far every low-rank value built on it may be off, :func:`update_error`)."""
    rhs = np.zeros((inside.shape[1], 2 + local.size))
    rhs[:, 0] = to_target[base_groups]
    rhs[:, 1] = 1.0
    rhs[local, 2 + np.arange(local.size)] = 1.0
    chain = inside[base_groups]
    solved = solve_chain(chain, rhs, live_node)
    steps = steps_bound(chain, solved[:, 1])
    return np.ascontiguousarray(solved[:, 0]), np.ascontiguousarray(solved[:, 2:]), steps


def update_error(steps: float, scale: float) -> float:
    """How far a low-rank value on a base chain left after at most ``steps`` steps (expected,
    from any state) may be off, for values up to ``scale``: a double solve of a chain whose
    condition number is at most ``2 steps`` loses that many units of roundoff, and the
    Woodbury products about as many again (the ill-conditioned systems themselves are valued
    exactly, :data:`~misdirect.core.tolerance.ILL_CONDITIONED`)."""
    return 4 * tolerance.UNIT_ROUNDOFF * max(steps, 1.0) * scale


class Basis(NamedTuple):
    """A base chain (every sensor unaltered) solved for every row that may be altered, with
    the row differences of every option (:class:`RowDeltas`, over every inner choice): a chain
    that fixes some sensors' options needs no solve, nor any pass over the chain's states.
    Woodbury on the fixed sensors' rows updates the options' table in low rank.

    ``W`` (live states x inner rows, hundreds of MB on a big map) is kept only where rows of
    it are read on demand (:class:`BaseRows`: chains with end components); elsewhere the
    options' table and the start's row are all its blocks read."""

    x0: np.ndarray
    W: np.ndarray | None  # None where no rows are read on demand
    w_start: np.ndarray | None  # the start's row of ``W`` (None: the start is not live)
    options: RowDeltas
    steps: float  # a proven bound on its expected steps before leaving (:func:`base_solve`)

    @staticmethod
    def of(
        inside: sp.csr_matrix,
        to_target: np.ndarray,
        groups: np.ndarray,
        regions: Sequence[np.ndarray],
        option_groups: Sequence[np.ndarray],
        live_node: np.ndarray,
        start: int,
        *,
        keep_rows: bool,
    ) -> Basis:
        """``groups``: per live state, its group in the base; ``regions``: per inner choice,
        its live states (local indices); ``option_groups``: per inner choice, per state of its
        region its group under each option; ``start``: the start's live index (-1: not
        live); ``keep_rows``: whether to keep ``W`` whole (rows read on demand)."""
        local = np.concatenate([np.zeros(0, dtype=np.int64), *regions]).astype(np.int64)
        x0, W, steps = base_solve(inside, to_target, groups, local, live_node)
        options = row_deltas(list(option_groups), groups[local], inside, to_target, x0, W)
        w_start = W[start].copy() if start >= 0 else None
        return Basis(x0, W if keep_rows else None, w_start, options, steps)

    def with_fixed(
        self,
        fixed: Sequence[tuple[int, int]],
        inner: Sequence[int] | np.ndarray,
        start: int,
        *,
        one_entry: bool = False,
    ) -> tuple[float, np.ndarray | None, RowDeltas, BaseRows | None] | None:
        """(value at the start, its row of ``W``, options' table of the ``inner`` choices, its
        rows on demand where ``W`` is kept) of the chain whose choices ``fixed`` (position,
        option) take those options: with ``F`` their changed rows,
        ``Z = (I − D_F W_F)⁻¹ [D_F x0 + Δb_F, D_F W]``, every row difference ``D`` of an inner
        option gets ``D W' = D W + (D W_F) Z`` (and its right-hand side likewise) and the
        start's row ``W' = W + W_F Z``. None when that system is ill-conditioned
        (:data:`~misdirect.core.tolerance.ILL_CONDITIONED`): every value of the block would
        inherit its error, so the block's base is better solved anew.

        ``one_entry``: every alteration of the block takes one inner option at most, so its
        system reads ``D W'`` only on that option's own rows and their columns; only those
        entries are updated (the others are left 0: nothing reads them). A search's subtree one
        sensor short of its budget is such a block, and updating the whole table (every row
        slot by every inner row, thousands by thousands) cost it several times its
        enumeration."""
        table = self.options
        if fixed:
            changed = np.concatenate(
                [table.flat_start[j, k] + np.arange(table.flat_length[j, k]) for j, k in fixed]
            ).astype(np.int64)
        else:
            changed = np.zeros(0, dtype=np.int64)
        inner = np.asarray(inner, dtype=np.int64)
        flat_start, flat_length = table.flat_start[inner], table.flat_length[inner]
        unchanged = self._rows(np.zeros(0, dtype=np.int64), np.zeros((0, 0)))
        if start < 0:
            trimmed = table._replace(flat_start=flat_start, flat_length=flat_length)
            return 0.0, None, trimmed, unchanged
        x_start, w_start = float(self.x0[start]), self.w_start
        assert w_start is not None  # kept for a live start
        if not changed.size:
            trimmed = table._replace(flat_start=flat_start, flat_length=flat_length)
            return x_start, w_start, trimmed, unchanged
        own = table.column[changed]
        d_w = table.d_w[:, :-1]  # without the pad's column
        system = np.eye(changed.size) - d_w[np.ix_(changed, own)]
        with np.errstate(all="ignore"):
            if not np.linalg.cond(system, 1) <= tolerance.ILL_CONDITIONED:
                return None
        z = np.linalg.solve(system, np.column_stack([table.rhs[changed], d_w[changed]]))
        reach = d_w[:, own]  # D W_F for every row slot (the pad's: zero)
        if one_entry:
            updated_d_w = _own_blocks(table, flat_start, flat_length, reach, z[:, 1:])
        else:
            updated_d_w = table.d_w.copy()
            updated_d_w[:, :-1] += reach @ z[:, 1:]
        return (
            x_start + float(w_start[own] @ z[:, 0]),
            w_start + w_start[own] @ z[:, 1:],
            RowDeltas(
                flat_start,
                flat_length,
                table.column,
                table.rhs + reach @ z[:, 0],
                updated_d_w,
                table.group,
            ),
            self._rows(own, z),
        )

    def _rows(self, own: np.ndarray, z: np.ndarray) -> BaseRows | None:
        return None if self.W is None else BaseRows(self.x0, self.W, own, z)


def _own_blocks(
    table: RowDeltas,
    flat_start: np.ndarray,
    flat_length: np.ndarray,
    reach: np.ndarray,
    z: np.ndarray,
) -> np.ndarray:
    """``table.d_w + reach @ z`` on each option's own rows and their columns (every option
    of ``flat_start``/``flat_length``), 0 elsewhere (calloc'd: the pages never written cost
    nothing)."""
    starts, lengths = flat_start.ravel(), flat_length.ravel()
    starts, lengths = starts[lengths > 0], lengths[lengths > 0]
    pairs = lengths * lengths
    option = np.repeat(np.arange(starts.size), pairs)
    within = rank_in_group(pairs)
    row = starts[option] + within // lengths[option]
    column = table.column[starts[option] + within % lengths[option]]
    updated = np.zeros(table.d_w.shape)
    updated[row, column] = table.d_w[row, column] + np.einsum("pf,fp->p", reach[row], z[:, column])
    return updated


class BaseRows(NamedTuple):
    """A block base's ``x0`` and rows of ``W`` on demand: the kept basis's, updated by the
    Woodbury factor ``z`` of the fixed rows (columns ``own``) as :meth:`Basis.with_fixed`
    updates the start's row (``own`` empty: the basis itself, or a base solved for the block).
    Only the rows a trap empties are ever needed, so ``W'`` is never formed whole."""

    x0: np.ndarray
    W: np.ndarray
    own: np.ndarray
    z: np.ndarray

    def x(self, states: np.ndarray) -> np.ndarray:
        """``x0'`` at the live ``states`` (any shape)."""
        x = self.x0[states]
        if self.own.size:
            x = x + self.W[states[..., None], self.own] @ self.z[:, 0]
        return cast(np.ndarray, x)

    def w(self, states: np.ndarray, columns: np.ndarray) -> np.ndarray:
        """``W'(s, c)`` for each state ``s`` of ``states`` (n, k) and column ``c`` of its
        alteration's ``columns`` (n, k): (n, k, k); a column past ``W``'s (the pad's) reads 0."""
        width = self.W.shape[1]
        inside = columns < width
        clipped = np.where(inside, columns, 0)
        w = self.W[states[:, :, None], clipped[:, None, :]]
        if self.own.size:
            lift = self.W[states[..., None], self.own]  # (n, k, own)
            w = w + np.matmul(lift, self.z[:, 1:][:, clipped].transpose(1, 0, 2))
        return np.where(inside[:, None, :], w, 0.0)


class RowDeltas(NamedTuple):
    """The rows an inner option changes: per inner observation ``j`` and option ``k``, the
    rows of its region whose group differs from the base (``flat_length[j, k]`` of them, from
    ``flat_start[j, k]``), each with its ``D W``, its right-hand side ``D x0 + Δb`` and its
    column among the inner rows (``column``). Rows an option leaves alone have zero ``D`` and
    ``Δb``, so the Woodbury system needs only the changed ones. A last row slot pads batches:
    its row of ``D W`` and its right-hand side are zero, and so is its column (the last one of
    ``d_w``). ``group``: each slot's new group (what a trap search follows)."""

    flat_start: np.ndarray
    flat_length: np.ndarray
    column: np.ndarray
    rhs: np.ndarray
    d_w: np.ndarray
    group: np.ndarray

    def system(self, slots: np.ndarray) -> np.ndarray:
        """``F = I − D W`` on each row of row ``slots`` (n, k): (n, k, k)."""
        coupling = self.d_w[slots[:, :, None], self.column[slots][:, None, :]]
        return cast(np.ndarray, np.eye(slots.shape[1]) - coupling)


def row_deltas(
    groups: Sequence[np.ndarray],
    base_groups: np.ndarray,
    inside: sp.csr_matrix,
    to_target: np.ndarray,
    x0: np.ndarray,
    W: np.ndarray,
) -> RowDeltas:
    """``groups[j]``: per live row of inner observation ``j`` (in the order of the inner rows),
    its group under each option of ``j``; ``base_groups``: every inner row's group in the
    base."""
    n_options = max((g.shape[1] for g in groups), default=1)
    flat_start = np.zeros((len(groups), n_options), dtype=np.int64)
    flat_length = np.zeros((len(groups), n_options), dtype=np.int64)
    new_rows, old_rows, columns, offset, first = [], [], [], 0, 0
    for j, g in enumerate(groups):
        base = base_groups[first : first + g.shape[0]]
        for k in range(g.shape[1]):
            changed = np.flatnonzero(g[:, k] != base)
            flat_start[j, k], flat_length[j, k] = offset, changed.size
            offset += changed.size
            new_rows.append(g[changed, k])
            old_rows.append(base[changed])
            columns.append(first + changed)
        first += g.shape[0]
    pad = np.zeros(1, dtype=np.int64)
    new_g = np.concatenate([*new_rows, pad]).astype(np.int64)
    old_g = np.concatenate([*old_rows, pad]).astype(np.int64)
    delta = inside[new_g] - inside[old_g]  # the pad row: a group minus itself, zero
    d_w = np.zeros((new_g.size, W.shape[1] + 1))
    d_w[:, :-1] = delta @ W  # the last column, the pad's, stays zero
    return RowDeltas(
        flat_start,
        flat_length,
        np.concatenate([*columns, [W.shape[1]]]).astype(np.int64),
        np.asarray(delta @ x0).ravel() + (to_target[new_g] - to_target[old_g]),
        d_w,
        new_g,
    )


def add_corrections(
    found: np.ndarray,
    altered: AlteredEntries,
    deltas: RowDeltas,
    w_start: np.ndarray,
    deadline: Deadline | None = None,
    chunk_entries: int | None = None,
    threads: int = 1,
    compiled: bool = True,
) -> np.ndarray:
    """Add the Woodbury correction to ``found`` for every alteration of ``altered`` (its
    choices are the inner observations); returns which got it (all, unless ``deadline`` passed
    first). ``compiled``: each child's step by the numba loop, else by its numpy twin (the
    loop's first call in a process loads numba's compiler, a cost a small run never repays).

    An alteration is its parent (the same without its last entry) bordered by one entry's
    rows. Per batch of parents, each parent's system ``A`` is inverted once, with
    ``G = A⁻¹ F(P, ·)`` (its coupling to every later row, one matrix product); each child then
    solves only the Schur complement on its last entry's rows (:func:`_children_of`), a system
    as wide as one sensor's region instead of all its sensors'. Parents go by number of entries,
    so a run cut short by the deadline has finished the smaller alterations, whose budgets stay
    proven.
    """
    if chunk_entries is None:
        chunk_entries = BATCH_ENTRIES if threads > 1 else CACHED_BATCH_ENTRIES
    n = altered.costs.size
    corrected = np.zeros(n, dtype=bool)
    corrected[altered.parent < 0] = True  # the unaltered one: the base value

    def expired() -> bool:
        return deadline is not None and deadline.expired()

    if expired():
        return corrected  # each step of the set-up takes seconds on ten million alterations
    tree = _Tree.of(altered, deltas, expired)
    if tree is None or expired():
        return corrected
    weight = np.append(w_start, 0.0)[deltas.column]  # per row slot; the pad's is 0
    parents, first_child, n_children = np.unique(
        altered.parent[altered.parent >= 0], return_index=True, return_counts=True
    )
    first_child += 1  # children are numbered after the unaltered alteration, by parent
    order = np.lexsort((tree.width[parents], tree.depth[parents]))
    if expired():
        return corrected

    def run(batch: np.ndarray) -> None:
        if expired():
            return
        counts = n_children[batch]
        kids = np.repeat(first_child[batch], counts) + rank_in_group(counts)
        local = np.repeat(np.arange(batch.size), counts)
        found[kids] += _children_of(parents[batch], kids, local, tree, deltas, weight, compiled)
        corrected[kids] = True  # batches are disjoint: threads never write the same entry

    n_slots = deltas.rhs.size - 1
    batches = list(_batches(order, tree.width[parents], n_children, n_slots, chunk_entries))
    # each batch's products are small: OpenBLAS's own threads would only spin beside ours
    with one_blas_thread():
        # the numpy twin holds the GIL: a second thread would only wait for it
        if threads == 1 or len(batches) == 1 or not compiled:
            for batch in batches:
                run(batch)
        else:  # taken in order, so a cut-short run has still done the smallest alterations
            with ThreadPoolExecutor(max_workers=threads) as pool:
                list(pool.map(run, batches))  # LAPACK and numpy's gathers release the GIL
    # bordered on an ill-conditioned parent (or Schur complement): each on its own system
    ill = np.flatnonzero(corrected & np.isnan(found))
    if ill.size:
        unaltered = float(found[np.flatnonzero(altered.parent < 0)[0]])  # the base value
        direct, done = _direct_corrections(ill, tree, deltas, weight, deadline)
        found[ill] = unaltered + direct
        corrected[ill[~done]] = False  # left by the deadline
    return corrected


def _direct_corrections(
    alterations: np.ndarray,
    tree: _Tree,
    deltas: RowDeltas,
    weight: np.ndarray,
    deadline: Deadline | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """(corrections, done) of ``alterations``, each from its own whole system rather than
    bordered on its parent's; NaN where that system is ill-conditioned
    (:data:`~misdirect.core.tolerance.ILL_CONDITIONED`: the caller values those exactly).
    A chunk at a time, between looks at ``deadline``: on a map of tiny probabilities most
    deep alterations come here, a large part of a run's time (docs/benchmarks.md);
    ``done`` says which the deadline left."""
    pad = deltas.rhs.size - 1
    out = np.full(alterations.size, np.nan)
    done = np.zeros(alterations.size, dtype=bool)
    width = tree.width[alterations]
    for w in np.unique(width):
        same = np.flatnonzero(width == w)
        for lo in range(0, same.size, DIRECT_CHUNK):
            if deadline is not None and deadline.expired():
                return out, done
            pick = same[lo : lo + DIRECT_CHUNK]
            done[pick] = True
            slots = tree.slots(alterations[pick], pad)
            z, ill = solved_and_conditioned(deltas.system(slots), deltas.rhs[slots])
            fine = ~ill
            out[pick[fine]] = np.einsum("ni,ni->n", weight[slots[fine]], z[fine])
    return out, done


def solved_and_conditioned(system: np.ndarray, rhs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per system of a stack: its solution for its ``rhs`` and whether it is ill-conditioned
    (1-norm condition number above :data:`~misdirect.core.tolerance.ILL_CONDITIONED`, or
    singular; its solution is then NaN), from one inverse each: the condition number needs
    the inverse anyway (numpy's ``cond`` inverts too), and a solve besides cost a fifth of a
    drone's enumeration. One singular system makes numpy's ``inv`` raise for the stack: then
    only those whose condition number, computed one by one, is fine are inverted."""
    with np.errstate(all="ignore"):
        try:
            inverse = np.linalg.inv(system)
        except np.linalg.LinAlgError:
            fine = np.linalg.cond(system, 1) <= tolerance.ILL_CONDITIONED
            inverse = np.full_like(system, np.nan)
            if fine.any():
                inverse[fine] = np.linalg.inv(system[fine])
        conditioned = _norm1(system) * _norm1(inverse)
        z = np.einsum("nij,nj->ni", inverse, rhs)
    ill = ~(conditioned <= tolerance.ILL_CONDITIONED)
    return np.where(ill[:, None], np.nan, z), ill


class _Tree(NamedTuple):
    """Per alteration, its number of entries, of changed rows (``width``) and its first entry;
    per entry, its row slots."""

    depth: np.ndarray
    width: np.ndarray
    first_entry: np.ndarray
    entry_slot: np.ndarray  # per entry: its first row slot
    entry_width: np.ndarray  # per entry: its number of row slots

    @staticmethod
    def of(
        altered: AlteredEntries, deltas: RowDeltas, expired: Callable[[], bool] | None = None
    ) -> _Tree | None:
        """The tree of ``altered``, a chunk of :data:`TREE_CHUNK` entries at a time with a
        look at ``expired`` between two (None once it says so: tens of millions of entries take
        seconds)."""
        n, n_entries = altered.costs.size, altered.alteration.size
        depth = np.zeros(n, dtype=np.int64)
        width = np.zeros(n, dtype=np.int64)
        entry_slot = np.empty(n_entries, dtype=deltas.flat_start.dtype)
        entry_width = np.empty(n_entries, dtype=deltas.flat_length.dtype)
        starts, lengths = deltas.flat_start.ravel(), deltas.flat_length.ravel()
        for lo in range(0, n_entries, TREE_CHUNK):
            if lo and expired is not None and expired():
                return None
            hi = min(lo + TREE_CHUNK, n_entries)
            # one flat index per entry, read twice
            flat = altered.choice[lo:hi] * deltas.flat_length.shape[1] + altered.option[lo:hi]
            entry_slot[lo:hi] = starts[flat]
            entry_width[lo:hi] = lengths[flat]
            # entries are grouped by alteration, in order: a chunk's alterations are a range
            owner = altered.alteration[lo:hi]
            first, last = int(owner[0]), int(owner[-1])
            depth[first : last + 1] += np.bincount(owner - first)
            width[first : last + 1] += np.bincount(
                owner - first, weights=entry_width[lo:hi]
            ).astype(np.int64)
        # each alteration's entries start where the last one's ended
        first_entry = np.zeros(n, dtype=np.int64)
        np.cumsum(depth[:-1], out=first_entry[1:])
        return _Tree(depth, width, first_entry, entry_slot, entry_width)

    def slots(self, alterations: np.ndarray, pad: int) -> np.ndarray:
        """(alterations, widest) row slots of each alteration's entries, padded with ``pad``."""
        counts = self.depth[alterations]
        entries = np.repeat(self.first_entry[alterations], counts) + rank_in_group(counts)
        rows_in = self.entry_width[entries]
        owner = np.repeat(np.repeat(np.arange(alterations.size), counts), rows_in)
        widths = self.width[alterations]
        slots = np.full((alterations.size, int(widths.max(initial=0))), pad, dtype=np.int64)
        slots[owner, rank_in_group(widths)] = np.repeat(
            self.entry_slot[entries], rows_in
        ) + rank_in_group(rows_in)
        return slots


def _batches(
    order: np.ndarray, width: np.ndarray, n_children: np.ndarray, n_slots: int, chunk_entries: int
) -> Iterator[np.ndarray]:
    """Consecutive slices of the parents in ``order`` holding about ``chunk_entries`` numbers
    (per parent: ``G``, its width times the row slots, and its children's blocks, its width
    times theirs, at most ``WIDEST_ENTRY``); a slice stops before a parent over 1.5 times as
    wide as its first, to keep the padding small."""
    position = 0
    while position < order.size:
        widest = max(int(width[order[position]]), 1)
        cost = np.cumsum(widest * (n_slots + WIDEST_ENTRY * n_children[order[position:]]))
        size = max(1, int(np.searchsorted(cost, chunk_entries, side="right")))
        batch = order[position : position + size]
        wider = np.flatnonzero(width[batch] * 2 > widest * 3)
        if wider.size:
            batch = batch[: max(1, wider[0])]
        position += batch.size
        yield batch


def _children_of(
    parents: np.ndarray,
    kids: np.ndarray,
    local: np.ndarray,
    tree: _Tree,
    deltas: RowDeltas,
    weight: np.ndarray,
    compiled: bool = True,
) -> np.ndarray:
    """The corrections of the alterations ``kids``, each the parent ``parents[local]`` plus its
    last entry, by the Schur complement of the parent's system ``A`` (rows ``P``):

        s = s_P + (g_E − Yᵀ g_P)ᵀ S⁻¹ (r_E − F_EP y),   Y = A⁻¹ F_PE,   S = F_EE − F_EP Y,

    with ``y = A⁻¹ r_P`` and ``s_P = g_Pᵀ y`` the parent's own correction, ``F = I − D W`` on
    the changed rows, ``r = D x0 + Δb`` and ``g`` the start's row of ``W``. The parents' part
    is batched in numpy; each child's (a few small products and a solve as wide as its last
    entry) is one compiled loop, :func:`_schur_corrections` (with ``compiled`` false, its numpy
    twin :func:`_schur_corrections_numpy`)."""
    rhs = deltas.rhs
    pad = rhs.size - 1
    slots_p = tree.slots(parents, pad)
    system = deltas.system(slots_p)
    inverse = np.linalg.inv(system) if slots_p.shape[1] else system
    y = np.einsum("pij,pj->pi", inverse, rhs[slots_p])
    # each parent's condition number (1-norm; a parent without rows: 1), for its children's
    conditioned = _norm1(system) * _norm1(inverse) if slots_p.shape[1] else np.ones(parents.size)
    s_p = np.einsum("pi,pi->p", weight[slots_p], y)
    last = tree.first_entry[kids] + tree.depth[kids] - 1
    first = tree.entry_slot[last].astype(np.int64)
    begin = int(first.min(initial=pad))
    # A⁻¹ D W(P, c) for every column c of a later slot (a child's entry comes after its
    # parent's, so deep parents need few). Per column, not per slot: the options of one sensor
    # share their rows' columns, and later slots' columns form one range, so the gather is a
    # slice of each parent row. Both operands contiguous, so each product of the stack is one
    # BLAS call (their transposes made numpy fall back to its own loop, 2x slower)
    later = deltas.column[begin:pad]
    low, high = int(later.min(initial=0)), int(later.max(initial=-1)) + 1
    gathered = deltas.d_w[slots_p.reshape(-1), low:high]
    gathered = gathered.reshape(parents.size, slots_p.shape[1], high - low)
    out = np.empty(kids.size)
    (_schur_corrections if compiled else _schur_corrections_numpy)(
        slots_p,
        np.matmul(inverse, gathered),
        low,
        y,
        s_p,
        local.astype(np.int64),
        first,
        tree.entry_width[last].astype(np.int64),
        deltas.d_w,
        deltas.column,
        rhs,
        weight,
        conditioned,  # NaN (a singular parent) reads as ill-conditioned there
        tolerance.ILL_CONDITIONED,
        out,
    )
    return out


def _norm1(matrices: np.ndarray) -> np.ndarray:
    """The 1-norm (largest column sum of magnitudes) of each matrix of a stack."""
    return cast(np.ndarray, np.abs(matrices).sum(axis=1).max(axis=1, initial=0.0))


@njit(cache=True, nogil=True, fastmath={"reassoc", "contract"})
def _schur_corrections(
    slots_p: np.ndarray,
    reach: np.ndarray,
    low: int,
    y: np.ndarray,
    s_p: np.ndarray,
    local: np.ndarray,
    first: np.ndarray,
    width: np.ndarray,
    d_w: np.ndarray,
    column: np.ndarray,
    rhs: np.ndarray,
    weight: np.ndarray,
    conditioned: np.ndarray,
    limit: float,
    out: np.ndarray,
) -> None:  # pragma: no cover (compiled; its results are tested against dense solves)
    """Per child ``c`` (parent ``p = local[c]``, last entry's slots ``first[c]`` onwards,
    ``width[c]`` of them): ``out[c] = s_P + grad · S⁻¹ right`` of :func:`_children_of`. With
    ``reach[p]`` the columns ``A⁻¹ D W(P, c)`` of the columns ``c`` from ``low`` on,
    ``Y = A⁻¹ F_PE = −G`` for ``G = reach[p][:, column(E) − low]``, so the signs cancel:
    ``S = F_EE − D W(E, P) G``. Padded parent slots have zero
    rows, columns and weights.

    A child whose system is ill-conditioned gets NaN (valued exactly by the caller): its
    estimate is the parent's condition number (``conditioned[p]``) times ``S``'s, estimated as
    its 1-norm over its smallest pivot (within a factor ``w`` of the true one), above
    ``limit``."""
    wp = slots_p.shape[1]
    widest = max(1, width.max()) if width.size else 1
    g = np.empty((widest, wp))  # Gᵀ = (A⁻¹ D W(P, E))ᵀ, one row per slot of E
    g_weight = np.empty(widest)  # G's columns times the parent's weights
    row_p = np.empty(wp)  # D W(i, P) of one row i of E
    columns_p = np.empty(wp, dtype=np.int64)
    weight_p = np.empty(wp)
    columns_e = np.full(widest, -1, dtype=np.int64)  # the columns G was gathered for
    schur = np.empty((widest, widest))
    right = np.empty(widest)
    grad = np.empty(widest)
    parent = -1
    for c in range(local.size):
        p = local[c]
        w = width[c]
        f = first[c]
        total = s_p[p]
        if w == 0:
            out[c] = total if conditioned[p] <= limit else np.nan
            continue
        if p != parent:  # children come grouped by parent
            parent = p
            for j in range(wp):
                columns_p[j] = column[slots_p[p, j]]
                weight_p[j] = weight[slots_p[p, j]]
            columns_e[:] = -1
        # the options of one sensor share their rows' columns, so siblings share G: gathered
        # again only where the columns differ
        for e in range(w):
            if columns_e[e] != column[f + e]:
                columns_e[e] = column[f + e]
                h = 0.0
                for j in range(wp):
                    g[e, j] = reach[p, j, column[f + e] - low]
                    h += g[e, j] * weight_p[j]
                g_weight[e] = h
        for i in range(w):
            row = f + i
            r = rhs[row]
            for j in range(wp):
                row_p[j] = d_w[row, columns_p[j]]
                r += row_p[j] * y[p, j]
            right[i] = r
            grad[i] = weight[row] + g_weight[i]
            for e in range(w):
                v = -d_w[row, column[f + e]]
                if i == e:
                    v += 1.0
                for j in range(wp):
                    v -= row_p[j] * g[e, j]
                schur[i, e] = v
        size = 0.0  # S's 1-norm, before elimination
        for e in range(w):
            column_sum = 0.0
            for i in range(w):
                column_sum += abs(schur[i, e])
            size = max(size, column_sum)
        # Gaussian elimination with partial pivoting: S z = right
        for k in range(w):
            pivot = k
            for i in range(k + 1, w):
                if abs(schur[i, k]) > abs(schur[pivot, k]):
                    pivot = i
            if pivot != k:
                for e in range(w):
                    schur[k, e], schur[pivot, e] = schur[pivot, e], schur[k, e]
                right[k], right[pivot] = right[pivot], right[k]
            for i in range(k + 1, w):
                factor = schur[i, k] / schur[k, k]
                for e in range(k, w):
                    schur[i, e] -= factor * schur[k, e]
                right[i] -= factor * right[k]
        smallest = np.inf
        for k in range(w):
            smallest = min(smallest, abs(schur[k, k]))
        if not conditioned[p] * size <= limit * smallest:  # NaN-safe: also a zero pivot
            out[c] = np.nan
            continue
        for k in range(w - 1, -1, -1):
            acc = right[k]
            for e in range(k + 1, w):
                acc -= schur[k, e] * right[e]
            right[k] = acc / schur[k, k]
        for i in range(w):
            total += grad[i] * right[i]
        out[c] = total


def _schur_corrections_numpy(
    slots_p: np.ndarray,
    reach: np.ndarray,
    low: int,
    y: np.ndarray,
    s_p: np.ndarray,
    local: np.ndarray,
    first: np.ndarray,
    width: np.ndarray,
    d_w: np.ndarray,
    column: np.ndarray,
    rhs: np.ndarray,
    weight: np.ndarray,
    conditioned: np.ndarray,
    limit: float,
    out: np.ndarray,
) -> None:
    """:func:`_schur_corrections` batched in numpy, the children grouped by the width of their
    last entry (each group's Schur complements solved at once; ``S``'s condition number
    computed, not estimated)."""
    out[:] = np.where(conditioned[local] <= limit, s_p[local], np.nan)  # no row changed
    columns_p, weight_p = column[slots_p], weight[slots_p]
    for w in np.unique(width[width > 0]):
        pick = np.flatnonzero(width == w)
        p = local[pick]
        rows = first[pick, None] + np.arange(w)  # an entry's slots are consecutive
        g = reach[p[:, None], :, column[rows] - low]  # Gᵀ, (children, w, wp)
        row_p = d_w[rows[:, :, None], columns_p[p][:, None, :]]  # D W(E, P)
        schur = np.eye(w) - d_w[rows[:, :, None], column[rows][:, None, :]]
        schur -= np.matmul(row_p, np.swapaxes(g, 1, 2))
        right = rhs[rows] + np.einsum("nij,nj->ni", row_p, y[p])
        grad = weight[rows] + np.einsum("nij,nj->ni", g, weight_p[p])
        with np.errstate(all="ignore"):
            z = np.linalg.solve(schur, right[..., None])[..., 0]
            ill = ~(conditioned[p] * np.linalg.cond(schur, 1) <= limit)
        out[pick] = np.where(ill, np.nan, out[pick] + np.einsum("ni,ni->n", grad, z))


def selected_groups(chain: ChoiceProduct, live: np.ndarray, chosen: np.ndarray) -> np.ndarray:
    """Group of every live state when the options in ``chosen`` are taken."""
    picked = chain.groups_taking(chosen)[np.flatnonzero(live)]
    if (picked < 0).any():
        raise AssertionError("a live state has no selected group")
    return picked


TRAP_BATCH_ENTRIES = 1_000_000  # numbers of the Woodbury systems solved in one batch


def flagged_values(
    table: RowDeltas,
    rows: BaseRows,
    w_start: np.ndarray,
    start: int,
    changed: tuple[np.ndarray, np.ndarray, np.ndarray],
    emptied: np.ndarray,
    count: int,
    deadline: Deadline | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Values at the live ``start`` of ``count`` alterations, each by its own Woodbury system
    (not bordered on a parent's, which may be singular): ``changed`` lists their rows (owner
    alteration, row slot of ``table``, live state), and the rows ``emptied`` marks can no
    longer reach the decoy (a trap search found them; each new closed class holds one).

    Emptied, a row reads ``x(t) = 0``: against the base its difference is ``D = −P(t)``, and as
    ``(I − P) W = E`` and ``(I − P) x0 = b`` on the base, ``D W = e_t − W(t)`` and
    ``D x0 + Δb = −x0(t)``. Its row of ``I − D W`` is then ``W(t)`` on the system's columns
    (no cancellation), read from :class:`BaseRows`. With a row of every new closed class
    emptied, the system is non-singular, and its solution the least fixed point.

    Returns (values, reached): alterations not reached were cut by ``deadline``; a reached one
    whose value is NaN had a singular or ill-conditioned system (:data:`~misdirect.core.
    tolerance.ILL_CONDITIONED`) and needs an exact solve."""
    values = np.full(count, np.nan)
    reached = np.zeros(count, dtype=bool)
    owner, slots, states = changed
    by_owner = np.argsort(owner, kind="stable")
    slots, states, emptied = slots[by_owner], states[by_owner], emptied[by_owner]
    width = np.bincount(owner, minlength=count)
    first = np.concatenate([[0], np.cumsum(width)])[:-1]
    pad = table.rhs.size - 1  # the pad slot: zero row, zero right-hand side, the pad column
    weight = np.append(w_start, 0.0)  # W(q0, ·) with the pad's column
    x_start = float(rows.x(np.array([start]))[0])
    order = np.argsort(width, kind="stable")
    position = 0
    while position < order.size:
        if deadline is not None and deadline.expired():
            break
        widest = max(int(width[order[position]]), 1)
        batch = order[position : position + max(1, TRAP_BATCH_ENTRIES // widest**2)]
        batch = batch[width[batch] * 2 <= widest * 3 + 1]  # a prefix (by width): small padding
        position += batch.size
        reached[batch] = True
        wide = int(width[batch].max(initial=1))
        place = (np.repeat(np.arange(batch.size), width[batch]), rank_in_group(width[batch]))
        entries = np.repeat(first[batch], width[batch]) + rank_in_group(width[batch])
        slot = np.full((batch.size, wide), pad, dtype=np.int64)
        slot[place] = slots[entries]
        state = np.zeros((batch.size, wide), dtype=np.int64)
        state[place] = states[entries]
        empty = np.zeros((batch.size, wide), dtype=bool)
        empty[place] = emptied[entries]
        column = table.column[slot]
        system = np.eye(wide) - table.d_w[slot[:, :, None], column[:, None, :]]
        rhs = table.rhs[slot]
        if empty.any():
            system = np.where(empty[:, :, None], rows.w(state, column), system)
            rhs = np.where(empty, -rows.x(state), rhs)
        z, _ = solved_and_conditioned(system, rhs)  # ill ones: NaN, solved by the caller
        values[batch] = x_start + np.einsum("ni,ni->n", weight[column], z)
    return values, reached
