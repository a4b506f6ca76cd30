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

This module computes the bound for one node, and says when a search should (:class:`CoverRule`,
the one place that decides it): on chains with end components, where the per-state bound did
not prune, once per budget level along a path (a node whose budget left is what it was at the
last cover above it frees one sensor fewer: its cover would hardly change), with the finest
groups whose unions the time left pays for. A union that stays above the incumbent is refined by
the search's branching: each child fixes one more sensor, and a child that alters it has less
budget left, so fewer, smaller unions.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from misdirect.core.blas import one_blas_thread
from misdirect.solvers.deadline import Deadline
from misdirect.solvers.engines.forked import Claims, forked_map
from misdirect.solvers.engines.kept_basis import KeptBasis
from misdirect.solvers.engines.per_state import PerStateRelaxation

MAX_UNIONS = 5_000  # a cover of more unions than this is not tried (each is a relaxation solve)
KEPT_FROM = 4  # unions from which a cover solves them on a kept basis (engines/kept_basis.py)
MAX_GROUPS = 24  # groups a cover splits the undecided sensors into, at most
COVER_SHARE = 0.25  # a node's cover may take this share of the search's time left
UNLIMITED_UNIONS = 200  # ... and without a time limit, this many unions
REFINE_DEPTH = 1  # times a union above a cover's threshold is split (covering_bound)
# A union whose proof fails (its bound the objective's largest value: a chain that lingers past
# what doubles resolve) is valued exactly, alteration by alteration, where it has at most this
# many within the budget: each is one whole-chain solve (26 ms on the 6,400 states of the
# 64-sensor turn-back grid), so 1,000 cost about what 100-150 unions' relaxations do. Three
# sensors with four options each at budget 3 have 125; six have 1,545 (split them first).
MAX_ENUMERATED = 1_000
FORK_FROM = 16  # unions a forked worker takes at least (each costs a fork's few milliseconds)


@dataclass(frozen=True)
class CoverBound:
    """A node's covering bound: the largest of its unions' proven bounds (``bound``), and each
    union (the groups it frees) with its own, largest first."""

    bound: float
    unions: list[tuple[tuple[int, ...], float]]
    refined: int = 0  # unions above the cover's threshold, split into halves (their bound: the
    # smaller of their own and their halves' cover)
    enumerated: int = 0  # unions (or sub-unions) whose proof failed, valued alteration by
    # alteration (their bound: the best of those exact values)
    solved: int = 0  # relaxations solved: the unions and the sub-unions of their refinements
    given_up: bool = False  # stopped at a union that reached ``give_up_at``: no bound (the
    # counts say what it cost, so a search can size its next cover)


