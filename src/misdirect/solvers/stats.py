"""What each method counted while it solved: typed records, one class per method.

A record is read by attribute (``stats.nodes``), tested by type (``isinstance(stats,
MilpStats)``: "a MILP answered"), and written as the JSON's ``stats`` object by ``to_dict``,
whose keys are the field names (nested records flattened as before). Each record is also a
read-only mapping of those keys, so ``stats["nodes"]`` keeps working for scripts written
against the JSON.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field, fields
from typing import Any

from misdirect.solvers.status import Status


@dataclass(frozen=True)
class MethodStats(Mapping[str, Any]):
    """Base of every method's record: a mapping of its JSON keys to their values."""

    def to_dict(self) -> dict[str, Any]:
        return {f.name: getattr(self, f.name) for f in fields(self)}

    def __getitem__(self, key: str) -> Any:
        return self.to_dict()[key]

    def __iter__(self) -> Iterator[str]:
        return iter(self.to_dict())

    def __len__(self) -> int:
        return len(self.to_dict())


@dataclass(frozen=True)
class NoStats(MethodStats):
    """A method that had nothing to count (e.g. a problem without any choice)."""


@dataclass(frozen=True)
class ExhaustiveStats(MethodStats):
    evaluations: int  # alterations evaluated exactly
    alterations_within_budget: int
    relevant_observations: int
    candidates_per_observation: list[int]


@dataclass(frozen=True)
class IncrementalStats(MethodStats):
    evaluations: int  # alterations valued (by low-rank updates or solves)
    factorisations: int  # blocks that solved a base chain (one per outer choice vector)
    inner_observations: int
    outer_observations: int


@dataclass(frozen=True)
class SegmentStats:
    """The segment search's share of a branch-and-bound answer, when it took the budget."""

    nodes: int
    root_bound: float | None
    enumerated: int  # nodes enumerated (low-rank updates) instead of bounded
    enumerated_alterations: int


@dataclass(frozen=True)
class BranchAndBoundStats(MethodStats):
    nodes: int
    pruned: int
    policy_evaluations: int  # exact linear solves of the relaxation
    root_bound: float | None
    relevant_observations: int
    segment: SegmentStats | None = None
    # node bounds proven, those left at the trivial bound although policy iteration's value
    # lay below it (no proof verified: "no proof yet", not "no bound known"), and the proofs
    # on the MDP with its end components collapsed, tried and successful
    proofs: int = 0
    trivial_bounds: int = 0
    collapsed_proofs: int = 0
    collapsed_proven: int = 0
    # covering bounds (solvers/engines/covering.py): nodes covered, the relaxations solved for
    # them (unions and their refinements), unions refined (above the incumbent), nodes the
    # cover pruned where the per-state bound did not, covers given up, and the root's
    covers: int = 0
    cover_unions: int = 0
    cover_refined: int = 0
    cover_pruned: int = 0
    covers_given_up: int = 0  # covers stopped at a union no better than the per-state bound,
    # or out of their share of the time
    root_cover_bound: float | None = None
    # an open budget's: what holds its bound up, "relaxation", "proof" or "time" (None: closed)
    weakest_bound: str | None = None

    def to_dict(self) -> dict[str, Any]:
        shown = {f.name: getattr(self, f.name) for f in fields(self) if f.name != "segment"}
        if self.segment is not None:
            segment = self.segment
            shown.update({f"segment_{f.name}": getattr(segment, f.name) for f in fields(segment)})
        return shown


@dataclass(frozen=True)
class MilpStats(MethodStats):
    """The model's size (``formulation``, ``variables``, ``binaries``, ``rows``,
    ``nonzeros``, ``build_time_s``, per-block counts), how the backend stopped, and its claim;
    ``backend`` holds the backend's own details (e.g. ``highs_status``)."""

    model: Mapping[str, Any]
    solver: str
    solve_time_s: float
    status: Status  # how the backend stopped; the point's status may be lower
    objective: float | None
    bound: float | None
    nodes: int | None
    claimed: float | None  # the objective, or its recomputation with rounded binaries
    violation: float  # how far the backend's point is from feasible
    backend: Mapping[str, Any] = field(default_factory=dict)

    @property
    def formulation(self) -> str:
        return str(self.model["formulation"])

    @property
    def variables(self) -> int:
        return int(self.model["variables"])

    @property
    def rows(self) -> int:
        return int(self.model["rows"])

    @property
    def nonzeros(self) -> int:
        return int(self.model["nonzeros"])

    @property
    def build_time_s(self) -> float:
        return float(self.model["build_time_s"])

    def to_dict(self) -> dict[str, Any]:
        own = {f.name: getattr(self, f.name) for f in fields(self)}
        del own["model"], own["backend"]
        return {**self.model, **own, **self.backend}


@dataclass(frozen=True)
class AutoStats(MethodStats):
    """auto's answer: the record of the stage whose answer it is, why auto chose as it did,
    and, after a hand-over, both stages' records."""

    answer: MethodStats
    reason: str
    stages: tuple[MethodStats, MethodStats] | None = None

    def to_dict(self) -> dict[str, Any]:
        shown = {**self.answer.to_dict(), "auto_reason": self.reason}
        if self.stages is not None:
            shown["stages"] = [stage.to_dict() for stage in self.stages]
        return shown
