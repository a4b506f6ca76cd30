"""Front door of the solvers: pick one, run it, and re-check every answer exactly.

Whatever the method, the probability reported for an alteration is the evaluator's, computed
from the product chain of that alteration; the solver's own number is kept only to detect
disagreement: a solver can be wrong, the chain cannot.
"""

from __future__ import annotations

import contextlib
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any

import numpy as np

from misdirect.core import tolerance
from misdirect.core.alterations import max_alteration_cost
from misdirect.core.attack import shared_preparation
from misdirect.core.checkpoint import interruptible
from misdirect.core.keywords import budget_keyword, checked_keywords
from misdirect.core.model import Alteration, AlterationArray, Problem, format_alteration
from misdirect.core.notebook import Shown
from misdirect.core.tables import dataframe, short_float
from misdirect.errors import OptionError, ProblemError
from misdirect.solvers import get_solver
from misdirect.solvers.auto import twin_scope
from misdirect.solvers.base import ProgressCallback, Solution, report
from misdirect.solvers.certification import (
    CurvePoint,
    Evidence,
    ExactValues,
    certify_curve,
    check_claims,
    exact_scope,
    take_evidence,
)
from misdirect.solvers.deadline import CancelToken, Deadline, DeadlineExpiredError, call_deadline
from misdirect.solvers.engines.alarm import (
    AlarmConstraint,
    Verdict,
    alarm_value,
    check_max_alarm,
    constraint_scope,
    tradeoff_scope,
)
from misdirect.solvers.options import SolveOptions, implied_method, implied_note
from misdirect.solvers.pool import TaskPool
from misdirect.solvers.stats import AutoStats, MethodStats, NoStats
from misdirect.solvers.status import Status, StopReason

if TYPE_CHECKING:
    from misdirect.core.notebook import Table, View


@dataclass(frozen=True, repr=False)
class BudgetResult(Shown):
    """The verified answer for one budget: one point of :attr:`SolveResult.curve`.

    Attributes
    ----------
    budget : float
        The attacker's budget of this point.
    status : Status
        ``optimal`` only when a proven upper bound meets the exact value; otherwise how the
        method stopped (``time_limit``, ``gap_limit``, ``feasible``, ``interrupted``,
        ``unverified``).
    probability : float
        The exact value of :attr:`alteration` (Pr(reach decoy), or the expected decoy weight
        with weighted decoy sets), recomputed on its own product chain.
    alteration : dict of str to str
        The alteration as names, only the observations that change.
    cost : float
        What the alteration costs.
    upper_bound : float or None
        A proven bound on the optimum at this budget, if one is known.
    solver_probability : float or None
        The method's own value for the alteration, kept to detect disagreement.
    stats : MethodStats
        The method's counters (nodes, alterations, ...); readable as a mapping.
    notes : dict of str to str
        What certification found worth saying (``replaced``, ``not_certified``, ...).
    alteration_array : Alteration or None
        The alteration as an :class:`~misdirect.core.model.Alteration` (an integer array).
    certified_by : str or None
        The method whose answer or bound proved the point optimal.
    error_bound : float or None
        A proven bound on the error of :attr:`probability` on the chain as built.
    stop_reason : StopReason or None
        How the method's work on this budget ended, in its own words: ``finished``, ``time``,
        ``nodes`` (a search's node limit), ``gap`` (the MILP's gap) or ``cancelled``; None
        where no method said. Only certification makes a point ``optimal``: a finished method
        may still leave it ``feasible``, and a point may be proven after a method's ``time``.
    alarm, alarm_error : float or None
        A monitored problem: Pr(the alarm before any decoy) under :attr:`alteration`, exactly,
        and a proven bound on its error (None: not monitored, or no error proven).
    """

    budget: float
    status: Status
    probability: float  # exact value of `alteration`
    alteration: dict[str, str]
    cost: float
    upper_bound: float | None
    solver_probability: float | None  # None when the solver stopped without an incumbent
    stats: MethodStats = field(default_factory=NoStats)  # the method's own counters
    # what certification found worth saying: "replaced", "not_certified", "certified_by_bound"
    notes: dict[str, str] = field(default_factory=dict)
    alteration_array: AlterationArray | None = field(default=None, repr=False)
    certified_by: str | None = None  # auto: the method whose answer (or bound) this is
    # proven bound on the error of ``probability`` on the chain as built; None: none proven
    error_bound: float | None = 0.0
    stop_reason: StopReason | None = None  # how the method stopped, before certification
    alarm: float | None = None  # a monitored problem: Pr(alarm first) of the alteration
    alarm_error: float | None = None  # its proven error bound

    @property
    def gap(self) -> float | None:
        """Proven distance to the optimum, in probability (0 when solved to optimality), the
        error of the exact value included: ``None`` when either is unknown."""
        if self.upper_bound is None or self.error_bound is None:
            return None
        return max(self.upper_bound - self.probability, 0.0) + self.error_bound

    def __repr__(self) -> str:
        return (
            f"BudgetResult(budget={self.budget:g}, status={self.status.value}, "
            f"probability={short_float(self.probability)}, alteration={self.alteration!r}, "
            f"upper_bound={short_float(self.upper_bound)})"
        )

    def _view(self) -> View:
        """The point in a notebook: status, value, proven bound, gap and the alteration."""
        from misdirect.core import notebook as nb

        facts = [
            ("status", nb.text(self.status.value)),
            ("value", nb.number(self.probability)),
            ("proven bound", nb.number(self.upper_bound)),
            ("gap", nb.small(self.gap)),
            ("error bound", nb.small(self.error_bound)),
            ("alteration", nb.changes(self.alteration)),
            ("cost", nb.amount(self.cost)),
        ]
        if self.alarm is not None:
            facts.append(("Pr(alarm)", nb.number(self.alarm)))
        if self.certified_by:
            facts.append(("certified by", nb.text(self.certified_by)))
        notes = [f"{key}: {note}" for key, note in self.notes.items()]
        return nb.View(f"Budget {self.budget:g}", facts, (), notes)

    def to_dict(self, *, stats: bool = True) -> dict[str, Any]:
        """The point as the JSON writes it (``misdirect-result/1``, ``$defs/point``): the
        exact value is ``value``, certification's notes are ``certification``. ``stats``:
        include the method's counters for this budget (auto's reason, common to the run, is
        left to the run's record)."""
        shown: dict[str, Any] = {
            "budget": self.budget,
            "status": str(self.status),
            "value": self.probability,
            "alteration": self.alteration,
            "cost": self.cost,
            "upper_bound": self.upper_bound,
            "error_bound": self.error_bound,
            "gap": self.gap,
            "certified_by": self.certified_by,
            "certification": dict(self.notes),
            "stop_reason": None if self.stop_reason is None else str(self.stop_reason),
        }
        if self.alarm is not None:  # a monitored problem
            shown["alarm"] = self.alarm
            shown["alarm_error"] = self.alarm_error
        if stats:
            shown["stats"] = {k: v for k, v in self.stats.to_dict().items() if k != "auto_reason"}
        return shown


