"""A budget-aware upper bound: Lagrangian relaxation of the budget, charged once per entry.

The per-state MDP relaxation of :mod:`misdirect.solvers.branch_and_bound` lets every product
state of a free observation deviate, so with dozens of sensors it lets dozens of them change at
once, whatever the budget. This module bounds ``max {V(α) : c(α) ≤ r}`` over the alterations
``α`` of a branch-and-bound node (some observations fixed, the free ones within the remaining
budget ``r``) by

    UB(λ) = λ r + G(λ)        for any λ ≥ 0,

where ``G(λ)`` is the optimal value of the **mode MDP** below, which is at least
``V(α) − λ c_free(α)`` for every such ``α`` (``c_free``: the cost of its free observations).
Since ``c_free(α) ≤ r``, ``UB(λ) ≥ V(α)``: every λ gives a proven bound, the search over λ
only makes it tighter.

**The mode MDP.** A run passes through the region of an observation (its live product states)
in *segments*: maximal stretches of consecutive states of that observation. On entering a
segment of a free observation ``o`` the scheduler picks a layer for the whole segment: the
default (its states take the unaltered group) or an affordable option ``k`` of ``o`` (every
state of the segment takes option ``k``'s group; consistent within a segment, free only across
segments), and option ``k`` costs ``λ · c_k / M_o``, with ``c_k`` its cost and ``M_o`` an upper
bound on the expected number of entries into
``o``'s region under any alteration of the node (the maximal expected number of entries over
the schedulers of the segment MDP at the search's root, from the start; computed by
:meth:`SegmentRelaxation.compute_entries`; without it every charge is 0). An alteration
``α`` is one scheduler of it: on every entry into an observation ``α`` alters, take ``α``'s
option. Its charges add up, in expectation, to
``λ Σ_{o altered} c_o E_α[entries into o] / M_o ≤ λ Σ c_o ≤ λ c_free(α)``.

The run and the charges stop at the decoy and at states that cannot reach it (their value is
0 under every scheduler, so a scheduler never pays there). Values are computed exactly by
policy iteration, which needs every policy to leave the live states with probability 1: the
bound is offered only when the choice product has no end component among its live states
(then no scheduler of the mode MDP, whose runs project onto runs of the choice product, has
one either). Otherwise :meth:`BudgetBound.create` returns None.
"""

from __future__ import annotations

import contextlib
import functools
import heapq
import threading
import time
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.linalg import lu_factor, lu_solve
from scipy.sparse.linalg import splu
from threadpoolctl import threadpool_limits

from misdirect.core.alterations import AlterationSpace, rank_in_group
from misdirect.core.choice_product import ChoiceProduct, end_component_states
from misdirect.solvers.base import Deadline

IMPROVE_TOLERANCE = 1e-12  # policy iteration switches a choice only on a larger gain
LOW_RANK = 32  # a policy differing from a factorised one in at most this many states is
# solved by Woodbury from that factorisation (a few solves, against a new LU of 13 ms on H1)
BUDGET_SLACK = 1e-9


@dataclass
class LagrangeResult:
    bound: float  # min over the multipliers tried of λ r + G(λ)
    multiplier: float  # the λ that gave it
    tried: int  # multipliers evaluated
    evaluations: int  # policy evaluations (linear solves)


class _UpdatedLU:
    """Solves ``A' = A + U Vᵀ`` from the LU of ``A`` (Woodbury): ``U`` the unit columns of the
    ``rows`` whose choice changed, ``Vᵀ = A'[rows] − A[rows]``. A policy improvement switches
    a few entries' choices; their rows are all that changes."""

    def __init__(self, base, rows: np.ndarray, delta: sp.csr_matrix):
        self.base, self.rows, self.delta = base, rows, delta
        units = np.zeros((delta.shape[1], rows.size))
        units[rows, np.arange(rows.size)] = 1.0
        self.z = base.solve(units)  # A⁻¹ U
        self.capacitance = lu_factor(np.eye(rows.size) + delta @ self.z)  # I + Vᵀ A⁻¹ U
        self.q = None  # A⁻ᵀ V, for transposed solves

    def solve(self, b: np.ndarray, trans: str = "N") -> np.ndarray:
        if trans == "N":
            y = self.base.solve(b)
            return y - self.z @ lu_solve(self.capacitance, self.delta @ y)
        if self.q is None:
            self.q = self.base.solve(self.delta.T.toarray(), trans="T")
        y = self.base.solve(b, trans="T")
        return y - self.q @ lu_solve(self.capacitance, y[self.rows], trans=1)


