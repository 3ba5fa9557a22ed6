"""QD-PG on Point-Maze: wall time and environment steps per second, split into
evaluation (episodes, insertion, buffer and archive writes), novelty (the fresh
novelty rewards of every diversity actor's batches), critic steps and actor steps
(the thesis's coupling interleaves them: ``qdnb.qd.qdpg``).  Writes
``bench/results/qdpg.json``.

    python bench/qdpg.py [--scale small] [--iterations 40]

Each part is one jitted function timed on the same warmed-up state, so the
parts add up to about one iteration; the novelty part scores every critic batch
of an iteration in one pass, as the coupled updates do; the actor steps are timed alone
(the iteration's policy-gradient steps of every actor against a fixed critic) and
the critic steps are the coupled updates less novelty and actor steps.  The whole loop is
timed two ways: compiled once as a single ``lax.scan`` (the steady rate,
extrapolated to the scale's budget), and as the notebook runs it, through
``run_seeds`` on the notebook's QD-PG seeds (``vmap``, jitted chunks) for the
scale's whole budget, whose median chunk after the first is its rate, the
statistic the notebook reports.  The notebook's rate should be within 15 %
of it.  The same run on one seed says what the ``vmap`` over seeds costs per
seed (1.0: the seeds cost what they would one after the other).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

import jax
import optax

from qdnb.book.registry import config
from qdnb.chapters.ch3_qdpg import build_algorithms, steady_rate
from qdnb.qd.algorithms import run_seeds


def timed(fn, *args, repeats: int = 5) -> float:
    jax.block_until_ready(fn(*args))
    start = time.perf_counter()
    for _ in range(repeats):
        jax.block_until_ready(fn(*args))
    return (time.perf_counter() - start) / repeats


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scale", default="small")
    parser.add_argument("--iterations", type=int, default=40)
    args = parser.parse_args()
    cfg = config("ch3_qdpg", args.scale)
    task = cfg.pointmaze
    algo = build_algorithms(cfg, "pointmaze")["QD-PG"]

    state, _ = jax.jit(algo.init)(jax.random.PRNGKey(0))
    step = jax.jit(algo.step)
    for _ in range(15):  # warm up: a buffer and an archive of 15 iterations
        state, _ = step(state)
    # Time on a buffer of its mid-run size: a batch drawn from 12,000 transitions
    # stays in the caches, one drawn from half a million does not (the early-run
    # rate would flatter the loop; the slots past the written ones hold zeros,
    # which cost the same).
    mid_run = min(state.buffer.capacity, task.num_steps // 2)
    state = state.replace(
        buffer=state.buffer.replace(size=jax.numpy.asarray(mid_run, jax.numpy.int32))
    )
    key = jax.random.PRNGKey(1)
    parents = jax.tree.map(lambda x: x[: task.num_actors], state.repertoire.genotypes)
    diversity = jax.numpy.arange(task.num_actors) < task.num_actors // 2

    def evaluation(s, k):
        rep, ev = algo.evaluate_and_insert(s.repertoire, parents, k)
        return rep, algo._record(s.buffer, s.archive, ev)

    n, steps, delay = task.num_actors, task.num_critic_steps, cfg.policy_delay

    def iteration_batches(s, k):
        rows = s.buffer.sample(k, steps * n * cfg.td3_batch_size)
        return jax.tree.map(lambda x: x.reshape((steps, n, cfg.td3_batch_size) + x.shape[1:]), rows)

    def novelty(s, k):
        return algo.actor_rewards(s.archive, iteration_batches(s, k), diversity)

    def updates(s, k):
        return algo.coupled_updates(s, parents, diversity, k)

    def actor_steps(s, k):
        obs = iteration_batches(s, k)["obs"][delay - 1 :: delay]  # one batch per actor step
        td3, opt = algo.td3, algo.td3.mutation_optimizer

        def one(carry, o):
            actors, opts = carry
            grads = jax.vmap(jax.grad(td3.actor_loss), in_axes=(0, None, 0))(
                actors, s.q_critic.critic, o
            )
            updates, opts = jax.vmap(opt.update)(grads, opts)
            return (optax.apply_updates(actors, updates), opts), None

        return jax.lax.scan(one, (parents, jax.vmap(opt.init)(parents)), obs)[0]

    parts = {
        name: timed(jax.jit(fn), state, key)
        for name, fn in (
            ("evaluation", evaluation),
            ("novelty", novelty),
            ("updates", updates),
            ("actor_steps", actor_steps),
        )
    }
    # the coupled updates compute the novelty rewards and the actor steps: the rest is critics
    parts["critic_steps"] = max(parts.pop("updates") - parts["novelty"] - parts["actor_steps"], 0.0)
    steps_per_iteration = task.num_actors * task.episode_length

    # Through run_seeds on the notebook's QD-PG seeds, with the notebook's statistic: the median
    # chunk after the first (which compiles).
    # The same on one seed: what the vmap over seeds costs per seed.
    def through_run_seeds(num_seeds):
        chunks = []
        start = time.perf_counter()
        _, _, history = run_seeds(
            algo,
            jax.random.split(key, num_seeds),
            task.num_iterations - 1,
            cfg.chunk_size,
            progress=False,
            chunk_seconds=chunks,
        )
        jax.block_until_ready(history)
        seconds = time.perf_counter() - start
        return steady_rate(chunks, cfg.chunk_size, seconds / task.num_iterations), seconds

    seeds = cfg.seeds("pointmaze", "QD-PG")
    run_seeds_per_iteration, loop = through_run_seeds(seeds)
    one_seed_per_iteration, _ = (
        through_run_seeds(1) if seeds > 1 else (run_seeds_per_iteration, loop)
    )
    # The steady rate: one compiled scan of the same iterations, timed on its second call.
    scan = jax.jit(
        lambda s: jax.lax.scan(lambda c, _: algo.step(c), s, None, length=args.iterations)
    )
    jax.block_until_ready(scan(state))
    start = time.perf_counter()
    _, evs = scan(state)
    jax.block_until_ready(evs)
    steady = time.perf_counter() - start
    env_steps = int(evs.length.sum())

    per_iteration = steady / args.iterations
    result = {
        "scale": args.scale,
        "device": jax.devices()[0].device_kind,
        "machine": platform.processor() or platform.machine(),
        "cpu_count": os.cpu_count(),
        "num_actors": task.num_actors,
        "episode_length": task.episode_length,
        "num_critic_steps": task.num_critic_steps,
        "coupling": algo.coupling,
        "actor_steps_per_mutation": task.num_critic_steps // cfg.policy_delay,
        "archive_size": task.archive_size,
        "archive_threshold": task.archive_threshold,
        "archive_entries_at_timing": int(state.archive.size),
        "buffer_size_at_timing": mid_run,
        "td3_batch_size": cfg.td3_batch_size,
        "seconds_per_iteration_parts": parts,
        "fraction_of_parts": {k: v / sum(parts.values()) for k, v in parts.items()},
        "iterations": args.iterations,
        "run_seeds_seconds_with_compile": loop,
        "loop_seconds_steady": steady,
        "steady_seconds_per_iteration": per_iteration,
        "run_seeds_num_seeds": seeds,
        "run_seeds_iterations": task.num_iterations,
        "run_seeds_seconds_per_iteration": run_seeds_per_iteration,
        "run_seeds_over_steady": run_seeds_per_iteration / per_iteration,
        "run_seeds_one_seed_seconds_per_iteration": one_seed_per_iteration,
        "vmap_cost_per_seed_over_one_seed": run_seeds_per_iteration
        / (seeds * one_seed_per_iteration),
        "env_steps_per_second": env_steps / steady,
        "scale_budget_steps": task.num_steps,
        "projected_seconds_for_scale_budget": per_iteration * task.num_iterations,
        "projected_seconds_for_1e6_steps": per_iteration * 1_000_000 / steps_per_iteration,
        # the notebook's way: its QD-PG seeds at once over the devices, per seed of 10^6 steps
        "run_seeds_seconds_for_1e6_steps_all_seeds": run_seeds_per_iteration
        * 1_000_000
        / steps_per_iteration,
        "run_seeds_seconds_per_seed_for_1e6_steps": run_seeds_per_iteration
        * 1_000_000
        / steps_per_iteration
        / seeds,
        "devices": len(jax.devices()),
    }
    out = Path(__file__).parent / "results" / "qdpg.json"
    out.parent.mkdir(exist_ok=True)
    out.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
