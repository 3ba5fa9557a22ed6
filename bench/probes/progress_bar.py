"""Does the progress bar slow a loop?  QD-PG on Point-Maze at the scale's
settings and seeds (as the Chapter 3 notebook runs it) through
``run_environment``, three ways: no bar, a bar with tqdm's monitor thread (its
default ``monitor_interval`` of 10 s), and a bar without it.  Records the
median chunk's seconds per iteration of each (measured: the three agree within
the loop's run-to-run spread, so ``qdnb.core.loops`` keeps tqdm's defaults).
Writes ``bench/results/progress_bar.json``.

    python bench/probes/progress_bar.py [--scale small] [--iterations 120]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import jax
from tqdm import tqdm

from qdnb.book.provenance import write_result
from qdnb.book.registry import config
from qdnb.chapters.ch3_qdpg import run_environment


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scale", default="small")
    parser.add_argument("--iterations", type=int, default=120)
    args = parser.parse_args()
    cfg = config("ch3_qdpg", args.scale).with_pointmaze_iterations(args.iterations)
    ways = {
        "no bar": (False, 0),
        "bar with the monitor thread": (True, 10),
        "bar without it": (True, 0),
    }
    rates = {}
    for name, (progress, interval) in ways.items():
        tqdm.monitor_interval = interval
        out = run_environment(
            cfg, "pointmaze", jax.random.PRNGKey(0), progress=progress, methods=("QD-PG",)
        )
        rates[name] = out.methods["QD-PG"].steady_seconds_per_iteration
        print(name, rates[name], flush=True)
    result = {
        "scale": args.scale,
        "iterations": args.iterations,
        "seeds": cfg.seeds("pointmaze", "QD-PG"),
        "seconds_per_iteration": rates,
        "monitor_over_no_bar": rates["bar with the monitor thread"] / rates["no bar"],
        "no_monitor_over_no_bar": rates["bar without it"] / rates["no bar"],
    }
    path = Path(__file__).parents[1] / "results" / "progress_bar.json"
    write_result(path, result)
    print(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
