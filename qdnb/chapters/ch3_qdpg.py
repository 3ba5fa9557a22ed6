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

import dataclasses
import json
import math
import time
from dataclasses import dataclass
from functools import cached_property
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np

from qdnb.core import claims as claim_records
from qdnb.core import health, paths
from qdnb.core.claims import finite_mean
from qdnb.core.config import config_hash
from qdnb.core.evaluation import Algorithm
from qdnb.core.io import load_arrays, load_summary, save_arrays
from qdnb.core.names import mean_sd, number_text, seeds_text
from qdnb.core.tree import take
from qdnb.envs import make_env
from qdnb.envs.base import Env
from qdnb.envs.pointmaze import GOAL as POINTMAZE_GOAL
from qdnb.envs.pointmaze import in_goal, reachable
from qdnb.envs.rollout import evaluate_policies
from qdnb.nets.mlp import MLP
from qdnb.qd.adaptation import bayes_opt, random_goals, random_search, reach_scores
from qdnb.qd.algorithms import run_seeds
from qdnb.qd.cvt import grid_centroids
from qdnb.qd.es import MEES, NSRAES, NSRES
from qdnb.qd.metrics import grid_cell
from qdnb.qd.pga import PGAMapElites
from qdnb.qd.qdpg import QDPG
from qdnb.rl.agac import AGACAgent, AGACConfig
from qdnb.rl.agents import TD3Agent
from qdnb.rl.cemrl import CEMRLAgent
from qdnb.rl.diayn import DIAYN
from qdnb.rl.p3s import P3STD3Agent
from qdnb.rl.rnd import RNDAgent
from qdnb.rl.sac import SACAgent
from qdnb.rl.td3 import TD3Config


@dataclass(frozen=True)
class QDPGTask:
    """Per-environment settings of Chapter 3 (Table 3.2 at ``paper`` scale).

    ``num_steps`` is the environment-step budget of every method; each iteration
    plays ``num_actors`` episodes of ``episode_length`` steps at most, so a run
    has ``num_steps // (num_actors * episode_length)`` iterations.  Per
    iteration each critic in use takes ``num_critic_steps`` TD3 steps; with the
    thesis's coupling (QD-PG and its ablations) each actor takes a step after
    every ``policy_delay`` of them, and ``num_pg_steps`` is the actor steps of
    the methods whose critics train apart (PGA-ME, and QD-PG's greedy readings in
    ``bench/qdpg_ab.py``); at ``paper`` scale the critic steps are Table 3.2's
    gradient-steps ratio times the episode length (4 x 200 on Point-Maze,
    0.1 x 3000 on the ants) and, on Point-Maze, the mutations' steps half of them,
    as the thesis's coupling gives its actors.  ``learning_rate`` drives the critics and their
    greedy actors, ``mutation_learning_rate`` the policy-gradient mutations of
    the population (Table 3.2 gives one rate for both; QDax uses 3e-4 and
    1e-3).  The state-descriptor archive admits a state whose mean distance to
    its K nearest neighbours exceeds ``archive_threshold`` (Section 3.6.3) and
    holds ``archive_size`` of them (FIFO).
    """

    num_steps: int
    episode_length: int
    num_actors: int
    bins: int
    policy_hidden: tuple[int, ...]
    critic_hidden: tuple[int, ...]
    optimizer: str
    learning_rate: float
    buffer_size: int
    num_critic_steps: int
    num_pg_steps: int
    archive_threshold: float
    mutation_learning_rate: float
    archive_size: int = 10_000

    @property
    def num_iterations(self) -> int:
        return self.num_steps // (self.num_actors * self.episode_length)


POINTMAZE_PAPER = QDPGTask(
    num_steps=1_000_000,
    episode_length=200,
    num_actors=4,
    bins=5,
    policy_hidden=(64, 32),
    critic_hidden=(64, 32),
    optimizer="sgd",
    learning_rate=6e-3,
    buffer_size=1_000_000,
    num_critic_steps=800,
    # a mutation's policy-gradient steps where the critics train apart (PGA-ME, QD-PG's
    # greedy readings): the thesis's coupling's 800 // 2, so that every method's mutation
    # takes the same 400 steps
    num_pg_steps=400,
    archive_threshold=1e-4,
    mutation_learning_rate=6e-3,
)
ANT_PAPER = QDPGTask(
    num_steps=100_000_000,
    episode_length=3000,
    num_actors=10,
    bins=7,
    policy_hidden=(256, 256),
    critic_hidden=(256, 256),
    optimizer="sgd",
    learning_rate=3e-4,
    buffer_size=500_000,
    num_critic_steps=300,
    num_pg_steps=300,
    archive_threshold=0.1,
    mutation_learning_rate=3e-4,
)

