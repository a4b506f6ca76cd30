"""Fuzzing the CLI with mutated example files (issue 15).

Whatever the mutation, ``misdirect evaluate`` and ``solve`` either answer (exit 0, a valid
JSON answer) or refuse with exactly one line naming the file (exit 2). An exit code 1 is an
internal error: a bug this test exists to find. Derandomised, so CI runs the same few hundred
cases every time."""

from __future__ import annotations

import json
import math
import tempfile
from pathlib import Path

from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from typer.testing import CliRunner

from misdirect.cli import app

runner = CliRunner()
EXAMPLES = sorted((Path(__file__).parent.parent / "examples").glob("*.yaml"))
TEXTS = {path.name: path.read_text(encoding="utf-8") for path in EXAMPLES}

# fragments a fuzzer found useful against YAML, numbers and names
NASTY = [
    "\n",
    "\x00",
    "\x1b[31m",
    "\u2028",
    "\t",
    "[",
    "]",
    "{",
    "}",
    ":",
    "- ",
    "&a ",
    "*a",
    "<<: ",
    "!!python/object:os.system ",
    "!!binary ",
    '"',
    "'",
    "#",
    "1e308",
    "-1",
    ".nan",
    ".inf",
    "0.5",
    "²",
    "yes",
    "~",
    "=",
    "budget: 5\n",
    "  ",
]


@st.composite
def mutated(draw) -> tuple[str, str]:
    """(example name, its text after one to four random edits)."""
    name = draw(st.sampled_from(sorted(TEXTS)))
    text = TEXTS[name]
    for _ in range(draw(st.integers(1, 4))):
        lines = text.split("\n")
        kind = draw(st.sampled_from(["insert", "delete", "replace", "line", "duplicate", "cut"]))
        at = draw(st.integers(0, max(len(text) - 1, 0)))
        if kind == "insert":
            fragment = draw(st.sampled_from(NASTY) | st.text(max_size=4))
            text = text[:at] + fragment + text[at:]
        elif kind == "delete":
            text = text[:at] + text[at + draw(st.integers(1, 8)) :]
        elif kind == "replace":
            text = text[:at] + draw(st.sampled_from(NASTY)) + text[at + 1 :]
        elif kind == "line" and lines:
            del lines[draw(st.integers(0, len(lines) - 1))]
            text = "\n".join(lines)
        elif kind == "duplicate" and lines:
            i = draw(st.integers(0, len(lines) - 1))
            lines.insert(i, lines[i])
            text = "\n".join(lines)
        else:
            text = text[:at]
    return name, text


def check_contract(result, path: Path) -> dict | None:
    """Exit 0 with one JSON object, or exit 2 with one line per problem (every schema problem
    of the file at once, up to 20 and a count), each naming the file or an option."""
    assert "Traceback" not in result.output, result.output
    if result.exit_code == 0:
        payload = json.loads(result.stdout)
        probability = payload["value"]
        assert math.isfinite(probability) and -1e-9 <= probability <= 1 + 1e-9, payload
        return payload
    assert result.exit_code == 2, (result.exit_code, result.output)
    message = result.stderr
    lines = message.splitlines()
    assert message.endswith("\n") and 1 <= len(lines) <= 21, repr(message)
    assert all(line.startswith("error: ") for line in lines), repr(message)
    assert "internal error" not in message
    for line in lines[:20]:
        assert str(path) in line or "--alter" in line, message
    return None


FUZZ = settings(
    max_examples=250,
    deadline=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
    database=None,
)


@FUZZ
@given(mutated())
def test_mutated_examples_evaluate_or_fail_in_one_line(case):
    name, text = case
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / name
        path.write_text(text, encoding="utf-8")
        check_contract(runner.invoke(app, ["evaluate", str(path), "--json"]), path)


@settings(FUZZ, max_examples=80)
@given(mutated())
def test_mutated_examples_solve_or_fail_in_one_line(case):
    name, text = case
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / name
        path.write_text(text, encoding="utf-8")
        args = ["solve", str(path), "--json", "--method", "exhaustive", "--time-limit", "20"]
        payload = check_contract(runner.invoke(app, args), path)
        if payload is not None:
            # exact: the cost is the float nearest the exact sum of the costs as written, which
            # fits the budget as written (core.tolerance.CostScale), and rounding keeps order
            assert payload["cost"] <= payload["budget"], payload
