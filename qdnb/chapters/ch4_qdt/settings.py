"""The QDT page's settings (Table 4.3): the task of each environment, the page's config,
its datasets and methods, and its scales.
"""

from __future__ import annotations

from dataclasses import dataclass

from qdnb.models.qdt.data import (
    NAIVE,
    SOURCES,
)


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
    train_steps: int  # gradient steps, the same for every dataset
    eval_every: int  # gradient steps between evaluations on the goals
    embed_dim: int = 256
    num_layers: int = 4
    num_heads: int = 8
    dropout: float = 0.1
    batch_size: int = 256
    learning_rate: float = 7e-4
    # the QDT as Algorithm 8 reads (linear head, Flax's initialisation, the raw BD), or
    # a labelled departure (qdnb.models.qdt.model): "tanh", "torch", True
    head: str = "linear"
    init_scheme: str = "flax"
    bd_scaling: bool = False
    heldout_episodes: int = 2  # per demonstrator: fresh episodes for the held-out error
    eval_episodes: int = 10
    tiles: int = 4  # the "Tiles" dataset: a tiles x tiles checkerboard, half of it removed
    density_bins: int = 30
    cvt_samples: int = 50_000
    cvt_iterations: int = 30
    environments: tuple[str, ...] = ("ant_omni", "halfcheetah_uni")
    full_seeds: int | None = None

    def __post_init__(self):
        if self.full_seeds is not None and not 1 <= self.full_seeds <= self.num_seeds:
            raise ValueError(
                f"full_seeds ({self.full_seeds}) must be between 1 and num_seeds ({self.num_seeds})"
            )
        if self.train_steps < 1 or self.eval_every < 1 or self.train_steps % self.eval_every:
            raise ValueError(
                f"train_steps ({self.train_steps}) must be a positive multiple of eval_every "
                f"({self.eval_every})"
            )
        if self.heldout_episodes < 1:
            raise ValueError(f"heldout_episodes must be at least 1, not {self.heldout_episodes}")
        if self.embed_dim % self.num_heads:
            raise ValueError(
                f"embed_dim ({self.embed_dim}) must be a multiple of num_heads ({self.num_heads})"
            )
        unknown = set(self.environments) - {"ant_omni", "halfcheetah_uni"}
        if unknown:
            raise ValueError(
                f"unknown environments {sorted(unknown)}; valid: ant_omni, halfcheetah_uni"
            )

    @property
    def num_full_seeds(self) -> int:
        return self.num_seeds if self.full_seeds is None else self.full_seeds

    def task(self, env_name: str) -> QDTTask:
        if env_name not in ("ant_omni", "halfcheetah_uni"):
            raise ValueError(f"unknown environment {env_name!r}; valid: ant_omni, halfcheetah_uni")
        return getattr(self, env_name)


DATASETS = SOURCES + (NAIVE,)
# each QDT of Table 4.4, by its label, and the dataset it learns from
METHODS = {f"QDT({name})": name for name in DATASETS}
CLAIM_SOURCES = (
    "ME",
    "ME-LS",
)  # the accuracy claim: QDT(ME-LS) against the ME repertoire and QDT(ME)


Config = QDTConfig


# The chapter's configs, one per scale (the rule of each is in the notebook's scale cell).
SCALES = {
    "tiny": QDTConfig(  # two seeds, one full: every code path runs
        num_seeds=2,
        full_seeds=1,
        train_steps=4,
        eval_every=2,
        embed_dim=16,
        num_layers=1,
        num_heads=2,
        batch_size=8,
        learning_rate=1e-3,
        eval_episodes=2,
        cvt_samples=2_000,
        cvt_iterations=10,
        density_bins=10,
        ant_omni=QDTTask(zones=8, goals=8, selection_episodes=2, episodes_per_policy=3),
        halfcheetah_uni=QDTTask(zones=6, goals=6, selection_episodes=2, episodes_per_policy=3),
    ),
    # small: the zones follow the repertoire (two of its 16 cells per zone, the fewest that
    # still leaves the selection a choice; the thesis's 10-20 cells per zone would leave one
    # or two zones); the goals are the Chapter 4 notebook's counts at this scale; seed 0
    # trains every QDT, seeds 1-2 the claim's two; 3 episodes per goal (with 5 the notebook
    # took 1057 s).  200 gradient steps, evaluated at 100 and 200: the most the time rule
    # allows (894 s; 500 steps took 1,852 s), against the 2,250 the learning curve asks for
    # (bench/qdt.py curve, bench/results/qdt_curve.json; the notebook's scale cell)
    "small": QDTConfig(
        num_seeds=3,
        full_seeds=1,
        train_steps=200,
        eval_every=100,
        embed_dim=64,
        num_layers=1,
        num_heads=2,
        batch_size=8,
        learning_rate=1e-3,
        eval_episodes=3,
        cvt_samples=20_000,
        ant_omni=QDTTask(zones=8, goals=25, selection_episodes=4, episodes_per_policy=16),
        halfcheetah_uni=QDTTask(zones=8, goals=16, selection_episodes=4, episodes_per_policy=16),
    ),
    "paper": QDTConfig(
        num_seeds=3,
        # Section 4.5.1: 100 epochs of 300,000 trajectories in batches of 256 (117,180
        # steps), evaluated every 5 epochs
        train_steps=117_180,
        eval_every=5_859,
        ant_omni=QDTTask(zones=100, goals=100, selection_episodes=10, episodes_per_policy=3000),
        halfcheetah_uni=QDTTask(
            zones=50, goals=50, selection_episodes=10, episodes_per_policy=6000
        ),
    ),
}
