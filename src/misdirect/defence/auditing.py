"""The audit: how strong the attacker is at every budget up to ``B``, and which sensors matter.

Per sensor it reports the attacker's best with only that sensor alterable and the sensor's
*criticality* — how much protecting it lowers the optimum at ``B`` — and, for scale, the online
attacker's value. It answers "where is the system weak?" before :mod:`misdirect.defence.hardening`
answers "what should be protected?".
"""

from __future__ import annotations

import time

from misdirect.core import tolerance
from misdirect.core.attack import shared_preparation
from misdirect.core.grid import grid_cells
from misdirect.core.model import Problem
from misdirect.defence.attack import (
    Attack,
    alterable_sensors,
    attack_of,
    attacker_budget,
    protect,
    shared_deadline,
    solve_at,
)
from misdirect.defence.online import online_attack_value
from misdirect.defence.results import AuditResult, OnlineAttack, SensorAudit
from misdirect.errors import ProblemError, SolverError
from misdirect.solvers.deadline import CancelToken, Deadline
from misdirect.solvers.run import SolveResult, default_budgets, solve


def audit(
    problem: Problem,
    *,
    budget: float | None = None,
    time_limit: float | None = None,
    method: str = "auto",
    deadline: Deadline | None = None,
    cancel: CancelToken | None = None,
) -> AuditResult:
    """Budget curve, per-sensor single value and criticality, online value (docs/defence.md).

    Criticality uses the exact shortcut: protecting a sensor the optimal alteration at ``B``
    does not alter leaves that alteration feasible and the optimum unchanged (protection only
    removes alterations), so only the sensors of the optimal attack are re-solved.

    ``time_limit`` (seconds) bounds the whole audit, within ``deadline`` when one is shared
    with other work; cancelling ``cancel`` (or the deadline's token) stops every solve of it.
    """
    started = time.perf_counter()
    clock = shared_deadline(time_limit, deadline, cancel)
    budget = attacker_budget(problem, budget)
    problem = problem.with_budget(budget)
    with shared_preparation():
        curve_result, optimum, notes = _optimum_curve(problem, budget, clock, method)
        rows = _sensor_rows(problem, budget, optimum, clock, method)
    online, note = _online_value(problem, budget, optimum)
    certified = optimum.certified and all(r.exact for r in rows)
    top = curve_result.curve[-1]
    return AuditResult(
        problem=problem.name,
        budget=budget,
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
    )


def _optimum_curve(
    problem: Problem, budget: float, clock: Deadline, method: str
) -> tuple[SolveResult, Attack, list[str]]:
    """The attacker's optimum at every budget up to ``budget``, within half the time left;
    returns the solve, its point at ``budget`` and a note if that point is not certified."""
    curve_result = solve(
        problem,
        method=method,
        budgets=default_budgets(budget),
        deadline=clock.within(clock.share(2)),
    )
    top = curve_result.curve[-1]
    optimum = attack_of(top, problem)
    notes: list[str] = []
    if not optimum.certified:
        notes.append(
            f"the optimum at budget {budget:g} is not certified (status {top.status}, proven "
            f"bound {optimum.upper:.9f}): criticalities are intervals, not values"
        )
    return curve_result, optimum, notes


def _sensor_rows(
    problem: Problem, budget: float, optimum: Attack, clock: Deadline, method: str
) -> list[SensorAudit]:
    """One row per sensor alterable within ``budget``, the most critical first."""
    sensors = alterable_sensors(problem, budget)
    names = problem.pomdp.observations
    everything = frozenset(range(problem.pomdp.n_observations))
    needs = [o for o in sensors if o in optimum.changed]
    # single-sensor values first: one observation's few candidates, cheap; the re-solves at
    # B (as hard as the optimum itself) then share what is left of the time
    singles = {}
    for k, o in enumerate(sensors):
        singles[o] = solve_at(
            protect(problem, everything - {o}),
            budget,
            clock,
            clock.share(len(sensors) - k + len(needs)),
            method="exhaustive",
        )
    re_solved = {}
    for k, o in enumerate(needs):
        re_solved[o] = solve_at(
            protect(problem, [o]), budget, clock, clock.share(len(needs) - k), method=method
        )
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
    return rows


def _criticality(optimum: Attack, protected: Attack | None) -> tuple[float, float]:
    """Proven ``(low, high)`` bounds on how much protecting one sensor lowers the optimum;
    ``protected``: the attacker's answer with it protected, None when it was not re-solved."""
    if protected is None:  # the optimal alteration stays feasible: the optimum is unchanged
        return 0.0, max(optimum.upper - optimum.value, 0.0)
    if optimum.certified and protected.certified:
        drop = max(optimum.value - protected.value, 0.0)
        return drop, drop
    # OPT ∈ [value, upper] on both sides
    return (
        max(optimum.value - protected.upper, 0.0),
        max(optimum.upper - protected.value, 0.0),
    )


def _online_value(
    problem: Problem, budget: float, optimum: Attack
) -> tuple[OnlineAttack, str | None]:
    """The online attacker's value, budgeted within ``budget`` when it can be computed (else
    unlimited only, with the reason), checked against the offline optimum it must bound."""
    note = None
    try:
        online = online_attack_value(problem, budget)
    except ProblemError as error:
        note = error.reason
        online = online_attack_value(problem, None)
    # the online attacker sees more than the offline one: below it would contradict a theorem
    if online.unlimited_probability < optimum.value - tolerance.CERTIFY:
        raise SolverError(
            f"online value {online.unlimited_probability:.12f} below the offline value "
            f"{optimum.value:.12f}"
        )
    return online, note
