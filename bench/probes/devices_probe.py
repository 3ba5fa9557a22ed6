"""A loop of each kind on however many devices this process has (``QDNB_DEVICES=N``, or
``XLA_FLAGS=--xla_force_host_platform_device_count=N`` set before it starts), at tiny
settings: the GA, Novelty Search, MAP-Elites and PGA-ME on Point-Maze (two seeds), a Brax
MAP-Elites loop (Chapter 4's ME on Ant-Omni, one seed: its population split), QD-PG on
Point-Maze (two seeds: the seeds split when the devices divide them; and three, padded), ME-
ES generations (two seeds), the FLT's training steps (simulation and training split) and a
QDT training step. Their results go to the ``.npz`` named on the command line, for
``tests/test_sharding.py`` to compare across device counts and across runs."""

from __future__ import annotations

import dataclasses
import sys

import jax
import jax.numpy as jnp
import numpy as np

from qdnb.book.registry import config
from qdnb.envs import make_env
from qdnb.nets.mlp import MLP
from qdnb.qd.algorithms import GeneticAlgorithm, NoveltySearch, PolicyMapElites, run_seeds
from qdnb.qd.cvt import grid_centroids
from qdnb.qd.pga import PGAMapElites
from qdnb.rl.td3 import TD3Config


def history_of(name: str, algorithm, seeds: int, iterations: int, chunk: int = 1) -> dict:
    keys = jax.random.split(jax.random.PRNGKey(0), seeds)
    _, _, history = run_seeds(algorithm, keys, iterations, chunk, progress=False)
    return {f"{name}/{k}": np.asarray(history[k]) for k in ("fitnesses", "descriptors")}


def map_elites_and_pga(batch: int = 8, iterations: int = 3) -> dict[str, np.ndarray]:
    env = make_env("pointmaze", episode_length=20)
    common = dict(
        env=env,
        network=MLP((8, env.action_size)),
        batch_size=batch,
        iso_sigma=0.01,
        line_sigma=0.1,
        centroids=grid_centroids((5, 5), (-1, -1), (1, 1)),
    )
    pga = PGAMapElites(
        **common,
        td3_config=TD3Config(batch_size=16, critic_hidden=(8,)),
        num_critic_steps=4,
        num_pg_steps=2,
        buffer_size=2000,
    )
    centroids = common.pop("centroids")
    return {
        **history_of("GA", GeneticAlgorithm(**common, population_size=8), 2, iterations),
        **history_of("NS", NoveltySearch(**common, population_size=8, archive_size=64), 2, 3),
        **history_of("ME", PolicyMapElites(**common, centroids=centroids), 2, iterations),
        **history_of("PGA-ME", pga, 2, iterations),
    }


def brax_map_elites() -> dict[str, np.ndarray]:
    from qdnb.chapters.ch4_reproducibility import build_algorithms, fitness_offset

    cfg = config("ch4_reproducibility", "tiny")
    env = cfg.make_env("ant_omni")
    network = MLP(cfg.policy_hidden + (env.action_size,))
    centroids = grid_centroids((4, 4), env.descriptor_low, env.descriptor_high)
    me = build_algorithms(cfg, env, network, centroids, fitness_offset("ant_omni", 50))["ME"]
    return history_of("ME-brax", me, 1, 2)


def qdpg_and_es() -> dict[str, np.ndarray]:
    from qdnb.chapters.ch3_qdpg import build_algorithms

    qdpg = build_algorithms(config("ch3_qdpg", "tiny"), "pointmaze", methods=("QD-PG",))
    es = config("ch3_evolution", "tiny").es_tasks("pointmaze")
    mees = build_algorithms(es, "pointmaze", methods=("ME-ES",))
    return {
        **history_of("QD-PG", qdpg["QD-PG"], 2, 3),
        **history_of("QD-PG-3-seeds", qdpg["QD-PG"], 3, 2),  # padded to 4 on 2 devices
        **history_of("ME-ES", mees["ME-ES"], 2, 3),
    }


def flt_steps(steps: int = 3) -> dict[str, np.ndarray]:
    from qdnb.models.lenia import flow_lenia as fl
    from qdnb.models.lenia.flt import make_model, train

    cfg = config("ch5_flow_lenia", "tiny")
    flt_cfg = dataclasses.replace(cfg.flt, train_steps=steps)
    system = fl.sample_system(jax.random.PRNGKey(3), cfg.world)
    model = make_model(cfg.world, flt_cfg)
    result = train(model, flt_cfg, cfg.world, system, jax.random.PRNGKey(4), progress=False)
    return {"FLT/losses": result.losses, "FLT/mean_frames": result.mean_frames}


def qdt_step(batch: int = 8) -> dict[str, np.ndarray]:
    from qdnb.models.qdt.data import Trajectories
    from qdnb.models.qdt.model import QDT, init_params
    from qdnb.models.qdt.train import loss_and_grads, make_train_step
    from qdnb.nets.transformer import make_optimizer

    T, obs, act, bd = 6, 5, 2, 2
    k = jax.random.split(jax.random.PRNGKey(1), 4)
    data = Trajectories(
        obs=jax.random.normal(k[0], (batch, T, obs)),
        actions=jnp.tanh(jax.random.normal(k[1], (batch, T, act))),
        bd=jax.random.uniform(k[2], (batch, bd)),
        valid=jnp.ones((batch, T), bool),
        fitness=jnp.zeros((batch,)),
        policy=jnp.arange(batch),
    )
    model = QDT(act, T, 16, 1, 2, 0.0)
    params = init_params(model, k[3], bd, obs)
    optimizer = make_optimizer(1e-3)
    loss, grads = jax.jit(lambda p: loss_and_grads(model, p, data))(params)
    stepped, _, step_loss = make_train_step(model, optimizer)(
        params, optimizer.init(params), data, jax.random.PRNGKey(2)
    )
    out = {"QDT/loss": np.asarray(loss), "QDT/step_loss": np.asarray(step_loss)}
    for i, (g, p) in enumerate(zip(jax.tree.leaves(grads), jax.tree.leaves(stepped))):
        out[f"QDT/grad{i}"], out[f"QDT/param{i}"] = np.asarray(g), np.asarray(p)
    return out


if __name__ == "__main__":
    results = {
        "devices": np.asarray(jax.device_count()),
        **map_elites_and_pga(),
        **brax_map_elites(),
        **qdpg_and_es(),
        **flt_steps(),
        **qdt_step(),
    }
    np.savez(sys.argv[1], **results)
