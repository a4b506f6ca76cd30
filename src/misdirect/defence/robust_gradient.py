"""The randomized master of robust synthesis (issue 54; docs/robust.md): a gradient search.

The class: ``k`` memory nodes, randomized. In node ``n`` reading ``o`` the robot draws
(action, next node) from ``μ(n, o) = softmax(θ[n, o, :])`` over the ``|A|·k`` pairs. For a
finite set ``K`` of alterations the master looks for the logits ``θ`` minimising the largest
of ``f_j(θ) = sense · V_j(θ)`` over ``K`` (``V_j``: Pr(target) of the product chain under
alteration ``j``; ``sense`` is 1 for decoy, -1 for goal), through the smooth maximum
``τ · log Σ_j exp(f_j / τ)`` with a temperature ``τ`` that tightens, by L-BFGS-B on the logits
from several starts.

Values and gradients are exact (up to rounding), by the adjoint method: per member of ``K``
one sparse LU of ``I - Q`` (``Q``: the chain among the product states that may still reach the
target), one forward solve ``(I - Q) x = b`` and one transposed solve ``(I - Q)ᵀ λ = e_start``;
then ``∂V/∂μ(n, o, a, n') = Σ λ(s, n) · P(s, a, s') · x(s', n')`` over the states ``s`` whose
reading is ``o`` (plus the target's worth), one ``bincount`` over the chain's entries.

Every move of a softmax controller has full support, so which product states can reach the
target does not depend on ``θ`` (nor on the alteration): a world state that can reach it
under some action, in any node. ``I - Q`` restricted to them is non-singular for every ``θ``.

Nothing this module computes is reported: it ranks controllers. The loop re-evaluates the
controller it returns exactly and certifies its worst case with the oracle. It proves no bound
on the min–max (a local search over a non-convex class).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.optimize import minimize
from scipy.sparse.linalg import bicgstab, gmres, splu

from misdirect.core import tolerance
from misdirect.core.model import Controller, Pomdp
from misdirect.solvers.deadline import Deadline, DeadlineExpiredError
from misdirect.solvers.engines.forked import forked_call

LOGIT_BOUND = 8.0  # |θ| at most this: no probability below about e^-16 / (|A| k), chains stay
# well conditioned (a near-zero exit probability would make I - Q nearly singular)
TEMPERATURES = (0.05, 0.01, 0.002, 0.0005)  # τ of the smooth maximum, relative to the values'
# scale, tightened in turn (each stage starts where the previous one ended)
ITERATIONS_PER_STAGE = 150  # L-BFGS-B iterations per temperature
DIRECT_LIMIT = 20_000  # product states up to which the chains are solved by a sparse LU; beyond,
# by BiCGSTAB (an LU of a 100,000-state grid-like chain fills in for minutes)
KRYLOV_ITERATIONS = 2_000  # Krylov iterations at most per solve
GMRES_RESTART = 50

ExactWorst = Callable[[Controller], tuple[float, float, float]]
"""The loop's exact ranking of a candidate, compared in order (smaller is better): how far its
nominal Pr(goal) falls short of the floor (0 without one), ``sense ·`` its worst value over K,
and a tie-break among candidates equal in both."""
FLOOR_WEIGHTS = (10.0, 100.0, 1000.0, 10000.0)  # ρ of the floor's penalty ρ·max(0, q - G)²,
# per temperature stage

PRUNE_LEVELS = (1e-4, 1e-3, 1e-2, 0.05)  # probabilities below these dropped in the candidates
# the master offers (a softmax controller has full support; exact zeros often do better)


@dataclass(frozen=True)
class MasterAnswer:
    """What a master returns for one set ``K``."""

    controller: Controller
    value: float  # sense-free: the controller's worst value over K (the master's own number)
    candidates: int  # controllers looked at (starts of the gradient master)
    iterations: int  # optimiser iterations, all starts together (0 for the exact master)
    finished: bool  # False when the deadline stopped it before a first answer


class ChainModel:
    """The product chains of ``k``-node randomized controllers, their values and gradients.

    Product index ``position(s) * k + n`` over the world states that can reach the target
    (non-target, non-absorbing); ``x`` on the target is its worth, elsewhere 0."""

    def __init__(
        self,
        pomdp: Pomdp,
        target: np.ndarray,
        worth: np.ndarray,
        memory: int,
        direct_limit: int = DIRECT_LIMIT,
    ) -> None:
        self.direct_limit = direct_limit  # product states up to which a sparse LU is used
        self.k, self.n_actions, self.n_obs = memory, pomdp.n_actions, pomdp.n_observations
        self.obs = np.asarray(pomdp.observation_of, dtype=np.int64)
        n_s = pomdp.n_states
        target = np.asarray(target, dtype=bool)
        worth = np.asarray(worth, dtype=np.float64)
        ended = np.asarray(pomdp.absorbing, dtype=bool) | target
        coo = pomdp.transitions.tocoo()
        action, source = np.divmod(coo.row.astype(np.int64), n_s)
        dest = coo.col.astype(np.int64)
        live = ~ended[source] & (coo.data > 0)
        action, source, dest, prob = action[live], source[live], dest[live], coo.data[live]
        # world states that reach the target under some action (backwards closure)
        reach = target.copy()
        graph = sp.csr_matrix((np.ones(dest.size), (source, dest)), shape=(n_s, n_s))
        frontier = target.copy()
        while frontier.any():
            grown = (graph @ frontier.astype(np.float64)) > 0
            frontier = grown & ~reach
            reach |= grown
        solve = reach & ~ended
        self.scale = float(np.max(np.abs(worth[target]), initial=0.0)) or 1.0
        position = np.full(n_s, -1, dtype=np.int64)
        position[solve] = np.arange(int(solve.sum()))
        self.n = int(solve.sum()) * memory
        self.start_world = int(pomdp.initial_state)
        self.start = int(position[self.start_world]) * memory if solve[self.start_world] else -1
        self.start_value = float(worth[self.start_world]) if target[self.start_world] else 0.0
        keep = solve[source] & (solve[dest] | target[dest])
        action, source, dest, prob = action[keep], source[keep], dest[keep], prob[keep]
        # every world entry once per (source node n, next node n')
        k = memory
        n_node = np.repeat(np.arange(k), k)
        n_next = np.tile(np.arange(k), k)
        e = source.size
        src = np.repeat(source, k * k)
        dst = np.repeat(dest, k * k)
        act = np.repeat(action, k * k)
        p = np.repeat(prob, k * k)
        node = np.tile(n_node, e)
        nxt = np.tile(n_next, e)
        row = position[src] * k + node
        into_target = target[dst]
        self.src, self.act, self.node, self.nxt = src, act, node, nxt
        # entries among solved states: the matrix; entries into the target: the right side
        m = ~into_target
        self.m_row, self.m_col, self.m_p = row[m], position[dst[m]] * k + nxt[m], p[m]
        self.b_row, self.b_w = row[into_target], p[into_target] * worth[dst[into_target]]
        self.m_sel, self.b_sel = np.flatnonzero(m), np.flatnonzero(into_target)
        # CSC structure of I - Q, duplicates (several actions to one successor) summed once
        diag = np.arange(self.n)
        keys = np.concatenate([self.m_col * self.n + self.m_row, diag * self.n + diag])
        unique, self.inverse = np.unique(keys, return_inverse=True)
        self.inverse = self.inverse.reshape(-1)
        self.indices = (unique % self.n).astype(np.int32)
        self.indptr = np.searchsorted(unique // self.n, np.arange(self.n + 1)).astype(np.int32)
        self.n_unique = unique.size
        self.size = k * self.n_obs * self.n_actions * k

    def cell_index(self, alteration: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per entry (matrix, right side), its index into the flat μ under ``alteration``."""
        read = np.asarray(alteration, dtype=np.int64)[self.obs[self.src]]
        flat = ((self.node * self.n_obs + read) * self.n_actions + self.act) * self.k + self.nxt
        return flat[self.m_sel], flat[self.b_sel]

    def value_and_gradient(
        self, mu: np.ndarray, index: tuple[np.ndarray, np.ndarray], gradient: bool = True
    ) -> tuple[float, np.ndarray | None]:
        """V and ∂V/∂μ (flat μ, shape ``(size,)``) of one alteration's chain."""
        if self.start < 0:
            return self.start_value, np.zeros(self.size) if gradient else None
        m_index, b_index = index
        q = self.m_p * mu[m_index]
        data = np.bincount(
            self.inverse,
            weights=np.concatenate([-q, np.ones(self.n)]),
            minlength=self.n_unique,
        )
        system = sp.csc_matrix((data, self.indices, self.indptr), shape=(self.n, self.n))
        rhs = np.bincount(self.b_row, weights=self.b_w * mu[b_index], minlength=self.n)
        unit = np.zeros(self.n)
        unit[self.start] = 1.0
        if self.n > self.direct_limit:  # an LU's fill-in would be too large: Krylov solves
            x = _krylov(system.tocsr(), rhs)
            value = float(x[self.start])
            if not gradient:
                return value, None
            lam = _krylov(system.T.tocsr(), unit)
        else:
            lu = splu(system)
            x = lu.solve(rhs)
            value = float(x[self.start])
            if not gradient:
                return value, None
            lam = lu.solve(unit, trans="T")
        grad = np.bincount(
            m_index, weights=lam[self.m_row] * self.m_p * x[self.m_col], minlength=self.size
        )
        grad += np.bincount(b_index, weights=lam[self.b_row] * self.b_w, minlength=self.size)
        return value, grad