# Ant-Maze and Ant-Trap share their settings below `paper` (Table 3.2 groups them too).
ANT_TINY = dataclasses.replace(
    ANT_PAPER,
    num_steps=1_500,
    episode_length=50,
    policy_hidden=(16, 16),
    critic_hidden=(32, 32),
    optimizer="adam",
    learning_rate=1e-3,
    mutation_learning_rate=1e-3,
    buffer_size=10_000,
    num_critic_steps=10,
    num_pg_steps=10,
)
ANT_SMALL = dataclasses.replace(
    ANT_PAPER,
    num_steps=55_000,
    episode_length=500,
    policy_hidden=(64, 64),
    critic_hidden=(64, 64),
    optimizer="adam",
    learning_rate=3e-4,
    mutation_learning_rate=1e-3,
    buffer_size=55_000,
    num_critic_steps=50,
    num_pg_steps=50,
)


@dataclass(frozen=True)
class QDPGConfig:
    """Chapter 3: QD-PG, its ablations, TD3 and PGA-ME on Point-Maze, Ant-Maze and
    Ant-Trap (Table 3.2 at ``paper`` scale), and the fast-adaptation search.

    ``ant_methods`` are the methods run on the two ant mazes (every method runs
    on Point-Maze).  PGA-ME uses the same networks, buffer and gradient steps as
    QD-PG, and iso+line variation for its genetic half.  Every method runs on
    ``num_seeds`` seeds, except QD-PG on Point-Maze, which runs on
    ``pointmaze_qdpg_seeds`` when it is set (more seeds for the method whose
    claims the chapter checks, where the budget allows no more for all).
    """

    num_seeds: int
    chunk_size: int
    pointmaze: QDPGTask
    antmaze: QDPGTask
    anttrap: QDPGTask
    pointmaze_qdpg_seeds: int | None = None
    ant_methods: tuple[str, ...] = ("QD-PG", "QD-PG Sum", "D-PG", "Q-PG", "TD3", "PGA-ME")
    archive_k: int = 10
    td3_batch_size: int = 256
    discount: float = 0.99
    tau: float = 0.005
    policy_delay: int = 2
    exploration_noise: float = 0.1
    iso_sigma: float = 0.005
    line_sigma: float = 0.05
    adaptation_goals: int = 100
    adaptation_budget: int = 20

    def __post_init__(self):
        for name in ("pointmaze", "antmaze", "anttrap"):
            task = getattr(self, name)
            if task.num_iterations < 1:
                raise ValueError(
                    f"{name}: a budget of {task.num_steps} steps is less than one iteration "
                    f"({task.num_actors} actors x {task.episode_length} steps)"
                )
            if task.optimizer not in ("adam", "sgd"):
                raise ValueError(f"{name}: unknown optimizer {task.optimizer!r}; valid: adam, sgd")
            if task.num_critic_steps % self.policy_delay:
                raise ValueError(
                    f"{name}: num_critic_steps={task.num_critic_steps} must be a multiple of "
                    f"policy_delay={self.policy_delay}"
                )
        unknown = set(self.ant_methods) - set(METHODS)
        if unknown:
            raise ValueError(f"unknown methods {sorted(unknown)}; valid: {', '.join(METHODS)}")
        for name, n in (
            ("num_seeds", self.num_seeds),
            ("pointmaze_qdpg_seeds", self.pointmaze_qdpg_seeds),
        ):
            if n is not None and n < 1:
                raise ValueError(f"{name}={n} must be at least 1")

    def task(self, env_name: str) -> QDPGTask:
        if env_name not in ("pointmaze", "antmaze", "anttrap"):
            raise ValueError(
                f"unknown environment {env_name!r}; valid: pointmaze, antmaze, anttrap"
            )
        return getattr(self, env_name)

    def methods(self, env_name: str) -> tuple[str, ...]:
        return QDPG_METHODS if env_name == "pointmaze" else self.ant_methods

    def seeds(self, env_name: str, method: str) -> int:
        """How many seeds ``method`` runs on ``env_name``."""
        if env_name == "pointmaze" and method == "QD-PG" and self.pointmaze_qdpg_seeds is not None:
            return self.pointmaze_qdpg_seeds
        return self.num_seeds

    def with_seeds(self, num_seeds: int) -> "QDPGConfig":
        """This config with every method, QD-PG on Point-Maze included, on ``num_seeds`` seeds."""
        return dataclasses.replace(self, num_seeds=num_seeds, pointmaze_qdpg_seeds=None)

    def with_pointmaze_iterations(self, iterations: int) -> "QDPGConfig":
        """This config with a Point-Maze budget of ``iterations`` iterations (benchmarks)."""
        task = self.pointmaze
        steps = iterations * task.num_actors * task.episode_length
        return dataclasses.replace(self, pointmaze=dataclasses.replace(task, num_steps=steps))


ENVIRONMENTS = ("pointmaze", "antmaze", "anttrap")


def make_task_env(cfg: QDPGConfig, env_name: str) -> Env:
    return make_env(env_name, episode_length=cfg.task(env_name).episode_length)


def fitness_offset(env_name: str, env: Env) -> float:
    """A lower bound of the performance, so that QD scores count every elite
    positively: the whole episode at the far corner (Point-Maze), the far corner
    of the maze (Ant-Maze), running backwards at 5 m/s (Ant-Trap)."""
    span = float(np.linalg.norm(np.asarray(env.descriptor_high) - np.asarray(env.descriptor_low)))
    return {
        "pointmaze": -span * env.episode_length,
        "antmaze": -span,
        "anttrap": -5.0 * env.episode_length,
    }[env_name]


