"""``misdirect audit -o DIR``: report.md, curve.csv, sensors.csv and the figures.

Every file goes through :func:`misdirect.io.files.write_output` (atomic: a temporary file
beside the target, moved into place once complete). Figures are drawn from the numbers in the
:class:`~misdirect.defence.AuditResult`, nothing is recomputed here except the grid layout.
"""

from __future__ import annotations

import csv
import io
from pathlib import Path

import numpy as np

from misdirect.core.grid import GridCells
from misdirect.core.model import Problem, format_alteration
from misdirect.defence import AuditResult, HardenResult
from misdirect.defence.results import MonitorComparison
from misdirect.io.files import write_output

CURVE_FIELDS = ["budget", "probability", "upper_bound", "status", "cost", "alteration"]
SENSOR_FIELDS = [
    "observation",
    "criticality",
    "criticality_upper",
    "criticality_exact",
    "in_optimal_attack",
    "single_probability",
    "single_status",
    "protected_probability",
    "protected_status",
    "single_alteration",
    "protected_alteration",
]


def _csv(rows: list[dict], fields: list[str]) -> str:
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=fields, lineterminator="\n")
    writer.writeheader()
    writer.writerows(rows)
    return buffer.getvalue()


def curve_rows(result: AuditResult) -> list[dict]:
    return [
        {
            "budget": f"{p.budget:g}",
            "probability": f"{p.probability:.12f}",
            "upper_bound": "" if p.upper_bound is None else f"{p.upper_bound:.12f}",
            "status": p.status,
            "cost": f"{p.cost:g}",
            "alteration": format_alteration(p.alteration),
        }
        for p in result.curve
    ]


def sensor_rows(result: AuditResult) -> list[dict]:
    return [
        {
            "observation": s.observation,
            "criticality": f"{s.criticality:.12f}",
            "criticality_upper": f"{s.criticality_upper:.12f}",
            "criticality_exact": "yes" if s.exact else "no",
            "in_optimal_attack": "yes" if s.in_optimal_attack else "no",
            "single_probability": f"{s.single_probability:.12f}",
            "single_status": s.single_status,
            "protected_probability": f"{s.protected_probability:.12f}",
            "protected_status": s.protected_status,
            "single_alteration": format_alteration(s.single_alteration),
            "protected_alteration": format_alteration(s.protected_alteration),
        }
        for s in result.sensors
    ]


def _save(fig, path: Path) -> Path:
    import matplotlib.pyplot as plt

    try:
        write_output(path, lambda p: fig.savefig(p, dpi=150, bbox_inches="tight"))
    finally:
        plt.close(fig)
    return path


def curve_figure(result: AuditResult):
    """The attacker's optimum against the budget, with bounds where not certified, and the
    online attacker's value as a line above it."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    budgets = np.array([p.budget for p in result.curve])
    values = np.array([p.probability for p in result.curve])
    fig, ax = plt.subplots(figsize=(5.2, 3.6), layout="constrained")
    ax.step(budgets, values, where="post", color="C0", label="offline optimum (exact)")
    ax.plot(budgets, values, "o", color="C0")
    open_points = [p for p in result.curve if p.status != "optimal" and p.upper_bound is not None]
    if open_points:
        ax.vlines(
            [p.budget for p in open_points],
            [p.probability for p in open_points],
            [p.upper_bound for p in open_points if p.upper_bound is not None],  # every one
            color="C3",
            label="not certified: up to the proven bound",
        )
    if result.online is not None:
        ax.axhline(
            result.online.unlimited_bound,
            color="C2",
            linestyle="--",
            label="online attacker, unlimited (upper bound)",
        )
    ax.axhline(result.baseline_probability, color="0.5", linestyle=":", label="no attack")
    ax.set_xlabel("attacker's budget")
    ax.set_ylabel(result.objective_label)
    ax.set_ylim(0, 1.02)
    ax.set_title(f"{result.problem}: the attacker's optimum", fontsize=10)
    ax.legend(fontsize=9, loc="lower right")
    return fig


def sensors_figure(result: AuditResult):
    """Per sensor: criticality (drop of the optimum when protected) and single-sensor value."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from misdirect.io.grid_map import BLANK_OBSERVATION

    rows = result.sensors
    # a grid's blank reading is no sensor: say so rather than list it as one
    names = [
        f"{s.observation} (no sensor)"
        if result.grid and s.observation == BLANK_OBSERVATION
        else s.observation
        for s in rows
    ]
    y = np.arange(len(rows))
    height = max(2.6, 0.28 * len(rows) + 1.4)
    fig, (left, right) = plt.subplots(1, 2, figsize=(8, height), sharey=True, layout="constrained")
    low = np.array([s.criticality for s in rows])
    high = np.array([s.criticality_upper for s in rows])
    left.barh(y, low, color="C3", label="criticality")
    if not all(s.exact for s in rows):  # proven, relative to the values (core.tolerance)
        left.barh(y, high - low, left=low, color="C3", alpha=0.3, label="up to (not certified)")
    left.set_xlabel("drop of the optimum at B when protected")
    left.set_yticks(y, names, fontsize=9)
    left.invert_yaxis()
    left.legend(fontsize=9)
    right.barh(y, [s.single_probability for s in rows], color="C0")
    right.axvline(result.baseline_probability, color="0.5", linestyle=":", label="no attack")
    right.set_xlabel("attacker's best with only this sensor")
    right.legend(fontsize=9)
    fig.suptitle(f"{result.problem}: sensors at budget {result.budget:g}", fontsize=10)
    return fig


