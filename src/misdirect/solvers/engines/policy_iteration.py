"""Maximal reachability by policy iteration, for MDPs that may have end components.

:class:`MaxReachability`: maximal reachability of a target (or the maximal expected value of
the first target state entered). Each policy is evaluated exactly as the *least* fixed point
(:func:`misdirect.core.reachability.reach_probabilities`), so a policy that cycles forever
scores 0, and a state switches only on a strict gain. It starts from a policy under which every
state that can reach the target does, and refuses a switch that would strand one
(:meth:`MaxReachability.proper`): from any other, a cycle scored 0 is left, then re-entered,
round after round. At termination the values are a fixed point of the Bellman operator
attained by some policy; every fixed point lies above the least one, which is the optimum, and
no policy lies above the optimum: so they are the optimum. The per-state relaxation and the
defender's MDPs use it. Its values are floating-point solutions, so the bound the searches
prune with is :meth:`MaxReachability.proven_bound`: a vector checked, with the rounding of
the check accounted for, to be a pre-fixed point of the Bellman operator, which lies above the
optimum (Knaster–Tarski); where end components defeat that check, the MDP with its end
components collapsed proves it (:mod:`misdirect.solvers.engines.end_components`). MDPs without
end components: :mod:`misdirect.solvers.engines.transient`.
"""

from __future__ import annotations

from collections.abc import Callable
from functools import cached_property
from typing import Literal, cast, overload

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import breadth_first_order, connected_components

from misdirect.core import residual, tolerance
from misdirect.core.choice_product import end_component_states
from misdirect.core.model import reachable_from, with_super_source
from misdirect.core.reachability import reach_probabilities, solve_chain
from misdirect.errors import SolverError
from misdirect.solvers.deadline import Deadline
from misdirect.solvers.engines.end_components import collapsed_bound

# A proof costs a few linear solves, like a round or two of policy iteration; one that does
# not verify within these gives the trivial bound.
PROOF_TRIES = 2  # offsets a proven bound tries after the first (each PROOF_GROWTH times more)
PROOF_GROWTH = 64.0
PROOF_LIFTS = 4  # rounds of raising the states a check fails at (ties, end components)...
PROOF_ROUNDS = 3  # ...before the other states are solved again above the raised ones
EXTENDED_TRIES = 1  # the same in double-double
EXTENDED_REFINE = 2  # refinement rounds (one solve each) of the double-double values
EXTENDED_SWITCHES = 3  # policy improvements in double-double, at most
PROOF_TIGHTEN = 2  # Bellman steps applied to a proven pre-fixed point (each one is one too)

# A faster solve of a proof's systems (e.g. on a kept basis, :mod:`misdirect.solvers.engines.
# kept_basis`): ``(policy, free, rhs)`` -> ``x`` with ``x = P_policy x + rhs`` on the ``free``
# states and 0 elsewhere, or None where the caller solves it on the whole chain. It only
# proposes values: every bound is proven by the check.
ChainSolve = Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray | None]