def _qdpg(update: str) -> Callable[[QDPGConfig, QDPGTask, dict], Algorithm]:
    def build(cfg: QDPGConfig, task: QDPGTask, parts: dict) -> Algorithm:
        return QDPG(
            **parts["shared"],
            update=update,
            td3_config=parts["td3"],
            num_critic_steps=task.num_critic_steps,
            num_pg_steps=task.num_pg_steps,
            buffer_size=task.buffer_size,
            archive_size=task.archive_size,
            archive_threshold=task.archive_threshold,
            archive_k=cfg.archive_k,
        )

    return build


def _pga_me(cfg: QDPGConfig, task: QDPGTask, parts: dict) -> Algorithm:
    return PGAMapElites(
        **parts["shared"],
        td3_config=parts["td3"],
        num_critic_steps=task.num_critic_steps,
        num_pg_steps=task.num_pg_steps,
        buffer_size=task.buffer_size,
    )


def _replay_agent(cls: type, **settings: Callable[[QDPGConfig, QDPGTask], Any]):
    """A replay-buffer agent (TD3 and the off-policy baselines): the task's network,
    TD3 settings, episodes and gradient steps per iteration and buffer size, and
    ``settings``, each read from the config and the task."""

    def build(cfg: QDPGConfig, task: QDPGTask, parts: dict) -> Algorithm:
        return cls(
            env=parts["env"],
            network=parts["network"],
            td3_config=parts["td3"],
            num_episodes=task.num_actors,
            num_critic_steps=task.num_critic_steps,
            buffer_size=task.buffer_size,
            **{name: value(cfg, task) for name, value in settings.items()},
        )

    return build


_exploration_noise = lambda cfg, task: cfg.exploration_noise  # noqa: E731
_td3 = _replay_agent(TD3Agent, exploration_noise=_exploration_noise)
_sac = _replay_agent(SACAgent)
_diayn = _replay_agent(DIAYN)
_rnd = _replay_agent(RNDAgent, exploration_noise=_exploration_noise)
# one learner per episode; the critic steps are shared among the learners
_p3s_td3 = _replay_agent(P3STD3Agent, exploration_noise=_exploration_noise)
# episode 0 plays the mean actor (its performance), the others the CEM population
_cem_rl = _replay_agent(CEMRLAgent, num_actor_steps=lambda cfg, task: task.num_pg_steps)


def _agac(cfg: QDPGConfig, task: QDPGTask, parts: dict) -> Algorithm:
    # on-policy: no replay buffer nor critic steps; its bonus decays over the run's iterations
    return AGACAgent(
        env=parts["env"],
        network=parts["network"],
        num_episodes=task.num_actors,
        config=AGACConfig(gamma=cfg.discount),
        num_iterations=task.num_iterations,
    )


def _evolution_strategy(cls: type) -> Callable[[QDPGConfig, QDPGTask, dict], Algorithm]:
    """An ES method whose generation is ``task.num_actors`` perturbations (the chapter's
    evolution page sets it), with its archive exactly as long as the run's descriptors
    (the reference codes keep them all: ME-ES one per generation, QDax's archive of
    ``total_generations``; NS-ES the meta-population's first ``M``, then one per
    generation) and, for ME-ES, the task's grid."""

    def build(cfg: QDPGConfig, task: QDPGTask, parts: dict) -> Algorithm:
        extra = {"centroids": parts["shared"]["centroids"]} if cls is MEES else {}
        entries = task.num_iterations
        if issubclass(cls, NSRES):
            entries += NSRES.meta_population_size - 1
        return cls(
            env=parts["env"],
            network=parts["network"],
            num_perturbations=task.num_actors,
            archive_size=max(cls.k, entries),
            **extra,
        )

    return build


# name -> builder(cfg, task, shared parts): adding a method is one entry (and its code)
METHODS: dict[str, Callable[[QDPGConfig, QDPGTask, dict], Algorithm]] = {
    "QD-PG": _qdpg("alternate"),
    "QD-PG Sum": _qdpg("sum"),
    "D-PG": _qdpg("diversity"),
    "Q-PG": _qdpg("quality"),
    "TD3": _td3,
    "PGA-ME": _pga_me,
    "SAC": _sac,
    "RND": _rnd,
    "CEM-RL": _cem_rl,
    "P3S-TD3": _p3s_td3,
    "AGAC": _agac,
    "DIAYN": _diayn,
    "ME-ES": _evolution_strategy(MEES),
    "NSR-ES": _evolution_strategy(NSRES),
    "NSRA-ES": _evolution_strategy(NSRAES),
}
QDPG_METHODS = ("QD-PG", "QD-PG Sum", "D-PG", "Q-PG", "TD3", "PGA-ME")  # this page's methods
Config = QDPGConfig


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


ANTMAZE_SOLVED = -10.0  # Table 3.3: Ant-Maze is solved when the best reward exceeds this
# bench/qdpg_ab.py's rule: a reading of QD-PG exits Point-Maze's trap when at least three
# quarters of its seeds (3 of 4; 5 of 6 once a reading one seed from that gets two more) reach
# the exit zone within 10^6 steps (a diverged seed does not); fewer than 4 seeds call nothing
READING_EXITS_SHARE = 0.75
READING_MIN_SEEDS = 4


