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


_CONFIGS: dict[str, dict[str, object]] = {
    "ch2_primer": {
        "tiny": PrimerConfig(num_seeds=2, num_iterations=40, batch_size=64, chunk_size=20, ns_population=64),
        "small": PrimerConfig(num_seeds=5, num_iterations=2000, batch_size=256, chunk_size=100),
        "paper": PrimerConfig(num_seeds=10, num_iterations=1000, batch_size=1024, chunk_size=100,
                              ns_population=1024, ns_archive_size=5000),
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
