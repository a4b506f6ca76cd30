"""Enumeration with low-rank updates: one base solve per outer choice, a tiny one per alteration.

Altering an observation changes only the rows of the product chain whose world state emits it.
Observations that cover few product states (sensors) are *inner*: for each choice of the
*outer* ones (the blank reading that covers most of the map), the chain is solved once, for
its value ``x0`` and for ``W = A⁻¹ E_R`` on the inner rows ``R`` (one call of
:func:`misdirect.core.reachability.solve_chain` with all those right-hand sides). An inner
alteration then replaces a few rows, and Sherman–Morrison–Woodbury gives the new value at the
start from an ``|C| x |C|`` system, ``C`` the changed rows:

    x'(q0) = x0(q0) + W(q0, C) (I − D W_C)⁻¹ (D x0 + Δb)

where ``D`` holds the row differences and ``Δb`` the differences in one-step decoy mass. An
alteration with several sensors borders the system of its parent (itself without its last
sensor), so it solves only the Schur complement on its last sensor's rows.

Applicable when the choice product has no end component among the states that can reach the
decoy: then ``I − P`` is invertible on them for *every* alteration, and its solution is the
least fixed point. Values within ``NEAR_TIE`` of the best count as tied (the cheapest wins);
the value reported is then re-computed exactly by :func:`misdirect.solve`, like every other.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import NamedTuple, TypedDict

import numba
import numpy as np

from misdirect.core.alterations import (
    AlterationSpace,
    AlteredEntries,
    ObservationChoices,
    rank_in_group,
)
from misdirect.core.attack import AttackInstance, prepare
from misdirect.core.evaluate import decoy_probability
from misdirect.core.model import Problem
from misdirect.core.reachability import solve_chain
from misdirect.errors import SolverError
from misdirect.solvers.base import (
    Deadline,
    ProgressCallback,
    Solution,
    Status,
    best_per_budget,
    check_threads,
    check_time_limit,
    refuse_options,
    report,
    thread_count,
)

INNER_ROWS = 200  # inner observations together may own at least this many product states,
INNER_ENTRIES = 50_000_000  # ... and more while W (live states x inner rows) stays this small
INNER_ROWS_MAX = 3_000  # ... up to this many (the corrections grow with their square)
INNER_BLOCK = 64  # ... and each at most this many (a bigger one is cheaper as an outer one)
MAX_ALTERATIONS = 12_000_000  # listed sparsely: about 2 GiB at 9.6 million (3 of 128 sensors)
THREADS = 2  # corrections computed in parallel by default (both cores of the target machine)
BATCH_ENTRIES = 4_000_000  # numbers per batch of parents when threads share the batches
CACHED_BATCH_ENTRIES = 250_000  # ... and on one thread: a batch's gathers stay in cache while
# its children read them (an H1 budget-5 subtree: 35.5 -> 31.5 ms; on two threads the pool's
# overhead per batch outweighs it: H2 budgets 0..3 33 -> 39 s)
WIDEST_ENTRY = 16  # rows of one sensor's option, for sizing batches (1-18 on sensor grids)
BASES_KEPT = 8  # base chains kept by a search between its enumerations (one per blank pick)
NEAR_TIE = 1e-9  # values this close count as equal: within the updates' rounding error


class NotApplicableError(SolverError):
    """The model can cycle without reaching the decoy; use another method."""


class IncrementalStats(TypedDict):
    """``stats`` of an incremental answer (the JSON's ``stats``)."""

    evaluations: int  # alterations valued (by low-rank updates or solves)
    factorisations: int  # outer choices, each one base solve
    inner_observations: int
    outer_observations: int


class _Enumerated(NamedTuple):
    """What :meth:`IncrementalSolver._enumerate` valued: per alteration its cost and value,
    listed block by block (one block per outer choice vector, ``offsets`` where each begins)."""

    costs: np.ndarray
    values: np.ndarray
    blocks: list  # per block: (outer choice vector, AlteredEntries of the inner ones)
    offsets: np.ndarray
    outer: list[int]
    inner: list[int]
    n_choices: int
    blocks_done: int
    next_outer_cost: float  # cost of the first outer vector not reached (inf: all were)
    unevaluated: float  # cheapest alteration of a reached block cut short by the deadline
    evaluations: int

    def complete_for(self, budget: float) -> bool:
        """Whether every alteration within ``budget`` was valued."""
        return self.next_outer_cost > budget + 1e-9 and self.unevaluated > budget + 1e-9

    def picks(self, index: int) -> np.ndarray:
        """The choice vector of alteration ``index``."""
        block = int(np.searchsorted(self.offsets, index, side="right")) - 1
        outer_pick, altered = self.blocks[block]
        picked = np.zeros(self.n_choices, dtype=np.int64)
        picked[self.outer] = outer_pick
        picked[self.inner] = altered.picks(index - self.offsets[block], len(self.inner))
        return picked


class IncrementalSolver:
    name = "incremental"
    curve_is_free = True

    def __init__(
        self,
        max_evaluations: int = MAX_ALTERATIONS,
        time_limit: float | None = None,
        threads: int | None = None,
        **options,
    ):
        refuse_options(self.name, options, accepted=("time_limit", "threads"))
        check_time_limit(time_limit)
        check_threads(threads)
        self.max_evaluations = max_evaluations
        self.time_limit = time_limit
        self.threads = thread_count(threads, THREADS)

    def solve(
        self,
        problem: Problem,
        budgets: Sequence[float],
        *,
        progress: ProgressCallback | None = None,
        deadline: Deadline | None = None,
    ) -> list[Solution]:
        deadline = deadline or Deadline(self.time_limit)
        top = max(budgets)
        instance = prepare(problem, top)
        space = instance.space
        self._check_applies(instance)
        if not space.choices:
            value = decoy_probability(problem, problem.identity())
            return [Solution(b, problem.identity(), value, upper_bound=value) for b in budgets]
        found = self._enumerate(instance, top, {}, deadline, progress)
        stats: IncrementalStats = {
            "evaluations": found.evaluations,
            "factorisations": found.blocks_done,
            "inner_observations": len(found.inner),
            "outer_observations": len(found.outer),
        }
        picked = best_per_budget(found.costs, found.values, budgets, tolerance=NEAR_TIE)
        complete = [found.complete_for(b) for b in budgets]
        if not all(complete):
            from misdirect.solvers.branch_and_bound import relaxation_bound

            relaxed = relaxation_bound(problem, top)  # bounds every smaller budget
        solutions = []
        for budget, index, finished in zip(budgets, picked, complete, strict=True):
            within = found.values[found.costs <= budget + 1e-9]
            bound = float(within.max())  # every alteration within the budget was enumerated
            if not finished:
                bound = max(bound, relaxed)
            solutions.append(
                Solution(
                    budget=budget,
                    alteration=space.alteration(problem, found.picks(index)),
                    solver_probability=float(found.values[index]),
                    status=Status.OPTIMAL if finished else Status.TIME_LIMIT,
                    upper_bound=bound,
                    stats=stats,
                )
            )
        return solutions

    @staticmethod
    def _check_applies(instance: AttackInstance) -> None:
        if instance.cycling.any():
            raise NotApplicableError(
                "the chain can cycle without reaching the decoy under some alteration, so "
                "low-rank updates are not safe here; use --method auto, exhaustive or milp"
            )

    def best_with(
        self,
        instance: AttackInstance,
        budget: float,
        fixed: dict[int, int],
        deadline: Deadline,
        bases: dict | None = None,
    ) -> tuple[float, np.ndarray] | None:
        """The best alteration within ``budget`` that takes option ``fixed[i]`` for choice
        ``i`` (value, choice vector), enumerated exhaustively; None when cut by ``deadline``.
        A search hands over the subtrees small enough to enumerate (:mod:`.budget_bound`).
        ``bases`` (kept by the caller between calls): each base chain is solved once, and a
        subtree's base is that one with its fixed sensors' rows updated in (low rank)."""
        self._check_applies(instance)
        found = self._enumerate(instance, budget, fixed, deadline, None, bases)
        if not found.complete_for(budget):
            return None
        index = int(best_per_budget(found.costs, found.values, [budget], tolerance=NEAR_TIE)[0])
        return float(found.values[index]), found.picks(index)

    def _enumerate(self, instance, top, fixed, deadline, progress, bases=None) -> _Enumerated:
        """Every alteration within ``top`` that agrees with ``fixed``, valued at the start."""
        problem, space = instance.problem, instance.space
        chain, live = instance.chain, instance.live
        options = chain.options
        observations = [c.observation for c in space.choices]
        live_index = np.full(chain.n_states, -1)
        live_index[live] = np.arange(int(live.sum()))
        state_obs = problem.pomdp.observation_of[chain.world_state]
        rows_of = {o: np.flatnonzero(live & (state_obs == o)) for o in observations}

        def rows_within(choices: list[int]) -> np.ndarray:
            """The live product states of ``choices``' observations, choice by choice."""
            parts = (rows_of[observations[i]] for i in choices)
            return np.concatenate([np.zeros(0, dtype=np.int64), *parts]).astype(np.int64)

        natural = inner_choices(instance)
        inner = [i for i in natural if i not in fixed]  # fixed ones: outer, with one option
        outer = [i for i in range(len(observations)) if i not in inner]
        # outer choices that are outer by size: a block's base is the basis of their picks
        # with the fixed inner ones updated in (when ``bases`` keeps those bases)
        by_size = [column for column, i in enumerate(outer) if i not in natural]

        # per state: the group each option selects (single-group states: that group)
        first_option = np.concatenate([[0], np.cumsum([c.size for c in space.choices])])
        group_of_option = chain.group_of_option
        to_target = chain.one_step()
        inside = chain.transitions[:, np.flatnonzero(live)].tocsr()  # (G, n_live)
        start = int(live_index[chain.initial]) if live[chain.initial] else -1
        live_node = chain.node[live]  # memory nodes: a separator for solve_chain to cut along

        costs, values, picks = [], [], []
        unevaluated = np.inf  # cheapest alteration left unevaluated by the deadline
        done, evaluations = 0, 0
        # fixed choices are outer ones with their one option
        outer_space = AlterationSpace(
            tuple(
                ObservationChoices(c.observation, c.targets[[fixed[i]]], c.costs[[fixed[i]]])
                if i in fixed
                else c
                for i, c in enumerate(space.choices)
            )
        )
        outer_table, outer_costs = outer_space.within(top, outer)
        for column, i in enumerate(outer):
            if i in fixed:
                outer_table[:, column] = fixed[i]
        # cheapest outer choices first: cut short, every budget below the first outer choice
        # not reached has all its alterations enumerated, so it is still proven
        ranked = np.argsort(outer_costs, kind="stable")
        outer_table, outer_costs = outer_table[ranked], outer_costs[ranked]
        n_outer = len(outer_costs)
        # a block is not started with less time left than it would take at the last one's
        # cost: its factorisation, and per alteration (later blocks cost more outside, so
        # they have fewer alterations: the first block of H2 has 9.5 million, the next 75,000)
        factor_s, per_alteration, last_count = 0.0, 0.0, 0
        inner_space = AlterationSpace(tuple(space.choices[i] for i in inner))
        for outer_pick, outer_cost in zip(outer_table, outer_costs, strict=True):
            if done > 0 and not self._block_fits(
                deadline, factor_s, per_alteration, last_count, inner_space, top - outer_cost
            ):
                break  # the first (unaltered outer) block always runs
            block_began = time.perf_counter()
            chosen = np.zeros(options.size, dtype=bool)
            for i, k in zip(outer, outer_pick, strict=True):
                chosen[first_option[i] + k] = True
            for i in inner:
                chosen[first_option[i]] = True  # inner observations unaltered in the base
            if bases is None:
                base_groups = _selected(chain, live, group_of_option, chosen)
                rows = rows_within(inner)
                x0, W = _base_solve(inside, to_target, base_groups, live_index[rows], live_node)
                deltas = _deltas(
                    [
                        group_of_option[
                            rows_of[observations[i]], first_option[i] : first_option[i + 1]
                        ]
                        for i in inner
                    ],
                    base_groups[live_index[rows]],
                    inside,
                    to_target,
                    x0,
                    W,
                )
                x_start, w_start = (x0[start], W[start]) if start >= 0 else (0.0, None)
            else:
                key = tuple(int(outer_pick[column]) for column in by_size)
                if key not in bases:
                    while len(bases) >= BASES_KEPT:  # the oldest goes (W: up to 400 MB each)
                        bases.pop(next(iter(bases)))
                    unaltered = chosen.copy()  # the fixed inner ones too
                    for i in natural:
                        unaltered[first_option[i] : first_option[i + 1]] = False
                        unaltered[first_option[i]] = True
                    root_groups = _selected(chain, live, group_of_option, unaltered)
                    bases[key] = _Basis.of(
                        inside,
                        to_target,
                        root_groups,
                        [rows_of[observations[i]] for i in natural],
                        [
                            group_of_option[:, first_option[i] : first_option[i + 1]]
                            for i in natural
                        ],
                        live_index,
                        live_node,
                    )
                position = {i: j for j, i in enumerate(natural)}
                x_start, w_start, deltas = bases[key].with_fixed(
                    [(position[i], fixed[i]) for i in natural if i in fixed],
                    [position[i] for i in inner],
                    start,
                )
            factored = time.perf_counter()
            # an option that changes no live row is worth its base value at a higher cost
            altered = space.altered_within(
                top - outer_cost,
                inner,
                limit=self.max_evaluations - evaluations,
                usable=deltas.flat_length > 0,
            )
            if altered is None:
                raise SolverError(f"more than {self.max_evaluations:,} alterations")
            inner_costs = altered.costs
            evaluations += len(inner_costs)
            found = np.full(len(inner_costs), float(chain.target_value[chain.initial]))
            if start >= 0:
                found[:] = x_start
                corrected = _add_corrections(
                    found, altered, deltas, w_start, deadline, threads=self.threads
                )
                if not corrected.all():  # cut short: those alterations were not evaluated
                    left = float(inner_costs[~corrected].min()) + outer_cost
                    unevaluated = min(unevaluated, left)
                    evaluations -= int((~corrected).sum())
                    inner_costs = np.where(corrected, inner_costs, np.inf)
            costs.append(outer_cost + inner_costs)
            values.append(found)
            picks.append((outer_pick, altered))
            done += 1
            factor_s, last_count = factored - block_began, len(inner_costs)
            per_alteration = (time.perf_counter() - factored) / max(last_count, 1)
            report(progress, done, n_outer, stage="incremental")

        return _Enumerated(
            costs=np.concatenate([np.zeros(0), *costs]),
            values=np.clip(
                np.concatenate([np.zeros(0), *values]), 0.0, problem.objective.max_value
            ),
            blocks=picks,
            offsets=np.cumsum([0, *(altered.costs.size for _, altered in picks)]),
            outer=outer,
            inner=inner,
            n_choices=len(space.choices),
            blocks_done=done,
            next_outer_cost=float(outer_costs[done]) if done < n_outer else np.inf,
            unevaluated=unevaluated,
            evaluations=evaluations,
        )

    def _block_fits(self, deadline, factor_s, per_alteration, last_count, space, budget) -> bool:
        """Whether the next outer block likely ends before ``deadline``: at most the last
        block's count of alterations (its outer cost is no smaller), else counted exactly."""
        left = deadline.remaining()
        if deadline.expired():
            return False
        if left is None or left >= factor_s + per_alteration * last_count:
            return True
        count = space.count_within(budget, self.max_evaluations)
        return left >= factor_s + per_alteration * count


def inner_choices(instance: AttackInstance) -> list[int]:
    """The choices enumerated inside a block (the others are outer: one base solve per pick):
    the smallest regions first, while ``W`` (live states x their rows) stays small."""
    sizes = instance.live_states_per_observation
    size_of = [int(sizes[c.observation]) for c in instance.space.choices]
    n_live = int(instance.live.sum())
    # every inner row saves the outer enumeration a factor; W's memory caps them
    inner_rows = max(INNER_ROWS, min(INNER_ENTRIES // max(n_live, 1), INNER_ROWS_MAX))
    inner, total = [], 0
    for i in sorted(range(len(size_of)), key=lambda i: size_of[i]):
        if total + size_of[i] > inner_rows or size_of[i] > INNER_BLOCK:
            break
        inner.append(i)
        total += size_of[i]
    return inner


def _base_solve(inside, to_target, base_groups, local, live_node):
    """``x0`` and ``W`` (the base chain's solution for ``b`` and for a unit column per inner
    row ``local``), as contiguous arrays: sparse @ dense copies a strided operand per call."""
    rhs = np.zeros((inside.shape[1], 1 + local.size))
    rhs[:, 0] = to_target[base_groups]
    rhs[local, 1 + np.arange(local.size)] = 1.0
    solved = solve_chain(inside[base_groups], rhs, live_node)
    return np.ascontiguousarray(solved[:, 0]), np.ascontiguousarray(solved[:, 1:])


class _Basis(NamedTuple):
    """A base chain (every sensor unaltered) solved for every row that may be altered, with
    the row differences of every option (:class:`_Deltas`, over every inner choice): a chain
    that fixes some sensors' options needs no solve, nor any pass over the chain's states.
    Woodbury on the fixed sensors' rows updates the options' table in low rank."""

    x0: np.ndarray
    W: np.ndarray
    options: _Deltas

    @staticmethod
    def of(inside, to_target, groups, regions, option_groups, live_index, live_node) -> _Basis:
        """``groups``: per live state, its group in the base; ``regions``: per inner choice,
        its live states; ``option_groups``: per inner choice, per state its group under each
        option."""
        rows = np.concatenate([np.zeros(0, dtype=np.int64), *regions]).astype(np.int64)
        local = live_index[rows]
        x0, W = _base_solve(inside, to_target, groups, local, live_node)
        options = _deltas(
            [g[region] for g, region in zip(option_groups, regions, strict=True)],
            groups[local],
            inside,
            to_target,
            x0,
            W,
        )
        return _Basis(x0, W, options)

    def with_fixed(self, fixed, inner, start: int):
        """(value at the start, its row of ``W``, options' table of the ``inner`` choices) of
        the chain whose choices ``fixed`` (position, option) take those options: with ``F``
        their changed rows, ``Z = (I − D_F W_F)⁻¹ [D_F x0 + Δb_F, D_F W]``, every row
        difference ``D`` of an inner option gets ``D W' = D W + (D W_F) Z`` (and its right-hand
        side likewise) and the start's row ``W' = W + W_F Z``."""
        table = self.options
        if fixed:
            changed = np.concatenate(
                [table.flat_start[j, k] + np.arange(table.flat_length[j, k]) for j, k in fixed]
            ).astype(np.int64)
        else:
            changed = np.zeros(0, dtype=np.int64)
        inner = np.asarray(inner, dtype=np.int64)
        flat_start, flat_length = table.flat_start[inner], table.flat_length[inner]
        if start < 0:
            return 0.0, None, table._replace(flat_start=flat_start, flat_length=flat_length)
        x_start, w_start = float(self.x0[start]), self.W[start]
        if not changed.size:
            return x_start, w_start, table._replace(flat_start=flat_start, flat_length=flat_length)
        own = table.column[changed]
        d_w = table.d_w[:, :-1]  # without the pad's column
        system = np.eye(changed.size) - d_w[np.ix_(changed, own)]
        z = np.linalg.solve(system, np.column_stack([table.rhs[changed], d_w[changed]]))
        reach = d_w[:, own]  # D W_F for every row slot (the pad's: zero)
        updated_d_w = table.d_w.copy()
        updated_d_w[:, :-1] += reach @ z[:, 1:]
        return (
            x_start + float(w_start[own] @ z[:, 0]),
            w_start + w_start[own] @ z[:, 1:],
            _Deltas(
                flat_start, flat_length, table.column, table.rhs + reach @ z[:, 0], updated_d_w
            ),
        )


class _Deltas(NamedTuple):
    """The rows an inner option changes: per inner observation ``j`` and option ``k``, the
    rows of its region whose group differs from the base (``flat_length[j, k]`` of them, from
    ``flat_start[j, k]``), each with its ``D W``, its right-hand side ``D x0 + Δb`` and its
    column among the inner rows (``column``). Rows an option leaves alone have zero ``D`` and
    ``Δb``, so the Woodbury system needs only the changed ones. A last row slot pads batches:
    its row of ``D W`` and its right-hand side are zero, and so is its column (the last one of
    ``d_w``)."""

    flat_start: np.ndarray
    flat_length: np.ndarray
    column: np.ndarray
    rhs: np.ndarray
    d_w: np.ndarray

    def system(self, slots: np.ndarray) -> np.ndarray:
        """``F = I − D W`` on each row of row ``slots`` (n, k): (n, k, k)."""
        coupling = self.d_w[slots[:, :, None], self.column[slots][:, None, :]]
        return np.eye(slots.shape[1]) - coupling


def _deltas(groups, base_groups, inside, to_target, x0, W) -> _Deltas:
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
    return _Deltas(
        flat_start,
        flat_length,
        np.concatenate([*columns, [W.shape[1]]]).astype(np.int64),
        np.asarray(delta @ x0).ravel() + (to_target[new_g] - to_target[old_g]),
        d_w,
    )


def _add_corrections(
    found,
    altered: AlteredEntries,
    deltas: _Deltas,
    w_start,
    deadline: Deadline | None = None,
    chunk_entries: int | None = None,
    threads: int = 1,
) -> np.ndarray:
    """Add the Woodbury correction to ``found`` for every alteration of ``altered`` (its
    choices are the inner observations); returns which got it (all, unless ``deadline`` passed
    first).

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
    tree = _Tree.of(altered, deltas)
    weight = np.append(w_start, 0.0)[deltas.column]  # per row slot; the pad's is 0
    parents, first_child, n_children = np.unique(
        altered.parent[altered.parent >= 0], return_index=True, return_counts=True
    )
    first_child += 1  # children are numbered after the unaltered alteration, by parent
    order = np.lexsort((tree.width[parents], tree.depth[parents]))

    def run(batch: np.ndarray) -> None:
        if deadline is not None and deadline.expired():
            return
        counts = n_children[batch]
        kids = np.repeat(first_child[batch], counts) + rank_in_group(counts)
        local = np.repeat(np.arange(batch.size), counts)
        found[kids] += _children_of(parents[batch], kids, local, tree, deltas, weight)
        corrected[kids] = True  # batches are disjoint: threads never write the same entry

    n_slots = deltas.rhs.size - 1
    batches = list(_batches(order, tree.width[parents], n_children, n_slots, chunk_entries))
    if threads == 1 or len(batches) == 1:
        for batch in batches:
            run(batch)
    else:  # taken in order, so a cut-short run has still done the smallest alterations
        with ThreadPoolExecutor(max_workers=threads) as pool:
            list(pool.map(run, batches))  # LAPACK and numpy's gathers release the GIL
    return corrected


class _Tree(NamedTuple):
    """Per alteration, its number of entries, of changed rows (``width``) and its first entry;
    per entry, its row slots."""

    depth: np.ndarray
    width: np.ndarray
    first_entry: np.ndarray
    entry_slot: np.ndarray  # per entry: its first row slot
    entry_width: np.ndarray  # per entry: its number of row slots

    @staticmethod
    def of(altered: AlteredEntries, deltas: _Deltas) -> _Tree:
        n = altered.costs.size
        entry_width = deltas.flat_length[altered.choice, altered.option]
        return _Tree(
            depth=np.bincount(altered.alteration, minlength=n),
            width=np.bincount(altered.alteration, weights=entry_width, minlength=n).astype(
                np.int64
            ),
            first_entry=np.searchsorted(altered.alteration, np.arange(n)),
            entry_slot=deltas.flat_start[altered.choice, altered.option],
            entry_width=entry_width,
        )

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


def _batches(order, width, n_children, n_slots, chunk_entries):
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


def _children_of(parents, kids, local, tree: _Tree, deltas: _Deltas, weight) -> np.ndarray:
    """The corrections of the alterations ``kids``, each the parent ``parents[local]`` plus its
    last entry, by the Schur complement of the parent's system ``A`` (rows ``P``):

        s = s_P + (g_E − Yᵀ g_P)ᵀ S⁻¹ (r_E − F_EP y),   Y = A⁻¹ F_PE,   S = F_EE − F_EP Y,

    with ``y = A⁻¹ r_P`` and ``s_P = g_Pᵀ y`` the parent's own correction, ``F = I − D W`` on
    the changed rows, ``r = D x0 + Δb`` and ``g`` the start's row of ``W``. The parents' part
    is batched in numpy; each child's (a few small products and a solve as wide as its last
    entry) is one compiled loop, :func:`_schur_corrections`."""
    rhs = deltas.rhs
    pad = rhs.size - 1
    slots_p = tree.slots(parents, pad)
    system = deltas.system(slots_p)
    inverse = np.linalg.inv(system) if slots_p.shape[1] else system
    y = np.einsum("pij,pj->pi", inverse, rhs[slots_p])
    s_p = np.einsum("pi,pi->p", weight[slots_p], y)
    last = tree.first_entry[kids] + tree.depth[kids] - 1
    first = tree.entry_slot[last].astype(np.int64)
    begin = int(first.min(initial=pad))
    # (A⁻¹ D W(P, E))ᵀ for every later slot E (a child's entry comes after its parent's, so
    # deep parents need few), one row per slot: a child reads its wp numbers at once. Rows
    # gathered first, then columns: one fancy index over three axes costs several times more
    gathered = np.take(deltas.d_w[slots_p.reshape(-1)], deltas.column[begin:pad], axis=1)
    gathered = gathered.reshape(parents.size, slots_p.shape[1], pad - begin)
    out = np.empty(kids.size)
    _schur_corrections(
        slots_p,
        np.matmul(np.swapaxes(gathered, 1, 2), np.swapaxes(inverse, 1, 2)),
        begin,
        y,
        s_p,
        local.astype(np.int64),
        first,
        tree.entry_width[last].astype(np.int64),
        deltas.d_w,
        deltas.column,
        rhs,
        weight,
        out,
    )
    return out


# reassociated sums: LLVM splits the short dot products into parallel chains (10 % on H1); the
# values stay within rounding of a dense solve (tested at 1e-12)
@numba.njit(cache=True, nogil=True, fastmath={"reassoc", "contract"})
def _schur_corrections(
    slots_p, reach, begin, y, s_p, local, first, width, d_w, column, rhs, weight, out
):  # pragma: no cover (compiled; its results are tested against dense solves)
    """Per child ``c`` (parent ``p = local[c]``, last entry's slots ``first[c]`` onwards,
    ``width[c]`` of them): ``out[c] = s_P + grad · S⁻¹ right`` of :func:`_children_of`. With
    ``reach[p]`` the rows ``(A⁻¹ D W(P, s))ᵀ`` of the slots ``s`` from ``begin`` on,
    ``Y = A⁻¹ F_PE = −G`` for ``G = reach[p][E − begin]ᵀ``, so the signs cancel:
    ``S = F_EE − D W(E, P) G``. Padded parent slots have zero
    rows, columns and weights."""
    wp = slots_p.shape[1]
    widest = max(1, width.max()) if width.size else 1
    g = np.empty((widest, wp))  # Gᵀ = (A⁻¹ D W(P, E))ᵀ, one row per slot of E
    row_p = np.empty(wp)  # D W(i, P) of one row i of E
    columns_p = np.empty(wp, dtype=np.int64)
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
            out[c] = total
            continue
        if p != parent:  # children come grouped by parent
            parent = p
            for j in range(wp):
                columns_p[j] = column[slots_p[p, j]]
        for e in range(w):
            for j in range(wp):
                g[e, j] = reach[p, f + e - begin, j]
        for i in range(w):
            row = f + i
            r = rhs[row]
            h = weight[row]
            for j in range(wp):
                row_p[j] = d_w[row, columns_p[j]]
                r += row_p[j] * y[p, j]
                h += g[i, j] * weight[slots_p[p, j]]
            right[i] = r
            grad[i] = h
            for e in range(w):
                v = -d_w[row, column[f + e]]
                if i == e:
                    v += 1.0
                for j in range(wp):
                    v -= row_p[j] * g[e, j]
                schur[i, e] = v
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
        for k in range(w - 1, -1, -1):
            acc = right[k]
            for e in range(k + 1, w):
                acc -= schur[k, e] * right[e]
            right[k] = acc / schur[k, k]
        for i in range(w):
            total += grad[i] * right[i]
        out[c] = total


def _selected(chain, live, group_of_option, chosen) -> np.ndarray:
    """Group of every live state when the options in ``chosen`` are taken."""
    table = group_of_option[np.flatnonzero(live)]
    picked = np.where(chosen[None, :] & (table >= 0), table, -1).max(axis=1)
    single = chain.groups_per_state[np.flatnonzero(live)] == 1
    fallback = group_of_option[np.flatnonzero(live), 0]
    picked = np.where(single, fallback, picked)
    if (picked < 0).any():
        raise AssertionError("a live state has no selected group")
    return picked
