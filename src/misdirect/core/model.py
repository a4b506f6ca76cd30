"""The OSA_DGM problem as integer-indexed arrays.

Outside this package everything has a name (states, actions, observations, memory nodes);
inside, every name is an index into a tuple of names, and the model is a handful of numpy /
scipy.sparse arrays so that product construction and evaluation are vectorised.

An *alteration* is an integer array ``alpha`` of length ``|Ω|`` with ``alpha[o]`` the observation
the robot receives instead of ``o`` (SPEC §1: a function, the initial observation fixed).
"""

from __future__ import annotations

import json
import re
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field, replace
from functools import cached_property
from pathlib import PurePath
from typing import TYPE_CHECKING, Any, cast

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import breadth_first_order

from misdirect.core import tolerance
from misdirect.core.notebook import Shown
from misdirect.core.objective import DecoySet, Objective
from misdirect.errors import ProblemError

if TYPE_CHECKING:
    from misdirect.core.notebook import View

# an alteration as a plain int array, ``alpha[o]`` = the observation received instead of ``o``:
# what the solvers pass around (an :class:`Alteration` is one too)
AlterationArray = np.ndarray


class Alteration(np.ndarray[Any, np.dtype[np.int64]]):
    """An alteration ``α: Ω → Ω`` that names its observations.

    It *is* the integer array ``alpha`` (``alpha[o]`` is the observation the robot receives
    instead of ``o``), so every function taking an alteration array takes it, and
    ``np.asarray(alteration)`` is the plain array; it also knows the observation names, so it
    prints and converts as names. Build one with :meth:`Problem.alteration`.

    Attributes
    ----------
    observations : tuple of str
        The problem's observation names, indexed like the array.

    Examples
    --------
    >>> from misdirect.scenarios import paper_grid
    >>> alteration = paper_grid(5).alteration({"o1": "o3"})
    >>> alteration
    Alteration({'o1': 'o3'})
    >>> alteration.changes
    {'o1': 'o3'}
    >>> alteration["o1"], int(alteration[1])
    ('o3', 3)
    >>> import numpy as np
    >>> np.asarray(alteration).tolist()
    [0, 3, 2, 3, 4, 5, 6, 7]
    """

    observations: tuple[str, ...]

    def __new__(cls, values: Any, observations: Iterable[str]) -> Alteration:
        names = tuple(observations)
        array = np.array(values, dtype=np.int64)
        if array.shape != (len(names),):
            raise ValueError(
                f"an alteration has one entry per observation ({len(names)}), "
                f"got shape {array.shape}"
            )
        alteration = array.view(cls)
        alteration.observations = names
        return alteration

    def __array_finalize__(self, obj: Any) -> None:
        self.observations = getattr(obj, "observations", ())

    def __array_wrap__(self, array: Any, context: Any = None, return_scalar: bool = False) -> Any:
        # arithmetic and comparisons give plain arrays: ``alpha != identity`` is a mask,
        # not an alteration
        plain = np.asarray(array)
        return plain[()] if return_scalar else plain

    def __getitem__(self, key: Any) -> Any:
        if isinstance(key, str):  # by name: the observation received instead of ``key``
            return self.observations[int(np.asarray(self)[self._index(key)])]
        item = super().__getitem__(key)
        return np.asarray(item) if isinstance(item, np.ndarray) else item

    def _index(self, name: str) -> int:
        try:
            return self.observations.index(name)
        except ValueError:
            known = _preview(self.observations)
            raise KeyError(f"unknown observation {name!r} (known: {known})") from None

    @property
    def changes(self) -> dict[str, str]:
        """``{observation: received observation}`` for the observations that change."""
        plain = np.asarray(self)
        names = self.observations
        return {
            names[o]: names[int(plain[o])] for o in np.flatnonzero(plain != np.arange(plain.size))
        }

    def to_dict(self) -> dict[str, str]:
        """The changes as names (:attr:`changes`), the form of every ``--json`` output."""
        return self.changes

    def __repr__(self) -> str:
        if self.ndim != 1 or len(self.observations) != self.size:
            return repr(np.asarray(self))
        return f"Alteration({self.changes!r})"

    def __str__(self) -> str:
        return format_alteration(self.changes) if self.ndim == 1 else str(np.asarray(self))

    def __reduce__(self) -> Any:  # pickles (worker processes) as names and values
        return (Alteration, (np.asarray(self).copy(), self.observations))


