"""The segment relaxation: a budget-aware node bound, the Lagrangian of the budget charged
once per entry into a sensor's region (one idea; its parts are the *segment MDP* and the
*Lagrangian* over it).

The per-state MDP relaxation (:mod:`misdirect.solvers.engines.per_state`) lets every product
state of a free observation deviate, so with dozens of sensors it lets dozens of them change at
once, whatever the budget. This module bounds ``max {V(α) : c(α) ≤ r}`` over the alterations
``α`` of a branch-and-bound node (some observations fixed, the free ones within the remaining
budget ``r``) by

    UB(λ) = λ r + G(λ)        for any λ ≥ 0,

where ``G(λ)`` is the optimal value of the **segment MDP** below, which is at least
``V(α) − λ c_free(α)`` for every such ``α`` (``c_free``: the cost of its free observations).
Since ``c_free(α) ≤ r``, ``UB(λ) ≥ V(α)``: every λ gives a proven bound, the search over λ
only makes it tighter.

**The segment MDP.** A run passes through the region of an observation (its live product states)
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
charges apply only when the choice product has no end component among its live states
(then no scheduler of the mode MDP, whose runs project onto runs of the choice product, has
one either); with end components the states in them get a stop row instead.

**Proven.** Policy iteration's values are rounded (on a model with probabilities of 1e-12
the root value lay 2.8e-5 of itself below the optimum), so a node's bound is a proof built
from them (:meth:`SegmentMdp.proven_value`), and so is each ``M_o`` (a charge computed from
too few entries would overcharge).
"""

from __future__ import annotations

import functools
import threading
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from misdirect.core import tolerance
from misdirect.core.alterations import AlterationSpace, rank_in_group
from misdirect.core.attack import AttackInstance, prepare
from misdirect.core.choice_product import ChoiceProduct
from misdirect.core.model import Problem
from misdirect.solvers.base import thread_count
from misdirect.solvers.deadline import Deadline
from misdirect.solvers.engines.lowrank import BasisCache, LowRankEnumeration
from misdirect.solvers.engines.per_state import PerStateRelaxation
from misdirect.solvers.engines.policy_iteration import MaxReachability
from misdirect.solvers.engines.transient import LinearSolver, TransientPolicyIteration

Layer = tuple[int, int, np.ndarray]  # (choice index, option, group per product state)


@dataclass
class LagrangeResult:
    bound: float  # min over the multipliers tried of λ r + G(λ)
    multiplier: float  # the λ that gave it
    tried: int  # multipliers evaluated
    evaluations: int  # policy evaluations (linear solves)


