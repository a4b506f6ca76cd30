"""The OSA_DGM problem as integer-indexed arrays.

Outside this package everything has a name (states, actions, observations, memory nodes);
inside, every name is an index into a tuple of names, and the model is a handful of numpy /
scipy.sparse arrays so that product construction and evaluation are vectorised.

An *alteration* is an integer array ``alpha`` of length ``|Ω|`` with ``alpha[o]`` the observation
the robot receives instead of ``o`` (SPEC §1: a function, the initial observation fixed).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field, replace
from functools import cached_property
from typing import Any

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import breadth_first_order

from misdirect.errors import ProblemError
from misdirect.objective import DecoySet, Objective

Alteration = np.ndarray  # int array, alpha[o] = received observation


@dataclass(frozen=True, eq=False)
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


@dataclass(frozen=True, eq=False)
class Controller:
    """Deterministic finite-state controller.

    ``action[n, o] = γ(n, o)`` and ``update[n, o] = δ(n, o)``.
    """

    nodes: tuple[str, ...]
    initial_node: int
    action: np.ndarray  # (|N|, |Ω|) int
    update: np.ndarray  # (|N|, |Ω|) int

    @property
    def n_nodes(self) -> int:
        return len(self.nodes)

    @cached_property
    def behaviour_class(self) -> np.ndarray:
        """Class id per observation; equal ids mean γ and δ agree on every node.

        Two targets of the same class are interchangeable for the attacker (only the cheaper one
        matters), which is what makes enumeration and the compact MILP small.
        """
        signature = np.vstack([self.action, self.update]).T  # one row per observation
        _, inverse = np.unique(signature, axis=0, return_inverse=True)
        return inverse.reshape(-1).astype(np.int64)


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
    def _pairs_by_source(self) -> dict[int, tuple[np.ndarray, np.ndarray]]:
        grouped: dict[int, tuple[list[int], list[float]]] = {}
        for (source, target), cost in self.pairs.items():
            targets, costs = grouped.setdefault(source, ([], []))
            targets.append(target)
            costs.append(cost)
        return {o: (np.array(t, dtype=np.int64), np.array(c)) for o, (t, c) in grouped.items()}

    def row(self, source: int) -> np.ndarray:
        """Costs of altering ``source`` to every observation (``inf`` where forbidden)."""
        costs = np.full(self.n_observations, np.inf if source in self.protected else self.default)
        if source not in self.protected and source in self._pairs_by_source:
            targets, values = self._pairs_by_source[source]
            costs[targets] = values
        costs[source] = 0.0
        return costs

    def matrix(self) -> np.ndarray:
        """Dense ``|Ω| x |Ω|`` cost table (for small models, reports and MILP export)."""
        return np.vstack([self.row(o) for o in range(self.n_observations)])

    def cost(self, alteration: Alteration) -> float:
        changed = np.flatnonzero(alteration != np.arange(self.n_observations))
        return float(sum(self.row(int(o))[alteration[o]] for o in changed))


@dataclass(frozen=True, eq=False)
class Problem:
    """One OSA_DGM instance: maximise Pr(reach decoy) over alterations with cost ≤ budget.

    With ``decoy_sets`` (weighted decoys) the objective is the expected weight of the first
    decoy state entered instead; ``decoy`` is then their union. Solvers read the objective
    through :attr:`objective` only, so both cases are one code path.
    """

    pomdp: Pomdp
    controller: Controller
    cost: CostModel
    decoy: np.ndarray  # (|S|,) bool
    budget: float
    name: str = ""
    source: str | None = None  # file it came from, for error messages
    decoy_sets: tuple[DecoySet, ...] = ()

    @cached_property
    def objective(self) -> Objective:
        if not self.decoy_sets:
            return Objective.single(self.decoy)
        objective = Objective.weighted(self.decoy_sets)
        if not np.array_equal(objective.target, np.asarray(self.decoy, dtype=bool)):
            raise ProblemError("decoy must be the union of decoy_sets", field="decoy")
        return objective

    def with_budget(self, budget: float) -> Problem:
        return replace(self, budget=float(budget))

    @cached_property
    def prepared_attacks(self) -> dict[float, Any]:
        """:class:`misdirect.attack.AttackInstance` s built for this problem, by budget, so
        that a second solver on the same problem does not build them again."""
        return {}

    def unweighted(self) -> Problem:
        """The same problem scoring 1 for every decoy state: Pr(reach any decoy)."""
        return replace(self, decoy_sets=()) if self.decoy_sets else self

    # -- alterations -------------------------------------------------------------------------
    def identity(self) -> Alteration:
        return np.arange(self.pomdp.n_observations, dtype=np.int64)

    def alteration_cost(self, alteration: Alteration) -> float:
        return self.cost.cost(alteration)

    def changed_observations(self, alteration: Alteration) -> dict[str, str]:
        """The alteration as names, listing only observations that change."""
        names = self.pomdp.observations
        return {
            names[o]: names[int(alteration[o])]
            for o in np.flatnonzero(alteration != self.identity())
        }

    def alteration(self, changes: Mapping[str, str], *, source: str = "alteration") -> Alteration:
        """Build and check an alteration from ``{observation: received observation}`` names."""
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
        return alpha

    def check_alteration(self, alteration: Alteration, *, source: str = "alteration") -> None:
        """Reject alterations the problem does not allow (initial observation, forbidden pairs)."""
        names = self.pomdp.observations
        o_init = self.pomdp.initial_observation
        if alteration[o_init] != o_init:
            raise ProblemError(
                f"the initial observation {names[o_init]!r} is never altered (SPEC §1)",
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
        return emitting[emitting != pomdp.initial_observation]


def format_alteration(changes: Mapping[str, str]) -> str:
    """``{"o1": "o3"}`` as ``o1 → o3`` (``none`` when nothing changes), for tables and logs."""
    return ", ".join(f"{o} → {t}" for o, t in changes.items()) or "none"


def reachable_from(graph: sp.csr_matrix, sources: np.ndarray) -> np.ndarray:
    """Boolean mask of nodes reachable from any of ``sources`` (BFS with a virtual super-source)."""
    n = graph.shape[0]
    sources = np.asarray(sources, dtype=np.int32)
    mask = np.zeros(n, dtype=bool)
    if sources.size == 0:
        return mask
    graph = graph.tocsr()
    indptr = np.concatenate([graph.indptr, [graph.indptr[-1] + sources.size]])
    indices = np.concatenate([graph.indices, sources])
    augmented = sp.csr_matrix(
        (np.ones(indices.size, dtype=np.int8), indices, indptr), shape=(n + 1, n + 1)
    )
    order = breadth_first_order(augmented, n, directed=True, return_predecessors=False)
    mask[order[order < n]] = True
    return mask


def _preview(names: Iterable[str], limit: int = 8) -> str:
    names = list(names)
    shown = ", ".join(names[:limit])
    return shown + (f", … ({len(names)} in all)" if len(names) > limit else "")
