"""Grid worlds written as maps, the way robotics users draw them.

A map is rows of whitespace-separated cells, the first row northmost. A digit (or a string of
digits) is a sensor id: cells with the same id emit the same observation, named by the id. Other
symbols are looked up in the legend: ``blank`` (emits ``b``), ``goal`` (absorbing), ``decoy``
(absorbing, the attacker's target), ``wall`` (not a state; moving into it keeps the robot in
place), or a mapping ``{kind, start, sensor}`` for a cell that is, say, the start and is also
watched by sensor 0.

Dynamics are the paper's (SPEC §3) with ``slip`` per orthogonal direction: the intended move
happens with ``1 - 2 slip`` (staying put when it would leave the grid or hit a wall); an
orthogonal move that would leave the grid gives its mass to the other orthogonal direction, and
one into a wall keeps the robot in place. Cell ``(x, y)`` is named ``"(x,y)"``, x growing East
and y North, so the paper's 5x5 grid drawn as a map is the ``paper-grid`` scenario exactly.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from misdirect.core.model import Pomdp
from misdirect.errors import ProblemError

DIRECTIONS = {"N": (0, 1), "E": (1, 0), "S": (0, -1), "W": (-1, 0)}
KINDS = ("blank", "goal", "decoy", "wall")
BLANK_OBSERVATION = "b"


@dataclass(frozen=True)
class LegendEntry:
    kind: str = "blank"
    start: bool = False
    sensor: str | None = None


@dataclass(frozen=True)
class GridWorld:
    pomdp: Pomdp
    decoy: np.ndarray  # (|S|,) bool
    width: int
    height: int


def compile_grid(
    text: str,
    legend: Mapping[str, LegendEntry],
    *,
    slip: float = 0.1,
    actions: Sequence[str] = ("N", "E", "S", "W"),
) -> GridWorld:
    """Parse and compile a map; errors name ``grid.map`` with line and column."""
    cells = _parse(text)
    height, width = len(cells), len(cells[0][1])
    kinds = np.empty((height, width), dtype=object)
    sensors = np.full((height, width), None, dtype=object)
    starts = []
    for row, (line, tokens) in enumerate(cells):
        y = height - 1 - row
        for x, (column, token) in enumerate(tokens):
            entry = legend.get(token)
            if entry is None and token.isdecimal():
                entry = LegendEntry(kind="blank", sensor=token)
            if entry is None:
                known = ", ".join(repr(k) for k in legend) or "none"
                raise ProblemError(
                    f"symbol {token!r} is not in grid.legend (defined: {known}; digits are "
                    "sensor ids)",
                    field=f"grid.map, line {line}, column {column}",
                )
            kinds[y, x], sensors[y, x] = entry.kind, entry.sensor
            if entry.start:
                starts.append((line, column, x, y))
    if not starts:
        raise ProblemError(
            "the map has no start cell: give one symbol {start: true} in grid.legend",
            field="grid.map",
        )
    if len(starts) > 1:
        (l1, c1, *_), (l2, c2, *_) = starts[:2]
        raise ProblemError(
            f"the map has {len(starts)} start cells (line {l1}, column {c1} and line {l2}, "
            f"column {c2}); a run starts in exactly one",
            field="grid.map",
        )
    _, _, sx, sy = starts[0]
    for symbol, entry in legend.items():
        if entry.kind == "wall" and (entry.start or entry.sensor is not None):
            raise ProblemError(
                "a wall is not a state: it cannot be the start or carry a sensor",
                field=f"grid.legend.{symbol}",
            )
    for name in actions:
        if name not in DIRECTIONS:
            raise ProblemError(
                f"unknown action {name!r}: grid actions are N, E, S, W", field="grid.actions"
            )
    if len(set(actions)) != len(actions):
        raise ProblemError("an action is listed twice", field="grid.actions")

    open_cell = kinds != "wall"
    state_of = np.full((height, width), -1, dtype=np.int64)
    ys, xs = np.nonzero(open_cell)
    order = np.lexsort((xs, ys))  # state index grows with x, then y: (y * width + x) order
    xs, ys = xs[order], ys[order]
    state_of[ys, xs] = np.arange(xs.size)

    sensor_ids = sorted({s for s in sensors[open_cell] if s is not None}, key=_sensor_order)
    observations = (*sensor_ids, BLANK_OBSERVATION)
    obs_index = {name: i for i, name in enumerate(observations)}
    observation_of = np.array(
        [obs_index[sensors[y, x] or BLANK_OBSERVATION] for x, y in zip(xs, ys, strict=True)],
        dtype=np.int64,
    )
    absorbing = np.isin(kinds[ys, xs].astype(str), ("goal", "decoy"))
    decoy = kinds[ys, xs].astype(str) == "decoy"

    parts = [_moves(a, DIRECTIONS[name], xs, ys, state_of, slip) for a, name in enumerate(actions)]
    action, source, target, probability = (np.concatenate(p) for p in zip(*parts, strict=True))
    pomdp = Pomdp.from_triplets(
        states=tuple(f"({x},{y})" for x, y in zip(xs, ys, strict=True)),
        actions=tuple(actions),
        observations=observations,
        initial_state=int(state_of[sy, sx]),
        observation_of=observation_of,
        action=action,
        source=source,
        target=target,
        probability=probability,
        absorbing=absorbing,
    )
    return GridWorld(pomdp, decoy, width, height)


def _sensor_order(name: str) -> tuple[int, str]:
    return (int(name), name) if name.isdecimal() else (10**9, name)


def _parse(text: str) -> list[tuple[int, list[tuple[int, str]]]]:
    """Rows as (line number, [(column, token)]); ragged rows are an error."""
    rows = []
    for number, raw in enumerate(text.splitlines(), start=1):
        tokens, column = [], 0
        for piece in raw.split():
            column = raw.index(piece, column)
            tokens.append((column + 1, piece))
            column += len(piece)
        if tokens:
            rows.append((number, tokens))
    if not rows:
        raise ProblemError("the map is empty", field="grid.map")
    width = len(rows[0][1])
    for number, tokens in rows:
        if len(tokens) != width:
            raise ProblemError(
                f"ragged map: this row has {len(tokens)} cells, the first has {width}",
                field=f"grid.map, line {number}",
            )
    return rows


def _moves(
    action: int,
    direction: tuple[int, int],
    xs: np.ndarray,
    ys: np.ndarray,
    state_of: np.ndarray,
    slip: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Transition entries of one action from every open cell."""
    height, width = state_of.shape
    here = state_of[ys, xs]

    def look(dx: int, dy: int) -> tuple[np.ndarray, np.ndarray]:
        tx, ty = xs + dx, ys + dy
        inside = (tx >= 0) & (tx < width) & (ty >= 0) & (ty < height)
        target = np.full(xs.size, -1, dtype=np.int64)
        target[inside] = state_of[ty[inside], tx[inside]]
        return inside, target  # target -1: outside or a wall

    dx, dy = direction
    _, ahead = look(dx, dy)
    entries = [(np.where(ahead >= 0, ahead, here), np.full(xs.size, 1.0 - 2.0 * slip))]
    sides = [look(dy, dx), look(-dy, -dx)]  # the two orthogonal directions
    for (inside_a, a), (_, b) in (sides, sides[::-1]):
        # own mass: move if open, stay if wall, hand to the other side if off the grid
        own = np.where(a >= 0, a, here)
        handed = ~inside_a
        own = np.where(handed, np.where(b >= 0, b, here), own)
        entries.append((own, np.full(xs.size, slip)))
    source = np.concatenate([here] * len(entries))
    target = np.concatenate([t for t, _ in entries])
    probability = np.concatenate([p for _, p in entries])
    return np.full(source.size, action), source, target, probability
