"""The tolerance policy: every comparison of costs, values and bounds in misdirect reads it here.

An exactness tool hides its soundness bugs in tolerances, so there is one place that says how
close is close enough, and why. Every solver, engine and report compares through these names;
none writes a literal. The decision "is this answer optimal?" built on them lives in
:mod:`misdirect.solvers.certification`.

Nothing here is absolute, because a problem may live at any scale (costs of 1e-10, decoy
weights of 1e-12, a decoy reached through a 1e-10 branch):

* **Costs** are compared exactly. A :class:`CostScale` (one per cost model) turns a budget into
  a *cap*: a float sum of the model's costs is ``<= cap`` exactly when the exact sum of the
  costs as written fits the budget (see :class:`CostScale` for the three cases).
* **Values** (probabilities, expected weights, bounds) are compared relative to the numbers
  compared (:func:`slack`): a gap of ``CERTIFY`` times the larger of them, so 1e-13 against
  4e-13 is as different as 0.1 against 0.4.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from fractions import Fraction

import numpy as np

CERTIFY = 1e-9
""""Optimal" means a proven upper bound within this (relative) of the exact value."""

PRUNE = CERTIFY
"""A subtree whose bound is this close (relative) to the incumbent cannot beat it but by a tie."""

NEAR_TIE = CERTIFY
"""Values of low-rank updates this close (relative) count as equal: their rounding error."""

STOCHASTIC = 1e-9
"""A distribution (a model's row, a controller's move) sums to 1 within this (its scale is 1)."""

TIE = 1e-12
"""Two exact values this close (relative) are the same number up to rounding."""

IMPROVE = 1e-12
"""Policy iteration switches a choice only on a gain larger than this, relative to the values
(else rounding may make it cycle)."""

MISMATCH = 1e-6
"""A solver's claim this far (relative) from the exact value of its alteration contradicts the
chain."""

GAP = CERTIFY / 4
"""The gap (relative) a MILP backend is asked to close. The MILP hands the backend a model
scaled so that its values are about 1 (:mod:`misdirect.solvers.milp`). A backend prunes with
its gap, so its bound may lie that far below the optimum: the bound counts only raised by it
(:meth:`~misdirect.solvers.milp.backends.Tolerances.margin`), which leaves three quarters of
:data:`CERTIFY` for the distance between the bound and the exact value. No absolute gap: it
would be margin that no relative tolerance covers on a problem whose optimum is 0."""


ALARM_MARGIN = 1e-7
"""A search's own (unproven) value of Pr(alarm) decides an alteration infeasible under
``max_alarm`` (δ) only when it exceeds δ by more than this; closer, the exact evaluator (or,
for δ = 0, the graph) decides."""

FEASIBILITY = 1e-9
"""A MILP point further than this from feasible (in the scaled model, values about 1) gets its
claim recomputed with rounded binaries."""

INTEGRALITY = FEASIBILITY
"""How far Gurobi and SCIP may leave a binary from 0 or 1 (SCIP: a row from feasible too). At
their defaults a binary off by 1e-6 loosens a Bellman row by as much and the claim overshoots
the exact value; a point looser than :data:`FEASIBILITY` is recomputed anyway. HiGHS keeps its
own (:mod:`misdirect.solvers.milp.backends` says why)."""

EXACT = CERTIFY / 10
"""A value's proven error must be this small relative to the value (a tenth of what
certification allows, so a method's own gap keeps its room): reachability refines until it is."""

ROUNDING = 2.0**-50
"""A difference this small relative to the objective's largest value (the largest decoy
weight: every chain's values lie below it) is the rounding of double arithmetic on the chain,
whatever the answer's own size: a claim of 2e-18 where the chain gives 0 is no contradiction,
and a bound of 2e-18 proves 0."""

ILL_CONDITIONED = 1e6
"""A low-rank update (a Woodbury system of the rows an alteration changes) whose condition
estimate exceeds this may be off by about ``u · 1e6 ≈ 1e-10`` of the values' scale, near what
:data:`NEAR_TIE` lets pass, and far more above it (an alteration that almost traps the robot
reads 1e11 and is 4e-7 off): its alteration is valued exactly instead, one chain each. On
chains without near-traps the systems read at most about 1e5."""

