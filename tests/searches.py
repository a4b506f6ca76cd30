"""Which budgets branch-and-bound searches, and in which order (tests of its schedule)."""

from __future__ import annotations

from misdirect.solvers.branch_and_bound import BranchAndBoundSolver


def count_searches(monkeypatch) -> list[float]:
    """The budgets branch-and-bound searches, in order, from now on."""
    searched: list[float] = []
    solve_budget = BranchAndBoundSolver._solve_budget

    def counted(self, curve, step, deadline, progress):
        searched.append(step.budget)
        return solve_budget(self, curve, step, deadline, progress)

    monkeypatch.setattr(BranchAndBoundSolver, "_solve_budget", counted)
    return searched
