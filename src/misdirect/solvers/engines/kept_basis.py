"""Relaxations on a kept basis: the per-state relaxation of many free sets at one node, each for
a few milliseconds of policy iteration instead of a whole-chain LU per round (issue 50).

A covering bound solves the per-state relaxation once per union of sensor groups, every union
at the same node: the decided sensors as decided, the union's sensors free, every other sensor
unaltered. Only the states the undecided sensors own (``O``: on a 40x40 turn-back grid with 64
sensors, 928 of 6,400) ever change their row; every other state moves as in the node's *base
chain* (every undecided sensor unaltered). So the base chain is solved once per node for its
first entries into ``O``: from each state outside ``O``, the probability of reaching the target
before ``O`` (``h``) and the distribution of the first state of ``O`` it enters (``H``), one
sparse LU and ``|O| + 1`` solves. Each relaxation is then exactly an MDP on ``O``: a row
``P_g`` of a state of ``O`` becomes ``r_g = P_g[target] + P_g[E] h`` to the target and
``q_g = P_g[O] + P_g[E] H`` into ``O`` (``E``: the states outside ``O`` that reach the target
or ``O`` under the base chain; the others are worth 0 in every relaxation of the node). Policy
iteration on that dense MDP of a few hundred states costs milliseconds a round.

The values found are lifted back to the whole chain (``v = h + H v_O`` outside ``O``) and the
bound is proven there, by :meth:`~misdirect.solvers.engines.policy_iteration.MaxReachability.
proven_bound`, as every bound of the per-state relaxation is: the reduction only finds the
values, it proves nothing. Where the reduced policy iteration does not settle (a round that
would strand a state, a singular solve), the relaxation is solved on the whole chain instead.
The proof's own solves run on the basis too: its first offset, and where that fails its later
attempts (the states its check raised held fixed) and its double-double refinement
(:meth:`KeptBasis.solve_chain`): a union's proof then takes no whole-chain LU unless it merges
an end component.

The dense algebra runs on one BLAS thread (:func:`~misdirect.core.blas.one_blas_thread`, taken
by the cover that calls it): these matrices are a few hundred wide, and OpenBLAS's threads
spinning for a core the other worker holds made a 140x140 solve take 80 ms instead of 0.2
(bench/results/covering).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence

import numpy as np
import scipy.sparse as sp

from misdirect.core import tolerance
from misdirect.core.model import reachable_from
from misdirect.core.reachability import factorise
from misdirect.solvers.deadline import Deadline
from misdirect.solvers.engines.per_state import PerStateRelaxation

MAX_ROUNDS = 64  # rounds of the reduced policy iteration before the whole chain takes over
MAX_KEPT_ENTRIES = 100_000_000  # numbers in the dense arrays a basis keeps (800 MB), at most
# states outside O that a proof's solve holds fixed, at most (each one more column of the LU's
# solves: beyond this the whole chain's LU is cheaper)
MAX_HELD_OUTSIDE = 256


class KeptBasis:
    """One node's base chain, solved for its first entries into the states of its undecided
    sensors; :meth:`bound` solves a free set's relaxation on it (see the module docstring)."""

    def __init__(
        self,
        relax: PerStateRelaxation,
        fixed: Mapping[int, int],
        undecided: Sequence[int],
    ):
        """``fixed``: choice index -> option of every decided choice; ``undecided``: the
        choices a free set may hold (the others count as unaltered)."""
        self.relax = relax
        chain = relax.chain
        self.fixed = dict(fixed)
        n = chain.n_states
        observation = relax.problem.pomdp.observation_of[chain.world_state]
        choice_of = np.full(relax.problem.pomdp.n_observations, -1, dtype=np.int64)
        for i, choice in enumerate(relax.space.choices):
            choice_of[choice.observation] = i
        self.state_choice = choice_of[observation]
        undecided_mask = np.zeros(len(relax.space.choices) + 1, dtype=bool)
        undecided_mask[list(undecided)] = True
        in_o = relax.live & (chain.groups_per_state > 1) & undecided_mask[self.state_choice]
        self.o_states = np.flatnonzero(in_o)
        base_options = relax.free_options((), 0.0, self.fixed)
        self.base_policy = relax.best_groups(
            np.where(relax.allowed_groups(base_options), 0.0, -np.inf)
        )[0]
        transitions = chain.transitions.tocsr()
        target = chain.target
        self.target_value = np.where(
            target, 1.0 if chain.target_value is None else chain.target_value, 0.0
        )
        base = transitions[self.base_policy]
        outside = relax.live & ~in_o
        # states outside O that reach the target or O along the base chain (through
        # states outside O); the others never leave what is worth 0
        through = base.multiply(outside[:, None]).tocsr()
        reaches = reachable_from(through.T.tocsr(), np.flatnonzero(target | in_o))
        self.e_states = np.flatnonzero(outside & reaches)
        self.position = np.full(n, -1, dtype=np.int64)
        self.position[self.o_states] = np.arange(self.o_states.size)
        self.e_position = np.full(n, -1, dtype=np.int64)
        self.e_position[self.e_states] = np.arange(self.e_states.size)
        self.in_kept = np.zeros(n, dtype=bool)  # E and O: the states a kept solve covers
        self.in_kept[self.e_states] = self.in_kept[self.o_states] = True
        self.reduced = self.fallbacks = 0  # relaxations solved on the basis, and without it
        # the reduced rows: every group of a state of O
        self.groups = np.flatnonzero(in_o[chain.group_state])
        # the dense arrays kept: H (E x O), the rows on O and their products with the base
        # inverse (groups x O, twice), the base inverse (O x O)
        size = max(self.o_states.size, 1)
        kept = size * (self.e_states.size + 2 * self.groups.size + size)
        self.usable = kept <= MAX_KEPT_ENTRIES
        if not self.usable:
            return
        e, o = self.e_states, self.o_states
        block = base[e][:, e]
        self.lu = factorise(block) if e.size else None
        rhs = np.empty((e.size, o.size + 1))
        rhs[:, : o.size] = base[e][:, o].toarray()
        rhs[:, o.size] = base[e] @ self.target_value
        solved = self.lu.solve(rhs) if self.lu is not None else rhs
        self.first_entry, self.before = solved[:, : o.size], solved[:, o.size]  # H, h
        rows = transitions[self.groups]
        self.into_e = rows[:, e].tocsr()
        self.q = rows[:, o].toarray() + self.into_e @ self.first_entry
        self.r = rows @ self.target_value + self.into_e @ self.before
        self.group_owner = self.position[chain.group_state[self.groups]]
        counts = np.bincount(self.group_owner, minlength=o.size)
        self._state_start = np.concatenate([[0], np.cumsum(counts)[:-1]])
        self.local = np.full(chain.group_state.size, -1, dtype=np.int64)
        self.local[self.groups] = np.arange(self.groups.size)
        self.base_local = self.local[self.base_policy[o]]
        self.e_rows = base[e].tocsr()  # the base chain's rows of E, every column
        # the base chain on O, inverted once: a policy differing from it in a few states is
        # solved by Woodbury (states it cannot lead to the target are stopped: worth 0)
        reaching = self._reaching(self.base_local)
        self.base_stopped = ~reaching
        self.base_q = np.where(reaching[:, None], self.q[self.base_local], 0.0)
        self.base_r = np.where(reaching, self.r[self.base_local], 0.0)
        try:
            self.base_inverse = np.linalg.inv(np.eye(o.size) - self.base_q)
        except np.linalg.LinAlgError:
            self.usable = False
            return
        self.base_values = self.base_inverse @ self.base_r
        self._inverse_t = np.ascontiguousarray(self.base_inverse.T)
        # q @ base inverse, row by row as policies pick them (each row once a node: a
        # Woodbury round then gathers its capacitance instead of multiplying it out)
        self._times_inverse = np.empty((self.groups.size, o.size))
        self._have_times_inverse = np.zeros(self.groups.size, dtype=bool)

    def bound(self, free: Sequence[int], cap: float, deadline: Deadline | None = None) -> float:
        """The proven bound of the per-state relaxation with the ``free`` choices free (their
        options within ``cap``), the decided ones as decided, every other choice unaltered."""
        relax = self.relax
        allowed_full = relax.allowed_groups(relax.free_options(free, cap, self.fixed))
        penalty = np.where(allowed_full, 0.0, -np.inf)
        found = self._reduced(allowed_full[self.groups]) if self.usable else None
        if found is None:  # the whole chain, as without a kept basis
            self.fallbacks += 1
            start = relax.best_groups(penalty)[0]
            bound, _, _ = relax.optimise(allowed_full, start, deadline)
            return float(bound)
        self.reduced += 1
        values_o, policy_o = found
        values = self.target_value.copy()
        values[self.o_states] = values_o
        if self.e_states.size:
            values[self.e_states] = self.before + self.first_entry @ values_o
        policy = self.base_policy.copy()
        policy[self.o_states] = self.groups[policy_o]
        offset = self.offset_solver(policy_o)
        return float(
            relax.mdp.proven_bound(
                values,
                policy,
                relax.chain.initial,
                penalty,
                deadline,
                offset=offset,
                chain=self.solve_chain,
            )
        )

    def _reduced(self, allowed: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        """Policy iteration on the reduced MDP among the ``allowed`` reduced rows, from the
        base chain's rows (always allowed: unaltered): (values on O, the chosen local row per
        state of O), or None where it does not settle. Only the rows of states with a choice
        (two allowed rows or more) are scored: every other state keeps its one row."""
        policy = self.base_local.copy()
        policy = self._proper(policy, allowed)
        owner = self.group_owner
        choices = np.bincount(owner, weights=allowed, minlength=self.o_states.size)
        rows = np.flatnonzero(allowed & (choices[owner] > 1))
        if not rows.size:
            values = self._evaluate(policy)
            return None if values is None else (values, policy)
        q_rows, r_rows, owners = self.q[rows], self.r[rows], owner[rows]
        ranked = np.lexsort((np.arange(rows.size), owners))  # rows grouped by state
        starts = np.flatnonzero(np.concatenate([[True], owners[ranked][1:] != owners[ranked][:-1]]))
        states = owners[ranked][starts]
        at = np.full(self.groups.size, -1, dtype=np.int64)
        at[rows] = np.arange(rows.size)
        for _ in range(MAX_ROUNDS):
            values = self._evaluate(policy)
            if values is None:
                return None
            score = r_rows + q_rows @ values
            order = np.lexsort((-score, owners))
            best = order[starts]
            current = score[at[policy[states]]]
            room = tolerance.IMPROVE * np.maximum(
                np.abs(score[best]), np.abs(values).max(initial=0.0)
            )
            switch = score[best] > current + room
            if not switch.any():
                return values, policy
            # a round that strands a state (no strict gain does, in exact arithmetic) makes
            # the next solve singular or its values no probabilities: the whole chain decides
            policy = policy.copy()
            policy[states[switch]] = rows[best[switch]]
        return None

    def _reaching(self, policy: np.ndarray) -> np.ndarray:
        """States of O from which ``policy`` reaches the target (through the reduced rows)."""
        q = self.q[policy]
        graph = sp.csr_matrix((q > 0).T.astype(np.int8))  # entered state -> its enterer
        return reachable_from(graph, np.flatnonzero(self.r[policy] > 0))

    def _proper(self, policy: np.ndarray, allowed: np.ndarray) -> np.ndarray:
        """``policy`` with every state that cannot reach the target under it switched to an
        allowed row one step closer to it (breadth-first), as
        :meth:`~misdirect.solvers.engines.policy_iteration.MaxReachability.proper` does."""
        if not self.base_stopped.any() and (policy == self.base_local).all():
            return policy  # the base chain reaches the target from every state of O
        reaching = self._reaching(policy)
        if reaching.all():
            return policy
        policy = policy.copy()
        closer = np.zeros(reaching.size, dtype=bool)
        stepping = allowed & (self.r > 0)  # rows into the target: the first layer
        while stepping.any():
            rows = np.flatnonzero(stepping & ~closer[self.group_owner])
            if not rows.size:
                break
            states, first = np.unique(self.group_owner[rows], return_index=True)
            switch = ~reaching[states]
            policy[states[switch]] = rows[first[switch]]
            closer[states] = True
            stepping = allowed & (self.q[:, closer] > 0).any(axis=1)
        return policy

    def _evaluate(self, policy: np.ndarray) -> np.ndarray | None:
        """Values on O of the reduced chain that takes row ``policy[s]`` in ``s``, by Woodbury
        from the base chain's inverse (the rows that differ replaced); None where that system
        is singular or its solution is not a probability (a policy that strands a state)."""
        solved = self._solve(policy, self.r[policy], self.base_values)
        if solved is None:
            return None
        top = float(self.target_value.max(initial=0.0))
        slack = tolerance.KEPT_BASIS_RANGE * max(top, 1.0)
        if not (np.isfinite(solved).all() and (solved >= -slack).all()):
            return None
        if (solved > top + slack).any():
            return None
        clipped: np.ndarray = np.clip(solved, 0.0, top)
        return clipped

    def _solve(
        self,
        policy: np.ndarray,
        rhs: np.ndarray,
        base_solution: np.ndarray | None = None,
        held: np.ndarray | None = None,
    ) -> np.ndarray | None:
        """``(I - q_policy)⁻¹ rhs`` on O by Woodbury from the base inverse (``base_solution``:
        the base inverse times the base rows' right-hand side, if at hand). ``held``: states
        of O whose row is the identity instead (held at ``rhs``), and a state the base chain
        stops takes its own row wherever ``held`` is given (the exact chain, not the base's
        stopping rule); ``rhs`` may hold several columns."""
        differs = policy != self.base_local
        if held is not None:
            differs = differs | held | self.base_stopped
        changed = np.flatnonzero(differs)
        inverse = self.base_inverse
        if not changed.size:
            return inverse @ rhs if base_solution is None else base_solution
        # columns of the base inverse at the changed states (rows of its transpose: a gather
        # of contiguous rows, not a strided one)
        columns = self._inverse_t[changed].T
        step = None
        if base_solution is None:
            base_solution = inverse @ rhs
            at_changed = base_solution[changed]
        else:
            # rhs differs from the base rows' only at the changed rows (unchanged rows are the
            # base's, and a state the base stops has no row into the target)
            step = rhs[changed] - self.base_r[changed]
            at_changed = base_solution[changed] + inverse[np.ix_(changed, changed)] @ step
        # Woodbury with delta = base_q[c] - q'[c] (rows of (I - q') - (I - q)), where
        # base_q @ inverse = inverse - I and q' @ inverse is gathered (:meth:`_times`)
        moved = self._times(policy[changed])
        if held is not None:
            moved[held[changed]] = 0.0
        capacitance = inverse[np.ix_(changed, changed)] - moved[:, changed]
        right = at_changed - rhs[changed] - moved @ rhs
        try:
            correction = np.linalg.solve(capacitance, right)
        except np.linalg.LinAlgError:
            return None
        solved: np.ndarray = base_solution + columns @ (
            -correction if step is None else step - correction
        )
        return solved

    def _times(self, rows: np.ndarray) -> np.ndarray:
        """``q[rows] @ base_inverse`` (a copy), each row multiplied once a node."""
        missing = np.unique(rows[~self._have_times_inverse[rows]])
        if missing.size:
            self._times_inverse[missing] = self.q[missing] @ self.base_inverse
            self._have_times_inverse[missing] = True
        taken: np.ndarray = self._times_inverse[rows]
        return taken

    def solve_chain(
        self, policy: np.ndarray, free: np.ndarray, rhs: np.ndarray
    ) -> np.ndarray | None:
        """The proof's solves on the kept basis (:data:`~misdirect.solvers.engines.
        policy_iteration.ChainSolve`): ``x`` with ``x = P x + rhs`` on the ``free`` states
        along the whole chain's ``policy``, 0 elsewhere; None where the basis does not cover
        the system (free states outside E and O, a policy off the base chain outside O, too
        many states of E held), and the caller solves it on the whole chain.

        The states of E and O that are not free are held at 0: those of O are rows of the
        reduced Woodbury update (:meth:`_solve`); those of E (``K``, few: a proof holds the
        states its check raised) change the LU's system by ``D = P[K, E ∪ O]``, solved by
        Woodbury once more, ``x = y - A⁻¹ E_K (I + D A⁻¹ E_K)⁻¹ D y`` (``A``: the system with
        only O's states held, ``y = A⁻¹ rhs``), ``|K|`` columns of the LU's solves."""
        if not self.usable or (free & ~self.in_kept).any():
            return None
        e, o = self.e_states, self.o_states
        if (policy[e] != self.base_policy[e]).any():
            return None
        policy_o = self.local[policy[o]]
        if (policy_o < 0).any():
            return None
        held_o = ~free[o]
        held_e = np.flatnonzero(~free[e])  # positions in E
        if held_e.size > MAX_HELD_OUTSIDE or (held_e.size and self.lu is None):
            return None
        into_e = self.into_e[policy_o]
        b_e = np.where(free[e], rhs[e], 0.0)
        b_o = np.where(held_o, 0.0, rhs[o])
        y = self._apply(policy_o, held_o, into_e, b_e, b_o)
        if y is None:
            return None
        y_e, y_o = y
        if held_e.size:
            # D: the held states' rows, over E then O (their rows of the base chain)
            rows = self.e_rows[held_e].tocoo()
            at_e, at_o = self.e_position[rows.col], self.position[rows.col]
            keep = (at_e >= 0) | (at_o >= 0)
            row, data = rows.row[keep], rows.data[keep]
            column = np.where(at_e[keep] >= 0, at_e[keep], e.size + at_o[keep])
            d_y = np.bincount(
                row, weights=data * np.concatenate([y_e, y_o])[column], minlength=held_e.size
            )
            units = np.zeros((e.size, held_e.size))
            units[held_e, np.arange(held_e.size)] = 1.0
            needed = np.unique(column)
            z = self._apply(
                policy_o, held_o, into_e, units, np.zeros((o.size, held_e.size)), needed
            )
            if z is None:
                return None
            z_needed = np.empty((e.size + o.size, held_e.size))
            z_needed[needed] = z[0]
            d = sp.csr_matrix((data, (row, column)), shape=(held_e.size, e.size + o.size))
            capacitance = np.eye(held_e.size) + d @ z_needed
            try:
                w = np.linalg.solve(capacitance, d_y)
            except np.linalg.LinAlgError:
                return None
            shift_e = np.zeros(e.size)
            shift_e[held_e] = w
            z_w = self._apply(policy_o, held_o, into_e, shift_e, np.zeros(o.size))
            if z_w is None:
                return None
            y_e, y_o = y_e - z_w[0], y_o - z_w[1]
        x = np.zeros(free.size)
        x[e], x[o] = y_e, y_o
        x[~free] = 0.0
        return x if np.isfinite(x).all() else None

    def _apply(
        self,
        policy_o: np.ndarray,
        held_o: np.ndarray,
        into_e: sp.csr_matrix,
        c_e: np.ndarray,
        c_o: np.ndarray,
        rows: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray] | None:
        """``A⁻¹ c`` for the chain along ``policy_o`` on O (the states of ``held_o`` held at
        0), the base chain on E: ``x_E = L c_E + H x_O`` with ``L`` the LU's solve, and
        ``(I - q) x_O = c_O + P_OE L c_E``; (x_E, x_O), or with ``rows`` (positions in E, then
        |E| + positions in O) only those of x, stacked, in the first array (and x_O)."""
        solved_e = self.lu.solve(c_e) if self.lu is not None else np.zeros_like(c_e)
        rhs_o = c_o + into_e @ solved_e
        rhs_o[held_o] = 0.0
        x_o = self._solve(policy_o, rhs_o, held=held_o)
        if x_o is None:
            return None
        if rows is None:
            return solved_e + self.first_entry @ x_o, x_o
        n_e = self.e_states.size
        on_e, on_o = rows[rows < n_e], rows[rows >= n_e] - n_e
        picked = np.concatenate([solved_e[on_e] + self.first_entry[on_e] @ x_o, x_o[on_o]])
        return picked, x_o

    def offset_solver(self, policy_o: np.ndarray) -> Callable[[np.ndarray], np.ndarray | None]:
        """What the proof's first offset asks for, on the kept basis: the expected sum of a
        cost along the whole chain's policy (``policy_o`` on O, the base chain elsewhere)
        until it stops; None where the system is singular."""

        def solve(cost: np.ndarray) -> np.ndarray | None:
            e, o = self.e_states, self.o_states
            from_e = (
                self.lu.solve(cost[e]) if self.lu is not None else np.zeros(e.size)
            )  # the sum collected outside O before entering it
            rhs = cost[o] + self.into_e[policy_o] @ from_e
            on_o = self._solve(policy_o, rhs)
            if on_o is None or not np.isfinite(on_o).all():
                return None
            total = np.zeros(cost.size)
            total[o] = on_o
            if e.size:
                total[e] = from_e + self.first_entry @ on_o
            return total

        return solve
