"""misdirect: optimal sensor deception for robots in POMDPs driven by finite-state controllers.

The library in a few names (the package layout: docs/architecture.md)::

    import misdirect

    problem = misdirect.scenarios.paper_grid(5)   # or misdirect.load_problem("model.yaml")
    report = misdirect.evaluate(problem, problem.alteration({"o1": "o3"}))
    result = misdirect.solve(problem, budgets=range(5))   # verified optimum + budget curve
    result.probability, result.status, [point.probability for point in result.curve]
"""

from misdirect import startup  # noqa: F401, I001 - first: Ctrl-C while the command imports
from misdirect import scenarios
from misdirect.core.attack import shared_preparation
from misdirect.core.evaluate import Evaluation, decoy_probability, evaluate
from misdirect.core.model import Alteration, Controller, CostModel, Pomdp, Problem
from misdirect.core.product import ProductChain, build_product
from misdirect.core.simulate import Simulation, simulate
from misdirect.defence import (
    AuditResult,
    HardenResult,
    OnlineAttack,
    audit,
    harden,
    RobustResult,
    online_attack_value,
    robust_controller,
)
from misdirect.errors import MisdirectError, OptionError, ProblemError, SolverError
from misdirect.io.exact_model import ExactModel, ExactValue, exact_model
from misdirect.io.model_problem import problem_from_model, with_controller
from misdirect.io.problem_file import load_problem, problem_from_dict, write_problem
from misdirect.solvers.base import ProgressCallback
from misdirect.solvers.deadline import CancelToken, Deadline
from misdirect.solvers.options import SolveOptions
from misdirect.solvers.run import BudgetResult, SolveResult, solve, solve_tradeoff
from misdirect.solvers.status import Status, StopReason

__version__ = "0.1.0"

__all__ = [
    "Alteration",
    "AuditResult",
    "BudgetResult",
    "CancelToken",
    "Controller",
    "CostModel",
    "Deadline",
    "Evaluation",
    "ExactModel",
    "ExactValue",
    "HardenResult",
    "MisdirectError",
    "OnlineAttack",
    "OptionError",
    "Pomdp",
    "Problem",
    "ProblemError",
    "ProductChain",
    "ProgressCallback",
    "RobustResult",
    "Simulation",
    "SolveOptions",
    "SolveResult",
    "SolverError",
    "Status",
    "StopReason",
    "audit",
    "build_product",
    "decoy_probability",
    "evaluate",
    "exact_model",
    "harden",
    "load_problem",
    "online_attack_value",
    "problem_from_dict",
    "problem_from_model",
    "robust_controller",
    "scenarios",
    "shared_preparation",
    "simulate",
    "solve",
    "solve_tradeoff",
    "with_controller",
    "write_problem",
]
