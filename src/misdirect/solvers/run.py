"""Front door of the solvers: pick one, run it, and re-check every answer exactly.

Whatever the method, the probability reported for an alteration is the evaluator's, computed
from the product chain of that alteration; the solver's own number is kept only to detect
disagreement (SPEC §2: a solver can be wrong, the chain cannot).
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field, fields, replace
from typing import Any

import numpy as np

from misdirect.core.alterations import max_alteration_cost
from misdirect.core.evaluate import decoy_probability
from misdirect.core.model import Alteration, Problem
from misdirect.errors import ProblemError
from misdirect.solvers import get_solver
from misdirect.solvers.base import (
    CERTIFY_TOLERANCE,
    ProgressCallback,
    Status,
    clear_stop,
    stop_requested,
)

MISMATCH_TOLERANCE = 1e-6  # a solver claim this far from the exact value is "unverified"


@dataclass(frozen=True)
class BudgetResult:
    """The verified answer for one budget."""

    budget: float
    status: Status
    probability: float  # exact value of `alteration`
    alteration: dict[str, str]
    cost: float
    upper_bound: float | None
    solver_probability: float | None  # None when the solver stopped without an incumbent
    stats: dict[str, Any] = field(default_factory=dict)  # the method's own counters
    alteration_array: Alteration | None = field(default=None, repr=False)
    certified_by: str | None = None  # auto: the method whose answer (or bound) this is

    @property
    def gap(self) -> float | None:
        """Proven distance to the optimum, in probability (0 when solved to optimality)."""
        if self.upper_bound is None:
            return None
        return max(self.upper_bound - self.probability, 0.0)

    def to_dict(self) -> dict[str, Any]:
        """JSON fields: the dataclass's own (arrays and the solver's claim left out), the gap,
        and ``certified_by`` inside ``stats``, where the JSON has always had it."""
        skip = {"alteration_array", "solver_probability", "certified_by", "stats"}
        shown = {f.name: getattr(self, f.name) for f in fields(self) if f.name not in skip}
        extra = {} if self.certified_by is None else {"certified_by": self.certified_by}
        return {**shown, "gap": self.gap, "stats": {**self.stats, **extra}}


@dataclass(frozen=True)
class SolveResult:
    """The curve over every budget solved; the answer is its last point (the largest budget
    asked for), whose fields the result also offers directly."""

    problem: str
    method: str
    baseline_probability: float
    time_s: float
    curve: list[BudgetResult]
    warnings: list[str] = field(default_factory=list)
    # the largest budget asked for, when it exceeded the most expensive complete alteration:
    # the solvers then ran at that alteration's cost instead (every budget above it is equal)
    budget_clamped_from: float | None = None
    budget_clamped_to: float | None = None
    interrupted: bool = False  # stopped early on request (Ctrl-C): the best found so far
    # what `probability` measures: "probability" (of reaching the decoy), or
    # "expected_decoy_weight" with weighted decoy sets
    objective: str = "probability"

    @property
    def final(self) -> BudgetResult:
        return self.curve[-1]

    status = property(lambda self: self.final.status)
    probability = property(lambda self: self.final.probability)
    alteration = property(lambda self: self.final.alteration)
    alteration_array = property(lambda self: self.final.alteration_array)
    cost = property(lambda self: self.final.cost)
    budget = property(lambda self: self.final.budget)
    upper_bound = property(lambda self: self.final.upper_bound)
    stats = property(lambda self: self.final.stats)
    certified_by = property(lambda self: self.final.certified_by)

    def to_dict(self) -> dict[str, Any]:
        """The answer's fields (the last point's) at the top level, then the run's; clamping
        and interruption appear only when they happened."""
        final = self.final.to_dict()
        document = {
            "problem": self.problem,
            "status": final["status"],
            "objective": self.objective,
            **{k: final[k] for k in ("probability", "alteration", "cost", "budget")},
            "baseline_probability": self.baseline_probability,
            "upper_bound": final["upper_bound"],
            "gap": final["gap"],
            "method": self.method,
            "time_s": self.time_s,
            "curve": [point.to_dict() for point in self.curve],
            "stats": final["stats"],
            "warnings": self.warnings,
        }
        if self.budget_clamped_from is not None:
            document["budget_clamped_from"] = self.budget_clamped_from
            document["budget_clamped_to"] = self.budget_clamped_to
        if self.interrupted:
            document["interrupted"] = True
        return document


def default_budgets(budget: float) -> list[float]:
    """Every whole budget from 0 up to ``budget``, and ``budget`` itself."""
    whole = [float(b) for b in range(math.floor(budget + 1e-9) + 1)]
    return whole if math.isclose(whole[-1], budget) else [*whole, float(budget)]


def solve(
    problem: Problem,
    *,
    method: str = "auto",
    budgets: Sequence[float] | None = None,
    progress: ProgressCallback | None = None,
    **options: Any,
) -> SolveResult:
    """Optimal alteration for ``problem.budget`` (or for each of ``budgets``), verified exactly.

    A budget above the cost of the most expensive complete alteration affords everything, so
    the solvers run at that cost instead and its answer is reported at the budget asked for
    (``budget_clamped_from`` / ``budget_clamped_to`` say so): no method then enumerates or
    sweeps a range it cannot need (a budget of 1e9 is "no limit", not a billion budgets).
    """
    solver = get_solver(method, **options)
    cap = max_alteration_cost(problem)
    asked = problem.budget if budgets is None else max(map(float, budgets), default=0.0)
    clamped_from = asked if math.isfinite(asked) and asked > cap else None
    if budgets is None:
        whole = default_budgets(min(problem.budget, cap)) if solver.curve_is_free else []
        budgets = [*whole, problem.budget]
    budgets = sorted({float(b) for b in budgets})
    for b in budgets:
        if not math.isfinite(b) or b < 0:
            raise ProblemError(f"a budget must be a non-negative number, got {b}", field="budget")
    if problem.budget > cap:
        problem = problem.with_budget(cap)
    # each budget above the cap is answered by the cap's solution, reported at its own budget
    clamped = sorted({min(b, cap) for b in budgets})
    started = time.perf_counter()
    clear_stop()
    solutions = solver.solve(problem, clamped, progress=progress)
    interrupted = stop_requested()
    elapsed = time.perf_counter() - started
    if clamped_from is not None:
        by_budget = {solution.budget: solution for solution in solutions}
        solutions = [
            replace(by_budget[min(b, cap)], budget=b) if b > cap else by_budget[b] for b in budgets
        ]

    exact_values: dict[bytes, float] = {}  # a budget curve often repeats an alteration

    def exact_value(alpha: np.ndarray) -> float:
        key = alpha.tobytes()
        if key not in exact_values:
            exact_values[key] = decoy_probability(problem, alpha)
        return exact_values[key]

    curve, warnings = [], []
    for solution in solutions:
        alpha = np.asarray(solution.alteration, dtype=np.int64)
        problem.check_alteration(alpha, source=f"{solver.name} solver")
        exact = exact_value(alpha)
        cost = problem.alteration_cost(alpha)
        status = Status(solution.status)
        claimed = solution.solver_probability
        stats = dict(solution.stats)
        # An incumbent cut short (time or gap limit, node limit) may claim less than its
        # alteration is worth: its continuous part (or a MILP's witness columns) was not yet
        # pushed to the best for its choices. Only claiming more, or any mismatch at a proven
        # optimum, contradicts the chain.
        if (
            claimed is not None
            and abs(exact - claimed) > MISMATCH_TOLERANCE
            and not (status.cut_short and claimed < exact)
        ):
            status = Status.UNVERIFIED
            warnings.append(
                f"budget {solution.budget:g}: the {solver.name} solver claimed "
                f"{claimed:.9f} but the chain gives {exact:.9f}; the answer is not optimal "
                "as far as anyone can tell"
            )
        if cost > solution.budget + 1e-9:
            warnings.append(f"budget {solution.budget:g}: returned alteration costs {cost:g}")
        upper_bound = solution.upper_bound
        if upper_bound is not None and upper_bound < exact:
            # a bound below a value we hold in hand is solver tolerance, or a bug if it is large
            if exact - upper_bound > MISMATCH_TOLERANCE:
                status = Status.UNVERIFIED
                warnings.append(
                    f"budget {solution.budget:g}: the {solver.name} solver's bound "
                    f"{upper_bound:.9f} is below the exact value {exact:.9f}"
                )
            upper_bound = exact
        curve.append(
            _Point(
                solution.budget,
                status,
                exact,
                alpha,
                cost,
                upper_bound,
                claimed,
                stats,
                solution.certified_by,
            )
        )
    _make_monotone(curve)
    if interrupted:  # stopped by request (Ctrl-C), not by the time limit
        for point in curve:
            if point.status == Status.TIME_LIMIT:
                point.status = Status.INTERRUPTED
    return SolveResult(
        problem=problem.name,
        method=solver.name,
        baseline_probability=exact_value(np.asarray(problem.identity(), dtype=np.int64)),
        time_s=elapsed,
        curve=[point.result(problem) for point in curve],
        warnings=warnings,
        budget_clamped_from=clamped_from,
        budget_clamped_to=None if clamped_from is None else cap,
        interrupted=interrupted,
        objective=problem.objective.kind,
    )


@dataclass
class _Point:
    """One budget's answer while ``solve`` checks the curve as a whole."""

    budget: float
    status: Status
    probability: float
    alteration: np.ndarray
    cost: float
    upper_bound: float | None
    claimed: float | None
    stats: dict[str, Any]
    certified_by: str | None

    def result(self, problem: Problem) -> BudgetResult:
        return BudgetResult(
            budget=self.budget,
            status=self.status,
            probability=self.probability,
            alteration=problem.changed_observations(self.alteration),
            cost=self.cost,
            upper_bound=self.upper_bound,
            solver_probability=self.claimed,
            stats=self.stats,
            alteration_array=self.alteration,
            certified_by=self.certified_by,
        )


