"""The option of every command that draws a model on a grid: ``--coordinates`` (``show``,
``audit -o``'s map, ``simulate --picture``); what it accepts is decided in one place,
:func:`misdirect.core.grid.state_cells`."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from misdirect.core.grid import GridCells
from misdirect.core.model import Problem

CoordinatesOption = Annotated[
    str | None,
    typer.Option(
        "--coordinates",
        help="Where each state is drawn: two integer variables of a PRISM model (x,y, the "
        "first across) or a regular expression with two groups on the state names, e.g. "
        "'cell(\\d+)_(\\d+)'. Default: states named (x,y), or a PRISM model's x and y. States "
        "without coordinates are left out (the caption counts them); states sharing a cell "
        "are drawn together (visits added up, the map's largest criticality).",
        show_default=False,
    ),
]

PictureOption = Annotated[
    Path | None,
    typer.Option(
        "--picture",
        help="Also draw the simulated visits per cell (.png/.svg/.pdf) on a model with "
        "coordinates (see --coordinates).",
        show_default=False,
    ),
]


def check_picture_suffix(path: Path, option: str) -> None:
    """A picture is .png, .svg or .pdf."""
    from misdirect.errors import ProblemError
    from misdirect.report.show import PICTURE_SUFFIXES

    if path.suffix.lower() not in PICTURE_SUFFIXES:
        raise ProblemError(
            f"cannot draw {path.suffix or 'a file without suffix'}: use "
            f"{', '.join(PICTURE_SUFFIXES)}",
            field=option,
        )


def picture_cells(problem: Problem, coordinates: str | None) -> GridCells:
    """The cells of ``problem``'s states for a picture (an error naming --coordinates when
    it has none)."""
    from misdirect.core.grid import state_cells
    from misdirect.errors import ProblemError

    cells = state_cells(problem, coordinates)
    if cells is None:
        raise ProblemError(
            "only models with coordinates are drawn as pictures: states named '(x,y)', PRISM "
            "models with integer variables x and y, or give them: --coordinates col,row (two "
            "integer variables) or a regular expression with two groups on the state names "
            "(like --coordinates 'cell(\\d+)_(\\d+)')",
            field="--picture",
        )
    return cells