def curve_table(points: Sequence[BudgetResult], *, caption: str = "") -> Table:
    """A curve as a notebook table: per budget its status, exact value, proven bound, gap,
    cost and alteration (the changes as names, wrapped between changes)."""
    from misdirect.core import notebook as nb

    header = ("budget", "status", "value", "proven bound", "gap", "cost", "alteration")
    rows = [
        (
            nb.amount(p.budget),
            nb.text(p.status.value),
            nb.number(p.probability),
            nb.number(p.upper_bound),
            nb.small(p.gap),
            nb.amount(p.cost),
            nb.changes(p.alteration),
        )
        for p in points
    ]
    return nb.Table(header, rows, caption)


def curve_fields(points: Sequence[BudgetResult]) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    """A curve's points and the run's ``stats``, kept apart as the JSON writes them: a method
    that answers every budget from one run (enumeration) has one record, given once for the
    run; one that solves each budget on its own (the MILP) has a record per point."""
    records = [point.stats for point in points]
    if all(record == records[-1] for record in records):
        return [p.to_dict(stats=False) for p in points], records[-1].to_dict()
    reasons = {r.reason for r in records if isinstance(r, AutoStats)}
    run = {"auto_reason": reasons.pop()} if len(reasons) == 1 else {}
    return [p.to_dict() for p in points], run