def exits_needed(num_seeds: int) -> int:
    """Seeds of ``num_seeds`` that must reach the exit zone for a reading to exit."""
    return math.ceil(READING_EXITS_SHARE * num_seeds)


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


def until_goal(env_name: str, num_seeds: int) -> Callable[[dict[str, Any]], bool]:
    """A ``run_seeds`` stop rule: true once every one of ``num_seeds`` seeds has reached
    the goal in the history seen so far (Point-Maze: an evaluated episode ended in the
    exit zone; Ant-Maze: the best reward exceeded ``ANTMAZE_SOLVED``), as
    ``steps_to_exit`` and ``MethodResult.steps_to_goal`` read it afterwards."""
    reached = np.zeros(num_seeds, bool)

    def stop(history: dict[str, Any]) -> bool:  # entries: iterations x seeds x ...
        reached[:] |= goal_hits(env_name, history).any(axis=0)
        return bool(reached.all())

    return stop


def goal_hits(env_name: str, history: dict[str, Any]) -> np.ndarray:
    """Whether the goal was reached, per entry of a history's first two axes (seeds x
    iterations in a result, iterations x seeds inside a loop): on Point-Maze an
    evaluated episode ended in the exit zone, on Ant-Maze the best reward exceeded
    ``ANTMAZE_SOLVED`` (Table 3.3)."""
    if env_name == "pointmaze":
        hit = in_exit_zone(np.asarray(history["descriptors"]))
        return hit.reshape(hit.shape[0], hit.shape[1], -1).any(axis=2)
    return np.asarray(history["max_fitness"]) > ANTMAZE_SOLVED


def steady_rate(chunk_seconds: list[float], chunk_size: int, fallback: float) -> float:
    """Seconds per iteration of a compiled loop: the median full chunk after the
    first (which compiles) and before the last (which may be partial);
    ``fallback`` when the loop ran in one chunk."""
    if len(chunk_seconds) < 2:
        return fallback
    return float(np.median(chunk_seconds[1:-1] or chunk_seconds)) / chunk_size


def reachable_cells(env_name: str, env: Env, bins: int) -> np.ndarray:
    """Which cells of the ``bins x bins`` grid hold a reachable point: on Point-Maze,
    a point of a 401 x 401 lattice of the arena outside the walls (``reachable``);
    on the ant mazes every cell counts."""
    if env_name != "pointmaze":
        return np.ones(bins * bins, bool)
    axis = np.linspace(-1.0, 1.0, 401)
    lattice = np.stack(np.meshgrid(axis, axis, indexing="ij"), axis=-1).reshape(-1, 2)
    cells = grid_cell(
        lattice[reachable(lattice)], (bins, bins), env.descriptor_low, env.descriptor_high
    )
    mask = np.zeros(bins * bins, bool)
    mask[np.asarray(cells)] = True
    return mask


def reachable_coverage(filled: np.ndarray, env_name: str, env: Env, bins: int) -> np.ndarray:
    """Per seed (leading axis of ``filled``, seeds x cells), the share of the grid's
    reachable cells (``reachable_cells``) that are filled."""
    mask = reachable_cells(env_name, env, bins)
    return np.asarray(filled)[:, mask].mean(axis=1)


def grid_coverage(
    descriptors: np.ndarray, env: Env, bins: int, env_name: str = "pointmaze"
) -> np.ndarray:
    """The share of the ``bins x bins`` grid's reachable cells reached by any
    evaluated episode, per seed (``descriptors``: seeds x iterations x episodes x 2).
    For TD3, which keeps no grid, this is the grid it would have filled."""
    d = descriptors.reshape(descriptors.shape[0], -1, descriptors.shape[-1])
    cells = np.asarray(grid_cell(d, (bins, bins), env.descriptor_low, env.descriptor_high))
    filled = np.zeros((len(cells), bins * bins), bool)
    for seed, c in enumerate(cells):
        filled[seed, c] = True
    return reachable_coverage(filled, env_name, env, bins)


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


def steps_to_exit(result: MethodResult) -> np.ndarray:
    """Per seed, the environment steps a Point-Maze method had used when one of
    its evaluated episodes first ended in the exit zone (``nan`` if none did);
    ``result`` is one method's entry of ``run_environment``."""
    hit = goal_hits("pointmaze", result.history)  # seeds x iterations
    steps = np.asarray(result.cumulative_steps, float)
    return np.where(hit.any(axis=1), steps[np.arange(len(steps)), np.argmax(hit, axis=1)], np.nan)


# ----- the chapter's claims and summary -----


def beats(a: np.ndarray, b: np.ndarray) -> bool:
    """Whether the per-seed values ``a`` beat ``b``: on the mean over seeds, and on
    most of the seeds of ``a`` (each against the mean of ``b``).  Diverged seeds (NaN)
    are in no mean, and count as seeds of ``a`` that do not beat it."""
    target = finite_mean(b)
    a = np.asarray(a, float)
    return bool(finite_mean(a) > target and np.mean(np.where(np.isnan(a), False, a > target)) > 0.5)


