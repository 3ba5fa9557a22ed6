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
