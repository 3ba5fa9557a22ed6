"""Tables as a reader of the book sees them.

``styled(df)`` renders a DataFrame the way a paper prints a table: no 0, 1, 2... index
(a meaningful index stays, as row labels), numbers to four significant digits, "—" for
a missing value, ✓ / ✗ for booleans, every row and every character (no "..."), dicts
and lists written out, the book's internal names (``ant_omni``, ``mean_frame``) as a
reader knows them (``qdnb.core.names.READER_NAMES``), and any other identifier (a
config's field, ``num_critic_steps``) in code type, as a reader would type it.  A table
fits the page's column; ``styled(df, dump=True)`` marks one that is a data dump and may
scroll sideways (the browser check refuses any other that does).  ``use_book_tables()``
makes ``styled`` the HTML of every DataFrame a notebook displays; the text form (a
terminal, a test) is pandas' own.
"""

from __future__ import annotations

import html
import numbers
from typing import Any

import numpy as np
import pandas as pd

from qdnb.core.names import IDENTIFIER, READER_NAMES, number_text

MISSING = "—"
DIGITS = 4
# a row label longer than this wraps in its cell (a short one, "PGA-ME-LS", never breaks)
LONG_LABEL = 16
LONG = ' class="long"'


def cell_text(value: Any, digits: int = DIGITS) -> str:
    """One cell as the book prints it."""
    if value is None:
        return MISSING
    if isinstance(value, (bool, np.bool_)):
        return "✓" if value else "✗"
    if isinstance(value, numbers.Integral):
        return f"{int(value):,}"  # 8,000 beside 20,000
    if isinstance(value, numbers.Real):  # NaN as MISSING, ∞ for an infinity
        return number_text(value, digits)
    if isinstance(value, dict):
        return ", ".join(f"{k}: {cell_text(v, digits)}" for k, v in value.items()) or MISSING
    if isinstance(value, (list, tuple, np.ndarray)):
        items = list(np.asarray(value).ravel()) if isinstance(value, np.ndarray) else value
        return ", ".join(cell_text(v, digits) for v in items) or MISSING
    text = str(value)
    return READER_NAMES.get(text, text) if text.strip() else MISSING


def _identifier_html(text: str) -> str:
    """``text`` escaped, its identifiers in code type."""
    out, last = [], 0
    for m in IDENTIFIER.finditer(text):
        out += [html.escape(text[last : m.start()]), f"<code>{html.escape(m.group(0))}</code>"]
        last = m.end()
    return "".join(out) + html.escape(text[last:])


def cell_html(value: Any, digits: int = DIGITS) -> str:
    """One cell's HTML: ``cell_text``, with identifiers (a dict's keys, a name the book
    has no reader's name for) in code type."""
    if isinstance(value, dict) and value:
        return ", ".join(f"{_label_html(k)}: {cell_html(v, digits)}" for k, v in value.items())
    if isinstance(value, (list, tuple)) and value:
        return ", ".join(cell_html(v, digits) for v in value)
    if isinstance(value, str):
        # Markdown's code spans (`tiny`) in code type, as the page's text shows them
        text = cell_text(value, digits)
        parts = text.split("`")
        if len(parts) % 2 == 0:  # an odd number of backticks: no spans
            return _identifier_html(text)
        return "".join(
            f"<code>{html.escape(part)}</code>" if i % 2 else _identifier_html(part)
            for i, part in enumerate(parts)
        )
    return html.escape(cell_text(value, digits))


def _has_default_index(df: pd.DataFrame) -> bool:
    index = df.index
    return (
        isinstance(index, pd.RangeIndex) and index.start == 0 and index.step == 1
    ) and index.name is None


def styled(df: pd.DataFrame, digits: int = DIGITS, dump: bool = False) -> str:
    """The HTML of ``df`` as a book table (see the module's docstring); ``dump`` marks a
    data dump, which may be wider than the column and scroll."""
    if isinstance(df, pd.Series):
        df = df.to_frame()
    show_index = not _has_default_index(df)
    head = []
    if show_index:
        head += [f"<th>{_label_html(n) if n else ''}</th>" for n in df.index.names]
    head += [f"<th>{_label_html(c)}</th>" for c in df.columns]
    rows = []
    for key, row in zip(df.index, df.itertuples(index=False, name=None)):
        cells = []
        if show_index:
            keys = key if isinstance(key, tuple) else (key,)
            cells += [f"<th{_long(k)}>{_label_html(k)}</th>" for k in keys]
        for value in row:
            text = cell_html(value, digits)
            numeric = isinstance(value, numbers.Number) and not isinstance(value, bool)
            cells.append(f'<td class="num">{text}</td>' if numeric else f"<td>{text}</td>")
        rows.append("<tr>" + "".join(cells) + "</tr>")
    kind = "qdnb-table qdnb-dump" if dump else "qdnb-table"
    return (
        f'<div class="{kind}"><table>'
        f"<thead><tr>{''.join(head)}</tr></thead>"
        f"<tbody>{''.join(rows)}</tbody></table></div>"
    )


def _long(key: Any) -> str:
    """The class of a row label a reader reads as a phrase, which may wrap."""
    return LONG if len(READER_NAMES.get(str(key), str(key))) > LONG_LABEL else ""


def _label_html(key: Any) -> str:
    if isinstance(key, tuple):
        return " / ".join(_label_html(k) for k in key)
    return _identifier_html(READER_NAMES.get(str(key), str(key)))


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


def loop_costs(runs: dict[tuple[str, str], Any], per: str = "iteration") -> pd.DataFrame:
    """What each loop of a run cost, one row per (environment, method): environment steps
    per seed, seeds, wall time (compilation included) and seconds per ``per`` of the
    compiled loop; ``runs`` maps the pair to a run with ``env_steps`` (one per seed),
    ``seconds`` and ``steady_seconds_per_iteration``."""
    return pd.DataFrame(
        {
            (READER_NAMES.get(env, env), method): {
                "env steps per seed": float(np.mean(r.env_steps)),
                "seeds": len(r.env_steps),
                "wall time (s)": round(r.seconds, 1),
                f"s per {per} (compiled loop)": round(r.steady_seconds_per_iteration, 3),
            }
            for (env, method), r in runs.items()
        }
    ).T
