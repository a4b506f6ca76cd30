"""The one place that turns results into the ``--json`` output of every command.

Every document follows one versioned JSON Schema, shipped with the package
(``misdirect/schema/misdirect-result-1.json``, described in docs/json-schema.md): it names
itself (``"schema": "misdirect-result/1"``) and its ``command``, and one concept has one name
whichever command prints it (``value``, ``alteration``, ``upper_bound``, ``status``,
``objective``, ``time_s``, ``written``, ``warnings``, ``notes``, ``outcomes``). The library's
result types write their own fields in these names (``to_dict``), so the mapping lives there
once; a document here adds the schema, the command and the files written.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterable, Sequence
from dataclasses import replace
from functools import cache
from importlib import resources
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from misdirect.core.evaluate import Evaluation
    from misdirect.core.model import Problem
    from misdirect.core.simulate import Simulation
    from misdirect.defence.results import AuditResult, HardenResult
    from misdirect.io.exact_model import ExactValue
    from misdirect.solvers.run import SolveResult

SCHEMA = "misdirect-result/1"
SCHEMA_FILE = "misdirect-result-1.json"


@cache
def result_schema() -> dict[str, Any]:
    """The JSON Schema every ``--json`` document follows (read from the package data)."""
    text = resources.files("misdirect").joinpath("schema", SCHEMA_FILE).read_text("utf-8")
    schema: dict[str, Any] = json.loads(text)
    return schema


def document(
    command: str,
    *,
    written: Iterable[str | Path] = (),
    warnings: Iterable[str] = (),
    notes: Iterable[str] = (),
    **fields: Any,
) -> dict[str, Any]:
    """A document of ``command``: the schema and command first, the fields, then the written
    files, warnings and notes (always lists, empty when there are none)."""
    return {
        "schema": SCHEMA,
        "command": command,
        **fields,
        "written": [str(path) for path in written],
        "warnings": list(warnings),
        "notes": list(notes),
    }


def error_document(command: str | None, message: str, **context: Any) -> dict[str, Any]:
    """The document of a command that failed, in one shape whatever failed: the ``message``,
    the ``field`` it names (an option, or a place in a file) and the ``source`` (the file),
    each null when there is none, and the input's ``problems`` when it has several."""
    shown = {k: v for k, v in context.items() if v and k not in ("field", "source")}
    located = {"field": context.get("field") or None, "source": context.get("source") or None}
    return {
        "schema": SCHEMA,
        "command": command,
        "error": {"message": message, **located, **shown},
    }


# -- solve --------------------------------------------------------------------------------------


def solve(
    result: SolveResult,
    *,
    notes: Iterable[str] = (),
    exact: Sequence[ExactValue | None] | None = None,
) -> dict[str, Any]:
    """``solve --json``: the result's own fields (:meth:`SolveResult.to_dict`), ``notes``
    added to its notes; with ``exact`` (one per curve point, ``--exact``) each point and the
    answer carry their value on the model as written."""
    fields = result.to_dict()
    fields["notes"] = [*fields["notes"], *notes]
    if exact is not None:
        for point, value in zip(fields["curve"], exact, strict=True):
            if value is not None:
                point["exact"] = value.to_dict()
        if exact[-1] is not None:
            fields["exact"] = exact[-1].to_dict()
    return document("solve", **fields)


# -- evaluate and simulate: outcomes ------------------------------------------------------------


def outcome(
    kind: str,
    state: str | None,
    probability: float,
    *,
    runs: int | None = None,
    interval: tuple[float, float] | None = None,
) -> dict[str, Any]:
    """Where runs end: ``kind`` is decoy, goal (absorbing, not a decoy), trapped (never
    absorbed) or unfinished (simulate: out of steps); ``state`` names the state, or is null
    for a whole kind. ``probability`` is exact (evaluate) or the observed frequency
    (simulate, which adds ``runs`` and the 95 % interval)."""
    shown: dict[str, Any] = {"kind": kind, "state": state, "probability": probability}
    if runs is not None:
        shown["runs"] = runs
    if interval is not None:
        shown["interval_95"] = list(interval)
    return shown


