"""MILP backends: HiGHS (default, embedded), Gurobi and SCIP (optional extras).

Each backend takes a :class:`MilpModel` in bulk (HiGHS ``passModel`` with the CSC arrays,
Gurobi ``addMVar``/``addMConstr``, SCIP by reading the MPS file HiGHS writes). Along a budget
curve the model is built once and only the budget row's bound changes between solves; each
solve accepts a start solution (the previous optimum).
"""

from __future__ import annotations

import math
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from misdirect.errors import ProblemError, SolverError
from misdirect.milp.model import MilpModel


@dataclass(frozen=True)
class SolverOptions:
    time_limit: float | None = None  # seconds per solve
    threads: int | None = None
    mip_gap: float = 1e-9  # relative; the default asks for a proven optimum
    verbose: bool = False


@dataclass
class BackendResult:
    status: str  # "optimal" | "time_limit" | "infeasible" | "error"
    values: np.ndarray | None  # incumbent column values, None if there is none
    objective: float | None
    bound: float | None  # proven upper bound on the objective
    nodes: int | None
    solve_time_s: float
    detail: dict[str, Any] = field(default_factory=dict)


class Backend(Protocol):
    name: str

    def load(self, model: MilpModel) -> None: ...

    def set_row_upper(self, row: int, value: float) -> None: ...

    def solve(self, start: tuple[np.ndarray, np.ndarray] | None) -> BackendResult: ...


class HighsBackend:
    """HiGHS through highspy. A fresh ``Highs`` instance per solve: passing the arrays again
    costs milliseconds and no state of an earlier solve can leak into the next."""

    name = "highs"

    def __init__(self, options: SolverOptions):
        import highspy

        self._highspy = highspy
        self.options = options
        self.model: MilpModel | None = None
        self.highs: Any = None

    def _fresh(self) -> Any:
        options = self.options
        highs = self._highspy.Highs()
        highs.setOptionValue("output_flag", bool(options.verbose))
        if options.time_limit is not None:
            highs.setOptionValue("time_limit", float(options.time_limit))
        if options.threads is not None:
            highs.setOptionValue("threads", int(options.threads))
        highs.setOptionValue("mip_rel_gap", float(options.mip_gap))
        highs.setOptionValue("mip_abs_gap", min(1e-9, float(options.mip_gap)))
        # Keep HiGHS' default feasibility tolerances: at 1e-9 its dual simplex recursed without
        # end (HEkkDualRHS::chooseNormal, stack overflow) on the 45x45 grid. Values are
        # re-evaluated exactly afterwards, so the tolerance never reaches a reported number.
        return highs

    def load(self, model: MilpModel) -> None:
        self.model = model

    def _pass(self, model: MilpModel) -> None:
        matrix = model.matrix.tocsc()
        status = self.highs.passModel(
            model.n_columns,
            model.n_rows,
            int(matrix.nnz),
            1,  # column-wise
            -1,  # maximise
            float(model.offset),
            model.objective.astype(np.float64),
            model.col_lower.astype(np.float64),
            model.col_upper.astype(np.float64),
            model.row_lower.astype(np.float64),
            model.row_upper.astype(np.float64),
            matrix.indptr.astype(np.int32),
            matrix.indices.astype(np.int32),
            matrix.data.astype(np.float64),
            model.integer.astype(np.int32),
        )
        if status == self._highspy.HighsStatus.kError:
            raise SolverError("HiGHS rejected the model (passModel failed)")

    def set_row_upper(self, row: int, value: float) -> None:
        assert self.model is not None
        self.model.row_upper[row] = value

    def write(self, path: Path) -> None:
        assert self.model is not None, "load() a model first"
        self.highs = self._fresh()
        self._pass(self.model)
        self.highs.writeModel(str(path))

    def solve(self, start: tuple[np.ndarray, np.ndarray] | None) -> BackendResult:
        hs = self._highspy
        assert self.model is not None, "load() a model first"
        self.highs = self._fresh()
        self._pass(self.model)
        if start is not None:
            columns, values = start
            self.highs.setSolution(
                int(columns.size), columns.astype(np.int32), values.astype(np.float64)
            )
        began = time.perf_counter()
        self.highs.run()
        elapsed = time.perf_counter() - began
        model_status = self.highs.getModelStatus()
        if model_status == hs.HighsModelStatus.kModelEmpty:  # nothing to choose: the offset
            offset = self.model.offset
            return BackendResult("optimal", np.zeros(0), offset, offset, 0, elapsed)
        info = self.highs.getInfo()
        has_incumbent = info.primal_solution_status == 2  # kSolutionStatusFeasible
        values = np.asarray(self.highs.getSolution().col_value) if has_incumbent else None
        status = {
            hs.HighsModelStatus.kOptimal: "optimal",
            hs.HighsModelStatus.kTimeLimit: "time_limit",
            hs.HighsModelStatus.kInterrupt: "time_limit",
            hs.HighsModelStatus.kInfeasible: "infeasible",
        }.get(model_status, "error")
        if not self.model.integer.any():  # a pure LP: its optimum is its bound
            bound = info.objective_function_value if status == "optimal" else None
        else:
            bound = info.mip_dual_bound if math.isfinite(info.mip_dual_bound) else None
        return BackendResult(
            status=status,
            values=values,
            objective=info.objective_function_value if has_incumbent else None,
            bound=bound,
            nodes=int(info.mip_node_count),
            solve_time_s=elapsed,
            detail={"highs_status": self.highs.modelStatusToString(model_status)},
        )


