"""Grid worlds: problems whose states sit on cells of a plane.

The paper-grid and sensor-grid scenarios, the drone scenario and grid maps name their states
``"(x,y)"``. PRISM models name them by their variables' values (``x=1,y=2``, or Storm's
``[x=1 & y=2]``): a model with exactly two integer variables ``x`` and ``y`` is placed by them
without being asked, and ``coordinates`` (``--coordinates``) places any other model, by two
variable names (``"col,row"``) or a regular expression with two groups on the state names
(``"cell(\\d+)_(\\d+)"``). :func:`state_cells` is the one place this is decided;
``show``, ``audit``'s map and ``simulate``'s picture all use it.

Knowing the cell of each state is model geometry, not drawing: the audit records whether a
problem is a grid world, and the figures place states on the grid. It lives here so that
neither has to import the other.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np

from misdirect.core.model import Problem
from misdirect.errors import ProblemError

CELL = re.compile(r"^\((-?\d+),(-?\d+)\)$")  # grid worlds name their states "(x,y)"
VARIABLES = re.compile(r"^\s*([A-Za-z_]\w*)\s*,\s*([A-Za-z_]\w*)\s*$")  # --coordinates x,y
INTEGER_ITEM = re.compile(r"^([A-Za-z_]\w*)=(-?\d+)$")  # x=3 in a valuation name
MAX_CELLS = 4_000_000  # a picture of more cells is not drawn (paper-grid n = 2,000 fits)
OPTION = "coordinates"  # the parameter (the CLI shows it as --coordinates)


@dataclass(frozen=True)
class GridCells:
    """Where each state is drawn.

    ``xy[s]`` is state ``s``'s cell, counted from the picture's lower-left cell, which is
    ``origin`` in the model's own coordinates; states with ``placed[s]`` False have no
    coordinates (sinks, counters, …) and are left out of the picture. Several states may share
    a cell (the other variables of a PRISM model, say): pictures add up or take the largest of
    their values there, as they add up the memory nodes of a state."""

    xy: np.ndarray  # (|S|, 2) int64, meaningful where placed
    placed: np.ndarray  # (|S|,) bool
    origin: tuple[int, int]
    how: str  # what placed them, for captions: "(x,y) names", "x,y", a regex

    @property
    def width(self) -> int:
        return int(self.xy[self.placed, 0].max()) + 1

    @property
    def height(self) -> int:
        return int(self.xy[self.placed, 1].max()) + 1

    @property
    def left_out(self) -> int:
        """States without coordinates, not drawn."""
        return int((~self.placed).sum())

    def caption(self) -> str:
        """What a picture's reader needs to know about what is not drawn."""
        if not self.left_out:
            return ""
        states = "state" if self.left_out == 1 else "states"
        return f"{self.left_out:,} {states} without coordinates ({self.how}) not drawn"


def grid_cells(problem: Problem) -> np.ndarray | None:
    """(|S|, 2) cell coordinates if every state is named ``"(x,y)"``, else None."""
    matches = [CELL.match(name) for name in problem.pomdp.states]
    if not all(matches):
        return None
    return np.array([(int(m.group(1)), int(m.group(2))) for m in matches if m is not None])


def state_cells(problem: Problem, coordinates: str | None = None) -> GridCells | None:
    """The cell of each state, or None when the problem has no coordinates and none were
    asked for.

    Without ``coordinates``: states named ``"(x,y)"``, else a PRISM model whose only integer
    variables are ``x`` and ``y``. With it: two variable names (``"x,y"``, the first across)
    or a regular expression with two groups (named ``x`` and ``y``, or else the first two)
    searched in each state name. Errors name ``--coordinates``: nothing matches, a coordinate
    that is not a whole number, every state in one cell, a picture too large to draw (their
    field is ``coordinates``)."""
    names = problem.pomdp.states
    if coordinates is None:
        cells = grid_cells(problem)
        if cells is not None and len(cells):
            return _checked(cells, np.ones(len(cells), dtype=bool), "(x,y) names", shift=False)
        if _integer_variables(names) == {"x", "y"}:
            return _by_variables(names, "x", "y", "PRISM variables x,y")
        return None
    if not coordinates.strip():
        raise ProblemError("is empty: give two variable names (x,y) or a regex", field=OPTION)
    variables = VARIABLES.match(coordinates)
    if variables is not None:
        return _by_variables(names, variables.group(1), variables.group(2), coordinates.strip())
    return _by_pattern(names, coordinates)


def _items(name: str) -> list[str]:
    """``x=1,y=2,!done`` or Storm's ``[x=1 & y=2]`` as its items."""
    return [item for item in re.split(r"\s*[,&]\s*", name.strip().strip("[]").strip()) if item]


