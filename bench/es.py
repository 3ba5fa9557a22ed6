"""Evolution strategies (``qdnb.qd.es``): environment steps per second of one generation
of ES, NSR-ES, NSRA-ES and ME-ES on Point-Maze and on Ant-Maze, beside a bare vmapped
rollout of as many policies in the same run (the target: at least 90 % of the bare
rate).  Writes ``bench/results/es.json``.

    python bench/es.py [--perturbations 1000] [--ant-perturbations 100] [--repeats 5]

A generation is timed as ``run_seeds`` runs it: ``repeats`` steps in one compiled
``lax.scan``, after a warm-up call; the bare rollout is ``evaluate_policies`` on the
same number of fixed policies, also in a ``lax.scan`` of ``repeats`` calls.  Rates count
every step of every episode (episodes that end early still run to the horizon here:
the loop has a fixed length).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

import jax

from qdnb.envs import make_env
from qdnb.envs.rollout import evaluate_policies
from qdnb.nets.mlp import MLP, init_policies
from qdnb.qd.es import MEES, NSRAES, NSRES, OpenAIES

METHODS = {"ES": OpenAIES, "NSR-ES": NSRES, "NSRA-ES": NSRAES, "ME-ES": MEES}


def timed_scan(body, carry, repeats: int) -> float:
    """Seconds per call of ``body`` in a compiled ``lax.scan`` of ``repeats`` calls."""
    loop = jax.jit(lambda c: jax.lax.scan(lambda c, _: (body(c), None), c, None, repeats)[0])
    jax.block_until_ready(loop(carry))  # compile and warm up
    start = time.perf_counter()
    jax.block_until_ready(loop(carry))
    return (time.perf_counter() - start) / repeats


def bench_env(env_name: str, episode_length: int, hidden, perturbations: int, repeats: int):
    env = make_env(env_name, episode_length=episode_length)
    network = MLP(tuple(hidden) + (env.action_size,), activation="relu")
    out = {"episode_length": episode_length, "policy_hidden": list(hidden), "methods": {}}
    policies = init_policies(network, jax.random.PRNGKey(0), perturbations, env.observation_size)

    def bare(key):
        key, sub = jax.random.split(key)
        ev = evaluate_policies(env, network.apply, policies, sub)
        return jax.random.fold_in(key, ev.length.sum())  # keep the rollout live

    bare_seconds = timed_scan(bare, jax.random.PRNGKey(1), repeats)
    bare_rate = perturbations * episode_length / bare_seconds
    out["bare"] = {"episodes": perturbations, "seconds": round(bare_seconds, 4)}
    out["bare"]["env_steps_per_second"] = round(bare_rate, 1)
    print(env_name, "bare", out["bare"], flush=True)
    for name, cls in METHODS.items():
        algo = cls(env=env, network=network, num_perturbations=perturbations)
        state, _ = jax.jit(algo.init)(jax.random.PRNGKey(2))
        seconds = timed_scan(lambda s: algo.step(s)[0], state, repeats)
        rate = algo.episodes_per_step * episode_length / seconds
        out["methods"][name] = {
            "episodes_per_generation": algo.episodes_per_step,
            "seconds_per_generation": round(seconds, 4),
            "env_steps_per_second": round(rate, 1),
            "rate_over_bare": round(rate / bare_rate, 3),
        }
        print(env_name, name, out["methods"][name], flush=True)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--perturbations", type=int, default=1000)
    parser.add_argument("--ant-perturbations", type=int, default=100)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--out", default=str(Path(__file__).parent / "results" / "es.json"))
    args = parser.parse_args()
    if args.repeats < 1 or args.perturbations < 2 or args.ant_perturbations < 2:
        parser.error("--repeats must be >= 1 and the perturbation counts >= 2")
    out = {
        "machine": platform.processor() or platform.machine(),
        "cpu_count": os.cpu_count(),
        "device": str(jax.devices()[0]),
        "repeats": args.repeats,
        "target_rate_over_bare": 0.9,
        "pointmaze": bench_env("pointmaze", 200, (64, 32), args.perturbations, args.repeats),
        "antmaze": bench_env("antmaze", 500, (64, 64), args.ant_perturbations, args.repeats),
    }
    Path(args.out).write_text(json.dumps(out, indent=2) + "\n")
    print("wrote", args.out)


if __name__ == "__main__":
    main()
