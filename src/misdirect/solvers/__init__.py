"""The methods, by the name ``method=`` (``--method``) gives them, and the interface they share.

Every method only proposes alterations; :func:`misdirect.solvers.run.solve` runs one and
certifies every answer exactly. Layers, bottom up: ``deadline``, ``status``, ``options``,
``base`` (the interface), ``certification`` (the one policy), ``engines/`` (the shared
machinery: relaxations, policy iteration, the low-rank enumeration, the searches), the methods
(``exhaustive``, ``incremental``, ``branch_and_bound``, ``milp/``), ``auto`` (a portfolio of
the methods: the one module that composes them), this registry, and ``run`` (the front door).
"""

from __future__ import annotations

from misdirect.errors import OptionError
from misdirect.solvers.auto import AutoSolver
from misdirect.solvers.base import Solver
from misdirect.solvers.branch_and_bound import BranchAndBoundSolver
from misdirect.solvers.exhaustive import ExhaustiveSolver
from misdirect.solvers.incremental import IncrementalSolver
from misdirect.solvers.milp.solver import MilpSolver
from misdirect.solvers.options import SolveOptions

SOLVERS: dict[str, type[Solver]] = {
    "auto": AutoSolver,
    "branch-and-bound": BranchAndBoundSolver,
    "exhaustive": ExhaustiveSolver,
    "incremental": IncrementalSolver,
    "milp": MilpSolver,
}


def get_solver(method: str, options: SolveOptions | None = None) -> Solver:
    """The method named ``method``, set up with ``options`` (each checked against what the
    method takes: an option it would ignore is an :class:`~misdirect.errors.OptionError`)."""
    if method not in SOLVERS:
        raise OptionError(
            f"unknown method {method!r} (choose from {', '.join(SOLVERS)})", parameter="method"
        )
    options = options or SolveOptions()
    solver_class = SOLVERS[method]
    options.check_taken_by(method, solver_class.accepts)
    return solver_class(options)  # type: ignore[call-arg]
