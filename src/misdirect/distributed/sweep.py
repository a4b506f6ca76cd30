"""``misdirect sweep SPEC``: many problems or generated scenarios × budgets × methods (× the
δ of ``max_alarm``, under a monitor), one results table.

Each row is one solve, identified by a stable ``row_id`` (a hash of its instance, budget and
method, not of the time limit or of where it runs). The table is rewritten atomically after
every row that completes (CSV; Parquet too, at most every few seconds and at the end), so a
run stopped in any way loses no finished row, and a second run with the same output skips
every row already there with a result (rows that failed with an error are run again).
"""

from __future__ import annotations

import collections.abc
import contextlib
import csv
import hashlib
import inspect
import io
import json
import math
import stat
import time
import typing
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

try:
    import fcntl
except ImportError:  # Windows: no advisory locks; concurrent sweeps need their own folders
    fcntl = None  # type: ignore[assignment]

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    TypeAdapter,
    ValidationError,
    field_validator,
)

from misdirect.core.model import Problem, format_alteration
from misdirect.errors import MisdirectError, ProblemError
from misdirect.io.files import parse_json, parse_yaml, read_text_file, write_output
from misdirect.io.problem_file import (
    CONSISTENCY,
    error_field,
    error_reason,
    load_problem,
    monitored,
    read_monitor,
)
from misdirect.scenarios import drone, knapsack, paper_grid, random_problem, sensor_grid
from misdirect.solvers import SOLVERS
from misdirect.solvers.deadline import CancelToken
from misdirect.solvers.pool import LocalPool, TaskPool
from misdirect.solvers.run import solve

FORMAT: Literal["misdirect-sweep/v1"] = "misdirect-sweep/v1"
PARQUET_EVERY_S = 5.0  # the Parquet copy is rewritten at most this often (and at the end)

GENERATORS: dict[str, Callable[..., Problem]] = {
    "random": random_problem,
    "sensor-grid": sensor_grid,
    "paper-grid": paper_grid,
    "knapsack": knapsack,
    "drone": drone,
}

# the results table: column, type (how a CSV cell reads back)
COLUMNS: tuple[tuple[str, type], ...] = (
    ("row_id", str),
    ("instance", str),
    ("seed", int),
    ("budget", float),
    ("method", str),
    ("status", str),
    ("probability", float),
    ("upper_bound", float),
    ("gap", float),
    ("cost", float),
    ("alteration", str),
    ("time_s", float),
    ("host", str),
    ("worker", str),
    ("pid", int),
    ("error", str),
    ("max_alarm", float),  # the δ of Pr(alarm) <= δ, where the sweep gives one
    ("alarm", float),  # a monitored row's Pr(alarm) for its answer
)
# columns a table written before they existed may lack (read back as empty)
OPTIONAL_COLUMNS = frozenset({"max_alarm", "alarm"})
ERROR = "error"  # the status of a row that raised: run again on resume


SEED_LIMIT = 2**63  # seeds are stored as int64 (the Parquet table's column)


class ScenarioSpec(BaseModel):
    """Generated instances: one per seed (or one, for generators without a seed)."""

    # strict: `seeds: ["7"]` and `budgets: [true]` are refused, not read as 7 and 1.0
    model_config = ConfigDict(extra="forbid", strict=True)
    scenario: Literal["random", "sensor-grid", "paper-grid", "knapsack", "drone"]
    parameters: dict[str, Any] = Field(default_factory=dict)
    seeds: list[int] | None = None

    @field_validator("seeds")
    @classmethod
    def _seeds(cls, seeds: list[int] | None) -> list[int] | None:
        for seed in seeds or []:
            if not 0 <= seed < SEED_LIMIT:
                raise ValueError(f"a seed must be a whole number in [0, 2^63), got {seed}")
        return seeds


