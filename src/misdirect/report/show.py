"""``misdirect show``: one picture of a problem under an alteration.

Grid worlds (every state named ``"(x,y)"``, as the paper-grid scenario and grid maps name
them; a PRISM model with integer variables ``x`` and ``y``; any model whose states
``coordinates`` places, see :func:`misdirect.core.grid.state_cells`) are drawn as a heat map of
the visits; any other problem is written as the product chain in graphviz ``dot``, as long as
it is small enough to read.
"""

from __future__ import annotations

from pathlib import Path

from misdirect.core.grid import GridCells, state_cells
from misdirect.core.model import AlterationArray, Problem
from misdirect.core.product import build_product
from misdirect.errors import ProblemError
from misdirect.io.files import one_line, write_output
from misdirect.report.figures import draw_grid

MAX_DOT_STATES = 200
PICTURE_SUFFIXES = (".png", ".svg", ".pdf")


def draw(
    problem: Problem,
    alteration: AlterationArray,
    output: Path,
    coordinates: str | None = None,
    **options,
) -> Path:
    """Write the picture (``.png/.svg/.pdf``: a grid world's heat map, ``options`` those of
    :func:`~misdirect.report.figures.grid_figure`) or the product chain (``.dot``)."""
    suffix = output.suffix.lower()
    if suffix == ".dot":
        return _write_dot(problem, alteration, output)
    if suffix not in PICTURE_SUFFIXES:
        raise ProblemError(
            f"cannot draw {suffix or 'a file without suffix'}: use "
            f"{', '.join(PICTURE_SUFFIXES)} or .dot",
            field="output",
        )
    return draw_grid(problem, alteration, require_cells(problem, coordinates), output, **options)


def require_cells(problem: Problem, coordinates: str | None) -> GridCells:
    """The cells of the states (:func:`~misdirect.core.grid.state_cells`), or the error that
    says how to give them."""
    cells = state_cells(problem, coordinates)
    if cells is None:
        raise ProblemError(
            "only models with coordinates are drawn as pictures: states named '(x,y)', PRISM "
            'models with integer variables x and y, or give them: coordinates="col,row" '
            "(two integer variables) or a regular expression with two groups on the state "
            "names (like 'cell(\\d+)_(\\d+)'); or write the product chain with "
            'output="chain.dot"',
            field="output",
        )
    return cells


def _write_dot(problem: Problem, alteration: AlterationArray, output: Path) -> Path:
    chain = build_product(problem, alteration)
    if chain.n_states > MAX_DOT_STATES:
        raise ProblemError(
            f"the product chain has {chain.n_states:,} states; a drawing stops being readable "
            f"well before that (limit {MAX_DOT_STATES})",
            field="output",
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