@dataclass(frozen=True, repr=False)
class SolveResult(Shown):
    """What :func:`misdirect.solve` returns: the curve over every budget solved.

    The answer is the curve's last point (the largest budget asked for), whose fields the
    result offers directly: ``status``, ``probability``, ``alteration``,
    ``alteration_array``, ``cost``, ``budget``, ``upper_bound``, ``error_bound``, ``stats``
    and ``certified_by`` (see :class:`BudgetResult`).

    Attributes
    ----------
    problem : str
        The problem's name.
    method : str
        The method that ran (``auto``, ``exhaustive``, ...).
    baseline_probability : float
        The exact value with no alteration.
    time_s : float
        Wall time of the whole call, exact re-evaluation included.
    curve : list of BudgetResult
        One verified answer per budget, in increasing budget order.
    warnings : list of str
        Disagreements between a method and the exact chain, and the problem's own doubts.
    notes : list of str
        What the answer should be read with, though nothing is wrong.
    budget_clamped_from, budget_clamped_to : float or None
        Set when the largest budget exceeded the cost of the most expensive complete
        alteration, which the methods then ran at instead.
    interrupted : bool
        Stopped early on request: the answers are the best found so far.
    objective : str
        ``probability``, or ``expected_decoy_weight`` with weighted decoy sets.
    max_alarm : float or None
        The δ the curve was solved for (``solve(..., max_alarm=δ)``): every point is the best
        alteration whose Pr(alarm) is proven at most δ; None: unconstrained.

    Examples
    --------
    >>> import misdirect
    >>> from misdirect.scenarios import paper_grid
    >>> result = misdirect.solve(paper_grid(5), budgets=[0, 1])
    >>> result
    SolveResult(problem='paper grid 5x5', method='auto', status=optimal, probability=0.719924,
                budget=1, alteration={'o1': 'o2'}, curve=2 points, time_s=...)
    >>> result.curve[0]
    BudgetResult(budget=0, status=optimal, probability=0.0849571, alteration={},
                 upper_bound=0.0849571)
    """

    problem: str
    method: str
    baseline_probability: float
    time_s: float
    curve: list[BudgetResult]
    warnings: list[str] = field(default_factory=list)
    # what the answer should be read with, though nothing is wrong (Problem.notes)
    notes: list[str] = field(default_factory=list)
    # the largest budget asked for, when it exceeded the most expensive complete alteration:
    # the solvers then ran at that alteration's cost instead (every budget above it is equal)
    budget_clamped_from: float | None = None
    budget_clamped_to: float | None = None
    interrupted: bool = False  # stopped early on request (Ctrl-C): the best found so far
    # what `probability` measures: "probability" (of reaching the decoy), or
    # "expected_decoy_weight" with weighted decoy sets
    objective: str = "probability"
    max_alarm: float | None = None  # the δ of Pr(alarm) <= δ, if the solve was constrained

    @property
    def final(self) -> BudgetResult:
        return self.curve[-1]

    status = property(lambda self: self.final.status)
    probability = property(lambda self: self.final.probability)
    alteration = property(lambda self: self.final.alteration)
    alteration_array = property(lambda self: self.final.alteration_array)
    cost = property(lambda self: self.final.cost)
    budget = property(lambda self: self.final.budget)
    upper_bound = property(lambda self: self.final.upper_bound)
    error_bound = property(lambda self: self.final.error_bound)
    stats = property(lambda self: self.final.stats)
    certified_by = property(lambda self: self.final.certified_by)
    alarm = property(lambda self: self.final.alarm)
    alarm_error = property(lambda self: self.final.alarm_error)

    def __repr__(self) -> str:
        return (
            f"SolveResult(problem={self.problem!r}, method={self.method!r}, "
            f"status={self.status.value}, probability={short_float(self.probability)}, "
            f"budget={self.budget:g}, alteration={self.alteration!r}, "
            f"curve={len(self.curve)} point{'s' * (len(self.curve) != 1)}, "
            f"time_s={self.time_s:.3g})"
        )

    def _view(self) -> View:
        """The result in a notebook: the answer, then the curve (per budget its status,
        value, proven bound, gap and alteration), warnings and notes."""
        from misdirect.core import notebook as nb
        from misdirect.core.objective import LABELS

        facts = [
            ("objective", nb.text(LABELS.get(self.objective, self.objective))),
            ("status", nb.text(self.status.value)),
            (f"value at budget {self.budget:g}", nb.number(self.probability)),
            ("proven bound", nb.number(self.upper_bound)),
            ("alteration", nb.changes(self.alteration)),
            ("without alteration", nb.number(self.baseline_probability)),
            ("method", nb.text(self.method)),
            ("time", nb.text(f"{self.time_s:.3g} s")),
        ]
        if self.max_alarm is not None:
            facts.insert(1, ("subject to", nb.text(f"Pr(alarm) <= {self.max_alarm:g}")))
        if self.certified_by:
            facts.insert(4, ("certified by", nb.text(self.certified_by)))
        notes = [*self.warnings, *self.notes]
        if self.budget_clamped_from is not None:
            notes.append(
                f"budget {self.budget_clamped_from:g} affords every alteration: solved at "
                f"{self.budget_clamped_to:g}, the cost of the most expensive one"
            )
        if self.interrupted:
            notes.append("interrupted: the best answers found so far")
        title = f"{self.problem or 'problem'}: optimal alterations"
        return nb.View(title, facts, [curve_table(self.curve)], notes)

    def to_dataframe(self) -> Any:
        """The curve as a ``pandas.DataFrame``, one row per budget.

        Columns: those of :meth:`BudgetResult.to_dict` (``budget``, ``status``, ``value``,
        ``alteration`` as ``o1 → o2, ...``, ``cost``, ``upper_bound``, ``error_bound``,
        ``gap``, ``certified_by``), without the nested ``certification`` and ``stats``.

        Raises
        ------
        ImportError
            pandas is not installed (it is optional: ``pip install pandas``).
        """
        return dataframe(
            [
                {**row, "alteration": format_alteration(row["alteration"])}
                for row in map(_table_row, self.curve)
            ],
            list(_table_row(self.final)),
        )

    def to_dict(self) -> dict[str, Any]:
        """The result as ``solve --json`` writes it (``misdirect-result/1``, the fields of
        ``$defs/solve``, ``warnings`` and ``notes``): the answer at the largest budget (its
        exact value is ``value``), then the curve and the run's ``stats``."""
        final = self.final.to_dict(stats=False)
        points, stats = curve_fields(self.curve)
        return {
            "problem": self.problem,
            "objective": self.objective,
            "status": final["status"],
            **{k: final[k] for k in ("value", "alteration", "cost", "budget")},
            "baseline_value": self.baseline_probability,
            **{k: final[k] for k in ("upper_bound", "gap", "error_bound")},
            "method": self.method,
            "certified_by": final["certified_by"],
            "stop_reason": final["stop_reason"],
            "budget_clamped_from": self.budget_clamped_from,
            "budget_clamped_to": self.budget_clamped_to,
            "interrupted": self.interrupted,
            "time_s": self.time_s,
            "curve": points,
            "stats": stats,
            "warnings": list(self.warnings),
            "notes": list(self.notes),
            **({} if self.final.alarm is None else {"alarm": self.final.alarm}),
            **({} if self.max_alarm is None else {"max_alarm": self.max_alarm}),
        }


