"""How QD-PG's critics meet its actors: the A/B of issue 35, on Point-Maze at 10^6 steps.

Every variant is QD-PG (``update="alternate"``) at the `small` settings (8 actors,
100 critic steps per iteration, Adam at QDax's rates per role, Table 3.2's
networks, archive and grid) and the thesis's budget of 10^6 environment steps, on
the same seeds (``--seeds``, default 6: on 2 devices 5 seeds would be padded to 6
anyway).  The variants (``qdnb.qd.qdpg``'s module docstring says what each does):

- ``a-greedy``: the book's earlier QD-PG: critics trained against their own greedy
  actors, never played; the mutations take 100 actor steps and only read them;
- ``b-thesis``: the thesis's coupling (Section 3.5): every critic step uses the actor
  being improved as its TD3 target policy, the gradients averaged over the actors of
  each critic, an actor step after every 2 critic steps (50 per mutation);
- ``c-qdax``: QDax's greedy actors: ``a-greedy`` whose two greedy actors also play an
  episode every iteration (6 mutations + 2 greedy actors: the same 8 episodes);
- ``d-<pick>-sum``: the one of ``b-thesis`` and ``c-qdax`` the data favour, with Eq.
  3.5's sum of the K distances as the novelty reward instead of their mean (§3.6.3).

Rules fixed before any run: the chapter's QD-PG is the thesis's reading (b), whatever
the data say; (a), (c) and (d) are shown beside it as labelled variants, and (c) joins
the chapter's methods only if it reaches the exit zone on more seeds than (b).  (d)
takes the variant of (b) and (c) with more seeds in the exit zone; on a tie, the
higher mean final performance.

Added after (d)'s result, outside the rules above (``--extra``): ``x-thesis-sum``, the
thesis's coupling with the sum, the run (d)'s result asks for next.

Table 3.2's gradient-step ratio (800 critic steps per iteration, 400 mutation steps in
the thesis's coupling) is not run: the script times two of its iterations and
records what 10^6 steps would cost (``table_3_2_ratio``).

Per variant and seed: the environment steps to the exit zone, the final performance,
where the episodes ended (the shares of every evaluated episode's final position in
each region of the maze, over the run and over its last tenth), the coverage of the
grid's reachable cells, and per variant the wall time (compilation included) and the
compiled seconds per iteration.  Writes ``bench/results/qdpg_coupling.json`` after
every variant and skips those already in it, so an interrupted run resumes.

    python bench/probes/qdpg_coupling.py [--seeds 6] [--steps 1000000]
    python bench/probes/qdpg_coupling.py --scale tiny --steps 8000 --seeds 2 --out /tmp/x.json
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import jax
import numpy as np

sys.path.insert(0, str(Path(__file__).parents[1]))  # bench/, where the sweep it reuses lives
from qdpg_sweep import summarise  # noqa: E402

from qdnb.book.provenance import git_sha, write_result
from qdnb.book.registry import config
from qdnb.chapters.ch3_qdpg import build_algorithms, make_task_env, run_method
from qdnb.envs.pointmaze import maze_regions
from qdnb.qd.qdpg import QDPG

VARIANTS = {
    "a-greedy": dict(coupling="greedy"),
    "b-thesis": dict(coupling="thesis"),
    "c-qdax": dict(coupling="qdax"),
}
EXTRA = {"x-thesis-sum": dict(coupling="thesis", novelty_reduction="sum")}
RULE = (
    "(d) takes the coupling of b-thesis or c-qdax with more seeds in the exit zone; on a "
    "tie, the higher mean final performance"
)


def pick(runs: dict) -> str:
    """The rule for (d), on the finished runs of (b) and (c)."""
    score = lambda name: (runs[name]["reached_exit"], runs[name]["mean_final_performance"])
    return max(("b-thesis", "c-qdax"), key=score)


def where_episodes_end(descriptors: np.ndarray) -> dict[str, list[float]]:
    """Per seed, the share of the evaluated episodes' final positions in each region of
    the maze, over the whole run and over its last tenth."""
    out = {}
    iterations = descriptors.shape[1]
    for label, part in (("run", descriptors), ("last tenth", descriptors[:, -iterations // 10 :])):
        regions = maze_regions(part.reshape(part.shape[0], -1, 2))
        for region, mask in regions.items():
            out[f"{region} ({label})"] = [float(v) for v in mask.mean(axis=1)]
    return out


def table_3_2_ratio(cfg, algo: QDPG) -> dict:
    """Two timed iterations of the thesis's coupling at Table 3.2's ratio (4 x 200 = 800
    critic steps per iteration), on a mid-run buffer, and the projection to 10^6 steps."""
    task = cfg.pointmaze
    heavy = dataclasses.replace(algo, num_critic_steps=800, num_pg_steps=800)
    state, _ = jax.jit(heavy.init)(jax.random.PRNGKey(0))
    state = state.replace(buffer=state.buffer.replace(size=jax.numpy.asarray(150_000)))
    step = jax.jit(heavy.step)
    jax.block_until_ready(step(state))
    start = time.perf_counter()
    for _ in range(2):
        jax.block_until_ready(step(state))
    per_iteration = (time.perf_counter() - start) / 2
    iterations = 1_000_000 // (task.num_actors * task.episode_length)
    return {
        "num_critic_steps": 800,
        "seconds_per_iteration_one_seed": per_iteration,
        "projected_seconds_per_seed_for_1e6_steps": per_iteration * iterations,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scale", default="small")
    parser.add_argument("--seeds", type=int, default=6)
    parser.add_argument("--steps", type=int, default=1_000_000)
    parser.add_argument(
        "--out", type=Path, default=Path(__file__).parents[1] / "results" / "qdpg_coupling.json"
    )
    parser.add_argument("--skip-ratio", action="store_true", help="do not time Table 3.2's ratio")
    parser.add_argument("--extra", action="store_true", help="also run the EXTRA variants")
    args = parser.parse_args()
    cfg = config("ch3_qdpg", args.scale)
    cfg = dataclasses.replace(
        cfg, pointmaze=dataclasses.replace(cfg.pointmaze, num_steps=args.steps)
    )
    env = make_task_env(cfg, "pointmaze")
    base = build_algorithms(cfg, "pointmaze", env, methods=("QD-PG",))["QD-PG"]
    keys = jax.random.split(jax.random.PRNGKey(35), args.seeds)
    result = json.loads(args.out.read_text()) if args.out.exists() else {}
    same = result.get("steps") == args.steps and result.get("seeds") == args.seeds
    result = result if same else {}
    result.update(
        scale=args.scale,
        steps=args.steps,
        seeds=args.seeds,
        settings={
            k: v
            for k, v in dataclasses.asdict(cfg.pointmaze).items()
            if k not in ("num_steps", "buffer_size")
        },
        devices=len(jax.devices()),
        rule=RULE,
    )
    runs = result.setdefault("runs", {})
    commit = git_sha()  # the code this process runs, read before it runs

    def run(name: str, overrides: dict) -> None:
        if name in runs:
            print(f"{name}: already in {args.out}")
            return
        algo = dataclasses.replace(base, **overrides)
        r = run_method(cfg, "pointmaze", env, algo, keys, desc=f"{name}")
        entry = summarise(r, r.seconds)
        entry.update(
            overrides=overrides,
            seconds_per_iteration=r.steady_seconds_per_iteration,
            where_episodes_end=where_episodes_end(np.asarray(r.history["descriptors"])),
            curve_steps=r.cumulative_steps[0, ::10].tolist(),
            curve_performance=np.asarray(r.history["max_fitness"][:, ::10]).tolist(),
            commit=commit,
        )
        runs[name] = entry
        write_result(args.out, result)
        print(name, {k: entry[k] for k in ("reached_exit", "final_performance", "seconds")})

    for name, overrides in VARIANTS.items():
        run(name, overrides)
    favoured = pick(runs)
    result["picked_for_d"] = favoured
    run(f"d-{favoured.split('-')[1]}-sum", {**VARIANTS[favoured], "novelty_reduction": "sum"})
    if args.extra:
        for name, overrides in EXTRA.items():
            run(name, overrides)
    if not args.skip_ratio and "table_3_2_ratio" not in result:
        result["table_3_2_ratio"] = table_3_2_ratio(
            cfg, dataclasses.replace(base, coupling="thesis")
        )
    write_result(args.out, result)


if __name__ == "__main__":
    main()
