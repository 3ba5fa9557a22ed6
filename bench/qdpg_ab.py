"""Why QD-PG stays in Point-Maze's trap: an A/B of its readings at Table 3.2's budget.

THE RULE (written before any run; the results file carries it):

- Budget, every variant: Table 3.2's per-iteration gradient budget on Point-Maze:
  N = 4 actors, 800 critic steps an iteration, 400 policy-gradient steps a mutation,
  10^6 environment steps (1,250 iterations of 4 episodes of 200 steps), the grid,
  networks, archive (10,000, threshold 1e-4) and K = 10 of ``POINTMAZE_PAPER``.
- Seeds: 4 a variant (seeds 0-3, run two side by side, one per core), more if a
  verdict is one seed from changing.
- Variants, in this order (the evidence first):
  1. ``thesis-adam``: the thesis's reading (mean novelty, its coupling), Adam at
     QDax's rates (critics 3e-4, mutations 1e-3), the base of 3-6;
  2. ``sum``: the base with Eq. 3.5 as printed (the sum of the K distances);
  3. ``thesis-sgd``: the thesis's reading as Table 3.2 gives it, SGD at 6e-3;
  4. ``qdax-novelty``: the base with QDax's scorer (mean squared distance, K = 5);
  5. ``qdax-greedy``: the base with QDax's coupling (each critic trained against
     its own greedy actor, which is played and competes for a cell);
  6. ``exploration-noise``: the base with the population playing its episodes with
     TD3's Gaussian exploration noise (0.1; our population plays deterministically,
     as QDax's QD-PG does).
- Per seed: environment steps to the exit zone (first evaluated episode ending in
  it), final performance (the grid's best return), share of the run's episodes
  ending above the upper wall (y > 0.21), reachable coverage of the grid, NaN
  (iteration and parts, ``qdnb.core.health``), wall time.
- A reading **exits** when at least 3 of its 4 seeds reach the exit zone; a
  diverged seed counts as not reaching it.
- Added on 2026-12-06, after thesis-adam's four seeds (2 of 4 in the exit zone) and before
  any further seed ran, to make "more if a verdict is one seed from changing" exact: a
  reading with exactly 2 of 4 seeds in the zone gets seeds 4-5 before the next variant,
  and is then read on its 6 seeds with the same share, three quarters (5 of 6).
- Stop early: once a variant exits, the variants after it in the order are not run
  (``thesis-sgd`` always runs: it is the thesis's own reading and its divergence is
  diagnosed from it).  The thesis's reading stays QD-PG in the chapter whatever
  exits; a variant that exits is shown beside it, labelled.
- Added on 2026-12-08, after the A/B above ended (``qdax-novelty`` exits, 3 of 4 seeds,
  so ``qdax-greedy`` and ``exploration-noise`` are not run) and before any of these seeds
  ran: diagnostics, outside the early stop, run only when named (``--variants``), each
  read by the same rule (3 of 4 seeds; 2 of 4 gets seeds 4-5), to say which of an exiting
  reading's differences made it exit.  ``squared-k10`` is ``qdax-novelty`` with the
  thesis's K = 10: if it exits, QDax's squared distance is enough; if it does not, K = 5
  is needed, alone or with the squared distance.

Resumable: each pair of seeds is one loop with checkpoints (every 5 minutes, under
``data/runs/bench/qdpg_ab/``), and its rows are written to
``bench/results/qdpg_ab.json`` as soon as it ends; a variant or pair already there
is skipped.  Commit the file as rows arrive: the whole A/B takes about an hour a
variant on 2 cores.

    python bench/qdpg_ab.py [--variants thesis-adam sum] [--steps 1000000] [--seeds 4]
    python bench/qdpg_ab.py --variants squared-k10    # a diagnostic: only when named
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import time
from pathlib import Path
from typing import Any, Callable

import jax
import numpy as np

from qdnb.book.provenance import code_version, write_result
from qdnb.book.registry import config
from qdnb.chapters.ch3_qdpg import (
    POINTMAZE_PAPER,
    READING_MIN_SEEDS,
    QDPGConfig,
    build_algorithms,
    make_task_env,
    reading_exits,
    reading_needs_more_seeds,
    run_method,
)
from qdnb.core import checkpoint, health
from qdnb.core.config import config_hash
from qdnb.envs.pointmaze import WALLS

RESULTS = Path(__file__).parent / "results" / "qdpg_ab.json"
CHECKPOINTS = Path(__file__).parents[1] / "data" / "runs" / "bench" / "qdpg_ab"
UPPER_WALL_TOP = WALLS[0][3]
ALWAYS = ("thesis-sgd",)


def table_3_2(steps: int) -> QDPGConfig:
    """``paper``'s Chapter 3 config with Point-Maze at Table 3.2 and ``steps`` steps."""
    cfg = config("ch3_qdpg", "paper")
    task = dataclasses.replace(POINTMAZE_PAPER, num_steps=steps, num_pg_steps=400)
    return dataclasses.replace(cfg, pointmaze=task, chunk_size=10)