class MaxReachability:
    """An MDP given by its choices: choice ``g`` belongs to state ``owner[g]`` and moves by
    row ``g`` of ``transitions``; ``target`` states score ``value`` (default 1)."""

    def __init__(
        self,
        owner: np.ndarray,
        transitions: sp.csr_matrix,
        target: np.ndarray,
        *,
        blocks: np.ndarray | None = None,
        value: np.ndarray | None = None,
        live: np.ndarray | None = None,
        cycling: np.ndarray | None = None,
    ):
        """``live``: the states outside the target that can reach it (found here if not
        given); ``cycling``: the live states in some end component, if the caller has them
        (:attr:`misdirect.core.attack.AttackInstance.cycling`), else found on first need."""
        n_states = target.size
        owner = np.asarray(owner, dtype=np.int64)
        counts = np.bincount(owner, minlength=n_states)
        if counts.min(initial=1) == 0:
            raise SolverError("every state of the MDP needs at least one choice")
        self.owner, self.transitions, self.target = owner, transitions, target
        self.blocks, self.value = blocks, value
        # position of each state's first choice once choices are sorted by state
        self.state_start = np.concatenate([[0], np.cumsum(counts)[:-1]])
        self.live = self._live() if live is None else live
        self._cycling = cycling
        self.evaluations = 0
        # proofs that needed the end components collapsed, and those that it improved
        self.proofs = 0  # proven bounds asked for
        self.trivial_proofs = 0  # ... that stayed at the largest value, far above the values
        self.collapsed_proofs = 0
        self.collapsed_proven = 0
        self.last_unproven = ""  # why the last collapsed proof found no bound ("": it did)
        self._by_state = np.argsort(owner, kind="stable")  # choices grouped by state
        self._row_excess: tuple[np.ndarray, np.ndarray] | None = None  # row sum less 1

    def _live(self) -> np.ndarray:
        """States outside the target that can reach it under some policy."""
        structure = (self.transitions != 0).astype(np.float64)
        owners = sp.csr_matrix(
            (np.ones(self.owner.size), (self.owner, np.arange(self.owner.size))),
            shape=(self.target.size, self.owner.size),
        )
        graph = (owners @ structure).tocsr()
        return cast(
            np.ndarray, reachable_from(graph.T.tocsr(), np.flatnonzero(self.target)) & ~self.target
        )

    def proper(self, policy: np.ndarray, allowed: np.ndarray | None = None) -> np.ndarray:
        """``policy`` with every live state that cannot reach the target under it switched to
        a choice of ``allowed`` (all, by default) that heads for the target
        (:meth:`_towards_target`). Policy iteration must start from such a policy: a strict
        improvement of one under which every state that can reach the target does never closes
        a cycle (in a closed class, the states of largest value gain nothing, so they kept
        their choices, and their class was closed before: a class of value 0, where nothing
        gains). From any other policy the least fixed point scores a cycle 0, its states
        switch out of it, the cycle opens, they switch back, and the rounds never end (a
        turn-back grid of 8x8 cells did this until the deadline)."""
        if not self._may_cycle:
            return policy
        stuck = self._stuck(policy)
        if not stuck.any():
            return policy
        heading = self._towards_target(allowed)
        return np.where(stuck & (heading >= 0), heading, policy)

    @cached_property
    def _may_cycle(self) -> bool:
        """Whether the MDP has an end component among its live states: without one every
        policy leaves them, so no round can close a cycle, and neither :meth:`proper` nor
        :meth:`_switched` has anything to check (a breadth-first search per round saved)."""
        cycling = self._cycling
        if cycling is None:
            cycling = end_component_states(self.owner, self.transitions, self.live)
        return bool(cycling.any())

    def _stuck(self, policy: np.ndarray) -> np.ndarray:
        """Live states that cannot reach the target under ``policy``."""
        moves = self.transitions[policy]
        reaching = reachable_from(moves.T.tocsr(), np.flatnonzero(self.target))
        return cast(np.ndarray, self.live & ~reaching)

    def _switched(self, policy: np.ndarray, best: np.ndarray, switch: np.ndarray) -> np.ndarray:
        """``policy`` with the states of ``switch`` on their ``best`` choice, but for those
        whose switch would leave a state unable to reach the target. In exact arithmetic no
        strict improvement does (:meth:`proper`); one that does rests on a gain of rounding (on
        the 8x8 turn-back grid, 1.4e-9 on values of 0.9997 whose chain runs long, closing a
        class of 95 states, and the next round switched them back), so it is refused."""
        if not self._may_cycle:
            return np.where(switch, best, policy) if switch.any() else policy
        stuck_before = self._stuck(policy)  # states no allowed choice leads to the target
        while switch.any():
            moved = np.where(switch, best, policy)
            stuck = self._stuck(moved) & ~stuck_before
            if not stuck.any():
                return moved
            undo = switch & stuck
            if not undo.any():
                break  # the closed class holds no switched state: not from a strict gain
            switch = switch & ~undo
        return policy

    def _towards_target(self, allowed: np.ndarray | None) -> np.ndarray:
        """Per state, a choice of ``allowed`` with an entry into a state one step closer to
        the target (breadth-first from the target over the allowed choices), -1 where none
        reaches it: the policy these make reaches the target from every state it can."""
        n = self.target.size
        entries = self.transitions.tocoo()
        keep = entries.data != 0
        if allowed is not None:
            keep &= allowed[entries.row]
        choice, into = entries.row[keep].astype(np.int64), entries.col[keep].astype(np.int64)
        state = self.owner[choice]
        sources = np.flatnonzero(self.target)
        # edges from each state entered back to the state whose choice enters it, and from a
        # virtual source (node n) to every target state
        backward = sp.csr_matrix((np.ones(into.size, dtype=np.int8), (into, state)), shape=(n, n))
        order, parent = breadth_first_order(
            with_super_source(backward, sources), n, directed=True, return_predecessors=True
        )
        found = order[(order < n)]
        found = found[~self.target[found]]
        heading = np.full(n, -1, dtype=np.int64)
        if not found.size:
            return heading
        # the first allowed choice of each found state with an entry into its parent
        key = state * (n + 1) + into
        by_key = np.lexsort((choice, key))
        wanted = found * (n + 1) + parent[found]
        at = np.searchsorted(key[by_key], wanted)
        heading[found] = choice[by_key[at]]
        return heading

    def first_choices(self) -> np.ndarray:
        """The lowest-numbered choice of every state."""
        order = np.argsort(self.owner, kind="stable")
        return cast(np.ndarray, order[self.state_start])

    def evaluate(self, policy: np.ndarray) -> np.ndarray:
        """Exact values of the chain that takes choice ``policy[s]`` in ``s``."""
        self.evaluations += 1
        return reach_probabilities(
            self.transitions[policy], self.target, blocks=self.blocks, value=self.value
        )

    def best_choices(self, score: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per state: the choice of highest score (the first on ties) and that score."""
        order = np.lexsort((-score, self.owner))
        best = order[self.state_start]
        return best, score[best]

    def optimise(
        self,
        policy: np.ndarray,
        penalty: np.ndarray | float = 0.0,
        max_rounds: int | None = None,
        deadline: Deadline | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """(optimal values, an optimal policy) from ``policy``, among the choices whose
        ``penalty`` is 0 (``-inf``: not allowed; ``policy`` must be allowed). Checks
        ``deadline`` before every round (one linear solve each) and raises
        :class:`DeadlineExpiredError` once it has passed."""
        rounds = 0
        allowed = None if np.isscalar(penalty) else np.asarray(penalty) > -np.inf
        policy = self.proper(policy, allowed)
        while True:
            if deadline is not None:
                deadline.check()
            values = self.evaluate(policy)
            score = self.transitions @ values + penalty
            best, best_score = self.best_choices(score)
            # a gain counts relative to the values' scale (a linear solve's error is normwise:
            # relative to the largest value, not to each), so a decoy of weight 1e-12 still
            # improves, and a state of value 1e-9 beside values of 0.2 does not switch on noise
            room = tolerance.IMPROVE * np.maximum(
                np.abs(np.where(np.isfinite(best_score), best_score, 0.0)),
                np.abs(values).max(initial=0.0),
            )
            switch = self.live & (best_score > score[policy] + room)
            moved = self._switched(policy, best, switch)
            if moved is policy:
                return values, policy
            policy = moved
            rounds += 1
            if max_rounds is not None and rounds >= max_rounds:
                raise SolverError(f"policy iteration did not settle in {max_rounds:,} rounds")

    def proven_bound(
        self,
        values: np.ndarray,
        policy: np.ndarray,
        state: int,
        penalty: np.ndarray | float = 0.0,
        deadline: Deadline | None = None,
        *,
        offset: Callable[[np.ndarray], np.ndarray | None] | None = None,
        chain: ChainSolve | None = None,
    ) -> float:
        """A proven upper bound at ``state`` on the optimum among the choices whose ``penalty``
        is 0, from the values and policy :meth:`optimise` returned; the largest target value
        (the trivial bound) when no proof is found. ``offset``: a faster solve of the first
        offset (the expected sum of a cost along ``policy``'s chain, at least the one summed
        until it leaves the states of positive value), e.g. on a kept basis
        (:mod:`misdirect.solvers.engines.kept_basis`); it only proposes ``u``, the check
        decides. ``chain``: a faster solve of the later attempts' systems (:data:`ChainSolve`),
        used where no end component is merged.

        The optimum is the least fixed point of the Bellman operator ``T`` (target states fixed
        at their value, values capped at the largest one: no value of the chain exceeds it),
        so every ``u`` with ``T u <= u`` lies above it (Knaster–Tarski), end components or
        not. ``u`` is policy iteration's values ``v`` plus an offset: the expected sum, along
        the policy's chain until it leaves the states of positive value, of each state's
        defect (how far ``T v`` lies above ``v``, rounding of the check included, plus
        :data:`~misdirect.core.tolerance.PROOF_OFFSET`), doubled. The offset falls along the
        policy by at least the defect, so the policy's rows stay below ``u``. States where
        another choice still lies above ``u`` (a tie) are raised to it, a few rounds, and the
        others solved again above them. A tie that closes a cycle (an end component of the
        tied choices) admits no falling offset: there ``u`` is one constant, which a row that
        stays inside meets exactly (:meth:`_upper`), and the component is one state of the
        policy's chain (:meth:`_tied_components`). ``u`` is accepted only when the check
        ``T u <= u`` holds, each row's product bounded above with its rounding; else the
        offset grows and it tries again. Raises :class:`DeadlineExpiredError` once
        ``deadline`` has passed.

        The order of the attempts: the first offset (no end components); where it fails or
        lies far above the values, the proof in double-double (:meth:`_proven_extended`);
        only where that too is far, the later offsets (with end components, growing). On the
        64-sensor turn-back grid's covers the later offsets never proved what the first did
        not (200 unions: 188 proven by the first, 12 by the double-double after the later
        offsets had failed, a third of the time), and elsewhere the order changed no bound
        (docs/benchmarks.md, "The proofs' order")."""
        target = self.target
        allowed, fixed, top = self._operator(penalty)
        if top <= 0.0 or not target.any():
            return 0.0
        matrix = self.transitions
        if matrix.nnz and matrix.data.min() < 0:
            return top  # not a probability matrix: nothing to prove with
        values = np.where(np.isfinite(values), values, top)
        values = np.clip(np.where(target, fixed, values), 0.0, top)
        positive = ~target & (values > 0) & (values < top)
        bellman = self._upper(values, allowed, target, fixed, top)

        def far(bound: float) -> bool:
            return bool(
                bound - values[state]
                > tolerance.PROOF_EXTENDED * max(values[state], tolerance.SMALLEST)
            )

        found = self._proven_double(
            values, bellman, policy, state, allowed, positive, deadline, offset, chain
        )
        bound = top if found is None else min(found, top)
        # far above the values (a chain absorbed after 10^8 steps: the check's own rounding,
        # 10^-16 a step, adds up): again with the values and the check in double-double
        if far(bound):
            if deadline is not None:
                deadline.check()
            components = self._tied_components(values, bellman, allowed, positive)
            extended = self._proven_extended(
                values, policy, state, allowed, positive, components, deadline, chain
            )
            if extended is not None:
                bound = min(bound, extended)
            if far(bound):  # the later offsets, in double, with the same tied components
                found = self._proven_double(
                    values,
                    bellman,
                    policy,
                    state,
                    allowed,
                    positive,
                    deadline,
                    offset,
                    chain,
                    later=components,
                )
                if found is not None:
                    bound = min(bound, found)
        if bound - values[state] > tolerance.PROOF_COLLAPSE * max(
            values[state], tolerance.SMALLEST
        ):
            # still far: an end component whose choices the guessed offset cannot fall along
            self.collapsed_proofs += 1
            collapsed = collapsed_bound(
                self.owner, matrix, target, fixed, allowed, state, policy, deadline
            )
            self.last_unproven = collapsed.why
            if collapsed.bound is not None and collapsed.bound < bound:
                bound = collapsed.bound
                self.collapsed_proven += 1
        self.proofs += 1
        if bound >= top and values[state] < top * (1 - tolerance.PROOF_COLLAPSE):
            self.trivial_proofs += 1
        return float(bound)

    def _proven_double(
        self,
        values: np.ndarray,
        bellman: np.ndarray,
        policy: np.ndarray,
        state: int,
        allowed: np.ndarray,
        positive: np.ndarray,
        deadline: Deadline | None,
        offset: Callable[[np.ndarray], np.ndarray | None] | None = None,
        chain: ChainSolve | None = None,
        later: np.ndarray | None = None,
    ) -> float | None:
        """:meth:`proven_bound` in double precision, its first offset (without end
        components): the bound, or None; with ``later`` (the tied components), its later
        offsets instead (with them, growing)."""
        target = self.target
        _, fixed, top = self._operator(0.0)
        defect = np.maximum(bellman - values, 0.0)
        cost = np.where(positive, 2 * defect + tolerance.PROOF_OFFSET * top, 0.0)
        components: np.ndarray | None = later
        internal = None if later is None else self._internal(later)
        for attempt in range(1, PROOF_TRIES + 1) if later is not None else range(1):
            if deadline is not None:
                deadline.check()
            if attempt >= 2:
                cost = cost * PROOF_GROWTH
            u = None
            if attempt == 0 and offset is not None:
                collected = offset(cost)
                if collected is not None:
                    u = np.where(positive, values + np.maximum(collected, cost), values)
            if u is None:
                u = self._settle(
                    policy, positive, values, cost, components, offset=attempt == 0, chain=chain
                )
            if u is None:
                continue
            u = np.minimum(u, top)
            raised = np.zeros(positive.size, dtype=bool)
            for round_ in range(PROOF_ROUNDS):
                if deadline is not None:
                    deadline.check()
                for _ in range(PROOF_LIFTS):
                    upper = self._upper(u, allowed, target, fixed, top, internal)
                    failing = upper > u
                    if not failing.any():
                        for _ in range(PROOF_TIGHTEN):  # T u <= u: so is T u, and tighter
                            u = np.minimum(u, self._upper(u, allowed, target, fixed, top, internal))
                        return float(u[state])
                    raised |= failing
                    u = np.maximum(u, upper)
                    if components is not None:
                        u, _ = _flatten(u, np.zeros_like(u), components)
                        raised |= _touched(components, raised)
                if round_ + 1 < PROOF_ROUNDS:  # the others follow the raised states
                    settled = self._settle(
                        policy, positive & ~raised, u, cost, components, chain=chain
                    )
                    if settled is not None:
                        u = np.minimum(settled, top)
        return None

    def _proven_extended(
        self,
        values: np.ndarray,
        policy: np.ndarray,
        state: int,
        allowed: np.ndarray,
        positive: np.ndarray,
        components: np.ndarray,
        deadline: Deadline | None,
        chain: ChainSolve | None = None,
    ) -> float | None:
        """:meth:`proven_bound` with ``u`` a double-double ``hi + lo``: policy iteration's
        values refined on the policy's chain (end components as one state), residuals
        computed exactly enough (:func:`misdirect.core.residual.residual`), so that the
        offset covers what the values lack, not the rounding of the check; the bound, or
        None."""
        top = self._operator(0.0)[2]
        internal = self._internal(components)
        hi, lo = _flatten(values.copy(), np.zeros(values.size), components)
        floor = np.where(positive, tolerance.PROOF_EXTENDED_OFFSET * top, 0.0)
        # policy iteration again, switching on the gains below its room: on a chain that
        # returns 10^7 times to a state, a gain of 10^-16 there is worth 10^-9
        # (in an end component, the member whose way out gains becomes the one whose row
        # the component takes)
        policy = policy.copy()
        prefer = np.zeros(positive.size, dtype=bool)
        inside = components >= 0
        if not self._refine(
            policy, positive, hi, lo, floor, components, EXTENDED_REFINE, chain=chain
        ):
            return None
        for _ in range(EXTENDED_SWITCHES):
            if deadline is not None:
                deadline.check()
            rise, best = self._rise(hi, lo, allowed, internal, choices=True)
            switch = positive & (rise > tolerance.PROOF_EXTENDED_GAIN * top) & (best >= 0)
            if not switch.any():
                break
            tried = np.where(switch, best, policy)
            preferred = (prefer & ~_touched(components, switch)) | (switch & inside)
            new_hi, new_lo = _flatten(hi, lo, components)
            refined = self._refine(
                tried,
                positive,
                new_hi,
                new_lo,
                floor,
                components,
                EXTENDED_REFINE,
                preferred,
                chain=chain,
            )
            # an improvement raises every value; a fall means a solve that went wrong (a
            # chain so close to closing that the switch closed it): keep the last policy
            if (
                not refined
                or ((new_hi - hi) + (new_lo - lo) < -tolerance.PROOF_EXTENDED_GAIN * top).any()
            ):
                break
            policy, prefer, hi, lo = tried, preferred, new_hi, new_lo
        # what the tied choices still gain, doubled
        cost = floor + 2 * np.maximum(rise, 0.0)
        for attempt in range(EXTENDED_TRIES):
            if deadline is not None:
                deadline.check()
            if attempt:
                cost = cost * PROOF_GROWTH
            if not self._refine(
                policy, positive, hi, lo, cost, components, EXTENDED_REFINE, prefer, chain=chain
            ):
                return None
            raised = np.zeros(positive.size, dtype=bool)
            for round_ in range(PROOF_ROUNDS):
                for _ in range(PROOF_LIFTS):
                    rise = self._rise(hi, lo, allowed, internal)
                    failing = rise > 0
                    if not failing.any():
                        return float(np.nextafter(hi[state] + lo[state], np.inf))
                    raised |= failing
                    hi, lo = _raise(hi, lo, np.where(failing, rise, 0.0), top)
                    hi, lo = _flatten(hi, lo, components)
                    raised |= _touched(components, raised)
                if round_ + 1 < PROOF_ROUNDS:
                    if deadline is not None:
                        deadline.check()
                    free = positive & ~raised
                    self._refine(
                        policy, free, hi, lo, cost, components, EXTENDED_REFINE, prefer, chain=chain
                    )
        return None

    def _excess(self) -> tuple[np.ndarray, np.ndarray]:
        """Per choice: lower and upper bounds, in exact arithmetic, on how far its row's sum
        exceeds 1 (0.8 + 0.2 is 1 + 2^-54 in doubles), computed once."""
        if self._row_excess is None:
            n = self.target.size
            ones = np.ones(n)
            r, bound = residual.residual(self.transitions.tocsr(), ones, np.zeros(n), self.owner)
            error = 2 * (bound - np.abs(r))
            self._row_excess = (r - error, r + error)
        return self._row_excess

    def _internal(self, components: np.ndarray | None) -> np.ndarray:
        """Per choice: whether its row stays inside its state's end component."""
        inside = np.zeros(self.owner.size, dtype=bool)
        if components is None or not (components >= 0).any():
            return inside
        matrix = self.transitions
        entry_row = np.repeat(np.arange(self.owner.size), np.diff(matrix.indptr))
        mine = components[self.owner]
        away = (components[matrix.indices] != mine[entry_row]).astype(np.float64)
        stays = np.bincount(entry_row, weights=away, minlength=mine.size) == 0
        return cast(np.ndarray, (mine >= 0) & stays)

    def _refine(
        self,
        policy: np.ndarray,
        free: np.ndarray,
        hi: np.ndarray,
        lo: np.ndarray,
        cost: np.ndarray,
        components: np.ndarray,
        rounds: int,
        prefer: np.ndarray | None = None,
        *,
        chain: ChainSolve | None = None,
    ) -> bool:
        """Refine ``hi + lo`` in place on the ``free`` states towards ``u = P u + cost`` along
        ``policy`` (end components as one state, :meth:`_quotient`), the others fixed:
        residuals in double-double, corrections solved in double (by ``chain`` where no end
        component is merged and it covers the system). False if a solve fails."""
        inner = np.flatnonzero(free)
        if not inner.size:
            return True
        if chain is not None and not _merges(components, inner):
            rows = self.transitions[policy[inner]].tocsr()
            for done in range(rounds):
                r, _ = residual.residual(rows, hi, lo, inner, cost[inner])
                full = np.zeros(free.size)
                full[inner] = r
                correction = chain(policy, free, full)
                if correction is None:
                    if done:  # the rest on the whole chain
                        break
                    return self._refine(policy, free, hi, lo, cost, components, rounds, prefer)
                hi[inner], lo[inner] = residual.add(hi[inner], lo[inner], correction[inner])
            else:
                return True
            rounds -= done
        node, reps, rows, block, labels = self._quotient_chain(
            policy, free, inner, components, prefer
        )
        for _ in range(rounds):
            r, _ = residual.residual(rows, hi, lo, reps, cost[reps])
            correction = _solved_or_none(block, r, labels)
            if correction is None:
                return False
            hi[inner], lo[inner] = residual.add(hi[inner], lo[inner], correction[node])
        return True

    @overload
    def _rise(
        self, hi: np.ndarray, lo: np.ndarray, allowed: np.ndarray, internal: np.ndarray
    ) -> np.ndarray: ...

    @overload
    def _rise(
        self,
        hi: np.ndarray,
        lo: np.ndarray,
        allowed: np.ndarray,
        internal: np.ndarray,
        *,
        choices: Literal[True],
    ) -> tuple[np.ndarray, np.ndarray]: ...

    def _rise(
        self,
        hi: np.ndarray,
        lo: np.ndarray,
        allowed: np.ndarray,
        internal: np.ndarray,
        *,
        choices: bool = False,
    ) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
        """Per state: an upper bound, in exact arithmetic, on ``(T u)(s) - u(s)`` for the
        double-double ``u = hi + lo`` (-inf where nothing is checked: target states and
        states at the largest value, which ``T`` caps); with ``choices``, also the choice
        that attains it (-1 where none)."""
        _, _, top = self._operator(0.0)
        checked = ~self.target & (hi < top)
        chosen = np.flatnonzero(allowed & checked[self.owner])
        rise = np.full(hi.size, -np.inf)
        if not chosen.size:
            return (rise, np.full(hi.size, -1)) if choices else rise
        rows = self.transitions[chosen].tocsr()
        own = self.owner[chosen]
        r, bound = residual.residual(rows, hi, lo, own)
        upper = r + 2 * (bound - np.abs(r))  # |exact - r| <= bound - |r|, doubled for rounding
        # a row inside an end component summing to 1 + e is read divided by its sum
        # (:meth:`_upper`): it may exceed u(s) by e u(s) (less 2^-50 of it for rounding)
        low, high = self._excess()
        inner = internal[chosen]
        upper = upper - np.where(inner, np.maximum(low[chosen], 0.0), 0.0) * hi[own] * (
            1 - 2.0**-50
        )
        # such a row, or one summing to at most 1, whose every successor lies at most at its
        # state's u: at most u (exactly)
        entry_row = np.repeat(np.arange(chosen.size), np.diff(rows.indptr))
        j, s = rows.indices, own[entry_row]
        above = (hi[j] > hi[s]) | ((hi[j] == hi[s]) & (lo[j] > lo[s]))
        below = np.bincount(entry_row, weights=above, minlength=chosen.size) == 0
        below &= inner | (high[chosen] <= 0)
        # a row whose every successor has u = 0 is 0, whatever its sum
        reached = ((hi[j] != 0) | (lo[j] != 0)).astype(np.float64)
        below |= np.bincount(entry_row, weights=reached, minlength=chosen.size) == 0
        upper = np.where(below, np.minimum(upper, 0.0), upper)
        np.maximum.at(rise, own, upper)
        if not choices:
            return rise
        best = np.full(hi.size, -1)
        attains = upper >= rise[own]
        best[own[attains]] = chosen[attains]
        return rise, best

    def pre_fixed(self, u: np.ndarray, penalty: np.ndarray | float = 0.0) -> bool:
        """Whether ``T u <= u`` is proven (``u >= 0``, target states at their value): then
        ``u`` lies above the optimum among the choices whose ``penalty`` is 0."""
        allowed, fixed, top = self._operator(penalty)
        u = np.asarray(u, dtype=np.float64)
        if (
            not (np.isfinite(u).all() and (u >= 0).all())
            or (u[self.target] < fixed[self.target]).any()
        ):
            return False
        if self.transitions.nnz and self.transitions.data.min() < 0:
            return False
        return bool((self._upper(u, allowed, self.target, fixed, top) <= u).all())

    @property
    def top(self) -> float:
        """The objective's largest value: the trivial bound, where a proof falls back to."""
        return self._operator(0.0)[2]

    def _operator(self, penalty: np.ndarray | float) -> tuple[np.ndarray, np.ndarray, float]:
        """The Bellman operator's data: allowed choices, target values, the cap."""
        target = self.target
        top = 1.0 if self.value is None else float(np.max(self.value[target], initial=0.0))
        penalties = np.broadcast_to(np.asarray(penalty, dtype=np.float64), (self.owner.size,))
        fixed = np.where(target, 1.0 if self.value is None else self.value, 0.0)
        return penalties == 0, fixed, top

    def _settle(
        self,
        policy: np.ndarray,
        free: np.ndarray,
        u: np.ndarray,
        cost: np.ndarray,
        components: np.ndarray | None,
        *,
        offset: bool = False,
        chain: ChainSolve | None = None,
    ) -> np.ndarray | None:
        """``u`` with its ``free`` states solved again: each the expected sum of ``cost``
        along ``policy``'s chain until it leaves them, plus ``u`` where it leaves to (the
        chain leaves surely: every free state reaches the target). With ``offset`` the solve
        is for the sum of ``cost`` alone, added to ``u`` (which keeps policy iteration's
        values as they are). The states of one end component (``components``) are one
        state, whose row is that of a member the policy leads out of it. ``chain`` solves
        it where no component is merged (and it covers the system). None if the solve
        fails."""
        inner = np.flatnonzero(free)
        if not inner.size:
            return u

        def settled(solved: np.ndarray) -> np.ndarray:
            """``u`` with the inner states' solution ``solved`` (one per inner state) in."""
            out = u.copy()
            out[inner] = u[inner] + np.maximum(solved, cost[inner]) if offset else solved
            return out

        if chain is not None and not _merges(components, inner):
            reward = cost if offset else (self.transitions @ np.where(free, 0.0, u))[policy] + cost
            found = chain(policy, free, np.where(free, reward, 0.0))
            if found is not None and np.isfinite(found[inner]).all():
                return settled(found[inner])
        node, reps, rows, block, labels = self._quotient_chain(policy, free, inner, components)
        reward = cost[reps] if offset else rows @ np.where(free, 0.0, u) + cost[reps]
        solved = _solved_or_none(block, reward, labels)
        return None if solved is None else settled(solved[node])

    def _quotient_chain(
        self,
        policy: np.ndarray,
        free: np.ndarray,
        inner: np.ndarray,
        components: np.ndarray | None,
        prefer: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray, sp.csr_matrix, sp.csr_matrix, np.ndarray | None]:
        """``policy``'s chain on the ``free`` states (``inner``: their indices) with each end
        component one node (:meth:`_quotient`): per inner state its node, per node the state
        whose row it takes, those rows, the block of them among the nodes, and the nodes'
        labels for :func:`~misdirect.core.reachability.solve_chain`."""
        node, reps = np.arange(inner.size), inner
        if components is not None and (components[inner] >= 0).any():
            node, reps = self._quotient(policy, inner, components, prefer)
        rows = self.transitions[policy[reps]].tocsr()
        aggregate = sp.csr_matrix(
            (np.ones(inner.size), (inner, node)), shape=(free.size, reps.size)
        )
        block = (rows @ aggregate).tocsr()
        labels = None if self.blocks is None else self.blocks[reps]
        return node, reps, rows, block, labels

    def _quotient(
        self,
        policy: np.ndarray,
        inner: np.ndarray,
        components: np.ndarray,
        prefer: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Per state of ``inner``: its node once each end component is one node; and per
        node, the state whose row it takes (for a component, a member the policy leads out
        of it; a component it never leaves stays apart, state by state)."""
        if prefer is None:
            prefer = np.zeros(components.size, dtype=bool)
        label = components[inner]
        rows = self.transitions[policy[inner]].tocoo()
        outside = np.full(components.size, -2)
        outside[inner] = label
        leaves = np.bincount(
            rows.row, weights=(outside[rows.col] != label[rows.row]), minlength=inner.size
        )
        exit_of = np.full(int(components.max(initial=-1)) + 1, -1)
        leaving = (label >= 0) & (leaves > 0)
        exits = np.flatnonzero(leaving & ~prefer[inner])
        exit_of[label[exits]] = exits  # any one member that leaves...
        exits = np.flatnonzero(leaving & prefer[inner])
        exit_of[label[exits]] = exits  # ...a preferred one if any
        merged = (label >= 0) & (exit_of[np.maximum(label, 0)] >= 0)
        # one node per merged component (its exit's), one per other state
        key = np.where(merged, exit_of[np.maximum(label, 0)], np.arange(inner.size))
        firsts, node = np.unique(key, return_inverse=True)
        return node, inner[firsts]

    def _tied_components(
        self, values: np.ndarray, bellman: np.ndarray, allowed: np.ndarray, positive: np.ndarray
    ) -> np.ndarray:
        """Per state: its end component of the tied choices among ``positive`` states (those
        whose product with ``values`` comes within :data:`~misdirect.core.tolerance.IMPROVE`
        of the best, the room policy iteration left), or -1. Maximal end components as
        usual: strongly connected components, less the choices that leave theirs, until
        none does."""
        matrix = self.transitions
        product = matrix @ values
        room = 4 * tolerance.IMPROVE * max(float(np.abs(values).max(initial=0.0)), 0.0)
        active = allowed & positive[self.owner] & (product >= bellman[self.owner] - room)
        n = positive.size
        while True:
            chosen = np.flatnonzero(active)
            if not chosen.size:
                return np.full(n, -1)
            rows = matrix[chosen].tocoo()
            source = self.owner[chosen][rows.row]
            graph = sp.csr_matrix((np.ones(rows.nnz), (source, rows.col)), shape=(n, n))
            _, scc = connected_components(graph, directed=True, connection="strong")
            out = (scc[rows.col] != scc[source]) | ~positive[rows.col]
            leaving = np.bincount(rows.row, weights=out, minlength=chosen.size) > 0
            if not leaving.any():
                break
            active[chosen[leaving]] = False
        has = np.zeros(n, dtype=bool)
        has[self.owner[chosen]] = True
        sizes = np.bincount(scc[has], minlength=int(scc.max()) + 1)
        keep = has & (sizes[scc] > 1)  # a lone state on its own loop needs no merging
        return np.where(keep, scc, -1)

    def _upper(
        self,
        u: np.ndarray,
        allowed: np.ndarray,
        target: np.ndarray,
        fixed: np.ndarray,
        top: float,
        internal: np.ndarray | None = None,
    ) -> np.ndarray:
        """An upper bound, in exact arithmetic, on ``(T u)(s)`` for every state (``u >= 0``).

        A row's value is at most its product computed in floats, raised by Higham's bound for
        a dot product of the row's length (``γ_n`` relative; doubled to cover computing the
        bound itself) plus the smallest subnormal per product that may underflow; and at most
        the largest ``u`` it reaches times its sum (at least 1). A row that stays inside an
        end component of ``internal`` stands for a distribution: one whose doubles sum to a
        little over 1 (0.8 + 0.2 is 1 + 2^-54) is read divided by its sum, else a run
        cycling through it would gain a factor 1 + 2^-54 per round and nothing below the
        largest value would bound the component. Its value is then at most the largest
        ``u`` it reaches (exact: a constant ``u`` on an end component passes)."""
        matrix = self.transitions
        product = matrix @ u
        length = np.diff(matrix.indptr)
        gamma = 2.02 * (length + 2) * tolerance.UNIT_ROUNDOFF
        bound = product + gamma * product + np.where(product > 0, tolerance.SMALLEST, 0.0)
        if matrix.nnz:
            smallest = float(matrix.data[matrix.data > 0].min(initial=1.0))
            if float(np.min(u[u > 0], initial=top)) * smallest < 2.0**-1000:
                # a product may be subnormal: its rounding is absolute
                hits = (matrix != 0).astype(np.float64) @ (u > 0).astype(np.float64)
                bound = bound + hits * tolerance.SMALLEST
            rows = length > 0
            largest = np.zeros(length.size)
            largest[rows] = np.maximum.reduceat(u[matrix.indices], matrix.indptr[:-1][rows])
            high = np.maximum(self._excess()[1], 0.0)
            if internal is not None:
                high = np.where(internal, 0.0, high)
            bound = np.minimum(bound, largest + 2 * high * largest)
        score = np.where(allowed, bound, -np.inf)[self._by_state]
        best = np.maximum.reduceat(score, self.state_start)
        return np.where(target, fixed, np.clip(best, 0.0, top))


def _flatten(
    hi: np.ndarray, lo: np.ndarray, components: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """``hi + lo`` with every end component at its largest member's value (double-doubles
    compare by ``hi``, then ``lo``)."""
    inside = np.flatnonzero(components >= 0)
    if not inside.size:
        return hi, lo
    label = components[inside]
    order = np.lexsort((lo[inside], hi[inside], label))
    last = np.flatnonzero(np.concatenate([label[order][1:] != label[order][:-1], [True]]))
    top_of = np.zeros(int(label.max()) + 1, dtype=np.int64)
    top_of[label[order][last]] = inside[order][last]
    hi, lo = hi.copy(), lo.copy()
    hi[inside], lo[inside] = hi[top_of[label]], lo[top_of[label]]
    return hi, lo


def _merges(components: np.ndarray | None, inner: np.ndarray) -> bool:
    """Whether a solve on the states ``inner`` merges an end component (:meth:`MaxReachability.
    _quotient`): then only the whole chain's solve takes it."""
    return components is not None and bool((components[inner] >= 0).any())


