"""What the defender's questions return: one frozen record per answer, each with ``to_dict``
(the ``--json`` output and the data of the audit report).

The records are kept apart from the computations so that the CLI and the report, which only
read answers, need not depend on how they were found.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from misdirect.core import tolerance
from misdirect.core.model import format_alteration
from misdirect.core.notebook import Shown
from misdirect.core.objective import LABELS
from misdirect.core.tables import dataframe, short_float
from misdirect.solvers.run import BudgetResult, curve_fields, curve_table
from misdirect.solvers.status import Status

if TYPE_CHECKING:
    from misdirect.core.notebook import View


@dataclass(frozen=True)
class OnlineAttack:
    """The online attacker's value: unlimited, and with a per-step budget if one was asked."""

    probability: float  # the value asked for: budgeted if ``budget`` is set, else unlimited
    unlimited_probability: float  # every allowed target at any cost (policy iteration's value)
    # a proven upper bound on it (hence on the offline optimum at every budget)
    unlimited_bound: float
    budget: float | None  # paid per altered reading along the run; None: not asked
    budgeted_probability: float | None
    budgeted_bound: float | None  # a proven upper bound on the budgeted value
    cost_unit: float | None  # the common unit the budgeted MDP counts costs in
    product_states: int
    mdp_states: int  # of the MDP actually solved (product states x budget levels)
    policy_evaluations: int
    time_s: float

    def to_dict(self) -> dict[str, Any]:
        """As the audit's JSON ``online`` object writes it (values named ``value``); the
        audit adds ``budgeted_note`` and ``upper_bounds_offline``."""
        return {
            "value": self.probability,
            "unlimited_value": self.unlimited_probability,
            "unlimited_bound": self.unlimited_bound,
            "budget": self.budget,
            "budgeted_value": self.budgeted_probability,
            "budgeted_bound": self.budgeted_bound,
            "cost_unit": self.cost_unit,
            "product_states": self.product_states,
            "mdp_states": self.mdp_states,
            "policy_evaluations": self.policy_evaluations,
            "time_s": self.time_s,
        }


@dataclass(frozen=True)
class DefenceOption:
    """One row of :class:`MonitorComparison`: the attacker's optimum at ``B`` under one
    defence (nothing, the monitor, protected sensors, or both)."""

    defence: str  # "nothing", "monitor", "protection" or "monitor and protection"
    monitor: str | None  # the monitor's name in place, None without one
    protection: list[str]  # the protected sensors, in the problem's order
    protection_cost: float
    probability: float  # exact value of the attacker's best reply
    upper_bound: float  # proven bound on the attacker's optimum under this defence
    status: str  # of that optimum: optimal when certified
    alteration: dict[str, str]  # the attacker's best reply
    # Pr(the monitor raises the alarm) under that reply, with the monitor in place (on the
    # rows without it: how often the monitor would catch the reply, were it added)
    alarm_probability: float

    def to_dict(self) -> dict[str, Any]:
        """As a row of the JSON ``monitor_comparison.rows``."""
        return {
            "defence": self.defence,
            "monitor": self.monitor,
            "protection": self.protection,
            "protection_cost": self.protection_cost,
            "status": self.status,
            "value": self.probability,
            "upper_bound": self.upper_bound,
            "alteration": self.alteration,
            "alarm_probability": self.alarm_probability,
        }


@dataclass(frozen=True)
class MonitorComparison:
    """ "Add this monitor" against "protect these sensors", at one attacker budget ``B``: the
    attacker's certified optimum with no defence, with the monitor, with the protection, and
    with both (:func:`misdirect.defence.monitoring.compare_defences`)."""

    monitor: str  # the monitor's name
    budget: float  # the attacker's budget B
    rows: list[DefenceOption]
    why: str  # how the protection was chosen

    def row(self, defence: str) -> DefenceOption:
        """The row of one defence (``nothing``, ``monitor``, ``protection``, ``monitor and
        protection``)."""
        return next(r for r in self.rows if r.defence == defence)

    def to_dict(self) -> dict[str, Any]:
        """As the JSON ``monitor_comparison`` of audit and harden."""
        return {
            "monitor": self.monitor,
            "budget": self.budget,
            "protection_chosen": self.why,
            "rows": [row.to_dict() for row in self.rows],
        }

    def table(self) -> Any:
        """The rows in a notebook table."""
        from misdirect.core import notebook as nb

        return nb.Table(
            ("defence", "protect", "cost", "attacker's optimum", "status", "Pr(alarm)", "reply"),
            [
                (
                    nb.text(_defence_label(r)),
                    nb.names(r.protection, empty="nothing"),
                    nb.amount(r.protection_cost),
                    nb.number(r.probability),
                    nb.text(r.status),
                    nb.number(r.alarm_probability),
                    nb.changes(r.alteration),
                )
                for r in self.rows
            ],
            f"the monitor against protection, at budget {self.budget:g}",
        )