class SweepSpec(BaseModel):
    """A sweep file (``format: misdirect-sweep/v1``)."""

    model_config = ConfigDict(extra="forbid", strict=True)
    format: Literal["misdirect-sweep/v1"] = FORMAT
    problems: list[str] = Field(default_factory=list)  # files, relative to the sweep file
    scenarios: list[ScenarioSpec] = Field(default_factory=list)
    budgets: list[float] = Field(min_length=1)
    methods: list[str] = Field(default_factory=lambda: ["auto"], min_length=1)
    time_limit: float | None = Field(default=None, gt=0)  # seconds per row
    # a monitor every row is watched by: "consistency", or a monitor file (relative to the
    # sweep file); it replaces a problem file's own
    monitor: str | None = None
    # each δ a row of its own: the best attack with Pr(alarm) <= δ (a monitor needed: the
    # sweep's, else a problem file's own, else the consistency monitor)
    max_alarm: list[float] | None = Field(default=None, min_length=1)

    @field_validator("max_alarm")
    @classmethod
    def _max_alarm(cls, deltas: list[float] | None) -> list[float] | None:
        for delta in deltas or []:
            if not 0.0 <= delta <= 1.0:
                raise ValueError(f"a max_alarm must be a probability in [0, 1], got {delta}")
        return deltas

    @field_validator("budgets")
    @classmethod
    def _budgets(cls, budgets: list[float]) -> list[float]:
        for b in budgets:
            if not b >= 0 or b == float("inf"):
                raise ValueError(f"a budget must be a non-negative number, got {b}")
        return budgets

    @field_validator("time_limit")
    @classmethod
    def _time_limit(cls, limit: float | None) -> float | None:
        if limit is not None and not math.isfinite(limit):
            raise ValueError(f"a time limit must be a finite number of seconds, got {limit}")
        return limit

    @field_validator("methods")
    @classmethod
    def _methods(cls, methods: list[str]) -> list[str]:
        for m in methods:
            if m not in SOLVERS:
                raise ValueError(f"unknown method {m!r} (choose from {', '.join(SOLVERS)})")
        return methods


@dataclass(frozen=True)
class Row:
    """One row to compute: an instance (a loaded problem, or a generator call), a budget, a
    method."""

    row_id: str
    instance: str
    budget: float
    method: str
    time_limit: float | None
    # which of the sweep's problem files (its index in the list :func:`expand` returns)
    problem: int | None = None
    scenario: str | None = None
    parameters: dict[str, Any] = field(default_factory=dict)
    seed: int | None = None
    monitor: str | None = None  # "consistency" or a monitor file's path
    max_alarm: float | None = None


@dataclass
class SweepReport:
    """What a run did: the whole table, and how many rows it computed, skipped or lost."""

    rows: list[dict[str, Any]]
    computed: int
    skipped: int
    failed: int
    csv: Path
    parquet: Path | None
    notes: list[str] = field(default_factory=list)


def load_sweep(path: Path) -> tuple[SweepSpec, Path]:
    """The validated sweep file and its folder; errors name the file and the field."""
    source = str(path)
    text = read_text_file(path)
    document = (
        parse_json(text, source=source)
        if path.suffix.lower() == ".json"
        else parse_yaml(text, source=source)
    )
    if not isinstance(document, dict):
        raise ProblemError(
            "the file must contain a mapping with budgets, methods, ...", source=source
        )
    try:
        spec = SweepSpec.model_validate(document)
    except ValidationError as error:
        first = error.errors()[0]
        where = error_field(first["loc"])
        raise ProblemError(error_reason(first), source=source, field=where or None) from None
    if not spec.problems and not spec.scenarios:
        raise ProblemError("lists no problems and no scenarios", source=source, field="problems")
    for k, item in enumerate(spec.scenarios):
        _check_parameters(item, source, f"scenarios[{k}]")
    return spec, path.parent


def _check_parameters(item: ScenarioSpec, source: str, where: str) -> None:
    """The generator takes every parameter given, of its type (and a seed, when seeds are
    given): a wrong type is the file's error, named here, not every row's TypeError."""
    generate = GENERATORS[item.scenario]
    accepted = inspect.signature(generate).parameters
    hints = typing.get_type_hints(generate)
    for name, value in item.parameters.items():
        if name not in accepted or name == "seed":
            known = ", ".join(p for p in accepted if p != "seed")
            raise ProblemError(
                f"{item.scenario} takes no parameter {name!r} (it takes {known})",
                source=source,
                field=f"{where}.parameters.{name}",
            )
        if name in hints:
            try:
                TypeAdapter(hints[name]).validate_python(value, strict=True)
            except ValidationError:
                raise ProblemError(
                    f"{item.scenario}'s {name} must be {_type_name(hints[name])}, got {value!r}",
                    source=source,
                    field=f"{where}.parameters.{name}",
                ) from None
    if item.seeds is not None and "seed" not in accepted:
        raise ProblemError(f"{item.scenario} takes no seed", source=source, field=f"{where}.seeds")


def _type_name(hint: Any) -> str:
    """A type as a sentence says it: ``int`` a whole number, ``float`` a number, ..."""
    names = {int: "a whole number", float: "a number", str: "a string", bool: "true or false"}
    if hint in names:
        return names[hint]
    args = [a for a in typing.get_args(hint) if a is not type(None)]
    if typing.get_origin(hint) in (list, collections.abc.Sequence) and args:
        return f"a list of {_type_name(args[0]).removeprefix('a ')}s"
    if len(args) == 1:  # X | None
        return _type_name(args[0])
    return str(hint)


