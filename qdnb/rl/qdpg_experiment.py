"""Chapter 3's experiment: QD-PG, its ablations, TD3 and PGA-ME on one environment.

``run_environment(cfg, env_name, key)`` runs every method of the config on the
same environment-step budget (each method's seeds at once, ``vmap``), and
returns, per method, the history of every iteration (performance, grid
coverage, environment steps, every evaluated policy's descriptor and fitness)
and the final MAP-Elites grids.

Performance follows Table 3.4: the episode return on Point-Maze and Ant-Trap,
the best reward of the episode (minus the closest distance to the goal) on
Ant-Maze.  For the MAP-Elites methods the performance at an iteration is the
best solution of the grid; for TD3 it is the greedy episode of its actor.
"""

from __future__ import annotations

import time
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from qdnb.envs import make_env
from qdnb.envs.base import Env
from qdnb.envs.pointmaze import in_goal
from qdnb.qd.algorithms import PGAMapElites, run_seeds
from qdnb.qd.cvt import grid_centroids
from qdnb.qd.metrics import grid_cell
from qdnb.rl.networks import MLP
from qdnb.rl.qdpg import QDPG, TD3Agent
from qdnb.rl.td3 import TD3Config
from qdnb.scale import QDPG_METHODS, QDPGConfig

ENVIRONMENTS = ("pointmaze", "antmaze", "anttrap")
QDPG_UPDATES = {"QD-PG": "alternate", "QD-PG Sum": "sum", "D-PG": "diversity", "Q-PG": "quality"}


def make_task_env(cfg: QDPGConfig, env_name: str) -> Env:
    return make_env(env_name, episode_length=cfg.task(env_name).episode_length)


def fitness_offset(env_name: str, env: Env) -> float:
    """A lower bound of the performance, so that QD scores count every elite
    positively: the whole episode at the far corner (Point-Maze), the far corner
    of the maze (Ant-Maze), running backwards at 5 m/s (Ant-Trap)."""
    span = float(np.linalg.norm(np.asarray(env.descriptor_high) - np.asarray(env.descriptor_low)))
    return {"pointmaze": -span * env.episode_length, "antmaze": -span,
            "anttrap": -5.0 * env.episode_length}[env_name]


def build_algorithms(cfg: QDPGConfig, env_name: str, env: Env | None = None) -> dict[str, Any]:
    """Every method of ``cfg`` on ``env_name``, with its Table 3.2 settings."""
    task = cfg.task(env_name)
    env = env if env is not None else make_task_env(cfg, env_name)
    network = MLP(task.policy_hidden + (env.action_size,), activation="relu")
    td3_config = TD3Config(gamma=cfg.discount, tau=cfg.tau, policy_delay=cfg.policy_delay,
                           critic_lr=task.learning_rate, actor_lr=task.learning_rate,
                           mutation_lr=task.mutation_learning_rate,
                           batch_size=cfg.td3_batch_size, critic_hidden=task.critic_hidden,
                           optimizer=task.optimizer)
    centroids = grid_centroids((task.bins, task.bins), env.descriptor_low, env.descriptor_high)
    shared = dict(env=env, network=network, batch_size=task.num_actors, iso_sigma=cfg.iso_sigma,
                  line_sigma=cfg.line_sigma, centroids=centroids, fitness_offset=fitness_offset(env_name, env))
    algorithms: dict[str, Any] = {}
    for method in cfg.methods(env_name):
        if method in QDPG_UPDATES:
            algorithms[method] = QDPG(
                **shared, update=QDPG_UPDATES[method], td3_config=td3_config,
                num_critic_steps=task.num_critic_steps, num_pg_steps=task.num_pg_steps,
                buffer_size=task.buffer_size, archive_size=task.archive_size,
                archive_threshold=task.archive_threshold, archive_k=cfg.archive_k)
        elif method == "PGA-ME":
            algorithms[method] = PGAMapElites(
                **shared, td3_config=td3_config, num_critic_steps=task.num_critic_steps,
                num_pg_steps=task.num_pg_steps, buffer_size=task.buffer_size)
        elif method == "TD3":
            algorithms[method] = TD3Agent(
                env=env, network=network, td3_config=td3_config, num_episodes=task.num_actors,
                num_critic_steps=task.num_critic_steps, exploration_noise=cfg.exploration_noise,
                buffer_size=task.buffer_size)
        else:
            raise ValueError(f"unknown method {method!r}; valid: {', '.join(QDPG_METHODS)}")
    return algorithms


def final_grid(state: Any) -> dict[str, np.ndarray] | None:
    """The final MAP-Elites grid of a run (leading axis: seeds), on the host."""
    rep = getattr(state, "repertoire", None)
    if rep is None:
        return None
    return jax.device_get({"genotypes": rep.genotypes, "fitnesses": rep.fitnesses,
                           "descriptors": rep.descriptors, "centroids": rep.centroids})