class SegmentLagrangian:
    """The Lagrangian bound for the nodes of one branch-and-bound search (one choice product)."""

    def __init__(
        self,
        chain: ChoiceProduct,
        state_obs: np.ndarray,
        live: np.ndarray,
        cycling: np.ndarray | None = None,
    ):
        self.chain = chain
        self.state_obs = state_obs
        self.live = live
        # live states in some end component of the choice product: their copies may stop
        self.cycling = np.zeros(chain.n_states, dtype=bool) if cycling is None else cycling
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
        self._potential_lock = threading.Lock()
        self._potential: tuple[np.ndarray | None] | None = None  # computed once, on first use

    def potential(self, deadline: Deadline | None = None) -> np.ndarray | None:
        """Per live state, a proven ``N(s) ≥ STEP_MARGIN + P_g N`` over every group ``g`` of
        the choice product (restricted to the live states): every segment MDP built on it
        falls along it at every step (:class:`SegmentMdp`), which is what proves its bounds.
        None with end components (runs may last for ever) or where it cannot be proven.
        Raises :class:`DeadlineExpiredError` once ``deadline`` has passed (computed again on
        the next call)."""
        with self._potential_lock:
            if self._potential is None:
                self._potential = (self._proven_potential(deadline),)
            return self._potential[0]

    def _proven_potential(self, deadline: Deadline | None) -> np.ndarray | None:
        if self.cycling.any() or not self.live_states.size:
            return None
        chain = self.chain
        groups = np.flatnonzero(self.live[chain.group_state])
        rows = chain.transitions[groups][:, self.live_states].tocsr()
        mdp = TransientPolicyIteration(
            self.live_index[chain.group_state[groups]], rows, self.live_states.size
        )
        return mdp.proven_potential(deadline)

    def lagrangian_on(
        self,
        mdp: SegmentMdp,
        remaining: float,
        *,
        stop_below: float = -np.inf,
        max_multipliers: int = 12,
        policy: np.ndarray | None = None,
        known_bound: float = np.inf,
        deadline: Deadline | None = None,
    ) -> tuple[LagrangeResult, np.ndarray | None, LinearSolver | None]:
        """(result, policy at the best multiplier, its factorisation) of the Lagrangian on a
        built segment MDP; policy iteration starts from ``policy`` (a parent's, say).

        With ``known_bound`` (a bound proven before, e.g. the parent's) and nothing charged,
        policy iteration stops at the first policy worth more than ``stop_below``: the node
        cannot be pruned, and ``known_bound`` stands as its bound. Its search then branches
        on that policy's usage, the parent's scheduler carried over, which keeps the tree
        smaller than branching on the re-optimised one (bench/hard_instances.py)."""
        start = mdp.start
        if start is None:
            value = float(self.chain.target_value[self.chain.initial])
            return LagrangeResult(value, 0.0, 0, 0), None, None
        lines: list[tuple[float, float, float]] = []  # (λ, h(λ), slope) at the multipliers tried
        best = (np.inf, 0.0)
        best_policy = best_lu = best_values = None
        lam = 0.0
        positive = mdp.charge[mdp.charge > 0]
        high = 1.0 / max(float(positive.min(initial=1.0)), tolerance.DENOMINATOR_FLOOR)
        if not positive.size:
            max_multipliers = 1  # nothing is charged: λ changes nothing
        lo_line = hi_line = None
        cut = np.isfinite(known_bound) and not positive.size  # one multiplier, λ = 0
        for _ in range(max_multipliers):
            reward = mdp.reward_const - lam * mdp.charge
            values, policy, lu, optimal = mdp.solver.optimise(
                reward,
                policy,
                start=start,
                enough=stop_below if cut else np.inf,
                deadline=deadline,
            )
            g = float(values[start]) if optimal else float(known_bound)
            k = float(lu.solve(mdp.charge[policy])[start]) if positive.size else 0.0
            h = lam * remaining + g
            slope = remaining - k
            if h < best[0]:
                best = (h, lam)
                best_policy, best_lu = policy, lu
                best_values = values if optimal else None
            if best[0] <= stop_below:
                break
            lines.append((lam, h, slope))
            if slope >= -tolerance.slack(
                remaining, k, rel=tolerance.TIE
            ):  # h grows from here: the minimum is at or left of λ
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
            if s2 - s1 <= tolerance.slack(s1, s2, rel=tolerance.TIE):
                break
            cross = (h1 - s1 * l1 - (h2 - s2 * l2)) / (s2 - s1)
            if not l1 < cross < l2:
                break
            predicted = h1 + s1 * (cross - l1)
            if best[0] - predicted <= tolerance.slack(best[0], predicted, rel=tolerance.TIE):
                break
            lam = cross
        self.evaluations += mdp.solver.evaluations
        bound = float(known_bound)  # proven before; the multipliers' values are rounded
        if best_values is not None:
            assert best_policy is not None  # it comes with the values
            # λ r rounded up (one product), then the sum
            charged = float(np.nextafter(best[1] * remaining, np.inf)) if best[1] > 0 else 0.0
            prune_at = stop_below - charged if np.isfinite(stop_below) else None
            g = mdp.proven_value(best[1], best_values, best_policy, deadline, best_lu, prune_at)
            bound = min(bound, tolerance.round_up(charged + g))
        result = LagrangeResult(bound, best[1], len(lines), mdp.solver.evaluations)
        return result, best_policy, best_lu