def row_id(
    instance: dict[str, Any],
    budget: float,
    method: str,
    monitor: str | None = None,
    max_alarm: float | None = None,
) -> str:
    """The stable key of a row: its instance, budget and method (not the time limit), and its
    monitor and δ where it has them (a row without keeps the key it had before they were)."""
    fields: dict[str, Any] = {"instance": instance, "budget": float(budget), "method": method}
    if monitor is not None:
        fields["monitor"] = monitor
    if max_alarm is not None:
        fields["max_alarm"] = float(max_alarm)
    key = json.dumps(fields, sort_keys=True)
    return hashlib.sha256(key.encode()).hexdigest()[:16]


def _watching(spec: SweepSpec, folder: Path) -> str | None:
    """The sweep's monitor as its rows name it (a file made absolute), checked once here:
    a wrong monitor file is one error naming it, not an error in every row."""
    if spec.monitor is None or spec.monitor == CONSISTENCY:
        return spec.monitor
    path = folder / spec.monitor
    try:
        read_monitor(path)
    except ProblemError as error:
        error.field = error.field or "monitor"
        raise
    return str(path.absolute())


def expand(
    spec: SweepSpec, folder: Path, pool: TaskPool | None = None
) -> tuple[list[Row], list[Any]]:
    """Every row of the sweep, in the file's order: instances × budgets × methods; and the
    problem files' problems (as the pool shares them) that rows name by index. Problem files
    are read (and checked) here, once, and handed to the pool once each: a row passes its
    problem to its task as an argument of its own, which a cluster resolves (a handle inside
    the row object would reach the worker unresolved)."""
    rows: list[Row] = []
    problems: list[Any] = []
    monitor = _watching(spec, folder)
    deltas: Sequence[float | None] = spec.max_alarm if spec.max_alarm is not None else [None]
    for k, name in enumerate(spec.problems):
        path = folder / name
        try:
            problem = load_problem(path)
        except ProblemError as error:
            error.field = error.field or f"problems[{k}]"
            raise
        problems.append(pool.share(problem) if pool is not None else problem)
        for b in spec.budgets:
            for m in spec.methods:
                for delta in deltas:
                    rid = row_id({"file": name}, b, m, spec.monitor, delta)
                    rows.append(
                        Row(
                            rid,
                            name,
                            float(b),
                            m,
                            spec.time_limit,
                            problem=k,
                            monitor=monitor,
                            max_alarm=delta,
                        )
                    )
    for item in spec.scenarios:
        accepted = inspect.signature(GENERATORS[item.scenario]).parameters
        seeds: Sequence[int | None] = item.seeds if item.seeds is not None else [None]
        if item.seeds is None and "seed" in accepted:
            seeds = [0]
        for seed in seeds:
            shown = ", ".join(f"{p}={v}" for p, v in item.parameters.items())
            label = f"{item.scenario}({shown}{', ' if shown else ''}seed={seed})"
            if seed is None:
                label = f"{item.scenario}({shown})"
            key = {"scenario": item.scenario, "parameters": item.parameters, "seed": seed}
            for b in spec.budgets:
                for m in spec.methods:
                    for delta in deltas:
                        rid = row_id(key, b, m, spec.monitor, delta)
                        rows.append(
                            Row(
                                rid,
                                label,
                                float(b),
                                m,
                                spec.time_limit,
                                None,
                                item.scenario,
                                dict(item.parameters),
                                seed,
                                monitor,
                                delta,
                            )
                        )
    return rows, problems


def run_row(row: Row, problem: Problem | None = None) -> dict[str, Any]:
    """Compute one row where it runs (``problem``: its problem file's, for a file's row); an
    error becomes the row's ``error`` (it never takes the sweep down)."""
    from misdirect.distributed.pool import where_am_i

    started = time.perf_counter()
    result: dict[str, Any] = {
        "row_id": row.row_id,
        "instance": row.instance,
        "seed": row.seed,
        "budget": row.budget,
        "method": row.method,
        "max_alarm": row.max_alarm,
        **where_am_i(),
    }
    try:
        if problem is None:
            generate = GENERATORS[row.scenario or ""]
            extra = {} if row.seed is None else {"seed": row.seed}
            if row.scenario == "random" and row.seed is not None:
                problem = generate(row.seed, **row.parameters)
            else:
                problem = generate(**row.parameters, **extra)
        problem = _watched(problem, row)
        solved = solve(
            problem,
            method=row.method,
            budgets=[row.budget],
            time_limit=row.time_limit,
            max_alarm=row.max_alarm,
        )
        point = solved.final
        result.update(
            status=str(point.status),
            probability=point.probability,
            upper_bound=point.upper_bound,
            gap=point.gap,
            cost=point.cost,
            alteration=format_alteration(point.alteration),
            alarm=point.alarm,
            error=None,
        )
    except (MisdirectError, ValueError, MemoryError) as error:
        result.update(status=ERROR, error=f"{type(error).__name__}: {error}")
    result["time_s"] = time.perf_counter() - started
    return result


