"""Figures: the grid with its sensors, the attack as a heat map, and the scalability panels.

Everything is drawn with matplotlib's object API on the Agg backend (no display needed), and
every function takes the numbers it draws, so the same data can be checked in tests.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.colors import LogNorm
from matplotlib.patches import Rectangle

SENSOR_COLOURS = plt.get_cmap("tab10").colors


def save(fig: plt.Figure, stem: Path, formats: Sequence[str] = (".png", ".svg")) -> list[Path]:
    """Write ``stem.png`` and ``stem.svg`` (or the given suffixes); returns the paths."""
    paths = [stem.with_suffix(suffix) for suffix in formats]
    for path in paths:
        fig.savefig(path, dpi=150, bbox_inches="tight")
    plt.close(fig)
    return paths


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
    ax.set_xlim(-0.5, n - 0.5)
    ax.set_ylim(-0.5, n - 0.5)
    ax.set_xticks(range(n))
    ax.set_yticks(range(n))
    ax.set_xticks(np.arange(-0.5, n), minor=True)
    ax.set_yticks(np.arange(-0.5, n), minor=True)
    ax.grid(which="minor", color="0.6", linewidth=0.5)
    ax.tick_params(which="minor", length=0)
    ax.set_aspect("equal")
    ax.set_xlabel("x (East)")
    ax.set_ylabel("y (North)")


def _mark(ax, cell: tuple[int, int], text: str, colour: str) -> None:
    ax.text(
        cell[0],
        cell[1] - 0.12,
        text,
        ha="center",
        va="center",
        fontsize=13,
        weight="bold",
        color=colour,
    )


def grid_layout(
    n: int,
    sensors: dict[str, list[tuple[int, int]]],
    start: tuple[int, int],
    goal: tuple[int, int],
    decoy: tuple[int, int],
    stem: Path,
) -> list[Path]:
    """The grid world: sensor regions, start, true goal and decoy (hazard)."""
    fig, ax = plt.subplots(figsize=(4.2, 4.2))
    _draw_cells(ax, n, sensors, alpha=0.55)
    _mark(ax, start, "S", "black")
    _mark(ax, goal, "G", "darkgreen")
    _mark(ax, decoy, "X", "crimson")
    ax.set_title(
        f"{n}x{n} grid: sensors o0–o6, start S,\ngoal G, decoy X (blank cells: b)", fontsize=9
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
) -> list[Path]:
    """One panel per budget: expected visits per cell under the optimal attack.

    Each panel dict has ``budget``, ``visits`` ((n, n) array indexed [y, x]), ``probability``,
    ``goal_probability`` and ``alteration`` ({observation: received}).
    """
    cols = len(panels)
    fig, axes = plt.subplots(1, cols, figsize=(4.4 * cols, 4.8), squeeze=False)
    positive = np.concatenate([p["visits"][p["visits"] > 0] for p in panels])
    norm = LogNorm(vmin=max(positive.min(), 1e-4), vmax=positive.max())
    image = None
    for ax, panel in zip(axes[0], panels, strict=True):
        visits = np.where(panel["visits"] > 0, panel["visits"], np.nan)
        image = ax.imshow(
            visits, origin="lower", cmap="magma_r", norm=norm, extent=(-0.5, n - 0.5, -0.5, n - 0.5)
        )
        _draw_cells(ax, n, {}, alpha=0)
        for k, (name, cells) in enumerate(sensors.items()):
            altered = name in panel["alteration"]
            for x, y in cells:
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
            x, y = cells[0]
            label = f"{name}→{panel['alteration'][name]}" if altered else name
            ax.text(
                x,
                y + 0.3,
                label,
                ha="center",
                va="center",
                fontsize=7,
                weight="bold" if altered else "normal",
                bbox={"facecolor": "white", "alpha": 0.8, "pad": 1, "edgecolor": "none"},
            )
        _mark(ax, start, "S", "black")
        _mark(ax, goal, "G", "darkgreen")
        _mark(ax, decoy, "X", "crimson")
        changes = ", ".join(f"{o}→{t}" for o, t in panel["alteration"].items()) or "no alteration"
        ax.set_title(
            f"budget {panel['budget']:g}\nPr(decoy) = {panel['probability']:.3f}, "
            f"Pr(goal) = {panel['goal_probability']:.3f}\n{changes}",
            fontsize=8,
        )
    fig.colorbar(image, ax=axes[0].tolist(), shrink=0.8, label="expected visits per cell")
    fig.suptitle("Where the robot goes under the attack (hatched: altered sensors)", fontsize=10)
    return save(fig, stem, formats)


def scalability_panels(
    rows: Sequence[dict], stem: Path, formats: Sequence[str] = (".png", ".svg")
) -> list[Path]:
    """The paper's Fig. 4 (variables, rows, construction time, solve time), both formulations.

    Rows have ``n``, ``formulation``, ``variables``, ``rows``, ``build_time_s``,
    ``solve_time_s``, ``solver_status`` and ``evaluation_time_s``. Solves stopped by the time
    limit are drawn as open markers at the limit and labelled "timed out", never dropped.
    """
    fig, axes = plt.subplots(1, 4, figsize=(16, 3.8))
    panels = [
        ("variables", "variables"),
        ("rows", "constraints (rows)"),
        ("build_time_s", "construction time (s)"),
        ("solve_time_s", "solve time (s)"),
    ]
    styles = {"compact": ("tab:blue", "o", "-"), "paper": ("tab:red", "s", "--")}
    for formulation, (colour, marker, line) in styles.items():
        mine = sorted((r for r in rows if r["formulation"] == formulation), key=lambda r: r["n"])
        if not mine:
            continue
        for ax, (key, label) in zip(axes, panels, strict=True):
            xs = [r["n"] for r in mine if r.get(key) is not None]
            ys = [r[key] for r in mine if r.get(key) is not None]
            ax.plot(xs, ys, line, color=colour, marker=marker, label=formulation)
            if key == "solve_time_s":
                late = [r for r in mine if r.get("solver_status") == "time_limit"]
                if late:
                    ax.scatter(
                        [r["n"] for r in late],
                        [r[key] for r in late],
                        s=140,
                        facecolors="none",
                        edgecolors=colour,
                        linewidths=2,
                        label=f"{formulation}: timed out",
                        zorder=5,
                    )
            ax.set_xlabel("grid size n")
            ax.set_ylabel(label)
            ax.set_yscale("log")
            ax.grid(True, which="both", alpha=0.3)
    floor = sorted({(r["n"], r["evaluation_time_s"]) for r in rows if r.get("evaluation_time_s")})
    if floor:
        for ax in axes[2:]:
            ax.plot(*zip(*floor, strict=True), ":", color="black", label="one exact evaluation")
    for ax in (axes[0], axes[3]):
        ax.legend(fontsize=7)
    fig.suptitle(
        "Scalability on the scaled grid (paper Fig. 4): compact vs the paper's MILP", fontsize=10
    )
    fig.tight_layout()
    return save(fig, stem, formats)
