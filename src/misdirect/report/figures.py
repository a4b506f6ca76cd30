"""Figures: grid worlds (the sensors, the attacks as heat maps, one picture per alteration for
``show``) and the scalability panels.

Everything is drawn with matplotlib's object API on the Agg backend (no display needed), and
every function takes the numbers it draws, so the same data can be checked in tests.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from matplotlib import patheffects
from matplotlib.collections import LineCollection
from matplotlib.colors import LogNorm
from matplotlib.lines import Line2D
from matplotlib.patches import Patch, Rectangle
from matplotlib.typing import LineStyleType

from misdirect.core.evaluate import evaluate
from misdirect.core.grid import GridCells
from misdirect.core.grid import grid_cells as grid_cells  # re-exported: now lives in core.grid
from misdirect.core.model import AlterationArray, Problem
from misdirect.io.files import write_output

SENSOR_COLOURS = plt.get_cmap("tab10").colors  # type: ignore[attr-defined]  # a ListedColormap
HEAT_MAP = "viridis"  # perceptual; the busiest cells are bright, never near-black
VISITS_FLOOR = 1e-3  # cells visited less than this share the darkest colour
ABSORBING_FILL = "0.85"  # grey, outside the heat map's colours
ALTERED = "#ff1f5b"  # outline of an altered sensor
HALO = [patheffects.withStroke(linewidth=3, foreground="white")]


def save(fig: plt.Figure, stem: Path, formats: Sequence[str] = (".png", ".svg")) -> list[Path]:
    """Write ``stem.png`` and ``stem.svg`` (or the given suffixes); returns the paths."""
    paths = [stem.with_suffix(suffix) for suffix in formats]
    try:
        for path in paths:  # atomic: a full disk leaves an earlier picture as it was
            write_output(path, lambda staged: fig.savefig(staged, dpi=150, bbox_inches="tight"))
    finally:
        plt.close(fig)
    return paths


def grid_frame(ax, width: int, height: int, origin: tuple[int, int] = (0, 0)) -> None:
    """Cells as unit squares centred on integer (x, y), x East and y North, with a light grid;
    the ticks read ``origin`` plus the column (row) when the picture does not start at 0."""
    ax.set_xlim(-0.5, width - 0.5)
    ax.set_ylim(-0.5, height - 0.5)
    step_x, step_y = max(1, width // 25), max(1, height // 25)  # at most about 25 tick labels
    ax.set_xticks(range(0, width, step_x), [str(origin[0] + v) for v in range(0, width, step_x)])
    ax.set_yticks(range(0, height, step_y), [str(origin[1] + v) for v in range(0, height, step_y)])
    ax.set_xticks(np.arange(-0.5, width), minor=True)
    ax.set_yticks(np.arange(-0.5, height), minor=True)
    ax.grid(which="minor", color="0.6", linewidth=0.5)
    ax.tick_params(which="minor", length=0)
    ax.set_aspect("equal")
    ax.set_xlabel("x (East)")
    ax.set_ylabel("y (North)")


def _draw_cells(ax, n: int, sensors: dict[str, list[tuple[int, int]]], alpha: float) -> None:
    for k, (name, cells) in enumerate(sensors.items()):
        for x, y in cells:
            ax.add_patch(
                Rectangle(
                    (x - 0.5, y - 0.5),
                    1,
                    1,
                    facecolor=SENSOR_COLOURS[k % 10],
                    alpha=alpha,
                    edgecolor="none",
                )
            )
        x, y = cells[0]
        ax.text(x, y + 0.28, name, ha="center", va="center", fontsize=8, weight="bold")
    grid_frame(ax, n, n)


def mark_cell(ax, cell: tuple[int, int], text: str, colour: str, dy: float = -0.12) -> None:
    """A big letter (S, G, X) in a cell, with a white halo so it reads on any colour."""
    ax.text(
        cell[0],
        cell[1] + dy,
        text,
        ha="center",
        va="center",
        fontsize=13,
        weight="bold",
        color=colour,
        path_effects=[patheffects.withStroke(linewidth=3.5, foreground="white")],
        zorder=6,
    )


def _outline(cells: Sequence[tuple[int, int]]) -> list[list[tuple[float, float]]]:
    """The boundary of a set of cells: every cell side not shared with another cell of the set."""
    inside = {tuple(c) for c in cells}
    segments = []
    for x, y in inside:
        for dx, dy in ((1, 0), (-1, 0), (0, 1), (0, -1)):
            if (x + dx, y + dy) in inside:
                continue
            if dx:
                edge = x + dx / 2
                segments.append([(edge, y - 0.5), (edge, y + 0.5)])
            else:
                edge = y + dy / 2
                segments.append([(x - 0.5, edge), (x + 0.5, edge)])
    return segments


def grid_layout(
    n: int,
    sensors: dict[str, list[tuple[int, int]]],
    start: tuple[int, int],
    goal: tuple[int, int],
    decoy: tuple[int, int],
    stem: Path,
) -> list[Path]:
    """The grid world: sensor regions, start, true goal and decoy (hazard)."""
    fig, ax = plt.subplots(figsize=(4.2, 4.2), layout="constrained")
    _draw_cells(ax, n, sensors, alpha=0.55)
    for cell in (goal, decoy):
        ax.add_patch(
            Rectangle((cell[0] - 0.5, cell[1] - 0.5), 1, 1, facecolor=ABSORBING_FILL, hatch="..")
        )
    mark_cell(ax, start, "S", "black")
    mark_cell(ax, goal, "G", "darkgreen")
    mark_cell(ax, decoy, "X", "crimson")
    ax.set_title(
        f"{n}x{n} grid: sensors o0–o6, start S, goal G, decoy X\n"
        "(grey: the run ends there; blank cells report b)",
        fontsize=9,
    )
    return save(fig, stem)


def attack_heatmaps(
    n: int,
    sensors: dict[str, list[tuple[int, int]]],
    start: tuple[int, int],
    goal: tuple[int, int],
    decoy: tuple[int, int],
    panels: Sequence[dict],
    stem: Path,
    formats: Sequence[str] = (".png", ".svg"),
    note: str = "",
) -> list[Path]:
    """One panel per budget: expected visits per cell under the optimal attack.

    Each panel dict has ``budget``, ``visits`` ((height, width) array indexed [y, x]),
    ``probability``, ``goal_probability`` and ``alteration`` ({observation: received}).
    ``note`` is printed under the title (e.g. how the controller reacts to each sensor).
    Goal and decoy are absorbing: no step is spent there, so they are drawn grey with the
    probability of ending there instead of a visit count.
    """
    cols = len(panels)
    height, width = np.asarray(panels[0]["visits"]).shape
    numbers = max(width, height) <= 8  # write the count in each cell while it stays readable
    fig, axes = plt.subplots(
        1, cols, figsize=(4.3 * cols + 1.2, 6.0), squeeze=False, layout="constrained"
    )
    top = max(float(np.max(p["visits"])) for p in panels)
    norm = LogNorm(vmin=VISITS_FLOOR, vmax=max(top, 10 * VISITS_FLOOR))
    cmap = plt.get_cmap(HEAT_MAP)
    ends = {goal: "goal_probability", decoy: "probability"}
    image = None
    for ax, panel in zip(axes[0], panels, strict=True):
        visits = np.asarray(panel["visits"], dtype=float)
        shown = np.clip(visits, VISITS_FLOOR, None)
        image = ax.imshow(
            shown,
            origin="lower",
            cmap=cmap,
            norm=norm,
            extent=(-0.5, width - 0.5, -0.5, height - 0.5),
        )
        grid_frame(ax, width, height)
        for cell, key in ends.items():
            if not (0 <= cell[0] < width and 0 <= cell[1] < height):
                continue
            ax.add_patch(
                Rectangle(
                    (cell[0] - 0.5, cell[1] - 0.5),
                    1,
                    1,
                    facecolor=ABSORBING_FILL,
                    edgecolor="0.4",
                    hatch="..",
                    zorder=2,
                )
            )
            ax.text(
                cell[0],
                cell[1] - 0.32,
                f"ends {panel[key]:.3f}",
                ha="center",
                va="center",
                fontsize=6.5,
                zorder=6,
                bbox={"facecolor": "white", "alpha": 0.85, "pad": 0.8, "edgecolor": "none"},
            )
        if numbers:
            for y in range(height):
                for x in range(width):
                    if (x, y) in ends:
                        continue
                    value = visits[y, x]
                    dark = norm(max(value, VISITS_FLOOR)) < 0.6
                    ax.text(
                        x + 0.44,
                        y - 0.42,
                        _count(value),
                        ha="right",
                        va="bottom",
                        fontsize=6,
                        color="white" if dark else "black",
                        zorder=4,
                    )
        for name, cells in sensors.items():
            altered = name in panel["alteration"]
            segments = _outline(cells)
            ax.add_collection(
                LineCollection(
                    segments,
                    colors=ALTERED if altered else "white",
                    linewidths=3.2 if altered else 2.2,
                    capstyle="projecting",
                    path_effects=[
                        patheffects.withStroke(
                            linewidth=5.4 if altered else 4.0,
                            foreground="white" if altered else "black",
                        )
                    ],
                    zorder=5,
                    clip_on=False,  # a region on the border keeps its full outline
                )
            )
            x, y = max(cells, key=lambda c: (c[1], -c[0]))  # top-left cell of the region
            label = f"{name}→{panel['alteration'][name]}" if altered else name
            ax.text(
                x,
                y + 0.27,
                label,
                ha="center",
                va="center",
                fontsize=7.5 if altered else 7,
                weight="bold",
                color=ALTERED if altered else "black",
                zorder=7,
                bbox={"facecolor": "white", "alpha": 0.9, "pad": 1.2, "edgecolor": "none"},
            )
        mark_cell(ax, start, "S", "black")
        mark_cell(ax, goal, "G", "darkgreen", dy=0.05)
        mark_cell(ax, decoy, "X", "crimson", dy=0.05)
        changes = ", ".join(f"{o}→{t}" for o, t in panel["alteration"].items()) or "none"
        ax.set_title(
            f"budget {panel['budget']:g}: Pr(end at X) = {panel['probability']:.3f}, "
            f"Pr(end at G) = {panel['goal_probability']:.3f}\naltered sensors: {changes}",
            fontsize=8.5,
        )
    assert image is not None  # there is a panel
    colorbar = fig.colorbar(image, ax=axes[0].tolist(), shrink=0.75, extend="min")
    colorbar.set_label(f"expected steps spent in the cell (log scale, < {VISITS_FLOOR:g} darkest)")
    handles = [
        Patch(
            facecolor=ABSORBING_FILL,
            edgecolor="0.4",
            hatch="..",
            label="goal G / decoy X: the run ends here (number: probability of ending there)",
        ),
        Line2D(
            [],
            [],
            color="white",
            linewidth=2.2,
            label="sensor region (unaltered)",
            path_effects=[patheffects.withStroke(linewidth=4.0, foreground="black")],
        ),
        Line2D(
            [],
            [],
            color=ALTERED,
            linewidth=3.2,
            label="altered sensor: o1→o2 means sensor o1 now reports o2",
        ),
        Line2D([], [], linestyle="none", marker="$S$", color="black", markersize=9, label="start"),
    ]
    fig.legend(handles=handles, loc="outside lower center", ncols=2, fontsize=8, frameon=False)
    title = "Where the robot goes under the optimal attack, budget by budget"
    fig.suptitle(title + (f"\n{note}" if note else ""), fontsize=10)
    return save(fig, stem, formats)


def _count(value: float) -> str:
    if value < VISITS_FLOOR:
        return f"<{VISITS_FLOOR:g}"
    return f"{value:.2f}" if value >= 0.01 else f"{value:.3f}"


def _claims(rows: Sequence[dict]) -> str:
    claimed = sorted(
        {
            round(float(r["solver_probability"]), 3)
            for r in rows
            if r.get("solver_probability") is not None
        }
    )
    if not claimed:
        return ""
    text = f"claims {claimed[0]:g}"
    if len(claimed) > 1:
        text += f"–{claimed[-1]:g}"
    exact = [float(r["probability"]) for r in rows if r.get("probability") is not None]
    if exact:
        text += f", true value ≤ {max(exact):.3g}"
    return text


def scalability_panels(
    rows: Sequence[dict],
    stem: Path,
    formats: Sequence[str] = (".png", ".svg"),
    *,
    time_limit: float | None = None,
) -> list[Path]:
    """The paper's Fig. 4 (variables, rows, construction time, solve time), both formulations.

    Rows have ``n``, ``formulation``, ``variables``, ``rows``, ``build_time_s``,
    ``solve_time_s``, ``solver_status`` and ``evaluation_time_s``; optionally ``status``
    (ours: ``unverified`` when the MILP's claimed value is not the exact value of its answer),
    ``solver_probability`` and ``probability``. Unverified answers are drawn hollow. Solves
    stopped by the time limit are drawn as upward triangles at the limit, or at the measured
    time if the solver overran it (the true time is longer either way), labelled "timed out",
    and not joined to the measured line; they are never dropped.
    Construction always finishes, so sizes and construction times are measurements.
    """
    fig, axes = plt.subplots(1, 4, figsize=(16, 4.6), layout="constrained")
    panels = [
        ("variables", "variables"),
        ("rows", "constraints (rows)"),
        ("build_time_s", "construction time (s)"),
        ("solve_time_s", "solve time (s)"),
    ]
    styles: dict[str, tuple[str, str, LineStyleType]] = {
        "compact": ("tab:blue", "o", "-"),
        "paper": ("tab:red", "s", "--"),
    }
    names = {"compact": "compact MILP", "paper": "paper MILP"}
    handles: list = []
    for formulation, (colour, marker, line) in styles.items():
        mine = sorted((r for r in rows if r["formulation"] == formulation), key=lambda r: r["n"])
        if not mine:
            continue
        handles.append(
            Line2D([], [], color=colour, marker=marker, linestyle=line, label=names[formulation])
        )
        wrong = [r for r in mine if r.get("status") == "unverified"]
        if wrong:
            claims = _claims(wrong)
            handles.append(
                Line2D(
                    [],
                    [],
                    color=colour,
                    marker=marker,
                    linestyle="none",
                    markerfacecolor="white",
                    markeredgewidth=2,
                    markersize=8,
                    label=f"{names[formulation]}: claimed optimum wrong"
                    + (f" ({claims})" if claims else ""),
                )
            )
        late = [r for r in mine if r.get("solver_status") == "time_limit"]
        if late:
            handles.append(
                Line2D(
                    [],
                    [],
                    color=colour,
                    marker="^",
                    linestyle="none",
                    markersize=10,
                    label=f"{names[formulation]}: timed out (no proof; true time ≥ the point)",
                )
            )
        for ax, (key, label) in zip(axes, panels, strict=True):
            timed_out = key == "solve_time_s"
            measured = [
                r
                for r in mine
                if r.get(key) is not None
                and not (timed_out and r.get("solver_status") == "time_limit")
            ]
            ax.plot([r["n"] for r in measured], [r[key] for r in measured], line, color=colour)
            for hollow in (False, True):
                pick = [r for r in measured if (r.get("status") == "unverified") == hollow]
                if pick:
                    ax.plot(
                        [r["n"] for r in pick],
                        [r[key] for r in pick],
                        linestyle="none",
                        marker=marker,
                        color=colour,
                        markersize=8 if hollow else 6,
                        markerfacecolor="white" if hollow else colour,
                        markeredgewidth=2 if hollow else 1,
                        zorder=4,
                    )
            if timed_out and late:
                # HiGHS can overrun its limit; the true time is at least what was measured
                ys = [max(time_limit or 0.0, r[key] or 0.0) for r in late]
                below = formulation == "compact"  # two labels at one n must not collide
                for r, y in zip(late, ys, strict=True):
                    hollow = r.get("status") == "unverified"
                    ax.plot(
                        [r["n"]],
                        [y],
                        linestyle="none",
                        marker="^",
                        markersize=11,
                        color=colour,
                        markerfacecolor="white" if hollow else colour,
                        markeredgecolor=colour if hollow else "black",
                        markeredgewidth=2 if hollow else 1,
                        zorder=5,
                        gid="timed-out",
                    )
                    ax.annotate(
                        "timed out",
                        (r["n"], y),
                        xytext=(0, -10 if below else 9),
                        textcoords="offset points",
                        ha="center",
                        va="top" if below else "bottom",
                        fontsize=7.5,
                        color=colour,
                        weight="bold",
                    )
            ax.set_xlabel("grid size n")
            ax.set_ylabel(label)
            ax.set_yscale("log")
            sizes = sorted({r["n"] for r in rows})
            ax.set_xticks(sizes)
            pad = 0.15 * max(sizes[-1] - sizes[0], 4)  # room for a "timed out" label at the end
            ax.set_xlim(sizes[0] - pad, sizes[-1] + pad)
            ax.grid(True, which="both", alpha=0.3)
    floor = sorted({(r["n"], r["evaluation_time_s"]) for r in rows if r.get("evaluation_time_s")})
    if floor:
        for ax in axes[2:]:
            ax.plot(*zip(*floor, strict=True), ":", color="black")
        handles.append(
            Line2D(
                [],
                [],
                linestyle=":",
                color="black",
                label="one exact evaluation of the chain (floor)",
            )
        )
    if time_limit is not None:
        axes[3].axhline(time_limit, color="0.4", linewidth=1, linestyle="-.")
        axes[3].margins(y=0.15)
        handles.append(
            Line2D(
                [],
                [],
                linestyle="-.",
                color="0.4",
                label=f"time limit ({time_limit:g} s per solve)",
            )
        )
    fig.legend(handles=handles, loc="outside lower center", ncols=3, fontsize=8, frameon=False)
    fig.suptitle(
        "Scalability on the scaled grid (paper Fig. 4): compact vs the paper's MILP", fontsize=10
    )
    return save(fig, stem, formats)


def as_grid_cells(cells: GridCells | np.ndarray) -> GridCells:
    """``(|S|, 2)`` coordinates (every state placed, as :func:`grid_cells` returns them) or
    :class:`GridCells` as :class:`GridCells`."""
    if isinstance(cells, GridCells):
        return cells
    xy = np.asarray(cells, dtype=np.int64)
    return GridCells(xy=xy, placed=np.ones(len(xy), dtype=bool), origin=(0, 0), how="(x,y) names")


def grid_arrays(
    problem: Problem,
    cells: GridCells | np.ndarray,
    per_state: np.ndarray,
    how: str = "sum",
) -> tuple[np.ndarray, np.ndarray]:
    """``(values, walls)``, both ``(height, width)`` indexed ``[y, x]``: ``per_state`` placed
    at each state's cell (NaN where no state is, or where every state's value is NaN), and the
    mask of cells that are no state (walls). Width and height are those of the cells the states
    occupy; states without coordinates are left out. Several states in one cell (the memory-free
    variables of a PRISM model, say) are aggregated: their values added up (``how="sum"``: visits,
    as the visits of a state's memory nodes are) or the largest taken (``how="max"``)."""
    grid = as_grid_cells(cells)
    values_in = np.asarray(per_state, dtype=float)
    xy = grid.xy[grid.placed]
    per = values_in[grid.placed]
    width, height = (int(v) for v in xy.max(axis=0) + 1)
    walls = np.ones((height, width), dtype=bool)
    walls[xy[:, 1], xy[:, 0]] = False
    finite = ~np.isnan(per)
    values = np.full((height, width), -np.inf if how == "max" else 0.0)
    if how == "max":
        np.maximum.at(values, (xy[finite, 1], xy[finite, 0]), per[finite])
    elif how == "sum":
        np.add.at(values, (xy[finite, 1], xy[finite, 0]), per[finite])
    else:
        raise ValueError(f"how: 'sum' or 'max', not {how!r}")
    counted = np.zeros((height, width), dtype=bool)
    counted[xy[finite, 1], xy[finite, 0]] = True
    values[~counted] = np.nan
    return values, walls


WALL_FILL = (
    "#8c9db0"  # slate: a colour of neither the heat maps (yellow-red-black, reds) nor blanks
)
UNVISITED_FILL = "white"
VISITS_MAP = "magma_r"  # light: few visits, dark: many


def grid_figure(
    problem: Problem,
    alteration: AlterationArray,
    cells: GridCells | np.ndarray,
    visits: np.ndarray | None = None,
    visits_label: str = "expected visits per cell",
    note: str = "",
):
    """The attack on a grid world: visits per cell (heat map: expected ones, or ``visits``
    per state, as a simulation counts them), walls, sensor regions (hatched when altered),
    start S, every goal G and every decoy X, with a legend that says what each colour means.
    States without coordinates are left out and counted under the title."""
    import matplotlib

    matplotlib.use("Agg")  # no display needed
    import matplotlib.pyplot as plt
    from matplotlib.colors import ListedColormap, LogNorm, Normalize
    from matplotlib.patches import Patch, Rectangle

    grid = as_grid_cells(cells)
    pomdp = problem.pomdp
    report = evaluate(problem, alteration)
    per_state = report.expected_visits if visits is None else visits
    visits_grid, walls = grid_arrays(problem, grid, per_state)
    height, width = visits_grid.shape
    positive = visits_grid[visits_grid > 0]
    norm = (
        LogNorm(vmin=max(positive.min(), 1e-4), vmax=max(positive.max(), 1e-4 * 1.01))
        if positive.size
        else Normalize(0.0, 1.0)
    )
    scale = 0.9 * max(3.0, min(10.0, 10.0 * max(width, height) / 12)) / max(width, height)
    fig, ax = plt.subplots(
        figsize=(max(5.5, width * scale + 2.4), max(4.5, height * scale + 2.6)),
        layout="constrained",
    )
    extent = (-0.5, width - 0.5, -0.5, height - 0.5)
    image = ax.imshow(
        np.where(visits_grid > 0, visits_grid, np.nan),
        origin="lower",
        cmap=VISITS_MAP,
        norm=norm,
        extent=extent,
        interpolation="nearest",
    )
    image.set_label("visits")
    wall_layer = ax.imshow(
        np.ma.masked_array(np.ones(walls.shape), mask=~walls),
        origin="lower",
        cmap=ListedColormap([WALL_FILL]),
        extent=extent,
        interpolation="nearest",
    )
    wall_layer.set_label("walls")
    grid_frame(ax, width, height, grid.origin)

    xy, placed = grid.xy, grid.placed
    changed = problem.changed_observations(alteration)
    stop = pomdp.absorbing | problem.decoy
    sensor_states = (np.array(pomdp.observations)[pomdp.observation_of] != "b") & ~stop & placed
    sensor_ids = list(dict.fromkeys(pomdp.observation_of[sensor_states].tolist()))
    outlined = len(sensor_ids) <= 40 and width * height <= 10_000
    any_altered = False
    for k, o in enumerate(sensor_ids if outlined else []):
        name = pomdp.observations[o]
        altered = name in changed
        any_altered |= altered
        where = np.unique(xy[sensor_states & (pomdp.observation_of == o)], axis=0)
        for x, y in where.tolist():
            ax.add_patch(
                Rectangle(
                    (x - 0.5, y - 0.5),
                    1,
                    1,
                    fill=False,
                    edgecolor=SENSOR_COLOURS[k % 10],
                    linewidth=3 if altered else 1.2,
                    hatch="//" if altered else None,
                )
            )
        x, y = where[0].tolist()
        ax.text(
            x,
            y + 0.3,
            f"{name}→{changed[name]}" if altered else name,
            ha="center",
            va="center",
            fontsize=7,
            weight="bold" if altered else "normal",
            bbox={"facecolor": "white", "alpha": 0.8, "pad": 1, "edgecolor": "none"},
        )
    goals = np.flatnonzero(pomdp.absorbing & ~problem.decoy)
    decoys = np.flatnonzero(problem.decoy)
    marks: list[tuple[int | np.integer, str, str]] = [(pomdp.initial_state, "S", "black")]
    marks += [(g, "G", "darkgreen") for g in goals] + [(d, "X", "crimson") for d in decoys]
    marked: set[tuple[int, int, str]] = set()
    for state, text, colour in marks:
        if not placed[state]:
            continue
        cell = tuple(xy[state].tolist())
        if (*cell, text) not in marked:  # several states of one cell: one letter
            marked.add((*cell, text))
            mark_cell(ax, cell, text, colour)
    goal_probability = sum(report.outcomes.get(pomdp.states[g], 0.0) for g in goals)
    changes = ", ".join(f"{o}→{t}" for o, t in changed.items()) or "no alteration"
    caption = "; ".join(part for part in (note, grid.caption()) if part)
    ax.set_title(
        f"{problem.title}: {changes} (cost {report.cost:g})\n"
        f"Pr(decoy) = {report.probability:.3f}, Pr(goal) = {goal_probability:.3f}"
        + (f"\n{caption}" if caption else ""),
        fontsize=8,
    )
    handles = [
        Patch(facecolor=WALL_FILL, edgecolor="0.6", label="wall: no state in this cell"),
        Patch(
            facecolor=UNVISITED_FILL,
            edgecolor="0.6",
            label="white: no step taken (never visited, or G/X: runs end there)",
        ),
        Patch(
            facecolor=plt.get_cmap(VISITS_MAP)(0.85),
            edgecolor="0.6",
            label="darker: more visits (scale on the right)",
        ),
        Line2D([], [], linestyle="none", marker="$S$", color="black", label="S start"),
        Line2D([], [], linestyle="none", marker="$G$", color="darkgreen", label="G goal"),
        Line2D([], [], linestyle="none", marker="$X$", color="crimson", label="X decoy"),
    ]
    if outlined and sensor_ids:
        handles.append(
            Patch(facecolor="none", edgecolor=SENSOR_COLOURS[0], label="outline: sensor region")
        )
    if any_altered:
        handles.append(
            Patch(
                facecolor="none",
                edgecolor=SENSOR_COLOURS[0],
                hatch="//",
                linewidth=2,
                label="hatched: altered sensor (o1→o2: o1 now reports o2)",
            )
        )
    fig.legend(
        handles=handles,
        loc="outside lower center",
        ncols=3,
        fontsize=7,
        frameon=False,
    )
    ratio = height / width  # keeps the colour bar as tall as the grid, whatever its shape
    fig.colorbar(
        image, ax=ax, fraction=0.046 * ratio, pad=0.04, label=f"{visits_label} (darker: more)"
    )
    return fig


def draw_grid(
    problem: Problem,
    alteration: AlterationArray,
    cells: GridCells | np.ndarray,
    output: Path,
    **options,
) -> Path:
    """:func:`grid_figure` written to ``output`` (``options``: its ``visits``,
    ``visits_label`` and ``note``)."""
    fig = grid_figure(problem, alteration, cells, **options)
    try:  # atomic, like every output: a temporary file beside it, then os.replace
        write_output(output, lambda path: fig.savefig(path, dpi=150, bbox_inches="tight"))
    finally:
        plt.close(fig)
    return output


def tradeoff_figure(curves: Sequence[Any], path: Path, *, title: str = "") -> Path:
    """Value against δ, one line per budget: the solves of
    :func:`misdirect.solve_tradeoff` (one :class:`~misdirect.SolveResult` per δ, increasing).
    A certified point is filled, any other hollow; a budget where nothing keeps Pr(alarm) <= δ
    (``infeasible``) has no point. Between two δ solved the line holds the smaller one's value
    (steps: the optimum only grows with δ, and is known only where solved). Written to
    ``path`` (its suffix picks the format)."""
    from misdirect.core.objective import LABELS

    fig, ax = plt.subplots(figsize=(6.0, 4.0))
    deltas = [float(curve.max_alarm) for curve in curves]
    for j, point in enumerate(curves[0].curve):
        xs, ys, proven = [], [], []
        for delta, curve in zip(deltas, curves, strict=True):
            p = curve.curve[j]
            if str(p.status) == "infeasible":
                continue
            xs.append(delta)
            ys.append(p.probability)
            proven.append(str(p.status) == "optimal")
        (line,) = ax.plot(xs, ys, "-", drawstyle="steps-post", label=f"budget {point.budget:g}")
        colour = line.get_color()
        for x, y, certified in zip(xs, ys, proven, strict=True):
            ax.plot(x, y, "o", color=colour, markerfacecolor=colour if certified else "white")
    positive = [d for d in deltas if d > 0]
    if positive and min(positive) < 0.1 * max(positive):
        ax.set_xscale("symlog", linthresh=min(positive))
    ax.set_xlabel("δ: the largest Pr(alarm) allowed")
    label = LABELS.get(curves[0].objective, curves[0].objective)
    ax.set_ylabel(f"{label} before the alarm")
    ax.set_title(title or "value against stealth")
    ax.grid(alpha=0.3)
    ax.legend(loc="upper left", fontsize="small")
    fig.tight_layout()
    path = Path(path)
    return save(fig, path, (path.suffix,))[0]


ROBUST_STYLES = {  # label -> (marker, colour); labels outside it cycle through tab10
    "given controller": ("s", "tab:red"),
    "observation-blind": ("^", "0.4"),
    "harden": ("D", "tab:orange"),
    "PAYNT nominal": ("P", "tab:purple"),
    "robust, max-min Pr(goal)": ("o", "tab:blue"),
    "robust, min-max Pr(decoy), Pr(goal) ≥ 0.9": ("*", "tab:green"),
    "robust randomized (2 nodes), Pr(goal) ≥ 0.9": ("X", "tab:cyan"),
}


def robust_tradeoff_figure(
    points: Sequence[dict[str, Any]], path: Path, *, title: str = ""
) -> Path:
    """Nominal Pr(goal) against certified worst-case Pr(decoy), one panel per attacker
    budget: what robustness costs in nominal performance (docs/robust.md). ``points`` are
    dicts with ``budget``, ``label``, ``nominal_goal``, ``worst_decoy`` and ``certified`` (a
    certified point is filled, any other hollow). Lower right is better. The worst case is on
    a log scale (linear below 0.01), and each label is drawn a little smaller than the one
    before, so controllers with the same numbers show as nested markers. Written to ``path``
    (its suffix picks the format)."""
    budgets = sorted({float(p["budget"]) for p in points})
    labels = list(dict.fromkeys(str(p["label"]) for p in points))
    columns = min(3, len(budgets))
    rows = -(-len(budgets) // columns)
    fig, axes = plt.subplots(
        rows, columns, figsize=(3.6 * columns + 0.4, 3.2 * rows + 0.8), squeeze=False
    )
    handles: dict[str, Line2D] = {}
    for ax, budget in zip(axes.flat, budgets, strict=False):
        for k, label in enumerate(labels):
            marker, colour = ROBUST_STYLES.get(label, ("o", SENSOR_COLOURS[k % 10]))
            for p in points:
                if float(p["budget"]) != budget or p["label"] != label:
                    continue
                face = colour if p["certified"] else "white"
                (handle,) = ax.plot(
                    p["nominal_goal"], p["worst_decoy"], marker, color=colour,
                    markerfacecolor=face, markersize=max(14 - 1.3 * k, 4), alpha=0.85,
                    linestyle="none",
                )  # fmt: skip
                handles.setdefault(label, handle)
        ax.set_yscale("symlog", linthresh=0.01)
        ax.set_ylim(-0.001, 1.5)
        ax.set_title(f"budget {budget:g}")
        ax.set_xlabel("nominal Pr(goal)")
        ax.set_ylabel("certified worst-case Pr(decoy)")
        ax.grid(alpha=0.3)
    for ax in list(axes.flat)[len(budgets) :]:
        ax.set_visible(False)
    fig.legend(
        [handles[label] for label in labels if label in handles],
        [label for label in labels if label in handles],
        loc="lower center", ncol=min(3, len(handles)), fontsize="small",
    )  # fmt: skip
    fig.suptitle(title or "robustness against nominal performance")
    fig.tight_layout(rect=(0, 0.06 + 0.03 * ((len(handles) + 2) // 3), 1, 1))
    path = Path(path)
    return save(fig, path, (path.suffix,))[0]
