"""The defender's view: which sensors are weak, which to protect, and what an online attacker
could do (docs/defence.md).

* :func:`audit` — the attacker's optimum for every budget up to ``B``, per sensor its
  single-sensor value and its *criticality* (how much protecting it lowers the optimum at
  ``B``), and the online attacker's value;
* :func:`harden` — the protection set, within a protection budget ``D``, that minimises the
  attacker's optimum at ``B`` (an exact min–max by hitting-set branching);
* :func:`online_attack_value` — an attacker who sees the true state and the controller's
  memory and may alter every reading differently: maximal reachability of the decoy in the
  product MDP with the attacker's choices, as the least fixed point (policy iteration).

Every attacker value printed is the exact value of an alteration the solver returned
(``misdirect.solve`` re-evaluates it); whatever is not certified is labelled.
"""

from __future__ import annotations

import math
import time
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from fractions import Fraction
from typing import Any

import numpy as np
import scipy.sparse as sp

from misdirect.core.alterations import alteration_space
from misdirect.core.attack import prepare
from misdirect.core.model import Problem, reachable_from
from misdirect.core.objective import LABELS
from misdirect.core.reachability import reach_probabilities
from misdirect.errors import ProblemError, SolverError
from misdirect.solvers.deadline import Deadline
from misdirect.solvers.run import BudgetResult, default_budgets, solve
from misdirect.solvers.status import Status

CERTIFY_TOLERANCE = 1e-9  # as everywhere in misdirect: "optimal" means within this
IMPROVE_TOLERANCE = 1e-12  # policy iteration switches a state only on a larger gain
MAX_POLICY_ROUNDS = 100_000
MAX_BUDGET_LEVELS = 100_000  # budgeted online MDP: at most this many remaining-budget levels
MAX_BUDGETED_STATES = 20_000_000
UNIT_DENOMINATOR = 1_000_000  # a cost unit is a fraction with at most this denominator
HITTING_NODE_LIMIT = 200_000  # the lower bound's hitting-set search gives up (soundly) beyond


# -- online attacker ----------------------------------------------------------------------------


@dataclass(frozen=True)
class OnlineAttack:
    """The online attacker's value: unlimited, and with a per-step budget if one was asked."""

    probability: float  # the value asked for: budgeted if ``budget`` is set, else unlimited
    unlimited_probability: float
    budget: float | None
    budgeted_probability: float | None
    cost_unit: float | None  # the common unit the budgeted MDP counts costs in
    product_states: int
    mdp_states: int  # of the MDP actually solved (product states x budget levels)
    policy_evaluations: int
    time_s: float

    def to_dict(self) -> dict[str, Any]:
        return {
            "probability": self.probability,
            "unlimited_probability": self.unlimited_probability,
            "budget": self.budget,
            "budgeted_probability": self.budgeted_probability,
            "cost_unit": self.cost_unit,
            "product_states": self.product_states,
            "mdp_states": self.mdp_states,
            "policy_evaluations": self.policy_evaluations,
            "time_s": self.time_s,
        }


def max_reach(
    owner: np.ndarray,
    transitions: sp.csr_matrix,
    target: np.ndarray,
    *,
    blocks: np.ndarray | None = None,
    value: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, int]:
    """Maximal reachability of ``target`` in an MDP given by its choices (with ``value``, a
    score per target state: the maximal expected score of the first target state entered).

    Choice ``g`` belongs to state ``owner[g]`` and moves by row ``g`` of ``transitions``.
    Policy iteration: each policy is evaluated exactly as the *least* fixed point
    (:func:`misdirect.core.reachability.reach_probabilities`), and a state switches only on a
    strict gain. At termination the values are a fixed point of the Bellman operator that some
    policy attains; every fixed point lies above the least one, which is the optimum, and no
    policy lies above the optimum — so they are the optimum (docs/defence.md). Returns
    ``(values, policy, evaluations)``.
    """
    n_states = target.size
    owner = np.asarray(owner, dtype=np.int64)
    if np.bincount(owner, minlength=n_states).min(initial=1) == 0:
        raise SolverError("every state of the MDP needs at least one choice")
    structure = (transitions != 0).astype(np.float64)
    owners = sp.csr_matrix(
        (np.ones(owner.size), (owner, np.arange(owner.size))), shape=(n_states, owner.size)
    )
    graph = (owners @ structure).tocsr()
    live = reachable_from(graph.T.tocsr(), np.flatnonzero(target)) & ~target
    order = np.argsort(owner, kind="stable")
    first = order[np.concatenate([[0], np.flatnonzero(np.diff(owner[order])) + 1])]
    policy = first.copy()  # the lowest-numbered choice of every state
    for evaluations in range(1, MAX_POLICY_ROUNDS + 1):
        values = reach_probabilities(
            transitions[policy].tocsr(), target, blocks=blocks, value=value
        )
        score = np.asarray(transitions @ values).ravel()
        ranked = np.lexsort((-score, owner))
        best = ranked[np.concatenate([[0], np.flatnonzero(np.diff(owner[ranked])) + 1])]
        switch = live & (score[best] > score[policy] + IMPROVE_TOLERANCE)
        if not switch.any():
            return values, policy, evaluations
        policy = np.where(switch, best, policy)
    raise SolverError(f"policy iteration did not settle in {MAX_POLICY_ROUNDS:,} rounds")