def per_seed(p: np.ndarray) -> str:
    """A mean over the finite seeds, and every seed when there are several ("diverged"
    for one that went NaN)."""
    each = ", ".join("diverged" if np.isnan(v) else f"{v:.1f}" for v in p)
    seeds = f" (seeds: {each})" if len(p) > 1 else ""
    return f"{finite_mean(p):.1f}{seeds}"


# the stable names of ``claims``'s rows, in order (the book's scorecard matches scales by them)
CLAIM_IDS = ("reaches_exit", "beats_td3", "beats_qpg", "dpg_explores")


def claims(results_by_env: dict[str, EnvironmentResult]) -> list[tuple[str, bool, str]]:
    """The chapter's Point-Maze claims as ``(claim, holds, numbers)``.  A comparison
    holds on the mean over seeds and on most of the seeds of the method it is about."""
    pm = results_by_env["pointmaze"].methods
    perf = lambda name: pm[name].final_performance
    cov = lambda name: finite_mean(pm[name].coverage)

    reached = pm["QD-PG"].reached_exit
    return [
        (
            "QD-PG reaches the exit zone (most seeds)",
            bool(reached.mean() > 0.5),
            f"{reached.sum()} of {seeds_text(len(reached))}",
        ),
        (
            "QD-PG beats TD3 on final performance (mean and most seeds)",
            beats(perf("QD-PG"), perf("TD3")),
            f"{per_seed(perf('QD-PG'))} vs {per_seed(perf('TD3'))}",
        ),
        (
            "QD-PG beats Q-PG on final performance (mean and most seeds)",
            beats(perf("QD-PG"), perf("Q-PG")),
            f"{per_seed(perf('QD-PG'))} vs {per_seed(perf('Q-PG'))}",
        ),
        (
            "D-PG explores: covers more reachable cells than Q-PG and TD3",
            cov("D-PG") > max(cov("Q-PG"), cov("TD3")),
            f"{cov('D-PG'):.2f} vs {cov('Q-PG'):.2f} (Q-PG), {cov('TD3'):.2f} (TD3)",
        ),
    ]


def method_summaries(
    results_by_env: dict[str, EnvironmentResult], expected: tuple[str, ...] = QDPG_METHODS
) -> dict[str, dict[str, Any]]:
    """``summary.json``'s per-environment, per-method entries; a method of ``expected``
    not run at this scale is said to be so (``"ran": False``), not invented."""
    out: dict[str, dict[str, Any]] = {}
    for env_name, res in results_by_env.items():
        out[env_name] = {}
        for name, r in res.methods.items():
            kept = r.final_performance[r.kept]
            entry = {
                "ran": True,
                "final_performance": finite_mean(r.final_performance),
                "final_performance_std": float(kept.std()) if kept.size else None,
                "final_performance_per_seed": [
                    None if np.isnan(v) else float(v) for v in r.final_performance
                ],
                "coverage": finite_mean(r.coverage),
                "env_steps": float(r.env_steps.mean()),
                "run_seconds": round(r.seconds, 1),
                "diverged": [
                    None if d is None else {"iteration": d.iteration, "parts": list(d.parts)}
                    for d in r.diverged
                ],
            }
            if env_name == "pointmaze":
                entry["reached_goal"] = bool(r.reached_exit.any())
                entry["steps_to_exit"] = [None if np.isnan(v) else float(v) for v in r.exit_steps]
            out[env_name][name] = entry
        for name in expected:
            if name not in res.methods:
                out[env_name][name] = {
                    "ran": False,
                    "final_performance": None,
                    "coverage": None,
                    "env_steps": 0,
                }
    return out


# ----- Section 3.7: fast adaptation on Ant-Maze -----


@dataclass(frozen=True)
class FastAdaptation:
    """QD-PG's final Ant-Maze grid (seed 0) searched for new goals (Figures 3.6, 3.7):
    ``paths`` (solutions, T, 2) and ``alive`` (solutions, T) of every stored
    solution's episode; per goal, the best score of Bayesian optimisation, the cell of
    the solution that scored it (``bo_pick``, -1 with no stored solution), the best
    score of random search with ``budget`` evaluations, and the exhaustive best."""

    goals: np.ndarray
    budget: int
    descriptors: np.ndarray
    valid: np.ndarray
    paths: np.ndarray
    alive: np.ndarray
    bo_best: np.ndarray
    bo_pick: np.ndarray
    rs_best: np.ndarray
    exhaustive: np.ndarray

    def summary(self) -> dict[str, Any]:
        return {
            "env": "antmaze",
            "goals": int(len(self.goals)),
            "budget": int(self.budget),
            "mean": float(self.bo_best.mean()),
            "std": float(self.bo_best.std()),
            "stored_solutions": int(self.valid.sum()),
        }