def _defence_label(row: DefenceOption) -> str:
    if row.defence == "monitor":
        return f"monitor {row.monitor}"
    if row.defence == "monitor and protection":
        return f"monitor {row.monitor} + protection"
    return row.defence


@dataclass(frozen=True)
class SensorAudit:
    """One sensor the attacker could alter within the budget."""

    observation: str
    single_probability: float  # attacker's best with only this sensor alterable
    single_status: str
    single_alteration: dict[str, str]
    in_optimal_attack: bool  # the optimal alteration at the budget alters this sensor
    criticality: float  # the drop of the optimum when this sensor is protected (lower bound)
    criticality_upper: float  # == criticality when exact
    protected_probability: float  # attacker's optimum with this sensor protected
    protected_status: str
    protected_alteration: dict[str, str]

    @property
    def exact(self) -> bool:
        return tolerance.proven(self.criticality, self.criticality_upper)

    def to_dict(self) -> dict[str, Any]:
        """As a row of the audit's JSON ``sensors`` (values named ``value``)."""
        return {
            "observation": self.observation,
            "single_value": self.single_probability,
            "single_status": self.single_status,
            "single_alteration": self.single_alteration,
            "in_optimal_attack": self.in_optimal_attack,
            "criticality": self.criticality,
            "criticality_upper": self.criticality_upper,
            "criticality_exact": self.exact,
            "protected_value": self.protected_probability,
            "protected_status": self.protected_status,
            "protected_alteration": self.protected_alteration,
        }