def _make_monotone(curve: list[_Point]) -> None:
    """What one budget's answer proves about the others, and "optimal" only when proven.

    * A larger budget can do whatever a smaller one can: a point worse than one at a smaller
      budget takes that alteration (a solver cut short may not have found it again).
    * An upper bound at a larger budget bounds every smaller one too.
    * ``optimal`` requires a proven bound within ``CERTIFY_TOLERANCE`` of the exact value of the
      alteration returned, whatever the method said; a point without one is ``feasible``, and a
      point whose bound (perhaps one from a larger budget) closes the gap becomes ``optimal``.
    """
    order = sorted(range(len(curve)), key=lambda j: curve[j].budget)
    best: _Point | None = None
    for j in order:
        point = curve[j]
        if best is not None and point.probability < best.probability - 1e-12:
            point.stats["replaced"] = (
                f"the solver's answer ({point.probability:.9f}) was worse than budget "
                f"{best.budget:g}'s, whose alteration it takes"
            )
            point.alteration, point.probability, point.cost = (
                best.alteration,
                best.probability,
                best.cost,
            )
            if point.upper_bound is not None:
                point.upper_bound = max(point.upper_bound, point.probability)
        if best is None or point.probability > best.probability:
            best = point
    bound: float | None = None
    for j in reversed(order):
        point = curve[j]
        if point.status == Status.UNVERIFIED:
            continue
        if bound is not None and (point.upper_bound is None or bound < point.upper_bound):
            point.upper_bound = max(bound, point.probability)
        if point.upper_bound is not None:
            bound = point.upper_bound
        certified = (
            point.upper_bound is not None
            and point.upper_bound - point.probability <= CERTIFY_TOLERANCE + 1e-12
        )
        if point.status == Status.OPTIMAL and not certified:
            point.stats["not_certified"] = (
                "no proven bound within 1e-9 of the exact value"
                if point.upper_bound is None
                else f"proven bound {point.upper_bound:.12f} is "
                f"{point.upper_bound - point.probability:.2e} above the exact value"
            )
            point.status = Status.FEASIBLE
        elif point.status.cut_short and certified:
            point.stats["certified_by_bound"] = "a bound at this or a larger budget meets it"
            point.status = Status.OPTIMAL