BOUND_MARGIN = 1e-9
"""A bound computed in floats (expected steps from a scaled Krylov solution, an error from a
residual times those steps) is raised by this, relative to itself: room for the rounding of
its last few operations, scale-free, far below what certification reads."""

TIME_BOUND_RTOLS = (1e-2, 1e-5, 1e-9)
"""Krylov's relative residuals tried in turn for the rough solution a proven bound on the
expected steps is scaled from: a loose solve usually proves one, a tighter one is paid for
only when it does not."""

REFINE_TARGET = 1e-13
"""Reachability's refinement stops once a proven error is this small (absolute: an absorption
probability, of scale 1; the values a person reads are refined further relative to themselves,
:data:`EXACT`)."""

KRYLOV_RTOL = 1e-13
"""The first refinement round's inner Krylov solve shrinks the residual this much (relative):
later rounds aim only at the rounding floor, which is all a proof can use."""

GRADIENT_SOLVE = 1e-10
"""The relative residual of the Krylov solves of the randomized robust master on chains too
large for a sparse LU (:mod:`misdirect.defence.robust_gradient`). Its values only rank
candidates (every number reported is re-evaluated exactly), so it needs no proof."""

PAYNT_STOCHASTIC = 1e-6
"""A distribution read from PAYNT's output sums to 1 within this: its probabilities are floats
from model checking, not numbers as written, so :data:`STOCHASTIC` is too tight for them."""

DENOMINATOR_FLOOR = 1e-300
"""Not a tolerance: a denominator is raised to at least this so that a ratio stays finite
where it may be 0 (far below any value compared)."""

UNIT_ROUNDOFF = 2.0**-53
SMALLEST = 2.0**-1074  # the smallest subnormal: every float is a multiple of it


def slack(*values: float, rel: float = CERTIFY) -> float:
    """``rel`` times the largest finite magnitude among ``values``: the room two values of
    this size may differ by and still count as equal (an infinite bound leaves no room,
    rather than infinite room)."""
    return rel * max((abs(float(v)) for v in values if math.isfinite(v)), default=0.0)


def round_up(value: float) -> float:
    """``value``, the rounded result of one operation, raised past its rounding: at least
    the exact result (for a proven upper bound)."""
    return float(np.nextafter(value + abs(value) * UNIT_ROUNDOFF, np.inf))


def tied(a: float, b: float, rel: float = TIE) -> bool:
    """Whether ``a`` and ``b`` are the same number up to rounding (relative ``rel``)."""
    return bool(abs(a - b) <= slack(a, b, rel=rel))


def better(a: float, b: float, rel: float = TIE) -> bool:
    """Whether ``a`` exceeds ``b`` by more than a tie (relative ``rel``)."""
    return bool(a > b + slack(a, b, rel=rel))


def proven(value: float, bound: float | None, scale: float = 0.0, floor: float = 0.0) -> bool:
    """Whether ``bound`` (a proven upper bound) certifies ``value`` as the optimum: within
    :data:`CERTIFY` of it, relative to the larger, or to ``scale``, the problem's (the
    largest exact value of its curve: a bound of 1e-15 proves 0 on a problem of values about
    1, not on one of values about 1e-15); ``floor``: a gap this small is rounding
    (:data:`ROUNDING` times the objective's largest value)."""
    if bound is None:
        return False
    return bool(bound - value <= max(slack(value, scale, rel=CERTIFY + TIE), floor))


def mismatch(exact: float, claimed: float, scale: float = 0.0, floor: float = 0.0) -> bool:
    """Whether a solver's ``claimed`` value contradicts the ``exact`` one, on a problem whose
    values are about ``scale`` (the largest exact value known); ``floor`` as for
    :func:`proven`."""
    return bool(abs(exact - claimed) > max(slack(exact, scale, rel=MISMATCH), floor))


def exact_enough(error: float, value: float) -> bool:
    """Whether a value's proven ``error`` is small enough to certify with (:data:`EXACT`)."""
    return error <= EXACT * abs(value)


def whole_units(budget: float, unit: float) -> int:
    """How many costs ``unit`` fit ``budget`` exactly (both as written): the largest ``k``
    with ``k unit <= budget``."""
    if not unit > 0:
        raise ValueError("a cost unit must be positive")
    return max(math.floor(_written(budget) / _written(unit)), 0)


