"""Test helper: check a ``--json`` document against the shipped result schema."""

from __future__ import annotations

import json
from typing import Any

from jsonschema import Draft202012Validator

from misdirect.report.json_output import result_schema

VALIDATOR = Draft202012Validator(result_schema())


def checked(text: str) -> dict[str, Any]:
    """The one JSON object of ``text`` (a command's stdout), valid under misdirect-result/1."""
    document = json.loads(text)
    errors = sorted(VALIDATOR.iter_errors(document), key=lambda e: list(e.absolute_path))
    assert not errors, "; ".join(f"{list(e.absolute_path)}: {e.message}" for e in errors[:5])
    return document
