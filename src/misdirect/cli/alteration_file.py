"""Alterations that travel between commands (``--alteration FILE``): the ``--json`` output of
``solve`` (one budget of its curve) or of ``evaluate``, or a small mapping
``{observation: received observation}`` in YAML or JSON, as ``solve -o FILE.yaml`` writes.

The names are read as written; the command checks them against its problem (a Storm
valuation such as ``[s=0]`` is matched as ``--alter`` matches it).
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

from misdirect.errors import ProblemError
from misdirect.io.files import parse_json, parse_yaml, read_text_file

RESULT_SCHEMA = "misdirect-result/1"  # the --json documents (misdirect.report.json_output)


def read_alteration_file(path: Path, at_budget: float | None = None) -> dict[str, str]:
    """The alteration ``path`` holds, as names: a ``solve`` document's point at
    ``at_budget`` (default: its largest budget), an ``evaluate`` document's alteration, or a
    plain mapping. Anything else is a :class:`ProblemError` naming the file and the field."""
    source = str(path)
    text = read_text_file(path, field="--alteration")
    if path.suffix.lower() == ".json":
        document = parse_json(text, source=source)
    else:
        document = parse_yaml(text, source=source)
    if not isinstance(document, dict):
        raise ProblemError(
            "expected a solve or evaluate --json document, or a mapping "
            "{observation: received observation}",
            source=source,
        )
    if "schema" in document:
        return _from_result(document, source, at_budget)
    if at_budget is not None:
        raise ProblemError(
            "is for a solve --json document; this file is one alteration",
            field="--at-budget",
        )
    return _mapping(document, source, field=None)


def _from_result(document: dict[str, Any], source: str, at_budget: float | None) -> dict[str, str]:
    if document.get("schema") != RESULT_SCHEMA:
        raise ProblemError(f"expected {RESULT_SCHEMA!r}", source=source, field="schema")
    command = document.get("command")
    if "error" in document:
        raise ProblemError("is the output of a command that failed", source=source, field="error")
    if command == "evaluate":
        if at_budget is not None:
            raise ProblemError(
                "is for a solve --json document; an evaluate document holds one alteration",
                field="--at-budget",
            )
        return _mapping(document.get("alteration"), source, field="alteration")
    if command != "solve":
        raise ProblemError(
            f"is the output of {command!r}; an alteration is read from solve's or evaluate's",
            source=source,
            field="command",
        )
    curve = document.get("curve")
    if not isinstance(curve, list) or not curve:
        raise ProblemError("expected a non-empty list of points", source=source, field="curve")
    budgets: list[float] = []
    for i, point in enumerate(curve):
        budget = point.get("budget") if isinstance(point, dict) else None
        if not isinstance(budget, (int, float)) or isinstance(budget, bool):
            raise ProblemError("expected a numeric budget", source=source, field=f"curve[{i}]")
        budgets.append(float(budget))
    if at_budget is None:
        at = max(range(len(curve)), key=lambda i: budgets[i])
    else:
        matching = [i for i, b in enumerate(budgets) if b == at_budget]  # as written: exact
        if not matching:
            listed = ", ".join(f"{b:g}" for b in budgets)
            raise ProblemError(
                f"{source} has no budget {at_budget:g} (it has {listed})", field="--at-budget"
            )
        at = matching[0]
    return _mapping(curve[at].get("alteration"), source, field=f"curve[{at}].alteration")


def _mapping(value: Any, source: str, field: str | None) -> dict[str, str]:
    if not isinstance(value, Mapping):
        raise ProblemError(
            "expected a mapping {observation: received observation}", source=source, field=field
        )
    changes: dict[str, str] = {}
    for original, received in value.items():
        where = str(original) if field is None else f"{field}.{original}"
        if not isinstance(original, str) or not isinstance(received, str):
            raise ProblemError(
                f"expected observation names, got {original!r}: {received!r}",
                source=source,
                field=where,
            )
        changes[original] = received
    return changes
