"""The MILP solver: build a formulation once, solve it for every budget, warm-starting each.

The model is built for the largest budget asked for; a smaller budget only lowers the bound of
the budget row, so every optimum is a valid start for the next (larger) budget. The first solve
starts from "alter nothing", which is always feasible, so a run stopped by the time limit still
has an incumbent to report.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from misdirect.errors import ProblemError, SolverError
from misdirect.milp.backends import SolverOptions, make_backend
from misdirect.milp.compact import build_compact
from misdirect.milp.model import MilpModel
from misdirect.milp.paper import build_paper
from misdirect.model import Problem
from misdirect.solvers.base import ProgressCallback, Solution

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
        for value, option in ((time_limit, "--time-limit"), (mip_gap, "--mip-gap")):
            if value is not None and not value >= 0:
                raise ProblemError(f"must be a non-negative number, got {value}", field=option)
        if threads is not None and threads < 1:
            raise ProblemError(f"must be at least 1, got {threads}", field="--threads")
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
    ) -> list[Solution]:
        model = build_formulation(problem, self.formulation, max(budgets))
        backend = make_backend(self.backend_name, self.options)
        try:
            return self._solve_curve(problem, model, backend, budgets, progress)
        finally:
            backend.close()

    def _solve_curve(
        self,
        problem: Problem,
        model: MilpModel,
        backend: Any,
        budgets: Sequence[float],
        progress: ProgressCallback | None,
    ) -> list[Solution]:
        backend.load(model)
        start = model.start_for(problem.identity())
        solutions = []
        for done, budget in enumerate(budgets, start=1):
            backend.set_row_upper(model.budget_row, budget)
            result = backend.solve(start)
            if result.status not in ("optimal", "time_limit", "infeasible"):
                raise SolverError(
                    f"{backend.name} stopped with status {result.detail} at budget {budget:g}"
                )
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
                start = model.start_for(alteration)
            stats: dict[str, Any] = {
                **model.stats(),
                "solver": backend.name,
                "solve_time_s": result.solve_time_s,
                "status": result.status,
                "objective": result.objective,
                "bound": result.bound,
                "nodes": result.nodes,
                **result.detail,
            }
            solutions.append(
                Solution(
                    budget=budget,
                    alteration=alteration,
                    claimed_probability=claimed,
                    status=result.status,
                    upper_bound=min(result.bound, 1.0)
                    if model.sound and result.bound is not None
                    else None,
                    stats=stats,
                )
            )
            if progress is not None:
                progress(done, len(budgets))
        return solutions
