"""``misdirect show``: one picture of a problem under an alteration.

Grid worlds (every state named ``"(x,y)"``, as the paper-grid scenario and grid maps name
them) are drawn as the attack heat map of ``misdirect reproduce``; any other problem is written
as the product chain in graphviz ``dot``, as long as it is small enough to read.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from misdirect.core.evaluate import evaluate
from misdirect.core.model import Alteration, Problem
from misdirect.core.product import build_product
from misdirect.errors import ProblemError
from misdirect.io.files import one_line, write_output

CELL = re.compile(r"^\((\d+),(\d+)\)$")
MAX_DOT_STATES = 200
PICTURE_SUFFIXES = (".png", ".svg", ".pdf")


def grid_cells(problem: Problem) -> np.ndarray | None:
    """(|S|, 2) cell coordinates if the problem is a grid world, else None."""
    matches = [CELL.match(name) for name in problem.pomdp.states]
    if not all(matches):
        return None
    return np.array([(int(m.group(1)), int(m.group(2))) for m in matches])


def draw(problem: Problem, alteration: Alteration, output: Path) -> Path:
    suffix = output.suffix.lower()
    cells = grid_cells(problem)
    if suffix == ".dot":
        return _write_dot(problem, alteration, output)
    if suffix not in PICTURE_SUFFIXES:
        raise ProblemError(
            f"cannot draw {suffix or 'a file without suffix'}: use "
            f"{', '.join(PICTURE_SUFFIXES)} or .dot",
            field="-o",
        )
    if cells is None:
        raise ProblemError(
            "only grid worlds (states named '(x,y)') are drawn as pictures; "
            "write the product chain with -o chain.dot instead",
            field="-o",
        )
    return _draw_grid(problem, alteration, cells, output)


def grid_arrays(
    problem: Problem, cells: np.ndarray, per_state: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """``(values, walls)``, both ``(height, width)`` indexed ``[y, x]``: ``per_state`` placed
    at each state's cell (NaN where no state is), and the mask of cells that are no state
    (walls). Width and height are those of the cells the states occupy."""
    width, height = (int(v) for v in cells.max(axis=0) + 1)
    values = np.full((height, width), np.nan)
    values[cells[:, 1], cells[:, 0]] = per_state
    walls = np.ones((height, width), dtype=bool)
    walls[cells[:, 1], cells[:, 0]] = False
    return values, walls


def grid_figure(problem: Problem, alteration: Alteration, cells: np.ndarray):
    """The attack on a grid world: expected visits per cell (heat map), walls, sensor regions
    (hatched when altered), start S, every goal G and every decoy X."""
    import matplotlib

    matplotlib.use("Agg")  # no display needed
    import matplotlib.pyplot as plt
    from matplotlib.colors import ListedColormap, LogNorm, Normalize
    from matplotlib.patches import Rectangle

    from misdirect.report.plots import SENSOR_COLOURS, grid_frame, mark_cell

    pomdp = problem.pomdp
    report = evaluate(problem, alteration)
    visits, walls = grid_arrays(problem, cells, report.expected_visits)
    height, width = visits.shape
    positive = visits[visits > 0]
    norm = (
        LogNorm(vmin=max(positive.min(), 1e-4), vmax=max(positive.max(), 1e-4 * 1.01))
        if positive.size
        else Normalize(0.0, 1.0)
    )
    scale = 0.9 * max(3.0, min(10.0, 10.0 * max(width, height) / 12)) / max(width, height)
    fig, ax = plt.subplots(figsize=(max(4.5, width * scale + 1.8), max(3.5, height * scale + 1.6)))
    extent = (-0.5, width - 0.5, -0.5, height - 0.5)
    image = ax.imshow(
        np.where(visits > 0, visits, np.nan),
        origin="lower",
        cmap="magma_r",
        norm=norm,
        extent=extent,
        interpolation="nearest",
    )
    image.set_label("visits")
    wall_layer = ax.imshow(
        np.ma.masked_array(np.ones(walls.shape), mask=~walls),
        origin="lower",
        cmap=ListedColormap(["#4d4d4d"]),
        extent=extent,
        interpolation="nearest",
    )
    wall_layer.set_label("walls")
    grid_frame(ax, width, height)

    changed = problem.changed_observations(alteration)
    stop = pomdp.absorbing | problem.decoy
    sensor_states = (np.array(pomdp.observations)[pomdp.observation_of] != "b") & ~stop
    sensor_ids = list(dict.fromkeys(pomdp.observation_of[sensor_states].tolist()))
    for k, o in enumerate(sensor_ids):
        name = pomdp.observations[o]
        altered = name in changed
        where = cells[sensor_states & (pomdp.observation_of == o)]
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
    marks = [(pomdp.initial_state, "S", "black")]
    marks += [(g, "G", "darkgreen") for g in goals] + [(d, "X", "crimson") for d in decoys]
    for state, text, colour in marks:
        mark_cell(ax, tuple(cells[state].tolist()), text, colour)
    goal_probability = sum(report.outcomes.get(pomdp.states[g], 0.0) for g in goals)
    changes = ", ".join(f"{o}→{t}" for o, t in changed.items()) or "no alteration"
    ax.set_title(
        f"{problem.name or 'problem'}: {changes} (cost {report.cost:g})\n"
        f"Pr(decoy) = {report.probability:.3f}, Pr(goal) = {goal_probability:.3f}\n"
        "S start, G goal, X decoy, dark grey: wall, hatched: altered sensor",
        fontsize=8,
    )
    ratio = height / width  # keeps the colour bar as tall as the grid, whatever its shape
    fig.colorbar(image, ax=ax, fraction=0.046 * ratio, pad=0.04, label="expected visits per cell")
    return fig


def _draw_grid(problem: Problem, alteration: Alteration, cells: np.ndarray, output: Path) -> Path:
    import matplotlib.pyplot as plt

    fig = grid_figure(problem, alteration, cells)
    try:  # atomic, like every output: a temporary file beside it, then os.replace
        write_output(output, lambda path: fig.savefig(path, dpi=150, bbox_inches="tight"))
    finally:
        plt.close(fig)
    return output


def _write_dot(problem: Problem, alteration: Alteration, output: Path) -> Path:
    chain = build_product(problem, alteration)
    if chain.n_states > MAX_DOT_STATES:
        raise ProblemError(
            f"the product chain has {chain.n_states:,} states; a drawing stops being readable "
            f"well before that (limit {MAX_DOT_STATES})",
            field="-o",
        )
    pomdp, nodes = problem.pomdp, problem.controller.nodes
    lines = ["digraph product {", "  rankdir=LR;", "  node [shape=box, fontsize=10];"]
    for q in range(chain.n_states):
        s = chain.world_state[q]
        style = (
            ', style=filled, fillcolor="#f4a6a6"'
            if problem.decoy[s]
            else (', style=filled, fillcolor="#b7e4b7"' if pomdp.absorbing[s] else "")
        )
        shape = ", peripheries=2" if q == chain.initial else ""
        label = f"{pomdp.states[s]} / {nodes[chain.node[q]]}"
        lines.append(f'  q{q} [label="{_quote(label)}"{style}{shape}];')
    coo = chain.matrix.tocoo()
    for q, r, p in zip(coo.row, coo.col, coo.data, strict=True):
        lines.append(f'  q{q} -> q{r} [label="{p:.3g}"];')
    lines.append("}")
    write_output(output, "\n".join(lines) + "\n")
    return output


def _quote(text: str) -> str:
    return one_line(text).replace("\\", "\\\\").replace('"', '\\"')
