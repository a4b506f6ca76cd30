"""Every code example of the README and the docs runs, and prints what it shows.

* ```python blocks are executed (in a scratch folder holding a copy of examples/); a line
  ``print(...)  # text``, or a print followed by comment lines, states the printed lines.
  ```py blocks are shown, not run (they need what a test machine lacks: a SLURM cluster).
* ```console blocks: each ``$ misdirect ...`` line is run as a command (in the same scratch
  folder, so a later command reads what an earlier one wrote); the lines shown under it must
  appear in its output in that order, each within one line (table borders and runs of spaces
  ignored). A shown line ``...`` skips any number of lines; ``...`` inside a line skips text.
* The docstrings' examples of the public API run as doctests.
* The generated CLI reference (docs/cli.md) is current.

Expected values come from the documents, which state hand-checked numbers (the trap example:
0.1 + 0.6 · 0.5 = 0.4) and the paper's published ones (0.720, 0.864 on its grid).
"""

from __future__ import annotations

import contextlib
import doctest
import importlib
import io
import os
import re
import shlex
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCUMENTS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
FENCE = re.compile(r"^```(\w+)[^\n]*\n(.*?)^```", re.M | re.S)
BORDERS = re.compile(r"[│┃┏┓┗┛┡┩┣┫┳┻╇╋━─└┘┌┐├┤┬┴┼]")
DOCTEST_MODULES = [
    "misdirect.core.model",
    "misdirect.core.evaluate",
    "misdirect.core.simulate",
    "misdirect.solvers.run",
    "misdirect.defence.auditing",
    "misdirect.defence.hardening",
    "misdirect.io.problem_file",
]


@dataclass(frozen=True)
class Block:
    document: Path
    language: str
    text: str
    line: int

    @property
    def name(self) -> str:
        return f"{self.document.relative_to(ROOT)}:{self.line}"


def _blocks(language: str) -> list[Block]:
    found = []
    for document in DOCUMENTS:
        text = document.read_text(encoding="utf-8")
        for match in FENCE.finditer(text):
            if match.group(1) == language:
                line = text.count("\n", 0, match.start()) + 1
                found.append(Block(document, language, match.group(2), line))
    return found


def _by_document(language: str) -> list[list[Block]]:
    grouped: dict[Path, list[Block]] = {}
    for block in _blocks(language):
        grouped.setdefault(block.document, []).append(block)
    return list(grouped.values())


