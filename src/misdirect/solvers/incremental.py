"""Enumeration with low-rank updates: one base solve per outer choice, a tiny one per alteration.

Altering an observation changes only the rows of the product chain whose world state emits it.
Observations that cover few product states (sensors) are *inner*: for each choice of the
*outer* ones (the blank reading that covers most of the map), the chain is solved once, for
its value ``x0`` and for ``W = A⁻¹ E_R`` on the inner rows ``R`` (one call of
:func:`misdirect.core.reachability.solve_chain` with all those right-hand sides). An inner
alteration then replaces a few rows, and Sherman–Morrison–Woodbury gives the new value at the
start from an ``|C| x |C|`` system, ``C`` the changed rows:

    x'(q0) = x0(q0) + W(q0, C) [Δb + (I − D W_C)⁻¹ (D x0 + D W_C Δb)]

where ``D`` holds the row differences and ``Δb`` the differences in one-step decoy mass.

Applicable when the choice product has no end component among the states that can reach the
decoy: then ``I − P`` is invertible on them for *every* alteration, and its solution is the
least fixed point. Values within ``NEAR_TIE`` of the best count as tied (the cheapest wins);
the value reported is then re-computed exactly by :func:`misdirect.solve`, like every other.
"""

from __future__ import annotations

import os
import time
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import NamedTuple, TypedDict

import numpy as np

from misdirect.core.alterations import AlteredEntries, rank_in_group
from misdirect.core.attack import prepare
from misdirect.core.evaluate import decoy_probability
from misdirect.core.model import Problem
from misdirect.core.reachability import solve_chain
from misdirect.errors import ProblemError, SolverError
from misdirect.solvers.base import (
    Deadline,
    ProgressCallback,
    Solution,
    Status,
    best_per_budget,
    check_time_limit,
    refuse_options,
    report,
)

INNER_ROWS = 200  # inner observations together may own at least this many product states,
INNER_ENTRIES = 50_000_000  # ... and more while W (live states x inner rows) stays this small
INNER_ROWS_MAX = 3_000  # ... up to this many (the corrections grow with their square)
INNER_BLOCK = 64  # ... and each at most this many (a bigger one is cheaper as an outer one)
MAX_ALTERATIONS = 12_000_000  # listed sparsely: about 2 GiB at 9.6 million (3 of 128 sensors)
THREADS = 2  # corrections computed in parallel by default (both cores of the target machine)
NEAR_TIE = 1e-9  # values this close count as equal: within the updates' rounding error


class NotApplicableError(SolverError):
    """The model can cycle without reaching the decoy; use another method."""


