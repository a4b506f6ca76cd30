"""The MILP solver: build a formulation once, solve it for every budget, warm-starting each.

The model is built for the largest budget asked for; a smaller budget only lowers the bound of
the budget row, so every optimum is a valid start for the next (larger) budget. The first solve
starts from "alter nothing", which is always feasible, so a run stopped by the time limit still
has an incumbent to report.

The backend gets the model scaled (:func:`_scaled`): the objective divided by its largest
coefficient (the largest decoy weight) and the budget row by the largest cost, so that its
absolute tolerances (a feasibility of 1e-6, an absolute gap of 1e-9) do not swallow a problem
whose weights or costs are 1e-12; its numbers are scaled back before anyone reads them. Its
value columns are scaled too, each by a proven power-of-two bound on its state's value
(:mod:`misdirect.solvers.milp.scaling`, from the per-state relaxation's values): a decoy
behind a branch of 1e-10 otherwise leaves values of 1e-10 that HiGHS reads as 0. The budget
row's bound is the largest exact sum of costs within the budget
(:meth:`~misdirect.core.tolerance.CostScale.snap`), never the budget plus a slack.

The backend's bound proves the optimum only where the backend sees the whole model: where it
drops a coefficient (HiGHS' ``small_matrix_value``, 1e-9; SCIP gets the file HiGHS writes) or
cannot tell one from 0 within its feasibility tolerance, its bound moves with what it did not
see (0.9999999947 "proven" where 0.9999999988 was there), and the point gets the per-state
relaxation's proven bound instead, with the reason in its notes. Elsewhere the bound counts
raised by the gap the backend prunes with (:class:`~misdirect.solvers.milp.backends.Tolerances`,
read from the backend's options as set).

The solver's claim for an alteration is its objective, or, when its point is more than
:data:`~misdirect.core.tolerance.FEASIBILITY` from feasible (binaries off 0/1, rows violated,
within its tolerances) or its objective more than :data:`~misdirect.core.tolerance.CERTIFY`
(relative) below its bound, the LP optimum with the binaries rounded: the tolerance would
otherwise leak into the claim (0.400001 for 0.4), and an incumbent whose probabilities are not
the largest for its alteration would look like a gap.

How it stopped, normalised from the backend's own codes: ``optimal`` (the backend's bound meets
its incumbent within :data:`~misdirect.core.tolerance.CERTIFY`; it is asked for
:data:`~misdirect.core.tolerance.GAP`), ``gap_limit`` (it stopped because
the relative gap fell under ``mip_gap``, with the bound further than that from the incumbent),
``time_limit``. Whether the answer is optimal is decided by the front door, on the exact value
of the decoded alteration.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import Any, ClassVar

import numpy as np

from misdirect.core import tolerance
from misdirect.core.memory import check_memory
from misdirect.core.model import Problem
from misdirect.errors import OptionError, SolverError
from misdirect.solvers import schedule
from misdirect.solvers.base import ProgressCallback, Solution, method_deadline, report
from misdirect.solvers.deadline import Deadline
from misdirect.solvers.engines.alarm import alarm_constraint
from misdirect.solvers.engines.per_state import relaxation_bound, relaxation_values
from misdirect.solvers.milp import backends
from misdirect.solvers.milp.backends import (
    BackendResult,
    BackendStatus,
    SolverOptions,
    Tolerances,
    make_backend,
)
from misdirect.solvers.milp.compact import build_compact
from misdirect.solvers.milp.model import MilpModel
from misdirect.solvers.milp.paper import build_paper
from misdirect.solvers.options import SolveOptions
from misdirect.solvers.stats import MilpStats
from misdirect.solvers.status import Status, StopReason

# Bytes a backend takes per non-zero on top of the model (its copy, presolve, the LP's
# row-wise copy, factors): HiGHS took 254 on the paper's MILP of a 14x14 sensor grid; the lower
# figure refuses only what certainly cannot fit
SOLVER_BYTES_PER_NONZERO = 150

# the largest objective coefficient a backend gets, relative to the objective's largest one
MAX_OBJECTIVE_UNITS = 2.0**52

FORMULATIONS: dict[str, Callable[..., MilpModel]] = {
    "compact": build_compact,
    "paper": lambda problem, budget, state_values=None: build_paper(problem, budget),
    "paper-pinned": lambda problem, budget, state_values=None: build_paper(
        problem, budget, pin_unreachable=True, state_values=state_values
    ),
}


def _check_formulation(formulation: str) -> None:
    if formulation not in FORMULATIONS:
        raise OptionError(
            f"{formulation!r} is not one of {', '.join(FORMULATIONS)}",
            parameter="formulation",
        )


def build_formulation(
    problem: Problem,
    formulation: str,
    budget: float | None = None,
    state_values: np.ndarray | None = None,
    max_alarm: float | None = None,
) -> MilpModel:
    """The MILP of ``problem`` in the named formulation, budget row set to ``budget``; with
    ``state_values`` (the per-state relaxation's, :func:`relaxation_values`), its value columns
    scaled to about 1 (:mod:`misdirect.solvers.milp.scaling`)."""
    _check_formulation(formulation)
    if max_alarm is not None:  # the alarm's system: the compact formulation's alone
        if formulation != "compact":
            raise OptionError(
                f"max_alarm needs the compact formulation, not {formulation!r}",
                parameter="formulation",
            )
        return build_compact(problem, budget, state_values, max_alarm=max_alarm)
    return FORMULATIONS[formulation](problem, budget, state_values=state_values)


def scaled_formulation(
    problem: Problem,
    formulation: str,
    budget: float | None = None,
    deadline: Deadline | None = None,
    max_alarm: float | None = None,
) -> MilpModel:
    """The MILP of ``problem`` exactly as a backend gets it (budget row set to ``budget``,
    default the problem's): value columns scaled by the per-state relaxation's values, the
    objective and the budget row by their units (:func:`_scaled`). What ``export-milp``
    writes, so that another solver sees the numbers HiGHS sees, not a 1e-12 branch."""
    budget = problem.budget if budget is None else float(budget)
    relaxed, values = relaxation_values(problem, budget, deadline)
    if max_alarm is not None:
        # states that reach only the alarm are worth 0 to the decoy: no scale fits them
        values = None
    model = build_formulation(problem, formulation, budget, values, max_alarm)
    return _scaled(problem, model, relaxed)


def _status(result: BackendResult, value: float | None) -> Status:
    """The backend's status, except that a solve it calls optimal while its bound lies more
    than the gap tolerance above ``value`` (its incumbent's: the better of its objective and
    the claim) is ``gap_limit``, a stop because the gap fell under ``mip_gap``."""
    if (
        result.status == BackendStatus.OPTIMAL
        and result.bound is not None
        and value is not None
        and result.bound - value
        > tolerance.slack(result.bound, value, rel=tolerance.CERTIFY + tolerance.TIE)
    ):
        return Status.GAP_LIMIT
    return Status(result.status)  # optimal or time_limit: checked by the caller


class MilpSolver:
    name: ClassVar[str] = "milp"
    curve_is_free: ClassVar[bool] = False
    accepts: ClassVar[tuple[str, ...]] = (
        "time_limit",
        "threads",
        "solver",
        "formulation",
        "mip_gap",
        "verbose",
        "max_alarm",
    )

    def __init__(self, options: SolveOptions | None = None):
        options = options or SolveOptions()
        self.backend_name = options.solver or "highs"
        self.formulation = options.formulation or "compact"
        _check_formulation(self.formulation)
        self.options = SolverOptions(
            time_limit=options.time_limit,
            threads=options.threads,
            mip_gap=tolerance.GAP if options.mip_gap is None else options.mip_gap,
            verbose=bool(options.verbose),
        )
        make_backend(self.backend_name, self.options)  # fail early on a missing backend
        self.max_alarm = options.alarm_limit

    def solve(
        self,
        problem: Problem,
        budgets: Sequence[float],
        *,
        progress: ProgressCallback | None = None,
        deadline: Deadline | None = None,
    ) -> list[Solution]:
        deadline = method_deadline(deadline, self.options.time_limit)
        # the values' scale: the relaxation's bound on the optimum, and on every state's value,
        # at the largest budget (a decoy behind a branch of 1e-10 has values of 1e-10, below
        # HiGHS's tolerances), in the time the schedule gives it
        quick = schedule.milp_scale(deadline)
        if self.max_alarm is not None:  # the decoy's value over the space of both values
            problem = alarm_constraint(problem, self.max_alarm).decoy_problem
        model = scaled_formulation(problem, self.formulation, max(budgets), quick, self.max_alarm)
        backend = make_backend(self.backend_name, self.options)
        try:
            return self._solve_curve(problem, model, backend, budgets, progress, deadline)
        finally:
            backend.close()

    def _solve_curve(
        self,
        problem: Problem,
        model: MilpModel,
        backend: Any,
        budgets: Sequence[float],
        progress: ProgressCallback | None,
        deadline: Deadline,
    ) -> list[Solution]:
        check_memory(
            model.matrix.nnz * SOLVER_BYTES_PER_NONZERO,
            f"{backend.name} on the {model.formulation} MILP ({model.n_columns:,} variables, "
            f"{model.n_rows:,} rows, {model.matrix.nnz:,} non-zeros)",
            field="milp",
        )
        backend.load(model)
        tolerances = backend.tolerances()
        curve = _Curve(
            problem,
            model,
            budgets,
            start=model.start_for(problem.identity()),
            tolerances=tolerances,
            distrust=_distrust(backend.name, backend.handed(model), tolerances),
        )
        solutions = []
        for done, budget in enumerate(budgets, start=1):
            backend.set_row_upper(model.budget_row, _budget_row(problem, model, budget))
            stage = f"milp ({backend.name}), budget {budget:g}"
            report(progress, done - 1, len(budgets), stage=stage)
            if deadline.cancelled:  # stopped: the budgets left are not handed to the backend
                result = BackendResult(BackendStatus.TIME_LIMIT, None, None, None, None, 0.0)
            else:
                result = backend.solve(
                    curve.start,
                    time_limit=schedule.milp_budget(deadline, len(budgets) - done + 1),
                    cancel=deadline.cancel,
                )
                result = self._within_budget(
                    problem, model, backend, curve, budget, result, deadline
                )
            solutions.append(self._solution(curve, backend.name, budget, result, deadline))
            report(progress, done, len(budgets), stage=f"milp ({backend.name})")
        return solutions

    @staticmethod
    def _within_budget(
        problem: Problem,
        model: MilpModel,
        backend: Any,
        curve: _Curve,
        budget: float,
        result: BackendResult,
        deadline: Deadline,
    ) -> BackendResult:
        """``result``, or where the budget row admitted an alteration over the budget (costs
        whose float sums are no proof, :meth:`~misdirect.core.tolerance.CostScale.ambiguous`:
        the row lets every sum that fits pass, and a few more), the answer of a solve with the
        row at the sums that surely fit, with the first solve's bound (over the larger set)."""
        scale = problem.cost.scale
        if scale.decisive or result.values is None:
            return result
        if problem.cost.fits(model.decode(result.values), budget):
            return result  # the best of a larger set, and within the budget: the best
        sure = scale.snap(scale.sure_cap(budget)) / model.cost_unit
        backend.set_row_upper(model.budget_row, sure)
        inner: BackendResult = backend.solve(
            curve.start, time_limit=schedule.milp_budget(deadline, 1), cancel=deadline.cancel
        )
        backend.set_row_upper(model.budget_row, _budget_row(problem, model, budget))
        if inner.values is None:
            return replace(result, values=None, objective=None, status=BackendStatus.TIME_LIMIT)
        return replace(inner, bound=result.bound)

    def _solution(
        self, curve: _Curve, backend: str, budget: float, result: BackendResult, deadline: Deadline
    ) -> Solution:
        """One budget's answer from the backend's result: its alteration, the claim for it,
        how the backend stopped, and a proven bound where there is one."""
        problem, model = curve.problem, curve.model
        # a backend's zero may be -0.0 (a bound of an empty objective): the same number;
        # the scaled model's values are brought back to the problem's
        unit = model.value_unit
        result = replace(
            result,
            objective=None if result.objective is None else result.objective * unit + 0.0,
            bound=None if result.bound is None else result.bound * unit + 0.0,
        )
        if result.status not in (
            BackendStatus.OPTIMAL,
            BackendStatus.TIME_LIMIT,
            BackendStatus.INFEASIBLE,
        ):
            raise SolverError(f"{backend} stopped with status {result.detail} at budget {budget:g}")
        violation = 0.0
        if result.values is None:
            if result.status == BackendStatus.INFEASIBLE and self.max_alarm is not None:
                # no alteration within the budget keeps Pr(alarm) <= δ
                return Solution(
                    budget=budget,
                    alteration=problem.identity(),
                    solver_probability=None,
                    status=Status.INFEASIBLE,
                    stop_reason=StopReason.FINISHED,
                )
            if result.status == BackendStatus.INFEASIBLE:
                raise SolverError(
                    f"the {self.formulation} MILP is infeasible at budget {budget:g}, "
                    "which cannot happen for a valid problem; please report it"
                )
            # stopped before any incumbent: "alter nothing" is always feasible
            alteration, claimed = problem.identity(), None
        else:
            alteration = model.decode(result.values)
            violation = backends.violation(model, result.values)
            claimed = _claim(
                model, result, violation, _budget_row(problem, model, budget), deadline
            )
            curve.start = model.start_for(alteration)  # the next (larger) budget starts here
        # the solver's objective carries its tolerances as its bound does; the claim may be
        # the better value of the same binaries
        incumbent = None if claimed is None else max(claimed, result.objective or claimed)
        status = _status(result, incumbent)
        notes: dict[str, str] = {}
        upper_bound = None
        if model.sound and result.bound is not None:
            if curve.distrust is None:
                # raised by the gap the backend prunes with (in the scaled model's units)
                margin = curve.tolerances.margin(result.bound / unit) * unit
                upper_bound = min(result.bound + margin, problem.objective.max_value)
                if status == Status.GAP_LIMIT:
                    # the backend closed its gap within an absolute tolerance of its own
                    # (HiGHS prunes a node within its feasibility tolerance of the incumbent:
                    # 1e-6 on a value of 40): the per-state relaxation here may meet the claim
                    upper_bound = min(
                        upper_bound,
                        curve.relaxed_bound_at(budget, schedule.closing_bound(deadline)),
                    )
            else:
                # its bound is no proof: the per-state relaxation's at this budget is
                notes["bound_untrusted"] = curve.distrust
                upper_bound = curve.relaxed_bound_at(budget, schedule.closing_bound(deadline))
        if upper_bound is None and model.sound and status != Status.OPTIMAL:
            # stopped before the solver had a bound: the per-state relaxation's is proven
            upper_bound = curve.relaxed_bound(schedule.closing_bound(deadline))
        stats = MilpStats(
            model=model.stats(),
            solver=backend,
            solve_time_s=result.solve_time_s,
            status=status,
            objective=result.objective,
            bound=result.bound,
            nodes=result.nodes,
            claimed=claimed,
            violation=violation,
            backend=result.detail,
        )
        return Solution(
            budget=budget,
            alteration=alteration,
            solver_probability=claimed,
            status=status,
            upper_bound=upper_bound,
            stats=stats,
            notes=notes,
            stop_reason=StopReason.of(status, deadline.cancelled),
        )


@dataclass
class _Curve:
    """What one budget of a curve hands the next: the warm start, the relaxation's bound."""

    problem: Problem
    model: MilpModel
    budgets: Sequence[float]
    start: tuple[Any, Any]
    tolerances: Tolerances
    distrust: str | None = None  # why the backend's bound proves nothing here (None: it does)
    relaxed: float | None = None

    def relaxed_bound(self, deadline: Deadline) -> float:
        """The per-state relaxation at the largest budget (it bounds every smaller one),
        computed once (the trivial bound if ``deadline`` passes first)."""
        if self.relaxed is None:
            self.relaxed = relaxation_bound(self.problem, max(self.budgets), deadline)
        return self.relaxed

    def relaxed_bound_at(self, budget: float, deadline: Deadline) -> float:
        """The per-state relaxation at ``budget`` (tighter than at the largest budget), no
        more than the largest budget's when that is known."""
        bound = relaxation_bound(self.problem, budget, deadline)
        return bound if self.relaxed is None else min(bound, self.relaxed)


def _distrust(name: str, model: MilpModel, tolerances: Tolerances) -> str | None:
    """Why ``name``'s bound on ``model`` (as it receives it) is no proof, or None: it drops
    coefficients, or some are too small to move a row beyond its feasibility tolerance, so the
    model it solves is not the one built (a 1e-12 branch, a value 1e-9 from 1)."""
    dropped, blind = backends.blind_spots(model, tolerances)
    if not dropped and not blind:
        return None
    parts = []
    if dropped:
        parts.append(f"drops {dropped} coefficient(s) of at most {tolerances.drop:g}")
    if blind:
        parts.append(
            f"cannot see {blind} more within its feasibility tolerance {tolerances.feasibility:g}"
        )
    return f"{name} {' and '.join(parts)}, so its bound is not a proof"


def _claim(
    model: MilpModel, result: BackendResult, violation: float, row: float, deadline: Deadline
) -> float:
    """The solver's value for its alteration: its objective, or, for a point off by the
    solver's tolerances or one whose continuous part is short of the best for its binaries,
    the formulation's own value of the decoded alteration (the LP with the binaries rounded;
    ``row``: the budget row's bound in the scaled model)."""
    claimed = result.objective
    assert claimed is not None and result.values is not None
    gapped = result.bound is not None and result.bound - claimed > tolerance.slack(
        result.bound, claimed, rel=tolerance.CERTIFY
    )
    # a stop request skips the LP (a second solve), which has the closing grace at most once
    # the time is up (no limit without one); the claim is only checked, never reported
    grace = None if deadline.end is None else schedule.closing_bound(deadline).remaining()
    if (violation > tolerance.FEASIBILITY or gapped) and not deadline.cancelled and grace != 0.0:
        rounded = backends.value_with_rounded_binaries(model, result.values, row, grace)
        claimed = claimed if rounded is None else rounded * model.value_unit
    return claimed


def _scaled(problem: Problem, model: MilpModel, relaxed: float) -> MilpModel:
    """``model`` as the backend gets it: objective (and offset) divided by the value's scale
    (``relaxed``, a bound on the optimum, or else the largest objective coefficient), the
    budget row by the largest cost, so that both are about 1 whatever the problem's scale;
    the model keeps the two units (``value_unit``, ``cost_unit``)."""
    objective = np.abs(model.objective)
    largest = float(objective.max()) if objective.size else 0.0
    value_unit = _unit(min(largest, relaxed) if 0 < relaxed < np.inf else largest)
    # the value columns are scaled to their states' values (compact, paper-pinned), so the
    # objective's coefficients are about the optimum already; the paper's are 1 however small
    # the optimum: at most 2^52 (1 / 1e-300 would be infinite)
    value_unit = max(value_unit, _unit(largest) * MAX_OBJECTIVE_UNITS**-1)
    matrix = model.matrix.copy().tocsr()
    begin, end = matrix.indptr[model.budget_row], matrix.indptr[model.budget_row + 1]
    row = matrix.data[begin:end]
    finite = np.abs(row[np.isfinite(row)])
    cost_unit = _unit(float(finite.max()) if finite.size else 0.0)
    matrix.data[begin:end] = row / cost_unit  # divided, not multiplied: 1 / 5e-324 is inf
    lower, upper = model.row_lower.copy(), model.row_upper.copy()
    lower[model.budget_row] = lower[model.budget_row] / cost_unit
    upper[model.budget_row] = _row_bound(problem, upper[model.budget_row], cost_unit)
    return replace(
        model,
        objective=model.objective / value_unit,
        offset=model.offset / value_unit,
        matrix=matrix,
        row_lower=lower,
        row_upper=upper,
        value_unit=value_unit,
        cost_unit=cost_unit,
    )


def _unit(size: float) -> float:
    """The power of two nearest ``size`` where it is far from 1 (below 1/1024 or above 1024),
    else 1: dividing by a power of two is exact, and a model of normal scale goes to the
    backend as it was built."""
    if not size > 0 or not np.isfinite(size) or 2.0**-10 <= size <= 2.0**10:
        return 1.0
    return float(2.0 ** round(np.log2(size)))


def _row_bound(problem: Problem, budget: float, cost_unit: float) -> float:
    """The budget row's bound for ``budget``, divided by the cost unit: the largest exact sum
    of costs within the budget (no slack: the backend's own tolerance is its only one)."""
    scale = problem.cost.scale
    return scale.snap(scale.cap(budget)) / cost_unit


def _budget_row(problem: Problem, model: MilpModel, budget: float) -> float:
    return _row_bound(problem, budget, model.cost_unit)
