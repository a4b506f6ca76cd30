"""The one place that turns results into the ``--json`` output of every command.

Every document follows one versioned JSON Schema, shipped with the package
(``misdirect/schema/misdirect-result-1.json``, described in docs/json-schema.md): it names
itself (``"schema": "misdirect-result/1"``) and its ``command``, and one concept has one name
whichever command prints it (``value``, ``alteration``, ``upper_bound``, ``status``,
``objective``, ``time_s``, ``written``, ``warnings``, ``notes``, ``outcomes``). The library's
result types keep their own ``to_dict``; the CLI's contract is built here, so that a new
command cannot invent a new name for an old concept.
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Sequence
from functools import cache
from importlib import resources
from pathlib import Path
from typing import TYPE_CHECKING, Any

from misdirect.core import tolerance
from misdirect.solvers.stats import AutoStats, MethodStats

if TYPE_CHECKING:
    from misdirect.core.evaluate import Evaluation
    from misdirect.core.model import Problem
    from misdirect.core.simulate import Simulation
    from misdirect.defence.results import AuditResult, HardenPoint, HardenResult
    from misdirect.solvers.run import BudgetResult, SolveResult

SCHEMA = "misdirect-result/1"
SCHEMA_FILE = "misdirect-result-1.json"


@cache
def result_schema() -> dict[str, Any]:
    """The JSON Schema every ``--json`` document follows (read from the package data)."""
    text = resources.files("misdirect").joinpath("schema", SCHEMA_FILE).read_text("utf-8")
    schema: dict[str, Any] = json.loads(text)
    return schema


def document(
    command: str,
    *,
    written: Iterable[str | Path] = (),
    warnings: Iterable[str] = (),
    notes: Iterable[str] = (),
    **fields: Any,
) -> dict[str, Any]:
    """A document of ``command``: the schema and command first, the fields, then the written
    files, warnings and notes (always lists, empty when there are none)."""
    return {
        "schema": SCHEMA,
        "command": command,
        **fields,
        "written": [str(path) for path in written],
        "warnings": list(warnings),
        "notes": list(notes),
    }


def error_document(command: str | None, message: str, **context: Any) -> dict[str, Any]:
    """The document of a command that failed: the message, and the field and file it names."""
    shown = {k: v for k, v in context.items() if v}
    return {"schema": SCHEMA, "command": command, "error": {"message": message, **shown}}


# -- solve and its curve ------------------------------------------------------------------------


def curve_point(point: BudgetResult, *, stats: bool = True) -> dict[str, Any]:
    """One budget's answer. ``stats``: the method's counters for this budget alone (left out
    when the whole run shares one record, which then sits at the top level)."""
    shown: dict[str, Any] = {
        "budget": point.budget,
        "status": str(point.status),
        "value": point.probability,
        "alteration": point.alteration,
        "cost": point.cost,
        "upper_bound": point.upper_bound,
        "error_bound": point.error_bound,
        "gap": point.gap,
        "certified_by": point.certified_by,
        "certification": dict(point.notes),
    }
    if stats:
        shown["stats"] = _point_stats(point.stats)
    return shown


def _point_stats(stats: MethodStats) -> dict[str, Any]:
    """A point's own counters (auto's reason, common to the run, left to the top level)."""
    shown = stats.to_dict()
    shown.pop("auto_reason", None)
    return shown


def curve(points: Sequence[BudgetResult]) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    """The curve's points and the run's ``stats``, kept apart: a method that answers every
    budget from one run (enumeration) has one record, shown once at the top level; one that
    solves each budget on its own (the MILP) has a record per point."""
    records = [point.stats for point in points]
    shared = all(record == records[-1] for record in records)
    if shared:
        return [curve_point(p, stats=False) for p in points], records[-1].to_dict()
    reasons = {r.reason for r in records if isinstance(r, AutoStats)}
    run = {"auto_reason": reasons.pop()} if len(reasons) == 1 else {}
    return [curve_point(p) for p in points], run


def solve(result: SolveResult, *, notes: Iterable[str] = ()) -> dict[str, Any]:
    """``solve --json``: the answer at the largest budget, then the curve and the run."""
    final = result.final
    points, stats = curve(result.curve)
    return document(
        "solve",
        problem=result.problem,
        objective=result.objective,
        status=str(final.status),
        value=final.probability,
        alteration=final.alteration,
        cost=final.cost,
        budget=final.budget,
        baseline_value=result.baseline_probability,
        upper_bound=final.upper_bound,
        gap=final.gap,
        error_bound=final.error_bound,
        method=result.method,
        certified_by=final.certified_by,
        budget_clamped_from=result.budget_clamped_from,
        budget_clamped_to=result.budget_clamped_to,
        interrupted=result.interrupted,
        time_s=result.time_s,
        curve=points,
        stats=stats,
        warnings=result.warnings,
        notes=[*result.notes, *notes],
    )


# -- evaluate and simulate: outcomes ------------------------------------------------------------


def outcome(
    kind: str,
    state: str | None,
    probability: float,
    *,
    runs: int | None = None,
    interval: tuple[float, float] | None = None,
) -> dict[str, Any]:
    """Where runs end: ``kind`` is decoy, goal (absorbing, not a decoy), trapped (never
    absorbed) or unfinished (simulate: out of steps); ``state`` names the state, or is null
    for a whole kind. ``probability`` is exact (evaluate) or the observed frequency
    (simulate, which adds ``runs`` and the 95 % interval)."""
    shown: dict[str, Any] = {"kind": kind, "state": state, "probability": probability}
    if runs is not None:
        shown["runs"] = runs
    if interval is not None:
        shown["interval_95"] = list(interval)
    return shown


def _kind(problem: Problem, state: str) -> str:
    index = problem.pomdp.states.index(state)
    return "decoy" if bool(problem.objective.target[index]) else "goal"


def evaluation(problem: Problem, result: Evaluation, baseline: float) -> dict[str, Any]:
    """``evaluate --json``: the exact value of one alteration and where runs end."""
    ends = [outcome(_kind(problem, s), s, p) for s, p in result.outcomes.items()]
    if result.never_absorbed > 0:
        ends.append(outcome("trapped", None, result.never_absorbed))
    extra = {"decoy_sets": result.decoy_sets} if result.decoy_sets else {}
    return document(
        "evaluate",
        problem=problem.name,
        objective=result.objective,
        value=result.probability,
        alteration=result.alteration,
        cost=result.cost,
        budget=problem.budget,
        within_budget=result.within_budget,
        baseline_value=baseline,
        error_bound=result.error_bound,
        outcomes=ends,
        **extra,
        product_states=result.product_states,
        product_transitions=result.product_transitions,
        time_s=result.time_s,
        warnings=result.warnings,
        notes=result.notes,
    )


def simulation(
    problem: Problem,
    alteration: dict[str, str],
    result: Simulation,
    *,
    exact: float,
    seed: int,
    max_steps: int,
    time_s: float,
    written: Iterable[str | Path] = (),
) -> dict[str, Any]:
    """``simulate --json``: per state and per kind, how many runs ended there, the frequency
    and its 95 % interval, with the exact decoy probability (``value``) beside them."""
    from misdirect.core.simulate import wilson_interval

    runs = result.runs

    def counted(kind: str, state: str | None, hits: int) -> dict[str, Any]:
        return outcome(kind, state, hits / runs, runs=hits, interval=wilson_interval(hits, runs))

    ends = [counted("decoy", s, n) for s, n in result.decoys.items()]
    ends += [counted("goal", s, n) for s, n in result.absorbed.items()]
    totals = {
        "decoy": counted("decoy", None, result.decoy_hits),
        "goal": counted("goal", None, sum(result.absorbed.values())),
        "trapped": counted("trapped", None, result.trapped),
        "unfinished": counted("unfinished", None, result.unfinished),
    }
    low, high = totals["decoy"]["interval_95"]
    return document(
        "simulate",
        problem=problem.name,
        objective="probability",  # a run hits a decoy or not: weights are not simulated
        alteration=alteration,
        runs=runs,
        seed=seed,
        max_steps=max_steps,
        value=exact,
        outcomes=ends,
        totals=totals,
        exact_within_interval=bool(low <= exact <= high),
        mean_steps_finished=result.mean_steps,
        time_s=time_s,
        written=written,
        warnings=problem.warnings,
        notes=problem.notes,
    )


# -- the defender's commands --------------------------------------------------------------------


def audit(result: AuditResult, *, written: Iterable[str | Path] = ()) -> dict[str, Any]:
    """``audit --json``: the optimum at B, its curve, each sensor, the online attacker."""
    points, stats = curve(result.curve)
    online = result.online
    return document(
        "audit",
        problem=result.problem,
        objective=result.objective,
        budget=result.budget,
        budget_clamped_from=result.budget_clamped_from,
        budget_clamped_to=result.budget_clamped_to,
        status=result.status,
        value=result.probability,
        alteration=result.alteration,
        upper_bound=result.upper_bound,
        baseline_value=result.baseline_probability,
        certified=result.certified,
        time_s=result.time_s,
        curve=points,
        stats=stats,
        sensors=[
            {
                "observation": s.observation,
                "single_value": s.single_probability,
                "single_status": s.single_status,
                "single_alteration": s.single_alteration,
                "in_optimal_attack": s.in_optimal_attack,
                "criticality": s.criticality,
                "criticality_upper": s.criticality_upper,
                "criticality_exact": s.exact,
                "protected_value": s.protected_probability,
                "protected_status": s.protected_status,
                "protected_alteration": s.protected_alteration,
            }
            for s in result.sensors
        ],
        online=None  # not computed within the time limit (the notes say so)
        if online is None
        else {
            "value": online.probability,
            "unlimited_value": online.unlimited_probability,
            "budget": online.budget,
            "budgeted_value": online.budgeted_probability,
            "budgeted_note": result.online_budgeted_note,
            "upper_bounds_offline": online.unlimited_probability
            >= result.probability - tolerance.CERTIFY,
            "cost_unit": online.cost_unit,
            "product_states": online.product_states,
            "mdp_states": online.mdp_states,
            "policy_evaluations": online.policy_evaluations,
            "time_s": online.time_s,
        },
        written=written,
        notes=result.notes,
    )


def _harden_point(point: HardenPoint) -> dict[str, Any]:
    return {
        "protect_budget": point.protect_budget,
        "protection": point.protection,
        "protection_cost": point.protection_cost,
        "status": str(point.status),
        "value": point.probability,
        "alteration": point.attack,
        "upper_bound": point.upper_bound,
        "lower_bound": point.lower_bound,
    }


def harden(
    result: HardenResult, *, objective: str, written: Iterable[str | Path] = ()
) -> dict[str, Any]:
    """``harden --json``: the protection, the attacker's best reply under it (``value``,
    ``alteration``, as in solve), the trade-off curve and the search's counters."""
    return document(
        "harden",
        problem=result.problem,
        objective=objective,
        budget=result.budget,
        budget_clamped_from=result.budget_clamped_from,
        budget_clamped_to=result.budget_clamped_to,
        protect_budget=result.protect_budget,
        protect_budget_clamped_from=result.protect_budget_clamped_from,
        protect_budget_clamped_to=result.protect_budget_clamped_to,
        protect_costs=result.protect_costs,
        protection=result.protection,
        protection_cost=result.protection_cost,
        status=result.status,
        value=result.value_after,
        alteration=result.best_reply,
        upper_bound=result.value_after_upper,
        lower_bound=result.lower_bound,
        value_unprotected=result.value_before,
        time_s=result.time_s,
        curve=[_harden_point(point) for point in result.curve],
        stats={"solves": result.solves, "nodes": result.nodes, "pruned": result.pruned},
        written=written,
        notes=result.notes,
    )


# -- commands that write files ------------------------------------------------------------------


def written_files(command: str, paths: Iterable[str | Path], **fields: Any) -> dict[str, Any]:
    """A command whose answer is the files it wrote (scenario, show, export-milp, ...)."""
    return document(command, **fields, written=paths)


def text_output(command: str, output: Path | None, text: str, **fields: Any) -> dict[str, Any]:
    """A command that writes one text: the file, or, without one, the text as ``content``."""
    if output is not None:
        return document(command, **fields, written=[output])
    return document(command, **fields, content=text)