class IncrementalStats(TypedDict):
    """``stats`` of an incremental answer (the JSON's ``stats``)."""

    evaluations: int  # alterations valued (by low-rank updates or solves)
    factorisations: int  # outer choices, each one base solve
    inner_observations: int
    outer_observations: int


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
        if threads is not None and threads < 1:
            raise ProblemError(f"must be at least 1, got {threads}", field="--threads")
        self.max_evaluations = max_evaluations
        self.time_limit = time_limit
        self.threads = min(threads or THREADS, os.cpu_count() or 1)

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
        space, chain, live = instance.space, instance.chain, instance.live
        if instance.cycling.any():
            raise NotApplicableError(
                "the chain can cycle without reaching the decoy under some alteration, so "
                "low-rank updates are not safe here; use --method auto, exhaustive or milp"
            )
        options = chain.options
        observations = [c.observation for c in space.choices]
        if not observations:
            value = decoy_probability(problem, problem.identity())
            return [Solution(b, problem.identity(), value, upper_bound=value) for b in budgets]

        live_index = np.full(chain.n_states, -1)
        live_index[live] = np.arange(int(live.sum()))
        n_live = int(live.sum())
        state_obs = problem.pomdp.observation_of[chain.world_state]
        rows_of = {o: np.flatnonzero(live & (state_obs == o)) for o in observations}
        order = sorted(range(len(observations)), key=lambda i: rows_of[observations[i]].size)
        # every inner row saves the outer enumeration a factor; W's memory caps them
        inner_rows = max(INNER_ROWS, min(INNER_ENTRIES // max(n_live, 1), INNER_ROWS_MAX))
        inner, total = [], 0
        for i in order:
            size = rows_of[observations[i]].size
            if total + size > inner_rows or size > INNER_BLOCK:
                break
            inner.append(i)
            total += size
        outer = [i for i in range(len(observations)) if i not in inner]

        # per state: the group each option selects (single-group states: that group)
        first_option = np.concatenate([[0], np.cumsum([c.size for c in space.choices])])
        group_of_option = _group_of_option(chain, live)
        to_target = chain.one_step()
        inside = chain.transitions[:, np.flatnonzero(live)].tocsr()  # (G, n_live)
        start = int(live_index[chain.initial]) if live[chain.initial] else -1
        live_node = chain.node[live]  # memory nodes: a separator for solve_chain to cut along

        costs, values, picks = [], [], []
        unevaluated = np.inf  # cheapest alteration left unevaluated by the deadline
        done, evaluations = 0, 0
        outer_table, outer_costs = space.within(top, outer)
        # cheapest outer choices first: cut short, every budget below the first outer choice
        # not reached has all its alterations enumerated, so it is still proven
        ranked = np.argsort(outer_costs, kind="stable")
        outer_table, outer_costs = outer_table[ranked], outer_costs[ranked]
        n_outer = len(outer_costs)
        block_s = 0.0  # the last outer block's time: a block is not started with less left
        for outer_pick, outer_cost in zip(outer_table, outer_costs, strict=True):
            left = deadline.remaining()
            if done > 0 and (deadline.expired() or (left is not None and left < block_s)):
                break  # the first (unaltered outer) block always runs
            block_began = time.perf_counter()
            chosen = np.zeros(options.size, dtype=bool)
            for i, k in zip(outer, outer_pick, strict=True):
                chosen[first_option[i] + k] = True
            for i in inner:
                chosen[first_option[i]] = True  # inner observations unaltered in the base
            base_groups = _selected(chain, live, group_of_option, chosen)
            rows = np.concatenate([rows_of[observations[i]] for i in inner]).astype(np.int64)
            local = live_index[rows]
            rhs = np.zeros((n_live, 1 + local.size))  # b, then one unit column per inner row
            rhs[:, 0] = to_target[base_groups]
            rhs[local, 1 + np.arange(local.size)] = 1.0
            solved = solve_chain(inside[base_groups], rhs, live_node)
            # contiguous copies: sparse @ dense ravels (copies) a strided operand on every call
            x0, W = np.ascontiguousarray(solved[:, 0]), np.ascontiguousarray(solved[:, 1:])
            deltas = _deltas(
                [
                    group_of_option[rows_of[observations[i]], first_option[i] : first_option[i + 1]]
                    for i in inner
                ],
                base_groups[live_index[rows]],
                inside,
                to_target,
                x0,
                W,
            )
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
                found[:] = x0[start]
                corrected = _add_corrections(
                    found, altered, deltas, W[start], deadline, threads=self.threads
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
            block_s = time.perf_counter() - block_began
            report(progress, done, n_outer, stage="incremental")

        costs_a, values_a = (
            np.concatenate(costs),
            np.clip(np.concatenate(values), 0.0, problem.objective.max_value),
        )
        offsets = np.cumsum([0, *(altered.costs.size for _, altered in picks)])
        stats: IncrementalStats = {
            "evaluations": evaluations,
            "factorisations": done,
            "inner_observations": len(inner),
            "outer_observations": len(outer),
        }
        picked = best_per_budget(costs_a, values_a, budgets, tolerance=NEAR_TIE)
        complete = [
            (done == n_outer or outer_costs[done] > b + 1e-9) and unevaluated > b + 1e-9
            for b in budgets
        ]
        if not all(complete):
            from misdirect.solvers.branch_and_bound import relaxation_bound

            relaxed = relaxation_bound(problem, top)  # bounds every smaller budget
        solutions = []
        for budget, index, finished in zip(budgets, picked, complete, strict=True):
            within = values_a[costs_a <= budget + 1e-9]
            bound = float(within.max())  # every alteration within the budget was enumerated
            if not finished:
                bound = max(bound, relaxed)
            solutions.append(
                Solution(
                    budget=budget,
                    alteration=self._alpha(problem, space, outer, inner, picks, offsets, index),
                    solver_probability=float(values_a[index]),
                    status=Status.OPTIMAL if finished else Status.TIME_LIMIT,
                    upper_bound=bound,
                    stats=stats,
                )
            )
        return solutions

    @staticmethod
    def _alpha(problem, space, outer, inner, picks, offsets, index):
        block = int(np.searchsorted(offsets, index, side="right")) - 1
        outer_pick, altered = picks[block]
        picked = [*outer_pick, *altered.picks(index - offsets[block], len(inner))]
        return space.alteration(problem, picked, [*outer, *inner])


class _Deltas(NamedTuple):
    """The rows an inner option changes: per inner observation ``j`` and option ``k``, the
    rows of its region whose group differs from the base (``flat_length[j, k]`` of them, from
    ``flat_start[j, k]``), each with its ``D x0``, ``D W`` and ``Δb`` and its column among the
    inner rows (``column``). Rows an option leaves alone have zero ``D`` and ``Δb``, so the
    Woodbury system needs only the changed ones. A last all-zero row pads batches."""

    flat_start: np.ndarray
    flat_length: np.ndarray
    column: np.ndarray
    d_x0: np.ndarray
    d_w: np.ndarray
    d_b: np.ndarray


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
    return _Deltas(
        flat_start,
        flat_length,
        np.concatenate([*columns, pad]).astype(np.int64),
        np.asarray(delta @ x0).ravel(),
        np.asarray(delta @ W),
        to_target[new_g] - to_target[old_g],
    )


def _add_corrections(
    found,
    altered: AlteredEntries,
    deltas: _Deltas,
    w_start,
    deadline: Deadline | None = None,
    chunk_entries: int = 4_000_000,
    threads: int = 1,
) -> np.ndarray:
    """Add the Woodbury correction to ``found`` for every alteration of ``altered`` (its
    choices are the inner observations); returns which got it (all, unless ``deadline`` passed
    first).

    Each alteration solves a system over the rows its options change. Alterations are sorted
    by how many observations they alter (cut short by the deadline, the small budgets are
    complete and stay proven), then by their number of rows, and solved in batches padded to
    the widest system of the batch with the zero row: its unknown is 0 and it adds nothing.
    Every gather is one fancy index, so the cost is LAPACK's, not Python's per alteration.
    """
    n = altered.costs.size
    corrected = np.zeros(n, dtype=bool)
    which, observation, kind = altered.alteration, altered.choice, altered.option
    length = deltas.flat_length[observation, kind]  # rows each altered entry changes
    width_of = np.bincount(which, weights=length, minlength=n).astype(np.int64)
    n_altered = np.bincount(which, minlength=n)
    corrected[width_of == 0] = True  # no row changes: the base value
    first_entry = np.searchsorted(which, np.arange(n))
    order = np.lexsort((width_of, n_altered))
    order = order[width_of[order] > 0]
    context = (deltas, observation, kind, length, width_of, n_altered, first_entry, w_start)

    def run(batch: np.ndarray) -> None:
        if deadline is not None and deadline.expired():
            return
        found[batch] += _corrections_of(batch, *context)
        corrected[batch] = True  # batches are disjoint: threads never write the same entry

    batches = list(_batches(order, width_of, chunk_entries))
    if threads == 1 or len(batches) == 1:
        for batch in batches:
            run(batch)
    else:  # taken in order, so a cut-short run has still done the smallest alterations
        with ThreadPoolExecutor(max_workers=threads) as pool:
            list(pool.map(run, batches))  # LAPACK and numpy's gathers release the GIL
    return corrected


def _batches(order: np.ndarray, width_of: np.ndarray, chunk_entries: int):
    """Consecutive slices of ``order`` of about ``chunk_entries`` system entries each; a
    slice stops before the first system over twice as wide as its first, to keep the padding
    small."""
    position = 0
    while position < order.size:
        width = int(width_of[order[position]])
        batch = order[position : position + max(1, chunk_entries // (width * width))]
        wider = np.flatnonzero(width_of[batch] > 2 * width)
        if wider.size:
            batch = batch[: wider[0]]
        position += batch.size
        yield batch


def _corrections_of(
    batch, deltas, observation, kind, length, width_of, n_altered, first_entry, w_start
) -> np.ndarray:
    """The Woodbury corrections of the alterations in ``batch``, each padded with the zero
    row to the widest system of the batch."""
    pad_row = deltas.d_x0.size - 1
    # entry e of alteration m fills the slots after the rows of m's earlier entries
    entries = _entries_of(batch, first_entry, n_altered)
    member = np.repeat(np.arange(batch.size), n_altered[batch])
    rows_in = length[entries]
    rep = np.repeat(np.arange(entries.size), rows_in)
    within_entry = rank_in_group(rows_in)
    widths = width_of[batch]
    slot = rank_in_group(widths)
    e = entries[rep]
    r_index = np.full((batch.size, int(widths.max())), pad_row, dtype=np.int64)
    r_index[member[rep], slot] = deltas.flat_start[observation[e], kind[e]] + within_entry
    c_index = deltas.column[r_index]
    n_columns = deltas.d_w.shape[1]
    flat = (r_index * n_columns)[:, :, None] + c_index[:, None, :]
    coupling = np.take(deltas.d_w.reshape(-1), flat)  # D W on the changed rows, (b, w, w)
    b_rows = deltas.d_b[r_index]
    rhs = deltas.d_x0[r_index] + np.einsum("crk,ck->cr", coupling, b_rows)
    np.negative(coupling, out=coupling)
    diagonal = coupling.reshape(batch.size, -1)[:, :: r_index.shape[1] + 1]
    diagonal += 1.0  # the system I - D W, in place
    correction = np.linalg.solve(coupling, rhs[..., None])[..., 0]
    return np.einsum("cr,cr->c", b_rows + correction, w_start[c_index])


def _entries_of(batch, first_entry, n_altered) -> np.ndarray:
    """Indices of the altered entries of the alterations in ``batch``, in batch order."""
    counts = n_altered[batch]
    return np.repeat(first_entry[batch], counts) + rank_in_group(counts)


def _group_of_option(chain, live) -> np.ndarray:
    """(Q, K) group index each option selects in each state (its only group if it has one)."""
    n_states, n_options = chain.n_states, chain.options.size
    table = np.full((n_states, max(n_options, 1)), -1, dtype=np.int64)
    single = chain.groups_per_state == 1
    first = np.zeros(n_states, dtype=np.int64)
    first[chain.group_state[::-1]] = np.arange(chain.n_groups)[::-1]
    table[single] = first[single][:, None]
    coo = chain.group_options.tocoo()
    table[chain.group_state[coo.row], coo.col] = coo.row
    # options of other observations leave a multi-group state's choice to its own observation
    return table


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
