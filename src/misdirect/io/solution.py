"""Reading another MILP solver's solution file: the value of each named column.

HiGHS (``--solution_file``, its raw format), Gurobi (``.sol``) and SCIP (``write solution``)
all list primal values as ``name value`` lines; they differ in the lines around them. HiGHS
follows the primal values with dual ones under ``# Dual solution values``, which are not read;
SCIP appends ``(obj:...)`` and leaves out columns at 0. A column the file does not list is 0.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from pathlib import Path

from misdirect.errors import ProblemError
from misdirect.io.files import read_text_file

_OBJECTIVE = re.compile(
    r"^\s*(?:#\s*)?(?:objective(?:\s+value)?)\s*[=:]?\s*(?P<value>\S+)\s*$", re.IGNORECASE
)
_VALUE = re.compile(r"^\s*(?P<name>\S+)\s+(?P<value>\S+)(?:\s+\(obj:[^)]*\))?\s*$")


@dataclass(frozen=True)
class Solution:
    values: dict[str, float]  # column name -> value, as the file lists them
    objective: float | None  # the objective the file reports, if it does


def read_solution(path: Path, *, field: str = "SOLUTION") -> Solution:
    """The ``name value`` lines of a HiGHS, Gurobi or SCIP solution file; a value that is no
    finite number is an error naming the line."""
    text = read_text_file(Path(path))
    values: dict[str, float] = {}
    objective = None
    for number, line in enumerate(text.splitlines(), start=1):
        if line.lstrip().lower().startswith("# dual"):
            break  # HiGHS: dual values follow, under the same column names
        found = _OBJECTIVE.match(line)
        if found is not None:
            objective = _number(found["value"], path, f"{field}, line {number}")
            continue
        if line.lstrip().startswith("#"):
            continue
        found = _VALUE.match(line)
        if found is None:
            continue  # status lines and headers ("Model status", "Feasible", ...)
        try:
            value = float(found["value"])
        except ValueError:
            continue  # "solution status: optimal solution found" and the like
        if not math.isfinite(value):
            raise ProblemError(
                f"column {found['name']!r} has value {found['value']!r}, not a finite number",
                source=str(path),
                field=f"line {number}",
            )
        values[found["name"]] = value
    if not values:
        raise ProblemError(
            "no 'name value' lines: expected a HiGHS, Gurobi or SCIP solution file",
            source=str(path),
        )
    return Solution(values=values, objective=objective)


def _number(text: str, path: Path, where: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise ProblemError(
            f"objective {text!r} is not a number", source=str(path), field=where
        ) from None
    return value
