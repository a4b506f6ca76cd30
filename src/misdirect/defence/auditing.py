"""The audit: how strong the attacker is at every budget up to ``B``, and which sensors matter.

Per sensor it reports the attacker's best with only that sensor alterable and the sensor's
*criticality* — how much protecting it lowers the optimum at ``B`` — and, for scale, the online
attacker's value. It answers "where is the system weak?" before :mod:`misdirect.defence.hardening`
answers "what should be protected?".
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence

from misdirect.core import tolerance
from misdirect.core.alterations import alteration_space, max_alteration_cost
from misdirect.core.attack import shared_preparation
from misdirect.core.grid import grid_cells
from misdirect.core.keywords import checked_keywords, one_budget_keyword
from misdirect.core.model import Problem
from misdirect.defence.attack import (
    Attack,
    attack_of,
    attacker_budget,
    protect,
    shared_deadline,
    solve_many,
)
from misdirect.defence.monitoring import (
    BOTH,
    MONITOR,
    NOTHING,
    PROTECTION,
    compare_defences,
    most_critical,
    protection_words,
    split_monitor,
)
from misdirect.defence.online import online_attack_value
from misdirect.defence.results import AuditResult, MonitorComparison, OnlineAttack, SensorAudit
from misdirect.errors import ProblemError, SolverError
from misdirect.solvers.certification import Evidence
from misdirect.solvers.deadline import CancelToken, Deadline, DeadlineExpiredError
from misdirect.solvers.pool import TaskPool
from misdirect.solvers.run import SolveResult, clamp_budget, default_budgets, recertify, solve
from misdirect.solvers.status import Status

SINGLES = "single-sensor optima"  # what certifies a budget that affords one sensor at most


@checked_keywords
def audit(
    problem: Problem,
    *,
    budget: float | None = None,
    budgets: float | Sequence[float] | None = None,
    time_limit: float | None = None,
    method: str = "auto",
    deadline: Deadline | None = None,
    cancel: CancelToken | None = None,
    pool: TaskPool | None = None,
) -> AuditResult:
    """Which sensors are weak: the attacker's optimum at every budget up to ``budget``, each
    sensor's criticality and single-sensor value, and the online attacker's value.

    Parameters
    ----------
    problem : Problem
        The POMDP, controller, costs and decoy.
    budget : float, optional
        The attacker's budget ``B``; default ``problem.budget``.
    budgets : float, optional
        The same parameter spelled as ``solve`` spells it (a number, or a sequence of one);
        both given and different is a ``TypeError``.
    time_limit : float, optional
        Seconds for the whole audit, every solve of it included.
    method : str
        The method of every attacker solve (:func:`misdirect.solve`); default ``auto``.
    deadline : Deadline, optional
        A deadline shared with other work; ``time_limit`` limits the audit further.
    cancel : CancelToken, optional
        Cancelling it stops every solve of the audit, which returns what it has.
    pool : TaskPool, optional
        Where the single-sensor solves and the re-solves run, all at once
        (:func:`misdirect.distributed.connect`); the curve's own solve stays here.

    Returns
    -------
    AuditResult
        The curve, one :class:`~misdirect.defence.results.SensorAudit` row per sensor
        alterable within ``B`` (most critical first) and the online attacker's value;
        ``certified`` says whether every number is proven.

    Raises
    ------
    ProblemError
        A negative budget, or one no sensor is alterable within.
    TypeError
        An unknown keyword argument (the message lists the valid ones).

    Notes
    -----
    Criticality uses the exact shortcut: protecting a sensor the optimal alteration at ``B``
    does not alter leaves that alteration feasible and the optimum unchanged (protection only
    removes alterations), so only the sensors of the optimal attack are re-solved. A budget
    of the curve that affords one sensor at most is bounded by the single-sensor optima, which
    often certify what the curve's own solve left open (the search's bound can be 1 there).

    ``time_limit`` (seconds) bounds the whole audit, within ``deadline`` when one is shared
    with other work; cancelling ``cancel`` (or the deadline's token) stops every solve of it.
    Details and proofs: docs/defence.md.

    Examples
    --------
    >>> import misdirect
    >>> from misdirect.scenarios import paper_grid
    >>> report = misdirect.audit(paper_grid(5), budget=4)
    >>> report.certified, round(report.probability, 6)
    (True, 0.863622)
    >>> [(row.observation, round(row.criticality, 3)) for row in report.sensors[:2]]
    [('o1', 0.123), ('o2', 0.088)]
    """
    started = time.perf_counter()
    clock = shared_deadline(time_limit, deadline, cancel)
    problem, plain = split_monitor(problem)
    asked = attacker_budget(problem, one_budget_keyword("audit", budget, budgets))
    # past the most expensive complete alteration every budget affords the same: work at it
    budget, clamped_from = clamp_budget(asked, max_alteration_cost(problem))
    problem = problem.with_budget(budget)
    listing: list[str] = []  # how the curve's budgets were thinned, if they were
    with shared_preparation():
        curve_result = _optimum_curve(problem, budget, clock, method, asked, listing)
        cheapest = _cheapest_alterations(problem, budget)
        # the re-solves at B the optimum is likely to need share the time with the singles
        likely = sum(o in attack_of(curve_result.curve[-1], problem).changed for o in cheapest)
        baseline = curve_result.baseline_probability
        singles = _single_values(problem, budget, list(cheapest), clock, likely, baseline, pool)
        evidence = _single_sensor_evidence(curve_result, cheapest, singles, problem.cost.scale)
        curve_result = recertify(curve_result, problem, evidence)
        optimum = attack_of(curve_result.curve[-1], problem)
        rows, re_solved = _sensor_rows(
            problem, budget, optimum, singles, clock, method, baseline, pool
        )
        comparison = (
            None
            if plain is None
            else _monitor_comparison(
                problem, plain.with_budget(budget), budget, optimum, re_solved, clock, method, pool
            )
        )
    notes = _not_certified(optimum, curve_result, budget) + listing
    online, note = _online_value(problem, asked, optimum, clock)
    if online is None:
        notes.append("the online attacker's value is not computed: the time limit was reached")
    certified = optimum.certified and all(r.exact for r in rows)
    top = curve_result.curve[-1]
    return AuditResult(
        problem=problem.title,
        budget=asked,
        baseline_probability=curve_result.baseline_probability,
        curve=curve_result.curve,
        status=top.status,
        probability=top.probability,
        upper_bound=top.upper_bound,
        alteration=top.alteration,
        sensors=rows,
        online=online,
        online_budgeted_note=note,
        certified=certified,
        notes=notes + list(curve_result.warnings),
        time_s=time.perf_counter() - started,
        objective=problem.objective.kind,
        grid=grid_cells(problem) is not None,
        budget_clamped_from=clamped_from,
        budget_clamped_to=None if clamped_from is None else budget,
        monitor_comparison=comparison,
    )


def _monitor_comparison(
    watched: Problem,
    plain: Problem,
    budget: float,
    optimum: Attack,
    re_solved: dict[int, Attack],
    clock: Deadline,
    method: str,
    pool: TaskPool | None,
) -> MonitorComparison:
    """The monitor against protecting one sensor, at ``budget``: the sensor is the one whose
    protection lowers the optimum *without* the monitor the most (what a defender without a
    monitor would protect first). The monitored answers come from the audit: its optimum, and
    its re-solve with that sensor protected (or the optimum itself, when its attack leaves the
    sensor alone)."""
    [nothing] = solve_many([plain], budget, clock, method)
    protection, solved = most_critical(plain, budget, nothing, clock, method, pool)
    known = {NOTHING: nothing, MONITOR: optimum}
    if not protection:  # no attack at all without the monitor: protection changes nothing
        known[PROTECTION] = nothing
    for o in protection:
        known[PROTECTION] = solved[o]
        if o in re_solved:
            known[BOTH] = re_solved[o]
        elif o not in optimum.changed:
            known[BOTH] = optimum
    names = plain.pomdp.observations
    why = (
        f"protect {protection_words(names, protection)}: the one sensor whose protection "
        "lowers the optimum without the monitor the most"
    )
    return compare_defences(
        watched,
        plain,
        budget,
        protection=protection,
        known=known,
        why=why,
        clock=clock,
        method=method,
        pool=pool,
    )


def _optimum_curve(
    problem: Problem,
    budget: float,
    clock: Deadline,
    method: str,
    asked: float,
    notes: list[str] | None = None,
) -> SolveResult:
    """The attacker's optimum at every budget up to ``budget`` (in the costs' unit when whole
    budgets would be too many: :func:`default_budgets`, which says in ``notes`` if it thins
    them), and at ``asked`` (solve answers a budget above the cap with the cap's answer),
    within half the time left."""
    listed = default_budgets(budget, problem.cost.scale, notes=notes)
    return solve(
        problem,
        method=method,
        budgets=sorted({*listed, asked}),
        deadline=clock.within(clock.share(2)),
    )


def _not_certified(optimum: Attack, curve_result: SolveResult, budget: float) -> list[str]:
    """A note if the optimum at ``budget`` is not certified."""
    if optimum.certified:
        return []
    return [
        f"the optimum at budget {budget:g} is not certified (status "
        f"{curve_result.curve[-1].status}, proven bound {optimum.upper:.9f}): criticalities "
        "are intervals, not values"
    ]


def _cheapest_alterations(problem: Problem, budget: float) -> dict[int, float]:
    """The sensors alterable within ``budget`` to something the controller reacts to
    differently (the others cannot change the outcome), each with the cost of its cheapest
    such alteration."""
    space = alteration_space(problem.with_budget(budget))
    return {int(c.observation): float(c.costs[1:].min()) for c in space.choices}


def _single_values(
    problem: Problem,
    budget: float,
    sensors: list[int],
    clock: Deadline,
    later: int,
    baseline: float,
    pool: TaskPool | None = None,
) -> dict[int, Attack]:
    """The attacker's optimum at ``budget`` with only one sensor alterable, for each sensor:
    one observation's few candidates, cheap; ``later`` re-solves at B (as hard as the optimum
    itself) then share what is left of the time."""
    everything = frozenset(range(problem.pomdp.n_observations))
    problems = [protect(problem, everything - {o}) for o in sensors]
    top = problem.objective.max_value

    def unsolved() -> Attack:  # each solve takes its 50 ms and its evaluations: none past the end
        return _unsolved(problem, baseline, top)

    found = solve_many(
        problems, budget, clock, "exhaustive", pool=pool, later=later, unsolved=unsolved
    )
    return dict(zip(sensors, found, strict=True))


def _unsolved(problem: Problem, baseline: float, upper: float) -> Attack:
    """An attacker's optimum not solved for want of time: at least the unaltered value
    ``baseline`` (every protection leaves it feasible), at most ``upper``."""
    identity = problem.identity()
    return Attack(
        value=baseline,
        upper=upper,
        status=Status.TIME_LIMIT,
        alteration={},
        changed=frozenset(),
        cost=0.0,
        alteration_array=identity,
    )


def _single_sensor_evidence(
    curve_result: SolveResult,
    cheapest: dict[int, float],
    singles: dict[int, Attack],
    scale: tolerance.CostScale,
) -> list[Evidence]:
    """What the single-sensor optima prove about the curve: a budget that affords no two
    sensors together (their two cheapest alterations cost more) only affords alterations of
    one sensor, so its optimum is at most the best bound of the sensors it affords (each
    proven over a larger budget, ``B``), and at least the best of their optimal alterations
    that fit it. With unit costs that is every budget below 2: the budget-1 optimum is the
    largest single-sensor optimum."""
    costs = sorted(cheapest.values())
    pair = costs[0] + costs[1] if len(costs) > 1 else math.inf
    evidence = []
    for point in curve_result.curve:
        b = point.budget
        if scale.fits(pair, b):
            continue
        fits = [singles[o] for o, cost in cheapest.items() if scale.fits(cost, b)]
        upper = max([a.upper for a in fits], default=curve_result.baseline_probability)
        best = _best_within([a for a in fits if scale.fits_exactly([a.cost], b)])
        evidence.append(
            Evidence(
                budget=b,
                source=SINGLES,
                why=f"budget {b:g} affords one sensor at most (two cost {pair:g})",
                upper_bound=max(upper, curve_result.baseline_probability),
                alteration=None if best is None else best.alteration_array,
                probability=None if best is None else best.value,
                cost=None if best is None else best.cost,
                error_bound=0.0 if best is None else best.error,
            )
        )
    return evidence


def _best_within(attacks: Sequence[Attack]) -> Attack | None:
    with_array = [a for a in attacks if a.alteration_array is not None]
    return max(with_array, key=lambda a: a.value, default=None)


def _sensor_rows(
    problem: Problem,
    budget: float,
    optimum: Attack,
    singles: dict[int, Attack],
    clock: Deadline,
    method: str,
    baseline: float,
    pool: TaskPool | None = None,
) -> tuple[list[SensorAudit], dict[int, Attack]]:
    """One row per sensor alterable within ``budget``, the most critical first, and the
    optimum re-solved with each sensor of the optimal attack protected."""
    sensors = list(singles)
    names = problem.pomdp.observations
    needs = [o for o in sensors if o in optimum.changed]
    problems = [protect(problem, [o]) for o in needs]

    def unsolved() -> Attack:  # protecting a sensor only lowers the optimum: bounded by it
        return _unsolved(problem, baseline, optimum.upper)

    found = solve_many(problems, budget, clock, method, pool=pool, unsolved=unsolved)
    re_solved = dict(zip(needs, found, strict=True))
    rows: list[SensorAudit] = []
    for o in sensors:
        single = singles[o]
        # a sensor the optimal alteration leaves alone keeps it feasible: the optimum stands
        hit = re_solved.get(o, optimum)
        low, high = _criticality(optimum, re_solved.get(o))
        rows.append(
            SensorAudit(
                observation=names[o],
                single_probability=single.value,
                single_status=single.status,
                single_alteration=single.alteration,
                in_optimal_attack=o in optimum.changed,
                criticality=low,
                criticality_upper=high,
                protected_probability=hit.value,
                protected_status=hit.status,
                protected_alteration=hit.alteration,
            )
        )
    rows.sort(key=lambda r: (-r.criticality, -r.single_probability, r.observation))
    return rows, re_solved


def _criticality(optimum: Attack, protected: Attack | None) -> tuple[float, float]:
    """Proven ``(low, high)`` bounds on how much protecting one sensor lowers the optimum;
    ``protected``: the attacker's answer with it protected, None when it was not re-solved."""
    if protected is None:  # the optimal alteration stays feasible: the optimum is unchanged
        # certified: exactly 0 (its bound may sit a rounding above its value, and a gap of
        # 1e-16 over 0 would read as unproven relative to 0)
        return 0.0, 0.0 if optimum.certified else max(optimum.upper - optimum.value, 0.0)
    if optimum.certified and protected.certified:
        drop = max(optimum.value - protected.value, 0.0)
        return drop, drop
    # OPT ∈ [value, upper] on both sides
    return (
        max(optimum.value - protected.upper, 0.0),
        max(optimum.upper - protected.value, 0.0),
    )


def _online_value(
    problem: Problem, budget: float, optimum: Attack, clock: Deadline
) -> tuple[OnlineAttack | None, str | None]:
    """The online attacker's value within the audit's time, budgeted within ``budget`` when
    it can be computed (else unlimited only, with the reason), checked against the offline
    optimum it must bound; None (with the reason) when even the unlimited value was cut."""
    expired = "the time limit was reached"
    if clock.expired():
        return None, expired
    note = None
    try:
        try:  # the budgeted MDP (one layer per budget unit) is the first to go
            online = online_attack_value(problem, budget, deadline=clock)  # never clamped
        except ProblemError as error:
            note = error.reason
            online = online_attack_value(problem, None, deadline=clock)
        except DeadlineExpiredError:
            note = expired
            online = online_attack_value(problem, None, deadline=clock)
    except DeadlineExpiredError:
        return None, expired
    # the online attacker sees more than the offline one: below it would contradict a theorem
    if tolerance.better(optimum.value, online.unlimited_bound, rel=tolerance.CERTIFY):
        raise SolverError(
            f"online bound {online.unlimited_bound:.12f} below the offline value "
            f"{optimum.value:.12f}"
        )
    return online, note
