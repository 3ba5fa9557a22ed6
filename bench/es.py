"""Evolution strategies (``qdnb.qd.es``): environment steps per second of one generation
of ES, NSR-ES, NSRA-ES and ME-ES on Point-Maze and on Ant-Maze, beside a bare vmapped
rollout of as many policies in the same run (the target: at least 90 % of the bare
rate).  Writes ``bench/results/es.json``.

    python bench/es.py [--scale small] [--trials 9] [--ant-methods ES ME-ES]
                       [--envs pointmaze antmaze]

The methods are those the evolution page runs at ``--scale`` (``ch3_evolution``:
built by the chapter's registry, so with the page's perturbations, episode lengths,
policy networks and archive sizes); ES is the core they share, built with the same
settings.  The bare rollout is ``evaluate_policies`` on as many policies as a
generation has perturbations, their parameters passed in as data (as an ES
generation's are) and every output an evaluation gives (returns, descriptors, lengths)
used, so that XLA computes all of them.  A generation is timed as one run of the page
does it (one seed, no ``vmap`` over seeds): ``repeats`` steps in one compiled ``lax.scan``, after a
warm-up call.  A method and the bare rollout are timed in alternation ``trials``
times; the rate over bare is the median of the trials' ratios (the machine's speed
drifts by a few per cent between calls), the seconds the fastest trial's.  Rates count
every step of every episode (episodes that end early still run to the horizon: the
loop has a fixed length).  ES uses no descriptors, so XLA drops the descriptor tally
from its rollout (on Point-Maze a recomputation of the wall step inside the episode loop,
about 1.5 ms of a ~110 ms generation): its rate can exceed the bare one's.
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import jax
import jax.numpy as jnp

from qdnb.book.provenance import write_result
from qdnb.chapters import ch3_evolution
from qdnb.chapters.ch3_qdpg import build_algorithms, make_task_env
from qdnb.envs.rollout import evaluate_policies
from qdnb.nets.mlp import init_policies
from qdnb.qd.es import OpenAIES

METHODS = ("ES", *ch3_evolution.EVOLUTION)


def scan_timer(body, carry, repeats: int):
    """A function that times one call of a compiled ``lax.scan`` of ``repeats`` calls
    of ``body`` (compiled and warmed up here) and returns the seconds per call."""
    loop = jax.jit(lambda c: jax.lax.scan(lambda c, _: (body(c), None), c, None, repeats)[0])
    jax.block_until_ready(loop(carry))

    def timed() -> float:
        start = time.perf_counter()
        jax.block_until_ready(loop(carry))
        return (time.perf_counter() - start) / repeats

    return timed


def bench_env(cfg, env_name: str, methods, repeats: int, trials: int) -> dict:
    tasks = cfg.es_tasks(env_name)
    task = tasks.task(env_name)
    env = make_task_env(tasks, env_name)
    registry = [m for m in methods if m != "ES"]
    algorithms = build_algorithms(tasks, env_name, env, tuple(registry))
    some = next(iter(algorithms.values()))
    if "ES" in methods:
        algorithms = {
            "ES": OpenAIES(env=env, network=some.network, num_perturbations=task.num_actors),
            **algorithms,
        }
    n, length = task.num_actors, task.episode_length
    policies = init_policies(some.network, jax.random.PRNGKey(0), n, env.observation_size)

    def bare(carry):
        key, params = carry
        key, sub = jax.random.split(key)
        ev = evaluate_policies(env, some.network.apply, params, sub)
        # keep every output an evaluation gives live (returns, descriptors, lengths):
        # XLA drops the reward and descriptor computations of a rollout whose only
        # used output is its lengths (a bare rollout then does less than an ES one)
        used = jnp.sum(ev.fitness) + jnp.sum(ev.descriptor) + jnp.sum(ev.length)
        return jax.random.fold_in(key, jax.lax.bitcast_convert_type(used, jnp.int32)), params

    bare_timer = scan_timer(bare, (jax.random.PRNGKey(1), policies), repeats)
    out = {
        "episode_length": length,
        "policy_hidden": list(task.policy_hidden),
        "perturbations": n,
        "methods": {},
    }
    bare_seconds = []
    for name, algo in algorithms.items():
        state, _ = jax.jit(algo.init)(jax.random.PRNGKey(2))
        timer = scan_timer(lambda s: algo.step(s)[0], state, repeats)
        pairs = [(bare_timer(), timer()) for _ in range(trials)]
        bare_seconds += [b for b, _ in pairs]
        ratios = [(algo.episodes_per_step / m) / (n / b) for b, m in pairs]
        seconds = min(m for _, m in pairs)
        out["methods"][name] = {
            "episodes_per_generation": algo.episodes_per_step,
            "archive_size": getattr(algo, "archive_size", None),
            "seconds_per_generation": round(seconds, 4),
            "env_steps_per_second": round(algo.episodes_per_step * length / seconds, 1),
            "rate_over_bare": round(statistics.median(ratios), 3),
            "rate_over_bare_per_trial": [round(r, 3) for r in ratios],
        }
        print(env_name, name, out["methods"][name], flush=True)
    best = min(bare_seconds)
    out["bare"] = {
        "episodes": n,
        "seconds": round(best, 4),
        "env_steps_per_second": round(n * length / best, 1),
    }
    print(env_name, "bare", out["bare"], flush=True)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scale", default="small", choices=sorted(ch3_evolution.SCALES))
    parser.add_argument("--trials", type=int, default=9)
    parser.add_argument("--repeats", type=int, default=5, help="Point-Maze generations per call")
    parser.add_argument("--ant-methods", nargs="+", default=["ES", "ME-ES"], choices=METHODS)
    parser.add_argument("--envs", nargs="+", default=["pointmaze", "antmaze"])
    parser.add_argument("--out", default=str(Path(__file__).parent / "results" / "es.json"))
    args = parser.parse_args()
    if args.repeats < 1 or args.trials < 1:
        parser.error("--repeats and --trials must be >= 1")
    cfg = ch3_evolution.SCALES[args.scale]
    out = {
        "scale": args.scale,
        "trials": args.trials,
        "target_rate_over_bare": 0.9,
    }
    if "pointmaze" in args.envs:
        out["pointmaze"] = bench_env(cfg, "pointmaze", METHODS, args.repeats, args.trials)
    if "antmaze" in args.envs:
        out["antmaze"] = bench_env(cfg, "antmaze", tuple(args.ant_methods), 1, args.trials)
    write_result(Path(args.out), out)
    print("wrote", args.out)


if __name__ == "__main__":
    main()
