"""The defender's commands (issue 14; docs/defence.md): audit and harden."""

from __future__ import annotations

import json
from enum import StrEnum
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer
from rich.markup import escape
from rich.table import Table

from misdirect.cli.cluster import ClusterOption, WorkersOption, check_workers
from misdirect.cli.common import (
    check_budget,
    check_range,
    check_seconds,
    fmt_alteration,
    out,
    print_json,
    print_notes,
    wrote,
)
from misdirect.cli.options import (
    AttackerBudgetOption,
    JsonOption,
    ProblemSource,
    one_budget,
    problem_input,
)
from misdirect.cli.pictures import CoordinatesOption
from misdirect.core.model import quoted_name
from misdirect.errors import ProblemError
from misdirect.io.files import check_output_path, prepare_output_dir, write_output
from misdirect.report import json_output

if TYPE_CHECKING:
    from misdirect.defence import AuditResult, HardenResult
    from misdirect.defence.results import MonitorComparison
    from misdirect.defence.robust import RobustResult


# -- audit --------------------------------------------------------------------------------------


@problem_input
def audit(
    source: ProblemSource,
    budget: AttackerBudgetOption = None,
    output: Annotated[
        Path | None,
        typer.Option(
            "--output", "-o", help="Folder for report.md, curve.csv, sensors.csv and figures."
        ),
    ] = None,
    time_limit: Annotated[
        float | None,
        typer.Option(
            help="Seconds for the audit's searches; what is not proven is labelled. Reading the "
            "model and the exact evaluation of each answer come on top."
        ),
    ] = None,
    cluster: ClusterOption = None,
    workers: WorkersOption = None,
    coordinates: CoordinatesOption = None,
    as_json: JsonOption = False,
) -> None:
    """Which sensors are weak: the attacker's optimum for every budget up to B, each sensor's
    criticality and single-sensor value, and the online attacker's value. With a monitor
    (--monitor, --stealth): also the optimum without it, with it, with the most critical
    sensor protected, and with both."""
    from misdirect.core.grid import state_cells
    from misdirect.defence import audit as run_audit
    from misdirect.distributed import connect

    check_workers(workers)
    attacker_budget = one_budget(budget, "audit")
    check_seconds(time_limit)
    if coordinates is not None and output is None:
        raise ProblemError(
            "places the states on -o DIR's map.png: give -o DIR", field="--coordinates"
        )
    problem = source.load()  # first: a file that does not load leaves no folder behind
    if coordinates is not None:
        state_cells(problem, coordinates)  # a wrong --coordinates fails before the audit
    if output is not None:
        prepare_output_dir(output, field="-o")  # before the audit's minutes
    with connect(cluster, workers) as pool:
        result = run_audit(problem, budget=attacker_budget, time_limit=time_limit, pool=pool)
    written: list[str] = []
    if output is not None:
        from misdirect.report.defence import write_audit_report

        written = [str(p) for p in write_audit_report(problem, result, output, coordinates)]
    if as_json:
        print_json(json_output.audit(result, written=written))
        return
    _print_audit(result)
    _print_comparison(result.monitor_comparison)
    if output is not None:
        wrote(f"wrote {len(written)} files to {output}/: {', '.join(_names(written))}")


def _names(written: list[str]) -> list[str]:
    """The files a report wrote, by name (they share its folder)."""
    return [Path(path).name for path in written]


def _print_audit(result: AuditResult) -> None:
    title = f"{result.problem}: sensors at budget {result.budget:g}"
    table = Table(title=escape(title))
    columns = ("sensor", "criticality", "protected → optimum", "single-sensor value", "in attack")
    for column in columns:
        table.add_column(column, justify="left" if column == "sensor" else "right", overflow="fold")
    for s in result.sensors:
        crit = (
            f"{s.criticality:.6f}" if s.exact else f"{s.criticality:.6f}..{s.criticality_upper:.6f}"
        )
        table.add_row(
            escape(s.observation),
            crit,
            f"{s.protected_probability:.6f}",
            f"{s.single_probability:.6f}",
            "yes" if s.in_optimal_attack else "",
        )
    out.print(table)
    online = result.online
    parts = [
        f"optimum at B {result.probability:.6f} ({result.status}: "
        f"{fmt_alteration(result.alteration)})",
        f"without attack {result.baseline_probability:.6f}",
    ]
    note = escape(result.online_budgeted_note or "")
    if online is None:
        parts.append(f"online attacker not computed: {note}")
    else:
        parts.append(
            f"online attacker: unlimited {online.unlimited_bound:.6f} (a proven upper bound)"
        )
        if online.budgeted_probability is not None:
            parts.append(f"paying per reading within B {online.budgeted_probability:.6f}")
        else:
            parts.append(f"budgeted online not computed: {note}")
    parts.append(f"{result.time_s:.2f} s")
    if result.budget_clamped_to is not None:
        parts.insert(0, f"B solved as {result.budget_clamped_to:g} (no alteration costs more)")
    out.print(" · ".join(parts), highlight=False)
    print_notes(result.notes)