class SegmentMdp:
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

    def __init__(
        self,
        owner: SegmentLagrangian,
        default_group: np.ndarray,
        layers: Sequence[tuple[int, np.ndarray]],
        charges: Sequence[float],
        keys: Sequence[int] | None = None,
        deadline: Deadline | None = None,
    ):
        """``default_group``: per product state, its group in the default layer (-1 if not
        live); ``layers``: list of (observation, group per product state of it);
        ``charges``: per layer, the charge per unit of λ; ``keys``: per layer, a number naming
        it across nodes (for :meth:`entry_choices` and :meth:`policy_from`); ``deadline``:
        the first MDP of a search computes its owner's potential, a policy iteration that
        raises :class:`DeadlineExpiredError` once it has passed."""
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
        self.start: int | None
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
        # the same raised past its rounding: what proofs use
        raised = _raised(to_target, np.bincount(coo.row, minlength=groups.size))
        self.reward_up = np.concatenate([raised, np.zeros(n_entries)])
        self.top = float(target.max(initial=0.0))
        # a proven potential, falling by 1 along every row (SegmentLagrangian.potential):
        # twice N in the layers, once more at the entries (whose choice is a step of its own)
        potential = owner.potential(deadline)
        self.potential: np.ndarray | None = None
        if potential is not None:
            twice = 2 * potential
            self.potential = np.concatenate(
                [
                    twice,
                    np.nextafter(twice[live_index[free_states]] + 1, np.inf),
                    twice[live_index[layer_states]],
                ]
            )
        charge = np.asarray(charges, dtype=float)
        self.charge = np.concatenate(
            [np.zeros(n_moving + free_states.size), charge[layer_of] if layers else []]
        )
        row_state = np.concatenate([np.arange(n_live), copy_index, entry_source]).astype(np.int64)
        # rows whose run leaves the live states (to the decoy or where it cannot be reached)
        leaks = np.bincount(coo.row[~keep], minlength=self.matrix.shape[0]) > 0
        # stop rows: every copy of a state in an end component may give the run up (value 0,
        # nothing charged), after the rows above, so no policy needs to cycle forever
        cycling = owner.cycling
        stopping = np.concatenate(
            [live_index[live_states[cycling[live_states]]], copy_index[cycling[layer_states]]]
        ).astype(np.int64)
        stop_row = None
        if stopping.size:
            n_rows = self.matrix.shape[0]
            self.matrix = sp.vstack([self.matrix, sp.csr_matrix((stopping.size, n))], format="csr")
            self.reward_const = np.concatenate([self.reward_const, np.zeros(stopping.size)])
            self.reward_up = np.concatenate([self.reward_up, np.zeros(stopping.size)])
            self.potential = None  # runs may stay for ever: the proof is by reachability
            self.charge = np.concatenate([self.charge, np.zeros(stopping.size)])
            row_state = np.concatenate([row_state, stopping])
            leaks = np.concatenate([leaks, np.ones(stopping.size, dtype=bool)])
            stop_row = np.full(n, -1, dtype=np.int64)
            stop_row[stopping] = n_rows + np.arange(stopping.size)
        self.solver = TransientPolicyIteration(
            row_state, self.matrix, n, leaks=leaks, stop_row=stop_row
        )
        self.layer_of_row = np.full(self.matrix.shape[0], -1)
        self.layer_of_row[n_moving + free_states.size : n_moving + n_entries] = layer_of
        self.entry_obs = np.full(n, -1)
        self.entry_obs[entry_index[free_states]] = state_obs[free_states]
        self.free_states, self.entry_index = free_states, entry_index
        self.keys = np.arange(len(layers)) if keys is None else np.asarray(keys, dtype=np.int64)
        self.rank = rank

    def proven_value(
        self,
        lam: float,
        values: np.ndarray,
        policy: np.ndarray,
        deadline: Deadline | None = None,
        lu: LinearSolver | None = None,
        prune_at: float | None = None,
    ) -> float:
        """A proven upper bound on ``G(λ)``, this MDP's optimum at the start with every
        charge at ``λ``, from policy iteration's ``values`` and ``policy`` (inf if none is
        found); ``prune_at``: the search's threshold for it, which spares a refinement that
        cannot change the decision (:meth:`TransientPolicyIteration.proven_bound`). Rewards
        are read raised past their rounding, charges lowered: the bound is then on an MDP
        that pays at least as much as the exact one.

        Without end components, by the potential (:meth:`TransientPolicyIteration.
        proven_bound`: one pass over the rows). With them nothing is charged, and the MDP is
        one of reachability: a target state worth the largest decoy weight, entered with
        probability ``reward / top`` (:meth:`MaxReachability.proven_bound`, end components
        and ill-conditioned chains included)."""
        assert self.start is not None
        charged = np.nextafter(lam * self.charge, 0.0) if lam > 0 else np.zeros_like(self.charge)
        reward = np.nextafter(self.reward_up - charged, np.inf)
        if self.potential is not None:
            return self.solver.proven_bound(
                reward, values, self.start, self.potential, policy, lu, prune_at
            )
        if (charged > 0).any() or self.top <= 0:
            return np.inf
        return self._reachability().proven_bound(
            np.concatenate([values, [self.top, 0.0]]),
            np.concatenate([policy, self.matrix.shape[0] + np.arange(2)]),
            self.start,
            deadline=deadline,
        )

    def _reachability(self) -> MaxReachability:
        """This MDP, uncharged, as one of reachability with stochastic rows: two more
        states, the target (worth ``top``), entered with (at least) each row's reward over
        ``top``, and a sink that takes what is left of each row."""
        n, n_rows = self.n, self.matrix.shape[0]
        into = np.nextafter(self.reward_up / self.top, np.inf) * (self.reward_up > 0)
        left = np.maximum(1.0 - (np.asarray(self.matrix.sum(axis=1)).ravel() + into), 0.0)
        rows = np.arange(n_rows)
        extra = sp.csr_matrix(
            (np.concatenate([into, left]), (np.tile(rows, 2), np.repeat([0, 1], n_rows))),
            shape=(n_rows, 2),
        )
        loops = sp.csr_matrix(([1.0, 1.0], ([0, 1], [n, n + 1])), shape=(2, n + 2))
        transitions = sp.vstack([sp.hstack([self.matrix, extra]), loops], format="csr")
        transitions.eliminate_zeros()
        owner = np.concatenate([self.solver.row_state, [n, n + 1]])
        target = np.zeros(n + 2, dtype=bool)
        target[n] = True
        value = np.where(target, self.top, 0.0)
        return MaxReachability(owner, transitions, target, value=value)

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

    def layer_usage(self, policy: np.ndarray, lu: LinearSolver, n_layers: int) -> np.ndarray:
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

    def entries(self, observations: Sequence[int], deadline: Deadline | None = None) -> np.ndarray:
        """Per observation: the maximal expected number of entries into its live region over
        the schedulers of this MDP (every alteration of the node is one), from the start.
        Infinite for all where the chain has end components: a run may then circle back into
        a region nearly surely (the maximum grew past 10^7 on a turn-back grid), and nothing is
        charged."""
        coo = self.matrix.tocoo()
        into = self.entry_obs[coo.col]
        result = np.zeros(len(observations))
        if self.start is None:
            return result
        if self.solver.stop_row is not None:
            return np.full(len(observations), np.inf)
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
            values, policy, _, optimal = self.solver.optimise(reward, policy, deadline=deadline)
            # a proven bound: a charge computed from less than the most entries overcharges
            if not optimal or self.potential is None:
                result[j] = np.inf
                continue
            terms = np.bincount(coo.row[hit], minlength=self.matrix.shape[0])
            raised = _raised(reward, terms)
            bound = self.solver.proven_bound(raised, values, self.start, self.potential)
            result[j] = np.nextafter(bound + first, np.inf)
        return result