def fast_adaptation(cfg: QDPGConfig, antmaze: EnvironmentResult, seed: int) -> FastAdaptation:
    """Section 3.7 on ``antmaze`` (``run_environment``'s result): each stored solution
    of QD-PG's seed-0 grid plays one recorded episode; ``cfg.adaptation_goals``
    random goals are scored by the best reward an episode gets for them
    (``reach_scores``), and Bayesian optimisation over the descriptors picks
    ``cfg.adaptation_budget`` solutions to try for each goal."""
    grid, maze = antmaze.methods["QD-PG"].grid, antmaze.env
    valid = np.isfinite(grid["fitnesses"][0])
    genotypes = take(grid["genotypes"], 0)
    network = policy_network(cfg, "antmaze", maze)
    episode = jax.jit(
        lambda g, k: evaluate_policies(maze, network.apply, g, k, return_trajectory=True)
    )(genotypes, _adaptation_episodes_key(seed))
    paths_xy = np.asarray(episode.trajectory["next_state_descriptor"])
    alive = np.asarray(episode.trajectory["valid"])
    k_goals, k_bo = jax.random.split(jax.random.PRNGKey(seed + 2))
    goals = np.asarray(random_goals(k_goals, cfg.adaptation_goals, (-4.5, -4.5), (39.5, 39.5)))
    scores = jax.vmap(lambda g: reach_scores(paths_xy, g, alive))(goals)  # goals x solutions
    keys = jax.random.split(k_bo, cfg.adaptation_goals)
    bounds = (maze.descriptor_low, maze.descriptor_high)
    bo = jax.vmap(
        lambda s, k: bayes_opt(
            grid["descriptors"][0], valid, s, k, budget=cfg.adaptation_budget, bounds=bounds
        )
    )(scores, keys)
    rs = jax.vmap(lambda s, k: random_search(valid, s, k, budget=cfg.adaptation_budget))(
        scores, keys
    )
    exhaustive = np.max(np.where(valid[None], np.asarray(scores), -np.inf), axis=1)
    return FastAdaptation(
        goals,
        cfg.adaptation_budget,
        np.asarray(grid["descriptors"][0]),
        valid,
        paths_xy,
        alive,
        np.asarray(bo["best_score"]),
        np.asarray(bo["best_index"]),
        np.asarray(rs["best_score"]),
        exhaustive,
    )


def _adaptation_episodes_key(seed: int) -> jax.Array:
    """The key of the one recorded episode each stored solution plays for Section 3.7."""
    return jax.random.PRNGKey(seed + 1)


def adaptation_picks(
    antmaze: EnvironmentResult, fast: FastAdaptation, seed: int, goal_ids: np.ndarray
) -> tuple[Any, jax.Array]:
    """The solutions Bayesian optimisation picked for the goals ``goal_ids`` (a batch of
    policy parameters) and the keys of the initial states their scored episodes started
    from, as ``evaluate_policies`` drew them, so ``render.episode_states`` replays the
    very episodes the scores were read from; a ``ValueError`` for a goal with no pick."""
    cells = fast.bo_pick[np.asarray(goal_ids)]
    if (cells < 0).any():
        raise ValueError(f"goals {np.asarray(goal_ids)[cells < 0]} have no picked solution")
    genotypes = take(antmaze.methods["QD-PG"].grid["genotypes"], 0)
    keys = jax.random.split(_adaptation_episodes_key(seed), len(fast.valid))
    return jax.tree.map(lambda x: x[cells], genotypes), keys[cells]


# ----- the thesis's references: a hand-written path, and the chapter's summary -----


def waypoint_policy(params: Any, obs: jax.Array) -> jax.Array:
    """A hand-written Point-Maze path: left through the lower wall's gap, right through
    the upper one, then to the exit (a reference for Table 3.4's returns)."""
    del params
    target = jnp.where(
        obs[1] < -0.45,
        jnp.array([-0.6, -0.42]),
        jnp.where(
            obs[1] < 0.25,
            jnp.where(obs[0] < 0.55, jnp.array([0.65, 0.0]), jnp.array([0.6, 0.3])),
            jnp.asarray(POINTMAZE_GOAL),
        ),
    )
    return jnp.clip((target - obs) * 10.0, -1.0, 1.0)


@dataclass(frozen=True)
class HandPath:
    """``waypoint_policy``'s returns and whether each episode ended in the exit zone."""

    returns: np.ndarray
    exited: np.ndarray


def hand_path(env: Env, key: jax.Array, starts: int = 256) -> HandPath:
    """``waypoint_policy`` on Point-Maze from ``starts`` random starts."""
    out = evaluate_policies(env, waypoint_policy, jnp.zeros((starts,)), key)
    return HandPath(np.asarray(out.fitness), in_exit_zone(np.asarray(out.descriptor)))


