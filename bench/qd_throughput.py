"""QD-loop throughput on Chapter 4's tasks: environment steps per second of one
MAP-Elites and one MAP-Elites Low-Spread iteration (selection, variation,
evaluation, insertion) against a bare vmapped `lax.scan` of the same brax
environment and policy with the same number of episodes, in the same run.

Target: the QD loop runs at no less than 90% of the bare simulator's rate.  The
defaults are the setting QDax 0.5.0 was timed at (batch 128, 100-step episodes,
256 cells, MLP 64 x 64); ``--episode-length 250 --batch 64`` is Chapter 4's `small`.
Writes bench/results/qd_throughput.json.  Usage:
    python bench/qd_throughput.py [--envs ant_omni halfcheetah_uni] [--batch 128]
        [--episodes 4] [--episode-length 100]
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

from qdnb.core.sharding import BRAX_CPU_FLAGS, add_xla_flags

if "--xla-default" not in sys.argv:
    add_xla_flags(BRAX_CPU_FLAGS)  # as the Chapter 4 notebook runs its Brax loops

import jax
from rollout import (
    bare_scan,  # bench/rollout.py: the same bare loop, batch taken from the parameters
)

from qdnb.book.provenance import write_result
from qdnb.envs import make_env
from qdnb.nets.mlp import MLP, init_policies
from qdnb.qd.algorithms import MapElitesLowSpread, PolicyMapElites
from qdnb.qd.cvt import cvt_centroids


def median_time(fn, arg, repeats):
    out = fn(arg)
    jax.block_until_ready(out)
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        out = fn(arg)
        jax.block_until_ready(out)
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def measure(env_name: str, args) -> list[dict]:
    """ME's and ME-LS's rows on one environment."""
    env = make_env(env_name, episode_length=args.episode_length)
    network = MLP((64, 64, env.action_size))
    centroids = cvt_centroids(
        jax.random.PRNGKey(0), 256, env.descriptor_low, env.descriptor_high, 5000, 20
    )
    common = dict(env=env, network=network, iso_sigma=0.005, line_sigma=0.05, centroids=centroids)
    rows = []
    for name, algo, episodes in [
        ("ME", PolicyMapElites(**common, batch_size=args.batch), 1),
        (
            "ME-LS",
            MapElitesLowSpread(
                **common, batch_size=args.batch // args.episodes, num_episodes=args.episodes
            ),
            args.episodes,
        ),
    ]:
        state, _ = jax.jit(algo.init)(jax.random.PRNGKey(1))
        step = jax.jit(lambda s: algo.step(s)[0])
        t_loop = median_time(step, state, args.repeats)
        n = algo.batch_size * episodes
        bare = bare_scan(env, network)
        params = init_policies(network, jax.random.PRNGKey(2), n, env.observation_size)
        t_bare = median_time(lambda k: bare(params, k), jax.random.PRNGKey(3), args.repeats)
        steps = n * env.episode_length
        rows.append(
            {
                "environment": env_name,
                "algorithm": name,
                "episodes_per_iteration": n,
                "episode_length": env.episode_length,
                "loop_steps_per_second": steps / t_loop,
                "bare_steps_per_second": steps / t_bare,
                "ratio": t_bare / t_loop,
            }
        )
        print(
            f"{env_name} {name}: loop {steps / t_loop:,.0f} steps/s, "
            f"bare {steps / t_bare:,.0f} steps/s, ratio {t_bare / t_loop:.2f}",
            flush=True,
        )
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--envs", nargs="+", default=["ant_omni", "halfcheetah_uni"])
    parser.add_argument("--batch", type=int, default=128)
    parser.add_argument("--episodes", type=int, default=4, help="episodes per candidate for ME-LS")
    parser.add_argument("--episode-length", type=int, default=100)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument(
        "--out", type=Path, default=None, help="default: results/qd_throughput[_xla_default].json"
    )
    parser.add_argument(
        "--xla-default", action="store_true", help="keep XLA's CPU defaults (BRAX_CPU_FLAGS off)"
    )
    args = parser.parse_args()
    if args.out is None:
        name = "qd_throughput_xla_default.json" if args.xla_default else "qd_throughput.json"
        args.out = Path(__file__).parent / "results" / name

    rows = []
    for env_name in args.envs:
        rows += measure(env_name, args)
    write_result(
        args.out,
        {
            "benchmark": "Chapter 4 QD iteration vs bare simulation",
            "batch": args.batch,
            "cells": 256,
            "xla_flags": os.environ.get("XLA_FLAGS", ""),
            "results": rows,
        },
    )


if __name__ == "__main__":
    main()
