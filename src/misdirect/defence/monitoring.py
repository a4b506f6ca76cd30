"""Add a monitor, or protect sensors? The defender's comparison on one table (issue 52).

A monitored problem (:func:`misdirect.core.monitor.with_monitor`) remembers the problem it
watches (:meth:`~misdirect.core.model.Problem.without_monitor`), so audit and harden can put,
at the attacker's budget ``B``, four certified optima side by side: with no defence, with the
monitor alone, with protected sensors alone, and with both. Each is a solve of its own
problem (or one the audit or the hardening already made); each row also says how often the
monitor raises the alarm under the attacker's reply, so the rows without the monitor show
what it would catch of the unconstrained attack.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from misdirect.core.evaluate import evaluate
from misdirect.core.model import Problem
from misdirect.defence.attack import Attack, protect, solve_many
from misdirect.defence.results import DefenceOption, MonitorComparison
from misdirect.solvers.deadline import Deadline
from misdirect.solvers.pool import TaskPool

NOTHING = "nothing"
MONITOR = "monitor"
PROTECTION = "protection"
BOTH = "monitor and protection"
DEFENCES = (NOTHING, MONITOR, PROTECTION, BOTH)


def split_monitor(problem: Problem) -> tuple[Problem, Problem | None]:
    """``(problem, the problem without its monitor)``; the first no longer carries the
    second (so that the many solves of an audit ship one problem, not two); None for a
    problem without a monitor."""
    if problem.unwatched is None:
        return problem, None
    plain = problem.without_monitor()
    from dataclasses import replace

    return replace(problem, unwatched=None), plain


def most_critical(
    plain: Problem,
    budget: float,
    optimum: Attack,
    clock: Deadline,
    method: str,
    pool: TaskPool | None = None,
) -> tuple[frozenset[int], dict[int, Attack]]:
    """The sensor whose protection lowers the attacker's optimum at ``budget`` the most (on
    ``plain``), among the sensors of its optimal attack ``optimum`` (protecting another one
    leaves that attack feasible: the optimum stands), and the re-solves made to find it."""
    sensors = sorted(optimum.changed)
    if not sensors:
        return frozenset(), {}
    found = solve_many([protect(plain, [o]) for o in sensors], budget, clock, method, pool=pool)
    names = plain.pomdp.observations
    solved = dict(zip(sensors, found, strict=True))
    best = min(sensors, key=lambda o: (solved[o].upper, solved[o].value, names[o]))
    return frozenset({best}), solved


def compare_defences(
    watched: Problem,
    plain: Problem,
    budget: float,
    *,
    protection: frozenset[int],
    both: frozenset[int] | None = None,
    costs: np.ndarray | None = None,
    known: Mapping[str, Attack] | None = None,
    why: str,
    clock: Deadline,
    method: str = "auto",
    pool: TaskPool | None = None,
) -> MonitorComparison:
    """The attacker's optimum at ``budget`` under each defence: nothing (``plain``), the
    monitor (``watched``), ``protection`` on ``plain``, and ``both`` (default: the same
    protection) on ``watched``.

    ``known`` holds the answers already solved, by defence (:data:`DEFENCES`); the others
    are solved here, sharing ``clock``. ``costs``: what protecting each sensor costs (default
    1 each); ``why`` says how the protection was chosen."""
    both = protection if both is None else both
    setups: dict[str, tuple[Problem, frozenset[int]]] = {
        NOTHING: (plain, frozenset()),
        MONITOR: (watched, frozenset()),
        PROTECTION: (plain, protection),
        BOTH: (watched, both),
    }
    answers = dict(known or {})
    missing = [d for d in DEFENCES if d not in answers]
    found = solve_many(
        [protect(setups[d][0], setups[d][1]) for d in missing], budget, clock, method, pool=pool
    )
    answers.update(zip(missing, found, strict=True))
    unit = np.ones(plain.pomdp.n_observations) if costs is None else costs
    names = plain.pomdp.observations
    monitor = watched.monitor or "monitor"
    rows = []
    for defence in DEFENCES:
        problem, protected = setups[defence]
        attack = answers[defence]
        rows.append(
            DefenceOption(
                defence=defence,
                monitor=monitor if problem is watched else None,
                protection=[names[o] for o in sorted(protected)],
                protection_cost=float(sum(float(unit[o]) for o in protected)),
                probability=attack.value,
                upper_bound=attack.upper,
                status=str(attack.status),
                alteration=attack.alteration,
                alarm_probability=_caught(watched, attack),
            )
        )
    return MonitorComparison(monitor=monitor, budget=budget, rows=rows, why=why)


def _caught(watched: Problem, attack: Attack) -> float:
    """Pr(the monitor raises the alarm) under the attacker's reply (the same alteration on
    the monitored problem: the observations are the same)."""
    alpha = attack.alteration_array
    report = evaluate(watched, watched.identity() if alpha is None else alpha)
    return float(report.alarm_probability or 0.0)


def protection_words(names: Sequence[str], protected: frozenset[int]) -> str:
    """The protected sensors, by name, in the problem's order."""
    return ", ".join(names[o] for o in sorted(protected)) or "nothing"
