"""Every core at work: the rate of each stage of the book on one device and at the
default device count (one XLA host device per core, ``qdnb.core.sharding``), side by
side in one run, with the alternatives the default was chosen against and the 1/2/4
forced-device sweep.  Writes ``bench/results/scale_out.json``.

    python bench/scale_out.py [--scale small] [--stages ...] [--sweep 4]
    python bench/scale_out.py --real           # on a GPU machine: its own devices only

Each configuration runs in its own process (the device count is fixed when JAX
starts): ``1`` (``QDNB_DEVICES=1``), ``default`` (what a notebook gets), then at the
default count the alternatives: ``populations`` (seeds never split: each seed's
population is split instead, QD-PG's too), ``padded-seeds`` (Chapter 4's loops on seeds
padded to a multiple of the devices and split, instead of their populations), and the
forced counts of ``--sweep`` (devices beyond the cores share them).  The training steps
compare their two placements inside each process, in alternation: split over the
devices (data parallel) and whole on one device.  The stages, at ``--scale``'s chapter settings:

- ``me_ls_ant_omni``: ME-LS on Ant-Omni, Chapter 4's seeds (a Brax MAP-Elites loop);
- ``pga_me_ant_omni``: PGA-ME on Ant-Omni, Chapter 4's seeds (a critic beside the
  population);
- ``me_pointmaze``: MAP-Elites on Point-Maze, the primer's seeds and batch;
- ``qdpg_pointmaze``: QD-PG on Point-Maze, the QD-PG page's seeds (critics and actors
  included), also as QD-PG seeds per hour at 10^6 steps each; ``qdpg_pointmaze_3_seeds``
  the same on three seeds (which two devices do not divide);
- ``es_pointmaze``: ME-ES generations on Point-Maze, the evolution page's seeds;
- ``flow_lenia_batch``: a batch of Chapter 5's held-out episodes (``eval_batch``);
- ``qdt_step``: QDT training steps (Chapter 4's model and minibatch at ``--scale``);
- ``flt_step``: FLT training steps, each simulating its batch of episodes.

Loops run through ``run_seeds`` as the notebooks run them: the rate is the median of the
chunks after the first (which compiles).  Agreement with one device: the loops' final
fitnesses (and the Flow Lenia frames) bit for bit, the training losses to a relative
gap (a split gradient sums in another order).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
STAGES = (
    "me_ls_ant_omni",
    "pga_me_ant_omni",
    "me_pointmaze",
    "qdpg_pointmaze",
    "qdpg_pointmaze_3_seeds",
    "es_pointmaze",
    "flow_lenia_batch",
    "qdt_step",
    "flt_step",
)
# the alternatives and the stages they can change
VARIANTS = {
    "populations": ("me_pointmaze", "qdpg_pointmaze", "qdpg_pointmaze_3_seeds", "es_pointmaze"),
    "padded-seeds": ("me_ls_ant_omni", "pga_me_ant_omni"),
}


def loop_rate(algorithm, num_seeds: int, iterations: int, chunk: int) -> dict:
    """A ``run_seeds`` loop as the notebooks run it: steps per second of its chunks."""
    import jax
    import numpy as np

    from qdnb.qd.algorithms import run_seeds

    keys = jax.random.split(jax.random.PRNGKey(1), num_seeds)
    seconds: list[float] = []
    _, _, history = run_seeds(
        algorithm, keys, iterations, chunk, progress=False, chunk_seconds=seconds
    )
    per_chunk = float(np.median(seconds[1:]))
    steps = np.asarray(history["env_steps"])  # (seeds, iterations + 1)
    steps_per_chunk = float(np.sum(steps[:, -chunk:]))  # every seed's, one chunk
    return {
        "seeds": num_seeds,
        "seconds_per_iteration": per_chunk / chunk,
        "env_steps_per_s": steps_per_chunk / per_chunk,
        "first_chunk_s": seconds[0],
        # every solution the last iteration evaluated, every seed
        "fingerprint": np.asarray(history["fitnesses"][:, -1]).ravel().tolist(),
    }


def me_ls_ant_omni(scale: str, method: str = "ME-LS") -> dict:
    import jax

    from qdnb.book.registry import config
    from qdnb.chapters.ch4_reproducibility import build_algorithms, fitness_offset
    from qdnb.nets.mlp import MLP
    from qdnb.qd.cvt import cvt_centroids

    cfg = config("ch4_reproducibility", scale)
    env = cfg.make_env("ant_omni")
    network = MLP(cfg.policy_hidden + (env.action_size,))
    centroids = cvt_centroids(
        jax.random.PRNGKey(0),
        cfg.num_cells,
        env.descriptor_low,
        env.descriptor_high,
        cfg.cvt_samples,
        cfg.cvt_iterations,
    )
    offset = fitness_offset("ant_omni", cfg.episode_length)
    algorithm = build_algorithms(cfg, env, network, centroids, offset)[method]
    return loop_rate(algorithm, cfg.num_seeds, 6, 1)


def pga_me_ant_omni(scale: str) -> dict:
    return me_ls_ant_omni(scale, "PGA-ME")


def me_pointmaze(scale: str) -> dict:
    from qdnb.book.registry import config
    from qdnb.chapters import ch2_primer

    cfg = config("ch2_primer", scale)
    env, network = ch2_primer.make_task(cfg)
    me = ch2_primer.build_algorithms(cfg, env, network)["ME"]
    return loop_rate(me, cfg.num_seeds, 60, 10)


def qdpg_pointmaze(scale: str, seeds: int | None = None) -> dict:
    from qdnb.book.registry import config
    from qdnb.chapters.ch3_qdpg import build_algorithms

    cfg = config("ch3_qdpg", scale)
    task = cfg.task("pointmaze")
    algo = build_algorithms(cfg, "pointmaze")["QD-PG"]
    seeds = cfg.seeds("pointmaze", "QD-PG") if seeds is None else seeds
    out = loop_rate(algo, seeds, 60, 10)
    steps_per_iteration = task.num_actors * task.episode_length  # every episode at full length
    hours_per_seed = 1e6 / steps_per_iteration * out["seconds_per_iteration"] / seeds / 3600
    out["seeds_per_hour_at_1e6_steps"] = 1.0 / hours_per_seed
    return out


def qdpg_pointmaze_3_seeds(scale: str) -> dict:
    return qdpg_pointmaze(scale, 3)


def es_pointmaze(scale: str) -> dict:
    from qdnb.book.registry import config
    from qdnb.chapters.ch3_qdpg import build_algorithms

    cfg = config("ch3_evolution", scale)
    tasks = cfg.es_tasks("pointmaze")
    algo = build_algorithms(tasks, "pointmaze", methods=("ME-ES",))["ME-ES"]
    return loop_rate(algo, cfg.seeds("pointmaze"), 6, 1)


def flow_lenia_batch(scale: str) -> dict:
    import jax
    import numpy as np

    from qdnb.book.registry import config
    from qdnb.models.lenia import flow_lenia as fl

    cfg = config("ch5_flow_lenia", scale)
    world = cfg.world
    system = fl.sample_system(jax.random.PRNGKey(3), world)
    key = jax.random.PRNGKey
    run = lambda i: fl.frames(fl.simulate_system(system, key(i), world, cfg.eval_batch))
    start = time.perf_counter()
    first = jax.block_until_ready(run(0))
    compile_s = time.perf_counter() - start
    times = []
    for i in range(1, 6):
        start = time.perf_counter()
        jax.block_until_ready(run(i))
        times.append(time.perf_counter() - start)
    per_batch = float(np.median(times))
    return {
        "episodes_per_batch": cfg.eval_batch,
        "seconds_per_batch": per_batch,
        "episodes_per_s": cfg.eval_batch / per_batch,
        "first_batch_s": compile_s,
        "fingerprint": np.asarray(first[:, -1]).ravel()[::97].tolist(),
    }


def paired(build, trials: int = 3) -> dict:
    """Seconds per step of two ways to place a training step, each ``build()`` call
    running some steps and returning their seconds per step and losses: "split" over
    the devices and "whole" (``mesh()`` patched to ``None``: one device), timed in
    alternation in this process (the machine's speed drifts between processes)."""
    import numpy as np

    from qdnb.core import sharding

    times: dict[str, list[float]] = {"split": [], "whole": []}
    losses = {}
    for _ in range(trials):
        for name in ("whole", "split"):
            saved = sharding.mesh
            if name == "whole":
                sharding.mesh = lambda: None  # nothing split: every array on one device
            try:
                seconds, losses[name] = build()
            finally:
                sharding.mesh = saved
            times[name] += seconds
    return {name: float(np.median(t)) for name, t in times.items()}, losses


def qdt_step(scale: str, steps: int = 20) -> dict:
    """QDT steps; "whole" and "split" over the devices timed in alternation (the step
    stays whole on CPU host devices: ``shard_batch(dense=True)``; "split" forces it)."""
    import jax
    import jax.numpy as jnp

    from qdnb.book.registry import config
    from qdnb.core import sharding
    from qdnb.models.qdt.data import Trajectories
    from qdnb.models.qdt.model import QDT, init_params
    from qdnb.models.qdt.train import make_train_step
    from qdnb.nets.transformer import make_optimizer

    env = config("ch4_reproducibility", scale).make_env("ant_omni")
    cfg = config("ch4_qdt", scale)
    T, B = env.episode_length, cfg.batch_size
    k = jax.random.split(jax.random.PRNGKey(2), 4)
    data = Trajectories(
        bd=jax.random.uniform(k[0], (B, env.descriptor_size)),
        obs=jax.random.normal(k[1], (B, T, env.observation_size)),
        actions=jnp.tanh(jax.random.normal(k[2], (B, T, env.action_size))),
        valid=jnp.ones((B, T), bool),
        fitness=jnp.zeros(B),
        policy=jnp.arange(B),
    )
    model = QDT(env.action_size, T, cfg.embed_dim, cfg.num_layers, cfg.num_heads, 0.0)
    optimizer = make_optimizer(cfg.learning_rate)

    def run(force_split: bool):
        sharding.SPLIT_DENSE_ON_CPU = force_split
        try:
            step = make_train_step(model, optimizer)
            params = init_params(model, k[3], env.descriptor_size, env.observation_size)
            opt_state = optimizer.init(params)
            params, opt_state, loss = step(params, opt_state, data, jax.random.PRNGKey(0))
            losses = [float(loss)]
            start = time.perf_counter()
            for i in range(steps):
                params, opt_state, loss = step(params, opt_state, data, jax.random.PRNGKey(i + 1))
                losses.append(float(loss))
            jax.block_until_ready(params)  # the loss can be ready before the update is
            return [(time.perf_counter() - start) / steps], losses
        finally:
            sharding.SPLIT_DENSE_ON_CPU = False

    per_step, losses = paired(lambda: run(jax.device_count() > 1))
    m = sharding.mesh()
    chosen = "split" if m is not None and sharding._splits_dense(m) else "whole"
    return {
        "tokens_per_step": 3 * T * B,
        "chosen": chosen,
        "seconds_per_step": per_step[chosen],
        "tokens_per_s": 3 * T * B / per_step[chosen],
        "seconds_per_step_split": per_step["split"],
        "seconds_per_step_whole": per_step["whole"],
        "losses": losses[chosen],
    }


def flt_step(scale: str, steps: int = 8) -> dict:
    """FLT steps (each simulating its batch); "whole" and "split" (what ``train`` does)
    timed in alternation."""
    import dataclasses

    import jax

    from qdnb.book.registry import config
    from qdnb.models.lenia import flow_lenia as fl
    from qdnb.models.lenia.flt import make_model, train

    cfg = config("ch5_flow_lenia", scale)
    flt_cfg = dataclasses.replace(cfg.flt, train_steps=steps + 2)
    system = fl.sample_system(jax.random.PRNGKey(3), cfg.world)
    model = make_model(cfg.world, flt_cfg)

    def run():
        seconds: list[float] = []
        key = jax.random.PRNGKey(4)
        result = train(model, flt_cfg, cfg.world, system, key, False, step_seconds=seconds)
        return seconds[2:], result.losses.tolist()  # the first compiles, the second settles

    per_step, losses = paired(run)
    return {
        "episodes_per_step": flt_cfg.batch_size,
        "chosen": "split",
        "seconds_per_step": per_step["split"],
        "episodes_per_s": flt_cfg.batch_size / per_step["split"],
        "seconds_per_step_split": per_step["split"],
        "seconds_per_step_whole": per_step["whole"],
        "whole_over_split": per_step["split"] / per_step["whole"],
        "losses": losses["split"],
    }


def measure(scale: str, stages: list[str], variant: str | None) -> dict:
    """Every stage on this process's devices (called in the child process)."""
    import jax

    from qdnb.core import sharding

    if variant == "populations":
        from qdnb.qd.qdpg import QDPG

        sharding.SPLIT_SEEDS = False
        QDPG.split = "population"
    elif variant == "padded-seeds":
        from qdnb.qd.algorithms import PolicyMapElites

        PolicyMapElites.split = "seeds"
    out = {
        "devices": jax.device_count(),
        "device_kind": str(getattr(jax.devices()[0], "device_kind", jax.devices()[0])),
        "chosen_by": sharding.device_choice().get("chosen_by"),
        "variant": variant,
    }
    for stage in stages:
        start = time.perf_counter()
        out[stage] = globals()[stage](scale)
        out[stage]["stage_wall_s"] = time.perf_counter() - start
        print(f"{stage}: {out[stage]['stage_wall_s']:.0f} s", file=sys.stderr, flush=True)
    return out


def child(name: str, devices: int | None, variant: str | None, stages, args) -> dict:
    from qdnb.core.sharding import with_device_count

    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(ROOT), env.get("PYTHONPATH")]))
    env.pop("QDNB_DEVICES", None)
    if devices == 1:
        env["QDNB_DEVICES"] = "1"
    elif devices is not None:  # forced: may exceed the cores
        env["JAX_PLATFORMS"] = "cpu"
        env["XLA_FLAGS"] = with_device_count(env.get("XLA_FLAGS", ""), devices)
    cmd = [sys.executable, __file__, "--child", "--scale", args.scale, "--stages", *stages]
    if variant:
        cmd += ["--variant", variant]
    print(f"── {name}", file=sys.stderr, flush=True)
    out = subprocess.run(cmd, env=env, stdout=subprocess.PIPE, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


RATES = {  # stage -> (rate field, unit)
    "me_ls_ant_omni": ("env_steps_per_s", "environment steps/s"),
    "pga_me_ant_omni": ("env_steps_per_s", "environment steps/s"),
    "qdpg_pointmaze_3_seeds": ("env_steps_per_s", "environment steps/s"),
    "me_pointmaze": ("env_steps_per_s", "environment steps/s"),
    "qdpg_pointmaze": ("env_steps_per_s", "environment steps/s"),
    "es_pointmaze": ("env_steps_per_s", "environment steps/s"),
    "flow_lenia_batch": ("episodes_per_s", "episodes/s"),
    "qdt_step": ("tokens_per_s", "tokens/s"),
    "flt_step": ("episodes_per_s", "training episodes/s"),
}


def agreement(stage: str, run: dict, reference: dict) -> dict:
    if "fingerprint" in run:
        return {"bitwise_equal_to_one_device": run.pop("fingerprint") == reference["fingerprint"]}
    gaps = [abs(a - b) / max(abs(b), 1e-12) for a, b in zip(run["losses"], reference["losses"])]
    return {"losses_max_relative_gap_to_one_device": max(gaps)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scale", default="small")
    parser.add_argument("--stages", nargs="+", default=list(STAGES), choices=STAGES)
    parser.add_argument("--sweep", type=int, nargs="*", default=[4], help="forced device counts")
    parser.add_argument("--real", action="store_true", help="this machine's own devices only")
    parser.add_argument("--variant", choices=sorted(VARIANTS), help=argparse.SUPPRESS)
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--out", default=str(ROOT / "bench" / "results" / "scale_out.json"))
    args = parser.parse_args()
    if args.child:
        print(json.dumps(measure(args.scale, args.stages, args.variant)))
        return
    from qdnb.core.sharding import cores, default_host_devices

    began = time.perf_counter()
    configs = {"default": child("default", None, None, args.stages, args)}
    if not args.real:
        configs = {"1": child("1 device", 1, None, args.stages, args), **configs}
        for variant, touched in VARIANTS.items():
            stages = [s for s in args.stages if s in touched]
            if stages:
                configs[variant] = child(variant, None, variant, stages, args)
        for n in args.sweep:
            configs[f"{n} forced"] = child(f"{n} forced", n, None, args.stages, args)
    reference = configs.get("1", configs["default"])
    table = {}
    for stage in args.stages:
        field, unit = RATES[stage]
        row = {"unit": unit}
        for name, run in configs.items():
            if stage not in run:
                continue
            r = run[stage]
            row[name] = {
                "devices": run["devices"],
                "rate": round(r[field], 1),
                **{k: round(v, 4) for k, v in r.items() if isinstance(v, float) and k != field},
                **agreement(stage, dict(r), reference[stage]),
            }
        if "1" in row:
            row["default_over_one_device"] = round(row["default"]["rate"] / row["1"]["rate"], 3)
        table[stage] = row
    out = {
        "scale": args.scale,
        "cores": cores(),
        "default_devices": default_host_devices(),
        "real_devices": args.real,
        "wall_s": round(time.perf_counter() - began, 1),
        "stages": table,
    }
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    from qdnb.book.provenance import write_result  # (jax in this process only now)

    write_result(Path(args.out), out)
    print(json.dumps({s: {k: v.get("rate") for k, v in row.items() if isinstance(v, dict)}
                      for s, row in table.items()}, indent=1))  # fmt: skip


if __name__ == "__main__":
    main()
