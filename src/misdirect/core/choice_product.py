"""The product of POMDP and controller with the attacker's choice left open (a product MDP).

In product state ``(s, n)`` the robot receives ``α(O(s))``, and the attacker's candidates for
``O(s)`` (one per behaviour class, :mod:`misdirect.core.alterations`) decide the robot's action and
next memory node. Different candidates often make the robot do the same thing *at this node*;
those share one **group** ``(s, n, move)``, the move being the controller's distribution over
(action, next node) (one pair for a deterministic controller) and the group's row its mixture.
A group is a choice of this MDP, and the options that select it are recorded so a MILP can
switch its Bellman row on and off.

The MDP over-approximates the attacker: it lets every product state choose independently,
whereas an alteration makes one choice per observation. It is used for what holds under *every*
alteration (which states can never reach the decoy, which can cycle forever), never for values.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import cast

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from misdirect.core.alterations import AlterationSpace, ObservationChoices, rank_in_group
from misdirect.core.checkpoint import checkpoint
from misdirect.core.memory import check_memory
from misdirect.core.model import AlterationArray, Problem, reachable_from


@dataclass(frozen=True)
class Options:
    """Flat list of the attacker's binary options: option ``k`` sends ``observation[k]`` to
    ``target[k]`` at ``cost[k]``. Option 0 of each observation is "leave it unaltered"."""

    observation: np.ndarray
    target: np.ndarray
    cost: np.ndarray

    @classmethod
    def from_space(cls, space: AlterationSpace) -> Options:
        if not space.choices:
            empty = np.zeros(0, dtype=np.int64)
            return cls(empty, empty, np.zeros(0))
        return cls(
            observation=np.concatenate(
                [np.full(c.size, c.observation, dtype=np.int64) for c in space.choices]
            ),
            target=np.concatenate([c.targets for c in space.choices]).astype(np.int64),
            cost=np.concatenate([c.costs for c in space.choices]).astype(np.float64),
        )

    @property
    def size(self) -> int:
        return int(self.observation.size)

    def decode(self, problem: Problem, chosen: np.ndarray) -> AlterationArray:
        """Alteration from a 0/1 (or near 0/1) vector over the options."""
        alpha = problem.identity()
        picked = np.flatnonzero(np.asarray(chosen) > 0.5)
        alpha[self.observation[picked]] = self.target[picked]
        return alpha

    def encode(self, alteration: AlterationArray) -> np.ndarray:
        """0/1 vector over the options selecting ``alteration`` (which must lie in the space)."""
        return cast(np.ndarray, (alteration[self.observation] == self.target).astype(np.float64))


# Bytes per entry of OptionGroups' table (one group index)
OPTION_TABLE_BYTES = 8


@dataclass(frozen=True, eq=False)
class OptionGroups:
    """The group each option selects in each product state, as a (Q, K) array reads.

    A state's choice reads one observation, so only that observation's options select a group
    there; a dense (Q, K) table would be almost all -1 (on a drone under a monitor, 74,606
    states x 24,411 options: 13.6 GiB). This keeps, per state with several groups, the
    options from the least one it has to the greatest, and answers the two ways the engines
    index it: ``[rows, k]`` (one option) and ``[rows, lo:hi]`` (a run of options)."""

    n_states: int
    n_options: int
    single: np.ndarray  # (Q,) bool: the state has one group, which every option selects
    first_group: np.ndarray  # (Q,) each state's first group
    slot: np.ndarray  # (Q,) row of the state in ``table`` (-1 for single-group states)
    low: np.ndarray  # (Q,) the least option with a group there (0 for single-group states)
    table: np.ndarray  # (rows of multi-group states, width) group of option low + j, or -1

    @classmethod
    def of(cls, chain: ChoiceProduct) -> OptionGroups:
        n_states, n_options = chain.n_states, max(chain.options.size, 1)
        single = chain.groups_per_state == 1
        coo = chain.group_options.tocoo()
        state, option = chain.group_state[coo.row], coo.col.astype(np.int64)
        low = np.full(n_states, n_options, dtype=np.int64)
        np.minimum.at(low, state, option)
        high = np.zeros(n_states, dtype=np.int64)
        np.maximum.at(high, state, option)
        low[single] = 0
        many = np.flatnonzero(~single & (high >= low))
        width = int((high[many] - low[many]).max()) + 1 if many.size else 0
        check_memory(
            float(many.size) * width * OPTION_TABLE_BYTES,
            f"the table of the options' groups ({many.size:,} states x {width:,} options)",
        )
        slot = np.full(n_states, -1, dtype=np.int64)
        slot[many] = np.arange(many.size)
        table = np.full((many.size, width), -1, dtype=np.int64)
        keep = slot[state] >= 0
        table[slot[state[keep]], option[keep] - low[state[keep]]] = coo.row[keep]
        return cls(n_states, n_options, single, chain.first_group, slot, low, table)

    @property
    def shape(self) -> tuple[int, int]:
        return (self.n_states, self.n_options)

    def __getitem__(self, key: tuple[np.ndarray | slice, int | slice | np.integer]) -> np.ndarray:
        rows, options = key
        states = np.arange(self.n_states)[rows]
        if isinstance(options, slice):
            columns = np.arange(self.n_options)[options]
            return self._lookup(states, columns)
        return self._lookup(states, np.array([int(options)]))[:, 0]

    def _lookup(self, states: np.ndarray, columns: np.ndarray) -> np.ndarray:
        out = np.full((states.size, columns.size), -1, dtype=np.int64)
        width = self.table.shape[1]
        slot = self.slot[states]
        many = np.flatnonzero(slot >= 0)
        if many.size and width:
            local = columns[None, :] - self.low[states[many]][:, None]
            inside = (local >= 0) & (local < width)
            found = self.table[slot[many][:, None], np.clip(local, 0, width - 1)]
            out[many] = np.where(inside, found, -1)
        one = self.single[states]
        out[one] = self.first_group[states[one]][:, None]
        return out


@dataclass(frozen=True, eq=False)
class ChoiceProduct:
    """Product MDP over reachable ``(s, n)``; groups are its choices."""

    world_state: np.ndarray  # (Q,)
    node: np.ndarray  # (Q,)
    initial: int
    target: np.ndarray  # (Q,) bool, world state is a decoy
    target_value: np.ndarray  # (Q,) float, its weight (1 for the paper's single decoy set)
    options: Options
    group_state: np.ndarray  # (G,) product state owning each group, sorted
    group_options: sp.csr_matrix  # (G, K) 1 where option k makes the state take this group
    transitions: sp.csr_matrix  # (G, Q) P(group -> q')

    @property
    def n_states(self) -> int:
        return int(self.world_state.size)

    @property
    def n_groups(self) -> int:
        return int(self.group_state.size)

    @property
    def groups_per_state(self) -> np.ndarray:
        return np.bincount(self.group_state, minlength=self.n_states)

    @cached_property
    def group_of_option(self) -> OptionGroups:
        """Group each option selects in each state (its only group if it has one; -1 where
        the state's choice belongs to another observation), indexed ``[rows, option]`` or
        ``[rows, lo:hi]`` like a (Q, K) array. Built once per chain: the enumeration, the
        local search and every node of the segment search read it."""
        return OptionGroups.of(self)

    def groups_taking(self, chosen: np.ndarray) -> np.ndarray:
        """(Q,) the group each state takes when the options marked in ``chosen`` (bool, (K,))
        are taken: a state with one group takes it, another the highest-numbered group that
        a chosen option selects there (-1 where none does)."""
        hit = np.flatnonzero(np.asarray(self.group_options @ chosen.astype(np.float64)) > 0.5)
        picked = np.full(self.n_states, -1, dtype=np.int64)
        np.maximum.at(picked, self.group_state[hit], hit)
        single = self.groups_per_state == 1
        picked[single] = self.first_group[single]
        return picked

    @cached_property
    def first_group(self) -> np.ndarray:
        """(Q,) each state's first group."""
        first = np.zeros(self.n_states, dtype=np.int64)
        first[self.group_state[::-1]] = np.arange(self.n_groups)[::-1]
        return first

    def one_step(self, groups: np.ndarray | None = None) -> np.ndarray:
        """Score collected in one step by each group (all, or ``groups``): the weight of the
        decoy states it moves into, times the probability of moving there."""
        rows = self.transitions if groups is None else self.transitions[groups]
        return np.asarray(rows @ self.target_value).ravel()

    def union_graph(self) -> sp.csr_matrix:
        """``q -> q'`` whenever some group of ``q`` can move to ``q'``."""
        return _union_graph(self.group_state, self.transitions, self.n_states)

    def can_reach_target(self) -> np.ndarray:
        """States from which *some* alteration (indeed some MDP scheduler) reaches the decoy."""
        return reachable_from(self.union_graph().T.tocsr(), np.flatnonzero(self.target))

    def selected_groups(self, alteration: AlterationArray) -> np.ndarray:
        """One group per state: the one the alteration selects (the matrix rows of its chain)."""
        chosen = self.options.encode(alteration)
        hits = np.asarray(self.group_options @ chosen).ravel() > 0.5
        single = self.groups_per_state[self.group_state] == 1
        picked = np.flatnonzero(hits | single)
        return picked[np.unique(self.group_state[picked], return_index=True)[1]]


# Bytes the construction holds per (product state, candidate) pair it expands (a dozen index
# arrays, the groups' keys) and per transition of a group's row (gathered world rows, their
# columns, the CSR matrix, the reachable sub-matrix)
BYTES_PER_CANDIDATE = 112
BYTES_PER_GROUP_TRANSITION = 60


def check_choice_product_fits(problem: Problem, candidates: np.ndarray) -> None:
    """Refuse, before allocating it, a choice product that cannot fit in memory:
    ``candidates[o]`` targets per observation (at least itself) make every product state of
    ``o`` expand into that many groups, each with a world row."""
    pomdp, controller = problem.pomdp, problem.controller
    per_state = np.maximum(np.asarray(candidates, dtype=np.int64), 1)[pomdp.observation_of]
    expanded = float(per_state.sum()) * controller.n_nodes
    successors = pomdp.transitions.nnz / max(pomdp.transitions.shape[0], 1)
    if not controller.is_deterministic:
        successors *= float(controller.move_size[controller.move].mean())
    check_memory(
        expanded * (BYTES_PER_CANDIDATE + successors * BYTES_PER_GROUP_TRANSITION),
        f"the attacker's choice product ({pomdp.n_states:,} states x {controller.n_nodes:,} "
        f"nodes, each with one group per candidate target: {expanded:,.0f} groups)",
        field="product",
    )


def build_choice_product(
    problem: Problem, space: AlterationSpace, *, reachable_only: bool = True
) -> ChoiceProduct:
    """Vectorised construction; ``reachable_only`` keeps states reachable from ``(s0, n0)``."""
    pomdp, controller = problem.pomdp, problem.controller
    n_s, n_n, n_o = pomdp.n_states, controller.n_nodes, pomdp.n_observations
    options = Options.from_space(space)

    # candidates per observation: the options of relevant ones, "itself" for the rest
    has_options = np.zeros(n_o, dtype=bool)
    has_options[options.observation] = True
    fixed = np.flatnonzero(~has_options)
    cand_obs = np.concatenate([options.observation, fixed])
    cand_target = np.concatenate([options.target, fixed])
    cand_option = np.concatenate([np.arange(options.size), np.full(fixed.size, -1)])
    order = np.argsort(cand_obs, kind="stable")
    cand_obs, cand_target, cand_option = cand_obs[order], cand_target[order], cand_option[order]
    cand_count = np.bincount(cand_obs, minlength=n_o)
    check_choice_product_fits(problem, cand_count)
    checkpoint()  # each stage below takes seconds on a million-state product
    cand_start = np.concatenate([[0], np.cumsum(cand_count)[:-1]])

    # expand every (s, n) into its candidates
    pair_obs = np.repeat(pomdp.observation_of, n_n)
    counts = cand_count[pair_obs]
    pair = np.repeat(np.arange(n_s * n_n), counts)
    within = rank_in_group(counts)
    cand = cand_start[pair_obs[pair]] + within
    node = pair % n_n
    move = controller.move[node, cand_target[cand]]
    checkpoint()

    # one group per distinct (pair, move); its row is the mixture over the move's entries
    n_m = controller.n_moves
    keys = pair.astype(np.int64) * n_m + move  # lexicographic order
    unique_keys, group_of = np.unique(keys, return_inverse=True)
    group_of = group_of.reshape(-1)
    g_pair, g_move = np.divmod(unique_keys, n_m)
    checkpoint()
    n_groups = g_pair.size
    with_option = cand_option[cand] >= 0
    group_options = sp.csr_matrix(
        (np.ones(int(with_option.sum())), (group_of[with_option], cand_option[cand][with_option])),
        shape=(n_groups, options.size),
    )
    checkpoint()
    owner, g_action, g_next, g_probability = controller.move_entries(g_move)
    rows = pomdp.transitions[g_action * n_s + g_pair[owner] // n_n]
    entry = np.repeat(np.arange(owner.size), np.diff(rows.indptr))
    columns = rows.indices.astype(np.int64) * n_n + g_next[entry]
    indptr = np.concatenate([[0], np.cumsum(np.bincount(owner[entry], minlength=n_groups))])
    transitions = sp.csr_matrix(
        (rows.data * g_probability[entry], columns, indptr), shape=(n_groups, n_s * n_n)
    )
    if not controller.is_deterministic:
        transitions.sum_duplicates()  # two entries of a move can lead to the same (s', n')

    checkpoint()
    start = pomdp.initial_state * n_n + controller.initial_node
    if reachable_only:
        graph = _union_graph(g_pair, transitions, n_s * n_n)
        checkpoint()
        keep = np.flatnonzero(reachable_from(graph, np.array([start])))
    else:
        keep = np.arange(n_s * n_n)
    renumber = np.full(n_s * n_n, -1)
    renumber[keep] = np.arange(keep.size)
    kept_groups = np.flatnonzero(renumber[g_pair] >= 0)
    checkpoint()
    return ChoiceProduct(
        world_state=keep // n_n,
        node=keep % n_n,
        initial=int(renumber[start]),
        target=problem.objective.target[keep // n_n],
        target_value=problem.objective.value[keep // n_n],
        options=options,
        group_state=renumber[g_pair[kept_groups]],
        group_options=group_options[kept_groups],
        transitions=transitions[kept_groups][:, keep].tocsr(),
    )


def _union_graph(
    group_state: np.ndarray, transitions: sp.csr_matrix, n_states: int
) -> sp.csr_matrix:
    """State graph of an MDP given by its groups: an edge wherever some group can move."""
    owner = sp.csr_matrix(
        (np.ones(group_state.size), (group_state, np.arange(group_state.size))),
        shape=(n_states, group_state.size),
    )
    graph = (owner @ (transitions != 0).astype(np.float64)).tocsr()
    graph.data[:] = 1.0
    return graph


def states_that_can_stay(
    group_state: np.ndarray, transitions: sp.csr_matrix, candidates: np.ndarray
) -> np.ndarray:
    """Largest set Z ⊆ ``candidates`` in which every state has a group moving only inside Z.

    Every end component lies in Z, and Z is empty exactly when there is none (a scheduler that
    stays inside Z forever ends in a bottom component). Computed backwards from the states that
    must leave, each edge looked at once, so it costs one pass even where the peeling of
    :func:`end_component_states` would take as many rounds as the longest path.
    """
    n_states = candidates.size
    structure = (transitions != 0).tocsr()
    into = structure.T.tocsr()  # state -> groups that can move into it
    group_stays = candidates[group_state] & (
        np.asarray(structure @ (~candidates).astype(np.int32)).ravel() == 0
    )
    staying_groups = np.bincount(group_state[group_stays], minlength=n_states)
    stay = candidates & (staying_groups > 0)
    frontier = np.flatnonzero(candidates & ~stay)
    while frontier.size:
        checkpoint()
        groups = _distinct(_row_entries(into, frontier))
        groups = groups[group_stays[groups]]
        group_stays[groups] = False
        staying_groups -= np.bincount(group_state[groups], minlength=n_states)
        touched = _distinct(group_state[groups])
        frontier = touched[stay[touched] & (staying_groups[touched] == 0)]
        stay[frontier] = False
    return stay


def _distinct(values: np.ndarray) -> np.ndarray:
    """Sorted distinct values (``np.unique`` without its per-call overhead on small arrays)."""
    values = np.sort(values)
    return values[np.concatenate(([True], values[1:] != values[:-1]))] if values.size else values


def _row_entries(matrix: sp.csr_matrix, rows: np.ndarray) -> np.ndarray:
    """Column indices of the given rows' entries, concatenated (no new matrix is built)."""
    return cast(np.ndarray, matrix.indices[_entry_positions(matrix.indptr, rows)])


def _entry_positions(indptr: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """Where the given rows' entries are stored in a CSR matrix with ``indptr``, row after
    row."""
    starts = indptr[rows]
    lengths = indptr[rows + 1] - starts
    return cast(np.ndarray, np.repeat(starts, lengths) + rank_in_group(lengths))


def end_component_states(
    group_state: np.ndarray, transitions: sp.csr_matrix, candidates: np.ndarray
) -> np.ndarray:
    """States of the MDP (restricted to ``candidates``) that lie in some end component.

    An end component is a set of states with a choice each that keeps the run inside and lets
    it visit all of them forever. These are exactly the states where a chain can cycle without
    ever leaving, so the only ones where a maximised Bellman inequality can overshoot (SPEC §2).
    Classic refinement: drop choices that leave the set or their strongly connected component,
    drop states left without choices, repeat until stable.
    """
    n_states = candidates.size
    structure = (transitions != 0).astype(np.int32).tocsr()
    entry_group = np.repeat(np.arange(group_state.size), np.diff(structure.indptr))
    states = states_that_can_stay(group_state, structure, candidates)
    if not states.any():  # the common case, found in one pass over the edges
        return states
    alive = states[group_state].copy()
    while True:
        checkpoint()
        before = int(alive.sum())
        alive &= states[group_state]
        alive &= np.asarray(structure @ (~states).astype(np.int32)).ravel() == 0
        kept = alive[entry_group]
        graph = sp.csr_matrix(
            (
                np.ones(int(kept.sum()), dtype=np.int8),
                (group_state[entry_group[kept]], structure.indices[kept]),
            ),
            shape=(n_states, n_states),
        )
        _, label = connected_components(graph, directed=True, connection="strong")
        crossing = label[structure.indices] != label[group_state[entry_group]]
        alive[entry_group[crossing]] = False
        remaining = np.zeros(n_states, dtype=bool)
        remaining[group_state[alive]] = True
        remaining &= states
        if int(alive.sum()) == before and np.array_equal(remaining, states):
            return states
        states = remaining


def distinct_options(
    chain: ChoiceProduct, space: AlterationSpace, live: np.ndarray
) -> AlterationSpace:
    """``space`` without the options that change nothing the value can see.

    Two behaviour classes of the controller (one option each) can still give the robot the same
    transitions: on a drone's border, "up" and "stay" both stay. An option whose rows equal the
    unaltered rows on every live state of its observation gives every alteration that takes it
    the value of the same alteration without it, at a higher cost; one whose rows equal a
    cheaper option's (or an earlier one of the same cost) gives the value of the alteration
    with that option instead. Rows elsewhere never matter: a state that is not live has its
    value fixed under every alteration. Dropping them is exact (the cheapest alteration of the
    best value is kept) and shrinks every enumeration (the alterations of budget 3 of a 7x7
    drone: 5.9·10^7 → 2.5·10^7). Returns ``space`` itself when nothing is dropped.
    """
    if not space.choices:
        return space
    canon = _row_classes(chain.transitions, chain.group_state)
    coo = chain.group_options.tocoo()
    state = chain.group_state[coo.row]
    on_live = live[state]
    option, state, klass = coo.col[on_live], state[on_live], canon[coo.row[on_live]]
    order = np.lexsort((state, option))
    option, klass = option[order], klass[order]
    starts = np.searchsorted(option, np.arange(chain.options.size + 1))
    kept: list[ObservationChoices] = []
    first = 0
    changed = False
    for choice in space.choices:
        block = slice(starts[first], starts[first + choice.size])
        rows = klass[block].reshape(choice.size, -1)  # per option, its row class per live state
        first += choice.size
        seen = {rows[0].tobytes()}
        keep = [0]
        # the cheapest of each distinct behaviour first (ties: the earlier option)
        for k in np.lexsort((np.arange(1, choice.size), choice.costs[1:])).tolist():
            signature = rows[k + 1].tobytes()
            if signature not in seen:
                seen.add(signature)
                keep.append(k + 1)
        keep.sort()
        changed |= len(keep) < choice.size
        if len(keep) > 1:
            kept.append(
                ObservationChoices(choice.observation, choice.targets[keep], choice.costs[keep])
            )
    if not changed:
        return space
    return AlterationSpace(tuple(kept), space.scale)


def _row_classes(rows: sp.csr_matrix, owner: np.ndarray) -> np.ndarray:
    """Per row, the index of the first row of the same ``owner`` with exactly the same entries
    (itself if none): candidates share two random projections, and are then compared entry by
    entry, so the classes are exact."""
    rows = rows.tocsr()
    if not rows.has_sorted_indices:
        rows = rows.sorted_indices()  # a copy: the chain's own matrix is left as it is
    projections = np.asarray(rows @ np.random.default_rng(0).random((rows.shape[1], 2)))
    nnz = np.diff(rows.indptr)
    keys = np.column_stack([owner, nnz, projections.view(np.int64)])
    _, first, inverse = np.unique(keys, axis=0, return_index=True, return_inverse=True)
    candidate = first[inverse.reshape(-1)]
    # compare each row with its candidate entry by entry
    differs = np.zeros(rows.shape[0], dtype=bool)
    twin = np.flatnonzero(candidate != np.arange(rows.shape[0]))
    if twin.size:
        # a row and its candidate have as many entries: their positions pair up one to one
        mine = _entry_positions(rows.indptr, twin)
        theirs = _entry_positions(rows.indptr, candidate[twin])
        bad = (rows.indices[mine] != rows.indices[theirs]) | (rows.data[mine] != rows.data[theirs])
        differs[np.repeat(twin, nnz[twin])[bad]] = True
    return np.where(differs, np.arange(rows.shape[0]), candidate)
