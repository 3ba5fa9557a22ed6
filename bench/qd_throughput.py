"""QD-loop throughput on Ant-Omni: environment steps per second of one MAP-Elites
and one MAP-Elites Low-Spread iteration (selection, variation, evaluation,
insertion) against a bare vmapped `lax.scan` of the same brax environment and
policy with the same number of episodes, in the same run.

Target: the QD loop runs at no less than 85% of the bare simulator's rate.
Writes bench/results/qd_throughput.json.  Usage:
    python bench/qd_throughput.py [--batch 64] [--episodes 4] [--episode-length 100]
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import jax
from rollout import (
    bare_scan,  # bench/rollout.py: the same bare loop, batch taken from the parameters
)

from qdnb.book.provenance import device, versions
from qdnb.core.io import atomic_write_json
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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--batch", type=int, default=64)
    parser.add_argument("--episodes", type=int, default=4, help="episodes per candidate for ME-LS")
    parser.add_argument("--episode-length", type=int, default=100)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument(
        "--out", type=Path, default=Path(__file__).parent / "results" / "qd_throughput.json"
    )
    args = parser.parse_args()

    env = make_env("ant_omni", episode_length=args.episode_length)
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
            MapElitesLowSpread(**common, batch_size=args.batch, num_episodes=args.episodes),
            args.episodes,
        ),
    ]:
        state, _ = jax.jit(algo.init)(jax.random.PRNGKey(1))
        step = jax.jit(lambda s: algo.step(s)[0])
        t_loop = median_time(step, state, args.repeats)
        n = args.batch * episodes
        bare = bare_scan(env, network)
        params = init_policies(network, jax.random.PRNGKey(2), n, env.observation_size)
        t_bare = median_time(lambda k: bare(params, k), jax.random.PRNGKey(3), args.repeats)
        steps = n * env.episode_length
        rows.append(
            {
                "algorithm": name,
                "episodes_per_iteration": n,
                "episode_length": env.episode_length,
                "loop_steps_per_second": steps / t_loop,
                "bare_steps_per_second": steps / t_bare,
                "ratio": t_bare / t_loop,
            }
        )
        print(
            f"{name}: loop {steps / t_loop:,.0f} steps/s, bare {steps / t_bare:,.0f} steps/s, "
            f"ratio {t_bare / t_loop:.2f}"
        )
    atomic_write_json(
        args.out,
        {
            "benchmark": "ant_omni QD iteration vs bare simulation",
            "device": device(),
            "versions": versions(),
            "batch": args.batch,
            "results": rows,
        },
    )


if __name__ == "__main__":
    main()
