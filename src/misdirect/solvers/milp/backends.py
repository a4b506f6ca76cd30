"""MILP backends: HiGHS (default, embedded), Gurobi and SCIP (optional extras).

Each backend takes a :class:`MilpModel` in bulk (HiGHS ``passModel`` with the CSC arrays,
Gurobi ``addMVar``/``addMConstr``, SCIP by reading the MPS file HiGHS writes). Along a budget
curve the model is built once and only the budget row's bound changes between solves; each
solve accepts a start solution (the previous optimum).
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import multiprocessing
import os
import signal
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from enum import StrEnum
from pathlib import Path
from typing import Any, Protocol, cast

import numpy as np
import scipy.sparse as sp

from misdirect.core import tolerance
from misdirect.errors import OptionError, ProblemError, SolverError, WriteError
from misdirect.solvers.deadline import CancelToken
from misdirect.solvers.milp.model import MilpModel

# A binary may sit this far from 0 or 1 in a Gurobi or SCIP answer. At their defaults (1e-5 in
# Gurobi, 1e-6 in SCIP) a binary at 1e-6 loosens a Bellman row by 1e-6, and the claimed value
# overshoots the exact value of the decoded alteration by that much (0.750002 for 0.75 on
# random_problem(5105) at budget 4 with SCIP), which marks a correct answer unverified. HiGHS
# keeps its default (1e-6): at 1e-9 its sub-MIP heuristic stalled at the root of the 15x15
# grid at budget 3 for the whole time limit. HiGHS reports the binaries rounded but leaves the
# rows that depend on them off by up to 1e-6 (0.400001 for 0.4 on random_problem(5380)). So,
# whatever the backend, a claim made at a point that is not feasible to 1e-9 is recomputed as
# the LP with the binaries rounded (``violation``, ``value_with_rounded_binaries``).
INTEGRALITY_TOLERANCE = tolerance.INTEGRALITY
# HiGHS 1.14.0's MIP presolve has reported bugs that return a wrong point as "optimal"
# (ERGO-Code/HiGHS#3073, #3094; fixed in 1.15, which this package cannot use yet). On these
# models it hits random_problem(5561) at budget 1 (0.5 where the optimum is 0.513430) through
# its doubleton-equation rule (the one-target rows), so that rule is switched off (bit 9).
# Switching presolve off altogether is worse: then HiGHS' root cuts cut off the optimum of
# random_problem(5269) at budget 2. Both are regression tests in tests/test_milp.py.
HIGHS_PRESOLVE_RULES_OFF = 1 << 9
# HiGHS checks its clock only now and then; the parent stops a worker still running this long
# after the limit (10 % + 1 s keeps a whole command within 10 % + 2 s of its limit)
STOP_POLL_S = 0.1  # how often a waiting parent looks for a stop request
HIGHS_GRACE_FACTOR = 1.1
HIGHS_GRACE_S = 1.0


@dataclass(frozen=True)
class SolverOptions:
    time_limit: float | None = None  # seconds per solve
    threads: int | None = None
    mip_gap: float = tolerance.GAP  # relative; the default asks for a proven optimum
    verbose: bool = False


@dataclass(frozen=True)
class Tolerances:
    """What a backend cannot see, read from the options it is actually given (never assumed):
    its bound proves the optimum only where none of these hides part of the model."""

    drop: float  # a coefficient this small or smaller is dropped: the backend reads it as 0
    feasibility: float  # rows hold only to within this (absolute, in the rows as handed)
    rel_gap: float  # it stops, and prunes nodes, once a bound is this close (relative) ...
    abs_gap: float  # ... or this close (absolute) to the incumbent

    def margin(self, bound: float) -> float:
        """How far below the optimum a bound of ``bound`` may lie because of the gap the
        backend prunes with (HiGHS reports the incumbent as its bound once every node left is
        within the gap of it): what the bound is raised by before it counts."""
        return max(self.abs_gap, self.rel_gap * abs(bound))


def blind_spots(model: MilpModel, tolerances: Tolerances) -> tuple[int, int]:
    """How many non-zero coefficients of ``model`` (as the backend gets it) the backend drops
    (at most ``drop``), and how many more it cannot tell from 0 within its feasibility
    tolerance (the coefficient times its column's range at most ``feasibility``: such a term
    moves its row by less than the row is allowed to be off). A model with either has a
    different optimum as far as the backend can see, so its bound is no proof."""
    matrix = model.matrix.tocsr()
    size = np.abs(matrix.data)
    width = (model.col_upper - model.col_lower)[matrix.indices]
    present = size > 0
    dropped = present & (size <= tolerances.drop)
    with np.errstate(invalid="ignore"):  # 0 x inf: an empty column range (fixed column)
        reach = np.where(np.isfinite(width), size * width, np.inf)
    blind = present & ~dropped & (reach <= tolerances.feasibility) & (width > 0)
    return int(dropped.sum()), int(blind.sum())


def _highs_option(highs: Any, name: str) -> float:
    """An option of a Highs instance (highspy returns ``(status, value)`` before 1.8)."""
    value = highs.getOptionValue(name)
    return float(value[1] if isinstance(value, tuple) else value)


class BackendStatus(StrEnum):
    """How a backend stopped, its own codes normalised at the boundary (each backend's table
    below; the code itself stays in :attr:`BackendResult.detail`). A ``str``: the same words
    as before in JSON and messages."""

    OPTIMAL = "optimal"  # proven, or stopped at its gap (MilpSolver tells which by the bound)
    TIME_LIMIT = "time_limit"  # out of time, or stopped on request
    INFEASIBLE = "infeasible"
    ERROR = "error"  # anything else


@dataclass
class BackendResult:
    status: BackendStatus
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

    def tolerances(self) -> Tolerances:
        """What this backend, with its options, cannot see."""
        ...

    def handed(self, model: MilpModel) -> MilpModel:
        """``model`` as this backend receives it (the rows SCIP gets are unscaled)."""
        ...

    def solve(
        self,
        start: tuple[np.ndarray, np.ndarray] | None,
        time_limit: float | None = None,
        cancel: CancelToken | None = None,
    ) -> BackendResult:
        """One solve from ``start``; ``time_limit`` (seconds) overrides the options'; a
        backend that runs elsewhere (HiGHS' worker) stops when ``cancel`` is cancelled."""
        ...

    def close(self) -> None: ...


class HighsBackend:
    """HiGHS through highspy, run in a worker process.

    HiGHS has crashed this process outright (a segmentation fault: unbounded recursion in its
    dual simplex, ``HEkkDualRHS::chooseNormal``) on budget curves of the larger grids, which
    would take the user's session with it. So the model lives in a forked worker: a crash
    costs a restart and a retry with another random seed, and a second crash becomes a clear
    error instead of a dead interpreter. Each solve uses a fresh ``Highs`` instance, so no state
    of an earlier solve leaks into the next.
    """

    name = "highs"
    retries = 2

    def __init__(self, options: SolverOptions):
        import highspy  # noqa: F401  (fail here, in the parent, if it is missing)

        self.options = options
        self.model: MilpModel | None = None
        self.crashes = 0
        self._worker: Any = None
        self._conn: Any = None

    def load(self, model: MilpModel) -> None:
        self.model = model
        self._stop_worker()

    def set_row_upper(self, row: int, value: float) -> None:
        assert self.model is not None, "load() a model first"
        self.model.row_upper[row] = value

    def tolerances(self) -> Tolerances:
        return highs_tolerances(self.options)

    def handed(self, model: MilpModel) -> MilpModel:
        return model

    def write(self, path: Path) -> None:
        assert self.model is not None, "load() a model first"
        import highspy

        highs = _new_highs(self.options, seed=0)
        _pass_model(highs, _model_arrays(self.model))
        if highs.writeModel(str(path)) == highspy.HighsStatus.kError or not Path(path).is_file():
            raise SolverError(f"HiGHS could not write {path}")
        # HiGHS does not check its writes: on a full disk it reports success for a cut-off
        # file, which must not replace a complete one. Both formats end in a last keyword.
        with open(path, "rb") as handle:
            handle.seek(max(handle.seek(0, os.SEEK_END) - 64, 0))
            tail = handle.read().split()
        if not tail or tail[-1].lower() not in (b"endata", b"end"):
            raise WriteError(f"cannot write {path}: HiGHS wrote an incomplete file (disk full?)")

    def solve(
        self,
        start: tuple[np.ndarray, np.ndarray] | None,
        time_limit: float | None = None,
        cancel: CancelToken | None = None,
    ) -> BackendResult:
        assert self.model is not None, "load() a model first"
        row = self.model.budget_row
        limit = self.options.time_limit if time_limit is None else time_limit
        code = None
        began = time.perf_counter()
        for attempt in range(self.retries):
            try:
                if self._worker is None:
                    self._start_worker()
                message = ("solve", row, float(self.model.row_upper[row]), start, attempt, limit)
                self._conn.send(message)
                # HiGHS overshoots its own limit (seconds, on large models): past the limit
                # and a grace period the worker is stopped and the solve counts as timed out
                grace = None if limit is None else limit * HIGHS_GRACE_FACTOR + HIGHS_GRACE_S
                if not self._answered(grace, cancel):
                    self._stop_worker(kill=True)
                    return BackendResult(
                        BackendStatus.TIME_LIMIT,
                        None,
                        None,
                        None,
                        None,
                        time.perf_counter() - began,
                        detail={"highs_status": "stopped at the time limit"},
                    )
                kind, payload = self._conn.recv()
            except KeyboardInterrupt:  # Ctrl-C or SIGTERM: stop HiGHS now, not after its solve
                self._stop_worker(kill=True)
                raise
            except (EOFError, OSError):
                code = getattr(self._worker, "exitcode", None)
                self._stop_worker()
                self.crashes += 1
                continue
            if kind == "error":
                raise SolverError(payload)
            payload.detail["highs_crashes"] = self.crashes
            return cast(BackendResult, payload)
        raise SolverError(
            f"HiGHS crashed {self.retries} times on this model (worker exit code {code}); "
            'try another backend: solver="scip" or solver="gurobi"'
        )

    def close(self) -> None:
        self._stop_worker()

    def _answered(self, seconds: float | None, cancel: CancelToken | None) -> bool:
        """Wait up to ``seconds`` (forever: None) for the worker's answer, in short slices so
        that a cancellation (Ctrl-C in the CLI) is seen within a fraction of a second."""
        end = None if seconds is None else time.perf_counter() + seconds
        while not self._conn.poll(STOP_POLL_S):
            cancelled = cancel is not None and cancel.cancelled
            if cancelled or (end is not None and time.perf_counter() >= end):
                return False
        return True

    def _start_worker(self) -> None:
        assert self.model is not None
        methods = multiprocessing.get_all_start_methods()
        context = (
            multiprocessing.get_context("fork")
            if "fork" in methods
            else multiprocessing.get_context("spawn")
        )
        self._conn, child = context.Pipe()
        if multiprocessing.current_process().daemon:
            # A daemonic process (a multiprocessing.Pool worker) may not have children: solve
            # in a thread of this process instead, without the protection against a crash.
            self._worker = threading.Thread(
                target=_highs_worker, args=(child, self.options), daemon=True
            )
        else:
            self._worker = context.Process(
                target=_highs_worker, args=(child, self.options), daemon=True
            )
        try:
            self._worker.start()
        except BaseException:
            self._worker = None
            raise
        if isinstance(self._worker, multiprocessing.process.BaseProcess):
            child.close()
        self._conn.send(("load", _model_arrays(self.model)))
        kind, payload = self._conn.recv()
        if kind == "error":
            raise SolverError(payload)

    def _stop_worker(self, kill: bool = False) -> None:
        if self._worker is not None:
            if kill and hasattr(self._worker, "kill"):
                self._worker.kill()
            with contextlib.suppress(OSError):
                self._conn.send(("stop",))
            self._worker.join(timeout=0.5 if kill else 5)
            if self._worker.is_alive() and hasattr(self._worker, "kill"):
                self._worker.kill()
            self._conn.close()
        self._worker = self._conn = None

    def __del__(self) -> None:
        self._stop_worker()


def _model_arrays(model: MilpModel) -> dict[str, Any]:
    """The model as plain arrays (what crosses the pipe; the callables stay behind)."""
    matrix = model.matrix.tocsc()
    return {
        "n_columns": model.n_columns,
        "n_rows": model.n_rows,
        "offset": float(model.offset),
        "objective": model.objective.astype(np.float64),
        "col_lower": model.col_lower.astype(np.float64),
        "col_upper": model.col_upper.astype(np.float64),
        "row_lower": model.row_lower.astype(np.float64),
        "row_upper": model.row_upper.astype(np.float64).copy(),
        "indptr": matrix.indptr.astype(np.int32),
        "indices": matrix.indices.astype(np.int32),
        "data": matrix.data.astype(np.float64),
        "integer": model.integer.astype(np.int32),
    }


def _new_highs(options: SolverOptions, seed: int) -> Any:
    import highspy

    highs = highspy.Highs()
    highs.setOptionValue("output_flag", bool(options.verbose))
    if options.time_limit is not None:
        highs.setOptionValue("time_limit", float(options.time_limit))
    if options.threads is not None:
        highs.setOptionValue("threads", int(options.threads))
    highs.setOptionValue("mip_rel_gap", float(options.mip_gap))
    highs.setOptionValue("mip_abs_gap", 0.0)  # relative only: see tolerance.GAP
    highs.setOptionValue("random_seed", int(seed))
    highs.setOptionValue("presolve_rule_off", HIGHS_PRESOLVE_RULES_OFF)
    # HiGHS' default feasibility tolerances: at 1e-9 its dual simplex crashed sooner, and at an
    # integrality tolerance of 1e-9 it stalled (see INTEGRALITY_TOLERANCE). Values are
    # re-evaluated exactly afterwards, so the tolerance never reaches a reported number.
    return highs


def highs_tolerances(options: SolverOptions) -> Tolerances:
    """HiGHS' tolerances as set for a solve: ``small_matrix_value`` (passModel drops smaller
    entries, also from the files it writes), the larger of its LP and MIP feasibility
    tolerances (the MIP checks rows against the latter), its gaps."""
    highs = _new_highs(options, seed=0)
    return Tolerances(
        drop=_highs_option(highs, "small_matrix_value"),
        feasibility=max(
            _highs_option(highs, "primal_feasibility_tolerance"),
            _highs_option(highs, "mip_feasibility_tolerance"),
        ),
        rel_gap=_highs_option(highs, "mip_rel_gap"),
        abs_gap=_highs_option(highs, "mip_abs_gap"),
    )


def _pass_model(highs: Any, arrays: dict[str, Any]) -> None:
    import highspy

    status = highs.passModel(
        arrays["n_columns"],
        arrays["n_rows"],
        int(arrays["data"].size),
        1,  # column-wise
        -1,  # maximise
        arrays["offset"],
        arrays["objective"],
        arrays["col_lower"],
        arrays["col_upper"],
        arrays["row_lower"],
        arrays["row_upper"],
        arrays["indptr"],
        arrays["indices"],
        arrays["data"],
        arrays["integer"],
    )
    if status == highspy.HighsStatus.kError:
        raise SolverError("HiGHS rejected the model (passModel failed)")


def run_highs(
    arrays: dict[str, Any],
    options: SolverOptions,
    start: tuple[np.ndarray, np.ndarray] | None,
    seed: int = 0,
) -> BackendResult:
    """One solve in this process (the worker's body; also usable directly)."""
    import highspy as hs

    highs = _new_highs(options, seed)
    _pass_model(highs, arrays)
    values: np.ndarray | None  # the start's, then the answer's
    if start is not None:
        columns, values = start
        highs.setSolution(int(columns.size), columns.astype(np.int32), values.astype(np.float64))
    began = time.perf_counter()
    highs.run()
    elapsed = time.perf_counter() - began
    model_status = highs.getModelStatus()
    if model_status == hs.HighsModelStatus.kModelEmpty:  # nothing to choose: the offset
        offset = arrays["offset"]
        return BackendResult(BackendStatus.OPTIMAL, np.zeros(0), offset, offset, 0, elapsed)
    info = highs.getInfo()
    has_incumbent = info.primal_solution_status == 2  # kSolutionStatusFeasible
    values = np.asarray(highs.getSolution().col_value) if has_incumbent else None
    status = {
        hs.HighsModelStatus.kOptimal: BackendStatus.OPTIMAL,
        hs.HighsModelStatus.kTimeLimit: BackendStatus.TIME_LIMIT,
        hs.HighsModelStatus.kInterrupt: BackendStatus.TIME_LIMIT,
        hs.HighsModelStatus.kInfeasible: BackendStatus.INFEASIBLE,
    }.get(model_status, BackendStatus.ERROR)
    if not arrays["integer"].any():  # a pure LP: its optimum is its bound
        bound = info.objective_function_value if status == BackendStatus.OPTIMAL else None
    else:
        bound = info.mip_dual_bound if math.isfinite(info.mip_dual_bound) else None
    return BackendResult(
        status=status,
        values=values,
        objective=info.objective_function_value if has_incumbent else None,
        bound=bound,
        nodes=int(info.mip_node_count),
        solve_time_s=elapsed,
        detail={"highs_status": highs.modelStatusToString(model_status)},
    )


def _highs_worker(conn: Any, options: SolverOptions) -> None:
    """Serve solves over a pipe until told to stop (or the parent goes away)."""
    if threading.current_thread() is threading.main_thread():
        # Ctrl-C reaches the whole process group: the parent handles it and kills this worker,
        # which must not print a KeyboardInterrupt traceback of its own (nor run the parent's
        # SIGTERM handler, inherited through fork)
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        signal.signal(signal.SIGTERM, signal.SIG_DFL)
        _die_with_parent()
    arrays: dict[str, Any] = {}
    while True:
        try:
            message = conn.recv()
        except (EOFError, OSError):
            return
        if message[0] == "stop":
            return
        try:
            if message[0] == "load":
                arrays = message[1]
                conn.send(("ok", None))
            else:
                _, row, value, start, seed, limit = message
                arrays["row_upper"][row] = value
                timed = dataclasses.replace(options, time_limit=limit)
                conn.send(("result", run_highs(arrays, timed, start, seed)))
        except SolverError as error:
            conn.send(("error", str(error)))


def _die_with_parent() -> None:
    """On Linux, have the kernel kill this worker when its parent dies, however it dies (a
    hard exit after a signal, SIGKILL): HiGHS, busy in a solve, would not notice the pipe
    close until its own time limit."""
    if sys.platform.startswith("linux"):
        with contextlib.suppress(Exception):
            import ctypes

            ctypes.CDLL(None).prctl(1, int(signal.SIGKILL))  # PR_SET_PDEATHSIG


# Gurobi reads a matrix coefficient below this as 0 (its documentation's "tiny" coefficients)
GUROBI_TINY = 1e-13


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
            if self.options.threads is not None:
                m.Params.Threads = self.options.threads
            m.Params.MIPGap = self.options.mip_gap
            m.Params.IntFeasTol = INTEGRALITY_TOLERANCE
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

    def tolerances(self) -> Tolerances:
        probe = self.gp.Model(env=self.env)
        try:
            probe.Params.MIPGap = self.options.mip_gap
            return Tolerances(
                drop=GUROBI_TINY,
                feasibility=float(probe.Params.FeasibilityTol),
                rel_gap=float(probe.Params.MIPGap),
                abs_gap=float(probe.Params.MIPGapAbs),
            )
        finally:
            probe.dispose()

    def handed(self, model: MilpModel) -> MilpModel:
        return model

    def close(self) -> None:
        if getattr(self, "model", None) is not None:
            self.model.dispose()
        self.env.dispose()

    def solve(
        self,
        start: tuple[np.ndarray, np.ndarray] | None,
        time_limit: float | None = None,
        cancel: CancelToken | None = None,
    ) -> BackendResult:
        gp = self.gp
        m = self.model
        limit = self.options.time_limit if time_limit is None else time_limit
        m.Params.TimeLimit = float("inf") if limit is None else limit
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
        if m.Status == gp.GRB.INTERRUPTED:  # Gurobi caught Ctrl-C itself: pass it on
            raise KeyboardInterrupt
        status = {
            gp.GRB.OPTIMAL: BackendStatus.OPTIMAL,
            gp.GRB.TIME_LIMIT: BackendStatus.TIME_LIMIT,
            gp.GRB.INTERRUPTED: BackendStatus.TIME_LIMIT,
            gp.GRB.INFEASIBLE: BackendStatus.INFEASIBLE,
        }.get(m.Status, BackendStatus.ERROR)
        has = m.SolCount > 0
        return BackendResult(
            status=status,
            values=np.asarray(self.vars.X) if has else None,
            objective=m.ObjVal if has else None,
            bound=m.ObjBound
            if status in (BackendStatus.OPTIMAL, BackendStatus.TIME_LIMIT)
            else None,
            nodes=int(m.NodeCount),
            solve_time_s=elapsed,
            detail={"gurobi_status": int(m.Status)},
        )


SCIP_MAX_SECONDS = 1e20  # SCIP's range of limits/time
SCIP_MAX_THREADS = 64  # SCIP's range of parallel/maxnthreads


def _set_scip(scip: Any, name: str, value: float | int, parameter: str) -> None:
    """One SCIP parameter; a value out of SCIP's range is an error in the option that set it."""
    try:
        scip.setParam(name, value)
    except ValueError:  # pyscipopt: "the value is invalid for the given parameter"
        raise OptionError(f"SCIP does not take {value!r} for {name}", parameter=parameter) from None


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

    def tolerances(self) -> Tolerances:
        """SCIP's, as :meth:`solve` sets them; its model comes through the MPS file HiGHS
        writes, so HiGHS' ``small_matrix_value`` drops entries before SCIP's own epsilon."""
        scip = self.pyscipopt.Model()
        scip.hideOutput(True)
        _set_scip(scip, "limits/gap", float(self.options.mip_gap), "mip_gap")
        scip.setParam("numerics/feastol", INTEGRALITY_TOLERANCE)
        written = highs_tolerances(SolverOptions())
        return Tolerances(
            drop=max(written.drop, float(scip.getParam("numerics/epsilon"))),
            feasibility=float(scip.getParam("numerics/feastol")),
            rel_gap=float(scip.getParam("limits/gap")),
            abs_gap=float(scip.getParam("limits/absgap")),
        )

    def handed(self, model: MilpModel) -> MilpModel:
        return unscaled(model)

    def close(self) -> None:
        pass

    def solve(
        self,
        start: tuple[np.ndarray, np.ndarray] | None,
        time_limit: float | None = None,
        cancel: CancelToken | None = None,
    ) -> BackendResult:
        """SCIP's answer; where its LP solver meets numerical trouble it cannot resolve, once
        more with SCIP's numerics emphasis (more careful LPs: Markowitz pivoting, no fast-MIP
        shortcuts), in the time left. The tolerances :meth:`tolerances` reports are set again
        after the emphasis, which leaves them alone."""
        limit = self.options.time_limit if time_limit is None else time_limit
        began = time.perf_counter()
        try:
            return self._solve_once(start, limit, cancel, careful=False)
        except _NumericalTroubleError:
            left = None if limit is None else limit - (time.perf_counter() - began)
            if left is not None and left <= 0:
                raise SolverError(
                    "SCIP failed: its LP solver met numerical trouble; try another backend: "
                    'solver="highs"'
                ) from None
        try:
            return self._solve_once(start, left, cancel, careful=True)
        except _NumericalTroubleError as error:
            raise SolverError(
                f"SCIP failed: {error} (also with its numerics emphasis); try another "
                'backend: solver="highs"'
            ) from None

    def _solve_once(
        self,
        start: tuple[np.ndarray, np.ndarray] | None,
        limit: float | None,
        cancel: CancelToken | None,
        *,
        careful: bool,
    ) -> BackendResult:
        # SCIP reads the model from the MPS file HiGHS writes: a bulk path with no per-row calls
        with tempfile.TemporaryDirectory() as folder:
            path = Path(folder) / "model.mps"
            write_model(unscaled(self.source), path)
            scip = self.pyscipopt.Model()
            scip.hideOutput(not self.options.verbose)
            scip.readProblem(str(path))
        if limit is not None:  # SCIP takes at most 1e20 s, which is no limit at all
            _set_scip(scip, "limits/time", min(float(limit), SCIP_MAX_SECONDS), "time_limit")
        _set_scip(scip, "limits/gap", float(self.options.mip_gap), "mip_gap")
        if careful:
            scip.setEmphasis(self.pyscipopt.SCIP_PARAMEMPHASIS.NUMERICS)
        scip.setParam("numerics/feastol", INTEGRALITY_TOLERANCE)  # also SCIP's integrality one
        threads = self.options.threads
        if threads is not None:
            # SCIP's branch and bound runs in one thread; more threads means its concurrent
            # mode (several solvers with different settings racing on the same model)
            if threads > SCIP_MAX_THREADS:
                raise OptionError(
                    f"SCIP takes at most {SCIP_MAX_THREADS}, got {threads}",
                    parameter="threads",
                )
            _set_scip(scip, "parallel/maxnthreads", int(threads), "threads")
            _set_scip(scip, "parallel/minnthreads", int(threads), "threads")
        by_index = {int(v.name[1:]): v for v in scip.getVars()}
        variables = [by_index[i] for i in range(self.source.n_columns)]
        values: np.ndarray | None  # the start's, then the answer's
        if start is not None:
            columns, values = start
            solution = scip.createPartialSol()
            for column, value in zip(columns.tolist(), values.tolist(), strict=True):
                scip.setSolVal(solution, variables[column], value)
            scip.addSol(solution)
        concurrent = int(threads) if threads is not None and threads > 1 else 0
        # SCIP's own Ctrl-C handler stopped it inside an LP ("error in LP solver") and kept
        # the signal from the command: the command's cancel token stops it instead, from a
        # thread that interrupts SCIP at its next safe point, as a limit would
        scip.setParam("misc/catchctrlc", False)
        stopper = _ScipStopper(scip, cancel)
        began = time.perf_counter()
        try:
            if concurrent:
                scip.solveConcurrent()
            else:
                scip.optimizeNogil()  # lets the stopper (and the CLI's signal watch) run
        except Exception as error:  # pyscipopt raises plain Exception ("error in LP solver")
            if cancel is not None and cancel.cancelled:
                raise KeyboardInterrupt from None  # cut short by the stop request: no answer
            raise _NumericalTroubleError(str(error)) from None
        finally:
            stopper.close()
        elapsed = time.perf_counter() - began
        raw = scip.getStatus()
        if raw == "userinterrupt" and not (cancel is not None and cancel.cancelled):
            raise KeyboardInterrupt  # not ours: pass it on, do not answer
        status = {
            "optimal": BackendStatus.OPTIMAL,
            "timelimit": BackendStatus.TIME_LIMIT,
            "userinterrupt": BackendStatus.TIME_LIMIT,
            "infeasible": BackendStatus.INFEASIBLE,
            "gaplimit": BackendStatus.OPTIMAL,  # MilpSolver tells a gap stop by the bound
        }.get(raw, BackendStatus.ERROR)
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
            detail={"scip_status": raw, "scip_threads": concurrent or 1},
        )


