"""The thesis's reported numbers, transcribed from its text into ``data/thesis``.

Tables 3.3, 3.4, 4.4, 4.5 and 5.1, one tidy CSV each.  Table 4.4 keeps the
numbers as printed with ``printed_scale`` (the Halfcheetah-Uni columns are
printed multiplied by 10^2): the real value is ``printed / printed_scale``.
"""

from __future__ import annotations

import pandas as pd

from qdnb.core import paths

TABLES = {
    "3.3": ("table_3_3.csv", "Comparison to evolutionary competitors on Ant-Maze"),
    "3.4": ("table_3_4.csv", "Final performance compared to ablations and PG baselines"),
    "4.4": ("table_4_4.csv", "Accuracy experiment: average distance to goals and spread"),
    "4.5": ("table_4_5.csv", "Reassessment experiment in Halfcheetah-Uni"),
    "5.1": ("table_5_1.csv", "Flow Lenia parameter space of the FLT dataset"),
}


def table(number: str) -> pd.DataFrame:
    """The thesis's Table ``number`` (e.g. ``"3.4"``) as a DataFrame."""
    if number not in TABLES:
        raise ValueError(f"no transcribed table {number!r}; available: {', '.join(TABLES)}")
    df = pd.read_csv(paths.THESIS_DATA / TABLES[number][0])
    if "printed_scale" in df:
        df["mean"] = df["printed_mean"] / df["printed_scale"]
        df["std"] = df["printed_std"] / df["printed_scale"]
    return df


def comparison(rows: list[dict]) -> pd.DataFrame:
    """A "thesis vs this run" table: each row a dict with ``quantity``,
    ``thesis`` (what the thesis reports), ``this run`` and ``note``."""
    columns = ["quantity", "thesis", "this run", "note"]
    for row in rows:
        missing = set(columns) - set(row)
        if missing:
            raise ValueError(f"comparison row {row} lacks {sorted(missing)}")
    return pd.DataFrame(rows, columns=columns)