def _written(cost: float) -> Fraction:
    """The decimal a float cost was written as (its shortest repr): 0.1 is 1/10."""
    return Fraction(repr(float(cost)))


@dataclass(frozen=True)
class CostScale:
    """How the costs of one cost model add up and fit a budget, exactly.

    Costs are floats from a file, and "0.1 + 0.2 fits 0.3" is what the file means, so a cost is
    the decimal it was written as, and the cost of an alteration is the exact sum of its costs.
    Solvers add costs in floats, so a budget becomes a *cap* (:meth:`cap`), and a float sum of at
    most ``terms`` costs is compared with it by plain ``<=``:

    * ``decimal``: every cost (as written) is a multiple of ``step`` and float sums stay within a
      quarter ``step`` of their exact sums. The cap lies half a step above the last multiple of
      ``step`` within the budget, so ``<=`` is exact (1e-10 does not fit 0; 0.1 + 0.2 fits 0.3).
    * ``binary``: otherwise, every cost is a multiple of the power of two ``step`` and sums stay
      below ``2^53`` steps: float sums are exact, costs are their float values, the cap is the
      budget (5e-324 + 5e-324 does not fit 5e-324).
    * ``rounded``: neither (costs of very different magnitudes, 1 beside 1e-300, or a third
      beside 1). Float sums are then no proof either way within their rounding of the budget,
      so there are two caps: :meth:`cap` lies above the budget by the largest rounding error
      of a sum (every sum that fits passes: what searches prune and bound with) and
      :meth:`sure_cap` below it (every sum that passes fits). A sum between the two is
      *ambiguous* (:meth:`ambiguous`) and decided on its terms, exactly
      (:meth:`fits_terms`), wherever an alteration is taken as an answer.

    The cap also absorbs ``cap - spent`` (a remaining budget) for sums of costs ``spent``.
    """

    kind: str  # "decimal", "binary" or "rounded"
    step: Fraction
    terms: int  # most costs ever added up (one per observation)
    largest: float  # largest finite cost
    _caps: dict[tuple[float, bool], float] = field(default_factory=dict, compare=False, repr=False)

    @classmethod
    def of(cls, costs: Iterable[float], terms: int) -> CostScale:
        """The scale of a cost model whose finite costs are ``costs`` (one alteration adds at
        most ``terms`` of them)."""
        values = sorted({float(c) for c in costs if math.isfinite(c) and c > 0})
        terms = max(int(terms), 1)
        if not values:
            return cls("binary", Fraction(1), terms, 0.0)
        largest = values[-1]
        total = terms * largest  # no sum of costs exceeds it
        # the error of a float sum of ``terms`` costs against their decimals: each cost is
        # rounded once (u relative, or half the least subnormal), each addition once
        error = 2 * (terms + 1) * UNIT_ROUNDOFF * total + terms * SMALLEST
        step = Fraction(0)
        for value in values:
            written = _written(value)
            step = (
                written
                if step == 0
                else Fraction(
                    math.gcd(
                        step.numerator * written.denominator, written.numerator * step.denominator
                    ),
                    step.denominator * written.denominator,
                )
            )
            if step.denominator > 10**340:
                break
        if step > 0 and error <= float(step) / 4 and total / float(step) < 2.0**50:
            return cls("decimal", step, terms, largest)
        low = min(_lowest_bit(v) for v in values)
        binary = Fraction(2) ** low
        if math.log2(total) - low < 52:  # ldexp would overflow for 1 beside 1e-300
            return cls("binary", binary, terms, largest)
        return cls("rounded", binary, terms, largest)

    @property
    def decisive(self) -> bool:
        """Whether ``<=`` against :meth:`cap` decides every budget alone (no ambiguous sums)."""
        return self.kind != "rounded"

    def cap(self, budget: float) -> float:
        """The float a float sum of costs (or a cost, against ``cap - spent``) is compared with
        by ``<=``: every sum whose exact value fits ``budget`` passes, and (but for the
        ``rounded`` kind, see :meth:`ambiguous`) no other."""
        return self._cap(float(budget), upper=True)

    def sure_cap(self, budget: float) -> float:
        """:meth:`cap` from below: every float sum ``<=`` it fits ``budget`` exactly (the
        same as :meth:`cap` but for the ``rounded`` kind)."""
        return self._cap(float(budget), upper=False)

    def _cap(self, budget: float, upper: bool) -> float:
        key = (budget, upper)
        if key in self._caps:
            return self._caps[key]
        if math.isnan(budget) or budget < 0:
            cap = -math.inf
        elif budget == 0:
            cap = 0.0  # a float sum of positive costs is positive: exact in every kind
        elif budget == math.inf or budget >= 2 * self.terms * self.largest:
            cap = math.inf  # every sum fits (the factor 2 is room for rounding)
        elif self.kind == "decimal":
            whole = math.floor(_written(budget) / self.step)
            cap = float((whole + Fraction(1, 2)) * self.step)
        elif self.kind == "binary":
            cap = budget
        else:
            cap = self._rounded(budget, upper)
        self._caps[key] = cap
        return cap

    def _rounded(self, budget: float, upper: bool) -> float:
        """A budget moved by the largest rounding error of a float sum of ``terms`` costs (and
        of as many subtractions from it, for ``cap - spent``): up, so that every sum that fits
        passes, or down, so that only such sums pass."""
        error = 4 * (self.terms + 2) * UNIT_ROUNDOFF
        if upper:
            return budget * (1 + error) + 2 * self.terms * SMALLEST
        return max(budget * (1 - error) - 2 * self.terms * SMALLEST, 0.0)

    def ambiguous(self, costs: np.ndarray, budget: float) -> np.ndarray:
        """Which float sums ``costs`` neither surely fit ``budget`` nor surely exceed it: their
        terms decide (:meth:`fits_terms`). None but in the ``rounded`` kind."""
        costs = np.asarray(costs, dtype=np.float64)
        if self.decisive:
            return np.zeros(costs.shape, dtype=bool)
        return (costs > self.sure_cap(budget)) & (costs <= self.cap(budget))

    def fits_terms(self, total: float, terms: Callable[[], Iterable[float]], budget: float) -> bool:
        """Whether a sum of costs fits ``budget`` exactly: its float sum ``total`` decides
        unless ambiguous, and then the exact sum of its ``terms`` (called only then)."""
        if not total <= self.cap(budget):
            return False
        if total <= self.sure_cap(budget):
            return True
        return self.fits_exactly(terms(), budget)

    def remaining(self, budget: float, spent: float) -> float:
        """A budget for what is left of ``budget`` once ``spent`` (a float sum of costs) is
        paid: a sum ``c`` fits it (:meth:`cap`) exactly when ``spent + c`` fits ``budget``
        (``rounded``: every such ``c`` passes, and perhaps a few more by rounding)."""
        if math.isinf(self.cap(budget)) and budget > 0:
            return math.inf
        if self.kind == "decimal":
            left = math.floor(_written(float(budget)) / self.step) - round(spent / float(self.step))
            return -1.0 if left < 0 else float((left + Fraction(1, 2)) * self.step)
        if self.kind == "binary":
            return budget - spent  # exact: both are multiples of a step the budget's ulp divides
        error = 4 * (self.terms + 2) * UNIT_ROUNDOFF * abs(budget)
        return budget - spent + error

    def snap(self, cap: float) -> float:
        """The largest sum of costs a ``cap`` admits, about (``decimal``: the last step below
        it), for relaxations that weigh the budget itself rather than compare with it."""
        if self.kind != "decimal" or not math.isfinite(cap) or cap < 0:
            return cap
        step = float(self.step)
        return math.floor(cap / step) * step

    def fits(self, cost: float | np.ndarray, budget: float) -> bool | np.ndarray:
        """Whether the float sum ``cost`` of some costs may fit ``budget`` (element-wise): every
        sum that fits does; exact but for :meth:`ambiguous` sums (decide those by their terms
        with :meth:`fits_terms` before taking one as an answer)."""
        return cost <= self.cap(budget)

    def value(self, cost: float) -> Fraction:
        """One cost as a number: as written (the shortest decimal that reads back as it), but
        in the ``binary`` kind, whose float sums are exact: its float value."""
        return Fraction(float(cost)) if self.kind == "binary" else _written(cost)

    def exact(self, costs: Iterable[float]) -> Fraction:
        """The exact sum of ``costs``."""
        return sum((self.value(c) for c in costs), Fraction(0))

    def fits_exactly(self, costs: Iterable[float], budget: float) -> bool:
        """Whether the exact sum of ``costs`` fits ``budget``: the final word on a budget."""
        if math.isnan(budget):
            return False
        if budget == math.inf:
            return True
        return self.exact(costs) <= self.value(budget)

    def same(self, a: float, b: float) -> bool:
        """Whether two float sums of costs stand for the same exact sum."""
        if self.kind == "decimal":
            return abs(a - b) < float(self.step) / 2
        if self.kind == "binary":
            return a == b
        return abs(a - b) <= 4 * (self.terms + 2) * UNIT_ROUNDOFF * max(abs(a), abs(b))

    def cheaper(self, a: float, b: float) -> bool:
        """Whether the sum ``a`` is less than ``b`` (and not the same sum)."""
        return a < b and not self.same(a, b)

    def units(self, cost: float) -> float:
        """A float sum of costs as a number that adds exactly (``decimal``: whole steps)."""
        return float(round(cost / float(self.step))) if self.kind == "decimal" else cost

    def units_cap(self, budget: float) -> float:
        """:meth:`cap` for sums of :meth:`units`."""
        cap = self.cap(budget)
        if self.kind != "decimal" or not math.isfinite(cap):
            return cap
        return float(math.floor(_written(float(budget)) / self.step))


