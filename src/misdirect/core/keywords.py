"""Keyword typos in the public functions: one ``TypeError`` naming the bad keyword, the likely
one meant and every valid one.

Python's own message (``solve() got an unexpected keyword argument 'time_limt'``) names the
typo but not what was meant; a user of ``solve(problem, time_limt=30)`` should not need
``help(solve)`` to find the spelling.
"""

from __future__ import annotations

import difflib
import functools
import inspect
from collections.abc import Callable
from typing import ParamSpec, TypeVar

P = ParamSpec("P")
R = TypeVar("R")

_NAMED = (inspect.Parameter.POSITIONAL_OR_KEYWORD, inspect.Parameter.KEYWORD_ONLY)


def checked_keywords(function: Callable[P, R]) -> Callable[P, R]:
    """``function`` raising a helpful ``TypeError`` for an unknown keyword argument.

    The signature (and so ``help()`` and the API reference) is the function's own; the check
    is one set lookup per keyword given.
    """
    valid = [p.name for p in inspect.signature(function).parameters.values() if p.kind in _NAMED]
    accepted = frozenset(valid)

    @functools.wraps(function)
    def call(*args: P.args, **kwargs: P.kwargs) -> R:
        unknown = [name for name in kwargs if name not in accepted]
        if unknown:
            raise TypeError(unknown_keyword(function.__name__, unknown[0], valid))
        return function(*args, **kwargs)

    return call


def unknown_keyword(function: str, name: str, valid: list[str]) -> str:
    """``solve() got an unexpected keyword argument 'x' (did you mean 'y'?); valid: ...``."""
    close = difflib.get_close_matches(name, valid, n=1)
    hint = f" (did you mean {close[0]!r}?)" if close else ""
    return (
        f"{function}() got an unexpected keyword argument {name!r}{hint}; "
        f"valid keywords: {', '.join(valid)}"
    )