class _PolicyIteration:
    """Max expected total reward of a transient MDP given by rows (choices)."""

    def __init__(self, row_state: np.ndarray, matrix: sp.csr_matrix, n_states: int):
        self.row_state = row_state
        self.matrix = matrix
        self.n_states = n_states
        order = np.lexsort((np.arange(row_state.size), row_state))
        self.sorted_rows = order
        ordered = row_state[order]
        starts = np.flatnonzero(np.concatenate([[True], ordered[1:] != ordered[:-1]]))
        if not row_state.size:
            starts = starts[:0]
        self.state_start = starts  # in sorted order, one per state (every state has a row)
        if starts.size != n_states:
            raise AssertionError("every state of the mode MDP needs a choice")
        self.evaluations = 0

    def first_rows(self) -> np.ndarray:
        return self.sorted_rows[self.state_start]

    def factorise(self, policy: np.ndarray):
        """LU of ``I − P`` for the chain that takes row ``policy[x]`` in ``x``: it solves
        for any reward on it (``solve``), and for visits (``solve(·, trans="T")``)."""
        self.evaluations += 1
        return splu((sp.identity(self.n_states, format="csc") - self.matrix[policy]).tocsc())

    def updated(self, base, base_policy: np.ndarray, policy: np.ndarray):
        """A solver for ``policy``'s system from ``base``, the factorisation of
        ``base_policy``'s: Woodbury on the rows that differ, if few; else None."""
        rows = np.flatnonzero(policy != base_policy)
        if rows.size > LOW_RANK:
            return None
        self.evaluations += 1
        delta = self.matrix[base_policy[rows]] - self.matrix[policy[rows]]  # of I − P
        return _UpdatedLU(base, rows, delta.tocsr())

    def optimise(
        self,
        reward: np.ndarray,
        policy: np.ndarray | None = None,
        *,
        start: int | None = None,
        enough: float = np.inf,
    ):
        """(values, policy, its factorisation, whether optimal), from ``policy`` (default:
        first rows). Stops early at a policy worth more than ``enough`` at ``start``: the
        optimum is above it too (each improvement only raises the values)."""
        if policy is None:
            policy = self.first_rows()
        lu = base = self.factorise(policy)
        base_policy = policy
        while True:
            values = lu.solve(reward[policy])
            if start is not None and values[start] > enough:
                return values, policy, lu, False
            score = self.matrix @ values + reward
            order = np.lexsort((-score, self.row_state))
            best = order[self.state_start]
            gain = score[best] - score[policy]
            switch = gain > IMPROVE_TOLERANCE * np.maximum(1.0, np.abs(values))
            if not switch.any():
                return values, policy, lu, True
            policy = np.where(switch, best, policy)
            lu = self.updated(base, base_policy, policy)
            if lu is None:
                lu = base = self.factorise(policy)
                base_policy = policy


class BudgetBound:
    """The Lagrangian bound for the nodes of one branch-and-bound search (one choice product)."""

    def __init__(self, chain: ChoiceProduct, state_obs: np.ndarray, live: np.ndarray):
        self.chain = chain
        self.state_obs = state_obs
        self.live = live
        self.live_index = np.full(chain.n_states, -1)
        self.live_states = np.flatnonzero(live)
        self.live_index[self.live_states] = np.arange(self.live_states.size)
        # each observation's region (its live states, ascending) and every live state's rank
        # in its region: a layer copy of the region keeps that order
        by_obs = self.live_states[np.argsort(state_obs[self.live_states], kind="stable")]
        observations, firsts, counts = np.unique(
            state_obs[by_obs], return_index=True, return_counts=True
        )
        self.region = {
            int(o): by_obs[first : first + count]
            for o, first, count in zip(observations, firsts, counts, strict=True)
        }
        self.rank_in_region = np.full(chain.n_states, -1)
        self.rank_in_region[by_obs] = rank_in_group(counts)
        self.evaluations = 0

    @classmethod
    def create(cls, chain: ChoiceProduct, state_obs: np.ndarray) -> BudgetBound | None:
        live = chain.can_reach_target() & ~chain.target
        cycling = end_component_states(chain.group_state, chain.transitions, live)
        if cycling.any():
            return None
        return cls(chain, state_obs, live)

    def lagrangian_on(
        self,
        mdp,
        remaining,
        *,
        stop_below=-np.inf,
        max_multipliers=12,
        policy=None,
        known_bound=np.inf,
    ):
        """(result, policy at the best multiplier, its factorisation) of the Lagrangian on a
        built segment MDP; policy iteration starts from ``policy`` (a parent's, say).

        With ``known_bound`` (a bound proven before, e.g. the parent's) and nothing charged,
        policy iteration stops at the first policy worth more than ``stop_below``: the node
        cannot be pruned, and ``known_bound`` stands as its bound. Its search then branches
        on that policy's usage, the parent's scheduler carried over: on H1 that made the tree
        less than half as large as branching on the re-optimised one."""
        start = mdp.start
        if start is None:
            value = float(self.chain.target_value[self.chain.initial])
            return LagrangeResult(value, 0.0, 0, 0), None, None
        lines: list[tuple[float, float]] = []  # (value at λ, slope) of h at the multipliers tried
        best = (np.inf, 0.0)
        best_policy = best_lu = None
        lam = 0.0
        positive = mdp.charge[mdp.charge > 0]
        high = 1.0 / max(float(positive.min(initial=1.0)), 1e-300)
        if not positive.size:
            max_multipliers = 1  # nothing is charged: λ changes nothing
        lo_line = hi_line = None
        cut = np.isfinite(known_bound) and not positive.size  # one multiplier, λ = 0
        for _ in range(max_multipliers):
            reward = mdp.reward_const - lam * mdp.charge
            values, policy, lu, optimal = mdp.solver.optimise(
                reward, policy, start=start, enough=stop_below if cut else np.inf
            )
            g = float(values[start]) if optimal else float(known_bound)
            k = float(lu.solve(mdp.charge[policy])[start]) if positive.size else 0.0
            h = lam * remaining + g
            slope = remaining - k
            if h < best[0]:
                best = (h, lam)
                best_policy, best_lu = policy, lu
            if best[0] <= stop_below:
                break
            lines.append((lam, h, slope))
            if slope >= -1e-12:  # h grows from here: the minimum is at or left of λ
                hi_line = (lam, h, slope) if hi_line is None or lam < hi_line[0] else hi_line
            else:
                lo_line = (lam, h, slope) if lo_line is None or lam > lo_line[0] else lo_line
            if hi_line is None:
                # no multiplier yet where h grows: jump far right
                lam = high if lam < high else 2 * lam + 1
                continue
            if lo_line is None:
                break  # slope ≥ 0 at the smallest λ tried (λ = 0 first): minimum there
            # Kelley step: where the two supporting lines cross
            (l1, h1, s1), (l2, h2, s2) = lo_line, hi_line
            if s2 - s1 <= 1e-15:
                break
            cross = (h1 - s1 * l1 - (h2 - s2 * l2)) / (s2 - s1)
            if not l1 < cross < l2:
                break
            predicted = h1 + s1 * (cross - l1)
            if best[0] - predicted <= 1e-12:
                break
            lam = cross
        self.evaluations += mdp.solver.evaluations
        result = LagrangeResult(best[0], best[1], len(lines), mdp.solver.evaluations)
        return result, best_policy, best_lu