def _watched(problem: Problem, row: Row) -> Problem:
    """``problem`` under the row's monitor (in place of its own), or under the consistency
    monitor where the row asks for a δ and nothing watches it."""
    if row.monitor is not None:
        given, where = read_monitor(row.monitor)
        plain = problem.without_monitor() if problem.unwatched is not None else problem
        return monitored(plain, given, source=where, field="")
    if row.max_alarm is not None and problem.unwatched is None:
        given, where = read_monitor(CONSISTENCY)
        return monitored(problem, given, source=where, field="")
    return problem


def lost_row(row: Row, error: BaseException) -> dict[str, Any]:
    """The row of a task the cluster could not finish (its worker lost, more than once)."""
    return {
        "row_id": row.row_id,
        "instance": row.instance,
        "seed": row.seed,
        "budget": row.budget,
        "method": row.method,
        "max_alarm": row.max_alarm,
        "status": ERROR,
        "error": f"{type(error).__name__}: {error}",
    }


# -- the table ------------------------------------------------------------------------------


def _cell(value: str, kind: type) -> Any:
    if value == "":
        return None
    return kind(value)


TABLE_LIMIT = 1 << 30  # a results table larger than this (bytes) is no table of ours


def read_table(path: Path) -> list[dict[str, Any]]:
    """The rows of a results CSV written by :func:`table_csv` (types restored). A path that
    is no regular file (a FIFO, a device such as ``/dev/zero``), or a file that is no such
    table, is refused naming the file: resuming from it would lose or invent rows."""
    try:
        info = path.stat()
    except OSError as error:
        raise ProblemError(f"cannot read it: {error.strerror}", source=str(path)) from None
    if not stat.S_ISREG(info.st_mode):
        raise ProblemError(
            "is not a regular file; name another output folder", source=str(path), field="out"
        )
    if info.st_size > TABLE_LIMIT:
        raise ProblemError(
            f"is larger than {TABLE_LIMIT >> 20} MB: not a results table", source=str(path)
        )
    try:
        with open(path, newline="", encoding="utf-8") as handle:
            reader = csv.DictReader(handle)
            if reader.fieldnames is None:
                return []
            missing = [
                name
                for name, _ in COLUMNS
                if name not in reader.fieldnames and name not in OPTIONAL_COLUMNS
            ]
            if missing:
                raise ProblemError(
                    f"is not a sweep's results table (no column {missing[0]!r}); remove it or "
                    "name another output folder",
                    source=str(path),
                )
            rows = []
            for number, line in enumerate(reader, start=2):
                try:
                    rows.append({name: _cell(line.get(name) or "", kind) for name, kind in COLUMNS})
                except ValueError as error:
                    raise ProblemError(
                        f"line {number}: not a results row ({error}); remove the line or the file",
                        source=str(path),
                    ) from None
            return rows
    except (UnicodeDecodeError, csv.Error) as error:
        raise ProblemError(
            f"is not a sweep's results table ({error}); remove it or name another folder",
            source=str(path),
        ) from None


@contextlib.contextmanager
def _table_lock(out: Path) -> Iterator[None]:
    """Hold the results folder's lock: two sweeps writing one table take turns, and each
    merges what the other wrote (no row of either is lost). Advisory (``flock``) where the
    system has it."""
    lock = out / ".results.lock"
    with open(lock, "a", encoding="utf-8") as handle:
        if fcntl is not None:
            fcntl.flock(handle.fileno(), fcntl.LOCK_EX)
        try:
            yield
        finally:
            if fcntl is not None:
                fcntl.flock(handle.fileno(), fcntl.LOCK_UN)


def _merged(
    path: Path, ours: Sequence[dict[str, Any]], order: Sequence[str]
) -> list[dict[str, Any]]:
    """The table on disk with ``ours`` written over it by row id: this sweep's rows in its
    ``order`` first, then every other row found there (another sweep's, or one this sweep
    has not reached), as they were."""
    on_disk = read_table(path) if path.exists() else []
    mine = {r["row_id"]: r for r in ours}
    theirs = {r["row_id"]: r for r in on_disk if r["row_id"] not in mine}
    first = [mine.get(rid) or theirs.pop(rid) for rid in order if rid in mine or rid in theirs]
    return first + list(theirs.values())