def map_figure(problem: Problem, result: AuditResult, cells: GridCells | None = None):
    """The grid with every sensor's cells coloured by its criticality, on a log scale (a
    criticality of 0.001 is not drawn as 0). Cells that read the blank ``b`` (no sensor) are
    drawn apart, not as a sensor; cells no alteration may touch are hatched. ``cells``: where
    each state is drawn (default: the problem's own coordinates); a cell several states share
    shows the largest criticality among them, states without coordinates are left out."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import ListedColormap, LogNorm
    from matplotlib.patches import Patch

    from misdirect.core.grid import state_cells
    from misdirect.io.grid_map import BLANK_OBSERVATION
    from misdirect.report.figures import WALL_FILL, grid_arrays, grid_frame, mark_cell

    if cells is None:
        cells = state_cells(problem)
    assert cells is not None
    xy, placed = cells.xy, cells.placed
    pomdp = problem.pomdp
    by_name = {s.observation: s.criticality for s in result.sensors}
    names = np.array(pomdp.observations)[pomdp.observation_of]
    stop = pomdp.absorbing | problem.decoy
    blank = (names == BLANK_OBSERVATION) & ~stop
    per_state = np.array([by_name.get(n, np.nan) for n in names], dtype=float)
    per_state[stop | blank] = np.nan
    values, walls = grid_arrays(problem, cells, per_state, how="max")
    blank_cells, _ = grid_arrays(problem, cells, np.where(blank, 1.0, np.nan), how="max")
    listed = np.array([by_name.get(n) is not None for n in names]) & ~stop & ~blank
    listed_cells, _ = grid_arrays(problem, cells, np.where(listed, 1.0, np.nan), how="max")
    height, width = values.shape
    scale = 0.9 * max(3.0, min(10.0, 10.0 * max(width, height) / 12)) / max(width, height)
    fig, ax = plt.subplots(figsize=(max(5.5, width * scale + 2.4), max(4.2, height * scale + 2.2)))
    extent = (-0.5, width - 0.5, -0.5, height - 0.5)
    positive = values[np.isfinite(values) & (values > 0)]
    top = float(positive.max()) if positive.size else 1.0
    low = float(positive.min()) if positive.size else top / 10
    # log scale down to the smallest positive criticality (at most four decades below the top)
    norm = LogNorm(vmin=max(min(low, top / 10), top * 1e-4), vmax=top)
    image = ax.imshow(
        np.ma.masked_less_equal(np.nan_to_num(values, nan=0.0), 0.0),
        origin="lower",
        cmap="Reds",
        norm=norm,
        extent=extent,
        interpolation="nearest",
    )
    zero = np.isfinite(values) & (values <= 0)  # a sensor the attack does not need
    layers = [
        (zero, "#e6e6e6"),
        (np.isfinite(blank_cells), "#dfe8f2"),
        (walls, WALL_FILL),
    ]
    for mask, colour in layers:
        ax.imshow(
            np.ma.masked_array(np.ones(walls.shape), mask=~mask),
            origin="lower",
            cmap=ListedColormap([colour]),
            extent=extent,
            interpolation="nearest",
        )
    # cells whose reading no alteration may change (the start's, protected ones): hatched
    locked = ~np.isfinite(listed_cells) & ~np.isfinite(blank_cells) & ~walls
    stops, _ = grid_arrays(problem, cells, np.where(stop, 1.0, np.nan), how="max")
    for y, x in np.argwhere(locked & ~np.isfinite(stops)):
        ax.add_patch(
            plt.Rectangle((x - 0.5, y - 0.5), 1, 1, fill=False, hatch="//", color="0.6", lw=0)
        )
    grid_frame(ax, width, height, cells.origin)
    if len(result.sensors) <= 40:
        for s in result.sensors:
            if s.observation == BLANK_OBSERVATION:
                continue
            o = pomdp.observations.index(s.observation)
            where = xy[(pomdp.observation_of == o) & ~stop & placed]
            if where.size:
                x, y = where[0].tolist()
                ax.text(x, y + 0.3, s.observation, ha="center", va="center", fontsize=9)
    goals = np.flatnonzero(pomdp.absorbing & ~problem.decoy)
    marks: list[tuple[int | np.integer, str, str]] = [(pomdp.initial_state, "S", "black")]
    marks += [(g, "G", "darkgreen") for g in goals]
    marks += [(d, "X", "crimson") for d in np.flatnonzero(problem.decoy)]
    for state, text, colour in marks:
        if placed[state]:
            mark_cell(ax, tuple(xy[state].tolist()), text, colour)
    handles = [
        Patch(facecolor="#e6e6e6", edgecolor="0.7", label="criticality 0"),
        Patch(facecolor="#dfe8f2", edgecolor="0.7", label=f"no sensor (reads {BLANK_OBSERVATION})"),
        Patch(facecolor="white", edgecolor="0.6", hatch="//", label="not alterable"),
        Patch(facecolor=WALL_FILL, edgecolor="0.7", label="wall: no state in this cell"),
    ]
    if blank.any() and BLANK_OBSERVATION in by_name:
        handles[1].set_label(
            f"no sensor (reads {BLANK_OBSERVATION}; criticality {by_name[BLANK_OBSERVATION]:.3g})"
        )
    fig.legend(handles=handles, loc="lower center", ncols=3, fontsize=9, frameon=False)
    caption = cells.caption()
    ax.set_title(
        f"{result.problem}: sensor criticality at budget {result.budget:g}\n"
        "(drop of the attacker's optimum when the sensor is protected)"
        + (f"\n{caption}" if caption else ""),
        fontsize=10,
    )
    ax.tick_params(labelsize=9)
    bar = fig.colorbar(image, ax=ax, fraction=0.046 * height / width, pad=0.04)
    bar.set_label("criticality (log scale)", fontsize=9)
    bar.ax.tick_params(labelsize=9)
    fig.subplots_adjust(bottom=0.18)
    return fig


def report_text(result: AuditResult, drawn: bool | None = None) -> str:
    """report.md: what the attacker can do, which sensors matter, what an online attacker adds."""
    lines = [
        f"# Sensor audit: {result.problem}",
        "",
        f"Attacker's budget B = {result.budget:g}. Without attack {result.objective_label} = "
        f"{result.baseline_probability:.9f}.",
        "",
        "## The attacker's optimum for every budget",
        "",
        f"| budget | max {result.objective_label} | upper bound | status | optimal alteration "
        "| cost |",
        "|---|---|---|---|---|---|",
    ]
    for p in result.curve:
        bound = "—" if p.upper_bound is None else f"{p.upper_bound:.9f}"
        lines.append(
            f"| {p.budget:g} | {p.probability:.9f} | {bound} | {p.status} | "
            f"{format_alteration(p.alteration)} | {p.cost:g} |"
        )
    lines += ["", "## Sensors", ""]
    if not result.certified:
        lines += [
            "**Not every number below is certified**: where the criticality is given as an "
            "interval, the optimum at B or with the sensor protected was not proven.",
            "",
        ]
    lines += [
        "Criticality: how much the attacker's optimum at B drops when the sensor is protected "
        "(made unalterable). A sensor the optimal attack does not alter has criticality 0 "
        "exactly (that attack stays feasible). Single: the attacker's best when only this "
        "sensor may be altered.",
        "",
        "| sensor | criticality | optimum with it protected | single-sensor value | "
        "in the optimal attack |",
        "|---|---|---|---|---|",
    ]
    for s in result.sensors:
        crit = (
            f"{s.criticality:.9f}"
            if s.exact
            else f"[{s.criticality:.9f}, {s.criticality_upper:.9f}] (bounds)"
        )
        mark = "" if s.protected_status == "optimal" else f" ({s.protected_status})"
        single = "" if s.single_status == "optimal" else f" ({s.single_status})"
        lines.append(
            f"| {s.observation} | {crit} | {s.protected_probability:.9f}{mark} | "
            f"{s.single_probability:.9f}{single} | {'yes' if s.in_optimal_attack else 'no'} |"
        )
    online = result.online
    lines += [
        "",
        "## The online attacker",
        "",
        "An attacker who sees the true state and the controller's memory and may alter every "
        "reading differently at every step (docs/defence.md).",
        "",
    ]
    if online is None:
        lines.append(f"* not computed ({result.online_budgeted_note}).")
    else:
        lines.append(
            "* unlimited (every allowed target, any cost): "
            f"**{online.unlimited_probability:.9f}** (proven at most "
            f"{online.unlimited_bound:.9f}) — an upper bound of the offline optimum "
            f"at every budget (offline at B: {result.probability:.9f});"
        )
        if online.budgeted_probability is not None:
            lines.append(
                f"* paying for every altered reading against B = {result.budget:g} "
                f"(cost unit {online.cost_unit:g}): **{online.budgeted_probability:.9f}** — "
                "a different threat, not a bound of the offline optimum either way."
            )
        else:
            lines.append(f"* budgeted variant not computed: {result.online_budgeted_note}")
    lines += comparison_lines(result.monitor_comparison)
    if result.notes:
        lines += ["", "## Notes", ""] + [f"* {note}" for note in result.notes]
    lines += [
        "",
        "Files: curve.csv, sensors.csv, curve.png, sensors.png"
        + (", map.png" if (result.grid if drawn is None else drawn) else "")
        + f". Computed in {result.time_s:.2f} s.",
        "",
    ]
    return "\n".join(lines)


def write_audit_report(
    problem: Problem, result: AuditResult, out: Path, coordinates: str | None = None
) -> list[Path]:
    """Write every file of the report into the folder ``out`` (which must exist); the map
    when the states have coordinates (their own, or ``coordinates``:
    :func:`~misdirect.core.grid.state_cells`)."""
    from misdirect.core.grid import state_cells

    out = Path(out)
    cells = state_cells(problem, coordinates)
    written = [
        write_output(out / "curve.csv", _csv(curve_rows(result), CURVE_FIELDS)),
        write_output(out / "sensors.csv", _csv(sensor_rows(result), SENSOR_FIELDS)),
        _save(curve_figure(result), out / "curve.png"),
        _save(sensors_figure(result), out / "sensors.png"),
    ]
    if cells is not None:
        written.append(_save(map_figure(problem, result, cells), out / "map.png"))
    written.append(write_output(out / "report.md", report_text(result, drawn=cells is not None)))
    return written


# -- harden -o DIR ------------------------------------------------------------------------------


def tradeoff_figure(result: HardenResult):
    """The trade-off: the attacker's optimum (at budget B) against the protection budget D,
    with the proven lower bound where the min-max is not proven."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    budgets = np.array([p.protect_budget for p in result.curve])
    values = np.array([p.probability for p in result.curve])
    lower = np.array([p.lower_bound for p in result.curve])
    fig, ax = plt.subplots(figsize=(5.6, 3.8), layout="constrained")
    ax.step(budgets, values, where="post", color="C3", label="attacker's optimum, best protection")
    ax.plot(budgets, values, "o", color="C3")
    open_points = np.array([p.status != "optimal" for p in result.curve], dtype=bool)
    if open_points.any():
        ax.vlines(
            budgets[open_points],
            lower[open_points],
            values[open_points],
            color="0.4",
            label="not proven: down to the lower bound",
        )
    ax.axhline(result.value_before, color="0.5", linestyle=":", label="nothing protected")
    for d, v, point in zip(budgets, values, result.curve, strict=True):
        text = ", ".join(point.protection) or "nothing"
        ax.annotate(text, (d, v), textcoords="offset points", xytext=(4, 6), fontsize=9)
    ax.set_xlabel("protection budget D", fontsize=10)
    ax.set_ylabel(f"attacker's optimum at B = {result.budget:g}", fontsize=10)
    top = max(float(values.max(initial=0)), result.value_before)
    ax.set_ylim(0, 1.05 * top if top > 0 else 1.0)  # values of any scale, 1e-12 included
    ax.tick_params(labelsize=9)
    ax.set_title(f"{result.problem}: protection against the attacker", fontsize=10)
    from matplotlib.ticker import MaxNLocator

    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax.legend(fontsize=9, loc="center right")
    return fig


