"""misdirect: optimal sensor deception for robots in POMDPs driven by finite-state controllers.

The library in five names::

    problem = misdirect.load_problem("examples/tiny.yaml")   # or misdirect.scenarios.paper_grid(5)
    report = misdirect.evaluate(problem, problem.alteration({"o1": "o3"}))
    result = misdirect.solve(problem, method="exhaustive")   # verified optimum + budget curve
"""

from misdirect.defence import (
    AuditResult,
    HardenResult,
    OnlineAttack,
    audit,
    harden,
    online_attack_value,
)
from misdirect.errors import MisdirectError, ProblemError, SolverError
from misdirect.evaluate import Evaluation, decoy_probability, evaluate
from misdirect.model import Controller, CostModel, Pomdp, Problem
from misdirect.problem_file import load_problem, write_problem
from misdirect.product import ProductChain, build_product
from misdirect.solve import BudgetResult, SolveResult, solve
from misdirect.solvers.base import Status

__version__ = "0.1.0"

__all__ = [
    "AuditResult",
    "BudgetResult",
    "Controller",
    "CostModel",
    "Evaluation",
    "HardenResult",
    "MisdirectError",
    "OnlineAttack",
    "Pomdp",
    "Problem",
    "ProblemError",
    "ProductChain",
    "SolveResult",
    "SolverError",
    "Status",
    "audit",
    "build_product",
    "decoy_probability",
    "evaluate",
    "harden",
    "load_problem",
    "online_attack_value",
    "solve",
    "write_problem",
]
