"""Chapter 4's reproducibility experiment (Sections 4.3-4.5.4), one environment
at a time: run ME, ME-LS, PGA-ME, PGA-ME-LS and ME-Sampling on the same budget
of environment steps, then put every final repertoire through the same tests:

- the accuracy experiment (Section 4.5.2): for each goal descriptor (the centroids
  of a CVT of the descriptor space), play the stored policy whose descriptor is
  nearest to the goal over fresh episodes; average distance to the goal and spread;
- the reassessment (Table 4.5): play every stored policy again and insert it into
  an empty repertoire;
- three representative policies (Figures 4.3-4.5), chosen by a fixed rule and
  played over many episodes.

``run_environment`` does all of it and returns plain numpy arrays; the
environments are independent, so ``run_environments`` runs them in concurrent
threads (JAX releases the interpreter while it computes: on a 2-core CPU the
two simulations then share the cores, about 1.5x faster than one after the other).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import Any

import jax
import numpy as np
from flax import traverse_util

from qdnb.core import claims as claim_records
from qdnb.core.io import load_arrays, save_arrays
from qdnb.core.loops import map_concurrently
from qdnb.core.names import ENV_LABELS
from qdnb.core.tree import stack
from qdnb.envs import env_names, make_env
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

THESIS_ANT_OMNI_BOX = 15.0  # Ant-Omni's descriptor box [-15, 15]^2 (Section 4.5.1)


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
    ant_omni_box: float = THESIS_ANT_OMNI_BOX
    # evaluation of the final repertoires (Section 4.5.2, Table 4.5, Figures 4.3-4.5)
    ant_omni_goals: int = 100
    halfcheetah_uni_goals: int = 50
    accuracy_episodes: int = 10
    reassess_episodes: int = 10
    representative_episodes: int = 30

    def __post_init__(self):
        if self.env_batch % self.num_episodes:
            raise ValueError(
                f"env_batch ({self.env_batch}) must be a multiple of num_episodes "
                f"({self.num_episodes})"
            )
        if self.env_batch // self.num_episodes < 2:
            raise ValueError(
                "env_batch // num_episodes must be at least 2 (one PG and one GA offspring)"
            )
        if not self.ant_omni_box > 0:
            raise ValueError(f"ant_omni_box must be positive, got {self.ant_omni_box}")

    def goals(self, env_name: str) -> int:
        return getattr(self, f"{env_name}_goals")

    def descriptor_box(self, env_name: str) -> dict[str, tuple[float, ...]]:
        """The descriptor bounds of ``env_name`` at this scale, as ``make_env`` keywords."""
        if env_name == "ant_omni":
            return {
                "descriptor_low": (-self.ant_omni_box,) * 2,
                "descriptor_high": (self.ant_omni_box,) * 2,
            }
        return {}

    def extent_note(self, env_name: str, thesis: float, ours: float) -> str:
        """For a distance in the descriptor space of a box that differs from the thesis's
        (Ant-Omni below ``paper``): both distances as a share of their box's side, the
        comparison that is like for like; empty where the boxes agree."""
        thesis_side, side = 2 * THESIS_ANT_OMNI_BOX, 2 * self.ant_omni_box
        if env_name != "ant_omni" or side == thesis_side:
            return ""
        return (
            f"as a share of the box's side: thesis {thesis / thesis_side:.2f} "
            f"(of {thesis_side:g} m), this run {ours / side:.2f} (of {side:g} m)"
        )

    def make_env(self, env_name: str):
        """The environment as this chapter runs it: its episode length and descriptor box."""

        return make_env(
            env_name, episode_length=self.episode_length, **self.descriptor_box(env_name)
        )


LOW_SPREAD = ("ME-LS", "PGA-ME-LS")
REPRESENTATIVE_QUANTILES = (0.5, 0.75, 0.95)


def fitness_offset(env_name: str, episode_length: int) -> float:
    """A lower bound on the fitness, subtracted in the QD score so that every
    elite counts positively: the largest action cost (||a||_2 <= sqrt(|A|) with
    actions in [-1, 1]) at every step, plus, for Halfcheetah-Uni, running
    backwards at 10 m/s (faster than any cheetah here runs)."""
    if env_name == "ant_omni":
        return -episode_length * float(np.sqrt(8))
    if env_name == "halfcheetah_uni":
        return -episode_length * (float(np.sqrt(6)) + 10.0)
    raise ValueError(f"no fitness offset for {env_name!r}")


REACH_QUANTILE = 0.95  # the box holds this share of the pilot's elites ...
REACH_STEP = 0.5  # ... rounded up to a multiple of this (metres)
COVERAGE_TARGET = 0.6  # of the cells, for every method (issue 36: at least 16 cells)


def reach_bound(
    descriptors: np.ndarray, quantile: float = REACH_QUANTILE, step: float = REACH_STEP
) -> float:
    """The half-width ``b`` of the smallest box [-b, b]^2, ``b`` a multiple of
    ``step``, holding at least the ``quantile`` share of ``descriptors`` (the
    ``(n, 2)`` final positions of every elite of a pilot run, all methods and
    seeds pooled): the thesis's rule for Ant-Omni's box ("methods ... tend to
    produce solutions within this range"), applied to a smaller budget."""
    d = np.asarray(descriptors, np.float64).reshape(-1, 2)
    d = d[np.all(np.isfinite(d), axis=1)]
    if d.size == 0:
        raise ValueError("no descriptors to bound")
    if not 0 < quantile <= 1 or step <= 0:
        raise ValueError(f"quantile must be in (0, 1] and step positive, got {quantile} and {step}")
    reach = np.quantile(np.max(np.abs(d), axis=1), quantile)
    return float(max(np.ceil(reach / step - 1e-9), 1) * step)


def cells_for_coverage(coverage: dict[int, np.ndarray], target: float = COVERAGE_TARGET) -> int:
    """The largest cell count whose measured coverage (``coverage[k]``: one value
    per method and seed of a pilot run on the bounded space) reaches ``target``
    for every method on the mean over seeds; the smallest count when none does."""
    if not coverage:
        raise ValueError("no cell counts measured")
    full = [k for k, c in coverage.items() if np.min(np.mean(np.atleast_2d(c), axis=-1)) >= target]
    return max(full) if full else min(coverage)


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


# ----- the chapter's derived metrics and claim checks -----

CLAIM_PAIRS = (("ME-LS", "ME"), ("PGA-ME-LS", "PGA-ME"))  # (Low-Spread variant, its baseline)
# the metrics the claim compares, and the direction that favours the Low-Spread variant
CLAIM_METRICS = (("avg_spread", np.less), ("avg_distance", np.less), ("coverage_kept", np.greater))
# each comparison in the thesis's words (the book's scorecard)
CLAIM_STATEMENTS = {
    "avg_spread": "{ls}'s policies spread less than {base}'s (average spread, Table 4.4)",
    "avg_distance": "{ls} lands closer to requested behaviours than {base} (Table 4.4)",
    "coverage_kept": "{ls} keeps more of its coverage than {base} when re-evaluated (Table 4.5)",
}


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


def comparisons(results_by_env: dict[str, EnvironmentResult]) -> list[tuple[str, str, str, str]]:
    """The claim's comparisons, in ``claim_checks``'s order: (environment, Low-Spread
    variant, its baseline, metric)."""
    return [
        (env_name, ls, base, metric)
        for env_name in results_by_env
        for ls, base in CLAIM_PAIRS
        for metric, _ in CLAIM_METRICS
    ]


def claim_checks(results_by_env: dict[str, EnvironmentResult]) -> list[dict[str, Any]]:
    """The chapter's claim, comparison by comparison (``comparisons``): each Low-Spread
    variant against its baseline on spread, distance and coverage kept.  A comparison
    holds when it goes the thesis's way on the mean over seeds and on most seeds."""
    checks = []
    for env_name, ls, base, metric in comparisons(results_by_env):
        better = dict(CLAIM_METRICS)[metric]
        scores = results_by_env[env_name].scores
        a, b = scores[ls][metric], scores[base][metric]
        wins = int(np.sum(better(a, b)))
        claim = (
            f"{ls} keeps more coverage than {base} on reassessment"
            if metric == "coverage_kept"
            else f"{ls} average {metric.removeprefix('avg_')} < {base}"
        )
        checks.append(
            {
                "environment": env_name,
                "claim": claim,
                "values (mean)": f"{a.mean():.3f} vs {b.mean():.3f}",
                "seeds where it holds": f"{wins}/{a.size}",
                "holds": bool(better(a.mean(), b.mean()) and wins > a.size / 2),
            }
        )
    return checks


def summary_results(
    cfg: ReproducibilityConfig, results_by_env: dict[str, EnvironmentResult]
) -> dict:
    """The ``results`` of ``summary.json`` (its schema is read by the book and the tests)."""
    checks = claim_checks(results_by_env)
    held, total = sum(c["holds"] for c in checks), len(checks)
    results: dict[str, Any] = {
        "headline": f"{held}/{total} claim comparisons hold",
        "claims_held": held,
        "claims_total": total,
        "claims": [
            claim_records.record(
                f"ch4/{env_name}/{ls}/{metric}",
                f"{ENV_LABELS[env_name]}: {CLAIM_STATEMENTS[metric].format(ls=ls, base=base)}",
                c["holds"],
                f"{c['values (mean)']} (mean); the claim's way on "
                f"{c['seeds where it holds']} seeds",
            )
            for (env_name, ls, base, metric), c in zip(comparisons(results_by_env), checks)
        ],
        "num_seeds": cfg.num_seeds,
        "descriptor_bounds": {
            e: {"low": list(res.env.descriptor_low), "high": list(res.env.descriptor_high)}
            for e, res in results_by_env.items()
        },
    }
    mean = lambda d: {k: float(np.mean(d[k])) for k in ("coverage", "max_fitness", "qd_score")}
    for env_name, res in results_by_env.items():
        results[env_name] = {}
        for name, r in res.methods.items():
            seeds = res.scores[name]
            results[env_name][name] = {
                **{
                    k: float(seeds[k].mean())
                    for k in (
                        "avg_distance",
                        "avg_spread",
                        "avg_promised_distance",
                        "reproduction_gap",
                    )
                },
                **mean(r.metrics),
                "reassessed": mean(r.metrics_reassessed),
                "coverage_kept": float(seeds["coverage_kept"].mean()),
                "env_steps": r.env_steps,
                "run_seconds": round(r.run_seconds, 1),
                "seeds": {k: np.asarray(v).tolist() for k, v in seeds.items()},
            }
    return results


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


Config = ReproducibilityConfig


# The chapter's configs, one per scale (the rule of each is in the notebook's scale cell).
SCALES = {
    "tiny": ReproducibilityConfig(
        num_seeds=1,
        num_iterations=3,
        env_batch=16,
        num_episodes=4,
        num_cells=16,
        chunk_size=4,
        episode_length=50,
        policy_hidden=(16, 16),
        critic_hidden=(32, 32),
        num_critic_steps=10,
        num_pg_steps=5,
        td3_batch_size=32,
        buffer_size=20_000,
        cvt_samples=2_000,
        cvt_iterations=10,
        ant_omni_goals=10,
        halfcheetah_uni_goals=8,
        accuracy_episodes=3,
        reassess_episodes=3,
        representative_episodes=6,
        ant_omni_box=2.5,
    ),
    # small's budget, by the notebook's rule (near 15 minutes on 2 cores): on a quiet
    # machine 16 evaluations took 1,236 s and 10 took 1,122 s (2026-12-06), about 19 s an
    # evaluation beside a fixed part no evaluation count removes, so it keeps 10 (the
    # notebook's scale rule has the measurements since)
    "small": ReproducibilityConfig(
        num_seeds=3,
        num_iterations=9,
        env_batch=64,
        num_episodes=4,
        num_cells=16,
        chunk_size=5,
        policy_hidden=(64, 64),
        critic_hidden=(64, 64),
        num_critic_steps=150,
        num_pg_steps=50,
        td3_batch_size=128,
        buffer_size=100_000,
        cvt_samples=20_000,
        accuracy_episodes=5,
        reassess_episodes=3,
        ant_omni_box=11.5,
        ant_omni_goals=25,
        halfcheetah_uni_goals=16,
    ),
    "paper": ReproducibilityConfig(
        num_seeds=5,
        num_iterations=1000,
        env_batch=1000,
        num_episodes=10,
        num_cells=1024,
        chunk_size=20,
    ),
}
