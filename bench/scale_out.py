"""Scale-out: environment steps per second of ME-LS on Ant-Omni and tokens per second
of QDT training at 1, 2 and 4 forced host devices (each count in its own process,
``XLA_FLAGS=--xla_force_host_platform_device_count=N``), and on a GPU machine its
real devices, with the agreement check across counts.  Writes
``bench/results/scale_out.json``.

    python bench/scale_out.py [--scale tiny] [--devices 1 2 4] [--iterations 5]
    python bench/scale_out.py --real           # on a GPU machine: its own devices

Forced host devices share the machine's cores, so on a 2-core CPU they show what
splitting costs, not what it gains; a GPU machine's devices are real.  ME-LS runs
with the chapter's config at ``--scale``; whether its final repertoire is the same bit
for bit at every device count is recorded (each device simulates its share of the
episodes with the same keys, but XLA compiles the physics for the shard's shape, and
a different shape may round differently, which the simulation then amplifies).  The
QDT step trains on random trajectories of the chapter's shapes; its losses agree to
float32 rounding (the gradient's sum is split).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def measure(scale: str, iterations: int, qdt_steps: int) -> dict:
    """Both rates on this process's devices (called in the child process)."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    from qdnb.book.registry import config
    from qdnb.chapters.ch4_reproducibility import build_algorithms, fitness_offset
    from qdnb.models.qdt.data import Trajectories
    from qdnb.models.qdt.model import QDT, init_params
    from qdnb.models.qdt.train import make_train_step
    from qdnb.nets.mlp import MLP
    from qdnb.nets.transformer import make_optimizer
    from qdnb.qd.algorithms import run_seeds
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
    me_ls = build_algorithms(cfg, env, network, centroids, offset)["ME-LS"]
    keys = jax.random.split(jax.random.PRNGKey(1), 1)
    chunks: list[float] = []  # one iteration each; the first includes compilation
    states, _, history = run_seeds(me_ls, keys, iterations, 1, progress=False, chunk_seconds=chunks)
    per_iteration = float(np.median(chunks[1:]))
    steps = float(np.mean(np.asarray(history["env_steps"])[:, 1:]))  # per iteration

    cfg_qdt = config("ch4_qdt", scale)
    T, B = env.episode_length, cfg_qdt.batch_size
    k = jax.random.split(jax.random.PRNGKey(2), 4)
    data = Trajectories(
        bd=jax.random.uniform(k[0], (B, env.descriptor_size)),
        obs=jax.random.normal(k[1], (B, T, env.observation_size)),
        actions=jnp.tanh(jax.random.normal(k[2], (B, T, env.action_size))),
        valid=jnp.ones((B, T), bool),
        fitness=jnp.zeros(B),
        policy=jnp.arange(B),
    )
    model = QDT(env.action_size, T, cfg_qdt.embed_dim, cfg_qdt.num_layers, cfg_qdt.num_heads, 0.0)
    params = init_params(model, k[3], env.descriptor_size, env.observation_size)
    optimizer = make_optimizer(cfg_qdt.learning_rate)
    step = make_train_step(model, optimizer)
    opt_state = optimizer.init(params)
    params, opt_state, loss = step(params, opt_state, data, jax.random.PRNGKey(0))  # compile
    losses = [float(loss)]
    start = time.perf_counter()
    for i in range(qdt_steps):
        params, opt_state, loss = step(params, opt_state, data, jax.random.PRNGKey(i + 1))
        losses.append(float(loss))
    qdt_seconds = time.perf_counter() - start
    return {
        "devices": jax.device_count(),
        "device_kind": str(getattr(jax.devices()[0], "device_kind", jax.devices()[0])),
        "me_ls": {
            "iterations": iterations,
            "env_steps_per_iteration": steps,
            "seconds_per_iteration": round(per_iteration, 4),
            "env_steps_per_s": round(steps / per_iteration, 1),
            "first_iteration_s": round(chunks[0], 1),
            "fitnesses": np.asarray(me_ls.elites(states.repertoire).fitnesses).tolist(),
        },
        "qdt": {
            "steps": qdt_steps,
            "tokens_per_step": 3 * T * B,
            "seconds": round(qdt_seconds, 3),
            "tokens_per_s": round(3 * T * B * qdt_steps / qdt_seconds, 1),
            "losses": losses,
        },
    }


def child(n: int | None, args) -> dict:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(ROOT), env.get("PYTHONPATH")]))
    if n is not None:
        env["JAX_PLATFORMS"] = "cpu"
        env["XLA_FLAGS"] = " ".join(
            filter(None, [env.get("XLA_FLAGS"), f"--xla_force_host_platform_device_count={n}"])
        )
    cmd = [sys.executable, __file__, "--child", "--scale", args.scale]
    cmd += ["--iterations", str(args.iterations), "--qdt-steps", str(args.qdt_steps)]
    out = subprocess.run(cmd, env=env, capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scale", default="tiny")
    parser.add_argument("--devices", type=int, nargs="+", default=[1, 2, 4])
    parser.add_argument("--iterations", type=int, default=5)
    parser.add_argument("--qdt-steps", type=int, default=10)
    parser.add_argument("--real", action="store_true", help="this machine's own devices")
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--out", default=str(ROOT / "bench" / "results" / "scale_out.json"))
    args = parser.parse_args()
    if args.child:
        print(json.dumps(measure(args.scale, args.iterations, args.qdt_steps)))
        return
    runs = [child(None, args)] if args.real else [child(n, args) for n in args.devices]
    first_fit, first_losses = runs[0]["me_ls"]["fitnesses"], runs[0]["qdt"]["losses"]
    for r in runs:  # the agreement check, against the first device count
        r["me_ls_repertoire_bitwise_equal"] = r["me_ls"].pop("fitnesses") == first_fit
        gaps = [abs(a - b) / max(abs(b), 1e-12) for a, b in zip(r["qdt"]["losses"], first_losses)]
        r["qdt_losses_max_relative_gap"] = max(gaps)
    out = {
        "scale": args.scale,
        "machine": platform.processor() or platform.machine(),
        "cpu_count": os.cpu_count(),
        "forced_host_devices": not args.real,
        "runs": runs,
        "note": "forced host devices share the CPU's cores: they measure the cost of "
        "splitting, not a speed-up",
    }
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(out, indent=2) + "\n")
    print(json.dumps({r["devices"]: (r["me_ls"]["env_steps_per_s"], r["qdt"]["tokens_per_s"])
                      for r in runs}))  # fmt: skip


if __name__ == "__main__":
    main()