class _ModeMdp:
    """The segment MDP of a node.

    States: every live product state in the *default layer* (it takes its default group: the
    node's fixed pick, or option 0 of a free observation), and, for every free observation
    ``o`` and affordable non-trivial option ``k`` of it, a copy of ``o``'s live states in
    layer ``(o, k)`` (they take the group of option ``k``). A run that moves into the region
    of a free observation from another observation's state arrives at an *entry* state, where
    the scheduler picks the layer of the segment: default (free) or ``(o, k)`` (charged
    ``λ · charge[(o, k)]``). Within a segment the layer stays; the only choices are at entries.

    Rows, in order: the default layer's, the layer copies', the entries' default choices, the
    entries' layer choices (layer by layer, each in its region's order).
    """

    def __init__(self, owner: BudgetBound, default_group: np.ndarray, layers, charges, keys=None):
        """``default_group``: per product state, its group in the default layer (-1 if not
        live); ``layers``: list of (observation, group per product state of it);
        ``charges``: per layer, the charge per unit of λ; ``keys``: per layer, a number naming
        it across nodes (for :meth:`entry_choices` and :meth:`policy_from`)."""
        chain, live, state_obs = owner.chain, owner.live, owner.state_obs
        live_states, live_index, rank = owner.live_states, owner.live_index, owner.rank_in_region
        n_live = live_states.size
        layer_obs = np.array([o for o, _ in layers], dtype=np.int64)
        free = live & np.isin(state_obs, layer_obs)
        free_states = np.flatnonzero(free)
        entry_index = np.full(chain.n_states, -1)
        entry_index[free_states] = n_live + np.arange(free_states.size)
        regions = [owner.region[o] for o, _ in layers]
        sizes = np.array([r.size for r in regions], dtype=np.int64)
        layer_of = np.repeat(np.arange(len(layers)), sizes)  # per layer copy state
        layer_states = np.concatenate([np.zeros(0, dtype=np.int64), *regions])
        first_copy = n_live + free_states.size + np.concatenate([[0], np.cumsum(sizes)[:-1]])
        copy_index = first_copy[layer_of] + rank[layer_states]  # per layer copy state
        n = n_live + free_states.size + layer_states.size
        self.n = n
        if not live[chain.initial]:
            self.start = None
        else:
            self.start = int(
                entry_index[chain.initial] if free[chain.initial] else live_index[chain.initial]
            )
        target = chain.target_value  # the decoy's value per state (its weight; 1 by default)

        # the default layer's and the copies' rows, all at once: a move within the source's
        # observation stays in its layer, another goes to the entry (or default) state
        sources = np.concatenate([live_states, layer_states])
        groups = np.concatenate(
            [
                default_group[live_states],
                *(g[r] for (_, g), r in zip(layers, regions, strict=True)),
            ]
        ).astype(np.int64)
        same_layer = np.concatenate([np.full(n_live, -1), first_copy[layer_of]])
        coo = chain.transitions[groups].tocoo()
        to_target = np.bincount(coo.row, weights=coo.data * target[coo.col], minlength=groups.size)
        keep = live[coo.col]
        r, c, p = coo.row[keep], coo.col[keep], coo.data[keep]
        same = state_obs[sources[r]] == state_obs[c]
        within = np.where(same_layer[r] >= 0, same_layer[r] + rank[c], live_index[c])
        elsewhere = np.where(free[c], entry_index[c], live_index[c])
        dest = np.where(same, within, elsewhere)
        n_moving = groups.size
        # entry choices: the default layer (free) or a layer of its observation (charged)
        self.layer_entry_start = n_moving + free_states.size + (first_copy - first_copy[:1])
        entry_source = np.concatenate([entry_index[free_states], entry_index[layer_states]])
        entry_dest = np.concatenate([live_index[free_states], copy_index])
        n_entries = entry_source.size
        entry_rows = n_moving + np.arange(n_entries)
        self.matrix = sp.csr_matrix(
            (
                np.concatenate([p, np.ones(n_entries)]),
                (np.concatenate([r, entry_rows]), np.concatenate([dest, entry_dest])),
            ),
            shape=(n_moving + n_entries, n),
        )
        self.reward_const = np.concatenate([to_target, np.zeros(n_entries)])
        charge = np.asarray(charges, dtype=float)
        self.charge = np.concatenate(
            [np.zeros(n_moving + free_states.size), charge[layer_of] if layers else []]
        )
        row_state = np.concatenate([np.arange(n_live), copy_index, entry_source]).astype(np.int64)
        self.solver = _PolicyIteration(row_state, self.matrix, n)
        self.layer_of_row = np.full(self.matrix.shape[0], -1)
        self.layer_of_row[n_moving + free_states.size :] = layer_of
        self.entry_obs = np.full(n, -1)
        self.entry_obs[entry_index[free_states]] = state_obs[free_states]
        self.free_states, self.entry_index = free_states, entry_index
        self.keys = np.arange(len(layers)) if keys is None else np.asarray(keys, dtype=np.int64)
        self.rank = rank

    def entry_choices(self, policy: np.ndarray) -> dict[int, np.ndarray]:
        """Per layer key chosen somewhere: the product states whose entries choose it."""
        layer = self.layer_of_row[policy[self.entry_index[self.free_states]]]
        chosen = layer >= 0
        states, layer = self.free_states[chosen], layer[chosen]
        return {int(self.keys[j]): states[layer == j] for j in np.unique(layer).tolist()}

    def policy_from(self, choices: dict[int, np.ndarray] | None) -> np.ndarray | None:
        """A policy that makes the entry choices of ``choices`` (another node's, from
        :meth:`entry_choices`) where this MDP has them, the default elsewhere."""
        if not choices:
            return None
        policy = self.solver.first_rows()  # the lowest row: an entry's default choice
        position = {int(key): j for j, key in enumerate(self.keys.tolist())}
        for key, states in choices.items():
            j = position.get(key)
            if j is None:
                continue
            states = states[self.entry_index[states] >= 0]
            policy[self.entry_index[states]] = self.layer_entry_start[j] + self.rank[states]
        return policy

    def layer_usage(self, policy: np.ndarray, lu, n_layers: int) -> np.ndarray:
        """Per layer: the expected number of entries that choose it, under ``policy`` (``lu``
        its factorisation: the visits solve the transposed system)."""
        if self.start is None:
            return np.zeros(n_layers)
        e = np.zeros(self.n)
        e[self.start] = 1.0
        visits = lu.solve(e, trans="T")
        layer = self.layer_of_row[policy]
        chosen = layer >= 0
        return np.bincount(layer[chosen], weights=visits[chosen], minlength=n_layers)

    def entries(self, observations) -> np.ndarray:
        """Per observation: the maximal expected number of entries into its live region over
        the schedulers of this MDP (every alteration of the node is one), from the start."""
        coo = self.matrix.tocoo()
        into = self.entry_obs[coo.col]
        result = np.zeros(len(observations))
        if self.start is None:
            return result
        policy = None
        for j, o in enumerate(observations):
            hit = into == o
            reward = np.bincount(
                coo.row[hit], weights=coo.data[hit], minlength=self.matrix.shape[0]
            )
            first = 1.0 if self.entry_obs[self.start] == o else 0.0
            if not reward.any():
                result[j] = first
                continue
            values, policy, _, _ = self.solver.optimise(reward, policy)
            result[j] = values[self.start] + first
        return result


