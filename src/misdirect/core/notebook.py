"""How results and problems show in a notebook: ``_repr_html_`` and ``_repr_markdown_``.

The objects a notebook user sees (:class:`~misdirect.core.model.Problem`, an evaluation, a
solve result and its points, an audit, a hardening) each describe themselves as a
:class:`View`: a title, a few facts, tables and notes, all plain strings. This module renders
any view, as HTML or as Markdown, and knows nothing of the objects: it sits in ``core`` so
that every layer can call it (the results of ``solvers`` and ``defence`` may not import
``report``), and the objects import it inside their ``_repr_*_`` methods only, so a program
that never shows one in a notebook never loads it.

Every string is escaped (names come from the user's files: an observation may be called
``<o&1>``). Nothing is abbreviated: an alteration is a list of ``o → o'`` changes that
wraps between changes, never inside one, and the tables are kept narrow enough for a
notebook or a documentation page (:data:`MAX_WIDTH`); a list too long to show whole says how
many it leaves out and where the rest is.
"""

from __future__ import annotations

import html
import re
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field

MAX_WIDTH = "48rem"  # a documentation page's text column; a notebook's output is wider
LISTED = 40  # names listed in a problem's view before "… and N more (where)"

# the style of every view: one <div> with no global CSS (a notebook's and mkdocs' own apply)
_TABLE = "border-collapse: collapse; margin: 0.3em 0; font-size: 0.9em; width: auto;"
_CELL = "padding: 0.15em 0.6em; vertical-align: top; border-bottom: 1px solid #ddd;"
_NUMBER = _CELL + " text-align: right; white-space: nowrap;"
_TEXT = _CELL + " text-align: left; white-space: normal; overflow-wrap: anywhere;"
_HEAD = "padding: 0.15em 0.6em; text-align: left; border-bottom: 1px solid #999;"
_CHANGE = "white-space: nowrap;"  # one ``o → o'`` never breaks; the list wraps between them

# Markdown's own characters, escaped with a backslash in a table cell or a line
_MARKDOWN = re.compile(r"([\\`*_\[\]|~])")


@dataclass(frozen=True)
class Cell:
    """A table cell: ``text`` shown as is (escaped), or ``parts`` shown as a list that wraps
    between its items (an alteration's changes, a protection's sensors)."""

    text: str = ""
    parts: tuple[str, ...] | None = None
    number: bool = False  # right-aligned, never wrapped


@dataclass(frozen=True)
class Table:
    """Rows of cells under a header; ``caption`` above it, if any."""

    header: Sequence[str]
    rows: Sequence[Sequence[Cell]]
    caption: str = ""


@dataclass(frozen=True)
class View:
    """What an object shows: a title, ``(label, value)`` facts, tables, then notes."""

    title: str
    facts: Sequence[tuple[str, Cell]] = ()
    tables: Sequence[Table] = ()
    notes: Sequence[str] = field(default_factory=tuple)

    def html(self) -> str:
        return render_html(self)

    def markdown(self) -> str:
        return render_markdown(self)


# -- building cells --------------------------------------------------------------------------


class Shown:
    """What a notebook shows of an object, by its :class:`View` (``_view``): Jupyter asks for
    ``_repr_html_``, renderers without HTML for ``_repr_markdown_``. A base of every result
    and of the problem."""

    def _view(self) -> View:
        raise NotImplementedError

    def _repr_html_(self) -> str:
        return self._view().html()

    def _repr_markdown_(self) -> str:
        return self._view().markdown()


def number(value: float | None, digits: int = 6) -> Cell:
    """A value to ``digits`` decimals (as the CLI prints it); ``None`` as an em dash."""
    return Cell("—" if value is None else f"{value:.{digits}f}", number=True)


def small(value: float | None) -> Cell:
    """A gap or an error bound: 0 as ``0``, else three significant digits (``7.94e-01``)."""
    if value is None:
        return Cell("—", number=True)
    return Cell("0" if value == 0 else f"{value:.2e}", number=True)


def amount(value: float | None) -> Cell:
    """A budget or a cost: as short as it is (``2``, ``2.5``)."""
    return Cell("—" if value is None else f"{value:g}", number=True)


def count(value: int) -> Cell:
    return Cell(f"{value:,}", number=True)


def text(value: object) -> Cell:
    return Cell(str(value))


