"""The CLI reference (docs/cli.md), generated from the typer app: every command's help text and
options, read off the click command tree, so the page cannot drift from the commands.

``python docs/hooks/cli_reference.py`` rewrites docs/cli.md (committed, so it reads on GitHub
too); as an mkdocs hook it regenerates the page at every build, and
tests/test_docs_examples.py checks that the committed page is current.
"""

from __future__ import annotations

import inspect
import sys
from pathlib import Path
from typing import Any

import typer

PAGE = Path(__file__).resolve().parents[1] / "cli.md"

HEADER = """# Command-line reference

Generated from the commands themselves (`docs/hooks/cli_reference.py`); do not edit by hand.
`misdirect COMMAND --help` prints the same. Every command that reports takes `--json` and then
prints one JSON object on standard output; bad input exits with code 2 and one line naming the
file (or option), the field and the reason.
"""


def unescaped(text: str) -> str:
    from misdirect.cli.helptext import unescaped

    return unescaped(text)


def _command_tree() -> Any:
    from misdirect.cli import app

    return typer.main.get_command(app)


def _is_group(command: Any) -> bool:
    # typer vendors its own click: duck typing, not isinstance against the click package
    return hasattr(command, "commands")


def _walk(command: Any, path: list[str]) -> list[tuple[list[str], Any]]:
    found = [(path, command)]
    if _is_group(command):
        for name in sorted(command.commands):
            sub = command.commands[name]
            if not sub.hidden:
                found += _walk(sub, [*path, name])
    return found


def _cell(text: Any) -> str:
    return " ".join(unescaped(str(text)).split()).replace("|", "\\|")


def _option_rows(command: Any, context: Any) -> list[str]:
    rows = []
    for param in command.get_params(context):
        if getattr(param, "hidden", False):
            continue
        record = param.get_help_record(context)
        if record is None:  # an argument
            names = f"`{param.human_readable_name}`"
            help_text = getattr(param, "help", None) or ""
        else:
            names = ", ".join(f"`{part.strip()}`" for part in record[0].split(", "))
            help_text = record[1]
        rows.append(f"| {names.replace('|', '/')} | {_cell(help_text)} |")
    return rows


def markdown() -> str:
    """The whole page."""
    root = _command_tree()
    parts = [HEADER]
    for path, command in _walk(root, ["misdirect"]):
        name = " ".join(path)
        with command.context_class(command, info_name=name) as context:
            usage = command.get_usage(context).replace("Usage: ", "")
            level = "##" if len(path) <= 2 else "###"
            parts.append(f"{level} `{name}`\n")
            help_text = unescaped(inspect.cleandoc(command.help or ""))
            if help_text:
                parts.append(help_text.replace("\b\n", "") + "\n")
            parts.append(f"```\n{usage}\n```\n")
            rows = _option_rows(command, context)
            if rows and not _is_group(command):
                parts.append("| option | meaning |\n|---|---|\n" + "\n".join(rows) + "\n")
            if _is_group(command):
                listed = [f"`{n}`" for n in sorted(command.commands)]
                parts.append("Commands: " + ", ".join(listed) + ".\n")
    return "\n".join(parts)


def on_files(files: Any, config: Any) -> Any:
    """mkdocs hook: the page as built is always the one generated now."""
    from mkdocs.structure.files import File

    page = files.get_file_from_path("cli.md")
    if page is not None:
        files.remove(page)
    files.append(File.generated(config, "cli.md", content=markdown()))
    return files


if __name__ == "__main__":
    PAGE.write_text(markdown(), encoding="utf-8")
    sys.stdout.write(f"wrote {PAGE}\n")