def _touched(components: np.ndarray, raised: np.ndarray) -> np.ndarray:
    """The states of every end component with a raised member."""
    inside = components >= 0
    if not inside.any():
        return np.zeros(raised.size, dtype=bool)
    label = np.maximum(components, 0)
    touched = np.zeros(int(components.max()) + 1, dtype=bool)
    touched[label[raised & inside]] = True
    return cast(np.ndarray, inside & touched[label])


def _raise(
    hi: np.ndarray, lo: np.ndarray, rise: np.ndarray, top: float
) -> tuple[np.ndarray, np.ndarray]:
    """``hi + lo + rise`` (``rise >= 0``), capped at ``top``."""
    hi, lo = residual.add(hi, lo, rise)
    capped = hi >= top
    return np.where(capped, top, hi), np.where(capped, 0.0, lo)


def _solved_or_none(
    block: sp.csr_matrix, rhs: np.ndarray, labels: np.ndarray | None
) -> np.ndarray | None:
    """``(I - block)⁻¹ rhs``, or None where the solve fails or is not finite: a proof that
    cannot solve gives up (the trivial bound), it never raises."""
    try:
        solved = solve_chain(block, rhs, labels)
    except (RuntimeError, ValueError, np.linalg.LinAlgError):
        return None
    return solved if np.isfinite(solved).all() else None