def _print_comparison(comparison: MonitorComparison | None) -> None:
    """With a monitor: the attacker's optimum at B under no defence, the monitor, the
    protection and both, one row each (docs/stealth.md)."""
    if comparison is None:
        return
    table = Table(
        title=escape(
            f"add the monitor ({comparison.monitor}) or protect sensors? the attacker's "
            f"optimum at budget {comparison.budget:g}"
        )
    )
    columns = ("defence", "protect", "cost", "attacker's optimum", "status", "caught", "reply")
    for column in columns:
        left = column in ("defence", "protect", "reply")
        table.add_column(column, justify="left" if left else "right", overflow="fold")
    labels = {
        "nothing": "nothing",
        "monitor": "monitor",
        "protection": "protection",
        "monitor and protection": "monitor + protection",
    }
    for row in comparison.rows:
        table.add_row(
            labels[row.defence],
            escape(", ".join(map(quoted_name, row.protection)) or "-"),
            f"{row.protection_cost:g}",
            f"{row.probability:.6f}",
            row.status,
            f"{row.alarm_probability:.6f}",
            fmt_alteration(row.alteration),
        )
    out.print(table)
    out.print(
        escape(
            f"{comparison.why} · caught: Pr(the monitor raises the alarm) under the "
            "attacker's reply (without the monitor: were it added)"
        ),
        highlight=False,
    )


# -- harden -------------------------------------------------------------------------------------


def parse_protect_costs(text: str | None) -> dict[str, float]:
    """``default=1,o3=2`` (split at the last ``=``, so names like Storm's ``o=2`` work)."""
    costs: dict[str, float] = {}
    for part in (text or "").split(","):
        if not part.strip():
            continue
        name, sep, value = part.rpartition("=")
        name = name.strip()
        if not sep or not name:
            raise ProblemError(
                f"expected OBS=COST or default=COST (e.g. default=1,o3=2), got {part!r}",
                field="--protect-cost",
            )
        try:
            costs[name] = float(value)
        except ValueError:
            raise ProblemError(
                f"the cost of {name!r} must be a number, got {value!r}", field="--protect-cost"
            ) from None
    return costs


@problem_input
def harden(
    protect_budget: Annotated[
        float, typer.Option("--protect-budget", help="Total protection cost D allowed.")
    ],
    source: ProblemSource,
    budget: AttackerBudgetOption = None,
    protect_cost: Annotated[
        str | None,
        typer.Option(
            "--protect-cost", help="Protection costs, e.g. default=1,o3=2 (default: 1 each)."
        ),
    ] = None,
    time_limit: Annotated[
        float | None,
        typer.Option(
            help="Seconds for the search; then the best protection found and a proven lower "
            "bound. Reading the model and the exact evaluation of each answer come on top."
        ),
    ] = None,
    cluster: ClusterOption = None,
    workers: WorkersOption = None,
    output: Annotated[
        Path | None,
        typer.Option(
            "--output",
            "-o",
            help="Folder for report.md and tradeoff.png (protection budget vs the attacker's "
            "optimum).",
        ),
    ] = None,
    as_json: JsonOption = False,
) -> None:
    """Which sensors to protect: the set within cost D that minimises the attacker's optimum
    at budget B (exact min-max), with the trade-off over every protection budget up to D.
    With a monitor (--monitor, --stealth): also the optimum without it, with it, with the
    best protection without it, and with both."""
    from misdirect.defence import harden as run_harden
    from misdirect.distributed import connect

    check_workers(workers)
    check_budget(protect_budget, "--protect-budget")
    attacker_budget = one_budget(budget, "harden")
    check_seconds(time_limit)
    costs = parse_protect_costs(protect_cost)
    problem = source.load()  # first: a file that does not load leaves no folder behind
    if output is not None:
        prepare_output_dir(output, field="-o")  # before the search's minutes
    try:
        with connect(cluster, workers) as pool:
            result = run_harden(
                problem,
                protect_budget=protect_budget,
                budget=attacker_budget,
                protect_costs=costs,
                time_limit=time_limit,
                pool=pool,
            )
    except ProblemError as error:
        if error.field == "protect_costs":
            error.field = "--protect-cost"
        raise
    written: list[str] = []
    if output is not None:
        from misdirect.report.defence import write_harden_report

        written = [str(p) for p in write_harden_report(result, output)]
    if as_json:
        print_json(json_output.harden(result, written=written))
    else:
        _print_harden(result)
        _print_comparison(result.monitor_comparison)
        if output is not None:
            wrote(f"wrote {len(written)} files to {output}/: {', '.join(_names(written))}")