def _lowest_bit(value: float) -> int:
    """The exponent of the lowest set bit of a positive float: it is a multiple of 2^that."""
    mantissa, exponent = math.frexp(value)
    numerator = int(math.ldexp(mantissa, 53))
    exponent -= 53
    while numerator and numerator % 2 == 0:
        numerator //= 2
        exponent += 1
    return max(exponent, -1074)


PROOF_OFFSET = 2.0**-50
"""The least offset (relative to the objective's largest value) a proven upper bound adds to
policy iteration's values before checking that they are a pre-fixed point of the Bellman
operator (:meth:`~misdirect.solvers.engines.policy_iteration.MaxReachability.proven_bound`):
a few units of rounding, so that values whose measured defect is 0 still leave room for the
rounding of the check itself."""

PROOF_EXTENDED = CERTIFY / 100
"""A proven bound further than this (relative) above policy iteration's value is sought again
with the values and the check in double-double: certification needs the bound within
:data:`CERTIFY`, and a chain absorbed after 10^8 steps adds up the check's rounding to more."""

KEPT_BASIS_RANGE = 1e-6
"""A kept basis's reduced values (:mod:`misdirect.solvers.engines.kept_basis`) may stray this
far (relative to the largest value) outside ``[0, top]`` before the solve is distrusted and
the relaxation solved on the whole chain: further out, a round stranded a state (a singular
system) rather than rounding."""