@dataclass(frozen=True, eq=False, repr=False)
class Pomdp:
    """World dynamics with a deterministic, state-based observation function.

    ``transitions`` stacks one ``|S| x |S|`` block per action: row ``a * |S| + s`` is the
    distribution ``P(s, a, ·)``. Absorbing states carry a self-loop under every action, so the
    matrix is stochastic and the product construction needs no special case for them.
    """

    states: tuple[str, ...]
    actions: tuple[str, ...]
    observations: tuple[str, ...]
    initial_state: int
    observation_of: np.ndarray  # (|S|,) int
    transitions: sp.csr_matrix  # (|A|*|S|, |S|)
    absorbing: np.ndarray  # (|S|,) bool

    def __repr__(self) -> str:
        return (
            f"Pomdp({self.n_states} states, {self.n_actions} actions, "
            f"{self.n_observations} observations, {self.transitions.nnz} transitions)"
        )

    @classmethod
    def from_triplets(
        cls,
        *,
        states: tuple[str, ...],
        actions: tuple[str, ...],
        observations: tuple[str, ...],
        initial_state: int,
        observation_of: np.ndarray,
        action: np.ndarray,
        source: np.ndarray,
        target: np.ndarray,
        probability: np.ndarray,
        absorbing: np.ndarray,
    ) -> Pomdp:
        """Assemble from ``(action, source, target, probability)`` entries.

        Absorbing states get their self-loops here; entries listed for them are ignored.
        """
        n_s, n_a = len(states), len(actions)
        absorbing = np.asarray(absorbing, dtype=bool)
        keep = ~absorbing[source] & (probability > 0)
        loops = np.flatnonzero(absorbing)
        rows = np.concatenate(
            [action[keep] * n_s + source[keep], (np.arange(n_a)[:, None] * n_s + loops).ravel()]
        )
        cols = np.concatenate([target[keep], np.tile(loops, n_a)])
        data = np.concatenate([probability[keep], np.ones(loops.size * n_a)])
        matrix = sp.csr_matrix((data, (rows, cols)), shape=(n_a * n_s, n_s))
        matrix.sum_duplicates()
        return cls(
            states=tuple(states),
            actions=tuple(actions),
            observations=tuple(observations),
            initial_state=int(initial_state),
            observation_of=np.asarray(observation_of, dtype=np.int64),
            transitions=matrix,
            absorbing=absorbing,
        )

    @property
    def n_states(self) -> int:
        return len(self.states)

    @property
    def n_actions(self) -> int:
        return len(self.actions)

    @property
    def n_observations(self) -> int:
        return len(self.observations)

    @property
    def initial_observation(self) -> int:
        return int(self.observation_of[self.initial_state])

    def transition_matrix(self, action: int) -> sp.csr_matrix:
        """``P(·, action, ·)`` as an ``|S| x |S|`` CSR matrix."""
        n = self.n_states
        return self.transitions[action * n : (action + 1) * n]

    @cached_property
    def successor_graph(self) -> sp.csr_matrix:
        """Union over actions of the transition structure (s -> s' possible under some action)."""
        n = self.n_states
        stacked = self.transitions.tocoo()
        graph = sp.csr_matrix(
            (np.ones(stacked.nnz, dtype=np.int8), (stacked.row % n, stacked.col)), shape=(n, n)
        )
        graph.sum_duplicates()
        return graph


