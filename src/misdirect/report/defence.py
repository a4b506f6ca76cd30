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

from misdirect.core.model import Problem, format_alteration
from misdirect.defence import AuditResult
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
    ax.axhline(
        result.online.unlimited_probability,
        color="C2",
        linestyle="--",
        label="online attacker, unlimited (upper bound)",
    )
    ax.axhline(result.baseline_probability, color="0.5", linestyle=":", label="no attack")
    ax.set_xlabel("attacker's budget")
    ax.set_ylabel(result.objective_label)
    ax.set_ylim(0, 1.02)
    ax.set_title(f"{result.problem or 'problem'}: the attacker's optimum", fontsize=9)
    ax.legend(fontsize=7, loc="lower right")
    return fig


def sensors_figure(result: AuditResult):
    """Per sensor: criticality (drop of the optimum when protected) and single-sensor value."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = result.sensors
    names = [s.observation for s in rows]
    y = np.arange(len(rows))
    height = max(2.6, 0.28 * len(rows) + 1.4)
    fig, (left, right) = plt.subplots(1, 2, figsize=(8, height), sharey=True, layout="constrained")
    low = np.array([s.criticality for s in rows])
    high = np.array([s.criticality_upper for s in rows])
    left.barh(y, low, color="C3", label="criticality")
    if np.any(high - low > 1e-9):
        left.barh(y, high - low, left=low, color="C3", alpha=0.3, label="up to (not certified)")
    left.set_xlabel("drop of the optimum at B when protected")
    left.set_yticks(y, names, fontsize=7)
    left.invert_yaxis()
    left.legend(fontsize=7)
    right.barh(y, [s.single_probability for s in rows], color="C0")
    right.axvline(result.baseline_probability, color="0.5", linestyle=":", label="no attack")
    right.set_xlabel("attacker's best with only this sensor")
    right.legend(fontsize=7)
    fig.suptitle(f"{result.problem or 'problem'}: sensors at budget {result.budget:g}", fontsize=9)
    return fig


def map_figure(problem: Problem, result: AuditResult):
    """The grid with every sensor's cells coloured by its criticality."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import ListedColormap

    from misdirect.core.grid import grid_cells
    from misdirect.report.figures import grid_arrays, grid_frame, mark_cell

    cells = grid_cells(problem)
    assert cells is not None
    pomdp = problem.pomdp
    by_name = {s.observation: s.criticality for s in result.sensors}
    names = np.array(pomdp.observations)[pomdp.observation_of]
    stop = pomdp.absorbing | problem.decoy
    per_state = np.array([by_name.get(n, np.nan) for n in names], dtype=float)
    per_state[stop] = np.nan
    values, walls = grid_arrays(problem, cells, per_state)
    height, width = values.shape
    scale = 0.9 * max(3.0, min(10.0, 10.0 * max(width, height) / 12)) / max(width, height)
    fig, ax = plt.subplots(figsize=(max(4.5, width * scale + 1.8), max(3.5, height * scale + 1.6)))
    extent = (-0.5, width - 0.5, -0.5, height - 0.5)
    top = max(float(np.nanmax(values)) if np.isfinite(values).any() else 0.0, 1e-9)
    image = ax.imshow(
        values,
        origin="lower",
        cmap="Reds",
        vmin=0,
        vmax=top,
        extent=extent,
        interpolation="nearest",
    )
    ax.imshow(
        np.ma.masked_array(np.ones(walls.shape), mask=~walls),
        origin="lower",
        cmap=ListedColormap(["#4d4d4d"]),
        extent=extent,
        interpolation="nearest",
    )
    grid_frame(ax, width, height)
    if len(result.sensors) <= 40:
        for s in result.sensors:
            o = pomdp.observations.index(s.observation)
            where = cells[(pomdp.observation_of == o) & ~stop]
            if where.size:
                x, y = where[0].tolist()
                ax.text(x, y + 0.3, s.observation, ha="center", va="center", fontsize=6)
    goals = np.flatnonzero(pomdp.absorbing & ~problem.decoy)
    marks: list[tuple[int | np.integer, str, str]] = [(pomdp.initial_state, "S", "black")]
    marks += [(g, "G", "darkgreen") for g in goals]
    marks += [(d, "X", "crimson") for d in np.flatnonzero(problem.decoy)]
    for state, text, colour in marks:
        mark_cell(ax, tuple(cells[state].tolist()), text, colour)
    ax.set_title(
        f"{result.problem or 'problem'}: sensor criticality at budget {result.budget:g}\n"
        "(drop of the attacker's optimum when the sensor is protected; blank: not alterable)",
        fontsize=8,
    )
    fig.colorbar(image, ax=ax, fraction=0.046 * height / width, pad=0.04, label="criticality")
    return fig


def report_text(result: AuditResult) -> str:
    """report.md: what the attacker can do, which sensors matter, what an online attacker adds."""
    lines = [
        f"# Sensor audit: {result.problem or 'problem'}",
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
        f"* unlimited (every allowed target, any cost): **{online.unlimited_probability:.9f}** "
        f"— an upper bound of the offline optimum at every budget (offline at B: "
        f"{result.probability:.9f});",
    ]
    if online.budgeted_probability is not None:
        lines.append(
            f"* paying for every altered reading against B = {result.budget:g} "
            f"(cost unit {online.cost_unit:g}): **{online.budgeted_probability:.9f}** — a "
            "different threat, not a bound of the offline optimum either way."
        )
    else:
        lines.append(f"* budgeted variant not computed: {result.online_budgeted_note}")
    if result.notes:
        lines += ["", "## Notes", ""] + [f"* {note}" for note in result.notes]
    lines += [
        "",
        "Files: curve.csv, sensors.csv, curve.png, sensors.png"
        + (", map.png" if result.grid else "")
        + f". Computed in {result.time_s:.2f} s.",
        "",
    ]
    return "\n".join(lines)


def write_audit_report(problem: Problem, result: AuditResult, out: Path) -> list[Path]:
    """Write every file of the report into the folder ``out`` (which must exist)."""
    out = Path(out)
    written = [
        write_output(out / "curve.csv", _csv(curve_rows(result), CURVE_FIELDS)),
        write_output(out / "sensors.csv", _csv(sensor_rows(result), SENSOR_FIELDS)),
        _save(curve_figure(result), out / "curve.png"),
        _save(sensors_figure(result), out / "sensors.png"),
    ]
    if result.grid:
        written.append(_save(map_figure(problem, result), out / "map.png"))
    written.append(write_output(out / "report.md", report_text(result)))
    return written