def evaluation(
    result: Evaluation, baseline: float, exact: ExactValue | None = None
) -> dict[str, Any]:
    """``evaluate --json``: the exact value of one alteration and where runs end
    (:meth:`Evaluation.to_dict`), with the value of no alteration beside it, and with
    ``exact`` (``--exact``) its value on the model as written."""
    fields = replace(result, baseline_value=baseline).to_dict()
    if exact is not None:
        fields["exact"] = exact.to_dict()
    return document("evaluate", **fields)


def simulation(
    problem: Problem,
    alteration: dict[str, str],
    result: Simulation,
    *,
    exact: float,
    seed: int,
    max_steps: int,
    time_s: float,
    written: Iterable[str | Path] = (),
) -> dict[str, Any]:
    """``simulate --json``: per state and per kind, how many runs ended there, the frequency
    and its 95 % interval, with the exact decoy probability (``value``) beside them."""
    from misdirect.core.simulate import wilson_interval

    runs = result.runs

    def counted(kind: str, state: str | None, hits: int) -> dict[str, Any]:
        return outcome(kind, state, hits / runs, runs=hits, interval=wilson_interval(hits, runs))

    ends = [counted("decoy", s, n) for s, n in result.decoys.items()]
    ends += [counted("goal", s, n) for s, n in result.absorbed.items()]
    totals = {
        "decoy": counted("decoy", None, result.decoy_hits),
        "goal": counted("goal", None, sum(result.absorbed.values())),
        "trapped": counted("trapped", None, result.trapped),
        "unfinished": counted("unfinished", None, result.unfinished),
    }
    monitored: dict[str, Any] = {}
    if result.alarm_state is not None:  # a monitored problem: the alarm is a kind of its own
        ends.append(counted("alarm", result.alarm_state, result.alarms))
        totals["alarm"] = counted("alarm", None, result.alarms)
        caught = result.alarm_mean_step
        monitored["alarm_mean_step"] = None if math.isnan(caught) else caught
    low, high = totals["decoy"]["interval_95"]
    return document(
        "simulate",
        problem=problem.name,
        objective="probability",  # a run hits a decoy or not: weights are not simulated
        alteration=alteration,
        runs=runs,
        seed=seed,
        max_steps=max_steps,
        value=exact,
        outcomes=ends,
        totals=totals,
        exact_within_interval=bool(low <= exact <= high),
        mean_steps_finished=result.mean_steps,
        **monitored,
        time_s=time_s,
        written=written,
        warnings=problem.warnings,
        notes=problem.notes,
    )


# -- the defender's commands --------------------------------------------------------------------


def audit(result: AuditResult, *, written: Iterable[str | Path] = ()) -> dict[str, Any]:
    """``audit --json``: the optimum at B, its curve, each sensor, the online attacker
    (:meth:`AuditResult.to_dict`)."""
    return document("audit", **result.to_dict(), written=written)


def harden(result: HardenResult, *, written: Iterable[str | Path] = ()) -> dict[str, Any]:
    """``harden --json``: the protection, the attacker's best reply under it (``value``,
    ``alteration``, as in solve), the trade-off curve and the search's counters
    (:meth:`HardenResult.to_dict`)."""
    return document("harden", **result.to_dict(), written=written)


# -- commands that write files ------------------------------------------------------------------


def written_files(command: str, paths: Iterable[str | Path], **fields: Any) -> dict[str, Any]:
    """A command whose answer is the files it wrote (scenario, show, export-milp, ...)."""
    return document(command, **fields, written=paths)


def text_output(command: str, output: Path | None, text: str, **fields: Any) -> dict[str, Any]:
    """A command that writes one text: the file, or, without one, the text as ``content``."""
    if output is not None:
        return document(command, **fields, written=[output])
    return document(command, **fields, content=text)
