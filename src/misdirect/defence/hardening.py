"""Hardening: which sensors to protect, within a protection budget ``D``, so that the
attacker's optimum at ``B`` is as low as possible — an exact min–max.

The inner problem (the attacker's optimum under one protection set) is a full solve, so the
search is built to make as few as possible: it branches only where protection can matter and
prunes with a lower bound that costs no solve at all (a hitting-set argument over the attacks
already found).
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping, Sequence
from dataclasses import replace

import numpy as np

from misdirect.core import tolerance
from misdirect.core.alterations import max_alteration_cost, options_bound
from misdirect.core.keywords import checked_keywords, one_budget_keyword
from misdirect.core.model import Problem
from misdirect.defence.attack import (
    Attack,
    alterable_sensors,
    attacker_budget,
    protect,
    shared_deadline,
    solve_at,
    solve_many,
)
from misdirect.defence.monitoring import (
    BOTH,
    MONITOR,
    NOTHING,
    PROTECTION,
    compare_defences,
    protection_words,
    split_monitor,
)
from misdirect.defence.results import HardenPoint, HardenResult, MonitorComparison
from misdirect.errors import ProblemError
from misdirect.solvers.deadline import CancelToken, Deadline
from misdirect.solvers.pool import TaskPool
from misdirect.solvers.run import clamp_budget, default_budgets
from misdirect.solvers.status import Status

HITTING_NODE_LIMIT = 200_000  # the lower bound's hitting-set search gives up (soundly) beyond


def protection_costs(
    problem: Problem, costs: Mapping[str, float] | None, *, field: str = "protect_costs"
) -> np.ndarray:
    """Per observation, what protecting it costs: ``costs`` by name, key ``default`` for the
    rest (default 1). Unknown names, negative or non-finite costs are refused."""
    names = problem.pomdp.observations
    index = {name: i for i, name in enumerate(names)}
    costs = dict(costs or {})
    default = 1.0
    if "default" in costs and "default" not in index:
        default = float(costs.pop("default"))
    table = np.full(len(names), default)
    for name, value in [("default", default), *costs.items()]:
        if name != "default" and name not in index:
            shown = ", ".join(names[:8]) + (", …" if len(names) > 8 else "")
            raise ProblemError(f"unknown observation {name!r} (known: {shown})", field=field)
        value = float(value)
        if not (math.isfinite(value) and value >= 0):
            raise ProblemError(
                f"the protection cost of {name!r} must be a non-negative number, got {value}",
                field=field,
            )
        if name != "default":
            table[index[name]] = value
    # protection budgets are compared with sums of these: one past the largest float is none
    if not math.isfinite(sum(table.tolist(), 0.0)):
        raise ProblemError(
            f"the protection costs sum to more than the largest number "
            f"({np.finfo(float).max:.3g}); scale them down",
            field=field,
        )
    return table


def _can_hit(
    sets: Sequence[frozenset[int]], room: float, costs: np.ndarray, work: list[int]
) -> bool:
    """Is there a set of sensors of total cost ≤ ``room`` meeting every one of ``sets``?
    (``room`` is a cap: :meth:`~misdirect.core.tolerance.CostScale.cap` of the protection
    budget, less what was spent; ``cost <= room`` is then exact.)

    Branches on the elements of the smallest set not yet met (every hitting set contains one
    of them). Beyond ``HITTING_NODE_LIMIT`` nodes it answers True, which only ever weakens the
    lower bound it serves, never invalidates it."""
    failed: set[frozenset[int]] = set()

    def search(chosen: frozenset[int], room: float) -> bool:
        open_sets = [s for s in sets if not (s & chosen)]
        if not open_sets:
            return True
        if chosen in failed:
            return False
        work[0] += 1
        if work[0] > HITTING_NODE_LIMIT:
            return True
        smallest = min(open_sets, key=len)
        for o in sorted(smallest, key=lambda o: costs[o]):
            if costs[o] <= room and search(chosen | {o}, room - costs[o]):
                return True
        failed.add(chosen)
        return False

    return search(frozenset(), room)


def hitting_lower_bound(
    attacks: Sequence[tuple[float, frozenset[int]]],
    fixed: frozenset[int],
    room: float,
    costs: np.ndarray,
) -> float:
    """A proven lower bound on min f(Q) over Q ⊇ ``fixed`` with cost(Q \\ fixed) ≤ ``room``.

    Each ``(v, A)`` is an alteration within the attacker's budget of exact value ``v`` that
    alters the sensors ``A``: under any protection Q missing A it stays feasible, so f(Q) ≥ v.
    Hence f(Q) ≥ max{v : A ∩ Q = ∅}, and the minimum of that over the Q allowed is the largest
    v such that the attacks of value ≥ v cannot all be met within ``room``. ``attacks`` must
    include the unaltered one (value: f with everything protected, A = ∅), which nothing meets.
    """
    live = sorted(((v, a - fixed) for v, a in attacks if not (a & fixed)), key=lambda t: -t[0])
    work = [0]
    must: list[frozenset[int]] = []
    i = 0
    while i < len(live):
        v = live[i][0]
        j = i
        while j < len(live) and live[j][0] >= v:
            must.append(live[j][1])
            j += 1
        if not _can_hit(must, room, costs, work):
            return v
        i = j
    return 0.0  # unreachable when the unaltered attack is included


@checked_keywords
def harden(
    problem: Problem,
    *,
    protect_budget: float,
    budget: float | None = None,
    budgets: float | Sequence[float] | None = None,
    protect_costs: Mapping[str, float] | None = None,
    time_limit: float | None = None,
    method: str = "auto",
    deadline: Deadline | None = None,
    cancel: CancelToken | None = None,
    pool: TaskPool | None = None,
) -> HardenResult:
    """The protection set within ``protect_budget`` minimising the attacker's optimum at
    ``budget``, with the trade-off curve over every whole protection budget up to it.

    Parameters
    ----------
    problem : Problem
        The POMDP, controller, costs and decoy.
    protect_budget : float
        The defender's budget ``D``: what the protected sensors may cost in all.
    budget : float, optional
        The attacker's budget ``B``; default ``problem.budget``.
    budgets : float, optional
        The same parameter spelled as ``solve`` spells it (a number, or a sequence of one);
        both given and different is a ``TypeError``.
    protect_costs : mapping of str to float, optional
        What protecting each sensor costs, by observation name (``"default"`` for the
        rest); default 1 each.
    time_limit : float, optional
        Seconds for the whole search; on expiry the best protection found, with a proven
        lower bound (``status`` ``time_limit``).
    method : str
        The method of every attacker solve (:func:`misdirect.solve`); default ``auto``.
    deadline : Deadline, optional
        A deadline shared with other work; ``time_limit`` limits the search further.
    cancel : CancelToken, optional
        Cancelling it stops every solve of the search.
    pool : TaskPool, optional
        Where the children of each node are solved, all at once, before the search visits
        them (:func:`misdirect.distributed.connect`): a child it then prunes was solved for
        nothing, but every answer is the one a local run finds.

    Returns
    -------
    HardenResult
        The protection, the attacker's optimum before and after, and the trade-off curve.

    Raises
    ------
    ProblemError
        A negative protection budget, an unknown sensor in ``protect_costs``, or a negative
        cost.
    TypeError
        An unknown keyword argument (the message lists the valid ones).

    Notes
    -----
    Hitting-set branching: with α*(P) the attacker's optimum under protection P, every
    superset of P that protects none of α*(P)'s sensors keeps α*(P) feasible and so has the
    same optimum (it cannot be higher: protecting more only removes alterations). The search
    therefore branches only on protecting one of α*(P)'s sensors, prunes a subtree when the
    hitting-set lower bound (:func:`hitting_lower_bound`) over every attack found so far
    cannot beat the best protection, and solves each protection set once.

    ``time_limit`` (seconds) bounds the whole search, within ``deadline`` when one is shared
    with other work; cancelling ``cancel`` (or the deadline's token) stops every solve of it.

    Examples
    --------
    >>> import misdirect
    >>> from misdirect.scenarios import paper_grid
    >>> plan = misdirect.harden(paper_grid(5), protect_budget=2, budget=4)
    >>> print(plan.status, plan.protection, round(plan.value_before, 6), round(plan.value_after, 6))
    optimal ['o1', 'o2'] 0.863622 0.100971
    """
    started = time.perf_counter()
    clock = shared_deadline(time_limit, deadline, cancel)
    problem, plain = split_monitor(problem)
    if not (math.isfinite(protect_budget) and protect_budget >= 0):
        raise ProblemError(
            f"must be a non-negative number, got {protect_budget}", field="protect_budget"
        )
    asked = attacker_budget(problem, one_budget_keyword("harden", budget, budgets))
    # budgets past what buys everything change nothing: B is clamped to the most expensive
    # complete alteration, D to protecting every sensor alterable within B
    budget, clamped_from = clamp_budget(asked, max_alteration_cost(problem))
    problem = problem.with_budget(budget)
    costs = protection_costs(problem, protect_costs)
    # the sensors that may be alterable, read off the costs (the space itself can be large)
    everything = float(costs[options_bound(problem) > 1].sum())
    d_cap, d_clamped_from = clamp_budget(float(protect_budget), everything)
    search = _Search(problem, budget, costs, clock, method, pool)
    curve: list[HardenPoint] = []
    best: frozenset[int] = frozenset()
    listing: list[str] = []  # how the protection budgets were thinned, if they were
    for d in (float(d) for d in default_budgets(d_cap, search.scale, notes=listing)):
        best = search.best_within(d, best)
        curve.append(search.point(d, best))
    if d_clamped_from is not None:  # the answer at the cap stands for the budget asked
        curve.append(replace(curve[-1], protect_budget=d_clamped_from))
    final = curve[-1]
    before = search.attack(frozenset())
    notes = search.notes() + listing
    comparison = None
    if plain is not None:
        comparison = _monitor_comparison(search, plain.with_budget(budget), d_cap, best)
    names = problem.pomdp.observations
    listed = {names[o]: float(costs[o]) for o in alterable_sensors(problem, budget)}
    return HardenResult(
        problem=problem.title,
        budget=asked,
        protect_budget=float(protect_budget),
        protect_costs=listed,
        protection=final.protection,
        protection_cost=final.protection_cost,
        value_before=before.value,
        value_after=final.probability,
        value_after_upper=final.upper_bound,
        lower_bound=final.lower_bound,
        best_reply=final.attack,
        status=final.status,
        curve=curve,
        solves=len(search.memo),
        nodes=search.nodes,
        pruned=search.pruned,
        time_s=time.perf_counter() - started,
        notes=notes,
        budget_clamped_from=clamped_from,
        budget_clamped_to=None if clamped_from is None else budget,
        protect_budget_clamped_from=d_clamped_from,
        protect_budget_clamped_to=None if d_clamped_from is None else d_cap,
        objective=problem.objective.kind,
        monitor_comparison=comparison,
    )


def _monitor_comparison(
    search: _Search, plain: Problem, d: float, best: frozenset[int]
) -> MonitorComparison:
    """The monitor against protection within ``d``: the best protection without the
    monitor (a search of its own on ``plain``, sharing the clock and the costs) and, with the
    monitor, the hardening's own answer ``best``."""
    alone = _Search(plain, search.budget, search.costs, search.clock, search.method, search.pool)
    chosen = alone.best_within(d, frozenset())
    names = plain.pomdp.observations
    proven = alone.complete and alone.certified
    why = (
        f"within protection budget {d:g}: the best protection without the monitor "
        f"({protection_words(names, chosen)}), and with it ({protection_words(names, best)})"
        + ("" if proven else "; the first is the best found, not proven (time or solver limit)")
    )
    known = {
        NOTHING: alone.attack(frozenset()),
        PROTECTION: alone.attack(chosen),
        MONITOR: search.attack(frozenset()),
        BOTH: search.attack(best),
    }
    return compare_defences(
        search.problem,
        plain,
        search.budget,
        protection=chosen,
        both=best,
        costs=search.costs,
        known=known,
        why=why,
        clock=search.clock,
        method=search.method,
    )


class _Search:
    """The min–max search over protection sets, shared by every protection budget of the
    curve: each protection set is solved once (``memo``), and every attack found is kept as
    evidence for the hitting-set lower bound (``attacks``)."""

    def __init__(
        self,
        problem: Problem,
        budget: float,
        costs: np.ndarray,
        clock: Deadline,
        method: str,
        pool: TaskPool | None = None,
    ) -> None:
        self.pool = pool
        self.problem = problem
        self.budget = budget
        self.costs = costs
        # protection budgets become caps: a float sum of these costs fits by ``<=`` exactly
        self.scale = tolerance.CostScale.of(costs.tolist(), len(costs))
        self.clock = clock
        self.method = method
        self.names = problem.pomdp.observations
        self.memo: dict[frozenset[int], Attack] = {}
        everything = frozenset(range(problem.pomdp.n_observations))
        floor = solve_at(protect(problem, everything), budget, clock, None, method="exhaustive")
        self.attacks: list[tuple[float, frozenset[int]]] = [(floor.value, frozenset())]
        self.nodes = 0
        self.pruned = 0
        self.complete = True  # the time limit never cut the search short
        self.certified = True  # every attacker optimum solved was proven

    def attack(self, protection: frozenset[int]) -> Attack:
        """The attacker's answer under ``protection`` (solved on first use)."""
        if protection not in self.memo:
            found = solve_at(
                protect(self.problem, protection),
                self.budget,
                self.clock,
                self.clock.share(4),
                method=self.method,
            )
            self._keep(protection, found)
        return self.memo[protection]

    def _keep(self, protection: frozenset[int], found: Attack) -> None:
        self.memo[protection] = found
        self.attacks.append((found.value, found.changed))
        self.certified &= found.certified

    def prefetch(self, protections: list[frozenset[int]]) -> None:
        """Solve the protection sets not solved yet at once on the pool (each with the share
        of time a lone solve gets: a quarter of what is left)."""
        new = [p for p in protections if p not in self.memo]
        if self.pool is None or len(new) < 2:
            return
        later = max(4 * self.pool.size - len(new), 0)
        problems = [protect(self.problem, p) for p in new]
        found = solve_many(
            problems, self.budget, self.clock, self.method, pool=self.pool, later=later
        )
        for protection, attack in zip(new, found, strict=True):
            self._keep(protection, attack)

    def cost_of(self, protection: frozenset[int]) -> float:
        """The exact sum, rounded once: equal sums compare equal, whatever their order."""
        return float(self.scale.exact(self.costs[o] for o in protection))

    def best_within(self, d: float, best: frozenset[int]) -> frozenset[int]:
        """The best protection of cost ≤ ``d``, starting from the incumbent ``best`` (the
        answer at a smaller budget, still within this one): depth first, the cheapest sensor
        first, pruning every subtree the hitting-set bound shows cannot beat the incumbent."""
        stack: list[frozenset[int]] = [frozenset()]
        seen: set[frozenset[int]] = set()
        while stack:
            if self.clock.expired():
                self.complete = False
                break
            node = stack.pop()
            if node in seen:
                continue
            seen.add(node)
            self.nodes += 1
            room = self.scale.cap(d) - self.cost_of(node)
            best_value = self.attack(best).upper
            bound = hitting_lower_bound(self.attacks, node, room, self.costs)
            if not tolerance.better(best_value, bound, rel=tolerance.CERTIFY):
                self.pruned += 1
                continue
            here = self.attack(node)
            if self.scale.fits_exactly([self.costs[o] for o in node], d) and _better(
                here, self.cost_of(node), self.attack(best), self.cost_of(best)
            ):
                best = node
            children = [
                node | {o}
                for o in sorted(here.changed, key=lambda o: (self.costs[o], self.names[o]))
                if self.costs[o] <= room and (node | {o}) not in seen
            ]
            self.prefetch(children)
            stack.extend(reversed(children))  # the cheapest sensor first
        return best

    def point(self, d: float, best: frozenset[int]) -> HardenPoint:
        """The curve's point at protection budget ``d`` for the protection ``best`` found."""
        reply = self.attack(best)
        proven = self.complete and self.certified
        lower = (
            reply.upper
            if proven
            else min(
                hitting_lower_bound(self.attacks, frozenset(), self.scale.cap(d), self.costs),
                reply.upper,
            )
        )
        status = (
            Status.OPTIMAL
            if proven
            else (Status.TIME_LIMIT if not self.complete else Status.FEASIBLE)
        )
        return HardenPoint(
            protect_budget=d,
            protection=sorted((self.names[o] for o in best), key=self.names.index),
            protection_cost=self.cost_of(best),
            probability=reply.value,
            upper_bound=reply.upper,
            lower_bound=lower,
            attack=reply.alteration,
            status=status,
        )

    def notes(self) -> list[str]:
        """What the answer does not prove, and why."""
        notes = []
        if not self.certified:
            notes.append(
                "some attacker optimum was not certified (solver time or node limit): values "
                "are reported with their proven bounds"
            )
        if not self.complete:
            notes.append("stopped by the time limit: best protection found, proven lower bound")
        return notes


def _better(candidate: Attack, cost: float, best: Attack, best_cost: float) -> bool:
    """Lower guaranteed attacker value, or tied within the tolerance (relative) and cheaper."""
    if tolerance.better(best.upper, candidate.upper, rel=tolerance.CERTIFY):
        return True
    tied = not tolerance.better(candidate.upper, best.upper, rel=tolerance.CERTIFY)
    return tied and cost < best_cost
