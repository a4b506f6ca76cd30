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
import numbers
from collections.abc import Callable, Iterable
from typing import Any, ParamSpec, TypeVar

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


def budget_keyword(function: str, budget: Any, budgets: Any) -> float | list[float] | None:
    """The budget of a public function that takes it as ``budget=`` or ``budgets=`` (one
    parameter, two spellings: ``solve``, ``audit`` and ``harden`` accept both): a number, or
    the list of a sequence (a ``range``, a generator: read once). Both given and different
    is a ``TypeError`` naming both."""
    given = _budget_value(function, "budget", budget)
    other = _budget_value(function, "budgets", budgets)
    if given is None:
        return other
    if other is not None and _listed(given) != _listed(other):
        raise TypeError(
            f"{function}() got budget={budget!r} and budgets={budgets!r}: they are the same "
            "parameter spelled two ways; give one"
        )
    return given


def one_budget_keyword(function: str, budget: Any, budgets: Any) -> float | None:
    """:func:`budget_keyword` of a function that takes one budget (``audit``'s and
    ``harden``'s attacker budget B, which answer every budget up to it): a sequence of more
    than one is a ``TypeError``."""
    given = budget_keyword(function, budget, budgets)
    if not isinstance(given, list):
        return given
    if len(given) != 1:
        raise TypeError(
            f"{function}() takes one attacker budget B (it answers every budget up to B), "
            f"got {given!r}"
        )
    return given[0]


def _budget_value(function: str, name: str, value: Any) -> float | list[float] | None:
    if value is None:
        return None
    if isinstance(value, numbers.Real) and not isinstance(value, bool):
        return float(value)
    if isinstance(value, (str, bytes)) or not isinstance(value, Iterable):
        raise TypeError(
            f"{function}() {name}= takes a number or a sequence of numbers, got {value!r}"
        )
    listed = list(value)
    if not all(isinstance(b, numbers.Real) and not isinstance(b, bool) for b in listed):
        raise TypeError(f"{function}() {name}= takes numbers, got {listed!r}")
    return [float(b) for b in listed]


def _listed(value: float | list[float]) -> list[float]:
    return value if isinstance(value, list) else [value]