def _print_harden(result: HardenResult) -> None:
    table = Table(
        title=escape(
            f"{result.problem}: protection against an attacker with budget {result.budget:g}"
        )
    )
    columns = ("D", "protect", "cost", "attacker's optimum", "lower bound", "best reply", "status")
    for column in columns:
        wide = column in ("protect", "best reply")
        table.add_column(column, justify="left" if wide else "right", overflow="fold")
    for point in result.curve:
        table.add_row(
            f"{point.protect_budget:g}",
            escape(", ".join(map(quoted_name, point.protection)) or "nothing"),
            f"{point.protection_cost:g}",
            f"{point.probability:.6f}",
            f"{point.lower_bound:.6f}",
            fmt_alteration(point.attack),
            point.status,
        )
    out.print(table)
    out.print(
        escape(
            f"protect {', '.join(map(quoted_name, result.protection)) or 'nothing'} (cost "
            f"{result.protection_cost:g}): the attacker's optimum drops from "
            f"{result.value_before:.6f} to {result.value_after:.6f} ({result.status}) · "
            f"{result.solves} attacker solves, {result.nodes} nodes · {result.time_s:.2f} s"
        ),
        highlight=False,
    )
    if result.budget_clamped_to is not None:
        out.print(f"B solved as {result.budget_clamped_to:g} (no alteration costs more)")
    if result.protect_budget_clamped_to is not None:
        out.print(
            f"D solved as {result.protect_budget_clamped_to:g} (protecting every sensor the "
            "attacker can alter costs no more)"
        )
    print_notes(result.notes)


# -- controller robust --------------------------------------------------------------------------


class RobustObjective(StrEnum):
    decoy = "decoy"
    goal = "goal"


class RobustMaster(StrEnum):
    exact = "exact"
    gradient = "gradient"
    paynt = "paynt"


@problem_input
def controller_robust(
    source: ProblemSource,
    output: Annotated[
        Path,
        typer.Option(
            "--output",
            "-o",
            help="The robust controller to write: PAYNT's .fsc.json, or misdirect's rules "
            "when the name ends in .yaml/.yml (either loads back with --controller).",
        ),
    ],
    budget: AttackerBudgetOption = None,
    memory: Annotated[
        int, typer.Option("--memory", help="Memory nodes of the controllers searched.")
    ] = 1,
    objective: Annotated[
        RobustObjective,
        typer.Option(
            help="decoy: minimise the worst-case Pr(decoy); goal: maximise the worst-case "
            "Pr(goal) (an absorbing state that is not a decoy)."
        ),
    ] = RobustObjective.decoy,
    randomized: Annotated[
        bool,
        typer.Option(
            "--randomized",
            help="Search randomized controllers by gradient (a local search: the worst case "
            "is certified, the controller's optimality is not); default: deterministic ones, "
            "by exact enumeration.",
        ),
    ] = False,
    master: Annotated[
        RobustMaster | None,
        typer.Option(
            "--master",
            help="The master: exact (deterministic, enumeration; the default), gradient "
            "(randomized; what --randomized picks) or paynt (deterministic controllers "
            "synthesized by PAYNT against the alterations found, reweighted toward the worst "
            "case; needs PAYNT). gradient and paynt prove no bound; the worst case is certified.",
        ),
    ] = None,
    min_goal: Annotated[
        float | None,
        typer.Option(
            help="With --objective decoy: a floor on the nominal Pr(goal). The exact master "
            "searches only controllers meeting it; --randomized ranks a controller meeting it "
            "first."
        ),
    ] = None,
    restarts: Annotated[
        int,
        typer.Option(help="--randomized: starts of the gradient search per round."),
    ] = 4,
    seed: Annotated[
        int, typer.Option(help="Seed of --randomized's random starts (and of the random scenario).")
    ] = 0,
    time_limit: Annotated[
        float | None,
        typer.Option(help="Seconds for the search; then the best controller with its bounds."),
    ] = None,
    baselines: Annotated[
        str,
        typer.Option(
            "--baselines",
            help="The baselines measured at the same budget, comma-separated: given, blind, "
            "harden (protection at the matching budget, unit costs only), paynt (PAYNT's "
            "nominally optimal controller, where installed); all, or none.",
        ),
    ] = "all",
    as_json: JsonOption = False,
) -> None:
    """The controller that holds up best against every alteration within budget B (constraint
    generation: a master over the class, deterministic by exact enumeration or --randomized by
    gradient, misdirect.solve as the certified oracle), with its certified worst case and the
    baselines' (docs/robust.md)."""
    from misdirect.defence.robust import robust_controller
    from misdirect.io.paynt import controller_to_paynt
    from misdirect.io.problem_file import controller_to_document, problem_document_text

    check_output_path(output)
    if randomized and master not in (None, RobustMaster.gradient):
        raise ProblemError(
            f"--randomized is the gradient master; --master {master.value} searches "
            "deterministic controllers",
            field="--master",
        )
    check_range("--memory", memory, 1, 8)
    check_range("--restarts", restarts, 1, 1000)
    if min_goal is not None:
        if objective != RobustObjective.decoy:
            raise ProblemError("needs --objective decoy", field="--min-goal")
        check_range("--min-goal", min_goal, 0, 1)
    kinds = baseline_kinds(baselines)
    attacker_budget = one_budget(budget, "controller robust")
    check_seconds(time_limit)
    problem = source.load()
    result = robust_controller(
        problem,
        attacker_budget,
        memory=memory,
        objective=objective.value,
        randomized=randomized,
        master=None if master is None else master.value,
        restarts=restarts,
        seed=seed,
        min_goal=min_goal,
        time_limit=time_limit,
        baselines=kinds,
    )
    if output.suffix.lower() in (".yaml", ".yml"):
        rules = controller_to_document(result.controller, problem.pomdp)
        write_output(output, problem_document_text(rules))
    else:
        document = controller_to_paynt(result.controller, problem.pomdp)
        write_output(output, json.dumps(document, indent=1) + "\n")
    if as_json:
        print_json(
            json_output.written_files("controller robust", [output], robust=result.to_dict())
        )
        return
    _print_robust(result)
    wrote(f"wrote {output} ({result.controller.n_nodes} nodes)")