def changes(alteration: Mapping[str, str]) -> Cell:
    """An alteration as its changes, ``o → o'`` each, or ``none``."""
    listed = tuple(f"{o} → {t}" for o, t in alteration.items())
    return Cell(parts=listed) if listed else Cell("none")


def names(items: Iterable[str], *, empty: str = "none", where: str = "") -> Cell:
    """Names as a list that wraps; past :data:`LISTED`, the first ones and how many more
    there are (and ``where`` to find them all), never cut silently."""
    listed = list(items)
    if not listed:
        return Cell(empty)
    if len(listed) > LISTED:
        rest = len(listed) - LISTED
        more = f"… and {rest:,} more" + (f" ({where})" if where else "")
        return Cell(parts=(*listed[:LISTED], more))
    return Cell(parts=tuple(listed))


# -- HTML ------------------------------------------------------------------------------------


def _html_cell(cell: Cell) -> str:
    if cell.parts is None:
        return html.escape(cell.text)
    spans = [f'<span style="{_CHANGE}">{html.escape(part)}</span>' for part in cell.parts]
    return ", ".join(spans)


def _html_table(table: Table) -> str:
    head = "".join(f'<th style="{_HEAD}">{html.escape(h)}</th>' for h in table.header)
    body = "".join(
        "<tr>"
        + "".join(
            f'<td style="{_NUMBER if cell.number else _TEXT}">{_html_cell(cell)}</td>'
            for cell in row
        )
        + "</tr>"
        for row in table.rows
    )
    caption = (
        f'<caption style="text-align: left; font-weight: bold;">{html.escape(table.caption)}'
        "</caption>"
        if table.caption
        else ""
    )
    return (
        f'<table style="{_TABLE}">{caption}<thead><tr>{head}</tr></thead>'
        f"<tbody>{body}</tbody></table>"
    )


def render_html(view: View) -> str:
    """The view as one ``<div>``, every string escaped, at most :data:`MAX_WIDTH` wide."""
    parts = [
        f'<div class="misdirect-view" style="max-width: {MAX_WIDTH};">',
        f"<strong>{html.escape(view.title)}</strong>",
    ]
    if view.facts:
        rows = "".join(
            f'<tr><th style="{_CELL} text-align: left; font-weight: normal; '
            f'white-space: nowrap;">{html.escape(label)}</th>'
            f'<td style="{_TEXT}">{_html_cell(value)}</td></tr>'
            for label, value in view.facts
        )
        parts.append(f'<table style="{_TABLE}"><tbody>{rows}</tbody></table>')
    parts += [_html_table(table) for table in view.tables]
    if view.notes:
        items = "".join(f"<li>{html.escape(note)}</li>" for note in view.notes)
        parts.append(f'<ul style="margin: 0.3em 0;">{items}</ul>')
    parts.append("</div>")
    return "".join(parts)


# -- Markdown --------------------------------------------------------------------------------


def escape_markdown(value: str) -> str:
    """``value`` as literal text in Markdown (a line, a table cell): Markdown's own
    characters behind a backslash, then ``&``, ``<`` and ``>`` as entities (Markdown passes
    HTML through); a line break as a space."""
    marked = _MARKDOWN.sub(r"\\\1", value.replace("\n", " "))
    return html.escape(marked, quote=False)


def _markdown_cell(cell: Cell) -> str:
    if cell.parts is None:
        return escape_markdown(cell.text)
    return ", ".join(escape_markdown(part) for part in cell.parts)


def render_markdown(view: View) -> str:
    """The view as Markdown: the title in bold, the facts as a list, pipe tables, notes."""
    lines = [f"**{escape_markdown(view.title)}**", ""]
    lines += [f"- {escape_markdown(label)}: {_markdown_cell(value)}" for label, value in view.facts]
    for table in view.tables:
        lines.append("")
        if table.caption:
            lines += [f"*{escape_markdown(table.caption)}*", ""]
        lines.append("| " + " | ".join(escape_markdown(h) for h in table.header) + " |")
        lines.append(
            "|" + "|".join("--:" if c.number else ":--" for c in table.rows[0]) + "|"
            if table.rows
            else "|" + "|".join(":--" for _ in table.header) + "|"
        )
        lines += ["| " + " | ".join(_markdown_cell(c) for c in row) + " |" for row in table.rows]
    if view.notes:
        lines.append("")
        lines += [f"- {escape_markdown(note)}" for note in view.notes]
    return "\n".join(lines) + "\n"
