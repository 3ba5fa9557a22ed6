"""Chapter 3's experiment: every method of the config on one environment's budget, seeds at
once, its results, and the QD-PG runs other pages reuse.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from functools import cached_property
from typing import TYPE_CHECKING, Any

import jax
import numpy as np

from qdnb.chapters.ch3_qdpg.measures import (
    ANTMAZE_SOLVED,
    grid_coverage,
    reachable_coverage,
    steps_to_exit,
    until_goal,
)
from qdnb.chapters.ch3_qdpg.methods import METHODS
from qdnb.chapters.ch3_qdpg.settings import ENVIRONMENTS, fitness_offset, make_task_env
from qdnb.core import health, paths
from qdnb.core.config import config_hash
from qdnb.core.evaluation import Algorithm
from qdnb.core.io import load_arrays, load_summary, save_arrays
from qdnb.core.names import mean_sd
from qdnb.envs.base import Env
from qdnb.nets.mlp import MLP
from qdnb.qd.algorithms import run_seeds
from qdnb.qd.cvt import grid_centroids
from qdnb.rl.td3 import TD3Config

if TYPE_CHECKING:
    from qdnb.chapters.ch3_qdpg.settings import QDPGConfig


def policy_network(cfg: QDPGConfig, env_name: str, env: Env) -> MLP:
    """Every method's policy on ``env_name``: Table 3.2's widths, relu (QDax's)."""
    return MLP(cfg.task(env_name).policy_hidden + (env.action_size,), activation="relu")


def build_algorithms(
    cfg: QDPGConfig,
    env_name: str,
    env: Env | None = None,
    methods: tuple[str, ...] | None = None,
) -> dict[str, Algorithm]:
    """The methods of ``cfg`` on ``env_name`` (or those of ``methods``, any of
    ``METHODS``), with their Table 3.2 settings."""
    methods = cfg.methods(env_name) if methods is None else methods
    unknown = set(methods) - set(METHODS)
    if unknown:
        raise ValueError(f"unknown methods {sorted(unknown)}; valid: {', '.join(METHODS)}")
    task = cfg.task(env_name)
    env = env if env is not None else make_task_env(cfg, env_name)
    network = policy_network(cfg, env_name, env)
    td3_config = TD3Config(
        gamma=cfg.discount,
        tau=cfg.tau,
        policy_delay=cfg.policy_delay,
        critic_lr=task.learning_rate,
        actor_lr=task.learning_rate,
        mutation_lr=task.mutation_learning_rate,
        batch_size=cfg.td3_batch_size,
        critic_hidden=task.critic_hidden,
        optimizer=task.optimizer,
    )
    centroids = grid_centroids((task.bins, task.bins), env.descriptor_low, env.descriptor_high)
    shared = dict(
        env=env,
        network=network,
        batch_size=task.num_actors,
        iso_sigma=cfg.iso_sigma,
        line_sigma=cfg.line_sigma,
        centroids=centroids,
        fitness_offset=fitness_offset(env_name, env),
    )
    parts = {"env": env, "network": network, "td3": td3_config, "shared": shared}
    return {method: METHODS[method](cfg, task, parts) for method in methods}


def final_grid(state: Any) -> dict[str, np.ndarray] | None:
    """The final MAP-Elites grid of a run (leading axis: seeds), on the host."""
    rep = getattr(state, "repertoire", None)
    if rep is None:
        return None
    return jax.device_get(
        {
            "genotypes": rep.genotypes,
            "fitnesses": rep.fitnesses,
            "descriptors": rep.descriptors,
            "centroids": rep.centroids,
        }
    )


@dataclass(frozen=True)
class MethodResult:
    """One method on one environment, all its seeds (axis 0 of every array).

    ``history``: per iteration (initial batch first), the algorithm's metrics, the
    environment steps, and every evaluated policy's descriptor and fitness;
    ``grid`` the final MAP-Elites grid (``None`` for TD3); ``final_performance``
    Table 3.4's performance at the end; ``coverage`` the grid's final coverage;
    ``cumulative_steps`` the environment steps after each iteration;
    ``steady_seconds_per_iteration`` the median compiled chunk's time; ``diverged`` per
    seed where it went NaN (``qdnb.core.health``; ``None``: it stayed finite).  A diverged
    seed's final performance and coverage are NaN: its numbers mean nothing, and every
    mean and count of the page leaves it out (``nanmean``; "most seeds" counts it as a
    failure)."""

    history: dict[str, np.ndarray]
    grid: dict[str, Any] | None
    final_performance: np.ndarray
    coverage: np.ndarray
    env_steps: np.ndarray
    cumulative_steps: np.ndarray
    seconds: float
    steady_seconds_per_iteration: float
    diverged: tuple[health.Divergence | None, ...] = ()
    policy: Any = None  # seed 0's policy to watch (``shown_policy``); None when read from disk

    @property
    def kept(self) -> np.ndarray:
        """Per seed, whether it stayed finite (is counted in means)."""
        n = len(self.final_performance)
        return np.array([i >= len(self.diverged) or self.diverged[i] is None for i in range(n)])

    def performance_text(self, digits: int = 1) -> str:
        """``mean ± std`` of the final performance over the seeds that stayed finite, and
        how many diverged."""
        return mean_sd(self.final_performance, digits, self.num_diverged)

    @property
    def num_diverged(self) -> int:
        return int(np.sum(~self.kept))

    @cached_property
    def exit_steps(self) -> np.ndarray:
        """Point-Maze: per seed, ``steps_to_exit`` (``nan`` where no episode ended in
        the exit zone)."""
        return steps_to_exit(self)

    @property
    def reached_exit(self) -> np.ndarray:
        """Point-Maze: per seed, whether an evaluated episode ended in the exit zone."""
        return ~np.isnan(self.exit_steps)

    def steps_to_goal(self, solved: float = ANTMAZE_SOLVED) -> list[float]:
        """Ant-Maze (Table 3.3): per seed, the environment steps when the best reward
        first exceeded ``solved`` (``inf`` if it never did)."""
        hit = self.history["max_fitness"] > solved
        return [
            float(self.cumulative_steps[s][hit[s]][0]) if hit[s].any() else float("inf")
            for s in range(hit.shape[0])
        ]


@dataclass(frozen=True)
class EnvironmentResult:
    env: Env
    env_name: str
    methods: dict[str, MethodResult]


def run_environment(
    cfg: QDPGConfig,
    env_name: str,
    key: jax.Array,
    progress: bool = True,
    methods: tuple[str, ...] | None = None,
    stop_at_goal: bool = False,
) -> EnvironmentResult:
    """Run every method of ``cfg`` (or those of ``methods``, any of ``METHODS``) on
    ``env_name``, each on ``cfg.seeds(env_name, method)`` seeds; ``history`` arrays
    have shape ``(num_seeds, num_iterations + 1, ...)``, or fewer iterations with
    ``stop_at_goal``: a method then stops after the chunk in which its last seed
    reached the goal (``until_goal``)."""
    env = make_task_env(cfg, env_name)
    algorithms = build_algorithms(cfg, env_name, env, methods)
    results = {
        method: run_method(
            cfg,
            env_name,
            env,
            algo,
            jax.random.split(key, cfg.seeds(env_name, method)),
            progress=progress,
            desc=f"{env_name} {method}",
            stop_at_goal=stop_at_goal,
        )
        for method, algo in algorithms.items()
    }
    return EnvironmentResult(env, env_name, results)


def run_method(
    cfg: QDPGConfig,
    env_name: str,
    env: Env,
    algo: Algorithm,
    keys: jax.Array,
    progress: bool = True,
    desc: str | None = None,
    stop_at_goal: bool = False,
) -> MethodResult:
    """One algorithm on ``env_name`` for the task's budget, one seed per key (at once):
    ``run_environment``'s entry for a method, and the benchmarks' for a variant."""
    task = cfg.task(env_name)
    start, chunks = time.perf_counter(), []
    states, _, history = run_seeds(
        algo,
        keys,
        task.num_iterations - 1,
        cfg.chunk_size,
        progress=progress,
        desc=desc,
        chunk_seconds=chunks,
        stop=until_goal(env_name, len(keys)) if stop_at_goal else None,
    )
    history = jax.device_get(history)
    seconds = time.perf_counter() - start
    steps = np.cumsum(history["env_steps"], axis=1)
    grid = final_grid(states)
    policy = shown_policy(states, grid)
    diverged = tuple(health.divergences(history["nan_parts"], health.part_names(states)))
    lost = np.array([d is not None for d in diverged])
    coverage = (
        reachable_coverage(grid["fitnesses"] > -np.inf, env_name, env, task.bins)
        if grid is not None
        else grid_coverage(history["descriptors"], env, task.bins, env_name)
    )
    return MethodResult(
        history=history,
        grid=grid,
        final_performance=np.where(lost, np.nan, history["max_fitness"][:, -1]),
        coverage=np.where(lost, np.nan, coverage),
        env_steps=steps[:, -1],
        cumulative_steps=steps,
        seconds=seconds,
        steady_seconds_per_iteration=steady_rate(
            chunks, cfg.chunk_size, seconds / task.num_iterations
        ),
        diverged=diverged,
        policy=policy,
    )


def shown_policy(states: Any, grid: dict[str, np.ndarray] | None) -> Any:
    """Seed 0's policy a reader watches (the chapter's videos): the fittest elite of its
    final grid, or TD3's actor, which it plays greedily; ``None`` for another method."""
    if grid is not None:
        fitness = np.nan_to_num(np.asarray(grid["fitnesses"][0], float), nan=-np.inf)
        if not np.isfinite(fitness).any():  # an empty grid, or a seed that diverged
            return None
        return jax.tree.map(lambda x: x[0, int(np.argmax(fitness))], grid["genotypes"])
    td3 = getattr(states, "td3", None)
    return None if td3 is None else jax.device_get(jax.tree.map(lambda x: x[0], td3.actor))


def steady_rate(chunk_seconds: list[float], chunk_size: int, fallback: float) -> float:
    """Seconds per iteration of a compiled loop: the median full chunk after the
    first (which compiles) and before the last (which may be partial);
    ``fallback`` when the loop ran in one chunk."""
    if len(chunk_seconds) < 2:
        return fallback
    return float(np.median(chunk_seconds[1:-1] or chunk_seconds)) / chunk_size


# ----- QD-PG's results, for Chapter 3's other pages (the baselines, the evolution strategies) -----


def qdpg_path(scale: str, env_name: str):
    return paths.run_dir(scale, "ch3_qdpg") / f"qdpg_{env_name}.npz"


def save_method_result(path, digest: str, r: MethodResult):
    """One method's result as an ``.npz`` artifact tagged with its config hash: its
    history, its grid's fitnesses, descriptors and centroids (not the policies)."""
    arrays = {f"history_{k}": v for k, v in r.history.items()}
    if r.grid is not None:
        arrays |= {f"grid_{k}": v for k, v in r.grid.items() if k != "genotypes"}
    return save_arrays(
        path,
        digest,
        **arrays,
        final_performance=r.final_performance,
        coverage=r.coverage,
        env_steps=r.env_steps,
        cumulative_steps=r.cumulative_steps,
        seconds=r.seconds,
        steady_seconds_per_iteration=r.steady_seconds_per_iteration,
        diverged_iteration=np.array([-1 if d is None else d.iteration for d in r.diverged]),
        diverged_parts=np.array(["" if d is None else ",".join(d.parts) for d in r.diverged]),
    )


def load_method_result(path, digest: str) -> MethodResult | None:
    """``save_method_result``'s result (its grid without policies), or ``None`` when
    missing or computed under another config."""
    a = load_arrays(path, digest)
    if a is None:
        return None
    part = lambda prefix: {k[len(prefix) :]: v for k, v in a.items() if k.startswith(prefix)}
    return MethodResult(
        history=part("history_"),
        grid=part("grid_") or None,
        final_performance=a["final_performance"],
        coverage=a["coverage"],
        env_steps=a["env_steps"],
        cumulative_steps=a["cumulative_steps"],
        seconds=float(a["seconds"]),
        steady_seconds_per_iteration=float(a["steady_seconds_per_iteration"]),
        diverged=tuple(
            None if i < 0 else health.Divergence(int(i), tuple(str(p).split(",")))
            for i, p in zip(a.get("diverged_iteration", []), a.get("diverged_parts", []))
        ),
    )


def save_qdpg_results(
    cfg: QDPGConfig, scale: str, results_by_env: dict[str, EnvironmentResult]
) -> list:
    """QD-PG's result on each environment of this run, for the chapter's next pages."""
    digest = config_hash(cfg)
    return [
        save_method_result(qdpg_path(scale, env_name), digest, res.methods["QD-PG"])
        for env_name, res in results_by_env.items()
    ]


def load_or_recompute_qdpg(
    cfg: QDPGConfig,
    scale: str,
    seed: int,
    progress: bool = True,
    environments: tuple[str, ...] = ENVIRONMENTS,
) -> tuple[dict[str, MethodResult], dict[str, str]]:
    """QD-PG's result on each of ``environments``, read from this scale's ``ch3_qdpg``
    run, or recomputed (and saved there) with that notebook's keys, so it is the same
    result: ``results[env]`` and ``status[env]`` (``"loaded"``, or why it was
    recomputed)."""
    unknown = set(environments) - set(ENVIRONMENTS)
    if unknown:
        raise ValueError(
            f"unknown environments {sorted(unknown)}; valid: {', '.join(ENVIRONMENTS)}"
        )
    digest = config_hash(cfg)
    summary = load_summary(scale, "ch3_qdpg")
    seed_differs = summary is not None and summary.get("seed") != seed
    results: dict[str, MethodResult] = {}
    status: dict[str, str] = {}
    for env_name in environments:
        i = ENVIRONMENTS.index(env_name)  # the QD-PG page's order gives its key
        path = qdpg_path(scale, env_name)
        loaded = None if seed_differs else load_method_result(path, digest)
        if loaded is not None:
            results[env_name], status[env_name] = loaded, "loaded from the QD-PG page's run"
            continue
        status[env_name] = (
            "recomputed: the QD-PG page's run used another seed"
            if seed_differs
            else "recomputed: no run of the QD-PG page"
            if not path.exists()
            else "recomputed: the QD-PG page's run used another config"
        )
        key = jax.random.fold_in(jax.random.PRNGKey(seed), i)  # the ch3_qdpg notebook's key
        out = run_environment(cfg, env_name, key, progress, methods=("QD-PG",))
        save_method_result(path, digest, out.methods["QD-PG"])
        results[env_name] = load_method_result(path, digest)
    return results, status
