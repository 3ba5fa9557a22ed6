"""Policy-evaluation throughput on Point-Maze: qdnb's `evaluate_policies` against a
bare `lax.scan` of the environment step and the policy forward pass, same batch.
The target: the evaluation loop (termination masking, return, descriptor) costs at
most 10% more than the bare loop.  A second bare loop gives the noise floor.

Writes bench/results/rollout.json.  Usage: python bench/rollout.py [--batches 256 1024]
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import jax

from qdnb.book.provenance import write_result
from qdnb.core.sharding import shard_batch
from qdnb.envs import make_env
from qdnb.envs.rollout import evaluate_policies
from qdnb.nets.mlp import MLP, init_policies


def bare_scan(env, network):
    """Reset, then step every environment for the full episode: no termination
    masking, no descriptor, no return bookkeeping beyond summing rewards."""

    def run(params, key):
        states = jax.vmap(env.reset)(jax.random.split(key, jax.tree.leaves(params)[0].shape[0]))
        params, states = shard_batch((params, states))  # over every device, as the QD loops

        def step(s, _):
            s = jax.vmap(env.step)(s, jax.vmap(network.apply)(params, s.obs))
            return s, s.reward

        _, rewards = jax.lax.scan(step, states, None, length=env.episode_length)
        return rewards.sum(0)

    return jax.jit(run)


def timed_pair(fns, params, key, repeats):
    """Median wall time of each function, calls interleaved so that machine noise
    hits both alike."""
    for fn in fns:
        jax.block_until_ready(fn(params, key))  # compile
    times = [[] for _ in fns]
    for i in range(repeats):
        k = jax.random.fold_in(key, i)
        for fn, t in zip(fns, times):
            start = time.perf_counter()
            jax.block_until_ready(fn(params, k))
            t.append(time.perf_counter() - start)
    return [statistics.median(t) for t in times]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--batches", type=int, nargs="+", default=[256, 1024])
    parser.add_argument("--repeats", type=int, default=30)
    parser.add_argument(
        "--out", type=Path, default=Path(__file__).parent / "results" / "rollout.json"
    )
    args = parser.parse_args()

    env = make_env("pointmaze")
    network = MLP((16, 16, env.action_size))
    qdnb_eval = jax.jit(lambda p, k: evaluate_policies(env, network.apply, p, k).fitness)
    bare = bare_scan(env, network)
    rows = []
    for batch in args.batches:
        params = init_policies(network, jax.random.PRNGKey(0), batch, env.observation_size)
        key = jax.random.PRNGKey(1)
        # a second, separately compiled bare loop measures the noise of the comparison itself
        t_qdnb, t_bare, t_control = timed_pair(
            [qdnb_eval, bare, bare_scan(env, network)], params, key, args.repeats
        )
        steps = batch * env.episode_length
        rows.append(
            {
                "batch": batch,
                "episode_length": env.episode_length,
                "qdnb_seconds": t_qdnb,
                "bare_seconds": t_bare,
                "qdnb_steps_per_second": steps / t_qdnb,
                "bare_steps_per_second": steps / t_bare,
                "overhead": t_qdnb / t_bare - 1.0,
                "noise_control": t_control / t_bare - 1.0,
            }
        )
        print(
            f"batch {batch}: qdnb {steps / t_qdnb:,.0f} steps/s, bare {steps / t_bare:,.0f} "
            "steps/s, "
            f"overhead {100 * (t_qdnb / t_bare - 1):+.1f}% (bare vs bare: "
            f"{100 * (t_control / t_bare - 1):+.1f}%)"
        )
    write_result(
        args.out,
        {
            "benchmark": "pointmaze policy evaluation",
            "policy": "MLP 2-16-16-2",
            "repeats": args.repeats,
            "results": rows,
        },
    )


if __name__ == "__main__":
    main()