def summary_results(
    cfg: QDPGConfig,
    results_by_env: dict[str, EnvironmentResult],
    fast: FastAdaptation,
    hand: HandPath,
) -> dict[str, Any]:
    """The chapter's ``summary.json`` results: the claims, every method's entry
    (``method_summaries``), the fast adaptation, Ant-Maze's steps to goal, Point-Maze's
    time per iteration and the hand-written path's return."""
    held = claims(results_by_env)
    count = sum(ok for _, ok, _ in held)
    pm = results_by_env["pointmaze"].methods
    return {
        "headline": f"{count}/{len(held)} Point-Maze claims hold",
        "claims_held": count,
        "claims_total": len(held),
        "claims": [
            claim_records.record(f"ch3_qdpg/{key}", f"Point-Maze: {text}", ok, numbers)
            for key, (text, ok, numbers) in zip(CLAIM_IDS, held)
        ],
        "num_seeds": cfg.num_seeds,
        "pointmaze_qdpg_seeds": cfg.seeds("pointmaze", "QD-PG"),
        "fast_adaptation": fast.summary(),
        **method_summaries(results_by_env),
        "antmaze_steps_to_goal": results_by_env["antmaze"].methods["QD-PG"].steps_to_goal(),
        "pointmaze_seconds_per_iteration": {
            name: r.steady_seconds_per_iteration for name, r in pm.items()
        },
        "pointmaze_hand_path_return": float(hand.returns.mean()),
    }


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


# small's Point-Maze environment steps: bench/results/ch3_small_budget.json's page checks
# (48,000 by the loops' probe; the executed page took 18.1 minutes at 48,000 and 16.1 at
# 32,000 an hour later, so 16,000, the budget both checks fit)
SMALL_POINTMAZE_STEPS = 16_000

# The chapter's configs, one per scale (the rule of each is in the notebook's scale cell).
SCALES = {
    "tiny": QDPGConfig(
        num_seeds=1,
        chunk_size=10,
        ant_methods=("QD-PG", "TD3"),
        adaptation_goals=20,
        adaptation_budget=10,
        pointmaze=dataclasses.replace(
            POINTMAZE_PAPER,
            num_steps=8_000,
            policy_hidden=(16, 16),
            critic_hidden=(32, 32),
            optimizer="adam",
            learning_rate=1e-3,
            mutation_learning_rate=1e-3,
            buffer_size=20_000,
            num_critic_steps=10,
            num_pg_steps=10,
        ),
        antmaze=ANT_TINY,
        anttrap=ANT_TINY,
    ),
    # small Point-Maze: Table 3.2 whole (N = 4 actors, 800 critic steps an iteration, 400
    # policy-gradient steps a mutation, SGD at 6e-3, networks, archive, grid) but for its
    # environment steps: the largest multiple of 16,000 for which the page takes at most 15
    # minutes on a 2-core CPU (bench/ch3_small_budget.py, its rule and measurements); QD-PG on
    # Point-Maze on 4 seeds (two per core), the other methods on 2.
    "small": QDPGConfig(
        num_seeds=2,
        chunk_size=10,
        ant_methods=("QD-PG", "TD3"),
        pointmaze_qdpg_seeds=4,
        pointmaze=dataclasses.replace(POINTMAZE_PAPER, num_steps=SMALL_POINTMAZE_STEPS),
        antmaze=ANT_SMALL,
        anttrap=ANT_SMALL,
    ),
    "paper": QDPGConfig(
        num_seeds=5,
        chunk_size=50,
        pointmaze=POINTMAZE_PAPER,
        antmaze=ANT_PAPER,
        anttrap=dataclasses.replace(ANT_PAPER, episode_length=1000),
    ),
}


# ----- the readings at Table 3.2's budget, the peer, the GPU run (computed outside the page) -----

AB_RESULTS = paths.ROOT / "bench" / "results" / "qdpg_ab.json"
PEER_RESULTS = paths.ROOT / "bench" / "results" / "qdax_qdpg.json"
PUBLISHED_POINTMAZE = paths.DATA / "published" / "paper" / "ch3_pointmaze" / "pointmaze-paper.json"
# the A/B's variants as the page names them (bench/qdpg_ab.py's VARIANTS, in its order)
READINGS = {
    "thesis-adam": "QD-PG, Adam (the A/B's base)",
    "sum": "Eq. 3.5's sum of the K distances",
    "thesis-sgd": "QD-PG, SGD 6·10⁻³ (Table 3.2)",
    "qdax-novelty": "QDax's novelty (mean squared distance, K = 5)",
    "qdax-greedy": "QDax's greedy actors, played",
    "exploration-noise": "the population plays with noise 0.1",
}


def read_json(path) -> dict | None:
    """A results file computed outside the page, or ``None`` if it is not there."""
    return json.loads(path.read_text()) if path.exists() else None


def _numbers(rows: list[dict], key: str) -> np.ndarray:
    """``key`` of each row as floats, NaN where a results file holds ``None`` (a diverged
    seed's numbers)."""
    return np.array([np.nan if r[key] is None else r[key] for r in rows], float)


def _steps(values: list) -> str:
    hits = [v for v in values if v is not None]
    return ", ".join(number_text(v) for v in hits) or "∞"  # (never)