def baseline_kinds(text: str) -> tuple[str, ...]:
    """``--baselines``: ``all``, ``none`` or names among given, blind, harden, paynt."""
    from misdirect.defence.robust_baselines import KINDS

    words = [w.strip() for w in text.split(",") if w.strip()]
    if words == ["all"]:
        return KINDS
    if words == ["none"] or not words:
        return ()
    for word in words:
        if word not in KINDS:
            raise ProblemError(
                f"unknown baseline {word!r}: choose from {', '.join(KINDS)}, all or none",
                field="--baselines",
            )
    return tuple(words)


def _print_robust(result: RobustResult) -> None:
    what = "Pr(decoy)" if result.objective == "decoy" else "Pr(goal)"
    table = Table(title=escape(f"{result.problem}: robust controller at budget {result.budget:g}"))
    for column in ("controller", f"nominal {what}", f"worst-case {what}", "certified", "attack"):
        table.add_column(column, justify="left" if column == "controller" else "right")
    table.add_row(
        "robust",
        f"{result.nominal:.6f}",
        f"{result.worst_case:.6f}",
        "yes" if result.certified else "no",
        fmt_alteration(result.alteration),
    )
    for b in result.baselines:
        table.add_row(
            escape(b.name),
            f"{b.nominal:.6f}",
            f"{b.worst_case:.6f}",
            "yes" if b.certified else "no",
            fmt_alteration(b.alteration),
        )
    out.print(table)
    bounds = (
        "no proven bounds"
        if result.lower is None or result.upper is None
        else f"min-max in [{result.lower:.6f}, {result.upper:.6f}] (gap {result.gap:.2g})"
    )
    status = "optimal" if result.optimal else "not proven optimal"
    if result.master in ("gradient", "paynt"):
        status = (
            "randomized (gradient master: worst case certified, optimality not claimed)"
            if result.master == "gradient"
            else "PAYNT master (worst case certified, optimality not claimed)"
        )
        bounds = (
            f"best certified {'upper' if result.objective == 'decoy' else 'lower'} bound "
            f"{result.upper if result.objective == 'decoy' else result.lower}"
        )
    out.print(
        f"{status} · {bounds} · |K| {result.k_size} · {len(result.rounds)} rounds · "
        f"stopped: {escape(result.stop_reason)} · {result.time_s:.2f} s",
        highlight=False,
    )
    print_notes(
        [
            *result.notes,
            *(f"baseline {b.name}: {b.note}" for b in result.baselines if b.note),
            *(f"baseline {b.kind} skipped: {b.reason}" for b in result.skipped_baselines),
            *(
                f"seed {s.name}: worst case {s.worst_case:.6f}"
                f"{'' if s.certified else ' (not certified)'}{f' ({s.note})' if s.note else ''}"
                for s in result.seeds
            ),
        ]
    )
