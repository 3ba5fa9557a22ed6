"""One MAP-Elites loop, one PGA-ME loop and one QDT training step on however many
devices this process has (set ``XLA_FLAGS=--xla_force_host_platform_device_count=N``
before it starts): their results go to the ``.npz`` named on the command line, for
``tests/test_sharding.py`` to compare across device counts, and
``bench/scale_out.py`` to time."""

from __future__ import annotations

import sys

import jax
import jax.numpy as jnp
import numpy as np

from qdnb.envs import make_env
from qdnb.nets.mlp import MLP
from qdnb.qd.algorithms import PolicyMapElites, run_seeds
from qdnb.qd.cvt import grid_centroids
from qdnb.qd.pga import PGAMapElites
from qdnb.rl.td3 import TD3Config


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
    out = {}
    pga = PGAMapElites(
        **common,
        td3_config=TD3Config(batch_size=16, critic_hidden=(8,)),
        num_critic_steps=4,
        num_pg_steps=2,
        buffer_size=2000,
    )
    keys = jax.random.split(jax.random.PRNGKey(0), 2)
    for name, algo in (("ME", PolicyMapElites(**common)), ("PGA-ME", pga)):
        states, _, history = run_seeds(algo, keys, iterations, 1, progress=False)
        out[f"{name}/fitnesses"] = np.asarray(states.repertoire.fitnesses)
        out[f"{name}/descriptors"] = np.asarray(history["descriptors"])
    return out


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
    results = {"devices": np.asarray(jax.device_count()), **map_elites_and_pga(), **qdt_step()}
    np.savez(sys.argv[1], **results)
