"""The covering bound: a bound on a node's completions that sees the budget where the chain has
end components (issue 50).

On such chains the per-state relaxation with every undecided sensor free reads about 1.0 from
budget 2 on: a scheduler that adapts at every state may touch every sensor. But an attacker
who adapts at every state while touching only a few sensors is barely stronger than the static
one (on a 40x40 turn-back grid, {s2, s13} free: 0.7200 against the budget-2 optimum 0.6822).
So cover the affordable sets instead of freeing everything:

Split the undecided sensors into groups. A completion that alters the set ``S`` (each of its
options affordable, all of them together within the budget left, ``r``) touches the groups
``T(S)``, and the cheapest option of each touched group adds up to at most ``r``. So ``S`` lies
inside the union of some *maximal* set of groups whose cheapest options fit ``r``, and the
completion is one scheduler of the per-state relaxation with that union free (every other
undecided sensor unaltered, the decided ones as decided). The largest of those relaxations'
proven bounds bounds every completion. Each relaxation only grows with its free set, so any
partition is sound; stratified groups (each with strong and weak sensors) keep the unions' bounds
low.

This module computes the bound for one node; when a search should use it (small budget left,
many undecided sensors) and how it refines the unions that stay above the incumbent are the
search's.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from misdirect.solvers.deadline import Deadline
from misdirect.solvers.engines.per_state import PerStateRelaxation

MAX_UNIONS = 5_000  # a cover of more unions than this is not tried (each is a relaxation solve)


@dataclass(frozen=True)
class CoverBound:
    """A node's covering bound: the largest of its unions' proven bounds (``bound``), and each
    union (the groups it frees) with its own, largest first."""

    bound: float
    unions: list[tuple[tuple[int, ...], float]]


def stratified_groups(
    choices: Sequence[int], n_groups: int, strength: np.ndarray | None = None
) -> list[list[int]]:
    """``choices`` dealt into ``n_groups`` groups, strongest first, round robin: each group
    holds strong and weak sensors alike (``strength`` per choice index; default: as given)."""
    order = list(choices)
    if strength is not None:
        order.sort(key=lambda i: -float(strength[i]))
    n_groups = max(1, min(n_groups, len(order)))
    return [order[j::n_groups] for j in range(n_groups)]


def maximal_group_sets(
    cheapest: Sequence[float], fits: Callable[[float], bool]
) -> list[tuple[int, ...]]:
    """Every maximal set of groups whose ``cheapest`` costs add up to a total that ``fits``
    (groups in index order), or all of them when they fit together. A set is maximal when no
    other group can join it."""
    g = len(cheapest)
    found: list[tuple[int, ...]] = []

    def grow(start: int, chosen: tuple[int, ...], spent: float) -> None:
        extended = False
        for j in range(start, g):
            if fits(spent + cheapest[j]):
                extended = True
                grow(j + 1, (*chosen, j), spent + cheapest[j])
                if len(found) > MAX_UNIONS:
                    return
        if not extended and all(j in chosen or not fits(spent + cheapest[j]) for j in range(g)):
            found.append(chosen)

    grow(0, (), 0.0)
    return found


def covering_bound(
    relax: PerStateRelaxation,
    groups: Sequence[Sequence[int]],
    cap: float,
    fixed: Mapping[int, int] | None = None,
    deadline: Deadline | None = None,
) -> CoverBound | None:
    """The covering bound of the node that fixes choice ``i`` to option ``fixed[i]`` (choice
    indices of the alteration space) with the budget left as ``cap`` (a
    :meth:`~misdirect.core.tolerance.CostScale.cap`, less what the fixed options spent), the
    undecided choices split into ``groups`` (every undecided choice with an affordable option
    in one of them); None where the cover would take more than
    :data:`MAX_UNIONS` unions. Raises
    :class:`~misdirect.solvers.deadline.DeadlineExpiredError` once ``deadline`` has passed."""
    fixed = dict(fixed or {})
    first, cost = relax.first_option, relax.option_cost
    scale = relax.space.scale

    def affordable(i: int) -> np.ndarray:
        options = cost[first[i] + 1 : first[i + 1]]
        return np.flatnonzero(options <= cap) + 1

    grouped = {i for group in groups for i in group}
    loose = [
        i
        for i in range(len(relax.space.choices))
        if i not in fixed and i not in grouped and affordable(i).size
    ]
    if loose:  # left out, it would count as unaltered: the bound would not hold
        raise ValueError(f"choices {loose[:5]} are undecided and in no group")
    # a group's cheapest affordable option; a group with none never joins a completion
    cheapest = []
    for group in groups:
        costs = [float(cost[first[i] + affordable(i)].min()) for i in group if affordable(i).size]
        cheapest.append(min(costs, default=np.inf))
    sets = maximal_group_sets(cheapest, lambda total: bool(scale.fits(total, cap)))
    if len(sets) > MAX_UNIONS:
        return None
    unions = []
    for chosen in sets:
        free = [i for j in chosen for i in groups[j]]
        unions.append((chosen, _relaxation(relax, free, cap, fixed, deadline)))
    unions.sort(key=lambda item: -item[1])
    return CoverBound(max((b for _, b in unions), default=-np.inf), unions)


def _relaxation(
    relax: PerStateRelaxation,
    free: Sequence[int],
    cap: float,
    fixed: Mapping[int, int],
    deadline: Deadline | None,
) -> float:
    """The proven bound of the per-state relaxation with the ``free`` choices free (their
    options within ``cap``), ``fixed`` as fixed and every other choice unaltered."""
    first = relax.first_option
    allowed = np.zeros(relax.option_cost.size, dtype=bool)
    allowed[first[:-1]] = True  # every choice may stay unaltered...
    for i in free:
        span = slice(first[i], first[i + 1])
        allowed[span] = relax.option_cost[span] <= cap
        allowed[first[i]] = True
    for i, k in fixed.items():  # ...but a decided one takes its option
        allowed[first[i] : first[i + 1]] = False
        allowed[first[i] + k] = True
    groups = relax.allowed_groups(allowed)
    start = relax.best_groups(np.where(groups, 0.0, -np.inf))[0]
    bound, _, _ = relax.optimise(groups, start, deadline)
    return float(bound)
