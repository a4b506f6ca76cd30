"""The time policy: how one solve's deadline is shared between its stages and budgets.

Every share of time any method gives any stage is computed here, so that a change of policy
is one edit and every number can be read side by side. Each share is a sub-deadline of the
solve's own (:meth:`Deadline.within`): it never outlives the solve, and a cancellation ends it.
The measurements behind the constants live in ``bench/`` (``hard_instances.py``).
"""

from __future__ import annotations

from typing import NamedTuple

from misdirect.solvers.deadline import Deadline

# -- auto: enumerate, or search first ------------------------------------------------------------
INCREMENTAL_SURE = 200_000  # alterations the low-rank enumeration always takes on
UPDATE_SECONDS = 5e-6  # about the enumeration's time per alteration, on 2 threads
ENUMERATION_FIRST = 0.5  # enumerate first when this share of the time left covers it; else
ENUMERATION_RESERVE = 0.9  # search first, keeping this share for enumerating what is left
SEARCH_FIRST = 0.25  # ... but giving the search at least this share of the time left
BLIND_SEARCH_SHARE = 0.9  # a staged enumeration's share where the search's bound cannot see
# the budget (end components): there the search seldom proves what the enumeration would
UNLIMITED_FIRST = 10.0  # with no time limit: enumerate first what takes at most this long,
UNLIMITED_SEARCH = 0.2  # else search first for this share of the enumeration's time
BASES_FIRST_SECONDS = 1.0  # an enumeration mostly of base solves, longer than this: search first
EVALUATION_SURE = 2.0  # seconds of one-by-one exact evaluation auto always spends enumerating
SAMPLE_EVALUATIONS = 8  # alterations auto evaluates to measure what one evaluation costs ...
SAMPLE_SECONDS = 0.2  # ... stopping once this long is spent (after the first)

# -- branch-and-bound: the per-state search, then the segment search ------------------------------
CLIMB_SHARE = 0.25  # of a budget's even share: the hill climb before its search
SEGMENT_MIN_SECONDS = 1.0  # the segment search backs a budget up with at least this much left
HANDOVER_MIN_SECONDS = 1.0  # a later stage of auto starts only with at least this much left: a
# MILP handed less still builds its model, solves, checks its claim and proves a bound, so it
# overruns the limit and answers nothing new
SEGMENT_SHARE = 0.95  # ... and takes this share of a budget's time (its bound is the tighter)
SEGMENT_FIRST_SECONDS = 5.0  # ... with no time limit, the per-state search gets this long first


def enumeration_seconds(count: int, per_alteration: float | None = None) -> float:
    """About how long enumerating ``count`` alterations takes at ``per_alteration`` seconds
    each (default: ``UPDATE_SECONDS``, the low-rank enumeration's update; one exact evaluation
    where it does not apply, as measured by auto)."""
    return count * (UPDATE_SECONDS if per_alteration is None else per_alteration)


STAGE_FROM = INCREMENTAL_SURE  # a budget of a curve is enumerated on its own (before the
# next) only when the next one's alterations are more than this: else one run of the next
# proves both, for little more than the smaller run alone would cost
RATE_SAMPLE = 10_000  # alterations an enumeration must have valued to measure its own rate


class Measured(NamedTuple):
    """What the last budget's enumeration took: its seconds, the alterations it valued, the
    base chains it solved and the seconds those took."""

    seconds: float
    alterations: int
    base_solves: int
    base_seconds: float = 0.0


