"""The baselines a robust controller is measured against (issue 54, docs/robust.md).

Each is a controller with its certified worst case at the same attacker budget (the oracle of
:mod:`misdirect.defence.robust_oracle`):

* **given**: the problem's own controller;
* **blind**: the best observation-blind controller (one action whatever it reads: nothing can
  alter what it does);
* **harden**: the given controller with the sensors :func:`misdirect.harden` protects when
  the defender may protect as many sensors as the attacker may alter (unit alteration costs
  only: otherwise the two budgets share no unit);
* **paynt**: PAYNT's nominally optimal controller (max Pr(goal), as many nodes as the robust
  class), where PAYNT is installed and finds one within :data:`PAYNT_SECONDS`.

A baseline that cannot be computed is skipped with its reason, never guessed.
"""

from __future__ import annotations

import math
import time
from collections.abc import Iterable
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from misdirect.core import tolerance
from misdirect.core.model import Controller, Problem
from misdirect.defence.robust_oracle import (
    goal_attack_problem,
    goal_states,
    memoryless_controller,
    objective_value,
    oracle,
)
from misdirect.errors import MisdirectError, ProblemError
from misdirect.solvers.deadline import Deadline

KINDS = ("given", "blind", "harden", "paynt")
HARDEN_SECONDS = 120.0  # harden's search for the protection baseline
PAYNT_SECONDS = 60.0  # PAYNT's synthesis of the nominal baseline, model build included
BASELINES_SHARE = 0.25  # of a robust run's time limit: every baseline together, at most
MIN_SEARCH_SECONDS = 0.1  # a search baseline (harden, PAYNT) given less than this is skipped


@dataclass(frozen=True)
class Baseline:
    """A reference controller and its certified worst case at the same budget."""

    name: str
    controller: Controller = field(repr=False)
    nominal: float  # the objective with no alteration
    worst_case: float  # exact value of the oracle's attack
    bound: float  # the oracle's proven bound on the worst case
    certified: bool
    alteration: dict[str, str]
    nominal_goal: float | None = None  # Pr(goal) with no alteration
    kind: str = ""  # one of KINDS
    protection: tuple[str, ...] | None = None  # harden: the sensors protected
    note: str | None = None  # how it was obtained, where that matters

    def to_dict(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "kind": self.kind,
            "nominal": self.nominal,
            "nominal_goal": self.nominal_goal,
            "worst_case": self.worst_case,
            "bound": self.bound,
            "certified": self.certified,
            "alteration": self.alteration,
            "protection": None if self.protection is None else list(self.protection),
            "note": self.note,
        }


@dataclass(frozen=True)
class Skipped:
    """A baseline not computed, and why."""

    kind: str
    reason: str

    def to_dict(self) -> dict[str, str]:
        return {"kind": self.kind, "reason": self.reason}


def blind_controllers(problem: Problem) -> list[Controller]:
    """One memoryless controller per action, playing it whatever it reads: no alteration can
    change what it does."""
    n_obs = problem.pomdp.n_observations
    zeros = np.zeros((1, n_obs), dtype=np.int64)
    return [
        memoryless_controller(problem, np.full((1, n_obs), a, dtype=np.int64), zeros)
        for a in range(problem.pomdp.n_actions)
    ]


def _shortfall(problem: Problem, controller: Controller, min_goal: float | None) -> float:
    """How far the nominal Pr(goal) of ``controller`` falls short of the floor (0 if none)."""
    if min_goal is None:
        return 0.0
    goal = objective_value(replace(problem, controller=controller), "goal", problem.identity())
    return max(min_goal - goal, 0.0)


def best_blind(problem: Problem, objective: str, min_goal: float | None = None) -> Controller:
    """The observation-blind controller with the best nominal value (= its worst case); among
    equals, the best in the other objective (decoy: the highest Pr(goal)). With a floor on
    Pr(goal), one meeting it first (or the one falling short the least)."""
    sense = 1.0 if objective == "decoy" else -1.0
    other = "goal" if objective == "decoy" else "decoy"

    def key(controller: Controller) -> tuple[float, float, float]:
        candidate = replace(problem, controller=controller)
        value = sense * objective_value(candidate, objective, problem.identity())
        short = round(_shortfall(problem, controller, min_goal), 12)
        return (
            short,
            round(value, 12),
            -sense * objective_value(candidate, other, problem.identity()),
        )

    return min(blind_controllers(problem), key=key)


def measured(
    name: str,
    kind: str,
    problem: Problem,
    controller: Controller,
    objective: str,
    budget: float,
    seconds: float | None = None,
    **extra: Any,
) -> Baseline:
    """``controller``'s certified worst case at ``budget`` on ``problem`` (which may have
    sensors protected), with its nominal values; its oracle's solve within ``seconds``
    (cut short: the best attack found and its bound, not certified)."""
    worst = oracle(problem, controller, objective, budget, seconds)
    candidate = replace(problem, controller=controller)
    return Baseline(
        name=name,
        controller=controller,
        nominal=objective_value(candidate, objective, problem.identity()),
        worst_case=worst.value,
        bound=worst.bound,
        certified=worst.certified,
        alteration=worst.changes,
        nominal_goal=objective_value(candidate, "goal", problem.identity()),
        kind=kind,
        **extra,
    )