def comparison_lines(comparison: MonitorComparison | None) -> list[str]:
    """The report's section "The monitor against protection" (none without a monitor)."""
    if comparison is None:
        return []
    lines = [
        "",
        "## The monitor against protection",
        "",
        f"The attacker's optimum at B = {comparison.budget:g} under each defence; caught: "
        f"Pr(the monitor {comparison.monitor} raises the alarm) under the attacker's reply "
        f"(on the rows without it: were it added). {comparison.why}.",
        "",
        "| defence | protect | cost | attacker's optimum | status | caught | reply |",
        "|---|---|---|---|---|---|---|",
    ]
    for row in comparison.rows:
        lines.append(
            f"| {row.defence} | {', '.join(row.protection) or 'nothing'} | "
            f"{row.protection_cost:g} | {row.probability:.9f} | {row.status} | "
            f"{row.alarm_probability:.6f} | {format_alteration(row.alteration)} |"
        )
    return lines


def harden_report_text(result: HardenResult) -> str:
    """report.md of ``harden -o DIR``: the protection, and the trade-off over D."""
    lines = [
        f"# Hardening: {result.problem}",
        "",
        f"Attacker's budget B = {result.budget:g}; protection budget D = "
        f"{result.protect_budget:g}.",
        "",
        f"Protect **{', '.join(result.protection) or 'nothing'}** (cost "
        f"{result.protection_cost:g}): the attacker's optimum drops from "
        f"{result.value_before:.9f} to {result.value_after:.9f} ({result.status}); no "
        f"protection within D holds it below {result.lower_bound:.9f}. The attacker's best "
        f"reply: {format_alteration(result.best_reply)}.",
        "",
        "## The trade-off",
        "",
        "| D | protect | cost | attacker's optimum | lower bound | best reply | status |",
        "|---|---|---|---|---|---|---|",
    ]
    for p in result.curve:
        lines.append(
            f"| {p.protect_budget:g} | {', '.join(p.protection) or 'nothing'} | "
            f"{p.protection_cost:g} | {p.probability:.9f} | {p.lower_bound:.9f} | "
            f"{format_alteration(p.attack)} | {p.status} |"
        )
    lines += comparison_lines(result.monitor_comparison)
    if result.notes:
        lines += ["", "## Notes", ""] + [f"* {note}" for note in result.notes]
    lines += [
        "",
        f"Files: tradeoff.png. {result.solves} attacker solves, {result.nodes} nodes, "
        f"{result.time_s:.2f} s.",
        "",
    ]
    return "\n".join(lines)


def write_harden_report(result: HardenResult, out: Path) -> list[Path]:
    """Write report.md and tradeoff.png into the folder ``out`` (which must exist)."""
    out = Path(out)
    return [
        _save(tradeoff_figure(result), out / "tradeoff.png"),
        write_output(out / "report.md", harden_report_text(result)),
    ]
