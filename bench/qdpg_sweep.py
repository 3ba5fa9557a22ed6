"""The sweep that chooses Chapter 3's `small` Point-Maze settings.

QD-PG and D-PG run on Point-Maze at the thesis's budget of 10^6 environment
steps, two seeds each (``vmap``), for each variant of a small grid stated below:
one factor changed at a time around a base, the factors the review of issue 14
named (learning rates per role, gradient steps per iteration, the archive's
acceptance threshold and capacity, actors per iteration).  Per variant and
method it records, per seed, the environment steps to the exit zone (``null``:
never), the final performance (Table 3.4's return), the final grid coverage,
and the wall time (compilation included).  Writes
``bench/results/qdpg_sweep.json`` after every run, and skips the runs already
in it, so an interrupted sweep resumes.

    python bench/qdpg_sweep.py                 # the `small` grid
    python bench/qdpg_sweep.py --grid tiny     # two variants at `tiny` (the test)

Round 1 changes one factor at a time around "base"; round 2, added once round
1 had picked ``archive-table-3.2``, changes one more factor around that pick.
The same rule applies to both rounds together.

Selection rule, fixed before any run: among the variants whose QD-PG iteration
fits the notebook's time budget, the one with the highest mean final
performance over QD-PG's and D-PG's seeds; ties go to the cheaper variant.  The
same settings then serve every method of the notebook that uses them.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import jax
import numpy as np

from qdnb.book.provenance import git_sha, write_result
from qdnb.book.registry import config
from qdnb.chapters.ch3_qdpg import run_environment, steps_to_exit

# Overrides of the scale's Point-Maze task, one factor at a time around "base".
BASE = dict(
    optimizer="adam",
    learning_rate=3e-4,
    mutation_learning_rate=1e-3,
    num_critic_steps=100,
    num_pg_steps=100,
    archive_threshold=0.1,
    archive_size=2_000,
    num_actors=4,
)
GRIDS = {
    "small": {
        # QDax's rates (3e-4 critics and greedy actors, 1e-3 mutations), a lasting coarse archive
        "base": {},
        "archive-table-3.2": dict(
            archive_threshold=1e-4, archive_size=10_000
        ),  # admits nearly every state
        "steps-200": dict(
            num_critic_steps=200, num_pg_steps=200
        ),  # twice the gradient steps per iteration
        "actors-8": dict(num_actors=8),  # twice the actors per iteration, half the iterations
        "one-rate-5e-3": dict(
            learning_rate=5e-3, mutation_learning_rate=5e-3
        ),  # the settings issue 14 reviewed
        "archive-0.03": dict(archive_threshold=0.03, archive_size=5_000),  # a finer lasting archive
        # Round 2, added after round 1 picked "archive-table-3.2": one more factor changed around
        # that pick.
        "table-3.2+steps-200": dict(
            archive_threshold=1e-4, archive_size=10_000, num_critic_steps=200, num_pg_steps=200
        ),  # the gradient-step ratio, the largest departure left
        "table-3.2+actors-8": dict(archive_threshold=1e-4, archive_size=10_000, num_actors=8),
    },
    "tiny": {
        "base": {},
        "steps-20": dict(num_critic_steps=20, num_pg_steps=20),
    },
}
SCALE = {"small": "small", "tiny": "tiny"}
BUDGET = {"small": 1_000_000, "tiny": 4_000}
TINY_BASE = dict(num_critic_steps=10, num_pg_steps=10, archive_size=256)


def variant_config(grid: str, name: str, seeds: int):
    cfg = config("ch3_qdpg", SCALE[grid])
    overrides = {
        **BASE,
        **(TINY_BASE if grid == "tiny" else {}),
        **GRIDS[grid][name],
        "num_steps": BUDGET[grid],
    }
    task = dataclasses.replace(cfg.pointmaze, **overrides)
    return dataclasses.replace(cfg.with_seeds(seeds), pointmaze=task), overrides


def summarise(result, seconds: float) -> dict:
    steps = steps_to_exit(result)
    perf = np.asarray(result.final_performance, float)
    return {
        "steps_to_exit": [None if np.isnan(s) else int(s) for s in steps],
        "reached_exit": int(np.sum(~np.isnan(steps))),
        "final_performance": perf.tolist(),
        "mean_final_performance": float(perf.mean()),
        "coverage": np.asarray(result.coverage, float).tolist(),
        "env_steps": np.asarray(result.env_steps).tolist(),
        "seconds": seconds,
    }


def select(runs: dict, budget_seconds: float | None) -> str | None:
    """The selection rule of the docstring, on the variants with every method run."""
    scored = []
    for name, methods in runs.items():
        if not all(m in methods for m in ("QD-PG", "D-PG")):
            continue
        seconds = methods["QD-PG"]["seconds"]
        if budget_seconds is not None and seconds > budget_seconds:
            continue
        perf = np.mean(methods["QD-PG"]["final_performance"] + methods["D-PG"]["final_performance"])
        scored.append((-perf, seconds, name))
    return min(scored)[2] if scored else None


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--grid", choices=sorted(GRIDS), default="small")
    parser.add_argument("--seeds", type=int, default=2)
    parser.add_argument("--methods", nargs="+", default=["QD-PG", "D-PG"])
    parser.add_argument("--only", nargs="+", help="run these variants only (in this order)")
    parser.add_argument(
        "--qdpg-budget-seconds",
        type=float,
        default=None,
        help="QD-PG's wall-time limit per run for the selection (default: none)",
    )
    parser.add_argument(
        "--out", type=Path, default=Path(__file__).parent / "results" / "qdpg_sweep.json"
    )
    args = parser.parse_args()
    names = args.only or list(GRIDS[args.grid])
    unknown = set(names) - set(GRIDS[args.grid])
    if unknown:
        parser.error(f"unknown variants {sorted(unknown)}; valid: {', '.join(GRIDS[args.grid])}")

    out = json.loads(args.out.read_text()) if args.out.exists() else {}
    if out.get("grid_name") != args.grid or out.get("seeds") != args.seeds:
        out = {}
    out.update(
        {
            "grid_name": args.grid,
            "seeds": args.seeds,
            "budget_steps": BUDGET[args.grid],
            "base": {**BASE, **(TINY_BASE if args.grid == "tiny" else {})},
            "grid": GRIDS[args.grid],
            "selection_rule": __doc__.split("Selection rule, ")[1].strip(),
        }
    )
    runs = out.setdefault("runs", {})
    for name in names:
        cfg, overrides = variant_config(args.grid, name, args.seeds)
        for method in args.methods:
            if method in runs.get(name, {}):
                continue
            start = time.perf_counter()
            result = run_environment(
                cfg, "pointmaze", jax.random.PRNGKey(0), progress=True, methods=(method,)
            )
            entry = summarise(result.methods[method], time.perf_counter() - start)
            entry["settings"] = overrides
            entry["commit"] = git_sha()  # wall times depend on the code that ran them
            runs.setdefault(name, {})[method] = entry
            out["selected"] = select(runs, args.qdpg_budget_seconds)
            args.out.parent.mkdir(parents=True, exist_ok=True)
            write_result(args.out, out)
            print(
                name,
                method,
                json.dumps(
                    {k: entry[k] for k in ("steps_to_exit", "final_performance", "seconds")}
                ),
                flush=True,
            )


if __name__ == "__main__":
    main()