def _integer_variables(names: tuple[str, ...]) -> set[str]:
    """The integer variables of valuation names (``x=1,y=2,flag``), empty if a name is not
    one (then the model is no PRISM model, or not named by its variables)."""
    found: set[str] = set()
    for name in names:
        for item in _items(name):
            match = INTEGER_ITEM.match(item)
            if match is not None:
                found.add(match.group(1))
    return found


def _by_variables(names: tuple[str, ...], x: str, y: str, how: str) -> GridCells:
    xy = np.zeros((len(names), 2), dtype=np.int64)
    placed = np.zeros(len(names), dtype=bool)
    seen: set[str] = set()
    for s, name in enumerate(names):
        values: dict[str, str] = {}
        for item in _items(name):
            key, equals, value = item.partition("=")
            if not equals:  # a boolean: flag or !flag
                key, value = key.lstrip("!"), "false" if key.startswith("!") else "true"
            values[key.strip()] = value.strip()
        seen.update(values)
        if x in values and y in values:
            xy[s] = (_whole(values[x], name, x), _whole(values[y], name, y))
            placed[s] = True
    if not placed.any():
        missing = [v for v in (x, y) if v not in seen]
        known = sorted(v for v in seen if v)
        hint = (
            f"no state has {' or '.join(repr(v) for v in missing)} "
            f"(variables in the state names: {', '.join(known[:12]) or 'none'}); "
            if missing
            else f"no state has both {x!r} and {y!r}; "
        )
        raise ProblemError(
            f"{hint}state names look like {_examples(names)}. Give two integer variables "
            "(x,y) or a regex with two groups, e.g. 'cell(\\d+)_(\\d+)'",
            field=OPTION,
        )
    return _checked(xy, placed, how)


def _by_pattern(names: tuple[str, ...], text: str) -> GridCells:
    try:
        pattern = re.compile(text)
    except re.error as error:
        raise ProblemError(f"not a regular expression: {error}", field=OPTION) from None
    named = pattern.groupindex
    if "x" in named and "y" in named:
        groups: tuple[int | str, int | str] = ("x", "y")
    elif pattern.groups == 2:
        groups = (1, 2)
    else:
        raise ProblemError(
            f"{text!r} has {pattern.groups} group(s): give two variable names (x,y) or a regex "
            "with exactly two groups (or groups named x and y), e.g. 'cell(\\d+)_(\\d+)'",
            field=OPTION,
        )
    xy = np.zeros((len(names), 2), dtype=np.int64)
    placed = np.zeros(len(names), dtype=bool)
    for s, name in enumerate(names):
        match = pattern.search(name)
        if match is None or match.group(groups[0]) is None or match.group(groups[1]) is None:
            continue
        xy[s] = (
            _whole(match.group(groups[0]), name, "the first group"),
            _whole(match.group(groups[1]), name, "the second group"),
        )
        placed[s] = True
    if not placed.any():
        raise ProblemError(
            f"{text!r} matches no state name; state names look like {_examples(names)}",
            field=OPTION,
        )
    return _checked(xy, placed, text)


def _whole(value: str, name: str, what: str) -> int:
    try:
        return int(value.strip())
    except ValueError:
        raise ProblemError(
            f"state {name!r}: {what} is {value!r}, not a whole number; a picture needs whole "
            "coordinates",
            field=OPTION,
        ) from None


def _examples(names: tuple[str, ...]) -> str:
    shown = ", ".join(repr(n) for n in names[:3])
    return shown + (", …" if len(names) > 3 else "")


def _checked(xy: np.ndarray, placed: np.ndarray, how: str, *, shift: bool = True) -> GridCells:
    """Cells counted from the picture's lower-left corner (the ``(x,y)`` names of grid worlds
    keep 0 there, as their maps do), refused when they cannot be drawn."""
    low = xy[placed].min(axis=0)
    if not shift:
        low = np.minimum(low, 0)
    xy = np.where(placed[:, None], xy - low, 0)
    width, height = (int(v) + 1 for v in xy[placed].max(axis=0))
    if width * height > MAX_CELLS:
        raise ProblemError(
            f"the coordinates ({how}) span {width:,} x {height:,} cells; a picture stops at "
            f"{MAX_CELLS:,}",
            field=OPTION,
        )
    if width == height == 1 and placed.sum() > 1:
        raise ProblemError(
            f"every one of the {int(placed.sum()):,} placed states falls in one cell ({how}): "
            "that is no picture; give the variables or groups that tell the cells apart",
            field=OPTION,
        )
    return GridCells(xy=xy, placed=placed, origin=(int(low[0]), int(low[1])), how=how)