def _krylov(system: sp.csr_matrix, rhs: np.ndarray) -> np.ndarray:
    """``system⁻¹ rhs`` by BiCGSTAB (I - Q of an absorbing chain: it converges without a
    preconditioner in practice), GMRES where BiCGSTAB breaks down (it does on small chains);
    the answer as it stands if neither converges (the values only rank candidates)."""
    x, info = bicgstab(system, rhs, rtol=tolerance.GRADIENT_SOLVE, maxiter=KRYLOV_ITERATIONS)
    if info != 0:
        x, _ = gmres(
            system,
            rhs,
            rtol=tolerance.GRADIENT_SOLVE,
            restart=GMRES_RESTART,
            maxiter=KRYLOV_ITERATIONS // GMRES_RESTART,  # restart cycles
        )
    return np.asarray(x)


def softmax(theta: np.ndarray, shape: tuple[int, int, int]) -> np.ndarray:
    """μ (flat) from logits θ (flat), one distribution per (node, reading)."""
    z = theta.reshape(shape)
    z = z - z.max(axis=-1, keepdims=True)
    e = np.exp(z)
    return np.asarray((e / e.sum(axis=-1, keepdims=True)).reshape(-1))


def softmax_backward(
    mu: np.ndarray, grad_mu: np.ndarray, shape: tuple[int, int, int]
) -> np.ndarray:
    """∂/∂θ from ∂/∂μ through the softmax of each (node, reading)."""
    m, g = mu.reshape(shape), grad_mu.reshape(shape)
    return np.asarray((m * (g - (m * g).sum(axis=-1, keepdims=True))).reshape(-1))


