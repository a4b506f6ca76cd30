"""Policy iteration for MDPs without end components: maximal expected total reward over
policies that all leave the states with probability 1, by LU factorisations of ``I − P``
(which also give visits, by transposed solves); a policy switching few choices is solved from
the last factorisation by Woodbury (:class:`UpdatedLU`). The segment relaxation uses it, and
so does the proof of a reachability bound on an MDP whose end components are collapsed
(:mod:`misdirect.solvers.engines.end_components`)."""

from __future__ import annotations

from typing import Protocol, cast

import numpy as np
import scipy.sparse as sp
from scipy.linalg import lu_factor, lu_solve
from scipy.sparse.linalg import SuperLU

from misdirect.core import residual, tolerance
from misdirect.core.model import reachable_from
from misdirect.core.reachability import factorise
from misdirect.solvers.deadline import Deadline

LOW_RANK = 32  # a policy differing from a factorised one in at most this many states is
# solved by Woodbury from that factorisation (a few solves instead of a new LU)
# what a proven potential falls by at least, per step of any policy: over 1, so that twice it
# plus one more step's mass (a row's doubles may sum to a little over 1) still falls by 1
STEP_MARGIN = 1.0 + 2.0**-30


class LinearSolver(Protocol):
    """A factorised ``I − P``: scipy's ``SuperLU`` or an :class:`UpdatedLU`."""

    def solve(self, b: np.ndarray, trans: str = ...) -> np.ndarray: ...


class UpdatedLU:
    """Solves ``A' = A + U Vᵀ`` from the LU of ``A`` (Woodbury): ``U`` the unit columns of the
    ``rows`` whose choice changed, ``Vᵀ = A'[rows] − A[rows]``. A policy improvement switches
    a few entries' choices; their rows are all that changes."""

    def __init__(self, base: LinearSolver, rows: np.ndarray, delta: sp.csr_matrix):
        self.base, self.rows, self.delta = base, rows, delta
        units = np.zeros((delta.shape[1], rows.size))
        units[rows, np.arange(rows.size)] = 1.0
        self.z = base.solve(units)  # A⁻¹ U
        self.capacitance = lu_factor(np.eye(rows.size) + delta @ self.z)  # I + Vᵀ A⁻¹ U
        self.q: np.ndarray | None = None  # A⁻ᵀ V, for transposed solves

    def solve(self, b: np.ndarray, trans: str = "N") -> np.ndarray:
        if trans == "N":
            y = self.base.solve(b)
            return cast(np.ndarray, y - self.z @ lu_solve(self.capacitance, self.delta @ y))
        if self.q is None:
            self.q = self.base.solve(self.delta.T.toarray(), trans="T")
        y = self.base.solve(b, trans="T")
        return cast(np.ndarray, y - self.q @ lu_solve(self.capacitance, y[self.rows], trans=1))


