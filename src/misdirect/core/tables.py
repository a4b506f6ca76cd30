"""Results as tables: ``to_dataframe()`` on the results whose natural shape is one.

pandas is optional (``pip install pandas``): it is imported only when a table is asked for, so
the library loads without it.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any


def dataframe(rows: Sequence[dict[str, Any]], columns: Sequence[str]) -> Any:
    """A ``pandas.DataFrame`` of ``rows`` with ``columns`` in that order.

    Raises
    ------
    ImportError
        pandas is not installed; the message says how to install it.
    """
    try:
        import pandas
    except ImportError:
        raise ImportError(
            "to_dataframe() needs pandas, which is not installed: pip install pandas"
        ) from None
    return pandas.DataFrame(list(rows), columns=list(columns))


def short_float(value: float | None) -> str:
    """A value for a one-line repr: six significant digits, ``None`` as is."""
    return "None" if value is None else f"{value:.6g}"
