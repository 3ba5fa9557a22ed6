"""Flow Lenia simulation speed: the separable 9-cell scatter reintegration
(``flow_lenia.reintegrate``) against the straightforward gather over the whole
``(2 reach + 1)^2 = 121``-cell neighbourhood (``reintegrate_reference``).

On a 128x128 grid with the default world (10 kernels, Table 5.1, the reference
code's rules: walls, the flow bound, deterministic mixing), for one system
and for a batch of 8 (``vmap``), a whole episode (``lax.scan`` over ``steps``
steps, jitted) is timed with each reintegration: compilation apart, median of
``--repeats`` runs, simulation steps per second (system-steps for the batch).
Agreement (target: 1e-5): the two reintegrations sum the same parcels in a
different order, and a float rounding difference, amplified by the dynamics
(and by the parameter draw, whose winner can flip on a near tie), can grow over
an episode, so whole episodes may drift apart.  The check is
therefore step by step: the reference step is applied to every state of the
fast episode, with the same key, and compared with the fast episode's next
state; the largest differences on ``A`` and ``P`` over all steps and systems are
reported, next to the (larger) difference between the two free-running episodes'
last states.  The speed-up target is at least 5x.  Writes
``bench/results/flow_lenia.json``.

    python bench/flow_lenia.py [--size 128] [--steps 50] [--repeats 3]
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import time
from functools import partial
from pathlib import Path

import jax
import jax.numpy as jnp

from qdnb.book.provenance import write_result
from qdnb.models.lenia import flow_lenia as fl


def step_with(reintegrate, system, state, key, cfg):
    F = fl.flow(fl.affinity(system, state), state.A, cfg)
    A, P = reintegrate(state.A, state.P, fl.displacement(F, cfg), fl.mixing_key(key, cfg), cfg)
    return fl.State(A=A, P=P)


@partial(jax.jit, static_argnames=("cfg",))
def stepwise_difference(systems, states, keys, cfg):
    """Largest |reference step(x_t) - x_{t+1}| over a fast episode, per field."""

    def one(system, state, key):
        episode = fl.rollout(system, state, key, cfg)
        step_keys = jax.random.split(key, cfg.steps)
        now = jax.tree.map(lambda x: x[:-1], episode)
        ref = jax.vmap(lambda st, k: step_with(fl.reintegrate_reference, system, st, k, cfg))(
            now, step_keys
        )
        return (jnp.max(jnp.abs(ref.A - episode.A[1:])), jnp.max(jnp.abs(ref.P - episode.P[1:])))

    dA, dP = jax.vmap(one)(systems, states, keys)
    return jnp.max(dA), jnp.max(dP)


@partial(jax.jit, static_argnames=("cfg", "reference"))
def episodes(systems, states, keys, cfg, reference):
    reintegrate = fl.reintegrate_reference if reference else fl.reintegrate

    def one(system, state, key):
        def body(current, k):
            nxt = step_with(reintegrate, system, current, k, cfg)
            return nxt, None

        final, _ = jax.lax.scan(body, state, jax.random.split(key, cfg.steps))
        return final

    return jax.vmap(one)(systems, states, keys)


def timed(fn, repeats):
    start = time.perf_counter()
    out = jax.block_until_ready(fn())
    compile_s = time.perf_counter() - start
    runs = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(fn())
        runs.append(time.perf_counter() - start)
    return out, compile_s, statistics.median(runs)


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--size", type=int, default=128)
    parser.add_argument("--steps", type=int, default=50)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument(
        "--out", type=Path, default=Path(__file__).parent / "results" / "flow_lenia.json"
    )
    args = parser.parse_args()
    cfg = dataclasses.replace(
        fl.FlowLeniaConfig(), height=args.size, width=args.size, steps=args.steps
    )
    results = []
    for batch in (1, 8):
        key = jax.random.PRNGKey(batch)
        k_sys, k_init, k_run = jax.random.split(key, 3)
        systems = jax.vmap(fl.sample_system, in_axes=(0, None))(jax.random.split(k_sys, batch), cfg)
        states = jax.vmap(fl.initial_state, in_axes=(0, None))(jax.random.split(k_init, batch), cfg)
        keys = jax.random.split(k_run, batch)
        row = {
            "batch": batch,
            "grid": [cfg.height, cfg.width],
            "kernels": cfg.kernels,
            "steps": cfg.steps,
        }
        finals = {}
        for name, reference in (("scatter_9", False), ("gather_121", True)):
            final, compile_s, run_s = timed(
                lambda: episodes(systems, states, keys, cfg, reference), args.repeats
            )
            finals[name] = final
            row[name] = {
                "compile_s": round(compile_s, 3),
                "episode_s": round(run_s, 4),
                "steps_per_s": round(batch * cfg.steps / run_s, 1),
            }
            print(f"batch {batch}, {name}: {row[name]}")
        dA, dP = stepwise_difference(systems, states, keys, cfg)
        row["stepwise_max_abs_diff_A"], row["stepwise_max_abs_diff_P"] = float(dA), float(dP)
        row["agree_1e-5"] = (
            row["stepwise_max_abs_diff_A"] <= 1e-5 and row["stepwise_max_abs_diff_P"] <= 1e-5
        )
        row["free_running_final_max_abs_diff_A"] = float(
            jnp.max(jnp.abs(finals["scatter_9"].A - finals["gather_121"].A))
        )
        row["speedup"] = round(row["gather_121"]["episode_s"] / row["scatter_9"]["episode_s"], 2)
        print(
            f"batch {batch}: speed-up {row['speedup']}x, step by step max |dA| {float(dA):.2e}, "
            f"max |dP| {float(dP):.2e}; free-running episodes end "
            f"{row['free_running_final_max_abs_diff_A']:.2e} apart"
        )
        results.append(row)
    write_result(args.out, {"benchmark": "flow_lenia", "results": results})
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