@dataclass(frozen=True, repr=False)
class AuditResult(Shown):
    """Which sensors are weak, for the attacker's budget ``B`` (:func:`misdirect.audit`).

    ``curve`` holds the attacker's optimum at every budget up to ``B``; ``status``,
    ``probability``, ``upper_bound`` and ``alteration`` are its last point, the optimum at
    ``B``. ``sensors`` has one row per sensor alterable within ``B``, the most critical first.

    Attributes
    ----------
    problem : str
        The problem's name.
    budget : float
        The attacker's budget ``B``.
    baseline_probability : float
        The value with no alteration.
    curve : list of BudgetResult
        The attacker's verified optimum at every whole budget up to ``B``.
    status : str
        Of the optimum at ``B``: ``optimal`` when proven.
    probability : float
        The exact value of ``alteration``, the attacker's best at ``B``.
    upper_bound : float or None
        A proven bound on the optimum at ``B``.
    alteration : dict of str to str
        The attacker's best alteration found at ``B``, as names.
    sensors : list of SensorAudit
        Per alterable sensor: its criticality (how much protecting it lowers the optimum at
        ``B``; exactly 0 for a sensor the optimal attack leaves alone), the optimum with it
        protected, and its single-sensor value. :meth:`to_dataframe` tabulates them.
    online : OnlineAttack or None
        The online attacker's value (sees the state and the controller's memory): an upper
        bound of the offline optimum; None when the time limit cut it (not computed).
    online_budgeted_note : str or None
        Why the budgeted online value (or the whole online value) is missing, if it is.
    certified : bool
        The optimum at ``B`` and every criticality are proven.
    notes : list of str
        What is not proven, and the solver's warnings.
    time_s : float
        Wall time of the audit.
    value : float
        Read-only alias of ``probability``, the name ``to_dict()`` and the JSON use.
    """

    problem: str  # the problem's name
    budget: float  # the attacker's budget B
    baseline_probability: float  # the value with no alteration
    curve: list[BudgetResult]
    status: str  # of the optimum at ``budget``
    probability: float  # exact value of ``alteration``
    upper_bound: float | None  # proven bound on the optimum at ``budget``, if any
    alteration: dict[str, str]  # the attacker's best alteration found at ``budget``
    sensors: list[SensorAudit]
    online: OnlineAttack | None  # budgeted within ``budget`` if possible; None: cut by time
    online_budgeted_note: str | None  # why the budgeted (or any) online value is missing
    certified: bool  # the optimum at B and every criticality are exact
    notes: list[str]  # what is not proven, and the solver's warnings
    time_s: float
    grid: bool = False  # the states are grid cells: the report draws a map
    extra: dict[str, Any] = field(default_factory=dict)  # free for callers; not in to_dict
    objective: str = "probability"  # or "expected_decoy_weight" (weighted decoy sets)
    # B above the most expensive complete alteration: B asked, and the cost worked at instead
    budget_clamped_from: float | None = None
    budget_clamped_to: float | None = None
    # with a monitor: the attacker's optimum without it, with it, with protection and both
    monitor_comparison: MonitorComparison | None = None

    @property
    def objective_label(self) -> str:
        return LABELS[self.objective]

    @property
    def value(self) -> float:
        """``probability``, by the name of ``to_dict()`` and the JSON output."""
        return self.probability

    def __repr__(self) -> str:
        return (
            f"AuditResult(problem={self.problem!r}, budget={self.budget:g}, "
            f"status={self.status}, probability={short_float(self.probability)}, "
            f"alteration={self.alteration!r}, sensors={len(self.sensors)}, "
            f"certified={self.certified})"
        )

    def _view(self) -> View:
        """The audit in a notebook: the optimum at ``B``, the sensors by criticality, the
        curve and the online attacker."""
        from misdirect.core import notebook as nb

        facts = [
            ("objective", nb.text(self.objective_label)),
            ("status", nb.text(self.status)),
            (f"optimum at budget {self.budget:g}", nb.number(self.probability)),
            ("proven bound", nb.number(self.upper_bound)),
            ("alteration", nb.changes(self.alteration)),
            ("without alteration", nb.number(self.baseline_probability)),
            ("certified", nb.text("yes" if self.certified else "no")),
        ]
        if self.online is not None:
            facts.append(("online attacker", nb.number(self.online.probability)))
        facts.append(("time", nb.text(f"{self.time_s:.3g} s")))
        sensors = nb.Table(
            ("sensor", "criticality", "protected: optimum", "alone: optimum", "in attack"),
            [
                (
                    nb.text(row.observation),
                    nb.number(row.criticality)
                    if row.exact
                    else nb.Cell(
                        f"{row.criticality:.6f} to {row.criticality_upper:.6f}", number=True
                    ),
                    nb.number(row.protected_probability),
                    nb.number(row.single_probability),
                    nb.text("yes" if row.in_optimal_attack else "no"),
                )
                for row in self.sensors
            ],
            "sensors, the most critical first",
        )
        notes = list(self.notes)
        if self.online_budgeted_note:
            notes.append(self.online_budgeted_note)
        curve = curve_table(self.curve, caption="the attacker's optimum per budget")
        tables = [sensors, curve]
        if self.monitor_comparison is not None:
            tables.insert(0, self.monitor_comparison.table())
        return nb.View(f"{self.problem or 'problem'}: audit", facts, tables, notes)

    def to_dataframe(self) -> Any:
        """The sensors as a ``pandas.DataFrame``, one row per alterable sensor, most critical
        first (the columns of :meth:`SensorAudit.to_dict`, alterations as ``o1 → o2``).

        Raises
        ------
        ImportError
            pandas is not installed (it is optional: ``pip install pandas``).
        """
        rows = [sensor.to_dict() for sensor in self.sensors]
        for row in rows:
            for name in ("single_alteration", "protected_alteration"):
                row[name] = format_alteration(row[name])
        return dataframe(rows, list(rows[0]) if rows else [])

    def to_dict(self) -> dict[str, Any]:
        """The audit as ``audit --json`` writes it (``misdirect-result/1``, the fields of
        ``$defs/audit``, ``warnings`` and ``notes``): values are named ``value``."""
        points, stats = curve_fields(self.curve)
        return {
            "problem": self.problem,
            "objective": self.objective,
            "budget": self.budget,
            **_clamps(self, "budget"),
            "status": self.status,
            "value": self.probability,
            "alteration": self.alteration,
            "upper_bound": self.upper_bound,
            "baseline_value": self.baseline_probability,
            "certified": self.certified,
            "time_s": self.time_s,
            "curve": points,
            "stats": stats,
            "sensors": [sensor.to_dict() for sensor in self.sensors],
            "online": None
            if self.online is None
            else {
                **self.online.to_dict(),
                "budgeted_note": self.online_budgeted_note,
                "upper_bounds_offline": self.online.unlimited_probability
                >= self.probability - tolerance.CERTIFY,
            },
            "monitor_comparison": None
            if self.monitor_comparison is None
            else self.monitor_comparison.to_dict(),
            "warnings": [],
            "notes": list(self.notes),
        }


def _clamps(result: AuditResult | HardenResult, name: str) -> dict[str, float | None]:
    """A budget clamped: the one asked (``_from``) and the one worked at (``_to``), both
    null when it was not."""
    return {f"{name}_clamped_{end}": getattr(result, f"{name}_clamped_{end}") for end in EDGES}


EDGES = ("from", "to")