@pytest.fixture
def scratch(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """A folder with a copy of examples/, as the documents' relative paths expect."""
    shutil.copytree(ROOT / "examples", tmp_path / "examples")
    monkeypatch.chdir(tmp_path)
    return tmp_path


def _normal(line: str) -> str:
    return " ".join(BORDERS.sub(" ", line).split())


def _shown_prints(code: str) -> list[str]:
    """The lines the block says its prints print: inline comments of print lines, or the
    comment lines right after a print without one."""
    expected: list[str] = []
    lines = code.splitlines()
    for i, line in enumerate(lines):
        if not line.lstrip().startswith("print(") and not line.startswith("    print("):
            continue
        if "  # " in line:
            expected.append(line.split("  # ", 1)[1])
            continue
        for follow in lines[i + 1 :]:
            if not follow.startswith("# "):
                break
            expected.append(follow[2:])
    return expected


PYTHON_BLOCKS = _blocks("python")


def test_documents_have_examples() -> None:
    """The collection itself: the README and the tutorial do have both kinds of block."""
    named = {block.document.name for block in PYTHON_BLOCKS}
    assert {"README.md", "tutorial.md"} <= named
    assert {"README.md", "tutorial.md"} <= {block.document.name for block in _blocks("console")}


@pytest.mark.parametrize("block", PYTHON_BLOCKS, ids=lambda block: block.name)
def test_python_example(block: Block, scratch: Path) -> None:
    output = io.StringIO()
    with contextlib.redirect_stdout(output):
        exec(compile(block.text, block.name, "exec"), {"__name__": "__doc_example__"})
    printed = output.getvalue().splitlines()
    expected = _shown_prints(block.text)
    assert printed == expected, f"{block.name}: printed {printed}, the document shows {expected}"


def _commands(block: Block) -> list[tuple[str, list[str]]]:
    """(command line, lines shown under it) of a console block."""
    found: list[tuple[str, list[str]]] = []
    for line in block.text.splitlines():
        if line.startswith("$ "):
            found.append((line[2:], []))
        elif found:
            found[-1][1].append(line)
        else:
            raise AssertionError(f"{block.name}: output before any command: {line!r}")
    return found


def _matches(shown: str, actual: str) -> bool:
    position = 0
    for part in (_normal(piece) for piece in shown.split("...")):
        found = actual.find(part, position)
        if found < 0:
            return False
        position = found + len(part)
    return True


def check_output(name: str, shown: list[str], output: str) -> None:
    """Every shown line in ``output``, in order, each within one line."""
    actual = [_normal(line) for line in output.splitlines()]
    at = 0
    for line in shown:
        if line.strip() in ("", "..."):
            continue
        while at < len(actual) and not _matches(line, actual[at]):
            at += 1
        assert at < len(actual), f"{name}: {line.strip()!r} not in the output:\n{output}"
        at += 1


SITE_COLUMNS = 100  # what docs/stylesheets/extra.css fits in the site's text column


def test_shown_output_fits_the_site_width() -> None:
    """Every output line a console example shows fits the documentation site's column
    (issue 53: the solve table scrolled sideways, its status cut to "optim…")."""
    wide = [
        f"{block.name}: {len(line)} columns: {line}"
        for block in _blocks("console")
        for _, shown in _commands(block)
        for line in shown
        if len(line) > SITE_COLUMNS
    ]
    assert wide == []
    config = (ROOT / "mkdocs.yml").read_text(encoding="utf-8")
    assert "stylesheets/extra.css" in config
    assert "max-width" in (ROOT / "docs" / "stylesheets" / "extra.css").read_text()


def test_check_output_can_fail() -> None:
    """The comparison rejects a wrong number and a wrong order (it is no rubber stamp)."""
    output = "│ 1 │ 0.719924 │ o1 → o2 │\n│ 2 │ 0.860130 │ o1 → o2, o2 → o0 │\n"
    check_output("t", ["...", "│ 1 │ 0.719924 │ ...", "│ 2 │ 0.860130 │ ..."], output)
    with pytest.raises(AssertionError):
        check_output("t", ["│ 1 │ 0.719925 │"], output)
    with pytest.raises(AssertionError):
        check_output("t", ["│ 2 │ 0.860130 │", "│ 1 │ 0.719924 │"], output)


@pytest.mark.parametrize(
    "blocks", _by_document("console"), ids=lambda blocks: blocks[0].document.name
)
def test_console_examples(blocks: list[Block], scratch: Path) -> None:
    """The commands of one document, in order, in one scratch folder."""
    environment = {
        **os.environ,
        "COLUMNS": "120",
        "NO_COLOR": "1",
        "TERM": "dumb",
        "PYTHONPATH": os.pathsep.join([str(ROOT / "src"), os.environ.get("PYTHONPATH", "")]),
    }
    for block in blocks:
        for command, shown in _commands(block):
            words = shlex.split(command)
            assert words[0] == "misdirect", f"{block.name}: not a misdirect command: {command}"
            if words[1:3] == ["controller", "synthesize"]:
                pytest.importorskip("paynt")
            run = [sys.executable, "-c", "from misdirect.cli import main; main()", *words[1:]]
            done = subprocess.run(
                run, capture_output=True, text=True, env=environment, timeout=300, check=False
            )
            assert done.returncode == 0, f"{block.name}: {command}\n{done.stdout}{done.stderr}"
            check_output(f"{block.name}: {command}", shown, done.stdout + done.stderr)


@pytest.mark.parametrize("module", DOCTEST_MODULES)
def test_docstring_examples(module: str, scratch: Path) -> None:
    shutil.copytree(ROOT / "examples", scratch / "examples", dirs_exist_ok=True)
    flags = doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE
    result = doctest.testmod(importlib.import_module(module), optionflags=flags, verbose=False)
    assert result.failed == 0
    assert result.attempted > 0


def test_cli_reference_is_current() -> None:
    """docs/cli.md is what the generator writes from the commands as they are now."""
    sys.path.insert(0, str(ROOT / "docs" / "hooks"))
    try:
        generator = importlib.import_module("cli_reference")
    finally:
        sys.path.remove(str(ROOT / "docs" / "hooks"))
    committed = (ROOT / "docs" / "cli.md").read_text(encoding="utf-8")
    assert committed == generator.markdown(), "run: python docs/hooks/cli_reference.py"
