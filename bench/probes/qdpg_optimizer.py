"""SGD (Table 3.2) against Adam for QD-PG's networks on Point-Maze, at the `small`
scale's budget and gradient steps.  Writes ``bench/results/qdpg_optimizer.json``.

    python bench/probes/qdpg_optimizer.py [--methods D-PG,QD-PG] [--seed 0]

For each method and optimiser: the final performance, whether an episode ended in
the exit zone, the first environment step at which one did, and the grid coverage.
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path

import jax
import numpy as np

from qdnb.book.provenance import write_result
from qdnb.book.registry import config
from qdnb.chapters.ch3_qdpg import POINTMAZE_PAPER, build_algorithms, in_exit_zone
from qdnb.qd.algorithms import run_seeds


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--methods", default="D-PG,QD-PG")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    small = config("ch3_qdpg", "small")
    settings = {
        "sgd (Table 3.2)": dict(optimizer="sgd", learning_rate=POINTMAZE_PAPER.learning_rate),
        "adam (small scale)": dict(
            optimizer=small.pointmaze.optimizer, learning_rate=small.pointmaze.learning_rate
        ),
    }
    rows = []
    for label, change in settings.items():
        cfg = dataclasses.replace(
            small.with_seeds(1), pointmaze=dataclasses.replace(small.pointmaze, **change)
        )
        algorithms = build_algorithms(cfg, "pointmaze")
        for method in args.methods.split(","):
            start = time.perf_counter()
            _, _, h = run_seeds(
                algorithms[method],
                jax.random.PRNGKey(args.seed)[None],
                cfg.pointmaze.num_iterations - 1,
                cfg.chunk_size,
                progress=False,
            )
            h = jax.device_get(h)
            d = h["descriptors"][0]
            steps = np.cumsum(h["env_steps"][0])
            exit_zone = in_exit_zone(d).any(axis=-1)
            rows.append(
                {
                    "optimizer": label,
                    **change,
                    "method": method,
                    "final_performance": float(h["max_fitness"][0, -1]),
                    "coverage": float(h["coverage"][0, -1]),
                    "reached_exit": bool(exit_zone.any()),
                    "first_step_in_exit": float(steps[np.argmax(exit_zone)])
                    if exit_zone.any()
                    else None,
                    "env_steps": int(steps[-1]),
                    "seconds": round(time.perf_counter() - start, 1),
                }
            )
            print(rows[-1], flush=True)
    out = Path(__file__).parents[1] / "results" / "qdpg_optimizer.json"
    out.parent.mkdir(exist_ok=True)
    write_result(
        out,
        {
            "seed": args.seed,
            "num_critic_steps": small.pointmaze.num_critic_steps,
            "num_pg_steps": small.pointmaze.num_pg_steps,
            "runs": rows,
        },
    )


if __name__ == "__main__":
    main()