@dataclass(frozen=True)
class HardenPoint:
    """The best protection within one protection budget ``d``.

    The attacker's best reply is ``probability`` and ``attack``; ``value`` and
    ``alteration`` are read-only aliases of them, by the names of :meth:`to_dict` and the
    JSON output (as in :class:`~misdirect.SolveResult`).
    """

    protect_budget: float
    protection: list[str]  # the sensors to protect, in the problem's order
    protection_cost: float
    probability: float  # exact value of the attacker's best reply found
    upper_bound: float  # proven bound on the attacker's optimum under ``protection``
    lower_bound: float  # proven: no protection within d holds the attacker below this
    attack: dict[str, str]  # the attacker's best reply found under ``protection``
    status: Status  # optimal when the min–max is proven, else time_limit / feasible

    @property
    def value(self) -> float:
        """``probability``: the exact value of the attacker's best reply (the JSON's name)."""
        return self.probability

    @property
    def alteration(self) -> dict[str, str]:
        """``attack``: the attacker's best reply under ``protection`` (the JSON's name)."""
        return self.attack

    def to_dict(self) -> dict[str, Any]:
        """As a point of the harden JSON's ``curve``: the attacker's best reply is
        ``value`` and ``alteration``, as in solve."""
        return {
            "protect_budget": self.protect_budget,
            "protection": self.protection,
            "protection_cost": self.protection_cost,
            "status": str(self.status),
            "value": self.probability,
            "alteration": self.attack,
            "upper_bound": self.upper_bound,
            "lower_bound": self.lower_bound,
        }


