"""The low-rank enumeration: every alteration within a budget, one base solve per outer choice.

Altering an observation changes only the rows of the product chain whose world state emits it.
Observations that cover few product states (sensors) are *inner*: for each choice of the
*outer* ones (the blank reading that covers most of the map), the chain is solved once, and
every inner alteration is valued by a low-rank update of that solve
(:mod:`misdirect.solvers.engines.lowrank_updates`).

Where the choice product has no end component among the states that can reach the decoy,
``I − P`` is invertible on them for *every* alteration, and its solution is the least fixed
point. Where it has some, each base chain's closed classes are fixed to 0, and the alterations
that could close a class are searched for a trap: one that closes a class is still valued by
its own low-rank update, with its changed rows that can no longer reach the decoy emptied
(value 0); one that changes a row of a base closed class (which it may open) is valued
exactly, one chain each (:mod:`misdirect.solvers.engines.closed_classes`). Values within
:data:`~misdirect.core.tolerance.NEAR_TIE` of the best count as tied (the cheapest wins);
where a base is too ill-conditioned for its low-rank values to rank them, the candidates are
valued exactly first (:mod:`misdirect.solvers.engines.exact_revaluation`); with a floor, the
alterations the gain bound proves below it are left out
(:func:`~misdirect.solvers.engines.entry_gain.floor_filter`). Every value reported is
re-computed exactly by the front door.

Used by the ``incremental`` method (the whole curve) and by the segment search (the subtrees
small enough to enumerate, with their bases kept in a :class:`BasisCache`).
"""

from __future__ import annotations

import dataclasses
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import cached_property, partial
from typing import NamedTuple, cast

import numpy as np
import scipy.sparse as sp

from misdirect.core import tolerance
from misdirect.core.alterations import (
    AlterationSpace,
    AlteredEntries,
    ObservationChoices,
)
from misdirect.core.attack import AttackInstance
from misdirect.core.memory import memory_limit
from misdirect.errors import SolverError
from misdirect.solvers.base import (
    DEFAULT_THREADS,
    ProgressCallback,
    best_fitting,
    best_per_budget,
    report,
)
from misdirect.solvers.deadline import Deadline, DeadlineExpiredError
from misdirect.solvers.engines.closed_classes import (
    ClosedClasses,
    Cycles,
    Trap,
    TrapSearch,
    group_leaks,
    opening,
    with_extensions,
)
from misdirect.solvers.engines.entry_gain import (
    EntryGains,
    GainsOf,
    entry_gains,
    first_entry_gains,
    floor_filter,
    worth_filtering,
)
from misdirect.solvers.engines.exact_revaluation import (
    ExactChains,
    guard_ill_conditioned,
    value_one_chain_each,
)
from misdirect.solvers.engines.lowrank_updates import (
    BaseRows,
    Basis,
    RowDeltas,
    add_corrections,
    base_solve,
    flagged_values,
    row_deltas,
    selected_groups,
    update_error,
)

INNER_ROWS = 200  # inner observations together may own at least this many product states,
INNER_ENTRIES = 50_000_000  # ... and more while W (live states x inner rows) stays this small
# ... or this small where W lives only while its base is solved (no end components: a kept
# basis keeps the options' table, not W), within the memory limit: the solve holds about
# SOLVE_COPIES copies of it at once, and two blocks may be solved at a time
TRANSIENT_ENTRIES = 100_000_000
SOLVE_COPIES = 6
INNER_ROWS_MAX = 3_000  # ... up to this many (the corrections grow with their square)
INNER_BLOCK = 64  # ... and each at most this many (a bigger one is cheaper as an outer one)
MAX_ALTERATIONS = 12_000_000  # listed sparsely, their tables stay within a few GiB
BASES_KEPT = 8  # base chains a search keeps between its enumerations (one per blank pick)
FIRST_ENTRY_SHARE = 0.05  # of the time left: the root chain's first-entry gains, at most
OPENED_BLOCK_FROM = 16  # alterations opening a base closed class by one option: from this many
# on they are a block of their own (that option fixed, its base solved once, the rest by low
# rank); fewer are valued one chain each (a base solve costs several single chains)
COMPILED_FROM = 5_000  # alterations: fewer are corrected by numpy, not by the numba loop, whose
# first call in a process loads numba's compiler (even from its cache), a one-off cost that a
# small enumeration never repays; a search (many enumerations, bases kept) always takes the loop


class NotApplicableError(SolverError):
    """The enumeration does not apply to this model; use another method."""


@dataclass(frozen=True)
class Enumerated:
    """What one enumeration valued: per alteration its cost and value, listed block by block
    (one block per outer choice vector, ``offsets`` where each begins)."""

    costs: np.ndarray
    values: np.ndarray
    # per block: (outer choice vector, AlteredEntries of the inner ones)
    blocks: list[tuple[np.ndarray, AlteredEntries]]
    offsets: np.ndarray
    outer: list[int]
    inner: list[int]
    n_choices: int
    blocks_done: int
    next_outer_cost: float  # cost of the first outer vector not reached (inf: all were)
    unevaluated: float  # cheapest alteration of a reached block cut short by the deadline
    evaluations: int
    base_solves: int  # blocks that solved (or updated) a base chain: not those of one alteration
    scale: tolerance.CostScale  # how the costs fit a budget
    top: float  # the budget enumerated within: nothing costlier was listed
    base_seconds: float = 0.0  # spent solving (or updating) its base chains
    # the floor the run left out alterations below: it then answers for ``top`` only
    floor: float | None = None
    # per choice, its options' costs: the terms that decide a cost the scale calls ambiguous
    choice_costs: tuple[np.ndarray, ...] = ()

    def complete_for(self, budget: float) -> bool:
        """Whether every alteration within ``budget`` was valued (with a floor: every one
        that may reach it, and only ``top`` is answered)."""
        cap = self.scale.cap(budget)
        if cap > self.scale.cap(self.top):
            return False  # alterations above the run's own budget were never listed
        if self.floor is not None and cap < self.scale.cap(self.top):
            return False  # a cheaper alteration below the floor may be the best at ``budget``
        return not self.next_outer_cost <= cap and not self.unevaluated <= cap

    def picks(self, index: int) -> np.ndarray:
        """The choice vector of alteration ``index``."""
        block = int(np.searchsorted(self.offsets, index, side="right")) - 1
        outer_pick, altered = self.blocks[block]
        picked = np.zeros(self.n_choices, dtype=np.int64)
        picked[self.outer] = outer_pick
        picked[self.inner] = altered.picks(index - self.offsets[block], len(self.inner))
        return picked

    def terms(self, index: int) -> list[float]:
        """The costs alteration ``index`` adds up, one per altered choice."""
        picked = self.picks(index)
        return [float(self.choice_costs[i][k]) for i, k in enumerate(picked.tolist()) if k]

    def best_within(self, budgets: Sequence[float]) -> list[int]:
        """Index of the best alteration within each budget (near-ties: the cheapest)."""
        return best_per_budget(
            self.costs,
            self.values,
            budgets,
            self.scale,
            tie=tolerance.NEAR_TIE,
            terms=self.terms,
        )


