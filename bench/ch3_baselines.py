"""Chapter 3's policy-gradient baselines on Point-Maze: environment steps per second of
each (one seed, its whole loop compiled in ``run_seeds`` chunks, the median chunk
after the first), beside QD-PG's and TD3's in the same run.  Writes
``bench/results/ch3_baselines.json``.

    python bench/ch3_baselines.py [--scale small] [--iterations 40]

Each method runs ``--iterations`` iterations of the scale's Point-Maze settings (the
same episodes and gradient steps per iteration as the notebook), in chunks of 5.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import jax
import numpy as np

from qdnb.book.provenance import write_result
from qdnb.book.registry import config
from qdnb.chapters.ch3_baselines import BASELINES
from qdnb.chapters.ch3_qdpg import build_algorithms, steady_rate
from qdnb.qd.algorithms import run_seeds

CHUNK = 5


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scale", default="small")
    parser.add_argument("--iterations", type=int, default=40)
    parser.add_argument(
        "--out", default=str(Path(__file__).parent / "results" / "ch3_baselines.json")
    )
    args = parser.parse_args()
    if args.iterations < 2 * CHUNK:
        parser.error(f"--iterations must be at least {2 * CHUNK} (two chunks of {CHUNK})")
    cfg = config("ch3_baselines", args.scale)
    tasks = cfg.baseline_tasks("pointmaze").with_pointmaze_iterations(args.iterations)
    task = tasks.pointmaze
    steps_per_iteration = task.num_actors * task.episode_length
    methods = ("QD-PG", "TD3") + BASELINES
    algorithms = build_algorithms(tasks, "pointmaze", methods=methods)
    out = {
        "scale": args.scale,
        "iterations": args.iterations,
        "episodes_per_iteration": task.num_actors,
        "episode_length": task.episode_length,
        "gradient_steps_per_iteration": task.num_critic_steps,
        "methods": {},
    }
    for name, algo in algorithms.items():
        chunks: list[float] = []
        start = time.perf_counter()
        _, _, history = run_seeds(
            algo,
            jax.random.split(jax.random.PRNGKey(0), 1),
            args.iterations - 1,
            CHUNK,
            progress=False,
            chunk_seconds=chunks,
        )
        jax.block_until_ready(history)
        seconds = time.perf_counter() - start
        per_iteration = steady_rate(chunks, CHUNK, seconds / args.iterations)
        out["methods"][name] = {
            "seconds_with_compile": round(seconds, 2),
            "steady_seconds_per_iteration": round(per_iteration, 4),
            # nominal steps (episodes that end in the exit zone stop early)
            "env_steps_per_second": round(steps_per_iteration / per_iteration, 1),
            "measured_env_steps": int(np.sum(history["env_steps"])),
        }
        print(name, out["methods"][name], flush=True)
    qdpg = out["methods"]["QD-PG"]["env_steps_per_second"]
    for entry in out["methods"].values():
        entry["rate_over_qdpg"] = round(entry["env_steps_per_second"] / qdpg, 2)
    write_result(Path(args.out), out)
    print("wrote", args.out)


if __name__ == "__main__":
    main()
