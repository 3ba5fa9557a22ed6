"""Where QD-PG's and D-PG's transitions go in Point-Maze: a diagnosis of why
neither reaches the exit zone at `small` in 10^6 steps (``bench/qdpg_sweep.py``).

One seed of each method at the scale's Point-Maze settings, run for the thesis's
10^6 steps; the replay buffer (10^6 transitions, so it holds every transition
of the run, in order) and the novelty archive are read at the end.  For the
states visited (``psi(s_t)`` of every transition), the archive's entries and
the episodes' final positions, it counts the share in each region of the maze:
below the lower wall, between the walls, in the right-hand passage past the
upper wall's end (x > 0.5, between the walls), and above the upper wall
(where the exit zone is).  It also records how many steps had been taken when a
transition first started above the upper wall.  Writes
``bench/results/qdpg_reach.json``.

    python bench/probes/qdpg_reach.py [--steps 1000000] [--methods D-PG QD-PG]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import jax
import numpy as np

from qdnb.book.provenance import write_result
from qdnb.book.registry import config
from qdnb.chapters.ch3_qdpg import build_algorithms, make_task_env
from qdnb.envs.pointmaze import WALLS, maze_regions
from qdnb.qd.algorithms import run_seeds


def shares(masks: dict[str, np.ndarray]) -> dict[str, float]:
    """Share of the points in each region, from ``maze_regions``'s masks."""
    return {name: float(mask.sum() / max(mask.size, 1)) for name, mask in masks.items()}


def regions(points: np.ndarray) -> dict[str, float]:
    """Share of ``points`` (n x 2) in each region of the maze."""
    return shares(maze_regions(points))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scale", default="small")
    parser.add_argument("--steps", type=int, default=1_000_000)
    parser.add_argument("--methods", nargs="+", default=["D-PG", "QD-PG"])
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--out", type=Path, default=Path(__file__).parents[1] / "results" / "qdpg_reach.json"
    )
    args = parser.parse_args()
    cfg = config("ch3_qdpg", args.scale)
    cfg = dataclasses.replace(
        cfg.with_seeds(1), pointmaze=dataclasses.replace(cfg.pointmaze, num_steps=args.steps)
    )
    task = cfg.pointmaze
    if task.buffer_size < args.steps:
        parser.error(
            f"the buffer ({task.buffer_size}) must hold every transition of {args.steps} steps"
        )
    env = make_task_env(cfg, "pointmaze")
    algorithms = build_algorithms(cfg, "pointmaze", env)
    out = {
        "scale": args.scale,
        "steps": args.steps,
        "seed": args.seed,
        "walls": [list(w) for w in WALLS],
        "settings": {
            k: getattr(task, k)
            for k in (
                "optimizer",
                "learning_rate",
                "mutation_learning_rate",
                "num_critic_steps",
                "num_pg_steps",
                "archive_threshold",
                "archive_size",
                "num_actors",
            )
        },
        "methods": {},
    }
    for method in args.methods:
        start = time.perf_counter()
        states, _, history = run_seeds(
            algorithms[method],
            jax.random.PRNGKey(args.seed)[None],
            task.num_iterations - 1,
            cfg.chunk_size,
            desc=f"pointmaze {method}",
        )
        state = jax.tree.map(lambda x: np.asarray(x[0]), states)
        size = int(state.buffer.size)
        visited = state.buffer.data["state_descriptor"][:size]
        archive = state.archive.data[: int(min(state.archive.num_added, state.archive.capacity))]
        finals = np.asarray(history["descriptors"]).reshape(-1, 2)
        visited_regions = maze_regions(visited)
        above = np.flatnonzero(visited_regions["above the upper wall"])  # in step order
        out["methods"][method] = {
            "seconds": time.perf_counter() - start,
            "transitions": size,
            "visited_states": shares(visited_regions),
            "archive_entries": int(len(archive)),
            "archive": regions(archive),
            "episode_final_positions": regions(finals),
            "steps_when_first_above_the_upper_wall": int(above[0]) if len(above) else None,
            "highest_visited_y_right_of_the_wall_end": float(
                visited[visited[:, 0] > WALLS[0][1], 1].max(initial=-1.0)
            ),
        }
        print(method, json.dumps(out["methods"][method], indent=1), flush=True)
        args.out.parent.mkdir(parents=True, exist_ok=True)
        write_result(args.out, out)


if __name__ == "__main__":
    main()
