"""The certification policy: when an answer may be called optimal, decided in one place.

Methods only report how they stopped (finished, time or node limit, gap) with the bound they
proved; the front door (:func:`misdirect.solve`) re-evaluates every returned alteration
exactly (:class:`ExactValues`) and hands the curve to :func:`certify_curve`, the only code that
promotes or demotes a status. The tolerances come from :mod:`misdirect.core.tolerance`:
values are compared relative to their size (an answer of 1e-13 against 4e-13 is no tie), and
an alteration fits its budget only when its exact cost does (``CurvePoint.fits``, from
:meth:`misdirect.core.model.CostModel.fits`), with no slack.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Iterator
from contextvars import ContextVar
from dataclasses import dataclass, field

import numpy as np

from misdirect.core import tolerance
from misdirect.core.evaluate import decoy_value
from misdirect.core.model import Problem
from misdirect.core.reachability import Bounded
from misdirect.solvers.stats import MethodStats
from misdirect.solvers.status import Status, StopReason


class ExactValues:
    """Exact values of alterations of one problem, each computed once (a curve often repeats
    one, and auto compares its stages' answers on the same numbers the user will see): one per
    ``solve`` call, which stages reach through :func:`exact_values`. Each comes with its
    proven error bound (:meth:`error`), which :func:`decide` charges to the answer."""

    def __init__(self, problem: Problem):
        self.problem = problem
        self._values: dict[bytes, Bounded] = {}

    def __call__(self, alteration: np.ndarray) -> float:
        return self.bounded(alteration).value

    def error(self, alteration: np.ndarray) -> float:
        """Proven bound on the error of the value (``inf`` when none could be proven)."""
        return self.bounded(alteration).error

    def bounded(self, alteration: np.ndarray) -> Bounded:
        alpha = np.asarray(alteration, dtype=np.int64)
        key = alpha.tobytes()
        if key not in self._values:
            self._values[key] = decoy_value(self.problem, alpha)
        return self._values[key]


_current: ContextVar[ExactValues | None] = ContextVar("misdirect_exact_values", default=None)


@contextlib.contextmanager
def exact_scope(values: ExactValues) -> Iterator[ExactValues]:
    """Within this block, :func:`exact_values` of ``values.problem`` is ``values``."""
    token = _current.set(values)
    try:
        yield values
    finally:
        _current.reset(token)


def exact_values(problem: Problem) -> ExactValues:
    """The exact values of the current solve, if it is of ``problem``; else a new table."""
    current = _current.get()
    return current if current is not None and current.problem is problem else ExactValues(problem)


def decide(
    stopped: Status,
    exact: float,
    bound: float | None,
    error: float = 0.0,
    scale: float = 0.0,
    floor: float = 0.0,
) -> Status:
    """The status of an answer worth ``exact`` (within its proven ``error``) whose method
    stopped as ``stopped``, given the best proven upper bound on its budget's optimum:
    ``optimal`` exactly when ``bound`` meets the least value ``exact`` may have, so an answer
    whose value is not proven within :data:`~misdirect.core.tolerance.CERTIFY` (relative to
    the value, or to ``scale``, the problem's largest exact value) never is; a method that
    says it finished without such a bound gets ``feasible``."""
    if stopped == Status.UNVERIFIED:
        return stopped
    if tolerance.proven(exact - error, bound, scale, floor):
        return Status.OPTIMAL
    return Status.FEASIBLE if stopped == Status.OPTIMAL else stopped


@dataclass
class CurvePoint:
    """One budget's answer while the front door checks the curve as a whole."""

    budget: float
    status: Status
    probability: float  # exact value of ``alteration``
    alteration: np.ndarray
    cost: float
    upper_bound: float | None
    claimed: float | None  # the method's own value (None: it had no incumbent)
    stats: MethodStats
    certified_by: str | None
    notes: dict[str, str] = field(default_factory=dict)  # what certification says of it
    error_bound: float = 0.0  # proven bound on the error of ``probability`` (inf: none)
    fits: bool = True  # the alteration's exact cost fits ``budget`` (CostModel.fits)
    stop_reason: StopReason | None = None  # how the method stopped (never judged here)


@dataclass(frozen=True)
class Evidence:
    """What other work proved about one budget's optimum (the audit's single-sensor solves):
    a proven upper bound, and optionally an alteration within the budget with its exact value
    and cost. ``source`` names it in ``certified_by``, ``why`` says in the notes why it holds."""

    budget: float
    source: str
    why: str
    upper_bound: float
    alteration: np.ndarray | None = None
    probability: float | None = None  # exact value of ``alteration``
    cost: float | None = None
    error_bound: float = math.inf  # proven bound on the error of ``probability``


def take_evidence(point: CurvePoint, evidence: Evidence, fits: bool) -> None:
    """Fold ``evidence`` into ``point`` before :func:`certify_curve` decides: a better
    alteration (by more than a tie) replaces the point's, a tighter bound its bound. How the
    method stopped is kept; only the certification turns it into ``optimal``. A bound below
    the point's exact value contradicts the chain: the evidence is then not taken. ``fits``:
    the evidence's alteration fits the budget exactly (``CostModel.fits``)."""
    if point.probability - evidence.upper_bound > tolerance.slack(
        point.probability, rel=tolerance.MISMATCH
    ):
        point.notes["evidence_ignored"] = (
            f"{evidence.source}'s bound {evidence.upper_bound:.9f} is below the exact value "
            f"{point.probability:.9f}"
        )
        return
    if (
        evidence.alteration is not None
        and evidence.probability is not None
        and evidence.cost is not None
        and fits
        and tolerance.better(evidence.probability, point.probability)
    ):
        point.notes["replaced"] = (
            f"the solver's answer ({point.probability:.9f}) was worse than {evidence.source}'s, "
            "whose alteration it takes"
        )
        point.alteration = np.asarray(evidence.alteration, dtype=np.int64)
        point.probability, point.cost = evidence.probability, evidence.cost
        point.error_bound = evidence.error_bound
        point.fits = True
        point.certified_by = evidence.source
    bound = max(evidence.upper_bound, point.probability)
    if point.upper_bound is None or bound < point.upper_bound:
        point.upper_bound = bound
        point.notes["bound_from"] = f"{evidence.source}: {evidence.why}"
        if tolerance.proven(point.probability, bound):
            point.certified_by = evidence.source


def check_claims(
    point: CurvePoint, method: str, scale: float = 0.0, floor: float = 0.0
) -> list[str]:
    """Contradictions between the method's numbers and the chain: a claim or a bound off the
    exact value by more than :data:`~misdirect.core.tolerance.MISMATCH` (relative) makes the
    point ``unverified``; a bound slightly below the exact value (solver tolerance) is raised
    to it. ``scale`` is the problem's (the largest exact value of its curve, the baseline's):
    a claim of 1e-16 where the chain gives 0 is rounding on a problem of values about 1, but
    not on one of values about 1e-16 (``floor``: below it, every difference is rounding,
    :data:`~misdirect.core.tolerance.ROUNDING`). An alteration whose exact cost exceeds the
    budget is no answer: the point is ``unverified``. Returns the warnings for the user."""
    warnings = []
    exact, claimed = point.probability, point.claimed
    # An incumbent cut short (time or gap limit, node limit) may claim less than its
    # alteration is worth: its continuous part (or a MILP's witness columns) was not yet
    # pushed to the best for its choices. Only claiming more, or any mismatch at a proven
    # optimum, contradicts the chain.
    if (
        claimed is not None
        and tolerance.mismatch(exact, claimed, scale, floor)
        and not (point.status.cut_short and claimed < exact)
    ):
        point.status = Status.UNVERIFIED
        warnings.append(
            f"budget {point.budget:g}: the {method} solver claimed {claimed:.9g} but the chain "
            f"gives {exact:.9g}; the answer is not optimal as far as anyone can tell"
        )
    if not point.fits:
        point.status = Status.UNVERIFIED
        warnings.append(
            f"budget {point.budget:g}: the {method} solver returned an alteration costing "
            f"{point.cost:g}, over the budget; it is not an answer"
        )
    if point.upper_bound is not None and point.upper_bound < exact:
        room = max(tolerance.slack(exact, scale, rel=tolerance.MISMATCH), floor)
        if exact - point.upper_bound > room:
            point.status = Status.UNVERIFIED
            warnings.append(
                f"budget {point.budget:g}: the {method} solver's bound "
                f"{point.upper_bound:.9f} is below the exact value {exact:.9f}"
            )
        point.upper_bound = exact
    return warnings


def certify_curve(
    curve: list[CurvePoint],
    *,
    cancelled: bool = False,
    unaltered: tuple[np.ndarray, float, float] | None = None,
    floor: float = 0.0,
) -> None:
    """What one budget's answer proves about the others, and "optimal" only when proven.

    * A larger budget can do whatever a smaller one can: a point worse than one at a smaller
      budget (or than altering nothing, ``unaltered``: the identity, its exact value and that
      value's proven error) takes
      that alteration (a method cut short may not have found it again).
    * Ties go to the cheapest: a point whose exact value does not beat a cheaper known answer
      by more than :data:`~misdirect.core.tolerance.TIE` (relative) takes that answer (an
      alteration that gains nothing is not worth paying for).
    * An upper bound at a larger budget bounds every smaller one too.
    * Each point's status is :func:`decide`'s; a point cut short by a cancellation (not by its
      time limit) is ``interrupted``.
    """
    _carry_answers_up(curve, unaltered)
    # the problem's scale: the largest exact value known (bounds may be trivial)
    scale = max([p.probability for p in curve] + ([unaltered[1]] if unaltered else []))
    bound: float | None = None
    for point in sorted(curve, key=lambda p: p.budget, reverse=True):
        if point.status in (Status.UNVERIFIED, Status.INFEASIBLE):
            continue
        if bound is not None and (point.upper_bound is None or bound < point.upper_bound):
            point.upper_bound = max(bound, point.probability)
        if point.upper_bound is not None:
            bound = point.upper_bound
        status = decide(
            point.status, point.probability, point.upper_bound, point.error_bound, scale, floor
        )
        if status == Status.FEASIBLE and point.status == Status.OPTIMAL:
            point.notes["not_certified"] = _why_not(point)
        elif status == Status.OPTIMAL and point.status.cut_short:
            point.notes["certified_by_bound"] = "a bound at this or a larger budget meets it"
        if status == Status.OPTIMAL:  # a second pass (with evidence) may prove what was not
            point.notes.pop("not_certified", None)
            point.notes.pop("trivial_bound", None)  # a bound from elsewhere met it
        point.status = status
    if cancelled:
        for point in curve:
            if point.status == Status.TIME_LIMIT:
                point.status = Status.INTERRUPTED


def _why_not(point: CurvePoint) -> str:
    """Why a finished method's answer is not called optimal."""
    if point.error_bound > tolerance.slack(point.probability, rel=tolerance.CERTIFY):
        proven = (
            "has no proven error bound"
            if not math.isfinite(point.error_bound)
            else f"is proven only within {point.error_bound:.2e}"
        )
        return (
            f"the exact value {point.probability:.12f} {proven}: the chain is too "
            "ill-conditioned for double precision, even refined"
        )
    if point.upper_bound is None:
        return f"no proven bound within {tolerance.CERTIFY:g} (relative) of the exact value"
    error = f" (its error is up to {point.error_bound:.2e})" if point.error_bound else ""
    return (
        f"proven bound {point.upper_bound:.12f} is "
        f"{point.upper_bound - point.probability:.2e} above the exact value{error}"
    )


@dataclass(frozen=True)
class _Known:
    """An answer a point may take instead of its own: a smaller budget's, or altering nothing."""

    alteration: np.ndarray
    probability: float
    cost: float
    name: str  # "budget 1's", "altering nothing"
    error_bound: float = 0.0


def _carry_answers_up(
    curve: list[CurvePoint], unaltered: tuple[np.ndarray, float, float] | None
) -> None:
    best = None
    if unaltered is not None:
        identity, value, error = unaltered
        best = _Known(identity, value, 0.0, "altering nothing", error)
    for point in sorted(curve, key=lambda p: p.budget):
        if point.status == Status.INFEASIBLE:  # max_alarm: nothing fits, nothing to carry
            continue
        if best is not None:
            # costs are the floats of exact sums: compared as they are
            # an alteration over the budget is no answer (check_claims warned of it)
            worse = not point.fits or tolerance.better(best.probability, point.probability)
            costlier = point.cost > best.cost
            if not point.fits:
                point.notes["replaced"] = (
                    f"the solver's answer (cost {point.cost:g}) exceeds the budget; it takes "
                    f"{best.name}'s alteration"
                )
            elif worse:
                point.notes["replaced"] = (
                    f"the solver's answer ({point.probability:.9f}) was worse than "
                    f"{best.name}, whose alteration it takes"
                )
            elif costlier and not tolerance.better(point.probability, best.probability):
                point.notes["replaced"] = (
                    f"the solver's answer (cost {point.cost:g}) gains nothing over "
                    f"{best.name} (cost {best.cost:g}), whose alteration it takes"
                )
            else:
                worse = costlier = False
            if worse or costlier:
                point.alteration, point.probability, point.cost, point.error_bound = (
                    best.alteration,
                    best.probability,
                    best.cost,
                    best.error_bound,
                )
                point.fits = True
                if point.upper_bound is not None:
                    point.upper_bound = max(point.upper_bound, point.probability)
        if (
            best is None
            or tolerance.better(point.probability, best.probability)
            or point.cost < best.cost
        ):
            best = _Known(
                point.alteration,
                point.probability,
                point.cost,
                f"budget {point.budget:g}'s",
                point.error_bound,
            )