class SegmentRelaxation:
    """Node bounds of :class:`SegmentSearch`: the segment MDP, and its Lagrangian."""

    def __init__(
        self, instance: AttackInstance, relax: PerStateRelaxation, threads: int | None = None
    ):
        problem, space, chain = instance.problem, instance.space, instance.chain
        self.problem, self.space, self.chain, self.relax = problem, space, chain, relax
        self.instance = instance  # the prepared attack: subtrees can then be enumerated
        self.bases = BasisCache()  # their base chains, solved once
        self.threads = thread_count(threads)  # the enumeration's
        self.state_obs = problem.pomdp.observation_of[chain.world_state]
        self.bound = SegmentLagrangian(chain, self.state_obs, relax.live, instance.cycling)
        self.order = relax.order  # observations (choice indices) that own live states
        self.entries: dict[int, float] | None = None  # M_o, per choice index
        live = relax.live
        self.live_total = int(live.sum())
        self.region_size = {
            i: self.bound.region[space.choices[i].observation].size for i in self.order
        }

    def free_space(self, picks: dict[int, int]) -> AlterationSpace:
        """The alterations of the observations ``picks`` leaves free."""
        free = tuple(self.space.choices[i] for i in self.order if i not in picks)
        return AlterationSpace(free, self.space.scale)

    def completions(self, picks: dict[int, int], remaining: float, limit: int) -> int:
        """How many alterations of the free observations fit ``remaining`` (``limit + 1``
        once more than ``limit``)."""
        return self.free_space(picks).count_within(remaining, limit)

    @functools.cached_property
    def enumeration(self) -> LowRankEnumeration:
        """The low-rank enumeration of subtrees (built on first use; raises
        :class:`~misdirect.solvers.engines.lowrank.NotApplicableError` where it cannot apply)."""
        return LowRankEnumeration(self.instance, threads=self.threads)

    @property
    def outer(self) -> list[int]:
        """The choices outer to the enumeration (one base solve per pick of theirs)."""
        return self.enumeration.natural_outer

    def basis_ready(self, picks: dict[int, int]) -> bool:
        """Whether enumerating below ``picks`` needs no new base solve: its outer choices are
        fixed and their base is kept (else the node is bounded first: it may be pruned)."""
        key = self.enumeration.basis_key(picks)
        return key is not None and key in self.bases

    def enumerate(
        self,
        picks: dict[int, int],
        budget: float,
        deadline: Deadline,
        floor: float | None = None,
    ) -> tuple[float, tuple[int, ...], bool, float] | None:
        """The best completion of ``picks`` within ``budget`` (value, picks, whether it is
        the best of them all, and the best value of any completion valued: near-ties go to
        the cheapest, so it may lie a tie above ``value``), enumerated with low-rank updates:
        when ``deadline`` cuts the run short, the best of those valued (a candidate, not a
        proof); None when none was. With ``floor`` (the incumbent's value), only completions
        that may reach it count."""
        found = self.enumeration.best_with(budget, picks, deadline, self.bases, floor)
        if found is None:
            return None
        picked = tuple(int(found.picks[i]) for i in self.order)
        return found.value, picked, found.complete, found.bound

    @property
    def budget_blind(self) -> bool:
        """Whether the node bounds cannot see the budget: with end components among the live
        states nothing is charged (:meth:`SegmentMdp.entries`), so a node is pruned only
        where its free observations, each as often as it likes, cannot beat the incumbent;
        elsewhere only enumerating proves anything."""
        return bool(self.bound.cycling.any())

    def complete(self, picks: dict[int, int]) -> tuple[int, ...]:
        """The search's picks (in ``relax.order``) with every unlisted observation unaltered."""
        return tuple(picks.get(i, 0) for i in self.order)

    def layers_of(self, picks: dict[int, int], remaining: float) -> list[Layer]:
        """Per free observation: its affordable options that change some live state."""
        relax = self.relax
        found: list[Layer] = []
        default = self.chain.group_of_option
        for i in self.order:
            if i in picks:
                continue
            choice = self.space.choices[i]
            first = relax.first_option[i]
            states = self.bound.region[choice.observation]
            base = default[states, first]
            for k in range(1, choice.size):
                if choice.costs[k] > remaining:  # a cap (CostScale.cap) less what was spent
                    continue
                groups = default[:, first + k]
                if np.array_equal(groups[states], base):
                    continue
                found.append((i, k, groups))
        return found

    def compute_entries(self, remaining: float, deadline: Deadline | None = None) -> None:
        """M_o for every observation, at the root (valid for every node below it); raises
        :class:`DeadlineExpiredError` if ``deadline`` passes first."""
        layers = self.layers_of({}, remaining)
        default_group = self.relax.policy_of(self.complete({}))
        mdp = SegmentMdp(
            self.bound,
            default_group,
            [(self.space.choices[i].observation, g) for i, _, g in layers],
            [1.0] * len(layers),
            deadline=deadline,
        )
        observations = sorted({i for i, _, _ in layers})
        values = mdp.entries([self.space.choices[i].observation for i in observations], deadline)
        self.entries = dict(zip(observations, values.tolist(), strict=True))
        self.bound.evaluations += mdp.solver.evaluations

    def node(
        self,
        picks: dict[int, int],
        remaining: float,
        stop_below: float,
        warm: dict[int, np.ndarray] | None = None,
        known_bound: float = np.inf,
        deadline: Deadline | None = None,
    ) -> tuple[LagrangeResult, np.ndarray, list[Layer], dict[int, np.ndarray] | None]:
        """(bound, per layer usage, layers, entry choices) of the node; its policy iteration
        starts from ``warm``, the entry choices of another node (its parent's, say), and
        stops once the node cannot be pruned when ``known_bound`` (its parent's) is finite.
        Raises :class:`DeadlineExpiredError` if ``deadline`` passes first."""
        layers = self.layers_of(picks, remaining)
        default_group = self.relax.policy_of(self.complete(picks))
        if self.entries is None:
            charges = [0.0] * len(layers)
        else:
            # lowered past their rounding: a charge above c / M_o would overcharge
            charges = [
                float(np.nextafter(self.space.choices[i].costs[k] / self.entries[i], 0.0))
                if self.entries.get(i, 0.0) > 0
                else 0.0
                for i, k, _ in layers
            ]
        mdp = SegmentMdp(
            self.bound,
            default_group,
            [(self.space.choices[i].observation, g) for i, _, g in layers],
            charges,
            keys=[self.relax.first_option[i] + k for i, k, _ in layers],
            deadline=deadline,
        )
        result, policy, lu = self.bound.lagrangian_on(
            mdp,
            self.space.scale.snap(remaining),
            stop_below=stop_below,
            policy=mdp.policy_from(warm),
            known_bound=known_bound,
            deadline=deadline,
        )
        usage = np.zeros(len(layers))
        choices = None
        if policy is not None and layers:
            assert lu is not None  # it comes with the policy
            usage = mdp.layer_usage(policy, lu, len(layers))
            choices = mdp.entry_choices(policy)
        return result, usage, layers, choices


