"""A finished run as the runner leaves it, written by hand: the book's tests (the
scorecard, published runs, published verdicts) read these instead of running a page."""

import json
from pathlib import Path

import nbformat

from qdnb.core import paths

DEFAULTS = {
    "seed": 0,
    "git_sha": "0123456789abcdef",
    "device": "cpu: cpu x2 (2 CPU cores)",
    "devices": {"platform": "cpu", "count": 2},
    "wall_time_s": 12.0,
}


def write_run(scale: str, name: str, results: dict, notebook=None, **fields) -> Path:
    """``name``'s run at ``scale`` in the runs folder: its ``summary.json`` (``results``,
    and ``fields`` over ``DEFAULTS``), its executed notebook (``notebook``, else an empty
    one) and its execution record.  Returns the run's folder."""
    d = paths.run_dir(scale, name)
    summary = {"notebook": name, "scale": scale, **DEFAULTS, **fields, "results": results}
    nbformat.write(notebook or nbformat.v4.new_notebook(), d / f"{name}.ipynb")
    (d / "summary.json").write_text(json.dumps(summary))
    (d / "execution.json").write_text(json.dumps({"status": "ok", "fingerprint": "f"}))
    return d
