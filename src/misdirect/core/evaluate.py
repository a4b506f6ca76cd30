"""Exact value of one alteration: the probability of misleading the robot into the decoy.

:func:`decoy_probability` is the lean number every solver needs; :func:`evaluate` is the full
report a person reads (outcomes, sizes, expected visits per cell).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from misdirect.core import tolerance
from misdirect.core.keywords import checked_keywords
from misdirect.core.model import AlterationArray, Problem
from misdirect.core.notebook import Shown
from misdirect.core.product import ProductChain, build_product
from misdirect.core.reachability import (
    UNIT_ROUNDOFF,
    Bounded,
    Occupation,
    occupation,
    reach_probability_bounded,
)

if TYPE_CHECKING:
    from misdirect.core.notebook import View


def decoy_probability(problem: Problem, alteration: AlterationArray) -> float:
    """Pr(reach decoy) from ``(s0, n0)`` under ``alteration``, exactly (sparse LU); with
    weighted decoy sets, the expected weight of the first decoy state entered."""
    return decoy_value(problem, problem.as_alteration(alteration)).value


def decoy_value(problem: Problem, alteration: AlterationArray) -> Bounded:
    """:func:`decoy_probability` with a proven bound on its error on the product chain as
    built (``inf`` when none could be proven; see
    :func:`misdirect.core.reachability.reach_probability_bounded`)."""
    chain = build_product(problem, alteration)
    return _decoy_value(problem, chain)


def evaluation_time(problem: Problem, repeats: int = 3) -> float:
    """Best-of-``repeats`` wall time of one exact evaluation of the unaltered chain.

    The floor of every solver: none can certify an optimum faster than evaluating its answer,
    so benchmarks report their times against this.
    """
    best = float("inf")
    for _ in range(repeats):
        began = time.perf_counter()
        decoy_probability(problem, problem.identity())
        best = min(best, time.perf_counter() - began)
    return best


def _decoy_value(problem: Problem, chain: ProductChain) -> Bounded:
    objective = problem.objective
    target = objective.target[chain.world_state]
    value = None if objective.is_probability else objective.value[chain.world_state]
    return reach_probability_bounded(
        chain.matrix, target, chain.initial, blocks=chain.node, value=value
    )


@dataclass(frozen=True)
class AlarmSource:
    """Where a monitor raises the alarm: in world state ``state`` (which emits
    ``observation``), on the ``reading`` the robot receives there, with ``probability`` (the
    probability that the run is caught there, summed over the robot's memory)."""

    state: str
    observation: str
    reading: str
    probability: float

    def to_dict(self) -> dict[str, Any]:
        return {
            "state": self.state,
            "observation": self.observation,
            "reading": self.reading,
            "probability": self.probability,
        }


@dataclass(frozen=True)
class Evaluation(Shown):
    """Everything known about one alteration, computed exactly (:func:`evaluate`).

    ``outcomes`` lists the decoy and absorbing states a run can end in first, with non-zero
    probability only (a model may have thousands of absorbing states, most never entered);
    ``all_outcomes`` and ``first_entry`` keep every terminal state, zeros included.
    ``error_bound`` is a proven bound on the error of ``probability``, of each outcome and of
    each decoy set's probability, on the product chain as built (its doubles taken as exact);
    ``None`` when none could be proven (a chain too ill-conditioned for double precision
    even with refinement). The expected visits are proven only on wide chains, solved by the
    certified iterative route (:func:`misdirect.core.reachability.solve_certified`).

    Attributes
    ----------
    probability : float
        Pr(reach decoy); with weighted decoy sets the expected weight of the first decoy
        state entered (``objective`` says which).
    alteration : dict of str to str
        The alteration as names, only the observations that change.
    cost : float
        What the alteration costs; ``within_budget`` says whether the problem's budget
        affords it.
    outcomes : dict of str to float
        First decoy or absorbing state entered, with its probability (non-zero only).
    never_absorbed : float
        Probability of running forever without entering a decoy or absorbing state.
    product_states, product_transitions : int
        Size of the product chain (world state, memory node) that was solved.
    expected_visits : ndarray
        Expected steps spent in each world state.
    error_bound : float or None
        Proven bound on the error of the probabilities.
    """

    probability: float  # with weighted decoy sets: the expected weight (see `objective`)
    alteration: dict[str, str]
    cost: float
    within_budget: bool
    outcomes: dict[str, float]  # first decoy/absorbing state entered -> probability, if > 0
    never_absorbed: float  # runs that cycle forever without a decoy or absorbing state
    product_states: int
    product_transitions: int
    time_s: float
    expected_visits: np.ndarray = field(repr=False)  # (|S|,) expected steps spent per world state
    first_entry: np.ndarray = field(repr=False, default_factory=lambda: np.zeros(0))  # (|S|,)
    error_bound: float | None = None
    terminal_states: np.ndarray = field(repr=False, default_factory=lambda: np.zeros(0, int))
    state_names: tuple[str, ...] = field(repr=False, default=())  # the POMDP's, not a copy
    # weighted decoys: probability that the first decoy state entered is in each set
    decoy_sets: dict[str, float] = field(default_factory=dict)
    objective: str = "probability"  # or "expected_decoy_weight"
    warnings: tuple[str, ...] = ()  # the problem's (see Problem.warnings)
    notes: tuple[str, ...] = ()  # the problem's (see Problem.notes)
    problem: str = ""  # the problem's name
    budget: float = 0.0  # the problem's budget (``within_budget`` is about it)
    decoy_states: frozenset[str] = frozenset()  # the decoy states: outcomes of kind decoy
    # the value with no alteration, when it was computed (``evaluate --json`` does)
    baseline_value: float | None = None
    # a monitored problem's alarm sink (the outcome of kind "alarm"), else None
    alarm_state: str | None = None
    # where the alarm is raised: per world state the robot is in when its reading raises it,
    # with that reading and the probability (they sum to alarm_probability), largest first
    alarm_sources: tuple[AlarmSource, ...] = ()

    @property
    def all_outcomes(self) -> dict[str, float]:
        """Every decoy and absorbing state with its first-entry probability, zeros included."""
        values = self.first_entry[self.terminal_states].tolist()
        names = [self.state_names[s] for s in self.terminal_states]
        return dict(zip(names, values, strict=True))

    def _view(self) -> View:
        """The evaluation in a notebook: the value, the alteration and where runs end."""
        from misdirect.core import notebook as nb
        from misdirect.core.objective import LABELS

        within = "within" if self.within_budget else "over"
        facts = [
            (LABELS.get(self.objective, self.objective), nb.number(self.probability)),
            ("alteration", nb.changes(self.alteration)),
            ("cost", nb.text(f"{self.cost:g} ({within} the budget {self.budget:g})")),
            ("error bound", nb.small(self.error_bound)),
        ]
        if self.baseline_value is not None:
            facts.append(("without alteration", nb.number(self.baseline_value)))
        facts.append(
            (
                "product chain",
                nb.text(
                    f"{self.product_states:,} states, {self.product_transitions:,} transitions"
                ),
            )
        )
        rows = [
            (
                nb.text(row["kind"]),
                nb.text(row["state"] or "(never absorbed)"),
                nb.number(row["probability"]),
            )
            for row in self.outcome_list()
        ]
        ends = nb.Table(("kind", "state", "probability"), rows, "where runs end first")
        sets = (
            [
                nb.Table(
                    ("decoy set", "probability"),
                    [(nb.text(name), nb.number(p)) for name, p in self.decoy_sets.items()],
                )
            ]
            if self.decoy_sets
            else []
        )
        alarms = [
            nb.Table(
                ("state", "observation", "reading", "probability"),
                [
                    (
                        nb.text(a.state),
                        nb.text(a.observation),
                        nb.text(a.reading),
                        nb.number(a.probability),
                    )
                    for a in self.alarm_sources
                ],
                "where the alarm is raised",
            )
        ]
        tables = [ends, *(alarms if self.alarm_sources else []), *sets]
        title = f"{self.problem or 'problem'}: evaluation"
        return nb.View(title, facts, tables, [*self.warnings, *self.notes])

    def outcome_list(self, *, all_outcomes: bool = False) -> list[dict[str, Any]]:
        """:attr:`outcomes` (or :attr:`all_outcomes`) as the JSON lists them: ``kind``
        (decoy, alarm for a monitor's alarm, or goal for another absorbing state), ``state``
        and ``probability``; the
        runs never absorbed, if any, as kind ``trapped`` with no state."""
        ends = self.all_outcomes if all_outcomes else self.outcomes
        listed: list[dict[str, Any]] = [
            {"kind": self._kind(s), "state": s, "probability": p} for s, p in ends.items()
        ]
        if self.never_absorbed > 0:
            listed.append({"kind": "trapped", "state": None, "probability": self.never_absorbed})
        return listed

    def _kind(self, state: str) -> str:
        if state in self.decoy_states:
            return "decoy"
        return "alarm" if state == self.alarm_state else "goal"

    def alarm_readings(self) -> list[tuple[str, str, float]]:
        """Where the alarm fires, by reading: ``(observation, reading, probability)``, the
        states of one observation read alike added up, largest first (they sum to
        :attr:`alarm_probability`)."""
        by: dict[tuple[str, str], float] = {}
        for source in self.alarm_sources:
            key = (source.observation, source.reading)
            by[key] = by.get(key, 0.0) + source.probability
        return sorted(((o, r, p) for (o, r), p in by.items()), key=lambda t: (-t[2], t[:2]))

    @property
    def alarm_probability(self) -> float | None:
        """Pr(the monitor raises the alarm first) of a monitored problem, else None."""
        if self.alarm_state is None:
            return None
        return self.outcomes.get(self.alarm_state, 0.0)

    def to_dict(self, *, all_outcomes: bool = False) -> dict[str, Any]:
        """The evaluation as ``evaluate --json`` writes it (``misdirect-result/1``, the
        fields of ``$defs/evaluate``, ``warnings`` and ``notes``): the exact value is
        ``value``, ``outcomes`` a list (:meth:`outcome_list`); ``all_outcomes`` lists
        zero-probability terminal states too. ``baseline_value`` is null unless it was
        computed."""
        return {
            "problem": self.problem,
            "objective": self.objective,
            "value": self.probability,
            "alteration": self.alteration,
            "cost": self.cost,
            "budget": self.budget,
            "within_budget": self.within_budget,
            "baseline_value": self.baseline_value,
            "error_bound": self.error_bound,
            "outcomes": self.outcome_list(all_outcomes=all_outcomes),
            **({"decoy_sets": self.decoy_sets} if self.decoy_sets else {}),
            **(
                {"alarms": [source.to_dict() for source in self.alarm_sources]}
                if self.alarm_state is not None
                else {}
            ),
            "product_states": self.product_states,
            "product_transitions": self.product_transitions,
            "time_s": self.time_s,
            "warnings": list(self.warnings),
            "notes": list(self.notes),
        }


OUTCOME_ERROR = tolerance.CERTIFY
"""The proven error the first-entry probabilities may have to be shown (they are printed to six
digits; the value itself is held to :data:`~misdirect.core.tolerance.EXACT`)."""


def _unproven_outcomes(
    occ: Occupation | None,
    terminal: np.ndarray,
    decoy: np.ndarray,
    worth: np.ndarray,
    probability: float,
    error: float,
) -> str | None:
    """Why the first-entry distribution cannot be shown, or None when it can: its proven
    error is within :data:`OUTCOME_ERROR`, it is a distribution (each entry in [0, 1], all of
    them summing to 1, trapped runs included), and its decoy mass agrees with the proven
    value. A chain that lingers 10^15 steps, or rows whose doubles sum to 1 + 5e-11 (accepted
    as distributions), can make a solve that passes its residual check read 1.5 or 0.9."""
    if occ is None:
        return "the chain's occupation system is singular in double precision"
    slack = occ.error_bound + OUTCOME_ERROR
    if not math.isfinite(occ.error_bound) or occ.error_bound > OUTCOME_ERROR:
        return f"their error could not be proven below {OUTCOME_ERROR:g}"
    entered = occ.entered[terminal | occ.trapped]
    total = float(entered.sum())
    if not (np.isfinite(entered).all() and entered.min(initial=0.0) >= -slack):
        return "the solve gave probabilities outside [0, 1]"
    if entered.max(initial=0.0) > 1 + slack or abs(total - 1.0) > slack * max(entered.size, 1):
        return f"the first entries sum to {total:.9g}, not 1"
    decoy_mass = float(occ.entered[decoy] @ worth)
    if abs(decoy_mass - probability) > slack + error + tolerance.CERTIFY * probability:
        return (
            f"their decoy mass {decoy_mass:.9g} disagrees with the proven value {probability:.9g}"
        )
    return None


@checked_keywords
def evaluate(problem: Problem, alteration: AlterationArray | None = None) -> Evaluation:
    """The exact value of one alteration, with every outcome and the expected visits.

    Parameters
    ----------
    problem : Problem
        The POMDP, controller, costs, decoy and budget.
    alteration : Alteration, array of int or mapping of str to str, optional
        What the robot receives for each observation (:meth:`Problem.alteration` builds one
        from names, and reads a mapping given here: ``{"o1": "o3"}``; ``{}`` alters
        nothing). Default: no alteration.

    Returns
    -------
    Evaluation
        Pr(reach decoy) (or the expected decoy weight) with its proven error bound, the
        first decoy or absorbing state entered with its probability, the cost and the
        expected visits per world state.

    Raises
    ------
    ProblemError
        An alteration that the problem does not allow is refused by
        :meth:`Problem.alteration`; an array given directly is taken as is.

    Notes
    -----
    One transposed solve gives expected visits and every outcome at once
    (:func:`misdirect.core.reachability.occupation`); where it took the certified iterative
    route, the probability is read off it too (the mass first entering a decoy state), else
    it comes from the forward solve every solver uses.

    Examples
    --------
    >>> import misdirect
    >>> from misdirect.scenarios import paper_grid
    >>> problem = paper_grid(5)
    >>> report = misdirect.evaluate(problem, problem.alteration({"o1": "o3"}))
    >>> round(report.probability, 6), report.cost
    (0.719924, 1.0)
    >>> {state: round(p, 4) for state, p in report.outcomes.items()}
    {'(2,2)': 0.7199, '(4,4)': 0.2801}
    """
    started = time.perf_counter()
    alpha = problem.identity() if alteration is None else problem.as_alteration(alteration)
    chain = build_product(problem, alpha)

    pomdp, objective = problem.pomdp, problem.objective
    decoy = objective.target[chain.world_state]
    terminal = decoy | pomdp.absorbing[chain.world_state]
    occ: Occupation | None
    try:
        occ = occupation(chain.matrix, terminal, chain.initial, blocks=chain.node)
    except (RuntimeError, ValueError, np.linalg.LinAlgError):  # I - Q singular in doubles
        occ = None
    worth = objective.value[chain.world_state[decoy]]
    if occ is not None and occ.iterative:  # a run scores iff the first terminal state is a decoy
        probability = float(np.clip(occ.entered[decoy] @ worth, 0.0, objective.max_value))
        # the error of a sum of entries weighted by at most max_value, and its rounding
        error = occ.error_bound * objective.max_value + decoy.sum() * UNIT_ROUNDOFF * probability
        error = max(error, occ.error_bound)
    else:
        probability, error = _decoy_value(problem, chain)
    unproven = _unproven_outcomes(occ, terminal, decoy, worth, probability, error)
    notes = problem.notes
    if unproven is not None:
        notes = (*notes, f"outcomes and expected visits left out: {unproven}")
        occ = Occupation(
            np.zeros(chain.n_states),
            np.zeros(chain.n_states),
            np.zeros(chain.n_states, dtype=bool),
            np.zeros(chain.n_states, dtype=bool),
        )
    else:
        assert occ is not None
        error = max(error, occ.error_bound)
    first_entry = np.bincount(
        chain.world_state, weights=np.where(terminal, occ.entered, 0.0), minlength=pomdp.n_states
    )
    terminal_states = np.flatnonzero(objective.target | pomdp.absorbing)
    names = pomdp.states
    entered = terminal_states[first_entry[terminal_states] > 0]
    outcomes = dict(zip([names[s] for s in entered], first_entry[entered].tolist(), strict=True))
    visits = np.bincount(chain.world_state, weights=occ.visits, minlength=pomdp.n_states)
    sources = _alarm_sources(problem, chain, occ.visits, alpha)
    cost = problem.alteration_cost(alpha)
    return Evaluation(
        probability=probability,
        alteration=problem.changed_observations(alpha),
        cost=cost,
        within_budget=problem.cost.fits(alpha, problem.budget),
        outcomes=outcomes,
        never_absorbed=float(occ.entered[occ.trapped].sum()),
        product_states=chain.n_states,
        product_transitions=chain.n_transitions,
        time_s=time.perf_counter() - started,
        expected_visits=visits,
        first_entry=first_entry,
        error_bound=error if math.isfinite(error) else None,
        terminal_states=terminal_states,
        state_names=names,
        decoy_sets={d.name: float(first_entry[d.states].sum()) for d in objective.sets},
        objective=objective.kind,
        warnings=problem.warnings,
        notes=notes,
        problem=problem.name,
        budget=problem.budget,
        decoy_states=frozenset(names[s] for s in np.flatnonzero(objective.target)),
        alarm_state=None if problem.alarm_state is None else names[problem.alarm_state],
        alarm_sources=sources,
    )


def _alarm_sources(
    problem: Problem, chain: ProductChain, visits: np.ndarray, alpha: np.ndarray
) -> tuple[AlarmSource, ...]:
    """Where the alarm fires: the mass a run sends into the alarm sink from each world state
    (expected visits of each product state times its probability of moving into the sink,
    summed over memory nodes), non-zero only, largest first. Their sum is the first-entry
    probability of the sink: the same occupation measure gives both."""
    sink = problem.alarm_state
    if sink is None:
        return ()
    into = np.asarray(chain.matrix[:, chain.world_state == sink].sum(axis=1)).ravel()
    flow = np.bincount(chain.world_state, weights=visits * into, minlength=problem.pomdp.n_states)
    pomdp = problem.pomdp
    order = np.flatnonzero(flow > 0)
    order = order[np.argsort(-flow[order], kind="stable")]
    return tuple(
        AlarmSource(
            state=pomdp.states[s],
            observation=pomdp.observations[pomdp.observation_of[s]],
            reading=pomdp.observations[alpha[pomdp.observation_of[s]]],
            probability=float(flow[s]),
        )
        for s in order.tolist()
    )