class BestCompletion(NamedTuple):
    """What :meth:`LowRankEnumeration.best_with` found: the answer (near-ties: the cheapest,
    so ``value`` may lie up to a near-tie below the best value), and ``bound``, the best value
    of any alteration valued within the budget, which the subtree's optimum does not exceed
    (up to the updates' rounding) when ``complete``."""

    value: float
    picks: np.ndarray
    complete: bool
    bound: float


class _KeptBasis(NamedTuple):
    basis: Basis
    cycles: Cycles | None


class _BlockBase(NamedTuple):
    """A block's base chain: the value at the start, its row of ``W``, the row differences
    of the inner options, and (with end components) its :class:`Cycles`, the rows its
    fixed inner picks change (live states, groups), and its rows of ``x0`` and ``W`` on
    demand, which value the alterations that close a class
    (:func:`~misdirect.solvers.engines.lowrank_updates.flagged_values`)."""

    x_start: float
    w_start: np.ndarray | None
    deltas: RowDeltas
    cycles: Cycles | None = None
    fixed_rows: tuple[np.ndarray, np.ndarray] | None = None
    rows: BaseRows | None = None
    steps: float = np.inf  # proven bound on the base chain's expected steps (its conditioning)


# one block's (inner costs, values, alterations, the cost from which budgets stay open)
_Block = tuple[np.ndarray, np.ndarray, AlteredEntries, float]


class _BlockRun(NamedTuple):
    """What one outer block of :meth:`LowRankEnumeration.run` enumerates."""

    outer: list[int]
    outer_pick: np.ndarray
    inner: list[int]
    fixed: dict[int, int]
    remaining: float  # the budget left for inner alterations
    floor: float | None
    compiled: bool


class _BlockOutcome(NamedTuple):
    """How one outer block ran: its block (None: the deadline cut a block after the first
    while it was being listed), when its base was factored, the base's proven steps, whether
    the deadline cut the first block (it then holds its outer alteration alone), and whether
    a base was solved."""

    block: _Block | None
    factored: float
    steps: float = 0.0
    cut_first: bool = False
    base_solved: bool = False


class _BlockPace:
    """The time the blocks of one :meth:`LowRankEnumeration.run` take, measured as they run:
    whether the next block still fits ``share`` (seconds; the blocks left that solve a base,
    each as long as the last base, and their alterations at the last block's rate) and the
    deadline a block gets within it."""

    def __init__(self, per_block: np.ndarray | None, share: float | None):
        self.share = share
        self.began = time.perf_counter()
        self.factor_s = self.per_alteration = self.base_s = self.bases_s = 0.0
        self.last_count = self.blocks_done = 0
        if per_block is not None:  # per block, its inner alterations (by its budget left)
            self.after = np.cumsum(per_block[::-1])[::-1]  # alterations from each block on
            self.bases_after = np.cumsum((per_block > 1)[::-1])[::-1]  # blocks with a base

    def share_spent(self, done: int) -> bool:
        """Whether the blocks from the ``done``-th on would take the run past its share."""
        if self.share is None:
            return False
        projected = (
            time.perf_counter()
            - self.began
            + float(self.bases_after[done]) * self.base_s
            + self.per_alteration * float(self.after[done])
        )
        return projected > self.share

    def block_deadline(self, deadline: Deadline, began: float) -> Deadline:
        """``deadline``, or within it where the share ends."""
        if self.share is None:
            return deadline
        return deadline.within(max(self.share - (began - self.began), 0.0))

    def record(self, began: float, factored: float, count: int) -> None:
        """A block began at ``began``, had its base at ``factored`` and valued ``count``."""
        self.blocks_done += 1
        self.factor_s, self.last_count = factored - began, count
        self.bases_s += self.factor_s
        if count > 1:  # a block of one alteration solves no base
            self.base_s = self.factor_s
        self.per_alteration = (time.perf_counter() - factored) / max(count, 1)


class BasisCache:
    """Base chains kept between the enumerations of one search, at most ``kept`` of them
    (each ``W`` may take hundreds of MB), safe to share between its worker threads.

    A worker gets the basis itself, not a key into the cache: another worker evicting it
    later cannot pull it from under a running enumeration. One basis is built at a time."""

    def __init__(self, kept: int = BASES_KEPT):
        self.kept = kept
        self._bases: dict[tuple[int, ...], _KeptBasis] = {}
        self._lock = threading.Lock()
        self._building = threading.Lock()

    def __contains__(self, key: tuple[int, ...]) -> bool:
        with self._lock:
            return key in self._bases

    def get_or_build(self, key: tuple[int, ...], build: Callable[[], _KeptBasis]) -> _KeptBasis:
        with self._lock:
            if key in self._bases:
                return self._bases[key]
        with self._building:
            with self._lock:
                if key in self._bases:  # another worker built it meanwhile
                    return self._bases[key]
            basis = build()
            with self._lock:
                while len(self._bases) >= self.kept:  # the oldest goes
                    self._bases.pop(next(iter(self._bases)))
                self._bases[key] = basis
            return basis


