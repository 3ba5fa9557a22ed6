"""QD-PG on Point-Maze, one iteration split by part, at Table 3.2's settings
(``POINTMAZE_PAPER``) and at the chapter's `small` scale, with its novelty rewards
by brute force (before) and from the spatial index (after), in one run.  Writes
``bench/results/qdpg.json``.

    python bench/qdpg.py [--scales paper small] [--iterations 30]

Per scale and way: one seed is warmed up until its archive is full, its buffer
filled to the size it has mid-run (with copies of its transitions), and each part of an
iteration timed as one jitted function on that state (one seed alone on the machine):

- ``evaluation``: the offspring's episodes, their insertion in the grid, the
  buffer's writes and the archive's one-by-one insertion scan;
- ``sampling``: the iteration's replay batches (critic steps x actors x 256);
- ``novelty``: the fresh novelty rewards of every diversity actor's batches;
- ``actor_steps``: the iteration's policy-gradient steps of every actor;
- ``critic_steps``: the coupled updates less novelty, sampling and actor steps.

Then the loop as the notebook runs it: ``run_seeds`` on two seeds side by side
(one per core) for ``--iterations`` iterations from scratch, whose median chunk
after the first (which compiles) is its rate; from it, the wall time of 10^6
environment steps for the pair and the seeds an hour on this machine's cores.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import optax

from qdnb.book.provenance import write_result
from qdnb.book.registry import config
from qdnb.chapters.ch3_qdpg import build_algorithms, steady_rate
from qdnb.qd.algorithms import run_seeds

WAYS = {"brute force (before)": "brute", "spatial index (after)": "index"}


def timed(fn, *args, repeats: int = 3) -> float:
    jax.block_until_ready(fn(*args))
    start = time.perf_counter()
    for _ in range(repeats):
        jax.block_until_ready(fn(*args))
    return (time.perf_counter() - start) / repeats


def parts(cfg, algo) -> dict[str, float]:
    """Seconds per iteration of each part, on one seed's warmed-up state."""
    task = cfg.pointmaze
    state, _ = jax.jit(algo.init)(jax.random.PRNGKey(0))
    step = jax.jit(algo.step)
    while int(state.archive.num_added) < task.archive_size:  # an archive as full as mid-run
        state, _ = step(state)
    # the buffer at its mid-run size, filled with copies of the transitions it has (slots
    # of zeros would put most sampled states at the origin, which flatters brute force's
    # rival: the index's cost depends on where the states are)
    mid_run = min(state.buffer.capacity, task.num_steps // 2)
    have = int(state.buffer.size)
    rows = jnp.resize(state.buffer.storage[:have], (mid_run, state.buffer.storage.shape[1]))
    storage = state.buffer.storage.at[:mid_run].set(rows)
    state = state.replace(
        buffer=state.buffer.replace(storage=storage, size=jnp.asarray(mid_run, jnp.int32))
    )
    key = jax.random.PRNGKey(1)
    n, steps, delay = algo.num_mutations, task.num_critic_steps, cfg.policy_delay
    parents = jax.tree.map(lambda x: x[:n], state.repertoire.genotypes)
    diversity = jnp.arange(n) < n // 2

    def evaluation(s, k):
        rep, ev = algo.evaluate_and_insert(s.repertoire, parents, k)
        return rep, algo._record(s.buffer, s.archive, ev)

    def sampling(s, k):
        rows = s.buffer.sample(k, steps * n * cfg.td3_batch_size)
        return jax.tree.map(lambda x: x.reshape((steps, n, cfg.td3_batch_size) + x.shape[1:]), rows)

    def novelty(s, k):
        return algo.actor_rewards(s.archive, sampling(s, k), diversity)

    def updates(s, k):
        return algo.coupled_updates(s, parents, diversity, k)

    def actor_steps(s, k):
        obs = sampling(s, k)["obs"][delay - 1 :: delay]  # one batch per actor step
        td3, opt = algo.td3, algo.td3.mutation_optimizer

        def one(carry, o):
            actors, opts = carry
            grads = jax.vmap(jax.grad(td3.actor_loss), in_axes=(0, None, 0))(
                actors, s.q_critic.critic, o
            )
            updates, opts = jax.vmap(opt.update)(grads, opts)
            return (optax.apply_updates(actors, updates), opts), None

        return jax.lax.scan(one, (parents, jax.vmap(opt.init)(parents)), obs)[0]

    out = {
        name: timed(jax.jit(fn), state, key)
        for name, fn in (
            ("evaluation", evaluation),
            ("sampling", sampling),
            ("novelty", novelty),
            ("updates", updates),
            ("actor_steps", actor_steps),
        )
    }
    # the coupled updates sample, score novelty and take the actor steps: the rest is critics
    rest = out.pop("updates") - out["novelty"] - out["actor_steps"]
    out["critic_steps"] = max(rest, 0.0)
    out["novelty"] = max(out["novelty"] - out["sampling"], 0.0)  # novelty includes its sampling
    out["archive_entries"] = int(state.archive.size)
    out["buffer_size"] = mid_run
    return out


def loop(cfg, algo, iterations: int, seeds: int = 2) -> dict[str, float]:
    """The notebook's loop on ``seeds`` seeds side by side, from scratch."""
    chunks: list[float] = []
    start = time.perf_counter()
    _, _, history = run_seeds(
        algo,
        jax.random.split(jax.random.PRNGKey(0), seeds),
        iterations,
        cfg.chunk_size,
        progress=False,
        chunk_seconds=chunks,
    )
    jax.block_until_ready(history)
    seconds = time.perf_counter() - start
    per_iteration = steady_rate(chunks, cfg.chunk_size, seconds / iterations)
    task = cfg.pointmaze
    per_million = per_iteration * 1_000_000 / (task.num_actors * task.episode_length)
    return {
        "seeds_side_by_side": seeds,
        "iterations": iterations,
        "seconds_with_compilation": seconds,
        "seconds_per_iteration": per_iteration,
        "seconds_for_1e6_steps_all_seeds": per_million,
        "seeds_of_1e6_steps_per_hour": seeds * 3600 / per_million,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scales", nargs="+", default=["paper", "small"])
    parser.add_argument("--iterations", type=int, default=30)
    args = parser.parse_args()
    results = {}
    for scale in args.scales:
        cfg = dataclasses.replace(config("ch3_qdpg", scale), chunk_size=5)
        task = cfg.pointmaze
        base = build_algorithms(cfg, "pointmaze", methods=("QD-PG",))["QD-PG"]
        results[scale] = {
            "settings": {
                "num_actors": task.num_actors,
                "num_critic_steps": task.num_critic_steps,
                "actor_steps_per_mutation": task.num_critic_steps // cfg.policy_delay,
                "optimizer": task.optimizer,
                "archive_size": task.archive_size,
                "diversity_queries_per_iteration": task.num_critic_steps
                * (task.num_actors // 2)
                * cfg.td3_batch_size,
            }
        }
        for label, search in WAYS.items():
            algo = dataclasses.replace(base, novelty_search=search)
            row = {"seconds_per_iteration_parts": parts(cfg, algo)}
            row["loop"] = loop(cfg, algo, args.iterations)
            results[scale][label] = row
            print(scale, label, json.dumps(row), flush=True)
        before, after = (results[scale][label]["loop"] for label in WAYS)
        results[scale]["speed_up"] = (
            before["seconds_per_iteration"] / after["seconds_per_iteration"]
        )
    path = Path(__file__).parent / "results" / "qdpg.json"
    write_result(path, results)
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