def adam(cfg: QDPGConfig) -> QDPGConfig:
    task = dataclasses.replace(
        cfg.pointmaze, optimizer="adam", learning_rate=3e-4, mutation_learning_rate=1e-3
    )
    return dataclasses.replace(cfg, pointmaze=task)


# name -> (what differs, the config, the QD-PG fields changed)
VARIANTS: dict[str, tuple[str, Callable[[QDPGConfig], QDPGConfig], dict[str, Any]]] = {
    "thesis-adam": ("mean novelty, Adam (critics 3e-4, mutations 1e-3)", adam, {}),
    "sum": ("Eq. 3.5's sum of the K distances", adam, {"novelty_reduction": "sum"}),
    "thesis-sgd": ("mean novelty, SGD 6e-3 (Table 3.2)", lambda c: c, {}),
    "qdax-novelty": (
        "QDax's scorer: mean squared distance, K = 5",
        lambda c: dataclasses.replace(adam(c), archive_k=5),
        {"novelty_reduction": "mean_squared"},
    ),
    "qdax-greedy": (
        "QDax's coupling: greedy actors trained and played",
        adam,
        {"coupling": "qdax"},
    ),
    "exploration-noise": (
        "the population plays with Gaussian noise 0.1",
        adam,
        {"exploration_noise": 0.1},
    ),
}
# diagnostics of an exiting reading: outside the early stop, run only when named
DIAGNOSTICS: dict[str, tuple[str, Callable[[QDPGConfig], QDPGConfig], dict[str, Any]]] = {
    "squared-k10": (
        "QDax's squared distance at the thesis's K = 10 (which of qdax-novelty's two "
        "differences makes it exit)",
        adam,
        {"novelty_reduction": "mean_squared"},
    ),
}


def load(path: Path) -> dict[str, Any]:
    if path.exists():
        return json.loads(path.read_text())
    return {"rule": __doc__.split("THE RULE")[1].split("Resumable:")[0].strip(), "rows": []}


