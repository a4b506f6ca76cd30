"""Closed classes of a base chain, and which altered rows provably keep them: what makes the
low-rank enumeration exact on chains with end components.

Where the choice product has end components, some alteration may trap the robot in a closed
class of live states (it cycles there forever, never reaching the decoy). There ``I − P`` is
singular: a low-rank update of a base solve would divide by zero, or by rounding noise.

Within one block of the enumeration (its outer choices fixed, the inner ones enumerated), an
alteration changes only the rows of inner observations. Two facts decide what it does to the
closed classes:

* a class closed under the base chain stays closed unless one of its rows changes, and its
  values are 0 under every alteration that leaves it alone: the base solve fixes them to 0
  (:attr:`ClosedClasses.closed`, an empty row each), and the system on the other live states
  is non-singular;
* a new closed class needs a changed row whose successors all lie in it. A state is *safe* if
  it leaves the live states with positive probability under every alteration of the block,
  even one that picks inner options state by state (:attr:`ClosedClasses.safe`, the
  complement of the largest set such a choice can keep the run in): it lies in no closed
  class. A changed row with a safe successor, or whose mass partly leaves the live states, is
  in no closed class either.

So an alteration whose changed rows all have a safe successor (or leak) and avoid the base's
closed classes has exactly the base's closed classes: its low-rank value is the least fixed
point. Options that miss this test are *unsafe* (:func:`unsafe_options`); the alterations
using them are searched for a trap (:func:`closing_alterations`). One that closes a class has
a changed row in each new class; emptying the changed rows the search found trapped (value
0, which they have) leaves the base's closed classes only, so its low-rank update of the
base is again the least fixed point. One that changes a row of a base closed class may open
it, and is valued exactly, one chain each.

:class:`TrapSearch` asks these questions for the low-rank enumeration
(:mod:`misdirect.solvers.engines.lowrank`): a base's closed classes and unsafe options, whether
a kept basis with some options fixed keeps its classes, and which of a block's alterations
the batch must leave out (:class:`Trap`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple, cast

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components, shortest_path

from misdirect.core.alterations import AlteredEntries, rank_in_group
from misdirect.core.jit import njit
from misdirect.core.model import reachable_from, with_super_source
from misdirect.solvers.deadline import Deadline
from misdirect.solvers.engines.lowrank_updates import RowDeltas


@dataclass(frozen=True)
class ClosedClasses:
    """The closed classes of one base chain over the live states, and its safe states."""

    closed: np.ndarray  # per live state: in a class the base chain never leaves (value 0)
    safe: np.ndarray  # per live state: may leave the live states under every alteration


def group_leaks(transitions: sp.csr_matrix, live: np.ndarray) -> np.ndarray:
    """Per group of the choice product: whether some of its mass leaves the live states (to
    the decoy, or where the decoy cannot be reached)."""
    outside = transitions[:, np.flatnonzero(~live)]
    return np.asarray((outside != 0).sum(axis=1)).ravel() > 0


def closed_classes(
    inside: sp.csr_matrix,
    leaks: np.ndarray,
    base_groups: np.ndarray,
    inner_groups: tuple[np.ndarray, np.ndarray],
    deadline: Deadline | None = None,
) -> ClosedClasses:
    """The closed classes and safe states of the base chain whose live state ``q`` takes group
    ``base_groups[q]`` (``inside``: each group's transitions into the live states; ``leaks``:
    per group, whether it leaves them); ``inner_groups``: (live state, group) of every row an
    inner option may give a state. Past ``deadline``, no state is called safe (sound: every
    option then goes through the trap search, which stops at the deadline too)."""
    moves = inside[base_groups].tocsr()
    n = moves.shape[0]
    leaving = leaks[base_groups]
    stuck = ~reachable_from(moves.T.tocsr(), np.flatnonzero(leaving))
    closed = np.zeros(n, dtype=bool)
    if stuck.any():  # the bottom strongly connected components of the stuck states
        inner = np.flatnonzero(stuck)
        sub = moves[inner][:, inner].tocoo()
        _, labels = connected_components(sub, directed=True, connection="strong")
        exits = labels[sub.row] != labels[sub.col]
        not_bottom = np.zeros(labels.max(initial=-1) + 1, dtype=bool)
        not_bottom[labels[sub.row[exits]]] = True
        closed[inner] = ~not_bottom[labels]
    return ClosedClasses(closed, _safe(inside, leaks, base_groups, inner_groups, deadline))


def _safe(
    inside: sp.csr_matrix,
    leaks: np.ndarray,
    base_groups: np.ndarray,
    inner_groups: tuple[np.ndarray, np.ndarray],
    deadline: Deadline | None = None,
) -> np.ndarray:
    """Live states that leave the live states with positive probability under *every*
    alteration of the block (even one that picks an inner option per state): the complement
    of the largest set in which every state has a row (its base row; any option's, for inner
    states) that neither leaks nor leaves the set. A pass may remove a single state, so on a
    long chain the loop runs long: past ``deadline`` it stops and calls no state safe (an
    under-approximation, as every answer of this function must be)."""
    n = base_groups.size
    inner_state, inner_group = inner_groups
    row_state = np.concatenate([np.arange(n), inner_state]).astype(np.int64)
    row_group = np.concatenate([base_groups, inner_group]).astype(np.int64)
    rows = inside[row_group].tocsr()
    leaking = leaks[row_group]
    trapped = np.ones(n, dtype=bool)
    while True:
        if deadline is not None and deadline.expired():
            return np.zeros(n, dtype=bool)
        outside = (~trapped).astype(np.float64)
        stays = ~leaking & (np.asarray(rows @ outside).ravel() == 0)
        kept = np.zeros(n, dtype=bool)
        kept[row_state[stays]] = True
        kept &= trapped
        if (kept == trapped).all():
            return ~trapped
        trapped = kept


def unsafe_options(
    classes: ClosedClasses,
    inside: sp.csr_matrix,
    leaks: np.ndarray,
    option_groups: Sequence[np.ndarray],
    base_groups: np.ndarray,
    regions: Sequence[np.ndarray],
) -> np.ndarray:
    """Per inner choice ``j`` and option ``k`` (``option_groups[j]``: its region's live states
    ``regions[j]`` (local indices) by options), whether the option changes a row of a closed
    class, or a row with neither a safe successor nor a leak: alterations taking it may close
    a class, and are searched for a trap."""
    n_options = max((g.shape[1] for g in option_groups), default=1)
    unsafe = np.zeros((len(option_groups), n_options), dtype=bool)
    safe = classes.safe.astype(np.float64)
    for j, (groups, region) in enumerate(zip(option_groups, regions, strict=True)):
        if not region.size:
            continue
        flat = groups.ravel()
        escapes = leaks[flat] | (np.asarray(inside[flat] @ safe).ravel() > 0)
        changed = groups != base_groups[region][:, None]
        bad = changed & (~escapes.reshape(groups.shape) | classes.closed[region][:, None])
        unsafe[j, : groups.shape[1]] = bad.any(axis=0)
    return unsafe


@njit(cache=True, nogil=True)
def _search_from(
    origin: int,
    stamp: int,
    chain: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray],
    override: np.ndarray,
    scratch: tuple[np.ndarray, np.ndarray, np.ndarray],
) -> tuple[bool, int]:  # pragma: no cover (compiled; its callers are tested)
    """Depth-first search from ``origin`` over the rows of the chain (``chain``: indptr,
    indices, leaks, stop, base_group; ``override[s]``: the group of an altered state ``s``,
    else ``base_group[s]``), marking ``seen`` with ``stamp`` (``scratch``: seen, stack,
    visited): (whether it met a leaking row or a ``stop`` state, how many it visited)."""
    indptr, indices, leaks, stop, base_group = chain
    seen, stack, visited = scratch
    stack[0] = origin
    seen[origin] = stamp
    visited[0] = origin
    top, count = 1, 1
    if stop[origin]:
        return True, count
    while top > 0:
        top -= 1
        s = stack[top]
        g = override[s] if override[s] >= 0 else base_group[s]
        if leaks[g]:
            return True, count
        for p in range(indptr[g], indptr[g + 1]):
            t = indices[p]
            if stop[t]:
                return True, count
            if seen[t] != stamp:
                seen[t] = stamp
                stack[top] = t
                top += 1
                visited[count] = t
                count += 1
    return False, count


@njit(cache=True, nogil=True)
def _closes_a_class(
    chain: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray],
    override: np.ndarray,
    alteration_start: np.ndarray,
    changed_state: np.ndarray,
    changed_group: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:  # pragma: no cover (compiled; its caller is tested)
    """Per alteration (its changed rows ``changed_state``/``changed_group`` from
    ``alteration_start``): whether a depth-first search from one of its changed states, over
    its rows, exhausts without meeting a leaking row or a ``stop`` state (one that leaves under
    every alteration, or a base closed class, absorbing in the system): then that state lies
    in, or only leads to, a closed class. For such an alteration, every changed state is
    searched, and ``emptied`` marks the changed rows the exhausted searches saw: none of them
    can reach the decoy, and every new closed class holds one (it holds a changed state, whose
    own search stays in it)."""
    base_group = chain[4]
    n = base_group.size
    n_alterations = alteration_start.size - 1
    closes = np.zeros(n_alterations, dtype=np.bool_)
    emptied = np.zeros(changed_state.size, dtype=np.bool_)
    seen = np.zeros(n, dtype=np.int64)
    mine = np.full(n, -1, dtype=np.int64)  # the alteration whose trap a state joined last
    stamp = 0
    stack = np.empty(n, dtype=np.int64)
    visited = np.empty(n, dtype=np.int64)
    scratch = (seen, stack, visited)
    for a in range(n_alterations):
        lo, hi = alteration_start[a], alteration_start[a + 1]
        for e in range(lo, hi):
            override[changed_state[e]] = changed_group[e]
        for e in range(lo, hi):
            origin = changed_state[e]
            if mine[origin] == a:  # in a trap this alteration already found
                continue
            stamp += 1
            found, count = _search_from(origin, stamp, chain, override, scratch)
            if not found:
                closes[a] = True
                for i in range(count):
                    mine[visited[i]] = a
        for e in range(lo, hi):
            override[changed_state[e]] = -1
            emptied[e] = mine[changed_state[e]] == a
    return closes, emptied


@njit(cache=True, nogil=True)
def _closes_by_options(
    chain: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray],
    override: np.ndarray,
    alteration_start: np.ndarray,
    entry_choice: np.ndarray,
    entry_option: np.ndarray,
    flat_start: np.ndarray,
    flat_length: np.ndarray,
    slot_state: np.ndarray,
    slot_group: np.ndarray,
    slot_risky: np.ndarray,
) -> np.ndarray:  # pragma: no cover (compiled; its caller is tested)
    """Per alteration (its entries, options of inner choices, from ``alteration_start``):
    whether :func:`_closes_a_class` would say it closes a class. The same depth-first
    searches, read from the options' row slots in place (no list of every changed row is
    built), and only from the changed rows that could lie in a closed class
    (``slot_risky``: a row that leaks, or has a ``stop`` successor, or whose state is one,
    ends its search at once)."""
    base_group = chain[4]
    n = base_group.size
    n_alterations = alteration_start.size - 1
    closes = np.zeros(n_alterations, dtype=np.bool_)
    seen = np.zeros(n, dtype=np.int64)
    stack = np.empty(n, dtype=np.int64)
    visited = np.empty(n, dtype=np.int64)
    scratch = (seen, stack, visited)
    stamp = 0
    for a in range(n_alterations):
        lo, hi = alteration_start[a], alteration_start[a + 1]
        for e in range(lo, hi):
            first = flat_start[entry_choice[e], entry_option[e]]
            for slot in range(first, first + flat_length[entry_choice[e], entry_option[e]]):
                override[slot_state[slot]] = slot_group[slot]
        for e in range(lo, hi):
            if closes[a]:
                break
            first = flat_start[entry_choice[e], entry_option[e]]
            for slot in range(first, first + flat_length[entry_choice[e], entry_option[e]]):
                if not slot_risky[slot]:
                    continue
                stamp += 1
                found, _ = _search_from(slot_state[slot], stamp, chain, override, scratch)
                if not found:
                    closes[a] = True
                    break
        for e in range(lo, hi):
            first = flat_start[entry_choice[e], entry_option[e]]
            for slot in range(first, first + flat_length[entry_choice[e], entry_option[e]]):
                override[slot_state[slot]] = -1
    return closes


def _chain_arrays(
    inside: sp.csr_matrix, leaks: np.ndarray, classes: ClosedClasses, base_groups: np.ndarray
) -> tuple[
    sp.csr_matrix, np.ndarray, tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]
]:
    """(the transitions as CSR, the stop states, the chain as the compiled searches read it:
    indptr, indices, leaks, stop, base_group)."""
    inside = inside.tocsr()
    stop = classes.safe | classes.closed
    arrays = (
        inside.indptr.astype(np.int64),
        _nearest_exit_last(inside, leaks, stop, base_groups),
        leaks,
        stop,
        base_groups.astype(np.int64),
    )
    return inside, stop, arrays


def _nearest_exit_last(
    inside: sp.csr_matrix, leaks: np.ndarray, stop: np.ndarray, base_groups: np.ndarray
) -> np.ndarray:
    """``inside``'s column indices, each row's ordered so that the successor nearest an exit
    (a ``stop`` state or a leaking row, in steps of the base chain) comes last: the
    depth-first searches push a row's successors in order and pop the last first, so they
    head for an exit and most end within a few steps (the searches' answers do not depend on
    the order, only how long they take)."""
    n = base_groups.size
    exits = stop | leaks[base_groups]
    # breadth-first distances to an exit, backwards over the base chain's edges, from a
    # super-source (index n) joined to every exit
    backward = sp.csr_matrix(inside[base_groups].T)
    distance = shortest_path(
        with_super_source(backward, np.flatnonzero(exits)), unweighted=True, indices=n
    )
    row_of = np.repeat(np.arange(inside.shape[0]), np.diff(inside.indptr))
    order = np.lexsort((-distance[inside.indices], row_of))
    ordered: np.ndarray = inside.indices[order].astype(np.int64)
    return ordered


def _override(size: int, fixed: tuple[np.ndarray, np.ndarray] | None) -> np.ndarray:
    """Per live state, the group the block fixes for it (-1: none)."""
    override = np.full(size, -1, dtype=np.int64)
    if fixed is not None:
        override[fixed[0]] = fixed[1]
    return override


def may_close(
    inside: sp.csr_matrix,
    leaks: np.ndarray,
    classes: ClosedClasses,
    base_groups: np.ndarray,
    entries: tuple[np.ndarray, np.ndarray, np.ndarray],
    flat: tuple[np.ndarray, np.ndarray],
    slots: tuple[np.ndarray, np.ndarray],
    fixed: tuple[np.ndarray, np.ndarray] | None = None,
) -> np.ndarray:
    """Per alteration, whether its chain has a closed class through a changed state, as
    :func:`closing_alterations` says, without listing the changed rows: ``entries``
    (alteration start, choice, option per entry), ``flat`` (each option's first row slot and
    count) and ``slots`` (live state and new group per row slot). Most alterations of a chain
    with end components close nothing (none of 2.7 million on the 40x40 turn-back grid at
    budget 3): this finds the few that do, for :func:`closing_alterations` to detail."""
    inside, stop, chain = _chain_arrays(inside, leaks, classes, base_groups)
    slot_state, slot_group = slots
    escapes = leaks | (np.asarray(inside @ stop.astype(np.float64)).ravel() > 0)
    slot_risky = ~(stop[slot_state] | escapes[slot_group])
    start, choice, option = entries
    flat_start, flat_length = flat
    closes: np.ndarray = _closes_by_options(
        chain,
        _override(base_groups.size, fixed),
        start.astype(np.int64),
        choice.astype(np.int64),
        option.astype(np.int64),
        flat_start.astype(np.int64),
        flat_length.astype(np.int64),
        slot_state.astype(np.int64),
        slot_group.astype(np.int64),
        slot_risky,
    )
    return closes


class Traps(NamedTuple):
    """Per alteration, whether its chain has a closed class through a changed state
    (``closes``); per changed row, whether it is then one that can no longer reach the decoy
    (``emptied``): every new closed class holds such a row."""

    closes: np.ndarray
    emptied: np.ndarray


def closing_alterations(
    inside: sp.csr_matrix,
    leaks: np.ndarray,
    classes: ClosedClasses,
    base_groups: np.ndarray,
    alteration_start: np.ndarray,
    changed_state: np.ndarray,
    changed_group: np.ndarray,
    fixed: tuple[np.ndarray, np.ndarray] | None = None,
) -> Traps:
    """Per alteration (given by its changed rows: live state and new group, listed from
    ``alteration_start``): whether its chain has a closed class through a changed state, and
    its changed rows that can no longer reach the decoy (:class:`Traps`). An alteration without
    one keeps exactly the base's closed classes (unless it changes one of their rows, which
    the caller checks), so its low-rank value is the least fixed point. With one, emptying
    those rows (value 0, which they have) leaves no new closed class, as each holds one of
    them: the system is non-singular again and its solution the least fixed point.
    ``fixed``: rows (live state, group) every alteration of the block takes."""
    _, _, chain = _chain_arrays(inside, leaks, classes, base_groups)
    closes, emptied = _closes_a_class(
        chain,
        _override(base_groups.size, fixed),
        alteration_start.astype(np.int64),
        changed_state.astype(np.int64),
        changed_group.astype(np.int64),
    )
    return Traps(closes, emptied)


# The trap handling of the low-rank enumeration (misdirect.solvers.engines.lowrank): which of
# a block's alterations may close or open a class, found before its batch of low-rank updates
# divides by a singular system.

TRAP_BATCH = 100_000  # alterations per trap search between two looks at the deadline


class Cycles(NamedTuple):
    """What a base chain with end components needs besides its solve: its closed classes and
    safe states, the options that may close a class, and the live state and new group of every
    row slot of its :class:`~misdirect.solvers.engines.lowrank_updates.RowDeltas` (the changed
    rows, for the trap search)."""

    classes: ClosedClasses
    base_groups: np.ndarray
    unsafe: np.ndarray
    slot_state: np.ndarray
    slot_group: np.ndarray


class Trap(NamedTuple):
    """The alterations of a block the batch leaves out (``flagged``: those that may close or
    open a class, and their extensions; every one that takes an unsafe option when the deadline
    cut the search short), their row slots (``slots``, each owned by ``owner``, ``counts`` per
    alteration), and which of them may close a class (``closes``; None when cut short): those
    that change a row of a base closed class (``touched``), and the others, whose changed rows
    that can no longer reach the decoy ``emptied`` marks (per row slot)."""

    flagged: np.ndarray
    slots: np.ndarray
    owner: np.ndarray
    counts: np.ndarray
    closes: np.ndarray | None
    touched: np.ndarray | None = None
    emptied: np.ndarray | None = None


def with_extensions(parent: np.ndarray, roots: np.ndarray) -> np.ndarray:
    """Mask of the alterations ``roots`` and every alteration that extends one of them (whose
    chain of parents reaches it): the low-rank batch builds each alteration from its parent,
    so an alteration that closes a class takes its extensions out of the batch with it."""
    marked = np.zeros(parent.size, dtype=bool)
    marked[roots] = True
    has_parent = parent >= 0
    while True:
        grown = marked | (has_parent & marked[np.maximum(parent, 0)])
        if (grown == marked).all():
            return marked
        marked = grown


def opening(cycles: Cycles, table: RowDeltas) -> np.ndarray:
    """Per (choice, option), whether it changes a row of a base closed class (may open it):
    such an alteration's chain may not keep the base's closed classes, so no update of the
    base values it."""
    in_closed = np.concatenate([[0], np.cumsum(cycles.classes.closed[cycles.slot_state])])
    return cast(
        np.ndarray, in_closed[table.flat_start + table.flat_length] > in_closed[table.flat_start]
    )


def taking(altered: AlteredEntries, marked: np.ndarray) -> np.ndarray:
    """Per alteration, whether it takes some option that ``marked[choice, option]`` marks."""
    taken = np.zeros(altered.costs.size, dtype=bool)
    taken[altered.alteration[marked[altered.choice, altered.option]]] = True
    return taken


class TrapSearch:
    """The closed-class questions one enumeration asks of its base chains, on its transitions
    into live states (``inside``, an empty last row: ``closed_group``) and their ``leaks``:
    kept apart from the enumeration because they decide *whether* a low-rank value is the least
    fixed point, not what it is."""

    def __init__(self, inside: sp.csr_matrix, leaks: np.ndarray, closed_group: int):
        self.inside = inside
        self.leaks = leaks
        self.closed_group = closed_group

    def closing(
        self,
        base_groups: np.ndarray,
        option_groups: list[np.ndarray],
        regions: list[np.ndarray],
        deadline: Deadline | None = None,
    ) -> tuple[np.ndarray, list[np.ndarray], tuple[ClosedClasses, np.ndarray]]:
        """A base with end components: its closed classes take the empty group (their values
        are 0, so the system on the other live states is non-singular), and so does every
        option that leaves such a row as it is; with the closed classes, the options that may
        close a class (:func:`unsafe_options`)."""
        repeated = (np.repeat(r, g.shape[1]) for r, g in zip(regions, option_groups, strict=True))
        inner_rows = (
            np.concatenate([np.zeros(0, dtype=np.int64), *repeated]),
            np.concatenate([np.zeros(0, dtype=np.int64), *(g.ravel() for g in option_groups)]),
        )
        classes = closed_classes(self.inside, self.leaks, base_groups, inner_rows, deadline)
        unsafe = unsafe_options(
            classes, self.inside, self.leaks, option_groups, base_groups, regions
        )
        closed_base = np.where(classes.closed, self.closed_group, base_groups)
        option_groups = [
            np.where(g == base_groups[region][:, None], closed_base[region][:, None], g)
            for g, region in zip(option_groups, regions, strict=True)
        ]
        return closed_base, option_groups, (classes, unsafe)

    @staticmethod
    def cycles(
        closing: tuple[ClosedClasses, np.ndarray] | None,
        base_groups: np.ndarray,
        deltas: RowDeltas,
        inner_rows: np.ndarray,
    ) -> Cycles | None:
        """The :class:`Cycles` of a base: its row slots' live states (``inner_rows``: the
        live state of each column of ``W``) and new groups, as ``deltas`` lists them."""
        if closing is None:
            return None
        slots = deltas.column[:-1]  # without the pad
        return Cycles(closing[0], base_groups, closing[1], inner_rows[slots], deltas.group[:-1])

    def keeps_classes(
        self,
        cycles: Cycles,
        table: RowDeltas,
        fixed: list[tuple[int, int]],
        slots: np.ndarray,
    ) -> bool:
        """Whether the kept basis's chain with the options ``fixed`` (their row ``slots``)
        has exactly the basis's closed classes: none of them changes a row of one (which may
        open it), and the trap search from their changed rows finds no new one. Then the
        basis updated in low rank is the block's base, and a class closed by an inner
        alteration holds one of its changed rows, as the block's trap search assumes. An
        option that only *may* close a class rarely does (on the drones among patrolling
        agents, the search's subtrees fixed such options hundreds of times, each a new base
        solve)."""
        if not any(cycles.unsafe[j, k] for j, k in fixed):
            return True
        opens = opening(cycles, table)
        if any(opens[j, k] for j, k in fixed):
            return False
        traps = closing_alterations(
            self.inside,
            self.leaks,
            cycles.classes,
            cycles.base_groups,
            np.array([0, slots.size]),
            cycles.slot_state[slots],
            cycles.slot_group[slots],
        )
        return not bool(traps.closes[0])

    def search(
        self,
        altered: AlteredEntries,
        cycles: Cycles,
        table: RowDeltas,
        fixed_rows: tuple[np.ndarray, np.ndarray] | None,
        deadline: Deadline,
    ) -> Trap:
        """The alterations of a block that may close a class or open one, with every extension
        of those (the batch leaves them all out), their row slots, and which of them may close
        a class (``closes``; None when ``deadline`` cut the search short: ``flagged`` then
        lists every alteration that takes an unsafe option). ``table``: the block's row
        differences; ``fixed_rows``: the rows (live state, group) every alteration of the
        block takes."""
        n_alterations = altered.costs.size
        risky = taking(altered, cycles.unsafe)
        candidates = np.flatnonzero(risky)
        entries = np.flatnonzero(risky[altered.alteration])  # grouped by alteration
        counts = np.bincount(altered.alteration[entries], minlength=n_alterations)[candidates]
        start = np.concatenate([[0], np.cumsum(counts)])
        closing = np.zeros(candidates.size, dtype=bool)
        for lo in range(0, candidates.size, TRAP_BATCH):
            if deadline.expired():
                none = np.zeros(0, dtype=np.int64)
                return Trap(candidates, none, none, none, None)
            hi = min(lo + TRAP_BATCH, candidates.size)
            part = entries[start[lo] : start[hi]]
            closing[lo:hi] = may_close(
                self.inside,
                self.leaks,
                cycles.classes,
                cycles.base_groups,
                (start[lo : hi + 1] - start[lo], altered.choice[part], altered.option[part]),
                (table.flat_start, table.flat_length),
                (cycles.slot_state, cycles.slot_group),
                fixed_rows,
            )
        # an option that changes a row of a base closed class may open it: its alterations are
        # valued apart (the enumeration's _value_flagged)
        opens = opening(cycles, table)
        roots = np.union1d(candidates[closing], np.flatnonzero(taking(altered, opens) & risky))
        flagged = np.flatnonzero(with_extensions(altered.parent, roots))
        return self.details(flagged, altered, cycles, table, fixed_rows, deadline)

    def details(
        self,
        flagged: np.ndarray,
        altered: AlteredEntries,
        cycles: Cycles,
        table: RowDeltas,
        fixed_rows: tuple[np.ndarray, np.ndarray] | None,
        deadline: Deadline,
    ) -> Trap:
        """The trap search's details for the alterations ``flagged`` (few: those that may close
        or open a class, and their extensions): their row slots, which of them may close a
        class, and the changed rows found trapped."""
        entries = np.flatnonzero(np.isin(altered.alteration, flagged))
        choice, option = altered.choice[entries], altered.option[entries]
        lengths = table.flat_length[choice, option]
        slots = np.repeat(table.flat_start[choice, option], lengths) + rank_in_group(lengths)
        owner = np.searchsorted(flagged, np.repeat(altered.alteration[entries], lengths))
        counts = np.bincount(owner, minlength=flagged.size)
        start = np.concatenate([[0], np.cumsum(counts)])
        closes = np.zeros(flagged.size, dtype=bool)
        emptied = np.zeros(slots.size, dtype=bool)
        for lo in range(0, flagged.size, TRAP_BATCH):
            if deadline.expired():
                return Trap(flagged, slots, owner, counts, None)
            hi = min(lo + TRAP_BATCH, flagged.size)
            part = slots[start[lo] : start[hi]]
            traps = closing_alterations(
                self.inside,
                self.leaks,
                cycles.classes,
                cycles.base_groups,
                start[lo : hi + 1] - start[lo],
                cycles.slot_state[part],
                cycles.slot_group[part],
                fixed_rows,
            )
            closes[lo:hi] = traps.closes
            emptied[start[lo] : start[hi]] = traps.emptied
        # one that changes a row of a closed class may open it: valued exactly too
        touched = cycles.classes.closed[cycles.slot_state[slots]]
        touched = np.bincount(owner, weights=touched, minlength=flagged.size) > 0
        closes |= touched
        return Trap(flagged, slots, owner, counts, closes, touched, emptied)
