"""Where things live, relative to the repository, never to the working directory."""

from __future__ import annotations

from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
NOTEBOOKS = ROOT / "notebooks"
BOOK = ROOT / "book"
DATA = ROOT / "data"
THESIS_DATA = DATA / "thesis"
RUNS = DATA / "runs"


def run_dir(scale: str, notebook: str, create: bool = True) -> Path:
    """``data/runs/<scale>/<notebook>/``: the artifacts of one notebook at one scale."""
    path = RUNS / scale / notebook
    if create:
        path.mkdir(parents=True, exist_ok=True)
    return path
