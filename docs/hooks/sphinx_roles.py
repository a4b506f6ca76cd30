"""mkdocs hook: the docstrings' Sphinx roles (``:func:`name```, ``:class:`~a.b.Name```), read
by help() and IDEs as they are, shown on the site as plain code instead of ``:func:name``."""

from __future__ import annotations

import re
from typing import Any

# a role before a code span; "~" shows only the last component, as in Sphinx
ROLE = re.compile(r":(?:func|meth|class|mod|attr|data|exc|obj):<code>(~?)([\w.]+)</code>")


def _shown(match: re.Match[str]) -> str:
    name = match.group(2).rsplit(".", 1)[-1] if match.group(1) else match.group(2)
    return f"<code>{name}</code>"


def on_page_content(html: str, **kwargs: Any) -> str:
    return ROLE.sub(_shown, html)