def _table_row(point: BudgetResult) -> dict[str, Any]:
    """A point's flat fields: a row of :meth:`SolveResult.to_dataframe`."""
    row = point.to_dict(stats=False)
    del row["certification"]
    return row


def default_budgets(
    budget: float,
    scale: tolerance.CostScale | None = None,
    *,
    most: int = 1000,
    notes: list[str] | None = None,
) -> list[float]:
    """Every whole budget from 0 up to ``budget``, and ``budget`` itself.

    Past ``most`` whole budgets (costs of 10^9 and a budget of 10^10 would list ten billion),
    the multiples of the costs' step instead when ``scale`` has one above 1 (no alteration
    costs anything between two, so none is lost), and every k-th of those (or of the whole
    budgets) when still more than ``most``, said in ``notes``."""
    whole = math.floor(budget)
    if whole < most:
        listed = [float(b) for b in range(whole + 1)]
        return listed if listed[-1] == budget else [*listed, float(budget)]
    unit = scale.step if scale is not None and scale.kind != "rounded" and scale.step > 1 else 1
    count = tolerance.whole_units(budget, float(unit)) + 1  # multiples of unit from 0
    every = -(-count // most)
    listed = [float(k * unit) for k in range(0, count, every)]
    if every > 1 and notes is not None:
        notes.append(
            f"the curve lists every {float(every * unit):g} of budget up to {budget:g} "
            f"({len(listed)} of {count} budgets); ask for others by name"
        )
    return listed if listed[-1] == budget else [*listed, float(budget)]


@checked_keywords
def solve(
    problem: Problem,
    *,
    method: str = "auto",
    budget: float | Sequence[float] | None = None,
    budgets: float | Sequence[float] | None = None,
    options: SolveOptions | None = None,
    time_limit: float | None = None,
    threads: int | None = None,
    solver: str | None = None,
    formulation: str | None = None,
    mip_gap: float | None = None,
    verbose: bool | None = None,
    pool: TaskPool | None = None,
    deadline: Deadline | None = None,
    cancel: CancelToken | None = None,
    progress: ProgressCallback | None = None,
    max_alarm: float | None = None,
) -> SolveResult:
    """The optimal alteration for ``problem.budget`` (or each of ``budgets``), certified exactly.

    Every probability returned is the exact value of the returned alteration, recomputed on
    its own product chain, and a point is ``optimal`` only when a proven bound meets it
    (:mod:`misdirect.solvers.certification`), whatever the method or backend claimed.

    Parameters
    ----------
    problem : Problem
        The POMDP, controller, costs, decoy and budget (:func:`misdirect.load_problem`,
        :func:`misdirect.problem_from_dict` or a generator of :mod:`misdirect.scenarios`).
    method : {"auto", "exhaustive", "incremental", "branch-and-bound", "milp"}
        ``auto`` (default) picks and combines the exact methods; the others run one method.
    budget, budgets : float or sequence of float, optional
        One parameter, two spellings (as ``audit`` and ``harden`` take it; both given and
        different is a ``TypeError``). A number: the budget B instead of
        ``problem.budget``, with every whole budget below it where the method gets them for
        free. A sequence: exactly these budgets (the curve). Default: ``problem.budget``, as
        a number.
    options : SolveOptions, optional
        All options as one record; the keyword arguments below override its fields.
    time_limit : float, optional
        Seconds for the whole call, every stage and budget. On expiry each budget keeps the
        best alteration found, with status ``time_limit`` and its proven bound.
    threads : int, optional
        Worker threads (enumeration, segment search, MILP backend); default 2.
    solver : {"highs", "scip", "gurobi"}, optional
        MILP backend (methods ``milp`` and ``auto``); default ``highs``.
    formulation : {"compact", "paper", "paper-pinned"}, optional
        MILP formulation; ``paper`` is the paper's, larger and not exact (its points are
        reported ``unverified`` when its claim disagrees with the exact chain).
    mip_gap : float, optional
        MILP: relative gap to stop at (default 2.5e-10, a quarter of what
        certification allows: the backend prunes with it, so its bound counts raised by it).
    verbose : bool, optional
        MILP: the backend's log on standard output.
    pool : TaskPool, optional
        branch-and-bound and auto: where the segment search's subtrees run, with the
        incumbent shared (:func:`misdirect.distributed.connect`); default: here.
    deadline : Deadline, optional
        A :class:`~misdirect.solvers.deadline.Deadline` shared with other work (an audit's
        solves share one); ``time_limit`` then limits this call further.
    cancel : CancelToken, optional
        Cancelling it (from another thread or a signal handler) stops this solve, and only
        this one, with its best answers so far, marked ``interrupted``. Default: the
        deadline's token, else a fresh one.
    max_alarm : float, optional
        δ in [0, 1]: the best alteration whose Pr(alarm) is at most δ, on a monitored
        problem (:func:`misdirect.core.monitor.with_monitor`); δ = 0 asks for attacks the
        monitor never catches (decided on the altered chain's graph, exactly). Every point is
        then certified for the constrained problem: ``optimal`` only where its alteration's
        Pr(alarm) is proven at most δ and a proven bound on the constrained optimum meets its
        value; ``infeasible`` where no alteration within the budget is. Every method takes it
        (docs/stealth.md). One δ a call: a trade-off curve is one call per δ.
    progress : callable, optional
        Called as ``progress(done, total, stage=..., detail=..., note=...)`` while solving:
        ``done`` of ``total`` steps of ``stage`` (a method's name), ``detail`` a short status
        line (incumbent, bound, gap), ``note`` a hand-over worth a line of its own; a stage
        with ``total`` 0 is a phase without a count ("product", "bounds"), and the
        "enumeration" stage counts alterations valued, with ``rate=`` (a second) for a
        callback that takes it (a ``rate`` parameter or ``**kwargs``). It is
        called from the solving thread; keep it quick. See
        :class:`~misdirect.solvers.base.ProgressCallback`.

    Returns
    -------
    SolveResult
        The verified curve; its last point (the largest budget) is the answer.

    Raises
    ------
    TypeError
        An unknown keyword argument; the message names it, the likely one meant and every
        valid one.
    OptionError
        An option out of range, or one the method does not take (``solver`` with
        ``method="exhaustive"``); ``max_alarm`` outside [0, 1] or on a problem without a
        monitor.
    ProblemError
        A negative or non-finite budget.
    SolverError
        A MILP backend that is not installed.

    Notes
    -----
    A budget above the cost of the most expensive complete alteration affords everything,
    so the methods run at that cost instead and its answer is reported at the budget asked
    for (``budget_clamped_from`` / ``budget_clamped_to`` say so).

    Examples
    --------
    >>> import misdirect
    >>> from misdirect.scenarios import paper_grid
    >>> result = misdirect.solve(paper_grid(5), budgets=range(5))
    >>> print(result.status, round(result.probability, 6), result.cost, result.certified_by)
    optimal 0.863622 4.0 incremental
    >>> [round(point.probability, 3) for point in result.curve]
    [0.085, 0.72, 0.86, 0.862, 0.864]
    >>> misdirect.solve(paper_grid(5), time_limt=10)
    Traceback (most recent call last):
    TypeError: solve() got an unexpected keyword argument 'time_limt' (did you mean ...
    """
    asked = budget_keyword("solve", budget, budgets)
    if isinstance(asked, float):  # a budget B, as the problem's own would be
        problem, budgets = problem.with_budget(asked), None
    else:
        budgets = asked
    overrides: dict[str, Any] = {  # SolveOptions' fields, each of its own type
        "time_limit": time_limit,
        "threads": threads,
        "solver": solver,
        "formulation": formulation,
        "mip_gap": mip_gap,
        "verbose": verbose,
        "pool": pool,
    }
    limit = None if max_alarm is None else check_max_alarm(problem, max_alarm)
    if limit is not None:  # the methods solve δ = 1 unconstrained (SolveOptions.alarm_limit)
        overrides["max_alarm"] = limit
    given = {name: value for name, value in overrides.items() if value is not None}
    options = replace(options or SolveOptions(), **given)
    method, implying = implied_method(method, options.given())  # auto + a MILP option: milp
    method_solver = get_solver(method, options)
    notes = [implied_note(implying)] if implying else []
    budgets, cap, clamped_from = _budgets(problem, budgets, method_solver.curve_is_free, notes)
    if problem.budget > cap:
        problem = problem.with_budget(cap)
    # the methods' problem: its constraint is the one they find (engines.alarm)
    constraint = None if limit is None else AlarmConstraint(problem, limit)
    # each budget above the cap is answered by the cap's solution, reported at its own budget
    clamped = sorted({min(b, cap) for b in budgets})
    deadline = call_deadline(deadline, options.time_limit, cancel)
    started = time.perf_counter()
    exact_value = ExactValues(problem)  # every exact value of this call: the stages' and ours
    # the stages of this call share each prepared instance, and the exact values; building
    # the choice product stops at the deadline too (core.checkpoint)
    solutions: list[Solution] | None = None
    try:
        with (
            shared_preparation(),
            exact_scope(exact_value),
            interruptible(deadline.check),
            _constraint_scope(constraint),
        ):
            # the first phase, until the method reports its own: the product chain's build
            report(progress, 0, 0, stage="product")
            solutions = method_solver.solve(problem, clamped, progress=progress, deadline=deadline)
    except DeadlineExpiredError:  # cut before the method had anything
        pass
    interrupted = deadline.cancelled
    elapsed = time.perf_counter() - started  # the search's time: exact values come on top
    if solutions is None:
        solutions = _unaltered_solutions(problem, clamped, exact_value, interrupted)
    if clamped_from is not None:
        by_budget = {solution.budget: solution for solution in solutions}
        solutions = [
            replace(by_budget[min(b, cap)], budget=b) if b > cap else by_budget[b] for b in budgets
        ]
    curve, warnings = _exact_curve(problem, solutions, method_solver.name, exact_value)
    identity = problem.identity()
    nothing = (identity, exact_value(identity), exact_value.error(identity))
    unaltered: tuple[np.ndarray, float, float] | None = nothing
    if constraint is not None:
        warnings += _feasible_answers(curve, constraint, method_solver.name, nothing)
        if constraint.verdict(identity) != Verdict.FEASIBLE:
            unaltered = None  # altering nothing is no answer to carry up
    certify_curve(curve, cancelled=interrupted, unaltered=unaltered, floor=_floor(problem))
    if constraint is not None:
        warnings += _check_feasible(curve, constraint)
    for point in curve:  # a single method that proved its own point names itself
        if point.status == Status.OPTIMAL and point.certified_by is None:
            point.certified_by = method_solver.name
    return SolveResult(
        problem=problem.name,
        method=method_solver.name,
        baseline_probability=_clean(exact_value(identity)),
        time_s=elapsed,
        curve=[_result(point, problem, constraint) for point in curve],
        warnings=[*problem.warnings, *warnings],
        notes=[*notes, *problem.notes],
        budget_clamped_from=clamped_from,
        budget_clamped_to=None if clamped_from is None else cap,
        interrupted=interrupted,
        objective=problem.objective.kind,
        max_alarm=None if constraint is None else constraint.limit,
    )


def solve_tradeoff(
    problem: Problem, max_alarm: Sequence[float], **options: Any
) -> list[SolveResult]:
    """The trade-off between value and stealth: :func:`solve` once per δ of ``max_alarm``
    (in increasing order), each curve certified for Pr(alarm) <= δ. ``options`` are
    :func:`solve`'s (``budgets``, ``method``, ``time_limit`` per δ, ...). The solves share
    what δ does not change: the prepared instances, each alteration's exact Pr(alarm) and
    the enumerations' tables (a curve of enumerations pays for one).

    Examples
    --------
    >>> import misdirect
    >>> from misdirect.core.monitor import consistency_monitor, with_monitor
    >>> from misdirect.scenarios import paper_grid
    >>> grid = paper_grid(5)
    >>> watched = with_monitor(grid, consistency_monitor(grid))
    >>> curves = misdirect.solve_tradeoff(watched, [0, 0.25], budgets=[1], method="exhaustive")
    >>> [(c.max_alarm, round(c.probability, 6), round(c.alarm, 6)) for c in curves]
    [(0.0, 0.089186, 0.0), (0.25, 0.647903, 0.210195)]
    """
    if "max_alarm" in options:
        raise TypeError("solve_tradeoff() takes max_alarm once, as its list of δ")
    deltas = sorted({float(d) for d in max_alarm})
    if not deltas:
        raise OptionError("no δ to solve for: give at least one", parameter="max_alarm")
    with shared_preparation(), tradeoff_scope(problem), twin_scope():
        return [solve(problem, max_alarm=delta, **options) for delta in deltas]


def _constraint_scope(constraint: AlarmConstraint | None) -> contextlib.AbstractContextManager[Any]:
    return contextlib.nullcontext() if constraint is None else constraint_scope(constraint)


def _feasible_answers(
    curve: list[CurvePoint],
    constraint: AlarmConstraint,
    method: str,
    unaltered: tuple[np.ndarray, float, float],
) -> list[str]:
    """Under ``max_alarm``, before certification: an answer proven to break the constraint
    is no answer (a MILP's tolerances may admit one just above δ); it takes altering nothing
    where that is proven feasible (its bound, sound for the constrained problem, is kept),
    else the point is ``unverified``."""
    warnings = []
    identity, value, error = unaltered
    for point in curve:
        if point.status == Status.INFEASIBLE and constraint.verdict(identity) == Verdict.FEASIBLE:
            # a method's claim that nothing fits, against altering nothing, which does
            warnings.append(
                f"budget {point.budget:g}: the {method} solver found no alteration keeping "
                f"Pr(alarm) <= {constraint.limit:g}, but altering nothing does"
            )
            point.notes["replaced"] = "the solver's 'infeasible' is wrong: altering nothing fits"
            point.alteration, point.probability, point.error_bound = identity, value, error
            point.cost, point.fits, point.claimed = 0.0, True, None
            point.status, point.upper_bound = Status.FEASIBLE, None
            continue
        if point.status in (Status.INFEASIBLE, Status.UNVERIFIED):
            continue
        if constraint.verdict(point.alteration) != Verdict.INFEASIBLE:
            continue
        alarm = constraint.alarm(point.alteration).value
        warnings.append(
            f"budget {point.budget:g}: the {method} solver's answer has Pr(alarm) {alarm:.9g}, "
            f"above {constraint.limit:g}; it is not an answer"
        )
        if constraint.verdict(identity) == Verdict.FEASIBLE:
            point.notes["replaced"] = (
                f"the solver's answer breaks Pr(alarm) <= {constraint.limit:g}: it takes "
                "altering nothing"
            )
            point.alteration, point.probability, point.error_bound = identity, value, error
            point.cost, point.fits, point.claimed = 0.0, True, None
            if point.status == Status.OPTIMAL:
                point.status = Status.FEASIBLE
        else:
            point.status = Status.UNVERIFIED
    return warnings


def _check_feasible(curve: list[CurvePoint], constraint: AlarmConstraint) -> list[str]:
    """After certification, the final alterations (certification may have carried one up):
    ``optimal`` only where Pr(alarm) <= δ is proven; an alteration proven to break it is no
    answer (``unverified``)."""
    warnings = []
    for point in curve:
        if point.status in (Status.INFEASIBLE, Status.UNVERIFIED):
            continue
        verdict = constraint.verdict(point.alteration)
        if verdict == Verdict.FEASIBLE:
            continue
        alarm, error = constraint.alarm(point.alteration)
        if verdict == Verdict.UNDECIDED:
            point.notes["alarm_undecided"] = (
                f"Pr(alarm) {alarm:.12f} (error up to {error:.2e}) is not proven at most "
                f"{constraint.limit:g}"
            )
            if point.status == Status.OPTIMAL:
                point.status = Status.FEASIBLE
        else:
            point.status = Status.UNVERIFIED
            warnings.append(
                f"budget {point.budget:g}: Pr(alarm) {alarm:.9g} of the answer is above "
                f"{constraint.limit:g}; it is not an answer"
            )
    return warnings


def _unaltered_solutions(
    problem: Problem, budgets: Sequence[float], exact_value: ExactValues, cancelled: bool
) -> list[Solution]:
    """Answers for a call cut before its method had any: the unaltered chain, proven where no
    alteration fits the budget (then it is all there is), else open at the trivial bound. The
    method stopped by time, or (``cancelled``) on request, either way."""
    stop = StopReason.cut(cancelled)
    cheapest = problem.cheapest_alteration_cost()
    unaltered_value = exact_value(problem.identity())
    return [
        Solution(
            budget=b,
            alteration=problem.identity(),
            solver_probability=unaltered_value,
            status=Status.OPTIMAL,
            upper_bound=unaltered_value,
            stop_reason=stop,
        )
        if not problem.cost.scale.fits(cheapest, b)
        else Solution(
            budget=b,
            alteration=problem.identity(),
            solver_probability=None,
            status=Status.TIME_LIMIT,
            upper_bound=problem.objective.max_value,  # nothing proven: the trivial bound
            stop_reason=stop,
        )
        for b in budgets
    ]


def _exact_curve(
    problem: Problem, solutions: Sequence[Solution], method: str, exact_value: ExactValues
) -> tuple[list[CurvePoint], list[str]]:
    """The method's answers as curve points valued exactly on their own chains (the one place
    where answers are re-evaluated), and a warning per claim the exact value contradicts."""
    alterations = [np.asarray(s.alteration, dtype=np.int64) for s in solutions]
    for alpha in alterations:
        problem.check_alteration(alpha, source=f"{method} solver")
    # the problem's scale, which a claim is compared relative to: the largest exact value
    scale = max([exact_value(problem.identity()), *map(exact_value, alterations)])
    curve: list[CurvePoint] = []
    warnings: list[str] = []
    for solution, alpha in zip(solutions, alterations, strict=True):
        point = CurvePoint(
            budget=solution.budget,
            status=Status(solution.status),
            probability=exact_value(alpha),
            error_bound=exact_value.error(alpha),
            alteration=alpha,
            cost=problem.alteration_cost(alpha),
            fits=problem.cost.fits(alpha, solution.budget),
            upper_bound=solution.upper_bound,
            claimed=solution.solver_probability,
            stats=solution.stats,
            certified_by=solution.certified_by,
            notes=dict(solution.notes),
            stop_reason=solution.stop_reason,
        )
        warnings += check_claims(point, method, scale, _floor(problem))
        curve.append(point)
    return curve, warnings


def recertify(result: SolveResult, problem: Problem, evidence: Sequence[Evidence]) -> SolveResult:
    """``result`` with what other work proved about its budgets (``evidence``, exact values
    and proven bounds) folded in and the curve certified again by the same policy: a budget
    the method left open becomes ``optimal`` when the evidence's bound meets its value."""
    curve = [_point(answer) for answer in result.curve]
    by_budget = {point.budget: point for point in curve}
    for item in evidence:
        point = by_budget.get(item.budget)
        if point is not None and point.status != Status.UNVERIFIED:
            fits = item.alteration is not None and problem.cost.fits(
                np.asarray(item.alteration, dtype=np.int64), item.budget
            )
            take_evidence(point, item, fits)
    certify_curve(curve, cancelled=result.interrupted, floor=_floor(problem))
    return replace(result, curve=[_result(point, problem) for point in curve])


def _point(answer: BudgetResult) -> CurvePoint:
    """A certified answer back as a point (for :func:`recertify`)."""
    if answer.alteration_array is None:
        raise ValueError(f"budget {answer.budget:g}: no alteration array to certify again")
    return CurvePoint(
        budget=answer.budget,
        status=Status(answer.status),
        probability=answer.probability,
        alteration=np.asarray(answer.alteration_array, dtype=np.int64),
        cost=answer.cost,
        upper_bound=answer.upper_bound,
        claimed=answer.solver_probability,
        stats=answer.stats,
        certified_by=answer.certified_by,
        notes=dict(answer.notes),
        error_bound=math.inf if answer.error_bound is None else answer.error_bound,
        stop_reason=answer.stop_reason,
    )


def _budgets(
    problem: Problem,
    budgets: Sequence[float] | None,
    curve_is_free: bool,
    notes: list[str] | None = None,
) -> tuple[list[float], float, float | None]:
    """The budgets to answer (sorted, checked), the cap (the most expensive complete
    alteration's cost) and the largest budget asked for when it exceeds the cap; a default
    curve too long to list whole is thinned, said in ``notes``."""
    if budgets is not None and not len(budgets):
        raise OptionError(
            "no budget to answer: give at least one, or none for the problem's", parameter="budgets"
        )
    cap = max_alteration_cost(problem)
    asked = problem.budget if budgets is None else max(map(float, budgets), default=0.0)
    _, clamped_from = clamp_budget(asked, cap)
    if budgets is None:
        whole = (
            default_budgets(min(problem.budget, cap), problem.cost.scale, notes=notes)
            if curve_is_free
            else []
        )
        budgets = [*whole, problem.budget]
    ordered = sorted({float(b) for b in budgets})
    for b in ordered:
        if not math.isfinite(b) or b < 0:
            raise ProblemError(f"a budget must be a non-negative number, got {b}", field="budget")
    return ordered, cap, clamped_from


def _floor(problem: Problem) -> float:
    """Differences of values below this are rounding (:data:`~misdirect.core.tolerance.ROUNDING`
    times the objective's largest value)."""
    return tolerance.ROUNDING * float(problem.objective.max_value)


def clamp_budget(asked: float, cap: float) -> tuple[float, float | None]:
    """``asked``, or ``cap`` when it is more (a budget that already affords everything), and
    the budget asked when it was clamped (else None).

    ``cap`` is what buys everything (for an attacker, :func:`max_alteration_cost`; for a
    defender, protecting every alterable sensor): work past it lists budgets that change
    nothing, so solve, audit and harden run at the cap and report the budget asked."""
    if math.isfinite(asked) and asked > cap:
        return cap, asked
    return asked, None


def _clean(value: float) -> float:
    """``-0.0`` (a solver's bound, a sum of zeros) as ``0.0``: the same number, printed as one."""
    return value + 0.0


def _result(
    point: CurvePoint, problem: Problem, constraint: AlarmConstraint | None = None
) -> BudgetResult:
    alarm = None
    if problem.alarm_state is not None:  # a monitored problem: both probabilities
        alarm = (
            constraint.alarm(point.alteration)
            if constraint is not None
            else alarm_value(problem, point.alteration)
        )
    return BudgetResult(
        budget=point.budget,
        status=point.status,
        probability=_clean(point.probability),
        alteration=problem.changed_observations(point.alteration),
        cost=_clean(point.cost),
        upper_bound=None if point.upper_bound is None else _clean(point.upper_bound),
        solver_probability=point.claimed,
        stats=point.stats,
        notes=point.notes,
        alteration_array=Alteration(point.alteration, problem.pomdp.observations),
        certified_by=point.certified_by,
        error_bound=point.error_bound if math.isfinite(point.error_bound) else None,
        stop_reason=point.stop_reason,
        alarm=None if alarm is None else _clean(alarm.value),
        alarm_error=None if alarm is None or not math.isfinite(alarm.error) else alarm.error,
    )