class SegmentRelaxation:
    """Node bounds of :class:`SegmentSearch`: the segment MDP, and its Lagrangian."""

    def __init__(self, problem, space, chain, relax, instance=None, threads=None):
        self.problem, self.space, self.chain, self.relax = problem, space, chain, relax
        self.instance = instance  # the prepared attack: subtrees can then be enumerated
        self.bases: dict = {}  # their base chains, solved once (incremental's _Basis)
        self.basis_lock = threading.Lock()
        self.threads = threads  # the enumeration's (None: incremental's default)
        self.state_obs = problem.pomdp.observation_of[chain.world_state]
        self.bound = BudgetBound(chain, self.state_obs, relax.live)
        self.order = relax.order  # observations (choice indices) that own live states
        self.entries: dict[int, float] | None = None  # M_o, per choice index
        live = relax.live
        self.live_total = int(live.sum())
        self.region_size = {
            i: self.bound.region[space.choices[i].observation].size for i in self.order
        }

    def completions(self, picks: dict[int, int], remaining: float, limit: int) -> int:
        """How many alterations of the free observations fit ``remaining`` (``limit + 1``
        once more than ``limit``)."""
        free = tuple(self.space.choices[i] for i in self.order if i not in picks)
        return AlterationSpace(free).count_within(remaining, limit)

    @functools.cached_property
    def outer(self) -> list[int]:
        """The choices outer to the enumeration (one base solve per pick of theirs)."""
        from misdirect.solvers.incremental import inner_choices

        inner = set(inner_choices(self.instance))
        return [i for i in range(len(self.space.choices)) if i not in inner]

    def basis_ready(self, picks: dict[int, int]) -> bool:
        """Whether enumerating below ``picks`` needs no new base solve: its outer choices are
        fixed and their base is kept (else the node is bounded first: it may be pruned)."""
        if any(i not in picks for i in self.outer):
            return False
        return tuple(picks[i] for i in self.outer) in self.bases

    def enumerate(self, picks: dict[int, int], budget: float, deadline):
        """The best completion of ``picks`` within ``budget`` (value, picks), enumerated
        exhaustively with low-rank updates; None when cut by ``deadline``."""
        from misdirect.solvers.incremental import IncrementalSolver

        solver = IncrementalSolver(threads=self.threads)
        # a worker that needs a new base builds it alone (the others wait, or use theirs)
        with contextlib.nullcontext() if self.basis_ready(picks) else self.basis_lock:
            found = solver.best_with(self.instance, budget, picks, deadline, self.bases)
        if found is None:
            return None
        value, vector = found
        return value, tuple(int(vector[i]) for i in self.order)

    def complete(self, picks: dict[int, int]) -> tuple[int, ...]:
        """The search's picks (in ``relax.order``) with every unlisted observation unaltered."""
        return tuple(picks.get(i, 0) for i in self.order)

    def layers_of(self, picks: dict[int, int], remaining: float):
        """Per free observation: its affordable options that change some live state."""
        relax = self.relax
        found = []
        default = self.chain.group_of_option
        for i in self.order:
            if i in picks:
                continue
            choice = self.space.choices[i]
            first = relax.first_option[i]
            states = self.bound.region[choice.observation]
            base = default[states, first]
            for k in range(1, choice.size):
                if choice.costs[k] > remaining + BUDGET_SLACK:
                    continue
                groups = default[:, first + k]
                if np.array_equal(groups[states], base):
                    continue
                found.append((i, k, groups))
        return found

    def compute_entries(self, remaining: float) -> None:
        """M_o for every observation, at the root (valid for every node below it)."""
        layers = self.layers_of({}, remaining)
        default_group = self.relax.policy_of(self.complete({}))
        mdp = _ModeMdp(
            self.bound,
            default_group,
            [(self.space.choices[i].observation, g) for i, _, g in layers],
            [1.0] * len(layers),
        )
        observations = sorted({i for i, _, _ in layers})
        values = mdp.entries([self.space.choices[i].observation for i in observations])
        self.entries = dict(zip(observations, values.tolist(), strict=True))
        self.bound.evaluations += mdp.solver.evaluations

    def node(
        self,
        picks: dict[int, int],
        remaining: float,
        stop_below: float,
        warm=None,
        known_bound: float = np.inf,
    ):
        """(bound, per layer usage, layers, entry choices) of the node; its policy iteration
        starts from ``warm``, the entry choices of another node (its parent's, say), and
        stops once the node cannot be pruned when ``known_bound`` (its parent's) is finite."""
        layers = self.layers_of(picks, remaining)
        default_group = self.relax.policy_of(self.complete(picks))
        if self.entries is None:
            charges = [0.0] * len(layers)
        else:
            charges = [
                self.space.choices[i].costs[k] / max(self.entries.get(i, 0.0), 1e-300)
                if self.entries.get(i, 0.0) > 0
                else 0.0
                for i, k, _ in layers
            ]
        mdp = _ModeMdp(
            self.bound,
            default_group,
            [(self.space.choices[i].observation, g) for i, _, g in layers],
            charges,
            keys=[self.relax.first_option[i] + k for i, k, _ in layers],
        )
        result, policy, lu = self.bound.lagrangian_on(
            mdp,
            remaining,
            stop_below=stop_below,
            policy=mdp.policy_from(warm),
            known_bound=known_bound,
        )
        usage = np.zeros(len(layers))
        choices = None
        if policy is not None and layers:
            usage = mdp.layer_usage(policy, lu, len(layers))
            choices = mdp.entry_choices(policy)
        return result, usage, layers, choices