def cost_unit(costs: Iterable[float]) -> float | None:
    """The largest unit every cost is a whole multiple of (exactly, as fractions), or None."""
    fractions = []
    for cost in {float(c) for c in costs if np.isfinite(c) and c > 0}:
        fraction = Fraction(cost).limit_denominator(UNIT_DENOMINATOR)
        if float(fraction) != cost:
            return None
        fractions.append(fraction)
    if not fractions:
        return 1.0
    denominator = math.lcm(*(f.denominator for f in fractions))
    numerator = math.gcd(*(f.numerator * (denominator // f.denominator) for f in fractions))
    return float(Fraction(numerator, denominator))


def online_attack_value(problem: Problem, budget: float | None = None) -> OnlineAttack:
    """Value of the online attacker (docs/defence.md); ``budget``: costs paid per altered
    reading along the run, against ``budget``; None: every allowed target at any cost.

    The unlimited value bounds the offline optimum at every budget from above (an
    alteration is one of the online attacker's strategies). The budgeted value is a different
    threat (it pays for every altered reading, the offline attacker once per sensor), not a
    bound of the offline optimum either way.
    """
    started = time.perf_counter()
    if budget is not None and not (math.isfinite(budget) and budget >= 0):
        raise ProblemError(f"must be a non-negative number, got {budget}", field="budget")
    chain = prepare(problem, math.inf).chain
    values, _, evaluations = max_reach(
        chain.group_state,
        chain.transitions,
        chain.target,
        blocks=chain.node,
        value=chain.target_value,
    )
    unlimited = float(values[chain.initial])
    budgeted = unit = None
    mdp_states = chain.n_states
    if budget is not None:
        option_cost = chain.options.cost
        unit = cost_unit(option_cost)
        if unit is None:
            raise ProblemError(
                "the budgeted online value needs alteration costs that are whole multiples "
                "of a common unit (e.g. 0.5); these are not, so it is not computed",
                field="budget",
            )
        levels = math.floor(budget / unit + 1e-9) + 1
        if levels > MAX_BUDGET_LEVELS or levels * chain.n_states > MAX_BUDGETED_STATES:
            raise ProblemError(
                f"budget {budget:g} is {levels - 1:,} cost units of {unit:g}: too many budget "
                f"levels for the budgeted online MDP ({chain.n_states:,} product states each)",
                field="budget",
            )
        units = np.rint(option_cost / unit).astype(np.int64)
        # cheapest way to make a state take each group: min over the options selecting it
        # (option 0 of every observation, "unaltered", costs 0; groups without options too)
        membership = chain.group_options.tocoo()
        group_units = np.zeros(chain.n_groups, dtype=np.int64)
        has_option = np.zeros(chain.n_groups, dtype=bool)
        has_option[membership.row] = True
        group_units[has_option] = np.iinfo(np.int64).max
        np.minimum.at(group_units, membership.row, units[membership.col])
        owner, matrix, target, initial = _budgeted_mdp(chain, group_units, levels)
        b_values, _, b_evaluations = max_reach(
            owner, matrix, target, value=np.tile(chain.target_value, levels)
        )
        budgeted = float(b_values[initial])
        evaluations += b_evaluations
        mdp_states = target.size
    return OnlineAttack(
        probability=unlimited if budgeted is None else budgeted,
        unlimited_probability=unlimited,
        budget=None if budget is None else float(budget),
        budgeted_probability=budgeted,
        cost_unit=unit,
        product_states=chain.n_states,
        mdp_states=mdp_states,
        policy_evaluations=evaluations,
        time_s=time.perf_counter() - started,
    )


def _budgeted_mdp(chain, group_units: np.ndarray, levels: int):
    """The MDP over (product state, remaining units): state ``r * Q + q``; group ``g`` in
    level ``r ≥ cost(g)`` moves like ``g`` into level ``r - cost(g)``."""
    n_q = chain.n_states
    allowed = group_units[:, None] <= np.arange(levels)[None, :]
    groups, level = np.nonzero(allowed)
    rows = chain.transitions[groups].tocsr()
    shift = (level - group_units[groups]) * n_q
    indices = rows.indices.astype(np.int64) + np.repeat(shift, np.diff(rows.indptr))
    matrix = sp.csr_matrix((rows.data, indices, rows.indptr), shape=(groups.size, n_q * levels))
    owner = level * n_q + chain.group_state[groups]
    target = np.tile(chain.target, levels)
    return owner, matrix, target, (levels - 1) * n_q + chain.initial


# -- attacker solves under a protection ---------------------------------------------------------


@dataclass(frozen=True)
class _Attack:
    """The attacker's answer at budget B under one protection set."""

    value: float  # exact value of ``alteration``
    upper: float  # proven bound on the attacker's optimum (== value when certified)
    status: Status
    alteration: dict[str, str]
    changed: frozenset[int]
    cost: float

    @property
    def certified(self) -> bool:
        return self.status == Status.OPTIMAL


def protect(problem: Problem, observations: Iterable[int]) -> Problem:
    """``problem`` with ``observations`` made unalterable as well (CostModel.protected)."""
    protected = problem.cost.protected | frozenset(int(o) for o in observations)
    return replace(problem, cost=replace(problem.cost, protected=protected))


def _attack_of(point: BudgetResult, problem: Problem) -> _Attack:
    alpha = point.alteration_array
    changed = (
        frozenset(int(o) for o in np.flatnonzero(alpha != problem.identity()))
        if alpha is not None
        else frozenset()
    )
    # no bound from the method: the largest decoy weight bounds every value (1 for a probability)
    upper = point.upper_bound if point.upper_bound is not None else problem.objective.max_value
    return _Attack(
        value=point.probability,
        upper=max(upper, point.probability),
        status=point.status,
        alteration=point.alteration,
        changed=changed,
        cost=point.cost,
    )


def _deadline(seconds: float | None) -> Deadline:
    """The wall-clock limit shared by every solve of one audit or hardening (expired at once
    on Ctrl-C, like every solver's)."""
    if seconds is not None and not (math.isfinite(seconds) and seconds > 0):
        raise ProblemError(
            f"must be a positive number of seconds, got {seconds}", field="time_limit"
        )
    return Deadline(seconds)


def _solve_at(
    problem: Problem, budget: float, seconds: float | None, method: str = "auto"
) -> _Attack:
    options = {} if seconds is None else {"time_limit": max(seconds, 0.05)}
    result = solve(problem.with_budget(budget), method=method, budgets=[budget], **options)
    return _attack_of(result.curve[-1], problem)


# -- audit --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class SensorAudit:
    """One sensor the attacker could alter within the budget."""

    observation: str
    single_probability: float  # attacker's best with only this sensor alterable
    single_status: str
    single_alteration: dict[str, str]
    in_optimal_attack: bool
    criticality: float  # the drop of the optimum when this sensor is protected (lower bound)
    criticality_upper: float  # == criticality when exact
    protected_probability: float  # attacker's optimum with this sensor protected
    protected_status: str
    protected_alteration: dict[str, str]

    @property
    def exact(self) -> bool:
        return self.criticality_upper - self.criticality <= CERTIFY_TOLERANCE

    def to_dict(self) -> dict[str, Any]:
        return {
            "observation": self.observation,
            "single_probability": self.single_probability,
            "single_status": self.single_status,
            "single_alteration": self.single_alteration,
            "in_optimal_attack": self.in_optimal_attack,
            "criticality": self.criticality,
            "criticality_upper": self.criticality_upper,
            "criticality_exact": self.exact,
            "protected_probability": self.protected_probability,
            "protected_status": self.protected_status,
            "protected_alteration": self.protected_alteration,
        }


@dataclass(frozen=True)
class AuditResult:
    problem: str
    budget: float
    baseline_probability: float
    curve: list[BudgetResult]
    status: str  # of the optimum at ``budget``
    probability: float
    upper_bound: float | None
    alteration: dict[str, str]
    sensors: list[SensorAudit]
    online: OnlineAttack
    online_budgeted_note: str | None
    certified: bool  # the optimum at B and every criticality are exact
    notes: list[str]
    time_s: float
    grid: bool = False
    extra: dict[str, Any] = field(default_factory=dict)
    objective: str = "probability"  # or "expected_decoy_weight" (weighted decoy sets)

    @property
    def objective_label(self) -> str:
        return LABELS[self.objective]

    def to_dict(self) -> dict[str, Any]:
        return {
            "problem": self.problem,
            "objective": self.objective,
            "budget": self.budget,
            "baseline_probability": self.baseline_probability,
            "status": self.status,
            "probability": self.probability,
            "upper_bound": self.upper_bound,
            "alteration": self.alteration,
            "certified": self.certified,
            "curve": [point.to_dict() for point in self.curve],
            "sensors": [sensor.to_dict() for sensor in self.sensors],
            "online": {
                **self.online.to_dict(),
                "budgeted_note": self.online_budgeted_note,
                "upper_bounds_offline": self.online.unlimited_probability
                >= self.probability - CERTIFY_TOLERANCE,
            },
            "notes": self.notes,
            "time_s": self.time_s,
        }


def alterable_sensors(problem: Problem, budget: float) -> list[int]:
    """Observations the attacker can alter within ``budget`` to something the controller
    reacts to differently (the others cannot change the outcome)."""
    return [int(c.observation) for c in alteration_space(problem.with_budget(budget)).choices]


def audit(
    problem: Problem,
    *,
    budget: float | None = None,
    time_limit: float | None = None,
    method: str = "auto",
) -> AuditResult:
    """Budget curve, per-sensor single value and criticality, online value (docs/defence.md).

    Criticality uses the exact shortcut: protecting a sensor the optimal alteration at ``B``
    does not alter leaves that alteration feasible and the optimum unchanged (protection only
    removes alterations), so only the sensors of the optimal attack are re-solved.
    """
    started = time.perf_counter()
    clock = _deadline(time_limit)
    budget = problem.budget if budget is None else float(budget)
    if not (math.isfinite(budget) and budget >= 0):
        raise ProblemError(f"must be a non-negative number, got {budget}", field="budget")
    problem = problem.with_budget(budget)
    notes: list[str] = []
    half = None if time_limit is None else time_limit / 2
    options = {} if half is None else {"time_limit": half}
    curve_result = solve(problem, method=method, budgets=default_budgets(budget), **options)
    curve = curve_result.curve
    top = curve[-1]
    optimum = _attack_of(top, problem)
    if not optimum.certified:
        notes.append(
            f"the optimum at budget {budget:g} is not certified (status {top.status}, proven "
            f"bound {optimum.upper:.9f}): criticalities are intervals, not values"
        )

    sensors = alterable_sensors(problem, budget)
    names = problem.pomdp.observations
    everything = frozenset(range(problem.pomdp.n_observations))
    rows: list[SensorAudit] = []
    needs = [o for o in sensors if o in optimum.changed]
    # single-sensor values first: one observation's few candidates, cheap; the re-solves at
    # B (as hard as the optimum itself) then share what is left of the time
    singles = {}
    for k, o in enumerate(sensors):
        singles[o] = _solve_at(
            protect(problem, everything - {o}),
            budget,
            clock.share(len(sensors) - k + len(needs)),
            method="exhaustive",
        )
    re_solved = {}
    for k, o in enumerate(needs):
        re_solved[o] = _solve_at(
            protect(problem, [o]), budget, clock.share(len(needs) - k), method=method
        )
    for o in sensors:
        single = singles[o]
        if o in re_solved:
            hit = re_solved[o]
            if optimum.certified and hit.certified:
                low = high = max(optimum.value - hit.value, 0.0)
            else:  # OPT ∈ [value, upper] on both sides
                low = max(optimum.value - hit.upper, 0.0)
                high = max(optimum.upper - hit.value, 0.0)
        else:  # the optimal alteration stays feasible: the optimum is unchanged
            hit = optimum
            low, high = 0.0, max(optimum.upper - optimum.value, 0.0)
        rows.append(
            SensorAudit(
                observation=names[o],
                single_probability=single.value,
                single_status=single.status,
                single_alteration=single.alteration,
                in_optimal_attack=o in optimum.changed,
                criticality=low,
                criticality_upper=high,
                protected_probability=hit.value,
                protected_status=hit.status,
                protected_alteration=hit.alteration,
            )
        )
    rows.sort(key=lambda r: (-r.criticality, -r.single_probability, r.observation))

    note = None
    try:
        online = online_attack_value(problem, budget)
    except ProblemError as error:
        note = error.reason
        online = online_attack_value(problem, None)
    if online.unlimited_probability < optimum.value - 1e-9:  # would contradict a theorem
        raise SolverError(
            f"online value {online.unlimited_probability:.12f} below the offline value "
            f"{optimum.value:.12f}"
        )
    certified = optimum.certified and all(r.exact for r in rows)
    from misdirect.report.figures import grid_cells

    return AuditResult(
        problem=problem.name,
        budget=budget,
        baseline_probability=curve_result.baseline_probability,
        curve=curve,
        status=top.status,
        probability=top.probability,
        upper_bound=top.upper_bound,
        alteration=top.alteration,
        sensors=rows,
        online=online,
        online_budgeted_note=note,
        certified=certified,
        notes=notes + list(curve_result.warnings),
        time_s=time.perf_counter() - started,
        objective=problem.objective.kind,
        grid=grid_cells(problem) is not None,
    )


# -- hardening ----------------------------------------------------------------------------------


@dataclass(frozen=True)
class HardenPoint:
    """The best protection within one protection budget ``d``."""

    protect_budget: float
    protection: list[str]
    protection_cost: float
    probability: float  # exact value of the attacker's best reply found
    upper_bound: float  # proven bound on the attacker's optimum under ``protection``
    lower_bound: float  # proven: no protection within d holds the attacker below this
    attack: dict[str, str]
    status: Status  # optimal when the min–max is proven, else time_limit / feasible

    def to_dict(self) -> dict[str, Any]:
        return {
            "protect_budget": self.protect_budget,
            "protection": self.protection,
            "protection_cost": self.protection_cost,
            "probability": self.probability,
            "upper_bound": self.upper_bound,
            "lower_bound": self.lower_bound,
            "attack": self.attack,
            "status": self.status,
        }


@dataclass(frozen=True)
class HardenResult:
    problem: str
    budget: float
    protect_budget: float
    protect_costs: dict[str, float]
    protection: list[str]
    protection_cost: float
    value_before: float
    value_after: float
    value_after_upper: float
    lower_bound: float
    best_reply: dict[str, str]
    status: str
    curve: list[HardenPoint]
    solves: int
    nodes: int
    pruned: int
    time_s: float
    notes: list[str] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        return {
            "problem": self.problem,
            "budget": self.budget,
            "protect_budget": self.protect_budget,
            "protection": self.protection,
            "protection_cost": self.protection_cost,
            "value_before": self.value_before,
            "value_after": self.value_after,
            "value_after_upper": self.value_after_upper,
            "lower_bound": self.lower_bound,
            "best_reply": self.best_reply,
            "status": self.status,
            "curve": [point.to_dict() for point in self.curve],
            "protect_costs": self.protect_costs,
            "solves": self.solves,
            "nodes": self.nodes,
            "pruned": self.pruned,
            "time_s": self.time_s,
            "notes": self.notes,
        }


def protection_costs(
    problem: Problem, costs: Mapping[str, float] | None, *, field: str = "protect_costs"
) -> np.ndarray:
    """Per observation, what protecting it costs: ``costs`` by name, key ``default`` for the
    rest (default 1). Unknown names, negative or non-finite costs are refused."""
    names = problem.pomdp.observations
    index = {name: i for i, name in enumerate(names)}
    costs = dict(costs or {})
    default = 1.0
    if "default" in costs and "default" not in index:
        default = float(costs.pop("default"))
    table = np.full(len(names), default)
    for name, value in [("default", default), *costs.items()]:
        if name != "default" and name not in index:
            shown = ", ".join(names[:8]) + (", …" if len(names) > 8 else "")
            raise ProblemError(f"unknown observation {name!r} (known: {shown})", field=field)
        value = float(value)
        if not (math.isfinite(value) and value >= 0):
            raise ProblemError(
                f"the protection cost of {name!r} must be a non-negative number, got {value}",
                field=field,
            )
        if name != "default":
            table[index[name]] = value
    return table


def _can_hit(
    sets: Sequence[frozenset[int]], room: float, costs: np.ndarray, work: list[int]
) -> bool:
    """Is there a set of sensors of total cost ≤ ``room`` meeting every one of ``sets``?

    Branches on the elements of the smallest set not yet met (every hitting set contains one
    of them). Beyond ``HITTING_NODE_LIMIT`` nodes it answers True, which only ever weakens the
    lower bound it serves, never invalidates it."""
    failed: set[frozenset[int]] = set()

    def search(chosen: frozenset[int], room: float) -> bool:
        open_sets = [s for s in sets if not (s & chosen)]
        if not open_sets:
            return True
        if chosen in failed:
            return False
        work[0] += 1
        if work[0] > HITTING_NODE_LIMIT:
            return True
        smallest = min(open_sets, key=len)
        for o in sorted(smallest, key=lambda o: costs[o]):
            if costs[o] <= room + 1e-9 and search(chosen | {o}, room - costs[o]):
                return True
        failed.add(chosen)
        return False

    return search(frozenset(), room)


def hitting_lower_bound(
    attacks: Sequence[tuple[float, frozenset[int]]],
    fixed: frozenset[int],
    room: float,
    costs: np.ndarray,
) -> float:
    """A proven lower bound on min f(Q) over Q ⊇ ``fixed`` with cost(Q \\ fixed) ≤ ``room``.

    Each ``(v, A)`` is an alteration within the attacker's budget of exact value ``v`` that
    alters the sensors ``A``: under any protection Q missing A it stays feasible, so f(Q) ≥ v.
    Hence f(Q) ≥ max{v : A ∩ Q = ∅}, and the minimum of that over the Q allowed is the largest
    v such that the attacks of value ≥ v cannot all be met within ``room``. ``attacks`` must
    include the unaltered one (value: f with everything protected, A = ∅), which nothing meets.
    """
    live = sorted(((v, a - fixed) for v, a in attacks if not (a & fixed)), key=lambda t: -t[0])
    work = [0]
    must: list[frozenset[int]] = []
    i = 0
    while i < len(live):
        v = live[i][0]
        j = i
        while j < len(live) and live[j][0] >= v:
            must.append(live[j][1])
            j += 1
        if not _can_hit(must, room, costs, work):
            return v
        i = j
    return 0.0  # unreachable when the unaltered attack is included


def harden(
    problem: Problem,
    *,
    protect_budget: float,
    budget: float | None = None,
    protect_costs: Mapping[str, float] | None = None,
    time_limit: float | None = None,
    method: str = "auto",
) -> HardenResult:
    """The protection set within ``protect_budget`` minimising the attacker's optimum at
    ``budget``, with the trade-off curve over every whole protection budget up to it.

    Hitting-set branching: with α*(P) the attacker's optimum under protection P, every
    superset of P that protects none of α*(P)'s sensors keeps α*(P) feasible and so has the
    same optimum (it cannot be higher: protecting more only removes alterations). The search
    therefore branches only on protecting one of α*(P)'s sensors, prunes a subtree when the
    hitting-set lower bound (:func:`hitting_lower_bound`) over every attack found so far
    cannot beat the best protection, and solves each protection set once.
    """
    started = time.perf_counter()
    clock = _deadline(time_limit)
    if not (math.isfinite(protect_budget) and protect_budget >= 0):
        raise ProblemError(
            f"must be a non-negative number, got {protect_budget}", field="protect_budget"
        )
    budget = problem.budget if budget is None else float(budget)
    if not (math.isfinite(budget) and budget >= 0):
        raise ProblemError(f"must be a non-negative number, got {budget}", field="budget")
    problem = problem.with_budget(budget)
    costs = protection_costs(problem, protect_costs)
    names = problem.pomdp.observations
    memo: dict[frozenset[int], _Attack] = {}
    everything = frozenset(range(problem.pomdp.n_observations))
    floor = _solve_at(protect(problem, everything), budget, None, method="exhaustive")
    attacks: list[tuple[float, frozenset[int]]] = [(floor.value, frozenset())]
    stats = {"nodes": 0, "pruned": 0}
    complete = [True]
    certified = [True]

    def attack(protection: frozenset[int]) -> _Attack:
        if protection not in memo:
            memo[protection] = _solve_at(
                protect(problem, protection), budget, clock.share(4), method=method
            )
            found = memo[protection]
            attacks.append((found.value, found.changed))
            certified[0] &= found.certified
        return memo[protection]

    def cost_of(protection: frozenset[int]) -> float:
        return float(sum(costs[o] for o in protection))

    levels = [float(d) for d in default_budgets(protect_budget)]
    curve: list[HardenPoint] = []
    best: frozenset[int] = frozenset()
    for d in levels:
        stack = [frozenset()]
        seen: set[frozenset[int]] = set()
        while stack:
            if clock.expired():
                complete[0] = False
                break
            node = stack.pop()
            if node in seen:
                continue
            seen.add(node)
            stats["nodes"] += 1
            room = d - cost_of(node)
            best_value = attack(best).upper
            if hitting_lower_bound(attacks, node, room, costs) >= best_value - CERTIFY_TOLERANCE:
                stats["pruned"] += 1
                continue
            here = attack(node)
            if _better(here, cost_of(node), attack(best), cost_of(best)):
                best = node
            children = [
                node | {o}
                for o in sorted(here.changed, key=lambda o: (costs[o], names[o]))
                if costs[o] <= room + 1e-9 and (node | {o}) not in seen
            ]
            stack.extend(reversed(children))  # the cheapest sensor first
        reply = attack(best)
        proven = complete[0] and certified[0]
        lower = (
            reply.upper
            if proven
            else min(hitting_lower_bound(attacks, frozenset(), d, costs), reply.upper)
        )
        status = (
            Status.OPTIMAL
            if proven
            else (Status.TIME_LIMIT if not complete[0] else Status.FEASIBLE)
        )
        curve.append(
            HardenPoint(
                protect_budget=d,
                protection=sorted((names[o] for o in best), key=names.index),
                protection_cost=cost_of(best),
                probability=reply.value,
                upper_bound=reply.upper,
                lower_bound=lower,
                attack=reply.alteration,
                status=status,
            )
        )
    final = curve[-1]
    before = attack(frozenset())
    notes = []
    if not certified[0]:
        notes.append(
            "some attacker optimum was not certified (solver time or node limit): values are "
            "reported with their proven bounds"
        )
    if not complete[0]:
        notes.append("stopped by the time limit: best protection found, proven lower bound")
    listed = {names[o]: float(costs[o]) for o in alterable_sensors(problem, budget)}
    return HardenResult(
        problem=problem.name,
        budget=budget,
        protect_budget=float(protect_budget),
        protect_costs=listed,
        protection=final.protection,
        protection_cost=final.protection_cost,
        value_before=before.value,
        value_after=final.probability,
        value_after_upper=final.upper_bound,
        lower_bound=final.lower_bound,
        best_reply=final.attack,
        status=final.status,
        curve=curve,
        solves=len(memo),
        nodes=stats["nodes"],
        pruned=stats["pruned"],
        time_s=time.perf_counter() - started,
        notes=notes,
    )


def _better(candidate: _Attack, cost: float, best: _Attack, best_cost: float) -> bool:
    """Lower guaranteed attacker value, or tied within the tolerance and cheaper."""
    if candidate.upper < best.upper - CERTIFY_TOLERANCE:
        return True
    return candidate.upper <= best.upper + CERTIFY_TOLERANCE and cost < best_cost - 1e-12
