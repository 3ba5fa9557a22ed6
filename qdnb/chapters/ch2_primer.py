"""Chapters 1-2, the primer: a fitness-driven GA, Novelty Search and MAP-Elites on
the deceptive Point-Maze, under one budget and one variation operator (Figure 1.4,
Section 2.2.2).

``run(cfg, key)`` runs every method of ``METHODS`` on ``cfg.num_seeds`` seeds at
once and returns a ``Result``; ``method_metrics`` and ``claim`` derive the
chapter's table and verdict from it, so a notebook cell only reads.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from functools import cached_property
from typing import Any, Callable

import jax
import numpy as np

from qdnb.core import claims
from qdnb.core.tree import take
from qdnb.envs import make_env
from qdnb.envs.base import Env
from qdnb.envs.pointmaze import GOAL, in_goal
from qdnb.envs.render import episode_path
from qdnb.nets.mlp import MLP
from qdnb.qd.algorithms import (
    GeneticAlgorithm,
    NoveltySearch,
    PolicyMapElites,
    PolicySearch,
    run_seeds,
)
from qdnb.qd.cvt import grid_centroids
from qdnb.qd.repertoire import Repertoire


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

    @property
    def episodes(self) -> int:
        """Episodes per method and seed."""
        return self.batch_size * (self.num_iterations + 1)

    @property
    def env_steps(self) -> int:
        """Environment steps per method and seed (every episode at its full length)."""
        return self.episodes * self.episode_length


Config = PrimerConfig


def _ga(cfg: PrimerConfig, common: dict) -> PolicySearch:
    return GeneticAlgorithm(**common, population_size=cfg.ga_population)


def _ns(cfg: PrimerConfig, common: dict) -> PolicySearch:
    return NoveltySearch(
        **common,
        population_size=cfg.ns_population,
        k=cfg.ns_k,
        archive_size=cfg.ns_archive_size,
        archive_threshold=cfg.ns_archive_threshold,
    )


def _me(cfg: PrimerConfig, common: dict) -> PolicySearch:
    centroids = grid_centroids(
        cfg.me_bins, common["env"].descriptor_low, common["env"].descriptor_high
    )
    return PolicyMapElites(**common, centroids=centroids, fitness_offset=cfg.fitness_offset)


# name -> builder(cfg, common keywords): adding a method is one entry
METHODS: dict[str, Callable[[PrimerConfig, dict], PolicySearch]] = {"GA": _ga, "NS": _ns, "ME": _me}


def make_task(cfg: PrimerConfig) -> tuple[Env, MLP]:
    env = make_env("pointmaze", episode_length=cfg.episode_length)
    return env, MLP(cfg.policy_hidden + (env.action_size,))


def build_algorithms(cfg: PrimerConfig, env: Env, network: MLP) -> dict[str, PolicySearch]:
    common = dict(
        env=env,
        network=network,
        batch_size=cfg.batch_size,
        iso_sigma=cfg.iso_sigma,
        line_sigma=cfg.line_sigma,
    )
    return {name: build(cfg, common) for name, build in METHODS.items()}


@dataclass(frozen=True)
class MethodRun:
    """One method on every seed: ``history`` arrays are ``(seeds, iterations + 1, ...)``
    (entry 0 the initial batch): ``coverage`` and ``min_distance`` of the exploration
    track, ``descriptors`` and ``fitnesses`` of every evaluated policy, and the
    algorithm's own metrics; ``final`` the final states (seeds on axis 0)."""

    history: dict[str, np.ndarray]
    final: Any
    seconds: float


@dataclass(frozen=True)
class Result:
    config: PrimerConfig
    runs: dict[str, MethodRun]

    @property
    def steps_axis(self) -> np.ndarray:
        """Environment steps spent after each evaluation (iterations + 1 of them)."""
        cfg = self.config
        return (np.arange(cfg.num_iterations + 1) + 1) * cfg.batch_size * cfg.episode_length

    def me_repertoire(self, seed: int = 0) -> Repertoire:
        """MAP-Elites' final repertoire of one seed."""
        return take(self.runs["ME"].final.repertoire, seed)

    @cached_property
    def metrics(self) -> dict[str, dict[str, Any]]:
        """``method_metrics`` of this result, computed once."""
        return method_metrics(self)


def run(cfg: PrimerConfig, key: jax.Array, progress: bool = True) -> Result:
    """Every method of ``METHODS`` on ``cfg.num_seeds`` seeds (``vmap``) from ``key``."""
    env, network = make_task(cfg)
    keys = jax.random.split(key, cfg.num_seeds)
    runs = {}
    for name, algorithm in build_algorithms(cfg, env, network).items():
        start = time.time()
        states, _, history = run_seeds(
            algorithm,
            keys,
            cfg.num_iterations,
            cfg.chunk_size,
            cfg.metric_bins,
            GOAL,
            desc=name,
            progress=progress,
        )
        runs[name] = MethodRun(jax.device_get(history), states, time.time() - start)
    return Result(cfg, runs)


