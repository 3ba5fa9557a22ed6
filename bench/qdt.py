"""Quality-Diversity Transformer on Ant-Omni (250-step episodes): training
throughput and evaluation-rollout speed, with and without the key/value cache.

1. Training: tokens per second (3 tokens per timestep x 250 timesteps x batch
   size) of the jitted train step (``make_train_step(model,
   make_optimizer(lr))``, dropout on) on a synthetic batch of trajectories,
   compilation timed apart, median over the repeats; the same step with
   dropout 0 is timed too, since drawing the dropout masks (the attention
   weights' above all) is a large share of a step on CPU.
2. Evaluation: ``play(..., cached=True)`` (one timestep's new tokens per step,
   reusing the keys and values of the earlier ones) against ``play(...,
   cached=False)`` (the whole prefix recomputed every step), same parameters,
   goals (a CVT of the descriptor space) and key, both jitted; compile time apart
   from the median run time, environment steps per second, the speed-up
   cached/full (target: at least 5x) and the largest differences between the
   actions and descriptors the two give (reported, not asserted).  The physics
   amplifies float rounding over 250 steps, so closed-loop rollouts drift apart
   after a few dozen steps even when the two passes agree; the step where the
   actions first differ by more than 1e-4 is reported, and so is an open-loop
   check: the cached passes (``prefill`` then ``decode_step``) fed the synthetic
   batch's trajectories against one teacher-forced forward pass.

The model is the scale's (``config("ch4_qdt", scale)``: embedding size, layers,
heads, dropout, batch size, learning rate).  Writes ``bench/results/qdt.json``.

    python bench/qdt.py [--scale small] [--goals 8] [--episodes 1]
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import jax
import jax.numpy as jnp

from qdnb.book.provenance import device, versions
from qdnb.book.registry import config
from qdnb.core.io import atomic_write_json
from qdnb.envs import make_env
from qdnb.models.qdt.data import Trajectories
from qdnb.models.qdt.evaluate import play
from qdnb.models.qdt.model import QDT, TOKENS_PER_STEP, init_params
from qdnb.models.qdt.train import make_train_step
from qdnb.nets.transformer import make_optimizer
from qdnb.qd.cvt import cvt_centroids

EPISODE_LENGTH = 250  # Chapter 4's Ant-Omni episodes


def synthetic_batch(key: jax.Array, batch: int, env) -> Trajectories:
    """Random trajectories of the dataset's shapes: every step valid."""
    k_obs, k_act, k_bd, k_fit = jax.random.split(key, 4)
    low, high = jnp.asarray(env.descriptor_low), jnp.asarray(env.descriptor_high)
    return Trajectories(
        bd=jax.random.uniform(k_bd, (batch, env.descriptor_size), minval=low, maxval=high),
        obs=jax.random.normal(k_obs, (batch, EPISODE_LENGTH, env.observation_size)),
        actions=jax.random.uniform(
            k_act, (batch, EPISODE_LENGTH, env.action_size), minval=-1.0, maxval=1.0
        ),
        valid=jnp.ones((batch, EPISODE_LENGTH), bool),
        fitness=jax.random.normal(k_fit, (batch,)),
        policy=jnp.arange(batch, dtype=jnp.int32),
    )


def teacher_forced_difference(model, params, batch: Trajectories) -> float:
    """Largest difference between the actions of one full forward pass and of the
    cached passes fed the same trajectories one timestep at a time."""

    def cached(params, batch):
        cache = model.apply(params, batch.obs.shape[0], method=QDT.init_cache)
        first, cache = model.apply(params, batch.bd, batch.obs[:, 0], cache, method=QDT.prefill)

        def body(cache, t):
            out, cache = model.apply(
                params,
                batch.bd,
                batch.actions[:, t - 1],
                batch.obs[:, t],
                t,
                cache,
                method=QDT.decode_step,
            )
            return cache, out

        _, rest = jax.lax.scan(body, cache, jnp.arange(1, batch.obs.shape[1]))
        return jnp.concatenate([first[:, None], rest.swapaxes(0, 1)], axis=1)

    full = jax.jit(lambda p, b: model.apply(p, b.bd, b.obs, b.actions))(params, batch)
    return float(jnp.max(jnp.abs(jax.jit(cached)(params, batch) - full)))


