"""Chapter 3's settings: the tasks of Table 3.2 (Point-Maze, Ant-Maze, Ant-Trap), the
page's config and its scales.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from qdnb.chapters.ch3_qdpg.methods import METHODS, QDPG_METHODS
from qdnb.envs import make_env
from qdnb.envs.base import Env


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


Config = QDPGConfig


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
