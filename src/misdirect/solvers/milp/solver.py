"""The MILP solver: build a formulation once, solve it for every budget, warm-starting each.

The model is built for the largest budget asked for; a smaller budget only lowers the bound of
the budget row, so every optimum is a valid start for the next (larger) budget. The first solve
starts from "alter nothing", which is always feasible, so a run stopped by the time limit still
has an incumbent to report.

The solver's claim for an alteration is its objective, or, when its point is more than 1e-9
from feasible (binaries off 0/1, rows violated, within its tolerances) or its objective more
than 1e-9 below its bound, the LP optimum with the binaries rounded: the tolerance would
otherwise leak into the claim (0.400001 for 0.4), and an incumbent whose probabilities are not
the largest for its alteration would look like a gap.

Statuses: ``optimal`` (the solver's bound meets its incumbent within 1e-9), ``gap_limit`` (it
stopped because the relative gap fell under ``--mip-gap``, with the bound further than that
from the incumbent), ``time_limit``.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, TypedDict

from misdirect.core.evaluate import decoy_probability
from misdirect.core.model import Problem
from misdirect.errors import ProblemError, SolverError
from misdirect.solvers.base import (
    CERTIFY_TOLERANCE,
    Deadline,
    ProgressCallback,
    Solution,
    Status,
    check_threads,
    check_time_limit,
    report,
)
from misdirect.solvers.milp import backends
from misdirect.solvers.milp.backends import BackendResult, SolverOptions, make_backend
from misdirect.solvers.milp.compact import build_compact
from misdirect.solvers.milp.model import MilpModel
from misdirect.solvers.milp.paper import build_paper

FORMULATIONS = {
    "compact": build_compact,
    "paper": build_paper,
    "paper-pinned": lambda problem, budget: build_paper(problem, budget, pin_unreachable=True),
}


def _check_formulation(formulation: str) -> None:
    if formulation not in FORMULATIONS:
        raise ProblemError(
            f"unknown formulation {formulation!r} (choose from {', '.join(FORMULATIONS)})",
            field="--formulation",
        )


def build_formulation(problem: Problem, formulation: str, budget: float | None = None) -> MilpModel:
    """The MILP of ``problem`` in the named formulation, budget row set to ``budget``."""
    _check_formulation(formulation)
    return FORMULATIONS[formulation](problem, budget)


GAP_TOLERANCE = 1e-9  # a bound this close to the incumbent counts as a proof of optimality
FEASIBILITY_SLACK = 1e-9  # a point further than this from feasible gets its claim recomputed


def _status(result: BackendResult, value: float | None) -> Status:
    """The backend's status, except that a solve it calls optimal while its bound lies more
    than 1e-9 above ``value`` (its incumbent's: the better of its objective and the claim) is
    ``gap_limit``, a stop because the gap fell under ``--mip-gap``: optimal means the bound
    meets the incumbent."""
    if (
        result.status == "optimal"
        and result.bound is not None
        and value is not None
        and result.bound - value > GAP_TOLERANCE * max(1.0, abs(result.bound)) + 1e-12
    ):
        return Status.GAP_LIMIT
    return Status(result.status)  # optimal or time_limit: checked by the caller


class MilpStats(TypedDict, total=False):
    """``stats`` of a MILP answer (the JSON's ``stats``): the model's size (``formulation``,
    ``variables``, ``binaries``, ``rows``, ``nonzeros``, ``build_time_s``, per-block counts),
    how the backend stopped, and what its point is worth exactly; plus the backend's own
    details."""

    formulation: str
    variables: int
    binaries: int
    rows: int
    nonzeros: int
    build_time_s: float
    variables_by_block: dict[str, int]
    rows_by_block: dict[str, int]
    solver: str
    solve_time_s: float
    status: str  # how the backend stopped; the point's status may be lower
    objective: float | None
    bound: float | None
    nodes: int | None
    claimed: float | None  # the objective, or its recomputation with rounded binaries
    violation: float  # how far the backend's point is from feasible
    exact: float  # the chain's value of the decoded alteration
    not_certified: str


class MilpSolver:
    name = "milp"
    curve_is_free = False

    def __init__(
        self,
        solver: str = "highs",
        formulation: str = "compact",
        time_limit: float | None = None,
        threads: int | None = None,
        mip_gap: float = 1e-9,
        verbose: bool = False,
    ):
        _check_formulation(formulation)
        check_time_limit(time_limit)
        if mip_gap is not None and not mip_gap >= 0:
            raise ProblemError(f"must be a non-negative number, got {mip_gap}", field="--mip-gap")
        check_threads(threads)
        self.backend_name = solver
        self.formulation = formulation
        self.options = SolverOptions(
            time_limit=time_limit, threads=threads, mip_gap=mip_gap, verbose=verbose
        )
        make_backend(solver, self.options)  # fail early on a missing backend

    def solve(
        self,
        problem: Problem,
        budgets: Sequence[float],
        *,
        progress: ProgressCallback | None = None,
        deadline: Deadline | None = None,
    ) -> list[Solution]:
        deadline = deadline or Deadline(self.options.time_limit)
        model = build_formulation(problem, self.formulation, max(budgets))
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
        backend.load(model)
        start = model.start_for(problem.identity())
        solutions = []
        relaxed: float | None = None
        for done, budget in enumerate(budgets, start=1):
            backend.set_row_upper(model.budget_row, budget)
            report(
                progress, done - 1, len(budgets), stage=f"milp ({backend.name}), budget {budget:g}"
            )
            result = backend.solve(start, time_limit=deadline.share(len(budgets) - done + 1))
            if result.status not in ("optimal", "time_limit", "infeasible"):
                raise SolverError(
                    f"{backend.name} stopped with status {result.detail} at budget {budget:g}"
                )
            violation = 0.0
            if result.values is None:
                if result.status == "infeasible":
                    raise SolverError(
                        f"the {self.formulation} MILP is infeasible at budget {budget:g}, "
                        "which cannot happen for a valid problem; please report it"
                    )
                # stopped before any incumbent: "alter nothing" is always feasible
                alteration, claimed = problem.identity(), None
            else:
                alteration = model.decode(result.values)
                claimed = result.objective
                violation = backends.violation(model, result.values)
                gapped = result.bound is not None and result.bound - claimed > GAP_TOLERANCE
                if violation > FEASIBILITY_SLACK or gapped:
                    # a point off by the solver's tolerances, or one whose continuous part is
                    # short of the best for its binaries: the formulation's own value for the
                    # decoded alteration is the LP with the binaries rounded
                    rounded = backends.value_with_rounded_binaries(model, result.values, budget)
                    claimed = claimed if rounded is None else rounded
                start = model.start_for(alteration)
            # the solver's objective carries its tolerances as its bound does; the claim may be
            # the better value of the same binaries
            incumbent = None if claimed is None else max(claimed, result.objective or claimed)
            status = stopped = _status(result, incumbent)
            upper_bound = (
                min(result.bound, problem.objective.max_value)
                if model.sound and result.bound is not None
                else None
            )
            exact = decoy_probability(problem, alteration)
            if upper_bound is None and model.sound and status != Status.OPTIMAL:
                # stopped before the solver had a bound: the MDP relaxation's is always proven
                # (computed once, at the largest budget, which bounds every smaller one)
                if relaxed is None:
                    from misdirect.solvers.branch_and_bound import relaxation_bound

                    relaxed = relaxation_bound(problem, max(budgets))
                upper_bound = max(relaxed, exact)
            not_certified = None
            if status == Status.OPTIMAL and (
                upper_bound is None or upper_bound - exact > CERTIFY_TOLERANCE
            ):
                # within the solver's tolerances, but not proven to 1e-9 for the alteration
                # it returns (its point may rely on rows or binaries off by 1e-6): not optimal
                status = Status.FEASIBLE
                not_certified = (
                    "the formulation proves no bound"
                    if upper_bound is None
                    else f"{backend.name} stopped as optimal with its bound {upper_bound:.12f}, "
                    f"{upper_bound - exact:.2e} above the exact value of its answer"
                )
            stats: MilpStats = {
                **model.stats(),
                "solver": backend.name,
                "solve_time_s": result.solve_time_s,
                "status": stopped,  # how the solver stopped; the point's status may be lower
                "objective": result.objective,
                "bound": result.bound,
                "nodes": result.nodes,
                "claimed": claimed,  # the objective, or its recomputation with rounded binaries
                "violation": violation,  # how far the solver's point is from feasible
                "exact": exact,  # the chain's value of the decoded alteration
                **({"not_certified": not_certified} if not_certified else {}),
                **result.detail,
            }
            solutions.append(
                Solution(
                    budget=budget,
                    alteration=alteration,
                    solver_probability=claimed,
                    status=status,
                    upper_bound=upper_bound,
                    stats=stats,
                )
            )
            report(progress, done, len(budgets), stage=f"milp ({backend.name})")
        return solutions
