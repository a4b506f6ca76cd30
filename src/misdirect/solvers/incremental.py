"""Enumeration with low-rank updates: one LU per outer choice, a tiny solve per alteration.

Altering an observation changes only the rows of the product chain whose world state emits it.
Observations that cover few product states (sensors) are *inner*: for each choice of the
*outer* ones (the blank reading that covers most of the map), the chain is factorised once and
``W = A⁻¹ E_R`` is computed for the inner rows ``R``. An inner alteration then replaces a few
rows, and Sherman–Morrison–Woodbury gives the new value at the start from an ``|C| x |C|``
system, ``C`` the changed rows:

    x'(q0) = x0(q0) + W(q0, C) [Δb + (I − D W_C)⁻¹ (D x0 + D W_C Δb)]

where ``D`` holds the row differences and ``Δb`` the differences in one-step decoy mass.

Applicable when the choice product has no end component among the states that can reach the
decoy: then ``I − P`` is invertible on them for *every* alteration, and its solution is the
least fixed point. Values within ``NEAR_TIE`` of the best count as tied (the cheapest wins);
the value reported is then re-computed exactly by :func:`misdirect.solve`, like every other.
"""

from __future__ import annotations

from collections.abc import Sequence
from itertools import product as cartesian

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import splu

from misdirect.alterations import alteration_space
from misdirect.choice_product import build_choice_product, end_component_states
from misdirect.errors import SolverError
from misdirect.evaluate import decoy_probability
from misdirect.model import Problem
from misdirect.solvers.base import ProgressCallback, Solution, best_per_budget

INNER_ROWS = 200  # inner observations together may own at most this many product states
NEAR_TIE = 1e-9  # values this close count as equal: within the updates' rounding error


class NotApplicableError(SolverError):
    """The model can cycle without reaching the decoy; use another method."""


class IncrementalSolver:
    name = "incremental"
    curve_is_free = True

    def __init__(self, max_evaluations: int = 5_000_000):
        self.max_evaluations = max_evaluations

    def solve(
        self,
        problem: Problem,
        budgets: Sequence[float],
        *,
        progress: ProgressCallback | None = None,
    ) -> list[Solution]:
        top = max(budgets)
        space = alteration_space(problem.with_budget(top))
        chain = build_choice_product(problem, space)
        live = chain.can_reach_target() & ~chain.target
        if end_component_states(chain.group_state, chain.transitions, live).any():
            raise NotApplicableError(
                "the chain can cycle without reaching the decoy under some alteration"
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
        inner, total = [], 0
        for i in order:
            size = rows_of[observations[i]].size
            if total + size > INNER_ROWS:
                break
            inner.append(i)
            total += size
        outer = [i for i in range(len(observations)) if i not in inner]

        # per state: the group each option selects (single-group states: that group)
        first_option = np.concatenate([[0], np.cumsum([c.size for c in space.choices])])
        group_of_option = _group_of_option(chain, live)
        to_target = np.asarray(chain.transitions @ chain.target.astype(np.float64)).ravel()
        inside = chain.transitions[:, np.flatnonzero(live)].tocsr()  # (G, n_live)
        start = int(live_index[chain.initial]) if live[chain.initial] else -1

        costs, values, picks = [], [], []
        done, evaluations = 0, 0
        n_outer = _count(space, outer, top)
        for outer_pick, outer_cost in _combos(space, outer, top):
            chosen = np.zeros(options.size, dtype=bool)
            for i, k in zip(outer, outer_pick, strict=True):
                chosen[first_option[i] + k] = True
            for i in inner:
                chosen[first_option[i]] = True  # inner observations unaltered in the base
            base_groups = _selected(chain, live, group_of_option, chosen)
            matrix = sp.identity(n_live, format="csc") - inside[base_groups].tocsc()
            lu = splu(matrix)
            b = to_target[base_groups]
            x0 = lu.solve(b)
            rows = np.concatenate([rows_of[observations[i]] for i in inner]).astype(np.int64)
            local = live_index[rows]
            selector = np.zeros((n_live, local.size))
            selector[local, np.arange(local.size)] = 1.0
            W = lu.solve(selector) if local.size else np.zeros((n_live, 0))
            block_start = np.concatenate(
                [[0], np.cumsum([rows_of[observations[i]].size for i in inner])]
            )
            # per inner observation and option: D rows, D x0, D W, Δb
            pieces = {}
            for j, i in enumerate(inner):
                own = rows_of[observations[i]]
                base_g = base_groups[live_index[own]]
                for k in range(space.choices[i].size):
                    new_g = group_of_option[own, first_option[i] + k]
                    delta = inside[new_g] - inside[base_g]
                    pieces[j, k] = (
                        np.asarray(delta @ x0).ravel(),
                        np.asarray(delta @ W),
                        to_target[new_g] - to_target[base_g],
                    )
            w_start = W[start] if start >= 0 else None
            for inner_pick, inner_cost in _combos(space, inner, top - outer_cost):
                evaluations += 1
                if evaluations > self.max_evaluations:
                    raise SolverError(f"more than {self.max_evaluations:,} alterations")
                changed = [(j, k) for j, k in enumerate(inner_pick) if k != 0]
                value = x0[start] if start >= 0 else float(chain.target[chain.initial])
                if changed and start >= 0:
                    cols = np.concatenate(
                        [np.arange(block_start[j], block_start[j + 1]) for j, _ in changed]
                    )
                    d_x0 = np.concatenate([pieces[jk][0] for jk in changed])
                    d_w = np.vstack([pieces[jk][1][:, cols] for jk in changed])
                    d_b = np.concatenate([pieces[jk][2] for jk in changed])
                    inner_rhs = d_x0 + d_w @ d_b
                    correction = np.linalg.solve(np.eye(cols.size) - d_w, inner_rhs)
                    value = value + w_start[cols] @ (d_b + correction)
                costs.append(outer_cost + inner_cost)
                values.append(value)
                picks.append((outer_pick, inner_pick))
            done += 1
            if progress is not None:
                progress(done, n_outer)

        costs_a, values_a = np.array(costs), np.clip(np.array(values), 0.0, 1.0)
        stats = {
            "evaluations": evaluations,
            "factorisations": done,
            "inner_observations": len(inner),
            "outer_observations": len(outer),
        }
        picked = best_per_budget(costs_a, values_a, budgets, tolerance=NEAR_TIE)
        return [
            Solution(
                budget=budget,
                alteration=self._alpha(problem, space, outer, inner, picks[index]),
                claimed_probability=float(values_a[index]),
                upper_bound=float(values_a[index]),
                stats=stats,
            )
            for budget, index in zip(budgets, picked, strict=True)
        ]

    @staticmethod
    def _alpha(problem, space, outer, inner, pick):
        alpha = problem.identity()
        for indices, ks in ((outer, pick[0]), (inner, pick[1])):
            for i, k in zip(indices, ks, strict=True):
                choice = space.choices[i]
                alpha[choice.observation] = choice.targets[k]
        return alpha


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


def _combos(space, indices, budget):
    """Choice vectors over the given observations with total cost ≤ budget."""
    choices = [space.choices[i] for i in indices]
    for pick in cartesian(*(range(c.size) for c in choices)):
        cost = float(sum(c.costs[k] for c, k in zip(choices, pick, strict=True)))
        if cost <= budget + 1e-9:
            yield pick, cost


def _count(space, indices, budget) -> int:
    return sum(1 for _ in _combos(space, indices, budget))
