"""What the QDT page keeps of a run: the scores of each method against its goals, each
QDT's training run, and an environment's results over seeds.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import numpy as np

from qdnb.models.qdt.data import Selection


@dataclass(frozen=True)
class Scores:
    """Stored policies played on the evaluation goals (Section 4.5.2), seeds on axis 0:
    per goal the ``distance`` to it and the ``spread`` of the episodes ``(seeds,
    goals)``; ``filled`` the repertoire's stored policies per seed, where known."""

    distance: np.ndarray
    spread: np.ndarray
    filled: np.ndarray | None = None
    imitation: np.ndarray | None = None  # (seeds, zones): the demonstrators' own distance

    @property
    def avg_distance(self) -> np.ndarray:
        """Per seed, the mean distance over the goals."""
        return self.distance.mean(axis=1)

    @property
    def avg_spread(self) -> np.ndarray:
        return self.spread.mean(axis=1)


@dataclass(frozen=True)
class QDTRun:
    """One QDT per seed trained on one dataset, seeds on axis 0: the gradient ``steps``
    of the evaluations and per seed the curves at them, the training ``loss`` (mean over
    the steps before each evaluation), the ``best_step`` (the model kept) and its scores
    on the goals; its diagnostics (``conditioning_gap``: the held-out action error of
    the demonstrators' fresh episodes with their own BDs, ``heldout_mse``, and with BDs
    shuffled between demonstrators, ``shuffled_mse``) and, per zone, its distance to the
    BD its demonstrator reaches on average when conditioned on it (``imitation``, NaN
    where the zone has no demonstrator); for the ``tiles`` and ``upper`` prunings, the
    mean distance to the goals inside and outside the removed region."""

    steps: np.ndarray  # (evaluations,)
    avg_distance_curve: np.ndarray  # (seeds, evaluations)
    max_fitness_curve: np.ndarray  # (seeds, evaluations)
    loss: np.ndarray  # (seeds, evaluations)
    best_step: np.ndarray  # (seeds,)
    avg_distance: np.ndarray  # (seeds,)
    avg_spread: np.ndarray  # (seeds,)
    distance: np.ndarray  # (seeds, goals)
    spread: np.ndarray  # (seeds, goals)
    dataset_size: np.ndarray  # (seeds,)
    seconds: np.ndarray  # (seeds,)
    heldout_mse: np.ndarray  # (seeds,)
    shuffled_mse: np.ndarray  # (seeds,)
    imitation: np.ndarray  # (seeds, zones)
    avg_distance_removed: np.ndarray | None = None
    avg_distance_kept: np.ndarray | None = None

    @classmethod
    def stack(cls, runs: list[dict[str, Any]]) -> QDTRun:
        """The per-seed entries of one dataset's QDTs, stacked on axis 0."""
        fields = {f.name for f in dataclasses.fields(cls)} - {"steps"}
        return cls(
            steps=np.asarray(runs[0]["steps"]),
            **{k: np.stack([np.asarray(r[k]) for r in runs]) for k in fields if k in runs[0]},
        )


def by_name(per_seed: list[dict[str, Any]], part: str) -> dict[str, list[Any]]:
    """``seed[part][name]`` of every seed that has it, by name, in seed order (the
    claim's sources run on every seed, the others on the first ``full_seeds``, so
    position ``i`` of each list is seed ``i``)."""
    out: dict[str, list[Any]] = {}
    for seed in per_seed:
        for name, value in seed[part].items():
            out.setdefault(name, []).append(value)
    return out


@dataclass(frozen=True)
class EnvironmentResult:
    """Every experiment of the chapter on one environment, seeds on axis 0: the
    descriptor box (``low``, ``high``), the selection ``zones`` and evaluation
    ``goals`` (their own CVTs), the goals each pruning removes; per source the
    repertoire's and its kept policies' (``teachers``) ``Scores``, the zone
    ``selection`` and the ``datasets``' descriptors (one per seed: their sizes
    differ); per dataset the ``qdt`` and per pruning the ``generalization``
    ``QDTRun``.  The seeds past ``full_seeds`` hold only ``CLAIM_SOURCES``."""

    env_name: str
    low: tuple[float, ...]
    high: tuple[float, ...]
    zones: np.ndarray
    goals: np.ndarray
    removed_goals: dict[str, np.ndarray]
    repertoire: dict[str, Scores]
    teachers: dict[str, Scores]
    selection: dict[str, tuple[Selection, ...]]
    datasets: dict[str, tuple[np.ndarray, ...]]
    qdt: dict[str, QDTRun]
    generalization: dict[str, QDTRun]
    naive_episodes_per_policy: tuple[int, ...]
    full_seeds: int
    # seed 0's QDT(ME-LS) parameters (its best evaluation's), for episodes.goal_episodes
    watched: Any = None
    seconds: float = float("nan")

    @classmethod
    def collect(
        cls,
        env_name: str,
        low: tuple[float, ...],
        high: tuple[float, ...],
        zones: np.ndarray,
        goals: np.ndarray,
        removed_goals: dict[str, np.ndarray],
        per_seed: list[dict[str, Any]],
    ) -> EnvironmentResult:
        """The result from ``run_environment``'s per-seed entries."""

        def scores(part: str) -> dict[str, Scores]:
            return {
                name: Scores(
                    np.stack([s["distance"] for s in seeds]),
                    np.stack([s["spread"] for s in seeds]),
                    np.array([s["filled"] for s in seeds]) if "filled" in seeds[0] else None,
                    np.stack([s["imitation"] for s in seeds]) if "imitation" in seeds[0] else None,
                )
                for name, seeds in by_name(per_seed, part).items()
            }

        def runs(part: str) -> dict[str, QDTRun]:
            return {name: QDTRun.stack(r) for name, r in by_name(per_seed, part).items()}

        return cls(
            env_name,
            low,
            high,
            zones,
            goals,
            removed_goals,
            repertoire=scores("repertoire"),
            teachers=scores("teachers"),
            selection={k: tuple(v) for k, v in by_name(per_seed, "selection").items()},
            datasets={k: tuple(v) for k, v in by_name(per_seed, "datasets").items()},
            qdt=runs("qdt"),
            generalization=runs("generalization"),
            naive_episodes_per_policy=tuple(
                s["naive_episodes_per_policy"] for s in per_seed if "naive_episodes_per_policy" in s
            ),
            full_seeds=sum(bool(s["full"]) for s in per_seed),
            watched=per_seed[0].get("watched"),
        )