class GurobiBackend:
    name = "gurobi"

    def __init__(self, options: SolverOptions):
        try:
            import gurobipy as gp
        except ImportError:
            raise SolverError(
                "the Gurobi backend needs gurobipy: pip install 'misdirect[gurobi]' "
                "(and a Gurobi licence for models above the free size limit)"
            ) from None
        self.gp = gp
        self.options = options
        try:
            self.env = gp.Env(empty=True)
            self.env.setParam("OutputFlag", 1 if options.verbose else 0)
            self.env.start()
        except gp.GurobiError as error:
            raise SolverError(f"Gurobi could not start: {error}") from None

    def load(self, model: MilpModel) -> None:
        gp = self.gp
        try:
            self.model = gp.Model(env=self.env)
            m = self.model
            if self.options.time_limit is not None:
                m.Params.TimeLimit = self.options.time_limit
            if self.options.threads is not None:
                m.Params.Threads = self.options.threads
            m.Params.MIPGap = self.options.mip_gap
            vtype = np.where(model.integer, gp.GRB.BINARY, gp.GRB.CONTINUOUS)
            vtype[model.integer & (model.col_upper > 1)] = gp.GRB.INTEGER
            self.vars = m.addMVar(
                model.n_columns,
                lb=model.col_lower,
                ub=model.col_upper,
                vtype=vtype,
                obj=model.objective,
            )
            m.ObjCon = model.offset
            m.ModelSense = gp.GRB.MAXIMIZE
            self._rows: dict[int, Any] = {}
            lower, upper = model.row_lower, model.row_upper
            equal = lower == upper
            below = ~equal & np.isfinite(upper)
            above = ~equal & np.isfinite(lower)
            for mask, sense, rhs in ((equal, "=", upper), (below, "<", upper), (above, ">", lower)):
                rows = np.flatnonzero(mask)
                if rows.size:
                    constrs = m.addMConstr(model.matrix[rows], self.vars, sense, rhs[rows])
                    if sense == "<":
                        self._rows.update(zip(rows.tolist(), constrs.tolist(), strict=True))
            m.update()
        except gp.GurobiError as error:
            raise SolverError(f"Gurobi refused the model: {error}") from None

    def set_row_upper(self, row: int, value: float) -> None:
        self._rows[row].RHS = value

    def solve(self, start: tuple[np.ndarray, np.ndarray] | None) -> BackendResult:
        gp = self.gp
        m = self.model
        if start is not None:
            columns, values = start
            starts = np.full(m.NumVars, gp.GRB.UNDEFINED)
            starts[columns] = values
            self.vars.Start = starts
        began = time.perf_counter()
        try:
            m.optimize()
        except gp.GurobiError as error:
            raise SolverError(f"Gurobi failed: {error}") from None
        elapsed = time.perf_counter() - began
        status = {
            gp.GRB.OPTIMAL: "optimal",
            gp.GRB.TIME_LIMIT: "time_limit",
            gp.GRB.INTERRUPTED: "time_limit",
            gp.GRB.INFEASIBLE: "infeasible",
        }.get(m.Status, "error")
        has = m.SolCount > 0
        return BackendResult(
            status=status,
            values=np.asarray(self.vars.X) if has else None,
            objective=m.ObjVal if has else None,
            bound=m.ObjBound if status in ("optimal", "time_limit") else None,
            nodes=int(m.NodeCount),
            solve_time_s=elapsed,
            detail={"gurobi_status": int(m.Status)},
        )