class _NumericalTroubleError(Exception):
    """SCIP stopped with an error of its own (in practice: its LP solver's numerical trouble)."""


class _ScipStopper:
    """Interrupts a SCIP solve once ``cancel`` is cancelled: a thread that looks every
    ``STOP_POLL_S`` while SCIP runs without the GIL."""

    def __init__(self, scip: Any, cancel: CancelToken | None) -> None:
        self.done = threading.Event()
        self.thread = None
        if cancel is not None:
            self.thread = threading.Thread(target=self._watch, args=(scip, cancel), daemon=True)
            self.thread.start()

    def _watch(self, scip: Any, cancel: CancelToken) -> None:
        while not self.done.wait(STOP_POLL_S):
            if cancel.cancelled:  # asked again until SCIP returns: it may be between stages
                with contextlib.suppress(Exception):
                    scip.interruptSolve()

    def close(self) -> None:
        self.done.set()
        if self.thread is not None:
            self.thread.join()


BACKENDS: dict[str, Callable[[SolverOptions], Backend]] = {
    "highs": HighsBackend,
    "gurobi": GurobiBackend,
    "scip": ScipBackend,
}


def make_backend(name: str, options: SolverOptions) -> Backend:
    if name not in BACKENDS:
        raise OptionError(f"{name!r} is not one of {', '.join(BACKENDS)}", parameter="solver")
    return BACKENDS[name](options)