def controller_of(mu: np.ndarray, memory: int, n_obs: int, n_actions: int) -> Controller:
    """The controller playing μ (flat, ``(k, |Ω|, |A|, k)``), its zero entries left out."""
    table = mu.reshape(memory, n_obs, n_actions, memory)
    node, obs, action, nxt = np.nonzero(table > 0)
    names = tuple(f"n{i}" for i in range(memory))
    return Controller.from_entries(
        nodes=names,
        initial_node=0,
        n_observations=n_obs,
        node=node,
        observation=obs,
        action=action,
        next_node=nxt,
        probability=table[node, obs, action, nxt],
    )


def mu_of(controller: Controller, n_obs: int, n_actions: int) -> np.ndarray:
    """A controller of the class as flat μ (its initial node first)."""
    k = controller.n_nodes
    order = [controller.initial_node] + [n for n in range(k) if n != controller.initial_node]
    position = np.empty(k, dtype=np.int64)
    position[order] = np.arange(k)
    node = np.repeat(np.arange(k), n_obs)
    obs = np.tile(np.arange(n_obs), k)
    owner, action, nxt, p = controller.entries(node, obs)
    table = np.zeros((k, n_obs, n_actions, k))
    np.add.at(table, (position[node[owner]], obs[owner], action, position[nxt]), p)
    return table.reshape(-1)


