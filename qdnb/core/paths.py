"""Where things live, relative to the repository, never to the working directory."""

from __future__ import annotations

import os
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
NOTEBOOKS = ROOT / "notebooks"
BOOK = ROOT / "book"
DATA = ROOT / "data"
THESIS_DATA = DATA / "thesis"
# QDNB_RUNS puts the runs elsewhere (the tests' in-place nbmake run of the primer)
RUNS = Path(os.environ.get("QDNB_RUNS", DATA / "runs"))


def run_dir(scale: str, notebook: str, create: bool = True) -> Path:
    """``data/runs/<scale>/<notebook>/``: the artifacts of one notebook at one scale."""
    path = RUNS / scale / notebook
    if create:
        path.mkdir(parents=True, exist_ok=True)
    return path


def shown(path: Path) -> str:
    """``path`` as a page may show it: relative to the repository, or to ``$QDNB_RUNS``
    when the runs live elsewhere (never a path of the machine that built the page)."""
    path = Path(path).resolve()
    for base, prefix in ((ROOT, ""), (RUNS.resolve(), "$QDNB_RUNS/")):
        if path.is_relative_to(base):
            return prefix + str(path.relative_to(base))
    return path.name