def bench_training(model, params, batch, learning_rate, key, repeats):
    """Compile time and median seconds of one train step (the parameters and
    optimiser state carried from step to step, as in training)."""
    optimizer = make_optimizer(learning_rate)
    step = make_train_step(model, optimizer)
    opt_state = optimizer.init(params)
    start = time.perf_counter()
    compiled = step.lower(params, opt_state, batch, key).compile()
    compile_s = time.perf_counter() - start
    params, opt_state, loss = jax.block_until_ready(
        compiled(params, opt_state, batch, key)
    )  # warm-up
    times = []
    for i in range(repeats):
        k = jax.random.fold_in(key, i)
        start = time.perf_counter()
        params, opt_state, loss = jax.block_until_ready(compiled(params, opt_state, batch, k))
        times.append(time.perf_counter() - start)
    return compile_s, times, float(loss)


def bench_rollouts(env, model, params, goals, key, num_episodes, repeats):
    """Compile both rollouts, then time them interleaved (so that machine noise
    hits both alike) on the same parameters and key; returns the compile times,
    the run times and the last outputs of each."""
    compiled, compile_s = {}, {}
    for name, cached in (("cached", True), ("full", False)):
        fn = jax.jit(
            lambda p, k, cached=cached: play(env, model, p, goals, k, num_episodes, cached=cached)
        )
        start = time.perf_counter()
        compiled[name] = fn.lower(params, key).compile()
        compile_s[name] = time.perf_counter() - start
    outputs = {
        name: jax.block_until_ready(c(params, key)) for name, c in compiled.items()
    }  # warm-up
    times = {name: [] for name in compiled}
    for _ in range(repeats):
        for name, c in compiled.items():
            start = time.perf_counter()
            outputs[name] = jax.block_until_ready(c(params, key))
            times[name].append(time.perf_counter() - start)
    return compile_s, times, outputs


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scale", default="small")
    parser.add_argument("--train-repeats", type=int, default=20)
    parser.add_argument(
        "--goals", type=int, default=8, help="goals of the rollout comparison (a CVT)"
    )
    parser.add_argument(
        "--episodes", type=int, default=1, help="episodes per goal of the rollout comparison"
    )
    parser.add_argument("--rollout-repeats", type=int, default=3)
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "qdt.json")
    args = parser.parse_args()
    cfg = config("ch4_qdt", args.scale)

    env = make_env("ant_omni", episode_length=EPISODE_LENGTH)
    model = QDT(
        env.action_size, EPISODE_LENGTH, cfg.embed_dim, cfg.num_layers, cfg.num_heads, cfg.dropout
    )
    k_init, k_batch, k_train, k_goals, k_play = jax.random.split(jax.random.PRNGKey(0), 5)
    params = init_params(model, k_init, env.descriptor_size, env.observation_size)
    num_params = sum(x.size for x in jax.tree.leaves(params))

    # 1. training throughput
    batch = synthetic_batch(k_batch, cfg.batch_size, env)
    tokens = TOKENS_PER_STEP * EPISODE_LENGTH * cfg.batch_size
    train_compile, train_times, loss = bench_training(
        model, params, batch, cfg.learning_rate, k_train, args.train_repeats
    )
    train_s = statistics.median(train_times)
    no_dropout = model.clone(dropout=0.0)
    _, no_dropout_times, _ = bench_training(
        no_dropout, params, batch, cfg.learning_rate, k_train, args.train_repeats
    )
    no_dropout_s = statistics.median(no_dropout_times)
    print(
        f"training: batch {cfg.batch_size} x {TOKENS_PER_STEP * EPISODE_LENGTH} tokens, "
        f"{train_s * 1e3:.1f} ms/step, {tokens / train_s:,.0f} tokens/s (compile "
        f"{train_compile:.1f} s); "
        f"without dropout {no_dropout_s * 1e3:.1f} ms/step, {tokens / no_dropout_s:,.0f} tokens/s"
    )

    # 2. evaluation rollouts, cached against full recomputation
    low, high = env.descriptor_low, env.descriptor_high
    goals = cvt_centroids(k_goals, args.goals, low, high, cfg.cvt_samples, cfg.cvt_iterations)
    play_compile, play_times, outputs = bench_rollouts(
        env, model, params, goals, k_play, args.episodes, args.rollout_repeats
    )
    env_steps = args.goals * args.episodes * EPISODE_LENGTH
    rollout = {}
    for name in ("cached", "full"):
        seconds = statistics.median(play_times[name])
        rollout[name] = {
            "compile_seconds": play_compile[name],
            "seconds_per_rollout": seconds,
            "run_seconds": play_times[name],
            "env_steps_per_second": env_steps / seconds,
        }
    speedup = rollout["full"]["seconds_per_rollout"] / rollout["cached"]["seconds_per_rollout"]
    cached, full = outputs["cached"], outputs["full"]
    per_step = jnp.max(jnp.abs(cached.trajectory - full.trajectory), axis=(0, 1, 3))  # (T,)
    drift = jnp.flatnonzero(per_step > 1e-4)
    agreement = {
        "teacher_forced_max_abs_action_difference": teacher_forced_difference(model, params, batch),
        "max_abs_action_difference_first_step": float(per_step[0]),
        "max_abs_action_difference_first_10_steps": float(jnp.max(per_step[:10])),
        "first_step_action_difference_above_1e-4": int(drift[0]) if drift.size else None,
        "max_abs_action_difference": float(jnp.max(jnp.abs(cached.trajectory - full.trajectory))),
        "max_abs_descriptor_difference": float(
            jnp.max(jnp.abs(cached.descriptor - full.descriptor))
        ),
        "max_abs_fitness_difference": float(jnp.max(jnp.abs(cached.fitness - full.fitness))),
        "same_lengths": bool(jnp.all(cached.length == full.length)),
    }
    for name in ("cached", "full"):
        r = rollout[name]
        print(
            f"play {name:>6}: {r['seconds_per_rollout']:.3f} s per rollout of {args.goals} x "
            f"{args.episodes} "
            f"x {EPISODE_LENGTH} steps, {r['env_steps_per_second']:,.0f} env steps/s "
            f"(compile {r['compile_seconds']:.1f} s)"
        )
    print(f"speed-up cached vs full: {speedup:.1f}x (target >= 5x)")
    print(
        "agreement: teacher-forced max |action diff| "
        f"{agreement['teacher_forced_max_abs_action_difference']:.1e}; "
        "rollouts: max |action diff| first 10 steps "
        f"{agreement['max_abs_action_difference_first_10_steps']:.1e}, "
        f"first step above 1e-4: {agreement['first_step_action_difference_above_1e-4']}, "
        f"over the episode {agreement['max_abs_action_difference']:.2e} (actions), "
        f"{agreement['max_abs_descriptor_difference']:.2e} (descriptors)"
    )

    atomic_write_json(
        args.out,
        {
            "benchmark": "QDT training throughput and cached vs full-recomputation rollouts on "
            "ant_omni",
            "device": device(),
            "versions": versions(),
            "scale": args.scale,
            "config": {
                "embed_dim": cfg.embed_dim,
                "num_layers": cfg.num_layers,
                "num_heads": cfg.num_heads,
                "dropout": cfg.dropout,
                "batch_size": cfg.batch_size,
                "learning_rate": cfg.learning_rate,
                "episode_length": EPISODE_LENGTH,
                "observation_size": env.observation_size,
                "action_size": env.action_size,
                "descriptor_size": env.descriptor_size,
                "num_parameters": int(num_params),
            },
            "training": {
                "tokens_per_step": tokens,
                "compile_seconds": train_compile,
                "seconds_per_step": train_s,
                "step_seconds": train_times,
                "tokens_per_second": tokens / train_s,
                "repeats": args.train_repeats,
                "last_loss": loss,
                "without_dropout": {
                    "seconds_per_step": no_dropout_s,
                    "step_seconds": no_dropout_times,
                    "tokens_per_second": tokens / no_dropout_s,
                },
            },
            "rollout": {
                "goals": args.goals,
                "episodes_per_goal": args.episodes,
                "env_steps_per_rollout": env_steps,
                "repeats": args.rollout_repeats,
                **rollout,
                **agreement,
            },
            "speedup_cached_vs_full": speedup,
        },
    )


if __name__ == "__main__":
    main()