def reading_rows(ab: dict, peer: dict | None = None) -> list[dict[str, Any]]:
    """The A/B's table: per variant run so far (and QDax's own QD-PG), how many seeds
    reached the exit zone and when, the final performance, where the episodes ended,
    coverage, NaN and wall time; a diverged seed is in no mean."""
    rows = []
    for variant, label in READINGS.items():
        mine = [r for r in ab.get("rows", []) if r["variant"] == variant]
        if not mine:
            continue
        lost = [r for r in mine if r["diverged"]]
        rows.append(
            {
                "reading": label,
                "seeds in the exit zone": f"{sum(r['reached_exit'] for r in mine)}/{len(mine)}",
                "steps to the exit zone": _steps([r["steps_to_exit"] for r in mine]),
                "final performance": mean_sd(_numbers(mine, "final_performance")),
                "episodes ending above the upper wall": (
                    f"{np.mean([r['share_above_upper_wall'] for r in mine]):.1%}"
                ),
                # (every seed diverged: "—")
                "coverage": number_text(finite_mean(_numbers(mine, "coverage")), 2),
                "diverged (iteration)": ", ".join(str(r["diverged"]["iteration"]) for r in lost)
                or "none",
                "minutes a pair of seeds": (
                    f"{np.mean([r['pair_wall_seconds'] for r in mine]) / 60:.0f}"
                ),
            }
        )
    if peer and peer.get("rows"):
        p = peer["rows"]
        rows.append(
            {
                "reading": "QDax 0.5.0's own QD-PG (its example's settings)",
                "seeds in the exit zone": f"{sum(r['reached_exit'] for r in p)}/{len(p)}",
                "steps to the exit zone": _steps([r["steps_to_exit"] for r in p]),
                "final performance": mean_sd(np.array([r["final_performance"] for r in p])),
                "episodes ending above the upper wall": "",
                "coverage": f"{np.mean([r['coverage'] for r in p]):.2f} (of its 1,024 cells)",
                "diverged (iteration)": "",
                "minutes a pair of seeds": f"{2 * np.mean([r['wall_seconds'] for r in p]) / 60:.0f}"
                " (one at a time)",
            }
        )
    return rows


def _seeds_and_exits(ab: dict, variant: str) -> tuple[int, int]:
    """How many seeds of ``variant`` the A/B has run, and how many reached the exit zone."""
    mine = [r for r in ab.get("rows", []) if r["variant"] == variant]
    return len(mine), sum(r["reached_exit"] for r in mine)


def reading_exits(ab: dict, variant: str) -> bool:
    """Whether ``variant`` exits by the A/B's rule: at least ``READING_MIN_SEEDS`` seeds
    run, and three quarters of them in the exit zone."""
    seeds, reached = _seeds_and_exits(ab, variant)
    return seeds >= READING_MIN_SEEDS and reached >= exits_needed(seeds)


def reading_needs_more_seeds(ab: dict, variant: str) -> bool:
    """The rule's "more seeds if a verdict is one seed from changing": a reading run on
    exactly ``READING_MIN_SEEDS`` seeds whose count of exits is one short of the verdict
    (2 of 4) gets two more, and is then read on 6 (5 of 6 exit)."""
    seeds, reached = _seeds_and_exits(ab, variant)
    return seeds == READING_MIN_SEEDS and reached == exits_needed(seeds) - 1


# QD-PG's state (``QDPGState``'s fields) as a reader names its parts
STATE_PARTS = {
    "repertoire": "repertoire",
    "q_critic": "quality critic",
    "d_critic": "diversity critic",
    "buffer": "replay buffer",
    "archive": "novelty archive",
    "updates": "update statistics",
}


def divergence_rows(ab: dict) -> list[dict[str, Any]]:
    """For every seed of the A/B that went NaN: when, in which parts, and its critics'
    losses and gradient norms over the iterations before (the first and the last)."""
    rows = []
    for r in ab.get("rows", []):
        if not r["diverged"]:
            continue
        before = r["statistics_before_divergence"] or {}
        span = lambda k: " → ".join(number_text(v, 3) for v in (before[k][0], before[k][-2]))  # noqa: E731
        rows.append(
            {
                "reading": READINGS.get(r["variant"], r["variant"]),
                "seed": r["seed"],
                "NaN at iteration": r["diverged"]["iteration"],
                "parts": ", ".join(STATE_PARTS.get(p, p) for p in r["diverged"]["parts"]),
                "quality critic loss": span("critic_loss_q"),
                "diversity critic loss": span("critic_loss_d"),
                "quality critic gradient norm": span("critic_grad_norm_q"),
                "diversity critic gradient norm": span("critic_grad_norm_d"),
                "actor gradient norm": span("actor_grad_norm"),
            }
        )
    return rows


def published_rows(published: dict) -> list[dict[str, Any]]:
    """The published `paper` Point-Maze run (``bench/ch3_pointmaze_paper.py``): per
    method, the seeds in the exit zone and when, the final performance (Table 3.4's
    Point-Maze column) and coverage, NaN and time."""
    rows = []
    for name, m in published["methods"].items():
        seeds = m["seeds"]
        rows.append(
            {
                "method": name,
                "seeds in the exit zone": (
                    f"{sum(s['steps_to_exit'] is not None for s in seeds)}/{len(seeds)}"
                ),
                "steps to the exit zone": _steps([s["steps_to_exit"] for s in seeds]),
                "final performance": mean_sd(_numbers(seeds, "final_performance")),
                "coverage": f"{finite_mean(_numbers(seeds, 'coverage')):.2f}",
                "s per iteration": f"{m['seconds_per_iteration']:.3f}",
                "wall time (min)": f"{m['wall_seconds'] / 60:.1f}",
            }
        )
    return rows