def inner_choices(instance: AttackInstance) -> list[int]:
    """The choices enumerated inside a block (the others are outer: one base solve per pick):
    the smallest regions first, while ``W`` (live states x their rows) stays small."""
    sizes = instance.live_states_per_observation
    size_of = [int(sizes[c.observation]) for c in instance.space.choices]
    n_live = int(instance.live.sum())
    # every inner row saves the outer enumeration a factor; W's memory caps them
    entries = INNER_ENTRIES
    if not instance.cycling.any():
        limit, _ = memory_limit()
        fits = TRANSIENT_ENTRIES if limit is None else limit // (8 * SOLVE_COPIES * 2)
        entries = max(entries, min(TRANSIENT_ENTRIES, fits))
    inner_rows = max(INNER_ROWS, min(entries // max(n_live, 1), INNER_ROWS_MAX))
    inner, total = [], 0
    for i in sorted(range(len(size_of)), key=lambda i: size_of[i]):
        if total + size_of[i] > inner_rows or size_of[i] > INNER_BLOCK:
            break
        inner.append(i)
        total += size_of[i]
    return inner


class LowRankEnumeration:
    """The enumeration over one prepared instance; its layout (regions, the live block of the
    transitions) is computed once and shared by every call, from any thread."""

    def __init__(
        self,
        instance: AttackInstance,
        *,
        threads: int = DEFAULT_THREADS,
        max_evaluations: int = MAX_ALTERATIONS,
    ):
        self.instance = instance
        self.threads = threads
        self.max_evaluations = max_evaluations
        chain, live = instance.chain, instance.live
        space = instance.space
        self.observations = [c.observation for c in space.choices]
        self.live_index = np.full(chain.n_states, -1)
        self.live_index[live] = np.arange(int(live.sum()))
        state_obs = instance.problem.pomdp.observation_of[chain.world_state]
        self.rows_of = {o: np.flatnonzero(live & (state_obs == o)) for o in self.observations}
        self.first_option = np.concatenate([[0], np.cumsum([c.size for c in space.choices])])
        self.natural_inner = inner_choices(instance)
        natural = set(self.natural_inner)
        # outer by size: a base is the basis of their picks (fixed inner ones updated in)
        self.natural_outer = [i for i in range(len(space.choices)) if i not in natural]
        self.start = int(self.live_index[chain.initial]) if live[chain.initial] else -1
        # with end components: closed classes get an empty row (this extra group) in the base
        self.cycling = bool(instance.cycling.any())
        self.closed_group = chain.transitions.shape[0]
        # alterations valued one chain each (exactly, :attr:`exact_evaluations`): those that
        # could close a class, whose low-rank update was ill-conditioned, or that might be the
        # best on an ill-conditioned base
        self._exact = ExactChains(instance, self._chain_of)
        self.trap_updates = 0  # alterations that close a class, valued by low rank
        self.opened_blocks = 0  # blocks of alterations that open a base closed class
        self.filtered = 0  # alterations a floor and the gain bound left unvalued
        self._root_lock = threading.Lock()  # the root chain's first-entry gains, once
        self._root_first: EntryGains | None = None

    @property
    def exact_evaluations(self) -> int:
        """Alterations valued one chain each, exactly (:mod:`.exact_revaluation`)."""
        return self._exact.evaluations

    @cached_property
    def _traps(self) -> TrapSearch:
        """The closed-class questions of this enumeration's bases (:mod:`.closed_classes`)."""
        return TrapSearch(self._inside, self._leaks, self.closed_group)

    @cached_property
    def _inside(self) -> sp.csr_matrix:
        """The transitions into live states, (groups, live states), and an empty last row
        (the group of a closed class's states in a base chain)."""
        chain = self.instance.chain
        inside = chain.transitions[:, np.flatnonzero(self.instance.live)]
        return sp.vstack([inside, sp.csr_matrix((1, inside.shape[1]))], format="csr")

    @cached_property
    def _to_target(self) -> np.ndarray:
        return np.append(self.instance.chain.one_step(), 0.0)

    @cached_property
    def _leaks(self) -> np.ndarray:
        leaks = group_leaks(self.instance.chain.transitions, self.instance.live)
        return np.append(leaks, False)

    def _closing(
        self,
        base_groups: np.ndarray,
        option_groups: list[np.ndarray],
        regions: list[np.ndarray],
        deadline: Deadline | None = None,
    ) -> tuple[np.ndarray, list[np.ndarray], tuple[ClosedClasses, np.ndarray] | None]:
        """Without end components, the arguments. With them: the base's closed classes take
        the empty group (their values are 0), and so does every option that leaves such a row
        as it is; with the closed classes, the options that may close a class
        (:func:`~misdirect.solvers.engines.closed_classes.unsafe_options`)."""
        if not self.cycling:
            return base_groups, option_groups, None
        return self._traps.closing(base_groups, option_groups, regions, deadline)

    @cached_property
    def _live_node(self) -> np.ndarray:
        # memory nodes: a separator for solve_chain to cut along
        return cast(np.ndarray, self.instance.chain.node[self.instance.live])

    def basis_key(self, picks: dict[int, int]) -> tuple[int, ...] | None:
        """The key of the basis an enumeration below ``picks`` uses (None: some outer choice
        is still free, so it would enumerate several bases)."""
        if any(i not in picks for i in self.natural_outer):
            return None
        return tuple(picks[i] for i in self.natural_outer)

    def best_with(
        self,
        budget: float,
        fixed: dict[int, int],
        deadline: Deadline,
        bases: BasisCache,
        floor: float | None = None,
    ) -> BestCompletion | None:
        """The best alteration within ``budget`` that takes option ``fixed[i]`` for choice
        ``i`` (value, choice vector, whether every such alteration was valued: ``deadline``
        may cut the run short, and the best of those valued is then no proof); None when none
        was valued. Each base chain is solved once (kept in ``bases``), and a subtree's base
        is that one with its fixed sensors' rows updated in (low rank). With ``floor`` (a
        value some alteration within ``budget`` reaches), alterations proven to be worth less
        are not valued: "every alteration" then means every one that may reach it, and the
        value is ``-inf`` when none may."""
        found = self.run(budget, fixed, deadline, None, bases, floor=floor)
        costs = np.where(np.isnan(found.values), np.inf, found.costs)
        index = best_fitting(
            costs, found.values, budget, found.scale, tolerance.NEAR_TIE, found.terms
        )
        complete = found.complete_for(budget)
        if index is None:
            if floor is None or not found.values.size:
                return None
            # every alteration was left out: none can reach the floor (no value to offer)
            return BestCompletion(-np.inf, found.picks(0), complete, -np.inf)
        within = found.values[costs <= found.scale.cap(budget)]
        bound = max(float(found.values[index]), float(within.max(initial=-np.inf)))
        return BestCompletion(float(found.values[index]), found.picks(index), complete, bound)

    def bases_within(self, top: float) -> int:
        """How many base chains a run at ``top`` solves: one per outer block with room for an
        inner alteration (a block of one alteration is valued on its own chain)."""
        _, _, _, outer_costs, inner_space = self._layout(top, {})
        return int((self._per_block(inner_space, top, outer_costs, 1) > 1).sum())

    def _layout(
        self, top: float, fixed: dict[int, int]
    ) -> tuple[list[int], list[int], np.ndarray, np.ndarray, AlterationSpace]:
        """(inner choices, outer choices, outer blocks and their costs cheapest first, the
        inner alterations' space) of a run at ``top`` below ``fixed``."""
        inner = [i for i in self.natural_inner if i not in fixed]  # fixed ones: outer
        outer = [i for i in range(len(self.observations)) if i not in inner]
        outer_table, outer_costs = self._outer_blocks(top, fixed, outer)
        choices = self.instance.space.choices
        inner_space = AlterationSpace(tuple(choices[i] for i in inner), self.instance.space.scale)
        return inner, outer, outer_table, outer_costs, inner_space

    def _per_block(
        self, inner_space: AlterationSpace, top: float, outer_costs: np.ndarray, limit: int
    ) -> np.ndarray:
        """Per outer block, its inner alterations within the budget it leaves (``limit + 1``
        once more than ``limit``); a block of one has no base to solve."""
        scale = self.instance.space.scale
        counted: dict[float, int] = {}
        for cost in outer_costs.tolist():
            if cost not in counted:
                counted[cost] = inner_space.count_within(scale.remaining(top, cost), limit)
        return np.array([counted[c] for c in outer_costs.tolist()], dtype=np.int64)

    def run(
        self,
        top: float,
        fixed: dict[int, int] | None = None,
        deadline: Deadline | None = None,
        progress: ProgressCallback | None = None,
        bases: BasisCache | None = None,
        share: float | None = None,
        floor: float | None = None,
    ) -> Enumerated:
        """Every alteration within ``top`` that agrees with ``fixed``, valued at the start;
        outer blocks cheapest first, so a run cut short by ``deadline`` has still proven every
        budget below the first block it did not reach. With ``share`` (seconds), the run also
        stops before a block once the blocks left, at the last one's time, would take it past
        that: a caller with a search to hand the budget to keeps the time (each block of a
        big map is a base solve of thousands of columns). With ``floor`` (a value some
        alteration within ``top`` reaches), a block leaves out the alterations the first-entry
        gain bound proves to be worth less (:meth:`_filtered`): the run then answers for
        ``top`` only, not for the budgets below it."""
        fixed = fixed or {}
        deadline = deadline or Deadline()
        inner, outer, outer_table, outer_costs, inner_space = self._layout(top, fixed)
        scale = self.instance.space.scale
        compiled = bases is not None or (
            self.instance.space.count_within(top, COMPILED_FROM) > COMPILED_FROM
        )
        blocks: list[tuple[np.ndarray, AlteredEntries]] = []
        costs: list[np.ndarray] = []
        values: list[np.ndarray] = []
        unevaluated, evaluations, steps, base_solves = np.inf, 0, 0.0, 0
        pace = _BlockPace(
            None
            if share is None
            else self._per_block(inner_space, top, outer_costs, self.max_evaluations),
            share,
        )
        # the enumeration's progress: alterations valued of those within ``top``, and the rate
        space, limit = self.instance.space, self.max_evaluations
        total = 0 if progress is None else space.count_within(top, limit)
        started = time.perf_counter()
        report(progress, 0, total, stage="enumeration")
        for outer_pick, outer_cost in zip(outer_table, outer_costs, strict=True):
            remaining = scale.remaining(top, outer_cost)
            if blocks and (
                pace.share_spent(len(blocks))
                or not self._block_fits(
                    deadline,
                    pace.factor_s,
                    pace.per_alteration,
                    pace.last_count,
                    inner_space,
                    remaining,
                )
            ):
                break  # the first (unaltered outer) block always runs
            began = time.perf_counter()
            job = _BlockRun(outer, outer_pick, inner, fixed, remaining, floor, compiled)
            outcome = self._run_block(job, pace, deadline, bases, inner_space, evaluations)
            base_solves += outcome.base_solved
            if outcome.block is None:
                break  # the deadline cut a later block while it was being listed
            steps = max(steps, outcome.steps)
            inner_costs, found, altered, cut_at = outcome.block
            evaluations += int(np.isfinite(inner_costs).sum())
            unevaluated = min(unevaluated, cut_at + outer_cost)
            costs.append(outer_cost + inner_costs)
            values.append(found)
            blocks.append((outer_pick, altered))
            pace.record(began, outcome.factored, len(inner_costs))
            seconds = time.perf_counter() - started
            rate = evaluations / seconds if evaluations and seconds > 0 else None
            report(progress, evaluations, total, stage="enumeration", rate=rate)
            if outcome.cut_first:
                break
        done = len(blocks)
        enumerated = Enumerated(
            costs=np.concatenate([np.zeros(0), *costs]),
            values=np.clip(
                np.concatenate([np.zeros(0), *values]),
                0.0,
                self.instance.problem.objective.max_value,
            ),
            blocks=blocks,
            offsets=np.cumsum([0, *(altered.costs.size for _, altered in blocks)]),
            outer=outer,
            inner=inner,
            n_choices=len(self.observations),
            blocks_done=done,
            next_outer_cost=float(outer_costs[done]) if done < len(outer_costs) else np.inf,
            unevaluated=unevaluated,
            evaluations=evaluations,
            base_solves=base_solves,
            scale=scale,
            top=top,
            base_seconds=pace.bases_s,
            floor=floor,
            choice_costs=tuple(np.asarray(c.costs) for c in self.instance.space.choices),
        )
        return self._verified(enumerated, steps, deadline, floor)

    def _run_block(
        self,
        job: _BlockRun,
        pace: _BlockPace,
        deadline: Deadline,
        bases: BasisCache | None,
        inner_space: AlterationSpace,
        evaluations: int,
    ) -> _BlockOutcome:
        """One outer block of :meth:`run`: a single alteration on its own chain, or a base
        solve and its inner alterations by low-rank updates."""
        began = time.perf_counter()
        if inner_space.count_within(job.remaining, 1) <= 1:
            # no inner alteration fits: the block is one alteration, valued on its own chain
            # (a base solve would solve for every inner row, thousands on a big map)
            return _BlockOutcome(self._single_block(job.outer, job.outer_pick, deadline), began)
        # with a share, a block stops where the share ends too (its smaller alterations
        # first): the first block always starts, and one of a million deep alterations could
        # otherwise take the search's whole time (docs/benchmarks.md)
        block_deadline = pace.block_deadline(deadline, began)
        base_solved = False
        try:
            cheapest = inner_space.cheapest()
            one_entry = not self.instance.space.scale.fits(cheapest + cheapest, job.remaining)
            base = self._block_base(
                job.outer, job.outer_pick, job.inner, job.fixed, bases, block_deadline, one_entry
            )
            base_solved = True
            factored = time.perf_counter()
            block = self._block(
                job.remaining,
                job.inner,
                base,
                block_deadline,
                evaluations,
                job.compiled,
                job.outer,
                job.outer_pick,
                job.floor,
            )
            return _BlockOutcome(block, factored, base.steps, base_solved=True)
        except DeadlineExpiredError:
            # cut while listing the block's alterations (core.checkpoint: ten million take
            # seconds): the budgets from its cost are open. The first block keeps its
            # alteration without inner ones, valued on its own chain (budget 0)
            if pace.blocks_done:
                return _BlockOutcome(None, began, base_solved=base_solved)
            factored = time.perf_counter()
            costs_0, found_0, altered_0, cut_0 = self._single_block(
                job.outer, job.outer_pick, deadline
            )
            first = (costs_0, found_0, altered_0, min(cut_0, inner_space.cheapest()))
            return _BlockOutcome(first, factored, cut_first=True, base_solved=base_solved)

    def _verified(
        self, found: Enumerated, steps: float, deadline: Deadline, floor: float | None = None
    ) -> Enumerated:
        """``found`` with every alteration that may be the best within some budget valued
        exactly when its base chains (up to ``steps`` expected steps) are too ill-conditioned
        for its low-rank values to rank it
        (:func:`~misdirect.solvers.engines.exact_revaluation.guard_ill_conditioned`)."""
        unevaluated = guard_ill_conditioned(
            found.costs,
            found.values,
            found.unevaluated,
            found.scale,
            steps,
            self.instance.problem.objective.max_value,
            lambda index: self._exact.value(found.picks(index)),
            deadline,
            floor,
        )
        return dataclasses.replace(found, unevaluated=unevaluated)

    def _outer_blocks(
        self, top: float, fixed: dict[int, int], outer: list[int]
    ) -> tuple[np.ndarray, np.ndarray]:
        """Every outer choice vector within ``top`` (fixed choices with their one option) and
        its cost, cheapest first."""
        outer_space = AlterationSpace(
            tuple(
                ObservationChoices(c.observation, c.targets[[fixed[i]]], c.costs[[fixed[i]]])
                if i in fixed
                else c
                for i, c in enumerate(self.instance.space.choices)
            ),
            self.instance.space.scale,
        )
        listed = outer_space.within(top, outer)
        assert listed is not None  # no limit given: never None
        outer_table, outer_costs = listed
        for column, i in enumerate(outer):
            if i in fixed:
                outer_table[:, column] = fixed[i]
        ranked = np.argsort(outer_costs, kind="stable")
        return outer_table[ranked], outer_costs[ranked]

    def _block_base(
        self,
        outer: list[int],
        outer_pick: np.ndarray,
        inner: list[int],
        fixed: dict[int, int],
        bases: BasisCache | None,
        deadline: Deadline | None = None,
        one_entry: bool = False,
    ) -> _BlockBase:
        """The block's base chain: solved here, or (with ``bases``) a kept basis updated in
        low rank for the fixed inner choices (solved here if one of those may close a class).
        ``one_entry``: no inner alteration of the block takes two options (its table is then
        updated on each option's own rows only, :meth:`Basis.with_fixed`)."""
        chosen = self._chosen(outer, outer_pick, inner)
        if bases is None:
            return self._solved_base(chosen, inner, deadline)
        natural = self.natural_inner
        picks = dict(zip(outer, outer_pick.tolist(), strict=True))
        key = self.basis_key(picks)
        assert key is not None, "every outer choice is fixed in a block"
        kept = bases.get_or_build(key, lambda: self._basis(chosen, deadline))
        position = {i: j for j, i in enumerate(natural)}
        fixed_inner = [(position[i], fixed[i]) for i in natural if i in fixed]
        cycles, table = kept.cycles, kept.basis.options
        fixed_slots = np.concatenate(
            [np.zeros(0, dtype=np.int64)]
            + [table.flat_start[j, k] + np.arange(table.flat_length[j, k]) for j, k in fixed_inner]
        ).astype(np.int64)
        if cycles is not None and not self._keeps_classes(cycles, table, fixed_inner, fixed_slots):
            return self._solved_base(chosen, inner, deadline)  # its closed classes differ
        updated = kept.basis.with_fixed(
            fixed_inner, [position[i] for i in inner], self.start, one_entry=one_entry
        )
        if updated is None:  # ill-conditioned: the block's values would all inherit its error
            return self._solved_base(chosen, inner, deadline)
        x_start, w_start, deltas, rows = updated
        steps = kept.basis.steps
        if cycles is None:
            return _BlockBase(x_start, w_start, deltas, steps=steps)
        inner_cycles = cycles._replace(unsafe=cycles.unsafe[[position[i] for i in inner]])
        fixed_rows = (cycles.slot_state[fixed_slots], cycles.slot_group[fixed_slots])
        return _BlockBase(x_start, w_start, deltas, inner_cycles, fixed_rows, rows, steps)

    def _keeps_classes(
        self,
        cycles: Cycles,
        table: RowDeltas,
        fixed: list[tuple[int, int]],
        slots: np.ndarray,
    ) -> bool:
        """Whether the kept basis's chain with the options ``fixed`` (their row ``slots``)
        has exactly the basis's closed classes (:meth:`.TrapSearch.keeps_classes`)."""
        return self._traps.keeps_classes(cycles, table, fixed, slots)

    def _solved_base(
        self, chosen: np.ndarray, inner: list[int], deadline: Deadline | None = None
    ) -> _BlockBase:
        chain, live, start = self.instance.chain, self.instance.live, self.start
        group_of_option, first = chain.group_of_option, self.first_option
        base_groups = selected_groups(chain, live, chosen)
        regions = [self.live_index[self.rows_of[self.observations[i]]] for i in inner]
        option_groups = [
            group_of_option[self.rows_of[self.observations[i]], first[i] : first[i + 1]]
            for i in inner
        ]
        base_groups, option_groups, closing = self._closing(
            base_groups, option_groups, regions, deadline
        )
        rows = self._rows_within(inner)
        x0, W, steps = base_solve(
            self._inside, self._to_target, base_groups, self.live_index[rows], self._live_node
        )
        deltas = row_deltas(
            option_groups,
            base_groups[self.live_index[rows]],
            self._inside,
            self._to_target,
            x0,
            W,
        )
        cycles = TrapSearch.cycles(closing, base_groups, deltas, self.live_index[rows])
        if start < 0:
            return _BlockBase(0.0, None, deltas, cycles, steps=steps)
        if cycles is None:
            return _BlockBase(float(x0[start]), W[start], deltas, steps=steps)
        none = np.zeros(0, dtype=np.int64)
        solved = BaseRows(x0, W, none, np.zeros((0, 0)))  # kept: emptied rows read from it
        return _BlockBase(float(x0[start]), W[start], deltas, cycles, None, solved, steps)

    def _basis(self, chosen: np.ndarray, deadline: Deadline | None = None) -> _KeptBasis:
        """The basis of the outer picks in ``chosen`` with every natural inner one unaltered."""
        chain, live, first = self.instance.chain, self.instance.live, self.first_option
        unaltered = chosen.copy()  # the fixed inner ones too
        for i in self.natural_inner:
            unaltered[first[i] : first[i + 1]] = False
            unaltered[first[i]] = True
        root_groups = selected_groups(chain, live, unaltered)
        states = [self.rows_of[self.observations[i]] for i in self.natural_inner]
        option_groups = [
            chain.group_of_option[region, first[i] : first[i + 1]]
            for i, region in zip(self.natural_inner, states, strict=True)
        ]
        regions = [self.live_index[region] for region in states]
        root_groups, option_groups, closing = self._closing(
            root_groups, option_groups, regions, deadline
        )
        basis = Basis.of(
            self._inside,
            self._to_target,
            root_groups,
            regions,
            option_groups,
            self._live_node,
            self.start,
            keep_rows=closing is not None,  # rows on demand: only where classes may close
        )
        inner_rows = np.concatenate([np.zeros(0, dtype=np.int64), *regions]).astype(np.int64)
        cycles = TrapSearch.cycles(closing, root_groups, basis.options, inner_rows)
        return _KeptBasis(basis, cycles)

    def _rows_within(self, choices: list[int]) -> np.ndarray:
        """The live product states of ``choices``' observations, choice by choice."""
        parts = (self.rows_of[self.observations[i]] for i in choices)
        return np.concatenate([np.zeros(0, dtype=np.int64), *parts]).astype(np.int64)

    def _block(
        self,
        budget: float,
        inner: list[int],
        base: _BlockBase,
        deadline: Deadline,
        evaluations: int,
        compiled: bool,
        outer: list[int],
        outer_pick: np.ndarray,
        floor: float | None = None,
    ) -> tuple[np.ndarray, np.ndarray, AlteredEntries, float]:
        """(costs, values, the alterations, cheapest one left unvalued) of one block's inner
        alterations within ``budget``; a cost is ``inf`` where the deadline cut it short.
        With ``floor``, those proven to be worth less are left out first (:meth:`_filtered`).

        With end components, the alterations taking an option that may close a class are
        searched for a trap first (:meth:`.TrapSearch.search`). The batch then values every
        alteration but those that close one and their extensions (it builds each from its
        parent, and must not divide by a singular system); :meth:`_value_flagged` values
        those after it. If the deadline cuts the trap search, the risky options change no row
        in the batch and their alterations are left unvalued."""
        chain = self.instance.chain
        x_start, w_start, deltas = base.x_start, base.w_start, base.deltas
        usable = deltas.flat_length > 0
        if base.cycles is not None:
            usable |= base.cycles.unsafe[:, : usable.shape[1]]
        # an option that changes no live row is worth its base value at a higher cost
        altered = self.instance.space.altered_within(
            budget,
            inner,
            limit=self.max_evaluations - evaluations,
            usable=usable,
        )
        if altered is None:
            raise SolverError(f"more than {self.max_evaluations:,} alterations")
        reaches = None  # with a floor: which alterations may reach it (the rest are parents)
        if floor is not None:
            altered, reaches = self._filtered(altered, inner, outer, outer_pick, floor, deadline)
        trap, batch, in_batch = None, altered, np.ones(len(altered.costs), dtype=bool)
        if base.cycles is not None and base.cycles.unsafe.any():
            trap = self._trap_search(altered, base, deadline)
            if trap.closes is None:  # cut short: the risky options change no row
                unsafe = base.cycles.unsafe[:, : usable.shape[1]]
                deltas = deltas._replace(flat_length=np.where(unsafe, 0, deltas.flat_length))
            elif trap.closes.any():
                in_batch = ~with_extensions(altered.parent, trap.flagged[trap.closes])
                batch = altered.restricted(in_batch)
            else:
                trap = None  # no class closes: the batch values every alteration
        inner_costs = altered.costs if trap is None else altered.costs.copy()  # cut in place
        found = np.full(len(inner_costs), float(chain.target_value[chain.initial]))
        cut_at = np.inf
        block = (outer, outer_pick, inner)
        if self.start >= 0:
            assert w_start is not None  # the start is live: it has a row of W
            found[:] = x_start
            part = found[in_batch]
            corrected = add_corrections(
                part, batch, deltas, w_start, deadline, threads=self.threads, compiled=compiled
            )
            found[in_batch] = part
            cut = np.flatnonzero(in_batch)[~corrected]
            ill = np.flatnonzero(in_batch)[corrected & np.isnan(part)]
            if reaches is not None:  # kept only as parents: proven below the floor
                ill = ill[reaches[ill]]
            if (cut.size or ill.size) and inner_costs is altered.costs:
                inner_costs = inner_costs.copy()  # cut in place below
            if cut.size:  # cut short: those alterations were not evaluated
                cut_at = float(inner_costs[cut].min())
                inner_costs[cut] = np.inf
            if ill.size:  # ill-conditioned updates: one chain each, refined
                cut_at = min(
                    cut_at,
                    self._value_exactly(ill, found, inner_costs, altered, block, deadline),
                )
        if trap is not None:
            cut_at = min(
                cut_at,
                self._value_flagged(
                    found, inner_costs, altered, trap, base, block, (budget, compiled), deadline
                ),
            )
        if reaches is not None and not reaches.all():
            # the parents kept for their children are proven below the floor: not candidates
            # (an ill-conditioned base's low-rank values of them would be re-valued exactly)
            inner_costs = np.where(reaches, inner_costs, np.inf)
            found = np.where(reaches, found, 0.0)
        return inner_costs, found, altered, cut_at

    def _filtered(
        self,
        altered: AlteredEntries,
        inner: list[int],
        outer: list[int],
        outer_pick: np.ndarray,
        floor: float,
        deadline: Deadline,
    ) -> tuple[AlteredEntries, np.ndarray | None]:
        """``altered`` without the alterations that cannot reach ``floor``, and which of those
        kept may reach it (:func:`~misdirect.solvers.engines.entry_gain.floor_filter`). By the
        first-entry gain bound (:mod:`~misdirect.solvers.engines.entry_gain`), each is worth
        at most the block's base chain's value plus its altered regions' gains, and at most
        the unaltered chain's value plus the gains of every region it alters there, counted on
        first entries only (:meth:`_root_gains`; tighter where runs circle back). A small block
        is left whole (None): the gains cost about one solve of the base chain."""
        count = len(altered.costs)
        if not worth_filtering(count, int(self.instance.live.sum())):
            return altered, None
        picked = np.zeros(len(self.observations), dtype=np.int64)
        picked[outer] = outer_pick
        regions = np.asarray(inner)[altered.choice]
        bound = self._gains(picked).bounds(altered.alteration, regions, count)
        # and from the root chain, whose gains count first entries only
        root = self._root_gains(deadline).also_altering(np.flatnonzero(picked))
        bound = np.minimum(bound, root.bounds(altered.alteration, regions, count))
        kept = floor_filter(altered, bound, floor)
        self.filtered += kept.dropped
        return kept.altered, kept.reaches

    def _root_gains(self, deadline: Deadline) -> EntryGains:
        """The gains of every choice on the unaltered chain, each on its first entry only
        (one factorisation per choice, once per enumeration, within
        :data:`FIRST_ENTRY_SHARE` of the time ``deadline`` leaves; the choices left undone
        count every entry)."""
        with self._root_lock:
            if self._root_first is None:
                remaining = deadline.remaining()
                end = None if remaining is None else FIRST_ENTRY_SHARE * remaining
                began = time.perf_counter()

                def stop() -> bool:
                    late = end is not None and time.perf_counter() - began > end
                    return late or deadline.expired()

                self._root_first = self._gains(
                    np.zeros(len(self.observations), dtype=np.int64),
                    partial(first_entry_gains, stop=stop),
                )
            return self._root_first

    def _gains(self, picked: np.ndarray, gains_of: GainsOf = entry_gains) -> EntryGains:
        """The gains (``gains_of``: by default counted on every entry) of every choice on the
        chain taking option ``picked[i]`` of each choice ``i`` (its closed classes as they
        are: value 0)."""
        chain = self.instance.chain
        return gains_of(
            self._chain_of(picked),
            chain.target,
            chain.target_value,
            chain.initial,
            self._region,
            len(self.observations),
            self.instance.problem.objective.max_value,
        )

    @cached_property
    def _region(self) -> np.ndarray:
        """The choice whose observation each product state reads among the live ones (-1:
        none); the regions of the gain bound."""
        region = np.full(self.instance.chain.n_states, -1, dtype=np.int64)
        for i, o in enumerate(self.observations):
            region[self.rows_of[o]] = i
        return region

    def _chain_of(self, picked: np.ndarray) -> sp.csr_matrix:
        """The chain, within the choice product, of the alteration taking option
        ``picked[i]`` of every choice ``i``."""
        chain = self.instance.chain
        policy = self._unaltered_policy.copy()
        for i in np.flatnonzero(picked).tolist():
            rows = self.rows_of[self.observations[i]]
            policy[rows] = chain.group_of_option[rows, self.first_option[i] + picked[i]]
        return cast(sp.csr_matrix, chain.transitions[policy])

    def _single_block(
        self, outer: list[int], outer_pick: np.ndarray, deadline: Deadline | None = None
    ) -> tuple[np.ndarray, np.ndarray, AlteredEntries, float]:
        """:meth:`_block` for a block whose only alteration leaves every inner choice
        unaltered: its value exactly, from its own chain. Once ``deadline`` has passed it is
        left unvalued (cost ``inf``, the block cut at inner cost 0): a chain solve of a big map
        takes as long as the base solve before it, and the caller answers without it."""
        none = np.zeros(0, dtype=np.int64)
        altered = AlteredEntries(none, none, none, np.zeros(1), np.full(1, -1, dtype=np.int64))
        if deadline is not None and deadline.expired():
            return np.full(1, np.inf), np.zeros(1), altered, 0.0
        picked = np.zeros(len(self.observations), dtype=np.int64)
        picked[outer] = outer_pick
        value = self._exact.value(picked)
        return altered.costs, np.array([value]), altered, np.inf

    def _trap_search(self, altered: AlteredEntries, base: _BlockBase, deadline: Deadline) -> Trap:
        """The block's trap search (:meth:`.TrapSearch.search`): the alterations the batch
        must leave out, as they may close or open a class."""
        assert base.cycles is not None
        return self._traps.search(altered, base.cycles, base.deltas, base.fixed_rows, deadline)

    def _value_flagged(
        self,
        found: np.ndarray,
        inner_costs: np.ndarray,
        altered: AlteredEntries,
        trap: Trap,
        base: _BlockBase,
        block: tuple[list[int], np.ndarray, list[int]],
        inner_run: tuple[float, bool],
        deadline: Deadline,
    ) -> float:
        """Value (in place) the flagged alterations the batch left out (``block``: its outer
        choices, their picks, and its inner choices; ``inner_run``: its budget and whether it
        corrects by the compiled loop), each by its own low-rank update: where the trap search
        found a class closing, with the changed rows that can no longer reach the decoy emptied
        (:func:`~misdirect.solvers.engines.lowrank_updates.flagged_values`). Those that change
        a row of a base closed class (it may open) go by blocks of their own
        (:meth:`_value_opening`); those left, and any whose system is singular or
        ill-conditioned, are valued exactly, one chain each. One cut short by ``deadline`` (or
        by a trap search cut short) gets cost ``inf`` (not valued), as in
        :func:`add_corrections`; returns the cheapest of those (``inf``: none)."""
        flagged = trap.flagged
        if trap.closes is None:  # the trap search was cut: none of them is valued
            cut = flagged[np.isfinite(inner_costs[flagged])]
            inner_costs[cut] = np.inf
            return float(altered.costs[cut].min(initial=np.inf))
        assert trap.touched is not None and trap.emptied is not None
        # the batch left out those that close a class and their extensions
        left_out = with_extensions(altered.parent, flagged[trap.closes])[flagged]
        exact = trap.touched.copy()
        cut_at = np.inf
        if base.w_start is not None and base.rows is not None:
            low_rank = left_out & ~trap.touched
            cut_at = self._update_flagged(found, inner_costs, trap, low_rank, base, deadline)
            exact |= low_rank & np.isnan(found[flagged])  # singular, or ill-conditioned
            opened_at, valued = self._value_opening(
                flagged[trap.touched], found, inner_costs, altered, base, block, inner_run, deadline
            )
            cut_at = min(cut_at, opened_at)
            exact &= ~np.isin(flagged, valued)
        else:  # no start row (the start is not live) or no rows kept: one chain each
            exact = trap.closes.copy()
        return min(
            cut_at,
            self._value_exactly(flagged[exact], found, inner_costs, altered, block, deadline),
        )

    def _value_exactly(
        self,
        indices: np.ndarray,
        found: np.ndarray,
        inner_costs: np.ndarray,
        altered: AlteredEntries,
        block: tuple[list[int], np.ndarray, list[int]],
        deadline: Deadline,
    ) -> float:
        """Value the alterations ``indices`` (of ``block``'s ``altered``) one chain each, with
        its error proven and refined (:func:`~misdirect.core.reachability.
        reach_probability_bounded`): they are the ones a low-rank update would get wrong. Those
        the deadline leaves get cost ``inf``; returns the cheapest of them (``inf``: none)."""
        outer, outer_pick, inner = block
        picked = np.zeros(len(self.observations), dtype=np.int64)
        picked[outer] = outer_pick

        def value_of(index: int) -> float:
            picked[inner] = altered.picks(index, len(inner))
            return self._exact.value(picked)

        return value_one_chain_each(indices, found, inner_costs, value_of, deadline)

    def _value_opening(
        self,
        indices: np.ndarray,
        found: np.ndarray,
        inner_costs: np.ndarray,
        altered: AlteredEntries,
        base: _BlockBase,
        block: tuple[list[int], np.ndarray, list[int]],
        inner_run: tuple[float, bool],
        deadline: Deadline,
    ) -> tuple[float, np.ndarray]:
        """Value (in place) the alterations ``indices`` that change a row of a base closed
        class, by blocks of their own: those whose first such entry is option ``k`` of inner
        choice ``j`` are that option fixed and the other inner choices enumerated, so one
        base solve (with its own closed classes) and low-rank updates value them all, instead
        of one chain each (on a drone among patrolling agents those chains took most of a
        search's time: docs/benchmarks.md). Groups under :data:`OPENED_BLOCK_FROM` are left
        to the caller, and so is a block whose base is too ill-conditioned for low-rank
        values. Returns (cheapest alteration cut short by ``deadline``, ``inf``: none; the
        alterations valued or cut)."""
        cycles, table = base.cycles, base.deltas
        assert cycles is not None
        indices = indices[np.isfinite(inner_costs[indices])]
        if indices.size < OPENED_BLOCK_FROM:
            return np.inf, np.zeros(0, dtype=np.int64)
        outer, outer_pick, inner = block
        budget, compiled = inner_run
        opens = opening(cycles, table)
        entries = np.flatnonzero(
            np.isin(altered.alteration, indices) & opens[altered.choice, altered.option]
        )
        # entries are grouped by alteration: each one's first opening entry names its group
        owners, first = np.unique(altered.alteration[entries], return_index=True)
        keys = np.stack([altered.choice[entries[first]], altered.option[entries[first]]], axis=1)
        groups, group_of = np.unique(keys, axis=0, return_inverse=True)
        top_value = self.instance.problem.objective.max_value
        precise_to = tolerance.slack(top_value, rel=tolerance.NEAR_TIE) / 10
        cut_at, valued = np.inf, []
        for g, (j, k) in enumerate(groups.tolist()):
            members = owners[group_of.ravel() == g]
            if members.size < OPENED_BLOCK_FROM:
                continue
            i = inner[j]
            sub_inner = inner[:j] + inner[j + 1 :]
            sub_outer, sub_pick = [*outer, i], np.append(outer_pick, k)
            cost = float(self.instance.space.choices[i].costs[k])
            try:
                if deadline.expired():
                    raise DeadlineExpiredError
                sub_base = self._solved_base(
                    self._chosen(sub_outer, sub_pick, sub_inner), sub_inner, deadline
                )
                if update_error(sub_base.steps, top_value) > precise_to:
                    continue  # its values would inherit the base's error: one chain each
                sub_costs, sub_found, sub_altered, _ = self._block(
                    self.instance.space.scale.remaining(budget, cost),
                    sub_inner,
                    sub_base,
                    deadline,
                    0,
                    compiled,
                    sub_outer,
                    sub_pick,
                )
            except DeadlineExpiredError:
                cut_at = min(cut_at, float(inner_costs[members].min()))
                inner_costs[members] = np.inf
                valued.append(members)
                continue
            except SolverError:  # more alterations than a list may hold: one chain each
                continue
            self.opened_blocks += 1
            # match each member to the sub-block's alteration with the same other picks
            mine = np.delete(altered.picks_of(members, len(inner)), j, axis=1)
            theirs = sub_altered.picks_of(np.arange(sub_costs.size), len(sub_inner))
            where = {row.tobytes(): b for b, row in enumerate(theirs)}
            match = np.array([where.get(row.tobytes(), -1) for row in mine], dtype=np.int64)
            hit = members[match >= 0]
            b = match[match >= 0]
            done = np.isfinite(sub_costs[b])
            found[hit[done]] = sub_found[b[done]]
            if (~done).any():
                cut_at = min(cut_at, float(inner_costs[hit[~done]].min()))
                inner_costs[hit[~done]] = np.inf
            valued.append(hit)
        return cut_at, np.concatenate([np.zeros(0, dtype=np.int64), *valued])

    def _chosen(self, outer: list[int], outer_pick: np.ndarray, inner: list[int]) -> np.ndarray:
        """Per option of the choice product, whether a block's base takes it: its outer picks,
        and every inner choice unaltered."""
        chosen = np.zeros(self.instance.chain.options.size, dtype=bool)
        for i, k in zip(outer, outer_pick.tolist(), strict=True):
            chosen[self.first_option[i] + k] = True
        for i in inner:
            chosen[self.first_option[i]] = True
        return chosen

    def _update_flagged(
        self,
        found: np.ndarray,
        inner_costs: np.ndarray,
        trap: Trap,
        chosen: np.ndarray,
        base: _BlockBase,
        deadline: Deadline,
    ) -> float:
        """The low-rank values of the flagged alterations ``chosen`` selects (NaN where a
        system was singular). Those the deadline leaves get cost ``inf``; returns the cheapest
        of them (``inf``: none)."""
        assert trap.emptied is not None and trap.closes is not None
        assert base.cycles is not None and base.rows is not None and base.w_start is not None
        indices = trap.flagged[chosen]
        if not indices.size:
            return np.inf
        number = np.cumsum(chosen) - 1  # each chosen alteration's place among them
        on = chosen[trap.owner]
        slots = trap.slots[on]
        values, reached = flagged_values(
            base.deltas,
            base.rows,
            base.w_start,
            self.start,
            (number[trap.owner[on]], slots, base.cycles.slot_state[slots]),
            trap.emptied[on],
            indices.size,
            deadline,
        )
        found[indices[reached]] = values[reached]  # NaN: singular, solved exactly after
        self.trap_updates += int((reached & trap.closes[chosen] & ~np.isnan(values)).sum())
        cut = indices[~reached]
        cut_at = float(inner_costs[cut].min(initial=np.inf))
        inner_costs[cut] = np.inf
        return cut_at

    @cached_property
    def _unaltered_policy(self) -> np.ndarray:
        """Every product state's group with nothing altered (a state that cannot reach the
        decoy keeps its first group: its value is 0 whatever it takes)."""
        chain, live = self.instance.chain, self.instance.live
        policy = chain.first_group.copy()
        chosen = np.zeros(chain.options.size, dtype=bool)
        chosen[self.first_option[:-1]] = True
        policy[live] = selected_groups(chain, live, chosen)
        return policy

    def _block_fits(
        self,
        deadline: Deadline,
        factor_s: float,
        per_alteration: float,
        last_count: int,
        space: AlterationSpace,
        budget: float,
    ) -> bool:
        """Whether the next outer block likely ends before ``deadline``: at most the last
        block's count of alterations (its outer cost is no smaller), else counted exactly."""
        left = deadline.remaining()
        if deadline.expired():
            return False
        if left is None or left >= factor_s + per_alteration * last_count:
            return True
        count = space.count_within(budget, self.max_evaluations)
        return left >= factor_s + per_alteration * count