@dataclass(frozen=True)
class CoverRule:
    """When a search covers a node, and with which groups: see the module docstring."""

    share: float = COVER_SHARE
    unlimited_unions: int = UNLIMITED_UNIONS
    workers: int = 1  # processes a cover's unions are shared among (forked: see forked.py)

    @staticmethod
    def applies(cycling: bool) -> bool:
        """Covers pay on chains with end components, where the per-state bound does not see
        the budget; elsewhere that bound is tight enough, and a cover costs many of its
        solves."""
        return cycling

    @staticmethod
    def due(remaining: float, covered_at: float) -> bool:
        """Whether a node with ``remaining`` budget left is covered, ``covered_at`` being the
        budget left at the last cover on its path (inf: none)."""
        return remaining < covered_at

    def deadline(self, deadline: Deadline | None) -> Deadline | None:
        """One cover's own time: its share of the search's time left (a cover refines the
        unions above the incumbent, so its unions do not bound its time); None without a
        limit."""
        if deadline is None:
            return None
        left = deadline.remaining()
        return deadline.within(None if left is None else self.share * left)

    def unions_allowed(self, seconds_left: float | None, seconds_per_union: float) -> int:
        """How many unions a cover may solve: its share of the time left, at about
        ``seconds_per_union`` each (a node bound's time)."""
        if seconds_left is None:
            return self.unlimited_unions
        per_union = max(seconds_per_union, 1e-3)
        return min(MAX_UNIONS, int(self.share * max(seconds_left, 0.0) / per_union))

    @staticmethod
    def groups(
        free: Sequence[int],
        strength: np.ndarray,
        cheapest: Mapping[int, float],
        fits: Callable[[float], bool],
        allowed: int,
    ) -> list[list[int]] | None:
        """The finest stratified groups of the ``free`` choices (``cheapest``: each one's
        cheapest affordable option) whose cover takes at most ``allowed`` unions and frees
        less than all of them in each; None where no grouping does."""
        for n_groups in range(min(len(free), MAX_GROUPS), 1, -1):
            groups = stratified_groups(free, n_groups, strength)
            costs = [min(cheapest[i] for i in group) for group in groups]
            sets = maximal_group_sets(costs, fits)
            if len(sets) <= allowed and all(len(chosen) < n_groups for chosen in sets):
                return groups
        return None


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
    give_up_at: float = np.inf,
    refine_above: float = np.inf,
    refine_depth: int = REFINE_DEPTH,
    workers: int = 1,
) -> CoverBound | None:
    """The covering bound of the node that fixes choice ``i`` to option ``fixed[i]`` (choice
    indices of the alteration space) with the budget left as ``cap`` (a
    :meth:`~misdirect.core.tolerance.CostScale.cap`, less what the fixed options spent), the
    undecided choices split into ``groups`` (every undecided choice with an affordable option
    in one of them); None where the cover would take more than :data:`MAX_UNIONS` unions.
    It stops once a union's bound reaches ``give_up_at`` (a bound the caller has already: the
    cover could not beat it; the unions go strongest groups first, so such a union tends to
    come early), marked ``given_up``: no bound, only what it cost. A union whose bound lies
    above ``refine_above`` is refined (:func:`_refined`), at most ``refine_depth`` times over.
    With ``workers`` > 1
    the unions are shared among forked copies of this process
    (:func:`~misdirect.solvers.engines.forked.forked_map`; the same bound). Raises
    :class:`~misdirect.solvers.deadline.DeadlineExpiredError` once ``deadline`` has passed."""
    fixed = dict(fixed or {})
    first, cost = relax.first_option, relax.option_cost
    scale = relax.space.scale

    def affordable(i: int) -> np.ndarray:
        return relax.affordable(i, cap)

    grouped = {i for group in groups for i in group}
    loose = [
        i
        for i in range(len(relax.space.choices))
        if i not in fixed and i not in grouped and affordable(i).size
    ]
    if loose:  # left out, it would count as unaltered: the bound would not hold
        raise ValueError(f"choices {loose[:5]} are undecided and in no group")

    def cheapest_of(group: Sequence[int]) -> float:
        """The group's cheapest affordable option (inf: it never joins a completion)."""
        costs = [float(cost[first[i] + affordable(i)].min()) for i in group if affordable(i).size]
        return min(costs, default=np.inf)

    def fits(total: float) -> bool:
        return bool(scale.fits(total, cap))

    cheapest = [cheapest_of(group) for group in groups]
    sets = maximal_group_sets(cheapest, fits)
    if len(sets) > MAX_UNIONS:
        return None
    with one_blas_thread():
        basis = None
        if len(sets) >= KEPT_FROM:  # its cost (a node's solves) is repaid over a few unions
            basis = KeptBasis(relax, fixed, sorted(grouped))
            basis = basis if basis.usable else None

        solved = 0

        def solve(free: list[int]) -> float:
            nonlocal solved
            solved += 1
            if basis is not None:
                return basis.bound(free, cap, deadline)
            return _relaxation(relax, free, cap, fixed, deadline)

        top = relax.mdp.top
        enumerated = 0

        def finish(free: list[int], bound: float) -> float:
            """A union whose proof failed, valued exactly where it is small (the best of its
            alterations within the budget: every completion inside it is one of them)."""
            nonlocal enumerated
            if bound < top:
                return bound
            best = _enumerated(relax, free, cap, fixed, fits, deadline)
            if best is None:
                return bound
            enumerated += 1
            return min(bound, best)

        workers = max(1, min(workers, len(sets) // FORK_FROM))
        claims = Claims(len(sets), workers)

        def piece(_: int) -> _Piece:
            """The unions this worker claims, until one reaches ``give_up_at`` (then no worker
            claims another)."""
            before = _counts(relax, basis)
            solved_before, enumerated_before = solved, enumerated
            unions = []
            refined = 0
            for index in claims:
                chosen = sets[index]
                members = [groups[j] for j in chosen]
                free = [i for group in members for i in group]
                bound = finish(free, solve(free))
                if bound > refine_above:
                    refined += 1
                    bound = _refined(
                        members, bound, solve, finish, cheapest_of, fits, refine_above, refine_depth
                    )
                unions.append((chosen, bound))
                if bound >= give_up_at:
                    claims.stop()
                    break
            spent = _counts(relax, basis) - before
            return _Piece(
                unions,
                refined,
                enumerated - enumerated_before,
                solved - solved_before,
                spent,
                os.getpid(),
            )

        pieces = forked_map(piece, workers, deadline)
    for found in pieces:
        if found.pid != os.getpid():  # a child's counts, spent in its copies of the objects
            _add_counts(relax, basis, found.spent)
    unions = sorted(
        (u for found in pieces for u in found.unions), key=lambda item: (-item[1], item[0])
    )
    best = max((b for _, b in unions), default=-np.inf)
    return CoverBound(
        best,
        unions,
        sum(found.refined for found in pieces),
        sum(found.enumerated for found in pieces),
        sum(found.solved for found in pieces),
        given_up=best >= give_up_at,
    )


class _Piece(NamedTuple):
    """What one worker's share of a cover found: its unions with their bounds, and counts."""

    unions: list[tuple[tuple[int, ...], float]]
    refined: int
    enumerated: int
    solved: int
    spent: np.ndarray  # :func:`_counts` it added
    pid: int  # the process it ran in


def _counts(relax: PerStateRelaxation, basis: KeptBasis | None) -> np.ndarray:
    """The counters a cover adds to: the relaxation's evaluations and proofs, the basis's."""
    mdp = relax.mdp
    kept = (0, 0) if basis is None else (basis.reduced, basis.fallbacks)
    return np.array(
        [
            mdp.evaluations,
            mdp.proofs,
            mdp.trivial_proofs,
            mdp.collapsed_proofs,
            mdp.collapsed_proven,
            *kept,
        ],
        dtype=np.int64,
    )


def _add_counts(relax: PerStateRelaxation, basis: KeptBasis | None, spent: np.ndarray) -> None:
    """Add a forked worker's counts (:func:`_counts`) to this process's objects."""
    mdp = relax.mdp
    mdp.evaluations += int(spent[0])
    mdp.proofs += int(spent[1])
    mdp.trivial_proofs += int(spent[2])
    mdp.collapsed_proofs += int(spent[3])
    mdp.collapsed_proven += int(spent[4])
    if basis is not None:
        basis.reduced += int(spent[5])
        basis.fallbacks += int(spent[6])


def _refined(
    members: Sequence[Sequence[int]],
    bound: float,
    solve: Callable[[list[int]], float],
    finish: Callable[[list[int], float], float],
    cheapest_of: Callable[[Sequence[int]], float],
    fits: Callable[[float], bool],
    refine_above: float,
    depth: int,
) -> float:
    """A union's bound refined: its groups (``members``) each split in two (alternately, so
    each half stays stratified), and the union covered by the maximal sets of halves whose
    cheapest options fit, as the node is by its groups. A completion inside the union touches
    halves whose cheapest options its own cost pays for, so it lies inside one of those
    sub-unions: the largest of their bounds bounds it (and the union's own bound still does,
    so the smaller of the two). Sub-unions above ``refine_above`` are refined again, ``depth``
    levels in all; a (sub-)union whose proof fails is first ``finish``ed (valued exactly,
    alteration by alteration, where it is small: nothing bounds it tighter). A union whose
    relaxation policy iteration values below 1 but whose proof fails (a chain that lingers
    past what doubles resolve) mostly proves on its halves."""
    if depth <= 0:
        return bound
    halves = [half for group in members for half in (group[0::2], group[1::2]) if half]
    if len(halves) <= len(members):
        return bound  # single sensors: nothing left to split
    sets = maximal_group_sets([cheapest_of(half) for half in halves], fits)
    if len(sets) > MAX_UNIONS:
        return bound
    largest = -np.inf
    for chosen in sets:
        parts = [halves[j] for j in chosen]
        free = [i for half in parts for i in half]
        found = finish(free, solve(free))
        if found > refine_above:
            found = _refined(
                parts, found, solve, finish, cheapest_of, fits, refine_above, depth - 1
            )
        largest = max(largest, found)
        if largest >= bound:
            return bound  # the split does not help
    return min(bound, largest)


def _relaxation(
    relax: PerStateRelaxation,
    free: Sequence[int],
    cap: float,
    fixed: Mapping[int, int],
    deadline: Deadline | None,
) -> float:
    """The proven bound of the per-state relaxation with the ``free`` choices free (their
    options within ``cap``), ``fixed`` as fixed and every other choice unaltered."""
    groups = relax.allowed_groups(relax.free_options(free, cap, fixed))
    start = relax.best_groups(np.where(groups, 0.0, -np.inf))[0]
    bound, _, _ = relax.optimise(groups, start, deadline)
    return float(bound)


def _alterations(
    relax: PerStateRelaxation,
    free: Sequence[int],
    cap: float,
    fits: Callable[[float], bool],
    limit: int,
) -> list[dict[int, int]] | None:
    """Every alteration of the ``free`` choices whose options together ``fits`` (choice index
    to option index, the choices left out unaltered, the empty one included); None where
    there are more than ``limit``."""
    options = [
        (i, [(int(k), float(relax.option_cost[relax.first_option[i] + k])) for k in ks])
        for i in free
        if (ks := relax.affordable(i, cap)).size
    ]
    found: list[dict[int, int]] = []
    picks: dict[int, int] = {}

    def grow(j: int, spent: float) -> None:
        if len(found) > limit:
            return
        if j == len(options):
            found.append(dict(picks))
            return
        grow(j + 1, spent)  # this choice unaltered
        i, own = options[j]
        for k, c in own:
            if fits(spent + c):
                picks[i] = k
                grow(j + 1, spent + c)
                del picks[i]

    grow(0, 0.0)
    return None if len(found) > limit else found


def _enumerated(
    relax: PerStateRelaxation,
    free: Sequence[int],
    cap: float,
    fixed: Mapping[int, int],
    fits: Callable[[float], bool],
    deadline: Deadline | None,
    limit: int | None = None,
) -> float | None:
    """The best exact value (least fixed point of its chain) of the alterations of the
    ``free`` choices within ``cap`` (``fixed`` as fixed, every other choice unaltered); None
    where there are more than ``limit`` (default :data:`MAX_ENUMERATED`) of them. Every
    completion of the node that alters only choices in ``free`` is one of them, so it bounds
    them where the relaxation's proof does not."""
    combos = _alterations(relax, free, cap, fits, MAX_ENUMERATED if limit is None else limit)
    if combos is None:
        return None
    best = -np.inf
    for picks in combos:
        if deadline is not None:
            deadline.check()
        options = relax.free_options((), cap, {**fixed, **picks})
        penalty = np.where(relax.allowed_groups(options), 0.0, -np.inf)
        policy = relax.best_groups(penalty)[0]
        best = max(best, float(relax.evaluate(policy)[relax.chain.initial]))
    return best
