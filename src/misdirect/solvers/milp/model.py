"""A solver-neutral MILP: one sparse constraint matrix with row and column bounds.

Formulations build this once with numpy/scipy; backends hand it to a solver in bulk. Keeping
the model as plain arrays is what lets the same formulation go to HiGHS, Gurobi, SCIP or an
MPS/LP file without a per-row Python loop anywhere.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt
import scipy.sparse as sp

from misdirect.core.memory import check_memory
from misdirect.core.model import AlterationArray, Problem
from misdirect.errors import ProblemError

# Bytes a formulation's build holds at its peak per non-zero: the COO triplets of each row
# block (24), their concatenation (24), the CSR matrix and scipy's temporaries on the way, and
# the formulation's own index arrays; 88 measured on the paper's MILP of a 14x14 sensor grid
BUILD_BYTES_PER_NONZERO = 80


@dataclass(eq=False)
class MilpModel:
    """``maximise objective·x + offset`` s.t. ``row_lower ≤ A x ≤ row_upper``, column bounds."""

    formulation: str
    objective: np.ndarray
    offset: float
    matrix: sp.csr_matrix
    row_lower: np.ndarray
    row_upper: np.ndarray
    col_lower: np.ndarray
    col_upper: np.ndarray
    integer: np.ndarray  # bool per column
    budget_row: int
    column_blocks: dict[str, slice]
    row_blocks: dict[str, slice]
    decode: Callable[[np.ndarray], AlterationArray]  # column values -> alteration
    start_for: Callable[
        [AlterationArray], tuple[np.ndarray, np.ndarray]
    ]  # alteration -> (cols, vals)
    sound: bool = True  # does the optimum equal the true optimum (and the bound bound it)?
    row_scale: np.ndarray | None = None  # factor each row was multiplied by (None: all 1)
    # what the objective and the budget row were divided by before a backend got them
    # (misdirect.solvers.milp.solver scales both to about 1): multiply back to read them
    value_unit: float = 1.0
    cost_unit: float = 1.0
    build_time_s: float = 0.0
    notes: dict[str, Any] = field(default_factory=dict)
    # (column, observation, target) of every binary that says "observation reads target":
    # what another solver's solution is decoded through (misdirect decode)
    alteration_columns: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None

    @property
    def n_columns(self) -> int:
        return int(self.objective.size)

    @property
    def n_rows(self) -> int:
        return int(self.row_lower.size)

    def stats(self) -> dict[str, Any]:
        return {
            "formulation": self.formulation,
            "variables": self.n_columns,
            "binaries": int(self.integer.sum()),
            "rows": self.n_rows,
            "nonzeros": int(self.matrix.nnz),
            "build_time_s": self.build_time_s,
            "variables_by_block": {k: s.stop - s.start for k, s in self.column_blocks.items()},
            "rows_by_block": {k: s.stop - s.start for k, s in self.row_blocks.items()},
            **self.notes,
        }


COLUMN_MAP_SCHEMA = "misdirect-milp-columns/1"


def column_map(model: MilpModel, problem: Problem, budget: float) -> dict[str, Any]:
    """The JSON map from the model's columns (named ``c<index>`` in MPS/LP files) to the
    alteration they choose, for decoding another solver's solution: observation ``o`` reads
    ``target`` when that column is 1; an observation with no column at 1 is unaltered."""
    if model.alteration_columns is None:
        raise ValueError(f"the {model.formulation} formulation has no alteration columns")
    columns, observation, target = model.alteration_columns
    names = problem.pomdp.observations
    cost = problem.cost.matrix()
    return {
        "schema": COLUMN_MAP_SCHEMA,
        "formulation": model.formulation,
        "problem": problem.name,
        "budget": budget,
        "sense": "maximize",
        "objective_offset": model.offset,
        # the model is scaled as the solve scales it: the value is the objective (with its
        # offset) times value_unit, a cost in the budget row times cost_unit
        "value_unit": model.value_unit,
        "cost_unit": model.cost_unit,
        "columns": model.n_columns,
        "rule": "observation reads target where the column's value is 1 (above 0.5); "
        "observations without such a column are unaltered; the problem's value is "
        "(objective + objective_offset) x value_unit",
        "alteration_columns": [
            {
                "column": f"c{c}",
                "index": c,
                "observation": names[o],
                "target": names[t],
                "cost": 0.0 if o == t else float(cost[o, t]),
            }
            for c, o, t in zip(columns.tolist(), observation.tolist(), target.tolist(), strict=True)
        ],
    }


class ModelBuilder:
    """Collects column blocks and row blocks as COO triplets, then assembles one CSR matrix."""

    def __init__(self) -> None:
        self._col_parts: list[tuple[str, int, float, float, bool]] = []
        self._n_cols = 0
        self._row_parts: list[tuple[str, int]] = []
        self._n_rows = 0
        self._entries: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        self._lower: list[np.ndarray] = []
        self._upper: list[np.ndarray] = []
        self._scale: list[np.ndarray] = []
        self.column_blocks: dict[str, slice] = {}
        self.row_blocks: dict[str, slice] = {}

    def columns(
        self, name: str, count: int, lower: float, upper: float, *, integer: bool = False
    ) -> int:
        """Add ``count`` columns; returns the index of the first."""
        first = self._n_cols
        self._col_parts.append((name, int(count), lower, upper, integer))
        self.column_blocks[name] = slice(first, first + int(count))
        self._n_cols += int(count)
        return first

    def rows(
        self,
        name: str,
        count: int,
        entries: tuple[npt.ArrayLike, npt.ArrayLike, npt.ArrayLike],
        lower: np.ndarray | float,
        upper: np.ndarray | float,
        *,
        scale: float = 1.0,
    ) -> int:
        """Add ``count`` rows; ``entries`` are (row within block, column, coefficient).

        ``scale`` multiplies the rows (coefficients and bounds): a solver's absolute
        feasibility tolerance then allows only ``tolerance / scale`` in the original units.
        """
        first = self._n_rows
        row, col, val = (np.asarray(a) for a in entries)
        self._entries.append(
            (row.astype(np.int64) + first, col.astype(np.int64), scale * val.astype(np.float64))
        )
        self._lower.append(np.broadcast_to(scale * np.asarray(lower, dtype=np.float64), (count,)))
        self._upper.append(np.broadcast_to(scale * np.asarray(upper, dtype=np.float64), (count,)))
        self._scale.append(np.full(count, float(scale)))
        self.row_blocks[name] = slice(first, first + int(count))
        self._n_rows += int(count)
        return first

    @property
    def n_columns(self) -> int:
        return self._n_cols

    def build(self, *, objective: np.ndarray, **fields: Any) -> MilpModel:
        """Assemble the CSR matrix and bounds into a :class:`MilpModel`."""
        nonzeros = sum(part[0].size for part in self._entries)
        check_memory(
            nonzeros * (BUILD_BYTES_PER_NONZERO - 24),  # the triplets (24 bytes each) exist
            f"assembling the MILP ({self._n_cols:,} variables, {self._n_rows:,} rows, "
            f"{nonzeros:,} non-zeros)",
            field="milp",
        )
        if self._entries:
            rows, cols, vals = (np.concatenate(part) for part in zip(*self._entries, strict=True))
        else:
            rows = cols = np.zeros(0, dtype=np.int64)
            vals = np.zeros(0)
        matrix = sp.csr_matrix((vals, (rows, cols)), shape=(self._n_rows, self._n_cols))
        matrix.sum_duplicates()
        matrix.eliminate_zeros()
        parts = self._col_parts
        return MilpModel(
            objective=objective,
            matrix=matrix,
            row_lower=np.concatenate(self._lower) if self._lower else np.zeros(0),
            row_upper=np.concatenate(self._upper) if self._upper else np.zeros(0),
            row_scale=np.concatenate(self._scale) if self._scale else np.zeros(0),
            col_lower=np.concatenate(
                [np.full(n, lo, dtype=np.float64) for _, n, lo, _, _ in parts]
            ),
            col_upper=np.concatenate(
                [np.full(n, up, dtype=np.float64) for _, n, _, up, _ in parts]
            ),
            integer=np.concatenate([np.full(n, i, dtype=bool) for _, n, _, _, i in parts]),
            column_blocks=dict(self.column_blocks),
            row_blocks=dict(self.row_blocks),
            **fields,
        )


def decode_columns(
    problem: Problem, entries: list[dict[str, Any]], values: dict[str, float]
) -> AlterationArray:
    """The alteration a solution chooses, read through a column map's ``alteration_columns``
    (``values``: column name -> value; a column not listed is 0). Two targets chosen for one
    observation, or a name the problem does not know, is a ProblemError."""
    index = {name: i for i, name in enumerate(problem.pomdp.observations)}
    alteration = problem.identity()
    chosen: dict[str, str] = {}
    for k, entry in enumerate(entries):
        if values.get(entry["column"], 0.0) <= 0.5:
            continue
        observation, target = entry["observation"], entry["target"]
        for name in (observation, target):
            if name not in index:
                raise ProblemError(
                    f"the map names observation {name!r}, which the problem does not have "
                    "(a map of another problem?)",
                    field=f"alteration_columns[{k}]",
                )
        if observation in chosen and chosen[observation] != target:
            raise ProblemError(
                f"the solution sends {observation!r} to both {chosen[observation]!r} and "
                f"{target!r} (columns at 1); an alteration gives each observation one target",
                field=entry["column"],
            )
        chosen[observation] = target
        alteration[index[observation]] = index[target]
    return alteration
