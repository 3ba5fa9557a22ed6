"""Why Ant-Omni's elites end their episodes early: a diagnosis of the `small`
Chapter 4 run (issue 15).

Ant-Omni follows QDax's task where the thesis is silent, so an episode ends when
the torso leaves the healthy band [0.2, 1.0].  With the thesis's Eq. 4.2 alone,
-sum_t ||a_t|| over the steps played, an episode that ends early spends less
energy and scores higher; the first record of this script (commit 743cd22) found
56-71 % of the elites' episodes ending early.  The task now keeps brax's survival
reward, as QDax's does (``qdnb.envs.locomotion``): an episode that ends early
forfeits one per step not lived.  This script measures how often episodes end
early and why:

1. **Elites.**  Every stored policy of the final Ant-Omni repertoires that the
   Chapter 4 notebook saved at the scale (all methods, all seeds) plays
   ``--episodes`` fresh episodes; for each episode: the step it ended at, whether
   the torso went above the band (a bounce) or below it (a fall), and its
   fitness.
2. **Random policies on three brax pipelines.**  ``--random`` freshly
   initialised policies of the scale's width play one 250-step episode each
   (without the termination rule, to see the whole height path) on the
   ``spring`` pipeline the book uses and on ``positional`` and ``generalized``:
   the share whose torso ever leaves the band, and the simulation rate.

Writes ``bench/results/ant_omni_termination.json``.

    python bench/probes/ant_omni_termination.py [--scale small] [--episodes 4] [--random 64]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from qdnb.book.provenance import write_result
from qdnb.book.registry import config
from qdnb.chapters.ch4_qdt import repertoire_path
from qdnb.chapters.ch4_reproducibility import METHODS, load_repertoires
from qdnb.core import paths
from qdnb.core.config import config_hash
from qdnb.envs import make_env
from qdnb.nets.mlp import MLP


def height_path(env, network, params, key, terminate: bool = True):
    """One episode: (end step, highest and lowest torso height while alive, fitness)."""
    state = env.reset(key)
    low, high = env.healthy_z_range

    def body(carry, _):
        s, end, z_max, z_min, fitness = carry
        alive = end < 0
        nxt = env.step(s, network.apply(params, s.obs))
        z = nxt.core.x.pos[0, 2]
        out = nxt.done if terminate else nxt.steps >= env.episode_length
        end = jnp.where(alive & out, nxt.steps, end)
        return (
            nxt,
            end,
            jnp.where(alive, jnp.maximum(z_max, z), z_max),
            jnp.where(alive, jnp.minimum(z_min, z), z_min),
            fitness + jnp.where(alive, nxt.reward, 0.0),
        ), None

    init = (state, jnp.int32(-1), jnp.float32(-jnp.inf), jnp.float32(jnp.inf), jnp.float32(0.0))
    (_, end, z_max, z_min, fitness), _ = jax.lax.scan(body, init, None, length=env.episode_length)
    return end, z_max > high, z_min < low, fitness + env.fitness_shift


def elites(scale: str, episodes: int, key: jax.Array) -> dict:
    cfg = config("ch4_reproducibility", scale)
    env = cfg.make_env("ant_omni")
    network = MLP(cfg.policy_hidden + (env.action_size,))
    play = jax.jit(jax.vmap(lambda p, k: height_path(env, network, p, k)))
    out = {}
    for name in METHODS:
        path = repertoire_path(scale, "ant_omni", name)
        arrays = load_repertoires(path, config_hash(cfg))
        if arrays is None:
            raise SystemExit(
                f"{path} is missing or from another config: run the Chapter 4 notebook at {scale} "
                "first"
            )
        seeds, cells = np.nonzero(np.isfinite(arrays["fitnesses"]))
        params = jax.tree.map(
            lambda x: jnp.repeat(jnp.asarray(x[seeds, cells]), episodes, axis=0),
            arrays["genotypes"],
        )
        end, above, below, fitness = map(
            np.asarray,
            play(
                params, jax.random.split(jax.random.fold_in(key, len(out)), seeds.size * episodes)
            ),
        )
        early = end < env.episode_length
        out[name] = {
            "elites": int(seeds.size),
            "episodes": int(end.size),
            "ended_early": float(early.mean()),
            "above_band": float((early & above).mean()),
            "below_band": float((early & below).mean()),
            "median_end_step_of_early": float(np.median(end[early])) if early.any() else None,
            "fitness_early": float(fitness[early].mean()) if early.any() else None,
            "fitness_full": float(fitness[~early].mean()) if (~early).any() else None,
            "elites_with_an_early_end": float(early.reshape(-1, episodes).any(1).mean()),
        }
        print(name, out[name], flush=True)
    run_dir = paths.run_dir(scale, "ch4_reproducibility", create=False)
    return {
        "run": str(run_dir.relative_to(paths.ROOT)),
        "episodes_per_elite": episodes,
        "methods": out,
    }


def pipelines(scale: str, count: int, key: jax.Array) -> dict:
    cfg = config("ch4_reproducibility", scale)
    out = {}
    for backend in ("spring", "positional", "generalized"):
        env = make_env("ant_omni", episode_length=cfg.episode_length, backend=backend)
        network = MLP(cfg.policy_hidden + (env.action_size,))
        keys = jax.random.split(key, count)
        params = jax.vmap(lambda k: network.init(k, jnp.zeros(env.observation_size)))(keys)
        play = jax.jit(jax.vmap(lambda p, k: height_path(env, network, p, k, terminate=False)))
        jax.block_until_ready(play(params, keys))
        start = time.time()
        _, above, below, _ = map(np.asarray, play(params, keys))
        seconds = time.time() - start
        out[backend] = {
            "ever_above_band": float(above.mean()),
            "ever_below_band": float(below.mean()),
            "steps_per_second": count * cfg.episode_length / seconds,
        }
        print(backend, out[backend], flush=True)
    return {
        "policies": count,
        "note": "one episode each, the termination rule off; NaN heights count as neither",
        "pipelines": out,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scale", default="small")
    parser.add_argument("--episodes", type=int, default=4)
    parser.add_argument("--random", type=int, default=64)
    parser.add_argument(
        "--out",
        type=Path,
        default=Path(__file__).parents[1] / "results" / "ant_omni_termination.json",
    )
    args = parser.parse_args()
    key = jax.random.PRNGKey(2_000)
    out = {
        "benchmark": "Ant-Omni: episodes that end early, and why",
        "scale": args.scale,
        "elites": elites(args.scale, args.episodes, jax.random.fold_in(key, 0)),
        "random_policies": pipelines(args.scale, args.random, jax.random.fold_in(key, 1)),
    }
    write_result(args.out, out)
    print("wrote", args.out)


if __name__ == "__main__":
    main()
