"""Named scales: ``tiny`` (CI, minutes on 2 CPU cores), ``small`` (a laptop,
at most 25 minutes per notebook) and ``paper`` (one GPU, the thesis's budgets).

Each chapter has one frozen config per scale; ``config(chapter, scale)`` returns
it and raises a clear ``ValueError`` on an unknown name, before any compute.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from dataclasses import dataclass

from qdnb.lenia.flow_lenia import FlowLeniaConfig
from qdnb.lenia.flt import FLTConfig

SCALES = ("tiny", "small", "paper")


@dataclass(frozen=True)
class PrimerConfig:
    """Chapter 1-2 primer: GA, Novelty Search and MAP-Elites on Point-Maze.

    Every method evaluates ``batch_size`` policies at start and ``batch_size``
    per iteration, so all get ``batch_size * (num_iterations + 1)`` episodes.
    """

    num_seeds: int
    num_iterations: int
    batch_size: int
    chunk_size: int
    episode_length: int = 200
    policy_hidden: tuple[int, ...] = (16, 16)
    iso_sigma: float = 0.05
    line_sigma: float = 0.1
    ga_population: int = 32
    ns_population: int = 256
    ns_k: int = 15
    ns_archive_size: int = 1000
    ns_archive_threshold: float = 0.01
    me_bins: tuple[int, int] = (32, 32)
    metric_bins: tuple[int, int] = (32, 32)
    fitness_offset: float = -600.0


@dataclass(frozen=True)
class ReproducibilityConfig:
    """Chapter 4 reproducibility: ME, ME-LS, PGA-ME, PGA-ME-LS and ME-Sampling on
    Ant-Omni and Halfcheetah-Uni (Tables 4.1 and 4.2 at ``paper`` scale).

    ``env_batch`` is the number of episodes every method plays per iteration
    (Tables 4.1/4.2's "environment batch size"): ME and PGA-ME evaluate
    ``env_batch`` policies once, the multi-episode methods ``env_batch //
    num_episodes`` policies ``num_episodes`` times, so all methods get the same
    number of environment steps.
    """

    num_seeds: int
    num_iterations: int
    env_batch: int
    num_episodes: int
    num_cells: int
    chunk_size: int
    environments: tuple[str, ...] = ("ant_omni", "halfcheetah_uni")
    episode_length: int = 250
    policy_hidden: tuple[int, ...] = (256, 256)
    iso_sigma: float = 0.005
    line_sigma: float = 0.05
    # PGA-ME and PGA-ME-LS (Table 4.2); TD3's own defaults for the rest (Section 2.3.5)
    policy_lr: float = 1e-3
    critic_lr: float = 3e-4
    critic_hidden: tuple[int, ...] = (256, 256)
    policy_noise: float = 0.2
    noise_clip: float = 0.5
    discount: float = 0.99
    pg_proportion: float = 0.5
    num_critic_steps: int = 300
    num_pg_steps: int = 100
    td3_batch_size: int = 256
    buffer_size: int = 1_000_000
    cvt_samples: int = 50_000
    cvt_iterations: int = 30
    # Ant-Omni's descriptor box [-b, b]^2: the thesis's b = 15 "as methods presented in this
    # work tend to produce solutions within this range" (at 10^8 steps); smaller scales apply the
    # same rule to their own budget, measured once by bench/ant_omni_reach.py (never on the run
    # it evaluates).  Halfcheetah-Uni's [0, 1]^2 is reachable at every scale.
    ant_omni_box: float = 15.0
    # evaluation of the final repertoires (Section 4.5.2, Table 4.5, Figures 4.3-4.5)
    ant_omni_goals: int = 100
    halfcheetah_uni_goals: int = 50
    accuracy_episodes: int = 10
    reassess_episodes: int = 10
    representative_episodes: int = 30

    def __post_init__(self):
        if self.env_batch % self.num_episodes:
            raise ValueError(f"env_batch ({self.env_batch}) must be a multiple of num_episodes ({self.num_episodes})")
        if self.env_batch // self.num_episodes < 2:
            raise ValueError("env_batch // num_episodes must be at least 2 (one PG and one GA offspring)")
        if not self.ant_omni_box > 0:
            raise ValueError(f"ant_omni_box must be positive, got {self.ant_omni_box}")

    def goals(self, env_name: str) -> int:
        return getattr(self, f"{env_name}_goals")

    def descriptor_box(self, env_name: str) -> dict[str, tuple[float, ...]]:
        """The descriptor bounds of ``env_name`` at this scale, as ``make_env`` keywords."""
        if env_name == "ant_omni":
            return {"descriptor_low": (-self.ant_omni_box,) * 2, "descriptor_high": (self.ant_omni_box,) * 2}
        return {}

    def make_env(self, env_name: str):
        """The environment as this chapter runs it: its episode length and descriptor box."""
        from qdnb.envs import make_env

        return make_env(env_name, episode_length=self.episode_length, **self.descriptor_box(env_name))


@dataclass(frozen=True)
class QDPGTask:
    """Per-environment settings of Chapter 3 (Table 3.2 at ``paper`` scale).

    ``num_steps`` is the environment-step budget of every method; each iteration
    plays ``num_actors`` episodes of ``episode_length`` steps at most, so a run
    has ``num_steps // (num_actors * episode_length)`` iterations.  Per
    iteration each critic in use takes ``num_critic_steps`` TD3 steps and each
    actor ``num_pg_steps`` actor steps; at ``paper`` scale both are Table 3.2's
    gradient-steps ratio times the episode length (4 x 200 on Point-Maze,
    0.1 x 3000 on the ants).  ``learning_rate`` drives the critics and their
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


POINTMAZE_PAPER = QDPGTask(num_steps=1_000_000, episode_length=200, num_actors=4, bins=5, policy_hidden=(64, 32),
                           critic_hidden=(64, 32), optimizer="sgd", learning_rate=6e-3, buffer_size=1_000_000,
                           num_critic_steps=800, num_pg_steps=800, archive_threshold=1e-4,
                           mutation_learning_rate=6e-3)
ANT_PAPER = QDPGTask(num_steps=100_000_000, episode_length=3000, num_actors=10, bins=7, policy_hidden=(256, 256),
                     critic_hidden=(256, 256), optimizer="sgd", learning_rate=3e-4, buffer_size=500_000,
                     num_critic_steps=300, num_pg_steps=300, archive_threshold=0.1,
                     mutation_learning_rate=3e-4)

# Ant-Maze and Ant-Trap share their settings below `paper` (Table 3.2 groups them too).
ANT_TINY = dataclasses.replace(ANT_PAPER, num_steps=1_500, episode_length=50, policy_hidden=(16, 16),
                               critic_hidden=(32, 32), optimizer="adam", learning_rate=1e-3, mutation_learning_rate=1e-3,
                               buffer_size=10_000, num_critic_steps=10, num_pg_steps=10)
ANT_SMALL = dataclasses.replace(ANT_PAPER, num_steps=55_000, episode_length=500, policy_hidden=(64, 64),
                                critic_hidden=(64, 64), optimizer="adam", learning_rate=3e-4, mutation_learning_rate=1e-3,
                                buffer_size=55_000, num_critic_steps=50, num_pg_steps=50)

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
                raise ValueError(f"{name}: a budget of {task.num_steps} steps is less than one iteration "
                                 f"({task.num_actors} actors x {task.episode_length} steps)")
            if task.optimizer not in ("adam", "sgd"):
                raise ValueError(f"{name}: unknown optimizer {task.optimizer!r}; valid: adam, sgd")
            if task.num_critic_steps % self.policy_delay:
                raise ValueError(f"{name}: num_critic_steps={task.num_critic_steps} must be a multiple of "
                                 f"policy_delay={self.policy_delay}")
        unknown = set(self.ant_methods) - set(QDPG_METHODS)
        if unknown:
            raise ValueError(f"unknown methods {sorted(unknown)}; valid: {', '.join(QDPG_METHODS)}")
        for name, n in (("num_seeds", self.num_seeds), ("pointmaze_qdpg_seeds", self.pointmaze_qdpg_seeds)):
            if n is not None and n < 1:
                raise ValueError(f"{name}={n} must be at least 1")

    def task(self, env_name: str) -> QDPGTask:
        if env_name not in ("pointmaze", "antmaze", "anttrap"):
            raise ValueError(f"unknown environment {env_name!r}; valid: pointmaze, antmaze, anttrap")
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


QDPG_METHODS = ("QD-PG", "QD-PG Sum", "D-PG", "Q-PG", "TD3", "PGA-ME")


@dataclass(frozen=True)
class QDTTask:
    """Per-environment settings of the QDT chapter (Sections 4.4.4 and 4.5.1).

    The descriptor space is split into ``zones`` CVT zones; every stored policy
    plays ``selection_episodes`` episodes and the most consistent policy of each
    zone is kept; each kept policy then plays ``episodes_per_policy`` episodes
    into the dataset.  The QDT is evaluated on ``goals`` CVT goals (their own
    tessellation), ``eval_episodes`` episodes each (N = 10 in the thesis).
    """

    zones: int
    goals: int
    selection_episodes: int
    episodes_per_policy: int


@dataclass(frozen=True)
class QDTConfig:
    """Chapter 4's Quality-Diversity Transformer (Table 4.3 at ``paper`` scale).

    The datasets come from the repertoires of the Chapter 4 run at the same
    scale; QDT seed ``i`` uses that run's seed-``i`` repertoires.  The first
    ``full_seeds`` seeds (all of them when ``None``) train every QDT: the five
    datasets of Table 4.4 and the five pruned ones of Figures 4.10 and 4.11; the
    later seeds train only the two the accuracy claim compares, QDT(ME) and
    QDT(ME-LS), from the ME and ME-LS repertoires."""

    num_seeds: int
    ant_omni: QDTTask
    halfcheetah_uni: QDTTask
    epochs: int
    eval_every: int
    embed_dim: int = 256
    num_layers: int = 4
    num_heads: int = 8
    dropout: float = 0.1
    batch_size: int = 256
    learning_rate: float = 7e-4
    eval_episodes: int = 10
    tiles: int = 4  # the "Tiles" dataset: a tiles x tiles checkerboard, half of it removed
    density_bins: int = 30
    cvt_samples: int = 50_000
    cvt_iterations: int = 30
    environments: tuple[str, ...] = ("ant_omni", "halfcheetah_uni")
    full_seeds: int | None = None

    def __post_init__(self):
        if self.full_seeds is not None and not 1 <= self.full_seeds <= self.num_seeds:
            raise ValueError(f"full_seeds ({self.full_seeds}) must be between 1 and num_seeds ({self.num_seeds})")
        if self.epochs < 1 or self.eval_every < 1 or self.epochs % self.eval_every:
            raise ValueError(f"epochs ({self.epochs}) must be a positive multiple of eval_every ({self.eval_every})")
        if self.embed_dim % self.num_heads:
            raise ValueError(f"embed_dim ({self.embed_dim}) must be a multiple of num_heads ({self.num_heads})")
        unknown = set(self.environments) - {"ant_omni", "halfcheetah_uni"}
        if unknown:
            raise ValueError(f"unknown environments {sorted(unknown)}; valid: ant_omni, halfcheetah_uni")

    @property
    def num_full_seeds(self) -> int:
        return self.num_seeds if self.full_seeds is None else self.full_seeds

    def task(self, env_name: str) -> QDTTask:
        if env_name not in ("ant_omni", "halfcheetah_uni"):
            raise ValueError(f"unknown environment {env_name!r}; valid: ant_omni, halfcheetah_uni")
        return getattr(self, env_name)


@dataclass(frozen=True)
class FlowLeniaChapterConfig:
    """Chapter 5: Flow Lenia (Table 5.1), the FLT (Section 5.3.1) and the surprise search.

    ``world`` is the simulator (grid, kernels, Table 5.1 ranges; below ``paper``
    the grid, the initial patch and the kernel radii shrink together);
    ``flt`` the model and its training.  ``system_candidates`` systems are drawn
    for ``pick_system`` (``system_probes`` episodes each); ``eval_episodes``
    held-out episodes score the FLT and the baselines; the surprise search runs
    ``search_iterations`` MAP-Elites iterations of ``search_batch`` initial
    states on a ``search_bins`` grid.
    """

    num_seeds: int
    world: FlowLeniaConfig
    flt: FLTConfig
    gallery_systems: int = 6
    system_candidates: int = 16
    system_probes: int = 4
    eval_episodes: int = 128
    eval_batch: int = 16
    search_iterations: int = 20
    search_batch: int = 32
    search_bins: tuple[int, int] = (8, 8)
    search_sigma: float = 0.1
    search_chunk: int = 5

    def __post_init__(self):
        if self.eval_episodes < 64:
            raise ValueError(f"eval_episodes must be at least 64 (Figure 5.5's quartiles), got {self.eval_episodes}")
        for name in ("num_seeds", "gallery_systems", "system_candidates", "system_probes", "eval_batch",
                     "search_batch", "search_chunk"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be positive, got {getattr(self, name)}")
        if self.search_iterations < 0:
            raise ValueError(f"search_iterations must be non-negative, got {self.search_iterations}")
        if self.world.steps < 50:
            raise ValueError(f"Figure 5.4 shows t = 1 .. 50: world.steps must be at least 50, got {self.world.steps}")


def lenia_world(size: int, kernels: int = 10) -> FlowLeniaConfig:
    """A ``size x size`` world with the patch (40 cells at 128) and the kernel radii
    (``(R + 15) r`` cells at 128) scaled with the grid: ``radius_scale = size / 128``."""
    return FlowLeniaConfig(height=size, width=size, kernels=kernels, patch_size=max(2, round(40 * size / 128)),
                           radius_scale=size / 128)


_CONFIGS: dict[str, dict[str, object]] = {
    "ch2_primer": {
        "tiny": PrimerConfig(num_seeds=2, num_iterations=40, batch_size=64, chunk_size=20, ns_population=64),
        "small": PrimerConfig(num_seeds=5, num_iterations=2000, batch_size=256, chunk_size=100),
        "paper": PrimerConfig(num_seeds=10, num_iterations=1000, batch_size=1024, chunk_size=100,
                              ns_population=1024, ns_archive_size=5000),
    },
    "ch4_reproducibility": {
        "tiny": ReproducibilityConfig(
            num_seeds=1, num_iterations=3, env_batch=16, num_episodes=4, num_cells=16, chunk_size=4,
            episode_length=50, policy_hidden=(16, 16), critic_hidden=(32, 32), num_critic_steps=10,
            num_pg_steps=5, td3_batch_size=32, buffer_size=20_000, cvt_samples=2_000, cvt_iterations=10,
            ant_omni_goals=10, halfcheetah_uni_goals=8, accuracy_episodes=3, reassess_episodes=3,
            representative_episodes=6, ant_omni_box=2.5),
        "small": ReproducibilityConfig(
            num_seeds=3, num_iterations=8, env_batch=64, num_episodes=4, num_cells=16, chunk_size=3,
            policy_hidden=(64, 64), critic_hidden=(64, 64), num_critic_steps=150, num_pg_steps=50,
            td3_batch_size=128, buffer_size=100_000, cvt_samples=20_000, accuracy_episodes=5,
            reassess_episodes=3, ant_omni_box=9.5, ant_omni_goals=25, halfcheetah_uni_goals=16),
        "paper": ReproducibilityConfig(
            num_seeds=5, num_iterations=1000, env_batch=1000, num_episodes=10, num_cells=1024, chunk_size=20),
    },
    "ch4_qdt": {
        "tiny": QDTConfig(  # two seeds, one full: every code path runs
            num_seeds=2, full_seeds=1, epochs=2, eval_every=1, embed_dim=16, num_layers=1, num_heads=2, batch_size=8,
            learning_rate=1e-3, eval_episodes=2, cvt_samples=2_000, cvt_iterations=10, density_bins=10,
            ant_omni=QDTTask(zones=8, goals=8, selection_episodes=2, episodes_per_policy=3),
            halfcheetah_uni=QDTTask(zones=6, goals=6, selection_episodes=2, episodes_per_policy=3)),
        # small: the zones follow the repertoire (two of its 16 cells per zone, the fewest that still leaves
        # the selection a choice; the thesis's 10-20 cells per zone would leave one or two zones); the goals
        # are the Chapter 4 notebook's counts at this scale; seed 0 trains every QDT, seeds 1-2 the claim's two;
        # 3 episodes per goal (the reassessment's count): with 5 the notebook took 1057 s on 2 cores, over the
        # 15-minute aim (evaluations are about 13 s of each QDT's 14-55 s).
        "small": QDTConfig(
            num_seeds=3, full_seeds=1, epochs=10, eval_every=5, embed_dim=64, num_layers=1, num_heads=2,
            batch_size=8, learning_rate=1e-3, eval_episodes=3, cvt_samples=20_000,
            ant_omni=QDTTask(zones=8, goals=25, selection_episodes=4, episodes_per_policy=16),
            halfcheetah_uni=QDTTask(zones=8, goals=16, selection_episodes=4, episodes_per_policy=16)),
        "paper": QDTConfig(
            num_seeds=3, epochs=100, eval_every=5,
            ant_omni=QDTTask(zones=100, goals=100, selection_episodes=10, episodes_per_policy=3000),
            halfcheetah_uni=QDTTask(zones=50, goals=50, selection_episodes=10, episodes_per_policy=6000)),
    },
    "ch5_flow_lenia": {
        "tiny": FlowLeniaChapterConfig(
            num_seeds=1, world=lenia_world(16, kernels=4), gallery_systems=3, system_candidates=4, system_probes=2,
            eval_episodes=64, search_iterations=3, search_batch=8, search_bins=(4, 4), search_chunk=3,
            flt=FLTConfig(embed_dim=16, num_layers=1, num_heads=2, features=(4, 8), batch_size=4, train_steps=20)),
        "small": FlowLeniaChapterConfig(
            num_seeds=1, world=lenia_world(32),
            flt=FLTConfig(embed_dim=128, num_layers=2, num_heads=4, features=(8, 16, 32), batch_size=8,
                          learning_rate=1e-3, train_steps=800)),  # bench/flt_sweep.py: "narrow-cnn"
        "paper": FlowLeniaChapterConfig(
            num_seeds=1, world=lenia_world(128), eval_episodes=256, search_iterations=200, search_batch=64,
            search_bins=(16, 16),
            flt=FLTConfig(embed_dim=256, num_layers=4, num_heads=8, features=(32, 64, 128, 128), batch_size=32,
                          learning_rate=3e-4, train_steps=20_000)),
    },
    "ch3_qdpg": {
        "tiny": QDPGConfig(
            num_seeds=1, chunk_size=10, ant_methods=("QD-PG", "TD3"), adaptation_goals=20, adaptation_budget=10,
            pointmaze=dataclasses.replace(POINTMAZE_PAPER, num_steps=8_000, policy_hidden=(16, 16),
                                          critic_hidden=(32, 32), optimizer="adam", learning_rate=1e-3, mutation_learning_rate=1e-3,
                                          buffer_size=20_000, num_critic_steps=10, num_pg_steps=10),
            antmaze=ANT_TINY,
            anttrap=ANT_TINY),
        # small Point-Maze: Table 3.2's networks, minibatch, K, grid and archive (threshold 1e-4, 10,000
        # FIFO slots), with N = 8 actors per iteration: bench/qdpg_sweep.py's pick, variant
        # "table-3.2+actors-8" (round 2); 100 gradient steps per iteration and Adam at QDax's rates per
        # role; the largest equal budget for six methods, in steps of 1e5, that fits the notebook's
        # time on 2 cores (about 15 min), measured: see the notebook's small-rule cell (issue 14);
        # QD-PG on Point-Maze on 2 seeds, the other methods on 1.
        "small": QDPGConfig(
            num_seeds=1, chunk_size=10, ant_methods=("QD-PG", "TD3"), pointmaze_qdpg_seeds=2,
            pointmaze=dataclasses.replace(POINTMAZE_PAPER, num_steps=300_000, num_actors=8, optimizer="adam",
                                          learning_rate=3e-4, mutation_learning_rate=1e-3, buffer_size=1_000_000,
                                          num_critic_steps=100, num_pg_steps=100),
            antmaze=ANT_SMALL,
            anttrap=ANT_SMALL),
        "paper": QDPGConfig(num_seeds=5, chunk_size=50, pointmaze=POINTMAZE_PAPER, antmaze=ANT_PAPER,
                            anttrap=dataclasses.replace(ANT_PAPER, episode_length=1000)),
    },
}


def chapters() -> list[str]:
    return sorted(_CONFIGS)


def config(chapter: str, scale: str):
    """The frozen config of ``chapter`` at ``scale`` (``tiny``, ``small`` or ``paper``)."""
    if chapter not in _CONFIGS:
        raise ValueError(f"unknown chapter {chapter!r}; valid chapters: {', '.join(chapters())}")
    check_scale(scale)
    return _CONFIGS[chapter][scale]


def check_scale(scale: str) -> str:
    if scale not in SCALES:
        raise ValueError(f"unknown scale {scale!r}; valid scales: {', '.join(SCALES)}")
    return scale


def config_dict(cfg) -> dict:
    return {"type": type(cfg).__name__, **dataclasses.asdict(cfg)}


def config_hash(cfg) -> str:
    """A short, stable hash of a config (its class name and field values)."""
    blob = json.dumps(config_dict(cfg), sort_keys=True, default=list)
    return hashlib.sha256(blob.encode()).hexdigest()[:16]