@dataclass(frozen=True, repr=False)
class HardenResult(Shown):
    """Which sensors to protect: the protection within ``protect_budget`` (``D``) that
    minimises the attacker's optimum at ``budget`` (``B``) (:func:`misdirect.harden`).

    ``curve`` has one :class:`HardenPoint` per whole protection budget up to ``D``; the
    fields from ``protection`` to ``status`` repeat its last point, the answer at ``D``.

    Attributes
    ----------
    problem : str
        The problem's name.
    budget : float
        The attacker's budget ``B``.
    protect_budget : float
        The defender's budget ``D``.
    protect_costs : dict of str to float
        What protecting each sensor alterable within ``B`` costs.
    protection : list of str
        The sensors to protect, in the problem's order.
    protection_cost : float
        What that protection costs.
    value_before : float
        The attacker's optimum with nothing protected (exact value).
    value_after : float
        The exact value of the attacker's best reply under ``protection``.
    value_after_upper : float
        A proven bound on the attacker's optimum under ``protection``.
    lower_bound : float
        Proven: no protection within ``D`` holds the attacker below this.
    best_reply : dict of str to str
        The attacker's best reply under ``protection``, as names.
    status : str
        ``optimal`` when the min–max is proven, else ``time_limit`` or ``feasible``.
    curve : list of HardenPoint
        The trade-off: the best protection within every whole budget up to ``D``
        (:meth:`to_dataframe` tabulates it).
    solves, nodes, pruned : int
        Attacker solves, search nodes, and nodes cut off by the hitting-set bound.
    time_s : float
        Wall time of the search.
    notes : list of str
        What is not proven, and why.
    value, alteration, upper_bound, value_unprotected
        Read-only aliases of ``value_after``, ``best_reply``, ``value_after_upper`` and
        ``value_before``, by the names of :meth:`to_dict` and the JSON output (as in
        :class:`~misdirect.SolveResult`).
    """

    problem: str  # the problem's name
    budget: float  # the attacker's budget B
    protect_budget: float  # the defender's budget D
    protect_costs: dict[str, float]  # what protecting each sensor alterable within B costs
    protection: list[str]
    protection_cost: float
    value_before: float  # the attacker's optimum found with nothing protected (exact value)
    value_after: float  # exact value of the attacker's best reply under ``protection``
    value_after_upper: float  # proven bound on the attacker's optimum under ``protection``
    lower_bound: float  # proven: no protection within D holds the attacker below this
    best_reply: dict[str, str]
    status: str  # optimal when the min–max is proven, else time_limit / feasible
    curve: list[HardenPoint]
    solves: int  # attacker solves: one per protection set examined
    nodes: int  # search nodes visited over every protection budget
    pruned: int  # of which cut off by the hitting-set lower bound
    time_s: float
    notes: list[str] = field(default_factory=list)  # what is not proven, and why
    # a budget above what buys everything (B: every alteration; D: protecting every sensor
    # alterable within B): the budget asked, and the one worked at instead
    budget_clamped_from: float | None = None
    budget_clamped_to: float | None = None
    protect_budget_clamped_from: float | None = None
    protect_budget_clamped_to: float | None = None
    objective: str = "probability"  # or "expected_decoy_weight" (weighted decoy sets)
    # with a monitor: the attacker's optimum without it, with it, with protection and both
    monitor_comparison: MonitorComparison | None = None

    @property
    def value(self) -> float:
        """``value_after``: the exact value of the attacker's best reply under ``protection``."""
        return self.value_after

    @property
    def alteration(self) -> dict[str, str]:
        """``best_reply``: the attacker's best reply under ``protection``."""
        return self.best_reply

    @property
    def upper_bound(self) -> float:
        """``value_after_upper``: a proven bound on the attacker's optimum under
        ``protection``."""
        return self.value_after_upper

    @property
    def value_unprotected(self) -> float:
        """``value_before``: the attacker's optimum with nothing protected."""
        return self.value_before

    def __repr__(self) -> str:
        return (
            f"HardenResult(problem={self.problem!r}, budget={self.budget:g}, "
            f"protect_budget={self.protect_budget:g}, status={self.status}, "
            f"protection={self.protection!r}, value_before={short_float(self.value_before)}, "
            f"value_after={short_float(self.value_after)})"
        )

    def _view(self) -> View:
        """The hardening in a notebook: the protection, the attacker's optimum before and
        after, and the trade-off per protection budget."""
        from misdirect.core import notebook as nb

        facts = [
            ("objective", nb.text(LABELS.get(self.objective, self.objective))),
            ("status", nb.text(self.status)),
            ("protect", nb.names(self.protection, empty="nothing")),
            ("protection cost", nb.amount(self.protection_cost)),
            (f"attacker's optimum at budget {self.budget:g}, before", nb.number(self.value_before)),
            ("after", nb.number(self.value_after)),
            ("proven bound after", nb.number(self.value_after_upper)),
            ("no protection holds it below", nb.number(self.lower_bound)),
            ("attacker's best reply", nb.changes(self.best_reply)),
            ("time", nb.text(f"{self.time_s:.3g} s")),
        ]
        curve = nb.Table(
            ("protect budget", "protect", "cost", "status", "attacker", "bound", "reply"),
            [
                (
                    nb.amount(p.protect_budget),
                    nb.names(p.protection, empty="nothing"),
                    nb.amount(p.protection_cost),
                    nb.text(p.status.value),
                    nb.number(p.probability),
                    nb.number(p.upper_bound),
                    nb.changes(p.attack),
                )
                for p in self.curve
            ],
            "the best protection per protection budget",
        )
        title = f"{self.problem or 'problem'}: hardening"
        tables = [curve]
        if self.monitor_comparison is not None:
            tables.insert(0, self.monitor_comparison.table())
        return nb.View(title, facts, tables, self.notes)

    def to_dataframe(self) -> Any:
        """The trade-off curve as a ``pandas.DataFrame``: one row per protection budget
        (the columns of :meth:`HardenPoint.to_dict`, protections as ``o1, o2`` and
        alterations as ``o1 → o2``).

        Raises
        ------
        ImportError
            pandas is not installed (it is optional: ``pip install pandas``).
        """
        rows = [point.to_dict() for point in self.curve]
        for row in rows:
            row["protection"] = ", ".join(row["protection"])
            row["alteration"] = format_alteration(row["alteration"])
        return dataframe(rows, list(rows[0]) if rows else [])

    def to_dict(self) -> dict[str, Any]:
        """The hardening as ``harden --json`` writes it (``misdirect-result/1``, the fields
        of ``$defs/harden``, ``warnings`` and ``notes``): the attacker's best reply under the
        protection is ``value`` and ``alteration``, the optimum with nothing protected
        ``value_unprotected``."""
        return {
            "problem": self.problem,
            "objective": self.objective,
            "budget": self.budget,
            **_clamps(self, "budget"),
            "protect_budget": self.protect_budget,
            **_clamps(self, "protect_budget"),
            "protect_costs": self.protect_costs,
            "protection": self.protection,
            "protection_cost": self.protection_cost,
            "status": self.status,
            "value": self.value_after,
            "alteration": self.best_reply,
            "upper_bound": self.value_after_upper,
            "lower_bound": self.lower_bound,
            "value_unprotected": self.value_before,
            "time_s": self.time_s,
            "curve": [point.to_dict() for point in self.curve],
            "stats": {"solves": self.solves, "nodes": self.nodes, "pruned": self.pruned},
            "monitor_comparison": None
            if self.monitor_comparison is None
            else self.monitor_comparison.to_dict(),
            "warnings": [],
            "notes": list(self.notes),
        }
