"""The shared machinery the methods stand on; each module is one engine, named for what it is.

* ``policy_iteration``: policy iteration, written once for the two kinds of MDP solved here
  (maximal reachability with end components; transient total reward with LU and Woodbury).
* ``per_state``: the per-state MDP relaxation of the choice product (a node bound, and the
  proven bound every method falls back on).
* ``segment_relaxation``: the segment relaxation, a budget-aware bound (the segment MDP and
  the Lagrangian of the budget over it).
* ``incumbent``: a search's best assignment, its pruning and its proven bound.
* ``segment_search``: best-first branch-and-bound on the segment relaxation, two workers on one
  heap, with small subtrees enumerated.
* ``lowrank`` and ``lowrank_updates``: the enumeration of every alteration within a budget by
  low-rank updates of one base solve per outer choice.
* ``closed_classes``: a base chain's closed classes, and the enumeration's trap handling
  (which alterations may close or open a class, so that no update divides by a singular
  system).
* ``entry_gain``: the first-entry gain bound, and the enumeration's floor filter built on it.
* ``exact_revaluation``: the enumeration's exact-valuation guard (alterations its low-rank
  values cannot vouch for, valued on their own chains).
* ``end_components`` and ``transient``: the proof on the MDP with its end components
  collapsed, and policy iteration without end components (LU, Woodbury, potentials).
* ``covering``: the covering bound of a node (unions of sensor groups its budget can touch),
  and the rule for when a search covers one.
* ``kept_basis``: the per-state relaxation of many free sets at one node, on the node's base
  chain reduced to its undecided sensors' states.

Engines import no method; methods import engines, never each other (tests/test_layers.py).
"""
