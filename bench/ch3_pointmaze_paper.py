"""Chapter 3's Point-Maze at `paper` (Table 3.2: 10^6 steps, five seeds side by side), for
a GPU session: the run the Chapter 3 page imports as a published run.

Sized first, by the loops themselves at the thesis's shapes: each method of the order
below runs its first ``--probe`` iterations on every seed (compiling, then a steady
chunk), its full run is projected from the steady chunk, and methods are kept in that
order while the projected total fits ``--budget-s`` (QD-PG and TD3 always, the claims'
pair).  Then the kept methods run in full, and the result goes to
``data/published/paper/ch3_pointmaze/pointmaze-paper.json`` (``--out``): per method and
seed the final performance, the environment steps to the exit zone, the grid's
reachable coverage, where the episodes ended, a NaN divergence if any, and the best
return's curve; with the device, commit, date and host it ran on, and the sizing table.
Commit that file: the Chapter 3 page shows it, under a banner saying where and when it
ran (it is not computed by the build).

    python bench/ch3_pointmaze_paper.py [--budget-s 420] [--seeds 5] [--steps 1000000]

On a CPU, ``--steps 16000 --seeds 2 --out /tmp/x.json`` checks the whole path quickly.
"""

from __future__ import annotations

import argparse
import dataclasses
import platform
import time
from pathlib import Path

import jax
import numpy as np

from qdnb.book.provenance import write_result
from qdnb.book.registry import config
from qdnb.chapters.ch3_qdpg import build_algorithms, make_task_env, run_method
from qdnb.core import paths
from qdnb.envs.pointmaze import maze_regions

ORDER = ("QD-PG", "TD3", "Q-PG", "D-PG", "QD-PG Sum", "PGA-ME")
REQUIRED = ("QD-PG", "TD3")
OUT = paths.DATA / "published" / "paper" / "ch3_pointmaze" / "pointmaze-paper.json"


def curve(steps: np.ndarray, values: np.ndarray, points: int = 100) -> dict:
    """About ``points`` entries of a per-iteration curve (the last one kept)."""
    every = max(1, len(steps) // points)
    at = sorted(set(range(0, len(steps), every)) | {len(steps) - 1})
    return {"steps": steps[at].tolist(), "values": values[at].tolist()}


def finite(value: float) -> float | None:
    return None if np.isnan(value) else float(value)


def method_entry(r, seconds: float) -> dict:
    seeds = []
    for i in range(len(r.env_steps)):
        regions = maze_regions(np.asarray(r.history["descriptors"][i]))
        div = r.diverged[i] if i < len(r.diverged) else None
        best = np.asarray(r.history["max_fitness"][i])
        seeds.append(
            {
                "final_performance": finite(r.final_performance[i]),
                "steps_to_exit": finite(r.exit_steps[i]),
                "coverage": finite(r.coverage[i]),
                "episodes_ending": {k: float(np.mean(v)) for k, v in regions.items()},
                "diverged": None
                if div is None
                else {"iteration": div.iteration, "parts": div.parts},
                "best_return_curve": curve(r.cumulative_steps[i], best),
            }
        )
    return {
        "seeds": seeds,
        "env_steps": float(r.env_steps.mean()),
        "wall_seconds": seconds,
        "seconds_per_iteration": r.steady_seconds_per_iteration,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--budget-s", type=float, default=420.0)
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--steps", type=int, default=None, help="(default: Table 3.2's 10^6)")
    parser.add_argument("--probe", type=int, default=20, help="iterations each method is sized on")
    parser.add_argument("--out", type=Path, default=OUT)
    args = parser.parse_args()
    began = time.perf_counter()
    cfg = dataclasses.replace(config("ch3_qdpg", "paper"), chunk_size=10)
    if args.steps:
        cfg = dataclasses.replace(
            cfg, pointmaze=dataclasses.replace(cfg.pointmaze, num_steps=args.steps)
        )
    task = cfg.pointmaze
    env = make_task_env(cfg, "pointmaze")
    algorithms = build_algorithms(cfg, "pointmaze", env, methods=ORDER)
    keys = jax.random.split(jax.random.PRNGKey(0), args.seeds)
    probe_cfg = dataclasses.replace(
        cfg,
        pointmaze=dataclasses.replace(
            task, num_steps=(args.probe + 1) * task.num_actors * task.episode_length
        ),
    )
    sizing, kept, projected_total = {}, [], 0.0
    for name in ORDER:
        start = time.perf_counter()
        probe = run_method(probe_cfg, "pointmaze", env, algorithms[name], keys, progress=False)
        rate = probe.steady_seconds_per_iteration
        projected = rate * task.num_iterations
        sizing[name] = {
            "probe_seconds": time.perf_counter() - start,
            "seconds_per_iteration": rate,
            "projected_seconds": projected,
        }
        left = args.budget_s - (time.perf_counter() - began)
        if name in REQUIRED or projected_total + projected <= left:
            kept.append(name)
            projected_total += projected
        print(f"{name}: {rate:.3f} s/iteration, {projected:.0f} s projected", flush=True)
    methods = {}
    for name in kept:
        start = time.perf_counter()
        r = run_method(cfg, "pointmaze", env, algorithms[name], keys, desc=f"paper {name}")
        methods[name] = method_entry(r, time.perf_counter() - start)
        print(f"{name}: done in {methods[name]['wall_seconds']:.0f} s", flush=True)
    out = {
        "what": "Chapter 3's Point-Maze at paper scale (Table 3.2), "
        f"{args.seeds} seeds side by side",
        "host": platform.node(),
        "steps": task.num_steps,
        "seeds": args.seeds,
        "settings": dataclasses.asdict(task),
        "sizing": sizing,
        "not_run": [m for m in ORDER if m not in kept],
        "methods": methods,
        "wall_seconds": time.perf_counter() - began,
    }
    write_result(args.out, out)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