def table_csv(rows: Sequence[dict[str, Any]]) -> str:
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow([name for name, _ in COLUMNS])
    for row in rows:
        cells = [row.get(name) for name, _ in COLUMNS]
        writer.writerow(
            ["" if c is None else repr(c) if isinstance(c, float) else c for c in cells]
        )
    return buffer.getvalue()


def write_parquet(rows: Sequence[dict[str, Any]], path: Path) -> bool:
    """The table as Parquet (atomically); False when pyarrow is not installed."""
    try:
        import pyarrow as pa
        import pyarrow.parquet as pq
    except ImportError:
        return False
    types = {str: pa.string(), int: pa.int64(), float: pa.float64()}
    schema = pa.schema([(name, types[kind]) for name, kind in COLUMNS])
    table = pa.Table.from_pylist(
        [{name: row.get(name) for name, _ in COLUMNS} for row in rows], schema=schema
    )
    write_output(path, lambda staged: pq.write_table(table, staged), field="out")
    return True


def run_sweep(
    spec: SweepSpec,
    folder: Path,
    out: Path,
    *,
    pool: TaskPool | None = None,
    on_row: Callable[[dict[str, Any], int, int], None] | None = None,
    cancel: CancelToken | None = None,
) -> SweepReport:
    """Run every row of ``spec`` not already in ``out``/results.csv, writing the table after
    each; ``on_row(row, done, total)`` after each row (the progress bar). Without ``pool`` the
    rows run here, one after another."""
    if out.exists() and not out.is_dir():
        raise ProblemError(
            "is a file: the sweep writes a folder of results; name a folder", source=str(out)
        )
    rows, problems = expand(spec, folder, pool)  # every problem file read before writing
    out.mkdir(parents=True, exist_ok=True)
    csv_path, parquet_path = out / "results.csv", out / "results.parquet"
    order = [row.row_id for row in rows]
    with _table_lock(out):
        previous = read_table(csv_path) if csv_path.exists() else []
    done = {r["row_id"]: r for r in previous if r["status"] != ERROR}
    todo = [row for row in rows if row.row_id not in done]
    pool = pool if pool is not None else LocalPool()
    by_ticket: dict[Any, Row] = {}
    finished: dict[str, dict[str, Any]] = {}  # rows this run computed
    computed = failed = 0
    notes: list[str] = []
    last_parquet = time.monotonic()
    window = 2 * pool.size - 1  # a local pool runs a row when it is submitted: one at a time
    written: list[dict[str, Any]] = previous

    def write() -> list[dict[str, Any]]:
        """The table on disk merged with this run's rows, written back; held under the
        folder's lock so that a sweep writing the same folder loses none of its rows."""
        with _table_lock(out):
            table = _merged(csv_path, list(finished.values()), order)
            write_output(csv_path, table_csv(table), field="out")
            return table

    queue = list(reversed(todo))
    total, count = len(rows), len(done)
    try:
        while queue or pool.pending():
            while queue and pool.pending() < window and not (cancel and cancel.cancelled):
                row = queue.pop()
                problem = None if row.problem is None else problems[row.problem]
                by_ticket[pool.submit(run_row, row, problem)] = row
            if not pool.pending():
                break  # cancelled
            ticket, result, error = pool.next_done()
            row = by_ticket.pop(ticket)
            if error is not None:
                result = lost_row(row, error)
            finished[row.row_id] = result
            computed += 1
            failed += result["status"] == ERROR
            count += 1
            written = write()
            if time.monotonic() - last_parquet > PARQUET_EVERY_S:
                write_parquet(written, parquet_path)
                last_parquet = time.monotonic()
            if on_row is not None:
                on_row(result, count, total)
    finally:
        if computed or not parquet_path.exists():
            if not csv_path.exists():
                written = write()
            if not write_parquet(written, parquet_path):
                notes.append("pyarrow is not installed: wrote the CSV table only")
    mine = set(order)
    table = [r for r in written if r["row_id"] in mine] + [
        r for r in written if r["row_id"] not in mine
    ]
    return SweepReport(
        rows=table,
        computed=computed,
        skipped=sum(r.row_id in done for r in rows),
        failed=failed,
        csv=csv_path,
        parquet=parquet_path if parquet_path.exists() else None,
        notes=notes,
    )
