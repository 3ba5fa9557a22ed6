"""The reproducibility experiment (Sections 4.3-4.5.4), one environment at a time: the five
methods on one budget, then every final repertoire through the accuracy experiment, the
reassessment and three representative policies; the repertoires saved for the QDT page.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import TYPE_CHECKING, Any

import jax
import numpy as np
from flax import traverse_util

from qdnb.chapters.ch4_reproducibility.settings import (
    LOW_SPREAD,
    REPRESENTATIVE_QUANTILES,
    fitness_offset,
)
from qdnb.core.io import load_arrays, save_arrays
from qdnb.core.loops import map_concurrently
from qdnb.core.tree import stack
from qdnb.envs import env_names
from qdnb.envs.base import Env
from qdnb.envs.player import Player
from qdnb.nets.mlp import MLP
from qdnb.qd.algorithms import MapElitesLowSpread, MapElitesSampling, PolicyMapElites, run_seeds
from qdnb.qd.cvt import cvt_centroids
from qdnb.qd.low_spread import accuracy, reassess
from qdnb.qd.metrics import qd_metrics
from qdnb.qd.pga import PGAMapElites, PGAMapElitesLowSpread
from qdnb.qd.repertoire import Repertoire
from qdnb.rl.td3 import TD3Config

if TYPE_CHECKING:
    from qdnb.chapters.ch4_reproducibility.settings import ReproducibilityConfig


def build_algorithms(
    cfg: ReproducibilityConfig, env: Env, network: MLP, centroids: jax.Array, offset: float
) -> dict[str, PolicyMapElites]:
    """The five methods with the hyper-parameters of Tables 4.1 and 4.2."""
    multi = cfg.env_batch // cfg.num_episodes
    common = dict(
        env=env,
        network=network,
        iso_sigma=cfg.iso_sigma,
        line_sigma=cfg.line_sigma,
        centroids=centroids,
        fitness_offset=offset,
    )
    td3 = TD3Config(
        gamma=cfg.discount,
        policy_noise=cfg.policy_noise,
        noise_clip=cfg.noise_clip,
        critic_lr=cfg.critic_lr,
        actor_lr=cfg.policy_lr,
        batch_size=cfg.td3_batch_size,
        critic_hidden=cfg.critic_hidden,
    )
    pga = dict(
        td3_config=td3,
        num_critic_steps=cfg.num_critic_steps,
        num_pg_steps=cfg.num_pg_steps,
        pg_proportion=cfg.pg_proportion,
        buffer_size=cfg.buffer_size,
    )
    return {
        name: build(
            cfg, dict(common, batch_size=cfg.env_batch if name in ONE_EPISODE else multi), pga
        )
        for name, build in METHODS.items()
    }


ONE_EPISODE = ("ME", "PGA-ME")  # one episode per candidate; the others play num_episodes
# name -> builder(cfg, common keywords, PGA keywords), in table order: adding a method is one entry
METHODS = {
    "ME": lambda cfg, common, pga: PolicyMapElites(**common),
    "ME-LS": lambda cfg, common, pga: MapElitesLowSpread(**common, num_episodes=cfg.num_episodes),
    "PGA-ME": lambda cfg, common, pga: PGAMapElites(**common, **pga),
    "PGA-ME-LS": lambda cfg, common, pga: PGAMapElitesLowSpread(
        **common, **pga, num_episodes=cfg.num_episodes
    ),
    "ME-Sampling": lambda cfg, common, pga: MapElitesSampling(
        **common, num_episodes=cfg.num_episodes
    ),
}


def representative_cells(
    repertoire: Repertoire, env_name: str, quantiles: tuple[float, ...] = REPRESENTATIVE_QUANTILES
) -> np.ndarray:
    """The rule for Figures 4.3-4.5: rank the filled cells by how far the stored
    descriptor is from the start (Ant-Omni) or by fitness (Halfcheetah-Uni, whose
    descriptor has no start), and take the cells at the given quantiles of that
    ranking: a typical, a good and an outstanding policy of the repertoire."""
    filled = np.flatnonzero(np.asarray(repertoire.filled))
    if filled.size == 0:
        raise ValueError("the repertoire is empty")
    if env_name == "ant_omni":
        key = np.linalg.norm(np.asarray(repertoire.descriptors)[filled], axis=-1)
    else:
        key = np.asarray(repertoire.fitnesses)[filled]
    ranked = filled[np.argsort(key, kind="stable")]
    return ranked[[int(round(q * (ranked.size - 1))) for q in quantiles]]


@dataclass(frozen=True)
class MethodResult:
    """One method on one environment, all seeds: every array has the seeds on axis 0.

    ``history``: coverage, max fitness and QD score per iteration; ``repertoire``
    the final elites and ``spread_at_insertion`` their spread when inserted (NaN for
    the single-episode methods); ``accuracy`` the accuracy experiment (Section
    4.5.2); ``reassessed`` the elites re-inserted after replaying them, with their
    ``reassessed_spread`` (Table 4.5), without genotypes (the elites' own, re-filed: at
    paper scale a second copy of five seeds' 1,024 policies of 256x256 units is 1.5 GB
    per method, and the paper dry run ran out of host memory holding them); ``metrics``
    and ``metrics_reassessed`` the QD metrics before and after; ``representatives`` the
    three policies of Figures 4.3-4.5 (seed 0), played ``representative_episodes`` times."""

    history: dict[str, np.ndarray]
    repertoire: Repertoire
    spread_at_insertion: np.ndarray
    accuracy: Any
    reassessed: Repertoire
    reassessed_spread: np.ndarray
    metrics: dict[str, np.ndarray]
    metrics_reassessed: dict[str, np.ndarray]
    representatives: dict[str, np.ndarray]
    env_steps: int
    run_seconds: float
    seconds: float


@dataclass(frozen=True)
class EnvironmentResult:
    """Every method on one environment: the task, its CVT ``centroids`` (the
    repertoires' cells) and ``goals`` (the accuracy experiment's), the QD score's
    ``fitness_offset``, and a ``MethodResult`` per method."""

    env_name: str
    env: Env
    centroids: np.ndarray
    goals: np.ndarray
    fitness_offset: float
    methods: dict[str, MethodResult]

    @cached_property
    def scores(self) -> dict[str, dict[str, np.ndarray]]:
        """``seed_scores`` of every method, computed once."""
        return {name: seed_scores(self, name) for name in self.methods}


def run_environment(
    cfg: ReproducibilityConfig,
    env_name: str,
    key: jax.Array,
    progress: bool = True,
    methods: tuple[str, ...] = tuple(METHODS),
) -> EnvironmentResult:
    """Every method on ``env_name`` for ``cfg.num_seeds`` seeds, and the tests of
    their final repertoires."""
    unknown = set(methods) - set(METHODS)
    if unknown:
        raise ValueError(f"unknown methods {sorted(unknown)}; valid: {', '.join(METHODS)}")
    env = cfg.make_env(env_name)
    network = MLP(cfg.policy_hidden + (env.action_size,))
    k_cvt, k_goals, k_run, k_acc, k_re, k_rep = jax.random.split(key, 6)
    low, high = env.descriptor_low, env.descriptor_high
    centroids = cvt_centroids(k_cvt, cfg.num_cells, low, high, cfg.cvt_samples, cfg.cvt_iterations)
    goals = cvt_centroids(
        k_goals, cfg.goals(env_name), low, high, cfg.cvt_samples, cfg.cvt_iterations
    )
    offset = fitness_offset(env_name, cfg.episode_length)
    algorithms = build_algorithms(cfg, env, network, centroids, offset)

    # one compiled simulation for all the tests
    player = Player(env, network, chunk=cfg.env_batch, name=f"{env_name} test episodes")
    per_seed = lambda f, elites, k: stack(
        [
            f(jax.tree.map(lambda x: x[i], elites), k_i)
            for i, k_i in enumerate(jax.random.split(k, cfg.num_seeds))
        ]
    )
    accuracy_fn = lambda rep, k: accuracy(rep, goals, player.episodes(cfg.accuracy_episodes), k)
    reassess_fn = lambda rep, k: reassess(
        rep, player.episodes(cfg.reassess_episodes, only=rep.filled), k
    )
    metrics_fn = jax.vmap(lambda rep: qd_metrics(rep, offset))

    seeds = jax.random.split(k_run, cfg.num_seeds)
    results: dict[str, MethodResult] = {}
    for name in methods:
        algorithm = algorithms[name]
        start = time.time()
        states, _, history = run_seeds(
            algorithm,
            seeds,
            cfg.num_iterations,
            cfg.chunk_size,
            progress=progress,
            desc=f"{env_name} {name}",
            keep_evaluations=False,
        )
        jax.block_until_ready(states)
        run_seconds = time.time() - start
        elites = algorithm.elites(states.repertoire)
        acc = per_seed(accuracy_fn, elites, k_acc)
        reassessed, scores = per_seed(reassess_fn, elites, k_re)
        seed0 = jax.tree.map(lambda x: x[0], elites)
        cells = representative_cells(seed0, env_name)
        played = player.episodes(cfg.representative_episodes)(
            jax.tree.map(lambda x: x[cells], seed0.genotypes), k_rep
        )
        results[name] = MethodResult(
            history=jax.device_get(
                {k: history[k] for k in ("coverage", "max_fitness", "qd_score")}
            ),
            repertoire=jax.device_get(elites),
            spread_at_insertion=(
                np.asarray(states.repertoire.spreads)
                if name in LOW_SPREAD
                else np.full(np.shape(elites.fitnesses), np.nan)
            ),
            accuracy=jax.device_get(acc),
            reassessed=jax.device_get(reassessed.replace(genotypes=None)),
            reassessed_spread=np.where(
                np.asarray(elites.filled), np.asarray(scores.spread), np.nan
            ),
            metrics=jax.device_get(metrics_fn(elites)),
            metrics_reassessed=jax.device_get(metrics_fn(reassessed)),
            representatives={
                "cells": cells,
                "stored_descriptor": np.asarray(seed0.descriptors)[cells],
                "descriptor": np.asarray(played.descriptor),  # (3, episodes, d)
                "state_descriptor": np.asarray(played.trajectory),  # (3, episodes, T, d)
            },
            env_steps=int((cfg.num_iterations + 1) * cfg.env_batch * cfg.episode_length),
            run_seconds=run_seconds,
            seconds=time.time() - start,
        )
        del states, history, elites, reassessed  # before the next method's run: not beside it
    return EnvironmentResult(
        env_name, env, np.asarray(centroids), np.asarray(goals), offset, results
    )


def run_environments(
    cfg: ReproducibilityConfig, key: jax.Array, progress: bool = True, concurrent: bool = True
) -> dict[str, EnvironmentResult]:
    """``run_environment`` for each of ``cfg.environments``, each with its own
    key (``fold_in`` of the environment's index), in concurrent threads unless
    ``concurrent`` is false.  The numbers do not depend on the concurrency."""
    unknown = set(cfg.environments) - set(env_names())
    if unknown:  # before any thread starts computing
        raise ValueError(f"unknown environments {sorted(unknown)}; valid: {', '.join(env_names())}")
    keys = {name: jax.random.fold_in(key, i) for i, name in enumerate(cfg.environments)}
    return map_concurrently(
        lambda name: run_environment(cfg, name, keys[name], progress), cfg.environments, concurrent
    )


def seed_scores(res: EnvironmentResult, name: str) -> dict[str, np.ndarray]:
    """Per seed (axis 0), method ``name`` of an environment's result: the accuracy
    experiment's average distance and spread (Table 4.4), the distance the stored
    descriptors promised for the same goals and the reproduction gap (delivered minus
    promised), the coverage, and the share of it kept on reassessment (Table 4.5)."""
    r = res.methods[name]
    acc, rep = r.accuracy, r.repertoire
    chosen = np.take_along_axis(rep.descriptors, acc.chosen[..., None], axis=1)  # (seeds, goals, d)
    promised = np.linalg.norm(chosen - res.goals[None], axis=-1)
    before, after = r.metrics, r.metrics_reassessed
    return {
        "avg_distance": acc.distance.mean(1),
        "avg_spread": acc.spread.mean(1),
        "avg_promised_distance": promised.mean(1),
        "reproduction_gap": (acc.distance - promised).mean(1),
        "coverage": np.asarray(before["coverage"]),
        "coverage_kept": np.asarray(after["coverage"] / np.maximum(before["coverage"], 1e-12)),
    }


# ----- saving repertoires for the QDT chapter (pickle-free .npz) -----


def save_repertoires(
    path: Path,
    config_hash: str,
    repertoire: Repertoire,
    spread: np.ndarray,
    reassessed_spread: np.ndarray,
) -> Path:
    """Save a ``(seeds, cells, ...)`` stack of repertoires: centroids, fitnesses,
    descriptors, spreads and every parameter leaf (``genotype/<path>``)."""
    flat = traverse_util.flatten_dict(jax.device_get(repertoire.genotypes), sep="/")
    return save_arrays(
        path,
        config_hash,
        centroids=repertoire.centroids[0],
        fitnesses=repertoire.fitnesses,
        descriptors=repertoire.descriptors,
        spread=spread,
        reassessed_spread=reassessed_spread,
        **{f"genotype/{k}": v for k, v in flat.items()},
    )


def load_repertoires(path: Path, config_hash: str) -> dict[str, Any] | None:
    """The arrays written by ``save_repertoires`` with the genotypes as a nested
    parameter dict, or ``None`` when missing or computed under another config."""
    arrays = load_arrays(path, config_hash)
    if arrays is None:
        return None
    genotype = {k[len("genotype/") :]: v for k, v in arrays.items() if k.startswith("genotype/")}
    out = {k: v for k, v in arrays.items() if not k.startswith("genotype/")}
    out["genotypes"] = traverse_util.unflatten_dict(genotype, sep="/")
    return out