def best_episodes(result: Result, key: jax.Array, seed: int = 0) -> dict[str, np.ndarray]:
    """The fittest policy each method holds at the end of seed ``seed`` (the GA's and
    Novelty Search's best of their final population, MAP-Elites' best elite), each
    played for one episode from the same initial state (``key``): ``{method: (T + 1, 2)}``
    positions, held once the episode ends (the chapter's video)."""
    env, network = make_task(result.config)
    paths = {}
    for name, method in result.runs.items():
        final = take(method.final, seed)
        found = final.repertoire if name == "ME" else final
        policies = found.genotypes if name == "ME" else found.population
        best = int(np.argmax(np.asarray(found.fitnesses)))
        paths[name] = episode_path(env, network.apply, take(policies, best), key)
    return paths


def method_metrics(result: Result) -> dict[str, dict[str, Any]]:
    """Per method: final coverage and best distance to the goal (per seed), the
    seeds whose policies reached the goal zone, the environment steps to the first
    such policy, and the best episode return."""
    out = {}
    steps = result.steps_axis
    for name, r in result.runs.items():
        h = r.history
        hit = np.asarray(in_goal(h["descriptors"])).any(axis=-1)  # (seeds, iterations + 1)
        out[name] = {
            "coverage_per_seed": h["coverage"][:, -1],
            "min_distance_per_seed": h["min_distance"][:, -1],
            "reached_per_seed": hit.any(axis=1),
            "steps_to_goal_per_seed": [
                int(steps[np.argmax(row)]) if row.any() else None for row in hit
            ],
            "best_return_per_seed": h["fitnesses"].max(axis=(1, 2)),
            "seconds": r.seconds,
        }
    return out


def summary_results(result: Result) -> dict[str, Any]:
    """The ``results`` of ``summary.json`` (its schema is read by the book and the tests)."""
    cfg = result.config
    results: dict[str, Any] = {
        "env_steps": cfg.env_steps,
        "episodes": cfg.episodes,
        "num_seeds": cfg.num_seeds,
    }
    for name, m in result.metrics.items():
        results[name] = {
            "coverage": float(m["coverage_per_seed"].mean()),
            "coverage_per_seed": m["coverage_per_seed"],
            "min_distance_to_goal": float(np.median(m["min_distance_per_seed"])),
            "min_distance_to_goal_per_seed": m["min_distance_per_seed"],
            "seeds_reaching_goal": int(m["reached_per_seed"].sum()),
            "env_steps_to_goal_per_seed": m["steps_to_goal_per_seed"],
            "best_return": float(np.median(m["best_return_per_seed"])),
            "best_return_per_seed": m["best_return_per_seed"],
            "wall_time_s": round(m["seconds"], 1),
        }
    verdict = claim(result)
    results["headline"] = verdict["headline"]
    results["claims"] = [
        claims.record(
            "ch2/goal",
            "Novelty Search and MAP-Elites reach the maze's goal zone in every seed, the "
            "fitness-driven GA in none (Figure 1.4)",
            verdict["holds"],
            verdict["headline"],
        )
    ]
    return results


def claim(result: Result) -> dict[str, Any]:
    """Figure 1.4's claim: Novelty Search and MAP-Elites reach the goal zone in every
    seed, the fitness-driven GA in none.  Returns ``holds``, the counts, a
    ``headline`` and a ``verdict`` sentence."""
    n = result.config.num_seeds
    m = result.metrics
    ga, ns, me = (int(m[k]["reached_per_seed"].sum()) for k in ("GA", "NS", "ME"))
    holds = ns == n and me == n and ga == 0
    if holds:
        verdict = (
            "**The claim shows at this scale**: Novelty Search and MAP-Elites reached the goal "
            "zone in "
            "every seed, the fitness-driven GA in none."
        )
    elif ga == 0 and ns + me == 0:
        verdict = (
            "**The claim does not show at this scale**: no method reached the goal zone within "
            "this budget "
            "(at `tiny` scale this notebook only checks that every code path runs)."
        )
    else:
        verdict = (
            "**The claim shows only partly at this scale**: the goal zone was reached by NS in "
            f"{ns}/{n}, "
            f"ME in {me}/{n} and the GA in {ga}/{n} seeds."
        )
    return {
        "holds": holds,
        "GA": ga,
        "NS": ns,
        "ME": me,
        "seeds": n,
        "verdict": verdict,
        "headline": f"goal reached in NS {ns}/{n}, ME {me}/{n}, GA {ga}/{n} seeds",
    }


# The chapter's configs, one per scale (the rule of each is in the notebook's scale cell).
SCALES = {
    "tiny": PrimerConfig(
        num_seeds=2, num_iterations=40, batch_size=64, chunk_size=20, ns_population=64
    ),
    "small": PrimerConfig(num_seeds=10, num_iterations=4000, batch_size=256, chunk_size=100),
    "paper": PrimerConfig(
        num_seeds=10,
        num_iterations=1000,
        batch_size=1024,
        chunk_size=100,
        ns_population=1024,
        ns_archive_size=5000,
    ),
}