def next_level_fits(
    count: int,
    bases: int,
    measured: Measured | None,
    deadline: Deadline,
    *,
    search_sees_budget: bool = True,
) -> bool:
    """Whether a staged enumeration takes on its next budget, of ``count`` alterations and
    ``bases`` base solves, when it has a search to hand that budget to instead: when it fits
    in the fair share of the time left. ``measured`` is the last budget's run: each base costs
    at most what one of its bases took, whole (on a big map a base solve of thousands of
    columns takes seconds, whatever the count), and, from ``RATE_SAMPLE`` alterations on, its
    rate is trusted too (a small run is mostly the building of its bases); never faster than
    ``UPDATE_SECONDS`` each.

    Where the search's bound cannot see the budget (chains with end components: a relaxation
    steers round a cycle for free, and its bound stays near the largest value), the search
    rarely proves what the enumeration would, so the enumeration is costed at its truer rate,
    its alterations' seconds apart from its bases' (a small run is mostly its base). Elsewhere
    the whole rate stands: with the truer one, auto enumerated a budget of a sensor network
    that the search, whose bound sees the budget, proves sooner (docs/benchmarks.md)."""
    if count <= INCREMENTAL_SURE and bases <= 1:
        return True
    needed = enumeration_seconds(count)
    if measured is not None:
        # per base: the whole run's seconds, or (blind search) only its bases'
        per_base = measured.seconds if search_sees_budget else measured.base_seconds
        bases_cost = bases * per_base / max(measured.base_solves, 1)
        needed += bases_cost
        if measured.alterations >= RATE_SAMPLE:
            if search_sees_budget:
                rate = measured.seconds / measured.alterations
                projected = enumeration_seconds(count, rate)
            else:
                rate = max(measured.seconds - measured.base_seconds, 0.0) / measured.alterations
                projected = bases_cost + count * rate
            needed = max(needed, projected)
    return needed <= fair_share(deadline, search_sees_budget=search_sees_budget)


def fair_share(deadline: Deadline, *, search_sees_budget: bool = True) -> float:
    """What an enumeration may take before anything else runs: ``ENUMERATION_FIRST`` of the
    time left, or ``BLIND_SEARCH_SHARE`` where the search's bound cannot see the budget (with
    no limit: ``UNLIMITED_FIRST`` seconds); a run with a search to hand its budget to stops
    once its blocks project past it. Where the search's bound is blind, the larger share
    keeps a noisy machine from cutting short an enumeration for a search that would prove
    nothing in its place (docs/benchmarks.md, "Chains with cycles")."""
    left = deadline.remaining()
    if left is None:
        return UNLIMITED_FIRST
    return (ENUMERATION_FIRST if search_sees_budget else BLIND_SEARCH_SHARE) * left


def bases_seconds(bases: int, per_base: float) -> float:
    """About how long an enumeration's ``bases`` base solves take, at ``per_base`` seconds
    each (one exact evaluation of the chain, as auto measures it: a base factorises the same
    chain and solves more columns, so this is a lower bound); nothing for a single base."""
    return bases * per_base if bases > 1 else 0.0


def mostly_bases(needed: float, bases_s: float) -> bool:
    """Whether an enumeration of about ``needed`` seconds, ``bases_s`` of them base solves,
    is mostly bases and not quick (over ``BASES_FIRST_SECONDS``). A base solve costs about
    what a search node does (both solve the chain), so such an enumeration is a search that
    cannot prune: the search gets the first try. On the paper grid with the consistency
    monitor, budget 4's 97,119 alterations are 3,956 bases (35 s) where branch-and-bound
    certifies in about 200 nodes (docs/benchmarks.md, "Stealth")."""
    return bases_s > BASES_FIRST_SECONDS and 2 * bases_s > needed


def enumeration_fits(
    count: int,
    needed: float,
    deadline: Deadline,
    *,
    limit: int,
    bases_s: float = 0.0,
    search_sees_budget: bool = True,
) -> bool:
    """Whether auto enumerates ``count`` alterations (at most ``limit``; about ``needed``
    seconds, ``bases_s`` of them base solves) with low-rank updates before anything else:
    not when they are :func:`mostly_bases` and the search's bound sees the budget; else
    always up to ``INCREMENTAL_SURE``, and beyond when they take at most the fair share of
    the time left."""
    if search_sees_budget and mostly_bases(needed, bases_s):
        return False
    return count <= INCREMENTAL_SURE or (count <= limit and needed <= fair_share(deadline))


