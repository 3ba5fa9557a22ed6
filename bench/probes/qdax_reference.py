"""MAP-Elites in QDax 0.5.0 on brax v1, timed the way ``bench/qd_throughput.py``
times ours: environment steps per second of one jitted iteration (median of
``--repeats``), at the same setting (batch 128, 100-step episodes, 256 CVT cells,
MLP 64 x 64 with relu hidden layers and a tanh output, isoline variation with
iso_sigma 0.005 and line_sigma 0.05), on Ant-Omni and Halfcheetah-Uni.

The project never imports QDax: this script runs in a scratch environment of its
own, outside the project (issue 36), e.g.

    python3.11 -m venv /tmp/qdaxenv
    /tmp/qdaxenv/bin/pip install qdax==0.5.0 jax==0.4.28 jaxlib==0.4.28 brax==0.10.4 \\
        flax==0.8.5 mujoco==3.1.6 mujoco-mjx==3.1.6
    /tmp/qdaxenv/bin/python bench/probes/qdax_reference.py

Writes ``bench/results/qdax_reference.json``.
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import platform
import statistics
import time
from pathlib import Path

import jax
import jax.numpy as jnp


def steps_per_second(env_name: str, batch: int, episode_length: int, repeats: int) -> dict:
    import qdax
    import qdax.tasks.brax.v1 as environments
    from qdax.core.containers.mapelites_repertoire import compute_cvt_centroids
    from qdax.core.emitters.mutation_operators import isoline_variation
    from qdax.core.emitters.standard_emitters import MixingEmitter
    from qdax.core.map_elites import MAPElites
    from qdax.core.neuroevolution.buffers.buffer import QDTransition
    from qdax.core.neuroevolution.networks.networks import MLP
    from qdax.tasks.brax.v1.env_creators import scoring_function_brax_envs
    from qdax.utils.metrics import default_qd_metrics

    env = environments.create(env_name, episode_length=episode_length)
    policy = MLP(
        layer_sizes=(64, 64, env.action_size),
        kernel_init=jax.nn.initializers.lecun_uniform(),
        final_activation=jnp.tanh,
    )  # relu hidden layers: QDax's default
    key = jax.random.key(0)
    key, k_init = jax.random.split(key)
    params = jax.vmap(policy.init)(
        jax.random.split(k_init, batch), jnp.zeros((batch, env.observation_size))
    )

    def play_step(env_state, policy_params, key):
        actions = policy.apply(policy_params, env_state.obs)
        nxt = env.step(env_state, actions)
        transition = QDTransition(
            obs=env_state.obs,
            next_obs=nxt.obs,
            rewards=nxt.reward,
            dones=nxt.done,
            actions=actions,
            truncations=nxt.info["truncation"],
            state_desc=env_state.info["state_descriptor"],
            next_state_desc=nxt.info["state_descriptor"],
        )
        return nxt, policy_params, key, transition

    scoring = functools.partial(
        scoring_function_brax_envs,
        episode_length=episode_length,
        play_reset_fn=jax.jit(env.reset),
        play_step_fn=play_step,
        descriptor_extractor=environments.descriptor_extractor[env_name],
    )
    emitter = MixingEmitter(
        mutation_fn=lambda x, y: (x, y),
        variation_fn=functools.partial(isoline_variation, iso_sigma=0.005, line_sigma=0.05),
        variation_percentage=1.0,
        batch_size=batch,
    )
    me = MAPElites(
        scoring_function=scoring,
        emitter=emitter,
        metrics_function=functools.partial(
            default_qd_metrics, qd_offset=environments.reward_offset[env_name] * episode_length
        ),
    )
    low, high = env.descriptor_limits
    key, k_cvt, k_me = jax.random.split(key, 3)
    centroids = compute_cvt_centroids(
        num_descriptors=env.descriptor_length,
        num_init_cvt_samples=5000,
        num_centroids=256,
        minval=low,
        maxval=high,
        key=k_cvt,
    )
    repertoire, emitter_state, _ = me.init(params, centroids, k_me)
    update = jax.jit(me.update)
    times = []
    for i in range(repeats + 1):  # the first call compiles
        key, k = jax.random.split(key)
        start = time.perf_counter()
        repertoire, emitter_state, metrics = update(repertoire, emitter_state, k)
        jax.block_until_ready(metrics)
        if i:
            times.append(time.perf_counter() - start)
    t = statistics.median(times)
    return {
        "environment": env_name,
        "algorithm": "ME",
        "episodes_per_iteration": batch,
        "episode_length": episode_length,
        "seconds_per_iteration": t,
        "loop_steps_per_second": batch * episode_length / t,
        "qdax": qdax.__version__ if hasattr(qdax, "__version__") else "0.5.0",
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--envs", nargs="+", default=["ant_omni", "halfcheetah_uni"])
    parser.add_argument("--batch", type=int, default=128)
    parser.add_argument("--episode-length", type=int, default=100)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument(
        "--out", type=Path, default=Path(__file__).parents[1] / "results" / "qdax_reference.json"
    )
    args = parser.parse_args()
    rows = []
    for env_name in args.envs:
        rows.append(steps_per_second(env_name, args.batch, args.episode_length, args.repeats))
        print(rows[-1], flush=True)
    import brax

    out = {
        "benchmark": "QDax 0.5.0 MAP-Elites on brax v1, steps per second",
        "device": f"{jax.devices()[0].platform} x{jax.device_count()} ({os.cpu_count()} CPU cores)",
        "processor": platform.processor() or platform.machine(),
        "versions": {"jax": jax.__version__, "brax": brax.__version__},
        "batch": args.batch,
        "cells": 256,
        "results": rows,
    }
    args.out.write_text(json.dumps(out, indent=1) + "\n")
    print("wrote", args.out)


if __name__ == "__main__":
    main()
