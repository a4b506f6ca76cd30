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

import time
from collections.abc import Sequence
from typing import TypedDict

import numpy as np

from misdirect.core.attack import prepare
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
    check_time_limit,
    refuse_options,
    report,
)

INNER_ROWS = 200  # inner observations together may own at least this many product states,
INNER_ENTRIES = 50_000_000  # ... and more while W (live states x inner rows) stays this small
INNER_ROWS_MAX = 3_000  # ... up to this many (the corrections grow with their square)
PADDED_ROWS = 48  # up to this many inner rows, every alteration is solved at full size
INNER_BLOCK = 64  # ... and each at most this many (a bigger one is cheaper as an outer one)
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
        self, max_evaluations: int = 5_000_000, time_limit: float | None = None, **options
    ):
        refuse_options(self.name, options, accepted=("time_limit",))
        check_time_limit(time_limit)
        self.max_evaluations = max_evaluations
        self.time_limit = time_limit

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
            block_start = np.concatenate(
                [[0], np.cumsum([rows_of[observations[i]].size for i in inner])]
            )
            # per inner observation j and option k: D x0, D W and Δb on the rows it owns
            d_x0_of, d_w_of, d_b_of = [], [], []
            for i in inner:
                own = rows_of[observations[i]]
                size = space.choices[i].size
                base_g = base_groups[live_index[own]]
                new_g = group_of_option[own, first_option[i] : first_option[i] + size].T
                delta = inside[new_g.ravel()] - inside[np.tile(base_g, size)]
                d_x0_of.append(np.asarray(delta @ x0).reshape(size, own.size))
                d_w_of.append(np.asarray(delta @ W).reshape(size, own.size, W.shape[1]))
                d_b_of.append(to_target[new_g] - to_target[base_g][None, :])
            enumerated = space.within(top - outer_cost, inner, limit=self.max_evaluations)
            if enumerated is None or evaluations + len(enumerated[1]) > self.max_evaluations:
                raise SolverError(f"more than {self.max_evaluations:,} alterations")
            table, inner_costs = enumerated
            evaluations += len(inner_costs)
            found = np.full(len(inner_costs), float(chain.target_value[chain.initial]))
            if start >= 0:
                found[:] = x0[start]
                blocks = (block_start, d_x0_of, d_w_of, d_b_of)
                corrected = _add_corrections(found, table, blocks, W[start], deadline)
                if not corrected.all():  # cut short: those alterations were not evaluated
                    left = float(inner_costs[~corrected].min()) + outer_cost
                    unevaluated = min(unevaluated, left)
                    evaluations -= int((~corrected).sum())
                    inner_costs = np.where(corrected, inner_costs, np.inf)
            costs.append(outer_cost + inner_costs)
            values.append(found)
            picks.append((outer_pick, table))
            done += 1
            block_s = time.perf_counter() - block_began
            report(progress, done, n_outer, stage="incremental")

        costs_a, values_a = (
            np.concatenate(costs),
            np.clip(np.concatenate(values), 0.0, problem.objective.max_value),
        )
        offsets = np.cumsum([0, *(table.shape[0] for _, table in picks)])
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
        outer_pick, table = picks[block]
        picked = [*outer_pick, *table[index - offsets[block]]]
        return space.alteration(problem, picked, [*outer, *inner])


def _add_corrections(
    found, table, blocks, w_start, deadline: Deadline | None = None, chunk_entries: int = 4_000_000
) -> np.ndarray:
    """Add the Woodbury correction to ``found`` for every row of ``table`` (options picked);
    returns which rows got it (all, unless ``deadline`` passed first).

    Option 0 leaves an observation's rows as in the base, so its rows of ``D`` are zero and
    its rows of the small system are identity rows with a zero right-hand side: padding every
    alteration to all inner rows gives the same correction. When the inner rows are few that
    is one batched ``np.linalg.solve`` over all alterations; otherwise alterations that change
    the same observations are batched together, each with only its own rows.
    """
    block_start, d_x0_of, d_w_of, d_b_of = blocks
    n_rows = int(block_start[-1])
    corrected = np.zeros(table.shape[0], dtype=bool)
    if n_rows == 0:
        corrected[:] = True
        return corrected
    if n_rows <= PADDED_ROWS:
        step = max(1, chunk_entries // (n_rows * n_rows))
        identity = np.eye(n_rows)[None, :, :]
        for first in range(0, table.shape[0], step):
            if first > 0 and deadline is not None and deadline.expired():
                return corrected
            corrected[first : first + step] = True
            picked = list(enumerate(table[first : first + step].T))
            d_x0 = np.concatenate([d_x0_of[j][k] for j, k in picked], axis=1)
            d_b = np.concatenate([d_b_of[j][k] for j, k in picked], axis=1)
            d_w = np.concatenate([d_w_of[j][k] for j, k in picked], axis=1)
            rhs = d_x0 + np.einsum("crk,ck->cr", d_w, d_b)
            correction = np.linalg.solve(identity - d_w, rhs[..., None])[..., 0]
            found[first : first + step] += (d_b + correction) @ w_start
        return corrected
    altered = table != 0
    if altered.shape[1] <= 62:  # one integer per pattern: far faster to group than rows
        codes = altered @ (np.int64(1) << np.arange(altered.shape[1], dtype=np.int64))
    else:  # one byte string per pattern (np.unique over rows sorts 100x slower)
        packed = np.ascontiguousarray(np.packbits(altered, axis=1))
        codes = packed.view(np.dtype((np.void, packed.shape[1]))).ravel()
    _, first, which = np.unique(codes, return_index=True, return_inverse=True)
    patterns = altered[first]
    which = which.ravel()
    grouped = np.argsort(which, kind="stable")  # the rows of each pattern, one slice each
    bounds = np.concatenate([[0], np.cumsum(np.bincount(which, minlength=len(patterns)))])
    # fewest altered observations first (the first is "alter none of them"): cut short by the
    # deadline, the small budgets are complete and stay proven
    by_size = np.argsort(patterns.sum(axis=1), kind="stable")
    for step_index, index in enumerate(by_size):
        pattern = patterns[index]
        if step_index > 0 and deadline is not None and deadline.expired():
            return corrected
        members = grouped[bounds[index] : bounds[index + 1]]
        corrected[members] = True
        support = np.flatnonzero(pattern)
        if support.size == 0:
            continue
        cols = np.concatenate([np.arange(block_start[j], block_start[j + 1]) for j in support])
        if cols.size == 0:  # the altered observations own no live rows: nothing changes
            continue
        step = max(1, chunk_entries // (cols.size * cols.size))
        for first in range(0, members.size, step):
            rows = members[first : first + step]
            picked = [table[rows, j] for j in support]
            d_x0 = np.concatenate(
                [d_x0_of[j][k] for j, k in zip(support, picked, strict=True)], axis=1
            )
            d_b = np.concatenate(
                [d_b_of[j][k] for j, k in zip(support, picked, strict=True)], axis=1
            )
            d_w = np.concatenate(
                # the columns first: indexing by ``k`` first would copy every inner column
                [d_w_of[j][:, :, cols][k] for j, k in zip(support, picked, strict=True)], axis=1
            )
            rhs = d_x0 + np.einsum("crk,ck->cr", d_w, d_b)
            system = np.eye(cols.size)[None, :, :] - d_w
            correction = np.linalg.solve(system, rhs[..., None])[..., 0]
            found[rows] += (d_b + correction) @ w_start[cols]
    return corrected


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
