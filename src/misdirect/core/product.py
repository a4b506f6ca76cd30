"""The product Markov chain of a POMDP and its controller under an alteration (paper, Def. 4).

Product state ``(s, n)``: world state ``s``, memory node ``n``. The robot receives
``o = α(O(s))``, plays ``γ(n, o)``, moves its memory to ``δ(n, o)`` and the world draws
``s' ~ P(s, γ(n, o), ·)``; so ``(s, n) -> (s', δ(n, o))`` with probability ``P(s, γ(n, o), s')``.
A randomized controller draws (action, next node) from its move ``μ(n, o)``, and the row is
the mixture ``Σ_{(a, n')} μ(n, o)(a, n') · P(s, a, s')`` into ``(s', n')``.

The construction is vectorised: the full ``|S|·|N|`` chain is one fancy-indexing of the stacked
transition matrix, then restricted to the states reachable from ``(s0, n0)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from misdirect.core.memory import check_memory
from misdirect.core.model import AlterationArray, Problem, reachable_from


@dataclass(frozen=True, eq=False)
class ProductChain:
    """A Markov chain over reachable ``(world state, memory node)`` pairs."""

    world_state: np.ndarray  # (Q,) world state of each product state
    node: np.ndarray  # (Q,) memory node of each product state
    matrix: sp.csr_matrix  # (Q, Q) row-stochastic
    initial: int  # index of (s0, n0)

    @property
    def n_states(self) -> int:
        return int(self.world_state.size)

    @property
    def n_transitions(self) -> int:
        return int(self.matrix.nnz)


# Bytes the construction holds at its peak, per product state (the index arrays: world, node,
# received, action, next node, indptr) and per transition (gathered rows, their columns and
# row ids, the CSR copy, the reachable sub-matrix); measured to within a factor of about 1.5.
BYTES_PER_PRODUCT_STATE = 56
BYTES_PER_PRODUCT_TRANSITION = 48


def check_product_fits(problem: Problem) -> None:
    """Refuse, before allocating anything, a product chain that cannot fit in memory.

    A cheap upper bound: ``|S|·|N|`` product states, each with the POMDP's mean number of
    successors. Only a chain whose construction alone needs more than the available memory
    is refused (evaluating it needs more still), with its size and the estimate."""
    pomdp, n_nodes = problem.pomdp, problem.controller.n_nodes
    states = pomdp.n_states * n_nodes
    rows = max(pomdp.transitions.shape[0], 1)
    transitions = states * pomdp.transitions.nnz / rows
    if not problem.controller.is_deterministic:  # a row mixes the world rows of a move
        transitions *= float(problem.controller.move_size[problem.controller.move].mean())
    needed = states * BYTES_PER_PRODUCT_STATE + transitions * BYTES_PER_PRODUCT_TRANSITION
    check_memory(
        needed,
        f"the product chain (up to {pomdp.n_states:,} states x {n_nodes:,} controller nodes "
        f"= {states:,} states, about {transitions:,.0f} transitions)",
        field="product",
    )


def full_product_matrix(problem: Problem, alteration: AlterationArray) -> sp.csr_matrix:
    """Transition matrix over all ``|S|·|N|`` pairs, product index ``s * |N| + n``."""
    pomdp, controller = problem.pomdp, problem.controller
    n_states, n_nodes = pomdp.n_states, controller.n_nodes
    check_product_fits(problem)
    received = alteration[pomdp.observation_of]  # (S,) observation the robot gets in s
    world = np.repeat(np.arange(n_states), n_nodes)
    node = np.tile(np.arange(n_nodes), n_states)
    size = n_states * n_nodes
    if controller.is_deterministic:  # one world row per product state, kept as it is
        move = controller.move[node, received[world]]
        first = controller.move_ptr[move]
        action, next_node = controller.move_action[first], controller.move_next[first]
        rows = pomdp.transitions[action * n_states + world]
        entry_row = np.repeat(np.arange(world.size), np.diff(rows.indptr))
        columns = rows.indices.astype(np.int64) * n_nodes + next_node[entry_row]
        return sp.csr_matrix((rows.data, columns, rows.indptr), shape=(size, size))
    # randomized: each product state's row is the mixture over its move's entries
    owner, action, next_node, probability = controller.entries(node, received[world])
    rows = pomdp.transitions[action * n_states + world[owner]]
    lengths = np.diff(rows.indptr)
    entry = np.repeat(np.arange(owner.size), lengths)
    columns = rows.indices.astype(np.int64) * n_nodes + next_node[entry]
    indptr = np.concatenate([[0], np.cumsum(np.bincount(owner[entry], minlength=size))])
    matrix = sp.csr_matrix((rows.data * probability[entry], columns, indptr), shape=(size, size))
    matrix.sum_duplicates()  # two entries of a move can lead to the same (s', n')
    return matrix


def build_product(problem: Problem, alteration: AlterationArray) -> ProductChain:
    """The product chain restricted to states reachable from ``(s0, n0)``."""
    n_nodes = problem.controller.n_nodes
    full = full_product_matrix(problem, alteration)
    start = problem.pomdp.initial_state * n_nodes + problem.controller.initial_node
    keep = np.flatnonzero(reachable_from(full, np.array([start])))
    matrix = full[keep][:, keep].tocsr()
    return ProductChain(
        world_state=keep // n_nodes,
        node=keep % n_nodes,
        matrix=matrix,
        initial=int(np.searchsorted(keep, start)),
    )
