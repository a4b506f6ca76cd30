"""``--help`` as the source writes it: typer renders help text as rich markup, which ate
``misdirect[cluster]`` and ``misdirect[storm]`` (a tag to rich), and showed every flag with a
value type (``--json <bool>``, as if ``--json true`` were wanted). The command and group
classes here show flags as flags; :func:`literal_help` escapes a command's help texts once."""

from __future__ import annotations

import inspect
import typing
from collections.abc import Callable
from typing import Any

from rich.markup import escape
from typer.core import TyperCommand, TyperGroup, TyperOption
from typer.models import ParameterInfo

_ESCAPED: set[int] = set()  # the ParameterInfo objects escaped already (shared by commands)


class _FlagOption(TyperOption):
    """An on/off option (``--json``, ``--quick/--full``, ``--help``): no value type shown."""

    def display_type_rich(self, ctx: Any) -> str | None:
        return None if self.is_flag or self.count else super().display_type_rich(ctx)


def _flags_as_flags(params: list[Any]) -> list[Any]:
    for param in params:
        if type(param) is TyperOption and (param.is_flag or param.count):
            param.__class__ = _FlagOption  # the same option; only its help shows no type
    return params


class Command(TyperCommand):
    """A command whose flags are shown as flags in ``--help``."""

    def get_params(self, ctx: Any) -> list[Any]:
        return _flags_as_flags(super().get_params(ctx))


class Group(TyperGroup):
    """A group whose flags (``--version``, ``--help``) are shown as flags in ``--help``."""

    def get_params(self, ctx: Any) -> list[Any]:
        return _flags_as_flags(super().get_params(ctx))


def literal_help(command: Callable[..., Any]) -> str | None:
    """The help of ``command`` (its docstring) with rich markup escaped, and the help of each
    of its options and arguments escaped in place (once: options are shared by commands), so
    that ``--help`` shows ``[cluster]`` as it is written."""
    for annotation in typing.get_type_hints(command, include_extras=True).values():
        for info in getattr(annotation, "__metadata__", ()):
            if isinstance(info, ParameterInfo) and info.help and id(info) not in _ESCAPED:
                info.help = escape(info.help)
                _ESCAPED.add(id(info))
    doc = inspect.getdoc(command)
    return None if doc is None else escape(doc)


def unescaped(text: str) -> str:
    """Help text as written, without the escapes :func:`literal_help` added (for the
    generated CLI reference, which is Markdown, not rich markup)."""
    return text.replace("\\[", "[")