def seed_rows(variant: str, seeds: list[int], result, parts: tuple[str, ...], wall: float):
    """One row per seed of a finished pair."""
    descriptors = np.asarray(result.history["descriptors"])  # seeds x iterations x N x 2
    stats = {k: np.asarray(result.history[k]) for k in ("critic_loss_q", "critic_loss_d",
             "critic_grad_norm_q", "critic_grad_norm_d", "actor_grad_norm")}  # fmt: skip
    rows = []
    for i, (seed, div) in enumerate(
        zip(seeds, health.divergences(result.history["nan_parts"], parts))
    ):
        end = div.iteration if div else descriptors.shape[1]
        finals = descriptors[i, :end].reshape(-1, 2)
        exit_steps = result.exit_steps[i]
        rows.append(
            {
                "variant": variant,
                "seed": seed,
                "reached_exit": bool(not np.isnan(exit_steps)),
                "steps_to_exit": None if np.isnan(exit_steps) else float(exit_steps),
                "final_performance": None if div else float(result.final_performance[i]),
                "share_above_upper_wall": float(np.mean(finals[:, 1] > UPPER_WALL_TOP)),
                "coverage": None if div else float(result.coverage[i]),
                "diverged": None
                if div is None
                else {"iteration": div.iteration, "parts": div.parts},
                # every 25th iteration's update statistics, and the 10 before a divergence
                "statistics_every_25": {k: v[i, ::25].tolist() for k, v in stats.items()},
                "statistics_before_divergence": (
                    {k: v[i, max(0, end - 10) : end + 1].tolist() for k, v in stats.items()}
                    if div
                    else None
                ),
                "best_return_every_25": {
                    "steps": result.cumulative_steps[i, ::25].tolist(),
                    "values": np.asarray(result.history["max_fitness"][i, ::25]).tolist(),
                },
                "env_steps": float(result.env_steps[i]),
                "pair_wall_seconds": wall,
                "seconds_per_iteration": result.steady_seconds_per_iteration,
            }
        )
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--variants", nargs="+", default=list(VARIANTS), choices=[*VARIANTS, *DIAGNOSTICS]
    )
    parser.add_argument("--steps", type=int, default=1_000_000)
    parser.add_argument("--seeds", type=int, default=4)
    parser.add_argument("--out", type=Path, default=RESULTS, help="(a trial run's results)")
    args = parser.parse_args()
    if args.seeds % 2:
        raise SystemExit("--seeds must be even: the seeds run two side by side")
    out = load(args.out)
    base = table_3_2(args.steps)
    env = make_task_env(base, "pointmaze")
    for variant in args.variants:
        earlier = list(VARIANTS)[: list(VARIANTS).index(variant)] if variant in VARIANTS else []
        if variant not in ALWAYS and any(reading_exits(out, v) for v in earlier):
            print(f"{variant}: skipped, an earlier reading exits (the rule's early stop)")
            continue
        what, make_cfg, fields = {**VARIANTS, **DIAGNOSTICS}[variant]
        cfg = make_cfg(base)
        algo = dataclasses.replace(build_algorithms(cfg, "pointmaze", env)["QD-PG"], **fields)
        first = 0
        # the rule: a verdict one seed from changing after 4 seeds gets seeds 4-5
        while first < args.seeds or (
            first == READING_MIN_SEEDS and reading_needs_more_seeds(out, variant)
        ):
            seeds, first = [first, first + 1], first + 2
            if any(r["variant"] == variant and r["seed"] in seeds for r in out["rows"]):
                continue
            what_runs = f"{variant} {config_hash(cfg)} {sorted(fields.items())}"
            digest = hashlib.sha256(what_runs.encode()).hexdigest()[:16]
            checkpoint.activate(
                checkpoint.CheckpointPolicy(
                    CHECKPOINTS, digest, seeds[0], code_version(), every_seconds=300
                )
            )
            keys = np.stack([jax.random.fold_in(jax.random.PRNGKey(0), s) for s in seeds])
            start = time.perf_counter()
            result = run_method(
                cfg, "pointmaze", env, algo, keys, progress=True, desc=f"ab {variant} {seeds}"
            )
            wall = time.perf_counter() - start
            parts = health.part_names(jax.eval_shape(algo.init, jax.random.PRNGKey(0))[0])
            out["rows"] += seed_rows(variant, seeds, result, parts, wall)
            out.setdefault("variants", {})[variant] = what
            out["steps"] = args.steps
            out = write_result(args.out, out)  # (the provenance of the pair that finished last)
            print(f"{variant} seeds {seeds}: {wall:.0f} s, wrote {args.out}", flush=True)
            checkpoint.activate(None)


if __name__ == "__main__":
    main()