PROOF_COLLAPSE = 1e-6
"""A proven bound further than this (relative) above policy iteration's value after both
checks is proven once more on the MDP with its end components collapsed
(:mod:`misdirect.solvers.engines.end_components`): a proof that costs a policy iteration in
double-double, spent where the direct check failed outright (a bound of 1.0 over 0.46), not
where it is a little loose (a search's nodes prune with it as well)."""

PROOF_COLLAPSED_GAIN = 2.0**-100
"""In the proof on the collapsed MDP, a gain (relative to the values' scale) that policy
iteration in double-double still switches for: a defect left behind is collected along every
tied run, and a region a scheduler lingers in for 10^15 steps turns 2^-100 into 10^-15; the
residuals' own rounding (about 2^-104) lies below it."""

PROOF_COLLAPSED_FALL = 2.0**-60
"""A value that falls by more than this (relative to the values' scale) after a policy
improvement in double-double means the solve went wrong (an improvement only raises values):
the proof on the collapsed MDP gives up rather than prove near a wrong fixed point."""

PROOF_EXTENDED_OFFSET = 2.0**-90
""":data:`PROOF_OFFSET` for the double-double check: above the rounding of its residuals
(about 10^-32 relative), far below anything certification sees even after 10^9 steps."""

PROOF_EXTENDED_GAIN = 2.0**-80
"""In double-double, a gain (relative to the objective's largest value) that policy iteration
switches for before proving: far below :data:`IMPROVE`'s room, whose refused gains add up on a
chain that returns to a state 10^7 times, and far above the residuals' rounding."""
