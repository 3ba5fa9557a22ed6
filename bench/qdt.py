"""Quality-Diversity Transformer: training throughput and rollout speed on Ant-Omni
(``speed``, the default), and the learning curve that sets ``small``'s training budget
(``curve``).

``python bench/qdt.py speed``, Ant-Omni's 250-step episodes:

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

    python bench/qdt.py [speed] [--scale small] [--goals 8] [--episodes 1]

``python bench/qdt.py curve``: one QDT per reading trained on the ``small`` ME-LS
dataset of Halfcheetah-Uni (the chapter's seed 0: the same repertoire, zones, goals,
selection and episodes as the notebook) and evaluated every ``--eval-every`` steps:
training loss, held-out action error of the demonstrators' fresh episodes with their
own BDs and with BDs shuffled between demonstrators, distance to each demonstrator's
own BD when conditioned on it, distance to the goals.  Writes
``bench/results/qdt_curve.json``; the rule that reads it is ``CURVE_RULE``.

    python bench/qdt.py curve [--steps 3000] [--eval-every 250] [--variants thesis tanh]
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from dataclasses import replace
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from qdnb.book.provenance import write_result
from qdnb.book.registry import config
from qdnb.chapters.ch4_qdt import (
    demonstrations,
    load_or_recompute_repertoires,
    qdt_model,
    setting,
)
from qdnb.envs import make_env
from qdnb.models.qdt.data import Trajectories, seed_repertoire
from qdnb.models.qdt.evaluate import goal_scores, imitation, play
from qdnb.models.qdt.model import QDT, TOKENS_PER_STEP, init_params
from qdnb.models.qdt.train import conditioning_gap, fit, make_train_step
from qdnb.nets.transformer import make_optimizer
from qdnb.qd.cvt import cvt_centroids

EPISODE_LENGTH = 250  # Chapter 4's Ant-Omni episodes

CURVE_RULE = """Written before the runs.  small's training budget (gradient steps, the same
for every dataset) is read from the thesis's reading (linear head, Flax's initialisation,
the raw BD) on the small ME-LS data of Halfcheetah-Uni, at small's batch size: the first
evaluated step count by which the held-out action error has made 90 % of its fall over
the run (h(s) <= h_min + 0.1 (h(first) - h_min)), provided the run's last third lowers it
by less than 5 % (else the curve has not flattened and the run is extended).  The
closed-loop distances (to the demonstrators' own BDs and to the goals) are read beside it:
a budget where the held-out error has flattened but they still fall is reported as such.
The other readings (tanh head, PyTorch's initialisation, the BD scaled to its box) are
taken in the chapter only if they lower the held-out error or the closed-loop distances at
that budget, and then as a labelled choice."""

# name -> the QDTConfig fields that differ from the thesis's reading
CURVE_VARIANTS = {
    "thesis": {},
    "tanh": {"head": "tanh"},
    "torch": {"init_scheme": "torch"},
    "box": {"bd_scaling": True},
}


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
    flops = step_flops(compiled)
    params, opt_state, loss = jax.block_until_ready(
        compiled(params, opt_state, batch, key)
    )  # warm-up
    times = []
    for i in range(repeats):
        k = jax.random.fold_in(key, i)
        start = time.perf_counter()
        params, opt_state, loss = jax.block_until_ready(compiled(params, opt_state, batch, k))
        times.append(time.perf_counter() - start)
    return compile_s, times, float(loss), flops


def step_flops(compiled) -> float:
    """XLA's count of the floating-point operations of one compiled call."""
    cost = compiled.cost_analysis()
    cost = cost[0] if isinstance(cost, (list, tuple)) else cost
    return float(cost.get("flops", float("nan")))


def matmul_rate(n: int = 1024, repeats: int = 20) -> float:
    """The machine's float32 matrix-multiply rate (FLOP/s, median of ``repeats``
    products of two ``n x n`` matrices, every core XLA uses): the ceiling a training
    step's rate is read against."""
    a = jax.random.normal(jax.random.PRNGKey(0), (n, n))
    product = jax.jit(lambda x: x @ x).lower(a).compile()
    jax.block_until_ready(product(a))
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(product(a))
        times.append(time.perf_counter() - start)
    return 2 * n**3 / statistics.median(times)


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


def flattening_step(steps: list[int], heldout: list[float]) -> tuple[int, bool]:
    """``CURVE_RULE``: the first step by which the held-out error made 90 % of its fall,
    and whether the run's last third lowered it by less than 5 % (flat)."""
    h, low = np.asarray(heldout), float(np.min(heldout))
    at = int(np.argmax(h <= low + 0.1 * (h[0] - low)))
    third = max(1, len(h) // 3)
    before = float(np.min(h[: len(h) - third]))
    return int(steps[at]), bool(before - low < 0.05 * before)


def curve(args) -> None:
    cfg = config("ch4_qdt", args.scale)
    repro_cfg = config("ch4_reproducibility", args.scale)
    if args.batch:
        cfg = replace(cfg, batch_size=args.batch)
    if args.episodes_per_policy:
        task = replace(cfg.task(args.env), episodes_per_policy=args.episodes_per_policy)
        cfg = replace(cfg, **{args.env: task})
    repertoires, status = load_or_recompute_repertoires(repro_cfg, args.scale, seed=0)
    # the chapter's keys for seed 0 of this environment (ch4_qdt.run_environments)
    env_key = jax.random.fold_in(jax.random.PRNGKey(0), cfg.environments.index(args.env))
    where = setting(cfg, repro_cfg, args.env, env_key)
    k_sel, k_rec, _, k_train, k_eval, _ = jax.random.split(jax.random.fold_in(where.k_seeds, 0), 6)
    rep = seed_repertoire(repertoires[args.env][args.source], 0)
    sel, data, heldout, targets = demonstrations(cfg, where, rep, k_sel, k_rec)
    print(
        f"{args.env} {args.source}: {sel.cells.size} demonstrators, {data.size} trajectories, "
        f"{heldout.size} held out; demonstrators' own distance "
        f"{np.nanmean(targets.distance):.3f}",
        flush=True,
    )
    out = {
        "benchmark": "QDT learning curves on small's data (CURVE_RULE)",
        "rule": CURVE_RULE,
        "scale": args.scale,
        "environment": args.env,
        "source": args.source,
        "repertoires": status[args.env][args.source],
        "batch_size": cfg.batch_size,
        "learning_rate": cfg.learning_rate,
        "model": {k: getattr(cfg, k) for k in ("embed_dim", "num_layers", "num_heads", "dropout")},
        "dataset_size": data.size,
        "demonstrators": int(sel.cells.size),
        "demonstrator_imitation": float(np.nanmean(targets.distance)),
        "variants": {},
    }
    if args.out.exists():  # earlier variants of the same run are kept
        earlier = json.loads(args.out.read_text())
        out["variants"] = earlier.get("variants", {})
    for name in args.variants:
        fields = CURVE_VARIANTS[name]
        if args.episodes_per_policy:  # the same reading on a larger dataset
            name = f"{name}, {args.episodes_per_policy} episodes per demonstrator"
        model = qdt_model(replace(cfg, **fields), where.env)
        play_goals = jax.jit(
            lambda p, k: play(where.env, model, p, where.goals, k, cfg.eval_episodes)
        )
        play_targets = jax.jit(
            lambda p, k: play(where.env, model, p, targets.padded, k, cfg.eval_episodes)
        )
        rows, clock = [], {"train": time.perf_counter(), "train_s": [], "eval_s": []}

        def evaluate(params, step_done):
            began = time.perf_counter()
            clock["train_s"].append(began - clock["train"])
            gap = conditioning_gap(model, params, heldout, k_eval)
            goals = goal_scores(where.goals, play_goals(params, k_eval))
            zones = imitation(targets, play_targets(params, k_eval))
            rows.append(
                {
                    "step": step_done,
                    **gap,
                    "imitation": float(np.nanmean(zones)),
                    "avg_distance": float(goals["distance"].mean()),
                }
            )
            out["variants"][name] = {"fields": fields, "evaluations": rows, "finished": False}
            write_result(args.out, out)  # a run cut short keeps its evaluations
            print(
                f"{name} step {step_done}: "
                + ", ".join(f"{k} {v:.4g}" for k, v in rows[-1].items() if k != "step"),
                flush=True,
            )
            clock["eval_s"].append(time.perf_counter() - began)
            clock["train"] = time.perf_counter()
            return {"avg_distance": rows[-1]["avg_distance"]}

        res = fit(
            model,
            data,
            k_train,
            args.steps,
            cfg.batch_size,
            cfg.learning_rate,
            args.eval_every,
            evaluate,
            progress=False,
        )
        for row, loss in zip(rows, res.losses):
            row["train_loss"] = loss
        steps, held = [r["step"] for r in rows], [r["heldout_mse"] for r in rows]
        flat_at, flat = flattening_step(steps, held)
        out["variants"][name] = {
            "fields": fields,
            "dataset_size": data.size,
            "evaluations": rows,
            "best_step": res.best_step,
            "flattening_step": flat_at,
            "flat": flat,
            # the first interval and evaluation compile: the later ones are the rate
            "train_seconds_per_step": float(np.median(clock["train_s"][1:] or clock["train_s"]))
            / args.eval_every,
            "seconds_per_evaluation": float(np.median(clock["eval_s"][1:] or clock["eval_s"])),
            "first_interval_seconds": clock["train_s"][0],
            "finished": True,
        }
        print(
            f"{name}: held-out error flattens at step {flat_at} "
            f"({'flat' if flat else 'still falling'}); "
            f"{out['variants'][name]['train_seconds_per_step']:.3f} s a step",
            flush=True,
        )
        write_result(args.out, out)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command")
    c = sub.add_parser("curve", help="learning curves on small's data (CURVE_RULE)")
    c.add_argument("--scale", default="small", help="(tiny: a quick check of the code)")
    c.add_argument("--env", default="halfcheetah_uni", choices=("halfcheetah_uni", "ant_omni"))
    c.add_argument("--source", default="ME-LS")
    c.add_argument("--steps", type=int, default=3000)
    c.add_argument("--eval-every", type=int, default=250)
    c.add_argument("--batch", type=int, default=0, help="batch size (default: small's)")
    c.add_argument(
        "--episodes-per-policy", type=int, default=0, help="dataset episodes (default: small's)"
    )
    c.add_argument(
        "--variants", nargs="+", default=list(CURVE_VARIANTS), choices=list(CURVE_VARIANTS)
    )
    c.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "qdt_curve.json")
    sub.add_parser("speed", help="training throughput and rollouts (the default)")
    args, rest = parser.parse_known_args()
    if args.command == "curve":
        curve(args)
    else:
        speed(rest)


def speed(argv) -> None:
    parser = argparse.ArgumentParser(description="QDT training throughput and rollouts")
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
    args = parser.parse_args(argv)
    cfg = config("ch4_qdt", args.scale)

    env = make_env("ant_omni", episode_length=EPISODE_LENGTH)
    model = qdt_model(cfg, env)
    k_init, k_batch, k_train, k_goals, k_play = jax.random.split(jax.random.PRNGKey(0), 5)
    params = init_params(model, k_init, env.descriptor_size, env.observation_size)
    num_params = sum(x.size for x in jax.tree.leaves(params))

    # 1. training throughput
    batch = synthetic_batch(k_batch, cfg.batch_size, env)
    tokens = TOKENS_PER_STEP * EPISODE_LENGTH * cfg.batch_size
    train_compile, train_times, loss, flops = bench_training(
        model, params, batch, cfg.learning_rate, k_train, args.train_repeats
    )
    train_s = statistics.median(train_times)
    rate = matmul_rate()
    print(
        f"training step: {flops / 1e9:.2f} GFLOP (XLA's count), {flops / train_s / 1e9:.1f} "
        f"GFLOP/s against a {rate / 1e9:.1f} GFLOP/s matrix product ({flops / train_s / rate:.0%})"
    )
    no_dropout = model.clone(dropout=0.0)
    _, no_dropout_times, _, _ = bench_training(
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

    write_result(
        args.out,
        {
            "benchmark": "QDT training throughput and cached vs full-recomputation rollouts on "
            "ant_omni",
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
                "flops_per_step": flops,
                "flops_per_second": flops / train_s,
                "matmul_flops_per_second": rate,
                "fraction_of_matmul_rate": flops / train_s / rate,
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