def run_environment(cfg: QDPGConfig, env_name: str, key: jax.Array, progress: bool = True,
                    methods: tuple[str, ...] | None = None) -> dict[str, Any]:
    """Run every method of ``cfg`` (or those of ``methods``) on ``env_name``,
    each on ``cfg.seeds(env_name, method)`` seeds.

    Returns ``{"env", "env_name", "methods": {name: {"history", "grid",
    "final_performance", "coverage", "env_steps", "seconds",
    "steady_seconds_per_iteration"}}}``; ``history``
    arrays have shape ``(num_seeds, num_iterations + 1, ...)``.
    """
    task = cfg.task(env_name)
    env = make_task_env(cfg, env_name)
    algorithms = build_algorithms(cfg, env_name, env)
    if methods is not None:
        unknown = set(methods) - set(algorithms)
        if unknown:
            raise ValueError(f"methods {sorted(unknown)} are not run on {env_name}; valid: {', '.join(algorithms)}")
        algorithms = {m: algorithms[m] for m in methods}
    out: dict[str, Any] = {"env": env, "env_name": env_name, "methods": {}}
    for method, algo in algorithms.items():
        keys = jax.random.split(key, cfg.seeds(env_name, method))
        start, chunks = time.perf_counter(), []
        states, _, history = run_seeds(algo, keys, task.num_iterations - 1, cfg.chunk_size,
                                       progress=progress, desc=f"{env_name} {method}", chunk_seconds=chunks)
        history = jax.device_get(history)
        seconds = time.perf_counter() - start
        steps = np.cumsum(history["env_steps"], axis=1)
        grid = final_grid(states)
        out["methods"][method] = {
            "history": history,
            "grid": grid,
            "final_performance": history["max_fitness"][:, -1],
            "coverage": (np.mean(grid["fitnesses"] > -np.inf, axis=1) if grid is not None
                         else grid_coverage(history["descriptors"], env, task.bins)),
            "env_steps": steps[:, -1],
            "cumulative_steps": steps,
            "seconds": seconds,
            "steady_seconds_per_iteration": steady_rate(chunks, cfg.chunk_size, seconds / task.num_iterations),
        }
    return out


def steady_rate(chunk_seconds: list[float], chunk_size: int, fallback: float) -> float:
    """Seconds per iteration of a compiled loop: the median full chunk after the
    first (which compiles) and before the last (which may be partial);
    ``fallback`` when the loop ran in one chunk."""
    if len(chunk_seconds) < 2:
        return fallback
    return float(np.median(chunk_seconds[1:-1] or chunk_seconds)) / chunk_size


def grid_coverage(descriptors: np.ndarray, env: Env, bins: int) -> np.ndarray:
    """Fraction of the ``bins x bins`` grid cells reached by any evaluated
    episode, per seed (``descriptors``: seeds x iterations x episodes x 2).  For
    TD3, which keeps no grid, this is the grid it would have filled."""
    d = descriptors.reshape(descriptors.shape[0], -1, descriptors.shape[-1])
    cells = np.asarray(grid_cell(d, (bins, bins), env.descriptor_low, env.descriptor_high))
    return np.array([len(np.unique(c)) / bins**2 for c in cells])


def in_exit_zone(descriptors: np.ndarray) -> np.ndarray:
    """Whether each Point-Maze final position lies in the exit zone (an episode
    stops there, so an episode that entered the zone ends in it); the shape of
    ``descriptors`` without its last axis."""
    flat = np.asarray(descriptors).reshape(-1, 2)
    return np.asarray(jax.vmap(in_goal)(flat)).reshape(np.shape(descriptors)[:-1])


def reached_goal(descriptors: np.ndarray) -> np.ndarray:
    """Per seed (leading axis), whether any evaluated Point-Maze episode ended in
    the exit zone."""
    return in_exit_zone(descriptors).reshape(np.shape(descriptors)[0], -1).any(axis=1)


def steps_to_exit(result: dict[str, Any]) -> np.ndarray:
    """Per seed, the environment steps a Point-Maze method had used when one of
    its evaluated episodes first ended in the exit zone (``nan`` if none did);
    ``result`` is one method's entry of ``run_environment``."""
    hit = in_exit_zone(result["history"]["descriptors"])  # seeds x iterations x episodes
    hit = hit.reshape(hit.shape[0], hit.shape[1], -1).any(axis=2)
    steps = np.asarray(result["cumulative_steps"], float)
    return np.where(hit.any(axis=1), steps[np.arange(len(steps)), np.argmax(hit, axis=1)], np.nan)