PRUNE_TOLERANCE = 1e-9
NEIGHBOURHOOD = 50_000  # the local search enumerates a neighbourhood of at most this many
BIG_REGION = 0.25  # an observation owning this share of the live states is branched on first


class SegmentSearch:
    """Best-first branch-and-bound for one budget, bounded by :class:`SegmentRelaxation`.

    A node fixes some observations to one candidate each (``picks``, by choice index); the
    rest are free within the ``remaining`` budget. It branches on the free observation whose
    layers the bound's optimal scheduler enters most, and its incumbent rounds that scheduler
    (per observation the layer entered most, most-entered first, within the budget).

    With ``enumerate_at``, a node with at most that many completions is not bounded but
    enumerated exactly (:meth:`IncrementalSolver.best_with`, low-rank updates of a base kept
    per outer pick). The bound cannot see the budget, but it does see which sensors are left:
    on sensor networks a few sensors carry the value (H1: with its top sensor fixed unaltered
    the unlimited attacker gets 0.182, under budget 3's optimum 0.206), so a node that leaves
    a strong sensor out is pruned, and one that alters it has a budget one smaller, soon small
    enough to enumerate. A node that would need a new base solve is bounded first.

    Each node's policy iteration starts from its parent's entry choices (mostly one
    factorisation, against about five from scratch). Whenever the incumbent improves, a local
    search enumerates its neighbourhoods (:meth:`local_search`). ``run(workers=2)`` bounds and
    enumerates two nodes at once from the one heap.
    """

    def __init__(self, seg: SegmentRelaxation, budget: float, seeds=(), enumerate_at: int = 0):
        self.seg, self.budget = seg, budget
        # a node with at most this many completions is enumerated instead of bounded
        enumerable = (
            seg.instance is not None
            and not seg.instance.cycling.any()
            and len(seg.space.choices) > 0
        )
        self.enumerate_at = enumerate_at if enumerable else 0
        self.enumerated = 0  # nodes
        self.enumerated_alterations = 0
        self.best_picks: tuple[int, ...] = seg.complete({})
        self.best_value = -1.0
        self.best_cost = 0.0
        self.evaluated: dict[tuple[int, ...], float] = {}
        self._lock = threading.Condition(threading.RLock())  # the heap and the incumbent
        self._error: BaseException | None = None
        self._in_flight: dict[int, float] = {}  # bound of every node a worker holds
        self._status: str | None = None  # set when the search is over: why
        self._local_running = False
        self._last_node_s = 0.0  # a node is not started with less time left than the last one
        self.searched: set = set()  # neighbourhoods the local search has enumerated
        self.improved = True  # the incumbent changed since the last local search
        self.offer(self.best_picks, self.value(self.best_picks))
        for picks in seeds:
            if picks is not None and seg.relax.cost(picks) <= budget + BUDGET_SLACK:
                self.offer(picks, self.value(picks))
        self.heap: list = []
        self.counter = 0
        self.nodes = self.pruned = 0
        self.pruned_bound = -np.inf
        self.root_bound: float | None = None
        big = [i for i in seg.order if seg.region_size[i] >= BIG_REGION * seg.live_total]
        if big:  # branch on the largest region at once: the root with it free is costly, loose
            i = max(big, key=lambda i: seg.region_size[i])
            costs = seg.space.choices[i].costs
            for k in np.flatnonzero(costs <= budget + BUDGET_SLACK)[::-1].tolist():
                self._push({i: int(k)}, budget - float(costs[k]), np.inf)
        else:
            self._push({}, budget, np.inf)

    def _push(self, picks, remaining, bound, bounded=False, warm=None):
        """``bounded``: ``bound`` is the node's own (not its parent's); ``warm``: the entry
        choices of its parent's bound, where its policy iteration starts."""
        self.counter += 1
        heapq.heappush(self.heap, (-bound, self.counter, picks, remaining, bounded, warm))

    def local_search(self, deadline) -> None:
        """Enumerate the incumbent's neighbourhoods: its altered sensors fixed (what one more
        sensor adds), and all of them but one (swap one); again from a better one.

        Good incumbents early make the search: H1's budget-5 optimum is budget 4's plus one
        sensor, found here in 9 ms; the search itself, from budget 4's, found it at its
        last node (105 s), having pruned every node against the lower value."""
        seg = self.seg
        if not self.enumerate_at:
            return
        while True:
            with self._lock:
                if not self.improved or self._status is not None:
                    return
                self.improved = False
                picks = dict(zip(seg.order, self.best_picks, strict=True))
            outer = {i: picks.get(i, 0) for i in seg.outer}  # one block each
            altered = {i: k for i, k in picks.items() if k and i not in outer}
            for drop in [None, *altered]:
                fixed = {**outer, **{i: k for i, k in altered.items() if i != drop}}
                key = tuple(sorted(fixed.items()))
                remaining = self.budget - seg.relax.cost(seg.complete(fixed))
                if key in self.searched or remaining < -BUDGET_SLACK:
                    continue
                self.searched.add(key)
                if seg.completions(fixed, remaining, NEIGHBOURHOOD) > NEIGHBOURHOOD:
                    continue
                found = seg.enumerate(fixed, self.budget, deadline)
                if found is None or self._status is not None:
                    return  # out of time, or the search is over
                if found[0] > self.best_value + PRUNE_TOLERANCE:
                    self.offer(found[1], self.value(found[1]))

    def value(self, picks: tuple[int, ...]) -> float:
        if picks not in self.evaluated:
            relax = self.seg.relax
            self.evaluated[picks] = float(
                relax.evaluate(relax.policy_of(picks))[relax.chain.initial]
            )
        return self.evaluated[picks]

    def offer(self, picks, value) -> None:
        cost = self.seg.relax.cost(picks)
        with self._lock:
            better = value > self.best_value + PRUNE_TOLERANCE
            tied = value >= self.best_value - PRUNE_TOLERANCE
            # among ties the cheapest, then the first in the picks' order: the same answer
            # whichever worker finds it first
            cheaper = cost < self.best_cost - 1e-12
            same_cost = abs(cost - self.best_cost) <= 1e-12
            if better or (tied and (cheaper or (same_cost and picks < self.best_picks))):
                self.best_picks, self.best_value, self.best_cost = picks, value, cost
                self.improved = self.improved or better

    def open_bound(self) -> float:
        top = -self.heap[0][0] if self.heap else -np.inf
        top = max([top, *self._in_flight.values()])
        ceiling = self.seg.problem.objective.max_value
        return float(min(max(self.best_value, self.pruned_bound, top), ceiling))

    def _prune(self, bound):
        if bound <= self.best_value + PRUNE_TOLERANCE:
            self.pruned += 1
            self.pruned_bound = max(self.pruned_bound, bound)
            return True
        return False

    def run(self, deadline=None, tick=None, max_nodes: int | None = None, workers: int = 1) -> str:
        """Search until every node is pruned or enumerated ("optimal"), the deadline passes
        ("time_limit") or ``max_nodes`` were bounded ("feasible"). ``workers`` threads take
        nodes from the one heap: the bounds' factorisations and the enumeration's compiled
        loop release the GIL, so two workers use both cores."""
        deadline = deadline or Deadline(None)
        self._status = None
        if workers <= 1:
            self._work(deadline, tick, max_nodes)
        else:
            threads = [
                threading.Thread(target=self._work, args=(deadline, tick, max_nodes))
                for _ in range(workers)
            ]
            # one BLAS thread per worker: OpenBLAS's own threads would spin on the cores the
            # workers need (H1 budget 4: 8.6 s on two workers with them, 6.1 s without)
            with threadpool_limits(limits=1, user_api="blas"):
                for thread in threads:
                    thread.start()
                for thread in threads:
                    thread.join()
        if self._error is not None:
            raise self._error
        return self._status or "optimal"

    def _work(self, deadline, tick, max_nodes) -> None:
        """One worker: take a task, do it outside the lock, apply its result under it."""
        try:
            while (task := self._next_task(deadline, tick, max_nodes)) is not None:
                kind, entry = task
                try:
                    if kind == "local":
                        self.local_search(deadline)
                    elif kind == "enumerate":
                        self._do_enumerate(entry, deadline)
                    else:
                        self._do_node(entry)
                finally:
                    with self._lock:
                        self._in_flight.pop(entry[1] if entry else -1, None)
                        if kind == "local":
                            self._local_running = False
                        self._lock.notify_all()
        except BaseException as error:  # re-raised by run, in the caller's thread
            with self._lock:
                self._error = error
                self._status = self._status or "error"
                self._lock.notify_all()

    def _next_task(self, deadline, tick, max_nodes):
        """Under the lock: the next node to bound or enumerate (pruned ones are dropped), a
        local search, or None when the search is over (``_status`` then says why)."""
        with self._lock:
            while True:
                if self._status is not None:
                    return None
                left = deadline.remaining()
                if deadline.expired() or (left is not None and left < self._last_node_s):
                    self._status = "time_limit"
                    self._lock.notify_all()
                    return None
                if max_nodes is not None and self.nodes >= max_nodes:
                    self._status = "feasible"
                    self._lock.notify_all()
                    return None
                if self.improved and self.enumerate_at and not self._local_running:
                    self._local_running = True
                    return "local", None
                if self.heap:
                    entry = heapq.heappop(self.heap)
                    negative, token, picks, remaining, bounded, _ = entry
                    if self._prune(-negative):
                        continue
                    kind, count = "node", self.enumerate_at + 1
                    if self.enumerate_at:
                        count = self.seg.completions(picks, remaining, self.enumerate_at)
                        # a node needing a new base solve is bounded first (it may be pruned)
                        if count <= self.enumerate_at and (bounded or self.seg.basis_ready(picks)):
                            kind = "enumerate"
                    entry = (*entry, count)
                    if kind == "node":
                        self.nodes += 1
                        if tick is not None and self.nodes % 16 == 0:
                            tick()
                    self._in_flight[token] = -negative
                    return kind, entry
                if not self._in_flight and not self._local_running:
                    self._status = "optimal"
                    self._lock.notify_all()
                    return None
                self._lock.wait(0.05)  # another worker's node may branch

    def _do_enumerate(self, entry, deadline) -> None:
        negative, _, picks, remaining, _, _, count = entry
        found = self.seg.enumerate(picks, self.budget, deadline)
        exact = None
        if found is not None and found[0] > self.best_value + PRUNE_TOLERANCE:
            exact = self.value(found[1])  # re-evaluated exactly, outside the lock
        with self._lock:
            if found is None:  # cut by the deadline: the node stays open
                self._push(picks, remaining, -negative, bounded=True)
                self._status = self._status or "time_limit"
                return
            self.enumerated += 1
            self.enumerated_alterations += count
            if exact is not None:
                self.offer(found[1], exact)

    def _do_node(self, entry) -> None:
        seg = self.seg
        choices = seg.space.choices
        negative, _, picks, remaining, _, warm, count = entry
        began = time.perf_counter()
        result, usage, layers, entry_choices = seg.node(
            picks, remaining, self.best_value + PRUNE_TOLERANCE, warm, known_bound=-negative
        )
        # both proven: the node's own and the one it was pushed with (its parent's)
        bound = min(float(result.bound), -negative, seg.problem.objective.max_value)
        if not layers:  # nothing affordable changes anything: the node is one alteration
            rounded = seg.complete(picks)
        else:  # round the scheduler to an alteration within the budget
            chosen, left = dict(picks), remaining
            for j in np.argsort(-usage, kind="stable"):
                if usage[j] <= 0:
                    break
                i, k, _ = layers[j]
                if i in chosen or choices[i].costs[k] > left + BUDGET_SLACK:
                    continue
                chosen[i] = k
                left -= float(choices[i].costs[k])
            rounded = seg.complete(chosen)
        value = self.value(rounded)
        with self._lock:
            self._last_node_s = time.perf_counter() - began
            if self.root_bound is None:
                self.root_bound = bound
            self.offer(rounded, value)
            if not layers or self._prune(bound):
                return
            if count <= self.enumerate_at:  # bounded, not pruned: enumerated next
                self._push(picks, remaining, bound, bounded=True)
                return
            per_obs: dict[int, float] = {}
            for (i, _, _), u in zip(layers, usage, strict=True):
                per_obs[i] = per_obs.get(i, 0.0) + float(u)
            big = [i for i in per_obs if seg.region_size[i] >= BIG_REGION * seg.live_total]
            # a region covering much of the map (the blank reading) first: its layers make the
            # MDP large and the bound loose; then the observation the scheduler enters most
            branch = max(
                big or per_obs,
                key=lambda i: (seg.region_size[i], per_obs[i]) if big else per_obs[i],
            )
            ranked = sorted(
                (
                    k
                    for k in range(choices[branch].size)
                    if choices[branch].costs[k] <= remaining + BUDGET_SLACK
                ),
                key=lambda k: (
                    -sum(
                        u
                        for (i, kk, _), u in zip(layers, usage, strict=True)
                        if i == branch and kk == k
                    )
                ),
            )
            for k in ranked:
                child = dict(picks)
                child[branch] = int(k)
                self._push(
                    child, remaining - float(choices[branch].costs[k]), bound, warm=entry_choices
                )


def segment_relaxation(problem, budget: float) -> SegmentRelaxation | None:
    """The segment relaxation of ``problem`` for budgets up to ``budget``; None when the choice
    product has an end component among its live states (policy iteration needs none)."""
    from misdirect.core.attack import prepare
    from misdirect.solvers.branch_and_bound import _Relaxation

    instance = prepare(problem, budget)
    space, chain = instance.space, instance.chain
    state_obs = problem.pomdp.observation_of[chain.world_state]
    if BudgetBound.create(chain, state_obs) is None:
        return None
    relax = _Relaxation(problem, space, chain)
    return SegmentRelaxation(problem, space, chain, relax, instance)


def segment_bound(problem, budget: float, *, lagrangian: bool = False) -> float | None:
    """Bound of the root node (every observation free): the segment MDP, with the Lagrangian
    of the budget when ``lagrangian`` (which first computes M_o, one policy iteration per
    observation). None where the relaxation does not apply."""
    seg = segment_relaxation(problem, budget)
    if seg is None:
        return None
    if lagrangian:
        seg.compute_entries(budget)
    return min(float(seg.node({}, budget, -np.inf)[0].bound), problem.objective.max_value)
