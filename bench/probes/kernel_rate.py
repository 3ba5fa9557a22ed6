"""Does running inside a Jupyter kernel slow QD-PG's loop?  QD-PG on Point-Maze
at the scale's settings and seeds (as the Chapter 3 notebook runs it) through
``run_environment`` with its progress bar, two ways: in this Python process,
and in a notebook of one cell executed by papermill with the kernel spec
``python -m qdnb run`` uses (``qdnb.book.runner.execute``).  Records the median
chunk's seconds per iteration of each, the statistic the notebook reports.
Writes ``bench/results/kernel_rate.json``.

    python bench/probes/kernel_rate.py [--scale small] [--iterations 120]
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

import jax
import nbformat

from qdnb.book.provenance import write_result
from qdnb.book.registry import config
from qdnb.book.runner import execute
from qdnb.chapters.ch3_qdpg import run_environment

CELL = """
import json
import jax
from qdnb.chapters.ch3_qdpg import run_environment
from qdnb.book.registry import config
cfg = config("ch3_qdpg", {scale!r}).with_pointmaze_iterations({iterations})
out = run_environment(cfg, "pointmaze", jax.random.PRNGKey(0), progress=True, methods=("QD-PG",))
with open({result!r}, "w") as f:
    json.dump(out.methods["QD-PG"].steady_seconds_per_iteration, f)
"""


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scale", default="small")
    parser.add_argument("--iterations", type=int, default=120)
    args = parser.parse_args()
    cfg = config("ch3_qdpg", args.scale).with_pointmaze_iterations(args.iterations)
    rates = {}
    with tempfile.TemporaryDirectory() as tmp:
        result = Path(tmp) / "rate.json"
        nb = nbformat.v4.new_notebook(
            cells=[
                nbformat.v4.new_code_cell(
                    CELL.format(scale=args.scale, iterations=args.iterations, result=str(result))
                )
            ]
        )
        source = Path(tmp) / "rate.ipynb"
        nbformat.write(nb, source)
        execute(source, Path(tmp) / "rate.out.ipynb", {}, "kernel_rate", progress=False)
        rates["in a papermill kernel"] = json.loads(result.read_text())
    out = run_environment(
        cfg, "pointmaze", jax.random.PRNGKey(0), progress=True, methods=("QD-PG",)
    )
    rates["in this process"] = out.methods["QD-PG"].steady_seconds_per_iteration
    record = {
        "scale": args.scale,
        "iterations": args.iterations,
        "seeds": cfg.seeds("pointmaze", "QD-PG"),
        "num_actors": cfg.pointmaze.num_actors,
        "seconds_per_iteration": rates,
        "kernel_over_process": rates["in a papermill kernel"] / rates["in this process"],
    }
    path = Path(__file__).parents[1] / "results" / "kernel_rate.json"
    write_result(path, record)
    print(json.dumps(record, indent=1))


if __name__ == "__main__":
    main()