class TransientPolicyIteration:
    """Max expected total reward of an MDP given by rows (choices), over its *proper* policies
    (those that leave its states with probability 1).

    Without ``stop_row`` every policy must be proper (no end components). With it, the states
    of end components have a stop row (no transitions, reward 0), and every policy iteration
    starts from a proper policy (:meth:`proper`). A strict improvement then never closes a
    cycle: in a class closed under the new policy, its stationary distribution weighs the
    gains of the switched states against rewards that are at most 0 (a row that keeps its
    mass inside cannot reach the target, and charges are costs), so no state of it switched
    and it was closed under the old, proper policy already. Every factorisation is then of a
    non-singular ``I − P``, and the optimum over proper policies is found: with stop rows it
    is the optimum over all schedulers (cycling forever is worth no more than stopping).
    """

    def __init__(
        self,
        row_state: np.ndarray,
        matrix: sp.csr_matrix,
        n_states: int,
        *,
        leaks: np.ndarray | None = None,
        stop_row: np.ndarray | None = None,
    ):
        """``leaks``: per row, whether some of its mass leaves the states (needed with
        ``stop_row``: per state, its stop row or -1)."""
        self.row_state = row_state
        self.matrix = matrix
        self.n_states = n_states
        self.leaks, self.stop_row = leaks, stop_row
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

    def proper(self, policy: np.ndarray) -> np.ndarray:
        """``policy`` with every state that cannot leave under it switched to its stop row:
        those states lie in closed classes, which only end components hold."""
        if self.stop_row is None:
            return policy
        assert self.leaks is not None
        moves = self.matrix[policy]
        leaving = reachable_from(moves.T.tocsr(), np.flatnonzero(self.leaks[policy]))
        if leaving.all():
            return policy
        stuck = ~leaving & (self.stop_row >= 0)
        policy = np.where(stuck, self.stop_row, policy)
        if not (leaving | stuck).all():  # an entry into a stopping state leaves through it
            again = reachable_from(
                self.matrix[policy].T.tocsr(), np.flatnonzero(self.leaks[policy])
            )
            if not again.all():
                raise AssertionError("a closed class without a stop row: not an end component")
        return policy

    def row_defects(self, reward: np.ndarray, values: np.ndarray) -> np.ndarray:
        """Per row ``a`` of state ``x``: a proven upper bound, in exact arithmetic, on
        ``reward_a + P_a v − v(x)`` (inf where it cannot be computed)."""
        zeros = np.zeros(values.size)
        r, bound = residual.residual(self.matrix, values, zeros, self.row_state, reward)
        upper = r + 2 * (bound - np.abs(r))  # |exact - r| <= bound - |r|, doubled for rounding
        return np.where(np.isfinite(upper), upper, np.inf)

    def defect(self, reward: np.ndarray, values: np.ndarray) -> float:
        """A proven upper bound, in exact arithmetic, on how far the Bellman operator raises
        ``values`` anywhere: ``max_x max_a (reward_a + P_a v − v(x))``, at least 0 (inf when
        it cannot be computed)."""
        return max(float(self.row_defects(reward, values).max(initial=0.0)), 0.0)

    def proven_bound(
        self,
        reward: np.ndarray,
        values: np.ndarray,
        state: int,
        potential: np.ndarray,
        policy: np.ndarray | None = None,
        lu: LinearSolver | None = None,
        prune_at: float | None = None,
    ) -> float:
        """A proven upper bound at ``state`` on the optimum (over every policy; this MDP has no
        end components) for ``reward``, from approximate ``values`` (policy iteration's).

        ``potential`` is a proven ``W`` with ``W(x) ≥ 1 + P_a W`` for every row ``a`` of
        every state ``x`` (:meth:`proven_potential`, or one built from it). With ``δ`` the
        largest defect of ``v`` (:meth:`defect`), ``u = v + δ W`` satisfies
        ``reward_a + P_a u ≤ v(x) + δ + δ (W(x) − 1) = u(x)``: a pre-fixed point of the Bellman
        operator, which lies above the optimum when every policy leaves the states (the
        operator's iterates from ``u`` fall to it). The rounding is in ``δ`` (its rows summed
        in double-double with a bound) and in the last sum, rounded up. ``inf`` if nothing is
        proven.

        A defect of one ulp where values are near 1 is charged at every step that way, which
        on a curve of value 1e-4 is more than certification allows. With ``policy`` (the one
        ``values`` are of) and ``lu`` (its factorisation), the defects are collected where
        runs meet them instead: ``w``, the most any policy collects of the row defects ``d``
        (policy iteration from ``policy``), then ``u = v + w + δ_w W`` with ``δ_w`` the largest
        defect of ``w`` for ``d`` (a few ulps of numbers of the size of ``d``). That costs a
        policy iteration, so given ``prune_at`` (a search's pruning threshold) it is skipped
        where it cannot change the decision: where the first bound is at most ``prune_at``
        already, or the values alone lie above it (the collected bound lies above them)."""
        if not values.size:
            return 0.0
        if not (np.isfinite(values).all() and np.isfinite(potential[state])):
            return np.inf
        defects = self.row_defects(reward, values)
        delta = max(float(defects.max(initial=0.0)), 0.0)
        raised = delta * float(potential[state]) * (1 + 4 * tolerance.UNIT_ROUNDOFF)
        bound = tolerance.round_up(float(values[state]) + raised)
        if policy is None or lu is None or not delta > 0 or not np.isfinite(delta):
            return bound
        if prune_at is not None and not float(values[state]) <= prune_at < bound:
            return bound  # pruned as it is, or not even at the values themselves
        d = np.maximum(defects, 0.0)
        w, _, _, optimal = self.optimise(d, policy, base=lu)
        if not (optimal and np.isfinite(w).all()):
            return bound
        w_delta = self.defect(d, w)
        collected = w_delta * float(potential[state]) * (1 + 4 * tolerance.UNIT_ROUNDOFF)
        raise_by = tolerance.round_up(float(w[state]) + collected)
        return min(bound, tolerance.round_up(float(values[state]) + raise_by))

    def proven_potential(self, deadline: Deadline | None = None) -> np.ndarray | None:
        """A proven ``W`` with ``W(x) ≥ STEP_MARGIN + P_a W`` for every row ``a`` of every
        state ``x``: a little over the largest expected number of steps before leaving, over
        every policy (None where it cannot be proven: end components, or a chain whose runs
        last so long that doubles cannot tell). Policy iteration for a reward of 1 per step
        gives ``N`` with defect ``D < 1``; then ``c N`` with ``c = margin / (1 − D)`` passes,
        and is checked to (one retry, a little higher)."""
        if self.stop_row is not None:
            return None
        n_rows = self.matrix.shape[0]
        steps, _, _, optimal = self.optimise(np.ones(n_rows), deadline=deadline)
        if not (optimal and np.isfinite(steps).all()) or (steps.size and steps.min() < 0):
            return None
        steps = np.maximum(steps, 1.0)
        # 1 + P N - N(x) <= D for every row: margin + P (c N) - c N(x) <= margin - c (1 - D)
        level = self.defect(np.ones(n_rows), steps)
        if not level < 0.5:
            return None
        scale = STEP_MARGIN / (1.0 - level)
        for attempt in range(2):
            scale *= 1 + (2.0**-40 if attempt == 0 else 2.0**-20)
            potential = steps * scale
            if self.defect(np.full(n_rows, STEP_MARGIN), potential) <= 0.0:
                return cast(np.ndarray, potential)
        return None

    def factorise(self, policy: np.ndarray) -> SuperLU:
        """LU of ``I − P`` for the chain that takes row ``policy[x]`` in ``x``: it solves
        for any reward on it (``solve``), and for visits (``solve(·, trans="T")``). A proper
        policy's ``I − P`` is a non-singular M-matrix: no pivoting, and a symmetric ordering
        that leaves less fill on grid-like chains (:func:`~misdirect.core.reachability.
        factorise`)."""
        self.evaluations += 1
        return factorise(self.matrix[policy])

    def updated(
        self, base: LinearSolver, base_policy: np.ndarray, policy: np.ndarray
    ) -> UpdatedLU | None:
        """A solver for ``policy``'s system from ``base``, the factorisation of
        ``base_policy``'s: Woodbury on the rows that differ, if few; else None."""
        rows = np.flatnonzero(policy != base_policy)
        if rows.size > LOW_RANK:
            return None
        self.evaluations += 1
        delta = self.matrix[base_policy[rows]] - self.matrix[policy[rows]]  # of I − P
        return UpdatedLU(base, rows, delta.tocsr())

    def optimise(
        self,
        reward: np.ndarray,
        policy: np.ndarray | None = None,
        *,
        start: int | None = None,
        enough: float = np.inf,
        deadline: Deadline | None = None,
        base: LinearSolver | None = None,
        max_rounds: int | None = None,
    ) -> tuple[np.ndarray, np.ndarray, LinearSolver, bool]:
        """(values, policy, its factorisation, whether optimal), from ``policy`` (default:
        first rows; ``base``: its factorisation, if at hand). Stops early at a policy worth
        more than ``enough`` at ``start``: the optimum is above it too (each improvement only
        raises the values). With ``max_rounds``, stops (not optimal) after that many
        improvements, or at once where an improvement returns to a policy it had left: gains
        at rounding level that cycle, each round a solve, forever (seen on a collapsed MDP of
        the 64-sensor turn-back grid: five policies in turn for minutes). Raises
        :class:`DeadlineExpiredError` once ``deadline`` has passed."""
        lu: LinearSolver | None
        if policy is not None and base is not None and self.stop_row is None:
            lu = base  # the policy's own factorisation (no stop rows: it stays as it is)
        else:
            policy = self.proper(self.first_rows() if policy is None else policy)
            lu = base = self.factorise(policy)
        base_policy = policy
        seen = {policy.tobytes()}
        rounds = 0
        while True:
            if deadline is not None:
                deadline.check()
            values = lu.solve(reward[policy])
            if start is not None and values[start] > enough:
                return values, policy, lu, False
            score = self.matrix @ values + reward
            order = np.lexsort((-score, self.row_state))
            best = order[self.state_start]
            gain = score[best] - score[policy]
            # relative to the size of the terms each score adds up (rewards may be negative,
            # so the scores themselves may cancel), and at least to the values' scale (the
            # solve's error is normwise): a gain below either is rounding, and switching on it
            # costs rounds without gain (docs/benchmarks.md, the H1 regression)
            size = self.matrix @ np.abs(values) + np.abs(reward)
            floor = np.abs(values).max(initial=0.0)
            switch = gain > tolerance.IMPROVE * np.maximum(
                np.maximum(size[best], size[policy]), floor
            )
            if not switch.any():
                return values, policy, lu, True
            policy = np.where(switch, best, policy)
            if max_rounds is not None:
                rounds += 1
                key = policy.tobytes()
                if rounds > max_rounds or key in seen:
                    return values, policy, lu, False
                seen.add(key)
            lu = self.updated(base, base_policy, policy)
            if lu is None:
                lu = base = self.factorise(policy)
                base_policy = policy