def violation(model: MilpModel, values: np.ndarray) -> float:
    """How far ``values`` is from a feasible point of ``model`` with integral binaries: the
    largest distance of an integer column from an integer, of a column from its bounds, or of
    a row activity from its bounds. A solver returns points up to its tolerances off; HiGHS,
    for one, rounds the binaries it reports but not the rows that depend on them."""
    integral = values[model.integer]
    activity = model.matrix @ values
    scale = 1.0 if model.row_scale is None else model.row_scale  # in the rows' own units
    parts = [
        np.abs(integral - np.round(integral)),
        model.col_lower - values,
        values - model.col_upper,
        (model.row_lower - activity) / scale,
        (activity - model.row_upper) / scale,
    ]
    return float(max((part.max() for part in parts if part.size), default=0.0))


def value_with_rounded_binaries(
    model: MilpModel, values: np.ndarray, budget: float, time_limit: float | None = None
) -> float | None:
    """The model's optimum with every integer column fixed to ``values`` rounded: what the
    formulation claims for the alteration those binaries decode to, free of the solver's
    integrality tolerance. A linear programme, solved by HiGHS in its worker process within
    ``time_limit`` seconds; None if it does not solve to optimality (the caller then keeps the
    solver's own objective)."""
    rounded = np.round(values[model.integer])
    lower, upper = model.col_lower.copy(), model.col_upper.copy()
    lower[model.integer] = upper[model.integer] = rounded
    row_upper = model.row_upper.copy()
    row_upper[model.budget_row] = budget
    fixed = dataclasses.replace(
        model,
        col_lower=lower,
        col_upper=upper,
        integer=np.zeros_like(model.integer),
        row_upper=row_upper,
    )
    backend = HighsBackend(SolverOptions())
    try:
        backend.load(fixed)
        result = backend.solve(None, time_limit=time_limit)
    finally:
        backend.close()
    return result.objective if result.status == BackendStatus.OPTIMAL else None


