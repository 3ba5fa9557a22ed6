"""Tables as a reader of the book sees them.

``styled(df)`` renders a DataFrame the way a paper prints a table: no 0, 1, 2... index
(a meaningful index stays, as row labels), numbers to four significant digits, "—" for
a missing value, ✓ / ✗ for booleans, every row and every character (no "..."), dicts
and lists written out, the book's internal names (``ant_omni``, ``mean_frame``) as a
reader knows them (``qdnb.core.names.READER_NAMES``).  ``use_book_tables()`` makes it
the HTML of every DataFrame a notebook displays; the text form (a terminal, a test) is
pandas' own.
"""

from __future__ import annotations

import html
import math
import numbers
from typing import Any

import numpy as np
import pandas as pd

from qdnb.core.names import READER_NAMES

MISSING = "—"
DIGITS = 4


def cell_text(value: Any, digits: int = DIGITS) -> str:
    """One cell as the book prints it."""
    if value is None:
        return MISSING
    if isinstance(value, (bool, np.bool_)):
        return "✓" if value else "✗"
    if isinstance(value, numbers.Integral):
        return f"{int(value):,}" if abs(int(value)) >= 10_000 else str(int(value))
    if isinstance(value, numbers.Real):
        x = float(value)
        if math.isnan(x):
            return MISSING
        if math.isinf(x):
            return "∞" if x > 0 else "−∞"
        text = f"{x:.{digits}g}"
        if "e" in text:  # 1.234e+07 -> 1.234e7
            mantissa, exponent = text.split("e")
            text = f"{mantissa}e{int(exponent)}"
        return text
    if isinstance(value, dict):
        return ", ".join(f"{k}: {cell_text(v, digits)}" for k, v in value.items()) or MISSING
    if isinstance(value, (list, tuple, np.ndarray)):
        items = list(np.asarray(value).ravel()) if isinstance(value, np.ndarray) else value
        return ", ".join(cell_text(v, digits) for v in items) or MISSING
    text = str(value)
    return READER_NAMES.get(text, text) if text.strip() else MISSING


def _has_default_index(df: pd.DataFrame) -> bool:
    index = df.index
    return (
        isinstance(index, pd.RangeIndex) and index.start == 0 and index.step == 1
    ) and index.name is None


def styled(df: pd.DataFrame, digits: int = DIGITS) -> str:
    """The HTML of ``df`` as a book table (see the module's docstring)."""
    if isinstance(df, pd.Series):
        df = df.to_frame()
    show_index = not _has_default_index(df)
    head = []
    if show_index:
        head += [f"<th>{html.escape(_label(n) if n else '')}</th>" for n in df.index.names]
    head += [f"<th>{html.escape(_label(c))}</th>" for c in df.columns]
    rows = []
    for key, row in zip(df.index, df.itertuples(index=False, name=None)):
        cells = []
        if show_index:
            keys = key if isinstance(key, tuple) else (key,)
            cells += [f"<th>{html.escape(_label(k))}</th>" for k in keys]
        for value in row:
            text = html.escape(cell_text(value, digits))
            numeric = isinstance(value, numbers.Number) and not isinstance(value, bool)
            cells.append(f'<td class="num">{text}</td>' if numeric else f"<td>{text}</td>")
        rows.append("<tr>" + "".join(cells) + "</tr>")
    return (
        '<div class="qdnb-table"><table>'
        f"<thead><tr>{''.join(head)}</tr></thead>"
        f"<tbody>{''.join(rows)}</tbody></table></div>"
    )


def _label(key: Any) -> str:
    if isinstance(key, tuple):
        return " / ".join(_label(k) for k in key)
    return READER_NAMES.get(str(key), str(key))


def use_book_tables() -> None:
    """Every DataFrame (and Series) a notebook displays renders as ``styled``; nothing
    outside IPython."""
    try:
        from IPython import get_ipython
    except ImportError:  # pragma: no cover - IPython ships with the notebooks' kernel
        return
    shell = get_ipython()
    if shell is None:
        return
    formatter = shell.display_formatter.formatters["text/html"]
    formatter.for_type(pd.DataFrame, styled)
    formatter.for_type(pd.Series, styled)