class ScipBackend:
    name = "scip"

    def __init__(self, options: SolverOptions):
        try:
            import pyscipopt
        except ImportError:
            raise SolverError(
                "the SCIP backend needs pyscipopt: pip install 'misdirect[scip]'"
            ) from None
        self.pyscipopt = pyscipopt
        self.options = options

    def load(self, model: MilpModel) -> None:
        self.source = model
        self._budget_row = model.budget_row

    def set_row_upper(self, row: int, value: float) -> None:
        self.source.row_upper[row] = value

    def solve(self, start: tuple[np.ndarray, np.ndarray] | None) -> BackendResult:
        # SCIP reads the model from the MPS file HiGHS writes: a bulk path with no per-row calls
        with tempfile.TemporaryDirectory() as folder:
            path = Path(folder) / "model.mps"
            write_model(self.source, path)
            scip = self.pyscipopt.Model()
            scip.hideOutput(not self.options.verbose)
            scip.readProblem(str(path))
        if self.options.time_limit is not None:
            scip.setParam("limits/time", float(self.options.time_limit))
        scip.setParam("limits/gap", float(self.options.mip_gap))
        by_index = {int(v.name[1:]): v for v in scip.getVars()}
        variables = [by_index[i] for i in range(self.source.n_columns)]
        if start is not None:
            columns, values = start
            solution = scip.createPartialSol()
            for column, value in zip(columns.tolist(), values.tolist(), strict=True):
                scip.setSolVal(solution, variables[column], value)
            scip.addSol(solution)
        began = time.perf_counter()
        scip.optimize()
        elapsed = time.perf_counter() - began
        raw = scip.getStatus()
        status = {
            "optimal": "optimal",
            "timelimit": "time_limit",
            "userinterrupt": "time_limit",
            "infeasible": "infeasible",
            "gaplimit": "optimal",
        }.get(raw, "error")
        has = scip.getNSols() > 0
        best = scip.getBestSol() if has else None
        values = np.array([scip.getSolVal(best, v) for v in variables]) if has else None
        return BackendResult(
            status=status,
            values=values,
            objective=scip.getObjVal() if has else None,
            bound=scip.getDualbound(),
            nodes=int(scip.getNNodes()),
            solve_time_s=elapsed,
            detail={"scip_status": raw},
        )


BACKENDS: dict[str, type] = {"highs": HighsBackend, "gurobi": GurobiBackend, "scip": ScipBackend}


def make_backend(name: str, options: SolverOptions) -> Backend:
    if name not in BACKENDS:
        raise ProblemError(
            f"unknown solver {name!r} (choose from {', '.join(BACKENDS)})", field="--solver"
        )
    return BACKENDS[name](options)


def write_model(model: MilpModel, path: Path) -> None:
    """Write ``model`` as MPS or LP (by suffix) through HiGHS; columns are named c0, c1, …"""
    suffix = Path(path).suffix.lower()
    if suffix not in (".mps", ".lp"):
        raise ProblemError(
            f"cannot write {suffix or 'a file without suffix'}: use .mps or .lp", field="-o"
        )
    backend = HighsBackend(SolverOptions())
    backend.load(model)
    backend.write(Path(path))
