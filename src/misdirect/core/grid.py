"""Grid worlds: problems whose states are cells, named ``"(x,y)"``.

The paper-grid and sensor-grid scenarios, the drone scenario and grid maps all name their
states this way. Knowing the cell of each state is model geometry, not drawing: the audit
records whether a problem is a grid world, and the figures place states on the grid. It
lives here so that neither has to import the other.
"""

from __future__ import annotations

import re

import numpy as np

from misdirect.core.model import Problem

CELL = re.compile(r"^\((\d+),(\d+)\)$")  # grid worlds name their states "(x,y)"


def grid_cells(problem: Problem) -> np.ndarray | None:
    """(|S|, 2) cell coordinates if the problem is a grid world, else None."""
    matches = [CELL.match(name) for name in problem.pomdp.states]
    if not all(matches):
        return None
    return np.array([(int(m.group(1)), int(m.group(2))) for m in matches if m is not None])
