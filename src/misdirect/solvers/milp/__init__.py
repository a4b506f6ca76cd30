"""The exact compact MILP (and the paper's formulation, for reproduction) on HiGHS, SCIP or
Gurobi: ``compact`` and ``paper`` build models, ``backends`` solve them, ``solver`` is the
method ``--method milp``."""

from misdirect.solvers.milp.solver import FORMULATIONS, MilpSolver, build_formulation

__all__ = ["FORMULATIONS", "MilpSolver", "build_formulation"]
