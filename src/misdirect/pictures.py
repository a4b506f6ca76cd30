"""``misdirect show``: one picture of a problem under an alteration.

Grid worlds (every state named ``"(x,y)"``, as the paper-grid scenario and grid maps name
them) are drawn as the attack heat map of ``misdirect reproduce``; any other problem is written
as the product chain in graphviz ``dot``, as long as it is small enough to read.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from misdirect.errors import ProblemError
from misdirect.evaluate import evaluate
from misdirect.model import Alteration, Problem
from misdirect.product import build_product

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


def _draw_grid(problem: Problem, alteration: Alteration, cells: np.ndarray, output: Path) -> Path:
    from misdirect import plots

    pomdp = problem.pomdp
    width, height = cells.max(axis=0) + 1
    report = evaluate(problem, alteration)
    visits = np.zeros((height, width))
    visits[cells[:, 1], cells[:, 0]] = report.expected_visits
    sensors: dict[str, list[tuple[int, int]]] = {}
    for s, o in enumerate(pomdp.observation_of):
        name = pomdp.observations[o]
        if name != "b" and not (pomdp.absorbing[s] or problem.decoy[s]):
            sensors.setdefault(name, []).append(tuple(cells[s]))
    goal_states = np.flatnonzero(pomdp.absorbing & ~problem.decoy)
    decoys = np.flatnonzero(problem.decoy)
    goal_probability = sum(report.outcomes[pomdp.states[g]] for g in goal_states)
    panel = {
        "budget": report.cost,
        "visits": visits,
        "probability": report.probability,
        "goal_probability": goal_probability,
        "alteration": report.alteration,
    }
    place = lambda states: tuple(cells[states[0]]) if len(states) else (-1, -1)  # noqa: E731
    stem = output.with_suffix("")
    plots.attack_heatmaps(
        int(max(width, height)),
        sensors,
        tuple(cells[pomdp.initial_state]),
        place(goal_states),
        place(decoys),
        [panel],
        stem,
        formats=(output.suffix.lower(),),
    )
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
    output.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return output


def _quote(text: str) -> str:
    return text.replace("\\", "\\\\").replace('"', '\\"')
