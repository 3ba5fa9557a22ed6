"""Chapter 3's `small` Point-Maze budget: how many environment steps the page can give
every Point-Maze method at Table 3.2's per-iteration gradient budget.

The rule (issue 48, written before measuring): `small` keeps ``POINTMAZE_PAPER``
whole (N = 4 actors, 800 critic steps an iteration, 400 policy-gradient steps a
mutation, SGD at 6e-3, networks, archive, grid) except its environment steps, which
are the largest multiple of 16,000 (20 iterations) for which the page takes at most
15 minutes on this 2-core CPU (and so 25 on a machine 1.7 times slower); QD-PG runs
on 4 seeds (two per core), the other five Point-Maze methods on 2.

Measured here: each Point-Maze method's loop on the page's seeds, ``--probe``
iterations (its wall time with compilation, and its steady seconds per iteration),
and the rest of the page (the two ant mazes, the fast adaptation) at its `small`
settings.  A budget of B iterations then costs the sum over the methods of their
compilation plus B times their rate, plus the rest.  Writes
``bench/results/ch3_small_budget.json``.

Then checked on the page itself: ``--check`` reads an executed `small` page's
``summary.json`` (its wall time, the Point-Maze steps it ran, each method's seconds per
iteration), projects the page at each budget from it the same way, and adds the check
to the JSON's ``page_checks``; where they disagree the pages' own measurements decide:
the budget every checked page fits (this machine's speed varies by a fifth within an
hour and by half over a day).

    python bench/ch3_small_budget.py [--probe 20]
    python bench/ch3_small_budget.py --check data/runs/small/ch3_qdpg
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import jax

from qdnb.book.provenance import write_result
from qdnb.book.registry import config
from qdnb.chapters.ch3_qdpg import (
    QDPG_METHODS,
    build_algorithms,
    fast_adaptation,
    make_task_env,
    run_environment,
    run_method,
)

PAGE_SECONDS = 15 * 60
STEP = 16_000  # budgets in multiples of 20 iterations of 4 x 200 steps
RESULTS = Path(__file__).parent / "results" / "ch3_small_budget.json"


def check(run_dir: Path) -> None:
    """The rule applied to an executed page: its wall time moved by each method's
    measured rate to every budget."""
    summary = json.loads((run_dir / "summary.json").read_text())
    cfg = config("ch3_qdpg", "small")
    steps_per_iteration = cfg.pointmaze.num_actors * cfg.pointmaze.episode_length
    ran = cfg.pointmaze.num_steps
    rates = summary["results"]["pointmaze_seconds_per_iteration"]
    rate = sum(rates.values())
    wall = summary["wall_time_s"]
    page = lambda steps: wall + rate * (steps - ran) / steps_per_iteration
    budgets = {str(b): page(b) for b in range(STEP, 400_001, STEP)}
    fitting = [b for b in range(STEP, 400_001, STEP) if page(b) <= PAGE_SECONDS]
    out = json.loads(RESULTS.read_text())
    checks = out.setdefault("page_checks", [])
    checks.append(
        {
            "run": str(run_dir),
            "commit": summary["git_sha"],
            "date": time.strftime("%Y-%m-%d"),
            "point_maze_steps_it_ran": ran,
            "page_wall_seconds": wall,
            "seconds_per_iteration": rates,
            "projected_page_seconds_by_budget": budgets,
            "chosen_steps": max(fitting) if fitting else None,
        }
    )
    chosen = [c["chosen_steps"] for c in checks]
    out["chosen_steps_by_the_pages"] = None if None in chosen else min(chosen)
    write_result(RESULTS, out, keep_provenance=True)  # (the measurement's stays)
    print(json.dumps({"chosen_steps": out["chosen_steps_by_the_pages"]}), f"wrote {RESULTS}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--probe", type=int, default=20)
    parser.add_argument("--check", type=Path, help="an executed small page's run folder")
    args = parser.parse_args()
    if args.check:
        return check(args.check)
    cfg = config("ch3_qdpg", "small")
    task = cfg.pointmaze
    steps_per_iteration = task.num_actors * task.episode_length
    probe = dataclasses.replace(
        cfg,
        pointmaze=dataclasses.replace(task, num_steps=(args.probe + 1) * steps_per_iteration),
    )
    env = make_task_env(probe, "pointmaze")
    algorithms = build_algorithms(probe, "pointmaze", env)
    loops = {}
    for name in QDPG_METHODS:
        seeds = probe.seeds("pointmaze", name)
        start = time.perf_counter()
        r = run_method(probe, "pointmaze", env, algorithms[name], jax.random.split(
            jax.random.PRNGKey(0), seeds), progress=False)  # fmt: skip
        wall = time.perf_counter() - start
        rate = r.steady_seconds_per_iteration
        loops[name] = {
            "seeds": seeds,
            "wall_seconds": wall,
            "seconds_per_iteration": rate,
            "fixed_seconds (compilation and first chunk)": max(wall - rate * args.probe, 0.0),
        }
        print(name, json.dumps(loops[name]), flush=True)
    start = time.perf_counter()
    ants = {
        e: run_environment(cfg, e, jax.random.PRNGKey(1), False) for e in ("antmaze", "anttrap")
    }
    fast_adaptation(cfg, ants["antmaze"], 0)
    rest = time.perf_counter() - start
    fixed = sum(v["fixed_seconds (compilation and first chunk)"] for v in loops.values())
    rate = sum(v["seconds_per_iteration"] for v in loops.values())
    page = lambda steps: fixed + rate * steps / steps_per_iteration + rest
    budgets = {str(b): page(b) for b in range(STEP, 400_001, STEP)}
    fitting = [b for b in range(STEP, 400_001, STEP) if page(b) <= PAGE_SECONDS]
    out = {
        "rule": __doc__.split("The rule")[1].split("Measured here")[0].strip(),
        "probe_iterations": args.probe,
        "point_maze_loops": loops,
        "rest_of_page_seconds (ant mazes, fast adaptation)": rest,
        "projected_page_seconds_by_budget": budgets,
        "chosen_steps": max(fitting) if fitting else None,
    }
    write_result(RESULTS, out)
    print(json.dumps({k: out[k] for k in ("chosen_steps",)}), f"wrote {RESULTS}")


if __name__ == "__main__":
    main()
