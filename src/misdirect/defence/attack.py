"""The attacker as the defender meets it: one solve at budget ``B`` under a protection set.

Audit and hardening both ask the same question many times — what is the attacker's optimum
if these sensors are protected? — under one shared clock, and both need the answer in the same
form: its exact value, a proven bound, and which sensors it alters. That question and its
answer live here, once. (Not to be confused with :mod:`misdirect.core.attack`, which prepares
the attacker's choices for the solvers.)
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from misdirect.core.alterations import alteration_space
from misdirect.core.model import Problem
from misdirect.errors import ProblemError
from misdirect.solvers.deadline import CancelToken, Deadline, call_deadline
from misdirect.solvers.options import check_time_limit
from misdirect.solvers.pool import TaskPool
from misdirect.solvers.run import BudgetResult, solve
from misdirect.solvers.status import Status


@dataclass(frozen=True)
class Attack:
    """The attacker's answer at budget B under one protection set."""

    value: float  # exact value of ``alteration``
    upper: float  # proven bound on the attacker's optimum (== value when certified)
    status: Status
    alteration: dict[str, str]
    changed: frozenset[int]
    cost: float
    # the alteration itself, to hand to the curve as evidence (not compared: an array)
    alteration_array: np.ndarray | None = field(default=None, compare=False, repr=False)
    error: float = 0.0  # proven bound on the error of ``value`` (inf: none proven)

    @property
    def certified(self) -> bool:
        return self.status == Status.OPTIMAL


def protect(problem: Problem, observations: Iterable[int]) -> Problem:
    """``problem`` with ``observations`` made unalterable as well (CostModel.protected)."""
    protected = problem.cost.protected | frozenset(int(o) for o in observations)
    return replace(problem, cost=replace(problem.cost, protected=protected))


def attack_of(point: BudgetResult, problem: Problem) -> Attack:
    """The solver's point as an :class:`Attack`: the sensors it alters, and a bound even when
    the method proved none."""
    alpha = point.alteration_array
    changed = (
        frozenset(int(o) for o in np.flatnonzero(alpha != problem.identity()))
        if alpha is not None
        else frozenset()
    )
    # no bound from the method: the largest decoy weight bounds every value (1 for a probability)
    upper = point.upper_bound if point.upper_bound is not None else problem.objective.max_value
    return Attack(
        value=point.probability,
        upper=max(upper, point.probability),
        status=point.status,
        alteration=point.alteration,
        changed=changed,
        cost=point.cost,
        alteration_array=alpha,
        error=math.inf if point.error_bound is None else point.error_bound,
    )


def shared_deadline(
    seconds: float | None, deadline: Deadline | None = None, cancel: CancelToken | None = None
) -> Deadline:
    """The wall-clock limit shared by every solve of one audit or hardening: ``seconds``
    from now, within the caller's ``deadline`` if given; cancelling ``cancel`` (default: the
    deadline's token) stops every one of its solves."""
    check_time_limit(seconds)
    return call_deadline(deadline, seconds, cancel)


def attacker_budget(problem: Problem, budget: float | None) -> float:
    """The attacker's budget ``B``: ``budget``, or the problem's own when None."""
    budget = problem.budget if budget is None else float(budget)
    if not (math.isfinite(budget) and budget >= 0):
        raise ProblemError(f"must be a non-negative number, got {budget}", field="budget")
    return budget


def solve_at(
    problem: Problem, budget: float, clock: Deadline, seconds: float | None, method: str = "auto"
) -> Attack:
    """The attacker's optimum at ``budget`` alone, within ``seconds`` (None: no limit; at
    least 50 ms, so that even a solve that starts late gets past its first incumbent), and
    cancelled with ``clock``."""
    limit = Deadline(None if seconds is None else max(seconds, 0.05), cancel=clock.cancel)
    result = solve(problem.with_budget(budget), method=method, budgets=[budget], deadline=limit)
    return attack_of(result.curve[-1], problem)


def alterable_sensors(problem: Problem, budget: float) -> list[int]:
    """Observations the attacker can alter within ``budget`` to something the controller
    reacts to differently (the others cannot change the outcome)."""
    return [int(c.observation) for c in alteration_space(problem.with_budget(budget)).choices]


def _solve_job(problem: Problem, budget: float, seconds: float | None, method: str) -> Attack:
    """One solve of :func:`solve_many`, where the pool runs it (no cancel token crosses a
    process: the time limit does)."""
    return solve_at(problem, budget, Deadline(None), seconds, method=method)


def solve_many(
    problems: Sequence[Problem],
    budget: float,
    clock: Deadline,
    method: str = "auto",
    *,
    pool: TaskPool | None = None,
    later: int = 0,
    unsolved: Callable[[], Attack] | None = None,
) -> list[Attack]:
    """:func:`solve_at` for each of ``problems``: one after another sharing ``clock`` (with
    ``later`` solves still to come after them), or all at once on ``pool``, each with the
    share of the time that a pool's width gives it. Each answer is the same either way when
    every solve finishes: a solve depends on its problem alone. ``unsolved``: the answer of a
    solve that ``clock`` has expired before (None: each still gets its 50 ms)."""
    n = len(problems)
    if unsolved is not None and clock.expired() and pool is not None:
        return [unsolved() for _ in problems]
    if pool is None:
        return [
            unsolved()
            if unsolved is not None and clock.expired()
            else solve_at(p, budget, clock, clock.share(n - k + later), method=method)
            for k, p in enumerate(problems)
        ]
    rounds = max(1, math.ceil((n + later) / pool.size))
    seconds = clock.share(rounds)
    tickets = {
        pool.submit(_solve_job, p, budget, seconds, method): k for k, p in enumerate(problems)
    }
    found: dict[int, Attack] = {}
    while pool.pending():
        ticket, attack, error = pool.next_done()
        if error is not None:
            raise error
        found[tickets[ticket]] = attack
    return [found[k] for k in range(n)]