def harden_budget(problem: Problem, budget: float) -> float | None:
    """The protection budget matching ``budget``: as many sensors as the attacker may alter
    (unit protection costs), when every change costs the same; None otherwise."""
    cost = problem.cost
    if cost.pairs or not (math.isfinite(cost.default) and cost.default > 0):
        return None
    return float(math.floor(budget / cost.default + tolerance.FEASIBILITY))


def hardened(
    problem: Problem, objective: str, budget: float, seconds: float | None = None
) -> Baseline | Skipped:
    """The given controller under ``harden``'s protection at the matching budget: harden's
    search and the oracle's solve within ``seconds`` together (harden at most
    :data:`HARDEN_SECONDS`)."""
    from misdirect.defence.attack import protect
    from misdirect.defence.hardening import harden

    d = harden_budget(problem, budget)
    if d is None:
        return Skipped(
            "harden",
            "alteration costs differ between changes: no protection budget matches the "
            "attacker's (compare with `misdirect harden` and your protection costs)",
        )
    # harden minimises the attacker's optimum; for goal, the attacker of Pr(non-goal end)
    target = problem if objective == "decoy" else goal_attack_problem(problem)
    searching = HARDEN_SECONDS if seconds is None else min(HARDEN_SECONDS, seconds / 2)
    began = time.perf_counter()
    plan = harden(target, protect_budget=d, budget=budget, time_limit=searching)
    left = None if seconds is None else max(seconds - (time.perf_counter() - began), 0.0)
    names = problem.pomdp.observations
    chosen = [names.index(name) for name in plan.protection]
    note = f"harden at D = {d:g} (one per sensor), {plan.status}"
    return measured(
        f"harden (protect {', '.join(plan.protection) or 'nothing'})",
        "harden",
        protect(problem, chosen),
        problem.controller,
        objective,
        budget,
        left,
        protection=tuple(plan.protection),
        note=note,
    )


def paynt_nominal(
    problem: Problem, objective: str, budget: float, memory: int, seconds: float | None = None
) -> Baseline | Skipped:
    """PAYNT's controller maximising the nominal Pr(goal), ``memory`` nodes: PAYNT and the
    oracle's solve within ``seconds`` together (PAYNT at most :data:`PAYNT_SECONDS`)."""
    synthesis = PAYNT_SECONDS if seconds is None else min(PAYNT_SECONDS, seconds / 2)
    began = time.perf_counter()
    try:
        from misdirect.io.paynt_synthesis import synthesize_problem

        found = synthesize_problem(problem, goal_states(problem), memory=memory, timeout=synthesis)
    except (ProblemError, MisdirectError) as error:
        return Skipped("paynt", str(error))
    note = f"PAYNT, Pmax=? [F goal], {memory} node(s), {found.synthesis.seconds:.1f} s"
    if found.undefined:
        note += (
            f"; {found.undefined} (node, reading) entries PAYNT left undefined play the first "
            "action and stay"
        )
    left = None if seconds is None else max(seconds - (time.perf_counter() - began), 0.0)
    return measured(
        "PAYNT nominal", "paynt", problem, found.controller, objective, budget, left, note=note
    )


def baselines(
    problem: Problem,
    objective: str,
    budget: float,
    memory: int,
    min_goal: float | None = None,
    kinds: Iterable[str] = KINDS,
    deadline: Deadline | None = None,
) -> tuple[tuple[Baseline, ...], tuple[Skipped, ...]]:
    """The baselines of ``kinds`` (in the order of :data:`KINDS`), and those skipped; with a
    ``deadline``, all of them within :data:`BASELINES_SHARE` of its time left, each within an
    even share of what is left of that (a baseline cut short is reported not certified)."""
    wanted = [kind for kind in KINDS if kind in set(kinds)]
    left = None if deadline is None else deadline.remaining()
    end = None if left is None else time.perf_counter() + BASELINES_SHARE * left

    def seconds(kind: str) -> float | None:
        """This baseline's share: what is left of the baselines' time, over those to go."""
        if end is None:
            return None
        return max(end - time.perf_counter(), 0.0) / (len(wanted) - wanted.index(kind))

    out: list[Baseline] = []
    skipped: list[Skipped] = []
    if "given" in wanted:
        out.append(
            measured(
                "given controller",
                "given",
                problem,
                problem.controller,
                objective,
                budget,
                seconds("given"),
            )
        )
    if "blind" in wanted:
        blind = best_blind(problem, objective, min_goal)
        out.append(
            measured(
                "observation-blind", "blind", problem, blind, objective, budget, seconds("blind")
            )
        )
    for kind, make in (
        ("harden", lambda: hardened(problem, objective, budget, seconds("harden"))),
        ("paynt", lambda: paynt_nominal(problem, objective, budget, memory, seconds("paynt"))),
    ):
        if kind not in wanted:
            continue
        share = seconds(kind)
        if share is not None and share < MIN_SEARCH_SECONDS:  # the ones before took it all
            skipped.append(
                Skipped(
                    kind,
                    f"no time left for it: the baselines take at most {BASELINES_SHARE:.0%} "
                    "of the time limit, and those before it used that share",
                )
            )
            continue
        got = make()
        if isinstance(got, Baseline):
            out.append(got)
        else:
            skipped.append(got)
    return tuple(out), tuple(skipped)


__all__ = [
    "KINDS",
    "Baseline",
    "Skipped",
    "baselines",
    "best_blind",
    "blind_controllers",
]