def embedded(mu: np.ndarray, n_obs: int, n_actions: int, memory: int) -> np.ndarray:
    """A controller's flat μ with ``k' ≤ memory`` nodes as a ``memory``-node one: the extra
    nodes, never entered, play as the initial node does."""
    k = math.isqrt(mu.size // (n_obs * n_actions))
    small = mu.reshape(k, n_obs, n_actions, k)
    table = np.zeros((memory, n_obs, n_actions, memory))
    table[:k, :, :, :k] = small
    table[k:, :, :, :k] = small[0][None]
    return table.reshape(-1)


def logits_of(mu: np.ndarray) -> np.ndarray:
    """Logits within the bounds whose softmax is closest to μ (its largest entries at the
    upper bound, zeros at the lower)."""
    floor = math.exp(-2 * LOGIT_BOUND)
    return np.asarray(
        np.clip(np.log(np.maximum(mu, floor)) + LOGIT_BOUND, -LOGIT_BOUND, LOGIT_BOUND)
    )


def pruned(mu: np.ndarray, level: float, shape: tuple[int, int, int]) -> np.ndarray:
    """μ with the probabilities below ``level`` dropped and each distribution renormalised
    (the largest entry of a distribution is always kept)."""
    m = mu.reshape(shape).copy()
    keep = (m >= level) | (m == m.max(axis=-1, keepdims=True))
    m = np.where(keep, m, 0.0)
    return np.asarray((m / m.sum(axis=-1, keepdims=True)).reshape(-1))


def better(score: tuple[float, ...], incumbent: tuple[float, ...]) -> bool:
    """Lexicographically smaller, entries within rounding of each other counting as equal."""
    for mine, theirs in zip(score, incumbent, strict=True):
        room = tolerance.slack(mine, theirs, rel=tolerance.TIE)
        if mine < theirs - room:
            return True
        if mine > theirs + room:
            return False
    return False


class _OutOfTimeError(Exception):
    """The deadline passed during an L-BFGS-B stage."""


class GradientMaster:
    """The randomized master: a local search, several starts, over ``k``-node controllers."""

    def __init__(
        self,
        model: ChainModel,
        sense: float,
        *,
        restarts: int = 4,
        seed: int = 0,
        seeds: list[np.ndarray] | None = None,
        floor: tuple[ChainModel, np.ndarray, float] | None = None,
    ) -> None:
        self.model, self.sense = model, sense
        self.shape = (model.k, model.n_obs, model.n_actions * model.k)
        self.restarts = max(int(restarts), 1)
        self.rng = np.random.default_rng(seed)
        # flat μ of controllers of the class given to start from (the baselines, the exact
        # one-node answer): each is a candidate as it is, so the answer over K is never worse
        self.seeds = [] if seeds is None else list(seeds)
        self.warm: np.ndarray | None = None  # the previous round's logits
        # a floor q on the nominal Pr(goal): the goal's chain model, no alteration, and q
        self.floor = floor
        self.floor_index = None if floor is None else floor[0].cell_index(floor[1])
        self._index: dict[bytes, tuple[np.ndarray, np.ndarray]] = {}

    def index(self, alteration: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        key = np.asarray(alteration, dtype=np.int64).tobytes()
        if key not in self._index:
            self._index[key] = self.model.cell_index(alteration)
        return self._index[key]

    def values(self, mu: np.ndarray, alterations: list[np.ndarray]) -> np.ndarray:
        """``sense · V_j`` for every member (full-support μ only)."""
        return np.array(
            [
                self.sense * self.model.value_and_gradient(mu, self.index(a), False)[0]
                for a in alterations
            ]
        )

    def starts(self) -> list[tuple[np.ndarray, np.ndarray | None]]:
        """(logits, the exact μ started from or None): the previous round's answer, the
        uniform controller, the seeds (their exact μ is a candidate too, so the answer is
        never worse than a seed over K), then seeded random logits; ``restarts`` in all, or
        more when the fixed ones are more."""
        size = self.model.size
        out: list[tuple[np.ndarray, np.ndarray | None]] = []
        if self.warm is not None:
            out.append((self.warm, None))
        out.append((np.zeros(size), None))
        for mu in self.seeds:
            out.append((logits_of(mu), mu))
        while len(out) < self.restarts:
            out.append((self.rng.normal(0.0, 1.5, size), None))
        return out

    def _descend(
        self, theta: np.ndarray, alterations: list[np.ndarray], deadline: Deadline
    ) -> tuple[np.ndarray, int]:
        indices = [self.index(a) for a in alterations]
        scale, model, shape = self.model.scale, self.model, self.shape
        iterations = 0
        for temperature, rho in zip(TEMPERATURES, FLOOR_WEIGHTS, strict=True):
            tau = temperature * scale
            lowest: list[tuple[float, np.ndarray]] = []  # the best point this stage evaluated

            def smooth_max(
                th: np.ndarray,
                tau: float = tau,
                rho: float = rho,
                lowest: list[tuple[float, np.ndarray]] = lowest,
            ) -> tuple[float, np.ndarray]:
                if deadline.expired():  # L-BFGS-B has no deadline: stop it from inside
                    raise _OutOfTimeError
                mu = softmax(th, shape)
                vals = np.empty(len(indices))
                grads = np.empty((len(indices), model.size))
                for j, index in enumerate(indices):
                    v, g = model.value_and_gradient(mu, index)
                    assert g is not None
                    vals[j], grads[j] = self.sense * v, self.sense * g
                top = vals.max()
                w = np.exp((vals - top) / tau)
                total = w.sum()
                value = top + tau * math.log(total)
                grad_mu = (w / total) @ grads / scale
                value /= scale
                if self.floor is not None and self.floor_index is not None:
                    goal, g_goal = self.floor[0].value_and_gradient(mu, self.floor_index)
                    short = self.floor[2] - goal
                    if short > 0 and g_goal is not None:
                        value += rho * short * short
                        grad_mu = grad_mu - 2.0 * rho * short * g_goal
                if not lowest or value < lowest[0][0]:
                    lowest[:] = [(value, np.array(th))]
                return value, softmax_backward(mu, grad_mu, shape)

            if deadline.expired():
                break
            try:
                result = minimize(
                    smooth_max,
                    theta,
                    jac=True,
                    method="L-BFGS-B",
                    bounds=[(-LOGIT_BOUND, LOGIT_BOUND)] * theta.size,
                    options={"maxiter": ITERATIONS_PER_STAGE},
                )
            except _OutOfTimeError:
                if lowest:
                    theta = lowest[0][1]
                break
            theta, iterations = result.x, iterations + int(result.nit)
        return theta, iterations

    def _ranked(
        self, exact_worst: ExactWorst, controller: Controller, deadline: Deadline
    ) -> tuple[float, float, float]:
        """``exact_worst(controller)``; on a chain past the direct solver's size in a forked
        copy killed at ``deadline``: one exact evaluation there is a sparse LU, which on a
        drone's 103,000-state chain of a sharp controller ran for more than ten minutes
        (the uniform one's takes a second), and cannot stop by itself."""
        if self.model.n <= self.model.direct_limit:
            return exact_worst(controller)
        return forked_call(lambda: exact_worst(controller), deadline)

    def solve(
        self,
        alterations: list[np.ndarray],
        deadline: Deadline,
        exact_worst: ExactWorst,
    ) -> MasterAnswer | None:
        """The best controller found against ``alterations``, or None when the deadline
        stopped the first start. ``exact_worst(controller)`` is the loop's exact evaluation
        (``sense ·`` the worst over K), which picks among the candidates: each start's
        softmax controller and its pruned versions."""
        best: tuple[tuple[float, float, float], Controller, np.ndarray] | None = None
        iterations = looked = 0
        for theta0, exact in self.starts():
            if deadline.expired() and best is not None:
                break
            theta, nit = self._descend(theta0, alterations, deadline)
            iterations += nit
            looked += 1
            mu = softmax(theta, self.shape)
            offered = [mu, *(pruned(mu, level, self.shape) for level in PRUNE_LEVELS)]
            for candidate in offered if exact is None else [exact, *offered]:
                if best is not None and deadline.expired():
                    break
                controller = controller_of(
                    candidate, self.model.k, self.model.n_obs, self.model.n_actions
                )
                try:
                    score = self._ranked(exact_worst, controller, deadline)
                except DeadlineExpiredError:
                    break
                if best is None or better(score, best[0]):
                    best = (score, controller, theta)
        if best is None:
            return None
        self.warm = best[2]
        return MasterAnswer(
            controller=best[1],
            value=self.sense * best[0][1],
            candidates=looked,
            iterations=iterations,
            finished=True,
        )