@dataclass(frozen=True, eq=False, init=False, repr=False)
class Controller:
    """Finite-state controller, deterministic or randomized.

    In node ``n`` reading ``o`` the robot plays the *move* ``move[n, o]``: a distribution over
    (action, next node) pairs, drawn jointly. The moves are one table in CSR form: move ``m``
    is entries ``move_ptr[m]:move_ptr[m + 1]`` of ``move_action``, ``move_next`` and
    ``move_probability``. Moves are canonical (no zero entries, no repeated pair, entries
    sorted by (action, next node), identical distributions share one id), so two cells play
    the same distribution exactly when they hold the same move id. A deterministic controller
    is the case where every move has one entry of probability 1; the factored form of the
    literature (γ(n, o) a distribution over actions, δ(n, o) over next nodes, drawn
    independently) is the product distribution (:func:`factored_entries`).

    ``Controller(nodes=..., initial_node=..., action=..., update=...)`` builds a deterministic
    one from ``action[n, o] = γ(n, o)`` and ``update[n, o] = δ(n, o)``;
    :meth:`from_entries` builds any.
    """

    nodes: tuple[str, ...]
    initial_node: int
    move: np.ndarray  # (|N|, |Ω|) int, the move played in node n on reading o
    move_ptr: np.ndarray  # (M + 1,) int, CSR pointer into the entry arrays
    move_action: np.ndarray  # (E,) int
    move_next: np.ndarray  # (E,) int
    move_probability: np.ndarray  # (E,) float, positive, summing to 1 per move

    def __init__(
        self,
        *,
        nodes: tuple[str, ...],
        initial_node: int,
        action: np.ndarray,
        update: np.ndarray,
    ) -> None:
        """A deterministic controller from its action and update tables."""
        action = np.asarray(action, dtype=np.int64)
        update = np.asarray(update, dtype=np.int64)
        n_nodes = len(nodes)
        keys, move = np.unique(action * n_nodes + update, return_inverse=True)
        move_action, move_next = np.divmod(keys, n_nodes)
        self._assign(
            nodes,
            initial_node,
            move.reshape(action.shape),
            np.arange(keys.size + 1),
            move_action,
            move_next,
            np.ones(keys.size),
        )

    def _assign(
        self,
        nodes: Iterable[str],
        initial_node: int,
        move: np.ndarray,
        ptr: np.ndarray,
        action: np.ndarray,
        next_node: np.ndarray,
        probability: np.ndarray,
    ) -> None:
        for name, value in (
            ("nodes", tuple(nodes)),
            ("initial_node", int(initial_node)),
            ("move", np.asarray(move, dtype=np.int64)),
            ("move_ptr", np.asarray(ptr, dtype=np.int64)),
            ("move_action", np.asarray(action, dtype=np.int64)),
            ("move_next", np.asarray(next_node, dtype=np.int64)),
            ("move_probability", np.asarray(probability, dtype=np.float64)),
        ):
            object.__setattr__(self, name, value)

    @classmethod
    def from_entries(
        cls,
        *,
        nodes: tuple[str, ...],
        initial_node: int,
        n_observations: int,
        node: np.ndarray,
        observation: np.ndarray,
        action: np.ndarray,
        next_node: np.ndarray,
        probability: np.ndarray,
    ) -> Controller:
        """Any controller from flat entries: in ``node[i]`` reading ``observation[i]``, play
        ``action[i]`` and move to ``next_node[i]`` with ``probability[i]``.

        Every (node, observation) needs entries summing to 1 (within 1e-9; they are then
        normalised exactly); repeated pairs are added up. Callers check their input with
        their own field names; this is the safety net."""
        n_nodes = len(nodes)
        node, observation, action, next_node = (
            np.asarray(a, dtype=np.int64) for a in (node, observation, action, next_node)
        )
        probability = np.asarray(probability, dtype=np.float64)
        n_actions = int(action.max(initial=-1)) + 1
        cell = node * n_observations + observation
        keys, inverse = np.unique(
            (cell * n_actions + action) * n_nodes + next_node, return_inverse=True
        )
        mass: np.ndarray = np.bincount(
            inverse.reshape(-1), weights=probability, minlength=keys.size
        )
        keep = mass > 0
        keys, mass = keys[keep], mass[keep]
        rest, e_next = np.divmod(keys, n_nodes)
        e_cell, e_action = np.divmod(rest, n_actions)
        n_cells = n_nodes * n_observations
        total = np.bincount(e_cell, weights=mass, minlength=n_cells)
        if np.any(np.abs(total - 1.0) > tolerance.STOCHASTIC):
            bad = int(np.flatnonzero(np.abs(total - 1.0) > tolerance.STOCHASTIC)[0])
            raise ProblemError(
                f"node {nodes[bad // n_observations]!r}, observation {bad % n_observations}: "
                f"the move's probabilities sum to {total[bad]:.12g}, not 1",
                field="controller",
            )
        mass = mass / total[e_cell]
        # identical distributions get one move id: cells are compared among those with the
        # same number of entries, each as one row (action, next, probability, ...)
        count = np.bincount(e_cell, minlength=n_cells)
        start = np.concatenate([[0], np.cumsum(count)[:-1]])
        move = np.empty(n_cells, dtype=np.int64)
        ptr, m_action, m_next, m_prob = [np.zeros(1, dtype=np.int64)], [], [], []
        n_moves = 0
        for k in np.unique(count).tolist():  # a handful of distinct support sizes
            cells = np.flatnonzero(count == k)
            at = start[cells][:, None] + np.arange(k)
            rows = np.concatenate([e_action[at], e_next[at], mass[at]], axis=1)
            distinct, which = np.unique(rows, axis=0, return_inverse=True)
            move[cells] = n_moves + which.reshape(-1)
            n_moves += distinct.shape[0]
            ptr.append(ptr[-1][-1] + k * np.arange(1, distinct.shape[0] + 1))
            m_action.append(distinct[:, :k].astype(np.int64).ravel())
            m_next.append(distinct[:, k : 2 * k].astype(np.int64).ravel())
            m_prob.append(distinct[:, 2 * k :].ravel())
        controller = cls.__new__(cls)
        controller._assign(
            nodes,
            initial_node,
            move.reshape(n_nodes, n_observations),
            np.concatenate(ptr),
            np.concatenate(m_action),
            np.concatenate(m_next),
            np.concatenate(m_prob),
        )
        return controller

    def __repr__(self) -> str:
        kind = "deterministic" if self.is_deterministic else "randomized"
        return (
            f"Controller({self.n_nodes} nodes, {kind}, initial {self.nodes[self.initial_node]!r})"
        )

    @property
    def n_nodes(self) -> int:
        return len(self.nodes)

    @property
    def n_moves(self) -> int:
        return int(self.move_ptr.size - 1)

    @cached_property
    def move_size(self) -> np.ndarray:
        """Number of (action, next node) entries of each move."""
        return np.diff(self.move_ptr)

    @cached_property
    def is_deterministic(self) -> bool:
        """Every move is one (action, next node) pair played with probability 1."""
        return bool(np.all(self.move_size[np.unique(self.move)] == 1))

    def _deterministic_table(self, what: str, values: np.ndarray) -> np.ndarray:
        if not self.is_deterministic:
            raise ProblemError(
                f"the controller is randomized: it has no single {what} per (node, "
                "observation); use its moves (Controller.entries)",
                field="controller",
            )
        return cast(np.ndarray, values[self.move_ptr[:-1]][self.move])

    @cached_property
    def action(self) -> np.ndarray:
        """``γ(n, o)`` of a deterministic controller, ``(|N|, |Ω|)``."""
        return self._deterministic_table("action", self.move_action)

    @cached_property
    def update(self) -> np.ndarray:
        """``δ(n, o)`` of a deterministic controller, ``(|N|, |Ω|)``."""
        return self._deterministic_table("next node", self.move_next)

    def move_entries(
        self, moves: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The entries of ``moves``, concatenated: ``(owner, action, next node, probability)``
        with ``owner[i]`` the position in ``moves`` the entry belongs to (non-decreasing)."""
        moves = np.asarray(moves, dtype=np.int64)
        starts, counts = self.move_ptr[moves], self.move_size[moves]
        owner = np.repeat(np.arange(moves.size), counts)
        offsets = np.cumsum(counts) - counts
        at = np.repeat(starts - offsets, counts) + np.arange(int(counts.sum()))
        return owner, self.move_action[at], self.move_next[at], self.move_probability[at]

    def entries(
        self, node: np.ndarray, received: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """What the robot may do in ``node[i]`` reading ``received[i]``, as
        :meth:`move_entries` (``owner`` indexes the given cells)."""
        return self.move_entries(self.move[node, received])

    def move_table(self, move: int) -> list[tuple[int, int, float]]:
        """Move ``move`` as ``[(action, next node, probability), ...]`` (for writing it)."""
        at = slice(int(self.move_ptr[move]), int(self.move_ptr[move + 1]))
        return list(
            zip(
                self.move_action[at].tolist(),
                self.move_next[at].tolist(),
                self.move_probability[at].tolist(),
                strict=True,
            )
        )

    def factored_move(self, move: int) -> tuple[dict[int, float], dict[int, float]] | None:
        """The action and next-node marginals of ``move`` when the move is their product
        (within 1e-12: the factored form describes it), else None."""
        table = self.move_table(move)
        by_action: dict[int, float] = {}
        by_next: dict[int, float] = {}
        for a, n, p in table:
            by_action[a] = by_action.get(a, 0.0) + p
            by_next[n] = by_next.get(n, 0.0) + p
        if len(table) != len(by_action) * len(by_next):
            return None
        if any(abs(p - by_action[a] * by_next[n]) > tolerance.TIE for a, n, p in table):
            return None
        return by_action, by_next

    @cached_property
    def behaviour_class(self) -> np.ndarray:
        """Class id per observation; equal ids mean the same move distribution on every node.

        Two targets of the same class are interchangeable for the attacker (only the cheaper one
        matters), which is what makes enumeration and the compact MILP small. Moves are
        canonical, so comparing move ids compares distributions exactly.
        """
        _, inverse = np.unique(self.move.T, axis=0, return_inverse=True)
        return inverse.reshape(-1).astype(np.int64)


def factored_entries(
    actions: Mapping[int, float], updates: Mapping[int, float]
) -> list[tuple[int, int, float]]:
    """The joint move of a factored choice: action and next node drawn independently
    (as PAYNT's ``FscFactored`` means it), ``[(action, next node, probability), ...]``."""
    return [(a, m, p * q) for a, p in actions.items() for m, q in updates.items()]


@dataclass(frozen=True, eq=False)
class CostModel:
    """Alteration costs ``c(o, o')``; ``inf`` marks a forbidden alteration.

    Stored as a default plus sparse overrides so that models with many observations do not
    need a dense ``|Ω| x |Ω|`` table; :meth:`row` materialises one source at a time.
    """

    n_observations: int
    default: float = 1.0
    pairs: Mapping[tuple[int, int], float] = field(default_factory=dict)
    protected: frozenset[int] = frozenset()

    @cached_property
    def pairs_by_source(self) -> dict[int, tuple[np.ndarray, np.ndarray]]:
        """:attr:`pairs` grouped by source: its targets and their costs, as arrays (read by
        :mod:`misdirect.core.alterations` to enumerate and bound without a row per source)."""
        grouped: dict[int, tuple[list[int], list[float]]] = {}
        for (source, target), cost in self.pairs.items():
            targets, costs = grouped.setdefault(source, ([], []))
            targets.append(target)
            costs.append(cost)
        return {o: (np.array(t, dtype=np.int64), np.array(c)) for o, (t, c) in grouped.items()}

    def row(self, source: int) -> np.ndarray:
        """Costs of altering ``source`` to every observation (``inf`` where forbidden)."""
        costs = np.full(self.n_observations, np.inf if source in self.protected else self.default)
        if source not in self.protected and source in self.pairs_by_source:
            targets, values = self.pairs_by_source[source]
            costs[targets] = values
        costs[source] = 0.0
        return costs

    def matrix(self) -> np.ndarray:
        """Dense ``|Ω| x |Ω|`` cost table (for small models, reports and MILP export)."""
        return np.vstack([self.row(o) for o in range(self.n_observations)])

    @cached_property
    def scale(self) -> tolerance.CostScale:
        """How this model's costs add up and fit a budget, exactly (budgets become caps)."""
        values = [self.default, *self.pairs.values()]
        return tolerance.CostScale.of(values, self.n_observations - len(self.protected))

    def terms(self, alteration: AlterationArray) -> list[float]:
        """The costs an alteration adds up, one per altered observation."""
        changed = np.flatnonzero(alteration != np.arange(self.n_observations))
        return [float(self.row(int(o))[alteration[o]]) for o in changed]

    def cost(self, alteration: AlterationArray) -> float:
        """The alteration's cost: the float nearest its exact sum (:meth:`fits` decides)."""
        terms = self.terms(alteration)
        return float(self.scale.exact(terms)) if np.isfinite(terms).all() else np.inf

    def fits(self, alteration: AlterationArray, budget: float) -> bool:
        """Whether the alteration's exact cost fits ``budget``: the final word on a budget."""
        terms = self.terms(alteration)
        return bool(np.isfinite(terms).all()) and self.scale.fits_exactly(terms, budget)


@dataclass(frozen=True, eq=False, repr=False)
class Problem(Shown):
    """One OSA_DGM instance: maximise Pr(reach decoy) over alterations with cost ≤ budget.

    With ``decoy_sets`` (weighted decoys) the objective is the expected weight of the first
    decoy state entered instead; ``decoy`` is then their union. Solvers read the objective
    through :attr:`objective` only, so both cases are one code path.

    Build one with :func:`misdirect.load_problem` (a file), :func:`misdirect.problem_from_dict`
    (the same document in memory) or a generator of :mod:`misdirect.scenarios`.

    Attributes
    ----------
    pomdp : Pomdp
        The world: states, actions, observations, transitions (names in ``pomdp.states``,
        ``pomdp.observations``, ...).
    controller : Controller
        The robot's finite-state controller.
    cost : CostModel
        What altering each observation into each other costs (``inf``: not allowed).
    decoy : ndarray of bool
        The decoy states.
    budget : float
        The attacker's budget.
    name : str
        A name for reports.
    source : str or None
        The file it came from.

    Examples
    --------
    >>> from misdirect.scenarios import paper_grid
    >>> paper_grid(5)
    Problem('paper grid 5x5': 25 states, 4 actions, 8 observations, 3 memory nodes, budget 4)
    """

    pomdp: Pomdp
    controller: Controller
    cost: CostModel
    decoy: np.ndarray  # (|S|,) bool
    budget: float
    name: str = ""
    source: str | None = None  # file it came from, for error messages
    decoy_sets: tuple[DecoySet, ...] = ()
    # doubts the reader had about the input (a PAYNT controller made for another build of the
    # model): every result about this problem repeats them
    warnings: tuple[str, ...] = ()
    # a monitored problem (misdirect.core.monitor.with_monitor): the absorbing state a run
    # enters when the monitor raises the alarm, and the monitor's name
    alarm_state: int | None = None
    monitor: str = ""
    # a PRISM property as the objective (misdirect.core.objective_property.with_property): its
    # text, and its step bound (a counter folded in; a run past it ends in alarm_state)
    reach_property: str = ""
    step_bound: int | None = None
    # the problem before with_monitor folded the monitor in (Problem.without_monitor)
    unwatched: Problem | None = field(default=None, repr=False)

    def __repr__(self) -> str:
        pomdp = self.pomdp
        return (
            f"Problem({self.name!r}: {pomdp.n_states} states, {pomdp.n_actions} actions, "
            f"{pomdp.n_observations} observations, {self.controller.n_nodes} memory nodes, "
            f"budget {self.budget:g})"
        )

    def _view(self) -> View:
        """The problem in a notebook: its sizes, names, decoys, costs and budget."""
        from misdirect.core import notebook as nb

        pomdp, controller, cost = self.pomdp, self.controller, self.cost
        decoys = [pomdp.states[s] for s in np.flatnonzero(self.decoy)]
        kind = "deterministic" if controller.is_deterministic else "randomized"
        s0 = pomdp.initial_state
        facts = [
            ("states", nb.text(f"{pomdp.n_states:,} ({int(pomdp.absorbing.sum()):,} absorbing)")),
            ("actions", nb.names(pomdp.actions, where="problem.pomdp.actions")),
            (
                f"observations ({pomdp.n_observations:,})",
                nb.names(pomdp.observations, where="problem.pomdp.observations"),
            ),
            ("memory nodes", nb.text(f"{controller.n_nodes:,} ({kind} controller)")),
            (
                "initial state",
                nb.text(
                    f"{pomdp.states[s0]} (reads {pomdp.observations[pomdp.initial_observation]})"
                ),
            ),
            (f"decoy states ({len(decoys):,})", nb.names(decoys, where="problem.decoy")),
            ("objective", nb.text(self.objective.label)),
            ("budget", nb.amount(self.budget)),
            ("cost of an alteration", nb.text(_cost_summary(cost))),
            (
                "protected sensors",
                nb.names(sorted(pomdp.observations[o] for o in cost.protected)),
            ),
        ]
        if self.decoy_sets:
            sets = [f"{d.name}: weight {d.weight:g}" for d in self.decoy_sets]
            facts.append(("decoy sets", nb.names(sets)))
        if self.source:
            facts.append(("file", nb.text(self.source)))
        return nb.View(f"Problem {self.title}", facts, (), [*self.warnings, *self.notes])

    @cached_property
    def objective(self) -> Objective:
        if not self.decoy_sets:
            return Objective.single(self.decoy)
        objective = Objective.weighted(self.decoy_sets)
        if not np.array_equal(objective.target, np.asarray(self.decoy, dtype=bool)):
            raise ProblemError("decoy must be the union of decoy_sets", field="decoy")
        return objective

    @property
    def title(self) -> str:
        """What titles call the problem: its name, else its file's name, else "problem"."""
        if self.name:
            return self.name
        return PurePath(self.source).name if self.source else "problem"

    @property
    def notes(self) -> tuple[str, ...]:
        """What every result about this problem says beside its numbers, though nothing is
        wrong: a robot that starts in a decoy state scores at once, whatever it reads."""
        s0 = self.pomdp.initial_state
        watched = self._monitor_note()
        if not self.decoy[s0]:
            return (*watched, *self._shared_initial_observation())
        score = float(self.objective.value[s0])
        return (
            *watched,
            f"the initial state {self.pomdp.states[s0]!r} is a decoy: every run scores "
            f"{score:g} at once, whatever the robot reads, so no alteration changes the value",
        )

    def _monitor_note(self) -> tuple[str, ...]:
        """A monitored problem says what its value means (docs/stealth.md)."""
        notes: list[str] = []
        if self.reach_property:
            notes.append(f"the objective is the property {self.reach_property}")
        if self.alarm_state is None:
            return tuple(notes)
        sink = self.pomdp.states[self.alarm_state]
        if self.step_bound is not None:
            notes.append(
                f"a run still outside the decoy after {self.step_bound} "
                f"step{'s' * (self.step_bound != 1)} ends in {sink!r}"
            )
        if self.monitor:
            notes.append(
                f"watched by a monitor ({self.monitor}): the value is Pr(reach a decoy before "
                f"the alarm); a run the alarm catches ends in {sink!r}"
            )
        return tuple(notes)

    def _shared_initial_observation(self) -> tuple[str, ...]:
        """The initial observation is never altered, so neither is any other state that emits
        it: say how many (a grid whose start cell has no sensor reads ``b`` there, which
        silently makes every blank cell unalterable)."""
        pomdp = self.pomdp
        o_init = pomdp.initial_observation
        shared = (pomdp.observation_of == o_init) & ~pomdp.absorbing
        shared[pomdp.initial_state] = False
        count = int(shared.sum())
        if count == 0:
            return ()
        live = int((~pomdp.absorbing).sum())
        name = pomdp.observations[o_init]
        return (
            f"the initial state {pomdp.states[pomdp.initial_state]!r} reads {name!r}, which is "
            f"never altered (the robot reads it before any attack), so the {count} other "
            f"state{'s' * (count > 1)} reading {name!r} ({count} of the {live} non-absorbing "
            "states) cannot be altered either; give the initial state an observation of its "
            "own (grid maps: a start cell with its own sensor, {start: true, sensor: ...})",
        )

    def with_budget(self, budget: float) -> Problem:
        return replace(self, budget=float(budget))

    def without_monitor(self) -> Problem:
        """The problem as it was before :func:`~misdirect.core.monitor.with_monitor` folded
        its monitor in, with this one's costs, protected sensors and budget (the alteration
        space is the same): what a defender compares the monitor with."""
        if self.unwatched is None:
            raise ProblemError(
                "the problem is not watched by a monitor (with_monitor)", field="monitor"
            )
        return replace(self.unwatched, cost=self.cost, budget=self.budget)

    def unweighted(self) -> Problem:
        """The same problem scoring 1 for every decoy state: Pr(reach any decoy)."""
        return replace(self, decoy_sets=()) if self.decoy_sets else self

    # -- alterations -------------------------------------------------------------------------
    def identity(self) -> AlterationArray:
        return np.arange(self.pomdp.n_observations, dtype=np.int64)

    def alteration_cost(self, alteration: AlterationArray) -> float:
        return self.cost.cost(alteration)

    def changed_observations(self, alteration: AlterationArray) -> dict[str, str]:
        """The alteration as names, listing only observations that change."""
        names = self.pomdp.observations
        return {
            names[o]: names[int(alteration[o])]
            for o in np.flatnonzero(alteration != self.identity())
        }

    def alteration(self, changes: Mapping[str, str], *, source: str = "alteration") -> Alteration:
        """Build and check an alteration from ``{observation: received observation}`` names.

        Parameters
        ----------
        changes : mapping of str to str
            Each observation to alter, with the observation the robot receives instead.
            Observations not named are left unaltered.
        source : str, optional
            What to name in an error message (a file, a flag).

        Returns
        -------
        Alteration
            The alteration, an integer array that names its observations.

        Raises
        ------
        ProblemError
            An unknown observation name, the initial observation altered, or a pair the cost
            model forbids (or protects).

        Examples
        --------
        >>> from misdirect.scenarios import paper_grid
        >>> paper_grid(5).alteration({"o1": "o3", "o2": "o0"})
        Alteration({'o1': 'o3', 'o2': 'o0'})
        """
        index = {name: i for i, name in enumerate(self.pomdp.observations)}
        alpha = self.identity()
        for original, received in changes.items():
            for name in (original, received):
                if name not in index:
                    known = _preview(self.pomdp.observations)
                    raise ProblemError(
                        f"unknown observation {name!r} (known: {known})",
                        source=source,
                        field=f"{original}={received}",
                    )
            alpha[index[original]] = index[received]
        self.check_alteration(alpha, source=source)
        return Alteration(alpha, self.pomdp.observations)

    def as_alteration(self, alteration: Any, *, source: str = "alteration") -> AlterationArray:
        """An alteration given as an array (``alpha[o]`` = the observation received instead
        of ``o``), checked where the library takes one: integers (``0.9`` is no observation,
        and is not truncated to 0), one per observation, each an observation's index (``-4``
        does not wrap around), and the initial observation left as it is. A mapping of names
        is read by :meth:`alteration` (``{}``: no alteration; ``np.asarray({})`` is a 0-d
        object array, which no check above would read as the unaltered chain)."""
        if isinstance(alteration, Mapping):
            return self.alteration(alteration, source=source)
        array = np.asarray(alteration)
        n = self.pomdp.n_observations
        if array.shape != (n,):
            raise ProblemError(
                f"expected one observation index per observation ({n}), got shape {array.shape}",
                source=source,
            )
        if array.dtype.kind not in "iu":
            raise ProblemError(
                f"expected integer observation indices, got {array.dtype} values "
                f"({', '.join(map(str, array[:4].tolist()))}{', …' if n > 4 else ''})",
                source=source,
            )
        outside = np.flatnonzero((array < 0) | (array >= n))
        if outside.size:
            o = int(outside[0])
            raise ProblemError(
                f"{self.pomdp.observations[o]!r} (index {o}) is sent to {array[o]}, not an "
                f"observation index (0 to {n - 1})",
                source=source,
            )
        array = array.astype(np.int64)
        o_init = self.pomdp.initial_observation
        if array[o_init] != o_init:
            names = self.pomdp.observations
            raise ProblemError(
                f"the initial observation {names[o_init]!r} is never altered "
                "(docs/problem-format.md)",
                source=source,
                field=f"{names[o_init]}={names[int(array[o_init])]}",
            )
        return array

    def check_alteration(self, alteration: AlterationArray, *, source: str = "alteration") -> None:
        """Reject alterations the problem does not allow (initial observation, forbidden pairs)."""
        names = self.pomdp.observations
        o_init = self.pomdp.initial_observation
        if alteration[o_init] != o_init:
            raise ProblemError(
                f"the initial observation {names[o_init]!r} is never altered "
                "(docs/problem-format.md)",
                source=source,
                field=f"{names[o_init]}={names[int(alteration[o_init])]}",
            )
        for o in np.flatnonzero(alteration != self.identity()):
            if not np.isfinite(self.cost.row(int(o))[alteration[o]]):
                reason = "protected" if int(o) in self.cost.protected else "forbidden"
                raise ProblemError(
                    f"altering {names[o]!r} to {names[int(alteration[o])]!r} is {reason} "
                    "by deception.cost",
                    source=source,
                    field=f"{names[o]}={names[int(alteration[o])]}",
                )

    # -- derived sets ------------------------------------------------------------------------
    @cached_property
    def relevant_observations(self) -> np.ndarray:
        """Observations whose alteration can change Pr(reach decoy).

        Only observations emitted by a world state that is reachable from the start without
        passing a decoy or absorbing state matter: once a decoy is hit the value is 1, and an
        absorbing non-decoy state keeps the value 0 whatever the robot believes. The initial
        observation is excluded because it is never altered.
        """
        pomdp = self.pomdp
        stop = self.decoy | pomdp.absorbing
        graph = (sp.diags((~stop).astype(np.float64)) @ pomdp.successor_graph).tocsr()
        graph.eliminate_zeros()
        reached = reachable_from(graph, np.array([pomdp.initial_state]))
        emitting = np.unique(pomdp.observation_of[reached & ~stop])
        return cast(np.ndarray, emitting[emitting != pomdp.initial_observation])

    def cheapest_alteration_cost(self) -> float:
        """The least any alteration costs (``inf``: none is allowed): below it, "alter
        nothing" is the only answer, which needs no search (nor the choice product)."""
        costs = [
            float(np.delete(self.cost.row(int(o)), int(o)).min(initial=np.inf))
            for o in self.relevant_observations.tolist()
        ]
        return min(costs, default=float("inf"))


def _cost_summary(cost: CostModel) -> str:
    """The cost model in a few words: the default, and how many pairs differ."""
    default = "forbidden" if not np.isfinite(cost.default) else f"{cost.default:g}"
    if not cost.pairs:
        return f"{default} per altered sensor"
    return f"{default} by default, {len(cost.pairs):,} pairs priced apart (problem.cost.pairs)"


def format_alteration(changes: Mapping[str, str]) -> str:
    """``{"o1": "o3"}`` as ``o1 → o3`` (``none`` when nothing changes), for tables and logs;
    a name that holds a separator is quoted (``"clk=0,!n" → "clk=0,n"``), so that the pairs
    read one way only."""
    pairs = (f"{quoted_name(o)} → {quoted_name(t)}" for o, t in changes.items())
    return ", ".join(pairs) or "none"


_SEPARATORS = re.compile(r'[\s,=→"\']')


def quoted_name(name: str) -> str:
    """An observation's name as text output shows it: as it is, or in double quotes (JSON's
    escapes) when it is empty or holds a separator (comma, ``=``, space, arrow, quote)."""
    return json.dumps(name, ensure_ascii=False) if not name or _SEPARATORS.search(name) else name


def reachable_from(graph: sp.csr_matrix, sources: np.ndarray) -> np.ndarray:
    """Boolean mask of nodes reachable from any of ``sources`` (BFS with a virtual super-source)."""
    n = graph.shape[0]
    sources = np.asarray(sources, dtype=np.int32)
    mask = np.zeros(n, dtype=bool)
    if sources.size == 0:
        return mask
    augmented = with_super_source(graph, sources)
    order = breadth_first_order(augmented, n, directed=True, return_predecessors=False)
    mask[order[order < n]] = True
    return mask


def with_super_source(graph: sp.spmatrix, sources: np.ndarray) -> sp.csr_matrix:
    """The structure of ``graph`` (``n x n``; every stored entry an edge) with one more node,
    ``n``, that has an edge to each of ``sources``: one breadth-first search from it is a
    search from all of them at once (which nodes they reach, in how few steps, by which edge)."""
    n = graph.shape[0]
    graph = sp.csr_matrix(graph)
    sources = np.asarray(sources)
    indptr = np.concatenate([graph.indptr, [graph.indptr[-1] + sources.size]])
    indices = np.concatenate([graph.indices, sources])
    return sp.csr_matrix(
        (np.ones(indices.size, dtype=np.int8), indices, indptr), shape=(n + 1, n + 1)
    )


def _preview(names: Iterable[str], limit: int = 8) -> str:
    names = list(names)
    shown = ", ".join(names[:limit])
    return shown + (f", … ({len(names)} in all)" if len(names) > limit else "")