def unscaled(model: MilpModel) -> MilpModel:
    """``model`` with its rows back in their own units (``row_scale`` undone): scaling helps a
    solver whose feasibility tolerance is absolute and loose (HiGHS, 1e-6), but SCIP runs at
    1e-9 already and its LP ran into numerical trouble on scaled sensor networks."""
    if model.row_scale is None or np.all(model.row_scale == 1.0):
        return model
    inverse = 1.0 / model.row_scale
    return dataclasses.replace(
        model,
        matrix=sp.diags(inverse, format="csr") @ model.matrix,
        row_lower=model.row_lower * inverse,
        row_upper=model.row_upper * inverse,
        row_scale=None,
    )


def write_model(model: MilpModel, path: Path) -> None:
    """Write ``model`` as MPS or LP (by suffix) through HiGHS; columns are named c0, c1, …"""
    suffix = Path(path).suffix.lower()
    if suffix not in (".mps", ".lp"):
        raise ProblemError(
            f"cannot write {suffix or 'a file without suffix'}: use .mps or .lp", field="path"
        )
    from misdirect.io.files import write_output

    backend = HighsBackend(SolverOptions())
    backend.load(model)
    # into a temporary file beside the target, moved into place only once HiGHS reports
    # success and the file exists (HiGHS crashes on some unwritable paths, e.g. under /proc)
    write_output(Path(path), backend.write)