def _raised(sums: np.ndarray, terms: np.ndarray) -> np.ndarray:
    """Row sums of ``terms`` products each, computed in doubles, raised past their rounding
    (Higham's bound, doubled, plus a subnormal per product that may underflow)."""
    relative = sums * (1 + 2.02 * (terms + 2) * tolerance.UNIT_ROUNDOFF)
    return np.where(sums > 0, relative + (terms + 1) * tolerance.SMALLEST, relative)


def segment_relaxation(problem: Problem, budget: float) -> SegmentRelaxation | None:
    """The segment relaxation of ``problem`` for budgets up to ``budget`` (on chains with end
    components too: their states get stop rows, and nothing is charged)."""
    instance = prepare(problem, budget)
    relax = PerStateRelaxation(problem, instance.space, instance.chain, instance.cycling)
    return SegmentRelaxation(instance, relax)


def segment_bound(problem: Problem, budget: float, *, lagrangian: bool = False) -> float | None:
    """Bound of the root node (every observation free): the segment MDP, with the Lagrangian
    of the budget when ``lagrangian`` (which first computes M_o, one policy iteration per
    observation). None where the relaxation does not apply."""
    seg = segment_relaxation(problem, budget)
    if seg is None:
        return None
    cap = seg.space.scale.cap(budget)
    if lagrangian:
        seg.compute_entries(cap)
    return min(float(seg.node({}, cap, -np.inf)[0].bound), problem.objective.max_value)
