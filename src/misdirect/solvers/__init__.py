"""The methods, by the name ``--method`` gives them, and the interface they share (``base``).

Every method only proposes alterations; :func:`misdirect.solvers.run.solve` runs one and
re-checks every answer exactly. ``auto`` picks among the others; ``milp`` holds the exact MILP.
"""

from __future__ import annotations

from typing import Any

from misdirect.errors import ProblemError
from misdirect.solvers.auto import AutoSolver
from misdirect.solvers.base import Solver
from misdirect.solvers.branch_and_bound import BranchAndBoundSolver
from misdirect.solvers.exhaustive import ExhaustiveSolver
from misdirect.solvers.incremental import IncrementalSolver
from misdirect.solvers.milp.solver import MilpSolver

SOLVERS: dict[str, type] = {
    "auto": AutoSolver,
    "branch-and-bound": BranchAndBoundSolver,
    "exhaustive": ExhaustiveSolver,
    "incremental": IncrementalSolver,
    "milp": MilpSolver,
}


def get_solver(method: str, **options: Any) -> Solver:
    try:
        return SOLVERS[method](**options)
    except KeyError:
        raise ProblemError(
            f"unknown method {method!r} (choose from {', '.join(SOLVERS)})", field="--method"
        ) from None