def search_before_enumerating(
    count: int, needed: float, deadline: Deadline, *, limit: int, bases: bool = False
) -> float | None:
    """Seconds for the search before enumerating ``count`` alterations (about ``needed``
    seconds), or None if they are not to be enumerated: within a limit, what the enumeration
    leaves of the time (if it needs under ``ENUMERATION_RESERVE`` of it), at least
    ``SEARCH_FIRST`` of it; without one, ``UNLIMITED_SEARCH`` of the enumeration's time, so a
    search that certifies at once saves it, at worst costing that; all of it where the
    enumeration is :func:`mostly_bases` (``bases``: its estimate is a lower bound, and each
    base costs about a search node)."""
    if count > limit:
        return None
    left = deadline.remaining()
    if left is None:
        return needed if bases else UNLIMITED_SEARCH * needed
    if needed > ENUMERATION_RESERVE * left:
        return None
    return max(left - needed / ENUMERATION_RESERVE, SEARCH_FIRST * left)


# -- the MILP: its values' scale, then each budget ------------------------------------------------
MILP_SCALE_PARTS = 10  # the relaxation that scales the MILP's values takes a tenth of the time


def milp_scale(deadline: Deadline) -> Deadline:
    """The per-state relaxation that gives the MILP its values' scale (its bound on every
    state's value at the largest budget): a tenth of the time left at most; without a limit,
    the grace of a closing bound. Cut short, it gives the trivial bound: scale 1."""
    share = deadline.share(MILP_SCALE_PARTS)
    return closing_bound(deadline) if share is None else Deadline(share, cancel=deadline.cancel)


def milp_budget(deadline: Deadline, budgets_left: int) -> float | None:
    """Seconds for the MILP's next budget: an even share of what is left (what a budget does
    not use rolls over to the next); None without a limit."""
    return deadline.share(budgets_left)


def climb(deadline: Deadline, budgets_left: int) -> Deadline:
    """The hill climb before a budget's search: a quarter of the budget's even share."""
    share = deadline.share(budgets_left)
    return deadline.within(None if share is None else share * CLIMB_SHARE)


def per_state_search(
    deadline: Deadline, budgets_left: int, *, segment_backs_up: bool, per_state_failed: bool
) -> Deadline:
    """The per-state search of a budget: twice the share of each later budget (the next one
    is the likelier to finish), or, where the segment search backs it up, what that one leaves
    (nothing once the per-state search has failed a smaller budget: its bound only loosens
    with the budget)."""
    share = deadline.front_share(budgets_left)
    if segment_backs_up:
        share = SEGMENT_FIRST_SECONDS if share is None else share * (1 - SEGMENT_SHARE)
        if per_state_failed:
            share = 0.0
    return deadline.within(share)


def segment_search(deadline: Deadline, budgets_left: int) -> Deadline:
    """The segment search of a budget the per-state search did not certify."""
    return deadline.within(deadline.front_share(budgets_left))


def segment_has_time(deadline: Deadline) -> bool:
    """Whether enough is left to build the segment relaxation and search with it."""
    left = deadline.remaining()
    return left is None or left >= SEGMENT_MIN_SECONDS


# -- closing bounds -------------------------------------------------------------------------------
CLOSING_BOUND_SECONDS = 1.0  # a method cut short proves its bound within this much more time


def closing_bound(deadline: Deadline) -> Deadline:
    """The deadline of the bound a method proves once it is cut short (its own time is up):
    ``CLOSING_BOUND_SECONDS`` past ``deadline``, one grace shared by every such bound of the
    run (a curve cut short proves one per budget: a grace each would add up past the limit),
    and a cancellation still ends it at once. Without a time limit, that much from
    now."""
    if deadline.end is None:
        return Deadline(CLOSING_BOUND_SECONDS, cancel=deadline.cancel)
    return Deadline(None, cancel=deadline.cancel, end=deadline.end + CLOSING_BOUND_SECONDS)


def can_hand_over(deadline: Deadline) -> bool:
    """Whether a later stage of a portfolio has time to answer anything
    (``HANDOVER_MIN_SECONDS`` left; without a time limit, unless stopped)."""
    left = deadline.remaining()
    return left is None or left >= HANDOVER_MIN_SECONDS
