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
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import traverse_util

from qdnb.envs import env_names, make_env
from qdnb.envs.base import Env
from qdnb.envs.rollout import Evaluation, evaluate_policies
from qdnb.loops import map_concurrently
from qdnb.provenance import load_arrays, save_arrays
from qdnb.qd.algorithms import (MapElites, MapElitesLowSpread, MapElitesSampling, PGAMapElites,
                                PGAMapElitesLowSpread, run_seeds)
from qdnb.qd.cvt import cvt_centroids
from qdnb.qd.low_spread import accuracy, reassess
from qdnb.qd.metrics import qd_metrics
from qdnb.qd.repertoire import Repertoire
from qdnb.rl.networks import MLP
from qdnb.rl.td3 import TD3Config
from qdnb.scale import ReproducibilityConfig

METHODS = ("ME", "ME-LS", "PGA-ME", "PGA-ME-LS", "ME-Sampling")
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
COVERAGE_TARGET = 0.8


def reach_bound(descriptors: np.ndarray, quantile: float = REACH_QUANTILE, step: float = REACH_STEP) -> float:
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


def build_algorithms(cfg: ReproducibilityConfig, env: Env, network: MLP, centroids: jax.Array,
                     offset: float) -> dict[str, MapElites]:
    """The five methods with the hyper-parameters of Tables 4.1 and 4.2."""
    multi = cfg.env_batch // cfg.num_episodes
    common = dict(env=env, network=network, iso_sigma=cfg.iso_sigma, line_sigma=cfg.line_sigma,
                  centroids=centroids, fitness_offset=offset)
    td3 = TD3Config(gamma=cfg.discount, policy_noise=cfg.policy_noise, noise_clip=cfg.noise_clip,
                    critic_lr=cfg.critic_lr, actor_lr=cfg.policy_lr, batch_size=cfg.td3_batch_size,
                    critic_hidden=cfg.critic_hidden)
    pga = dict(td3_config=td3, num_critic_steps=cfg.num_critic_steps, num_pg_steps=cfg.num_pg_steps,
               pg_proportion=cfg.pg_proportion, buffer_size=cfg.buffer_size)
    return {
        "ME": MapElites(**common, batch_size=cfg.env_batch),
        "ME-LS": MapElitesLowSpread(**common, batch_size=multi, num_episodes=cfg.num_episodes),
        "PGA-ME": PGAMapElites(**common, **pga, batch_size=cfg.env_batch),
        "PGA-ME-LS": PGAMapElitesLowSpread(**common, **pga, batch_size=multi, num_episodes=cfg.num_episodes),
        "ME-Sampling": MapElitesSampling(**common, batch_size=multi, num_episodes=cfg.num_episodes),
    }


def representative_cells(repertoire: Repertoire, env_name: str,
                         quantiles: tuple[float, ...] = REPRESENTATIVE_QUANTILES) -> np.ndarray:
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


def stack(trees: list[Any]) -> Any:
    return jax.tree.map(lambda *xs: jnp.stack(xs), *trees)


class Player:
    """Plays (policy, initial-state key) pairs in fixed-size chunks through one
    compiled simulation, whatever the number of episodes asked for: the tests of
    every repertoire then cost one compilation per environment.  Each episode's
    state-descriptor path comes back as its ``trajectory``; with ``record``, its
    ``obs``, ``action`` and ``valid`` steps instead (the QDT's datasets)."""

    def __init__(self, env: Env, network: MLP, chunk: int, record: bool = False):
        self.chunk = chunk
        kept = ("obs", "action", "valid") if record else "next_state_descriptor"

        def play(genotypes, keys):
            def one(g, k):
                ev = evaluate_policies(env, network.apply, jax.tree.map(lambda x: x[None], g), k, True)
                path = jax.tree.map(lambda x: x[0], {n: ev.trajectory[n] for n in kept} if record
                                    else ev.trajectory[kept])
                return ev.fitness[0], ev.descriptor[0], path
            return jax.vmap(one)(genotypes, keys)

        self._play = jax.jit(play)

    def play(self, genotypes: Any, keys: jax.Array) -> Evaluation:
        n = keys.shape[0]
        pad = (-n) % self.chunk
        padded = jax.tree.map(lambda x: jnp.concatenate([x, jnp.repeat(x[:1], pad, axis=0)]), (genotypes, keys))
        outs = [self._play(*jax.tree.map(lambda x: x[i:i + self.chunk], padded)) for i in range(0, n + pad, self.chunk)]
        fitness, descriptor, path = (jax.tree.map(lambda *xs: jnp.concatenate(xs)[:n], *parts)
                                     for parts in zip(*outs))
        length = jnp.sum(path["valid"], axis=1) if isinstance(path, dict) else jnp.full((n,), path.shape[1])
        return Evaluation(fitness=fitness, descriptor=descriptor, length=length, trajectory=path)

    def episodes(self, num_episodes: int, only: jax.Array | None = None):
        """``evaluate_fn(genotypes, key)``: each of the ``G`` policies over
        ``num_episodes`` episodes from different initial states; leaves ``(G, E, ...)``.
        With a boolean mask ``only``, the other policies are not played (zeros)."""

        def evaluate_fn(genotypes: Any, key: jax.Array) -> Evaluation:
            g = jax.tree.leaves(genotypes)[0].shape[0]
            rows = np.arange(g) if only is None else np.flatnonzero(np.asarray(only))
            repeated = jax.tree.map(lambda x: jnp.repeat(x[rows], num_episodes, axis=0), genotypes)
            ev = self.play(repeated, jax.random.split(key, rows.size * num_episodes))
            full = lambda x: jnp.zeros((g, num_episodes) + x.shape[1:], x.dtype).at[rows].set(
                x.reshape((rows.size, num_episodes) + x.shape[1:]))
            return jax.tree.map(full, ev)

        return evaluate_fn


def run_environment(cfg: ReproducibilityConfig, env_name: str, key: jax.Array, progress: bool = True,
                    methods: tuple[str, ...] = METHODS) -> dict[str, Any]:
    """Every method on ``env_name`` for ``cfg.num_seeds`` seeds, and the tests of
    their final repertoires.  Returns a dict of numpy arrays (see the keys below)."""
    unknown = set(methods) - set(METHODS)
    if unknown:
        raise ValueError(f"unknown methods {sorted(unknown)}; valid: {', '.join(METHODS)}")
    env = cfg.make_env(env_name)
    network = MLP(cfg.policy_hidden + (env.action_size,))
    k_cvt, k_goals, k_run, k_acc, k_re, k_rep = jax.random.split(key, 6)
    low, high = env.descriptor_low, env.descriptor_high
    centroids = cvt_centroids(k_cvt, cfg.num_cells, low, high, cfg.cvt_samples, cfg.cvt_iterations)
    goals = cvt_centroids(k_goals, cfg.goals(env_name), low, high, cfg.cvt_samples, cfg.cvt_iterations)
    offset = fitness_offset(env_name, cfg.episode_length)
    algorithms = build_algorithms(cfg, env, network, centroids, offset)

    player = Player(env, network, chunk=cfg.env_batch)  # one compiled simulation for all the tests
    per_seed = lambda f, elites, k: stack([f(jax.tree.map(lambda x: x[i], elites), k_i)
                                           for i, k_i in enumerate(jax.random.split(k, cfg.num_seeds))])
    accuracy_fn = lambda rep, k: accuracy(rep, goals, player.episodes(cfg.accuracy_episodes), k)
    reassess_fn = lambda rep, k: reassess(rep, player.episodes(cfg.reassess_episodes, only=rep.filled), k)
    metrics_fn = jax.vmap(lambda rep: qd_metrics(rep, offset))

    seeds = jax.random.split(k_run, cfg.num_seeds)
    out: dict[str, Any] = {"env_name": env_name, "env": env, "centroids": np.asarray(centroids), "goals": np.asarray(goals),
                           "fitness_offset": offset, "methods": {}}
    for name in methods:
        algorithm = algorithms[name]
        start = time.time()
        states, _, history = run_seeds(algorithm, seeds, cfg.num_iterations, cfg.chunk_size, progress=progress,
                                       desc=f"{env_name} {name}", keep_evaluations=False)
        jax.block_until_ready(states)
        run_seconds = time.time() - start
        elites = algorithm.elites(states.repertoire)
        acc = per_seed(accuracy_fn, elites, k_acc)
        reassessed, scores = per_seed(reassess_fn, elites, k_re)
        seed0 = jax.tree.map(lambda x: x[0], elites)
        cells = representative_cells(seed0, env_name)
        played = player.episodes(cfg.representative_episodes)(jax.tree.map(lambda x: x[cells], seed0.genotypes),
                                                                k_rep)
        result = {
            "history": jax.device_get({k: history[k] for k in ("coverage", "max_fitness", "qd_score")}),
            "repertoire": jax.device_get(elites),
            "spread_at_insertion": (np.asarray(states.repertoire.spreads) if name in LOW_SPREAD
                                    else np.full(np.shape(elites.fitnesses), np.nan)),
            "accuracy": jax.device_get(acc),
            "reassessed": jax.device_get(reassessed),
            "reassessed_spread": np.where(np.asarray(elites.filled), np.asarray(scores.spread), np.nan),
            "metrics": jax.device_get(metrics_fn(elites)),
            "metrics_reassessed": jax.device_get(metrics_fn(reassessed)),
            "representatives": {
                "cells": cells,
                "stored_descriptor": np.asarray(seed0.descriptors)[cells],
                "descriptor": np.asarray(played.descriptor),  # (3, episodes, d)
                "state_descriptor": np.asarray(played.trajectory),  # (3, episodes, T, d)
            },
            "env_steps": int((cfg.num_iterations + 1) * cfg.env_batch * cfg.episode_length),
            "run_seconds": run_seconds,
            "seconds": time.time() - start,
        }
        out["methods"][name] = result
    return out


def run_environments(cfg: ReproducibilityConfig, key: jax.Array, progress: bool = True,
                     concurrent: bool = True) -> dict[str, dict[str, Any]]:
    """``run_environment`` for each of ``cfg.environments``, each with its own
    key (``fold_in`` of the environment's index), in concurrent threads unless
    ``concurrent`` is false.  The numbers do not depend on the concurrency."""
    unknown = set(cfg.environments) - set(env_names())
    if unknown:  # before any thread starts computing
        raise ValueError(f"unknown environments {sorted(unknown)}; valid: {', '.join(env_names())}")
    keys = {name: jax.random.fold_in(key, i) for i, name in enumerate(cfg.environments)}
    return map_concurrently(lambda name: run_environment(cfg, name, keys[name], progress), cfg.environments,
                            concurrent)


# ----- saving repertoires for the QDT chapter (pickle-free .npz) -----

def save_repertoires(path: Path, config_hash: str, repertoire: Repertoire, spread: np.ndarray,
                     reassessed_spread: np.ndarray) -> Path:
    """Save a ``(seeds, cells, ...)`` stack of repertoires: centroids, fitnesses,
    descriptors, spreads and every parameter leaf (``genotype/<path>``)."""
    flat = traverse_util.flatten_dict(jax.device_get(repertoire.genotypes), sep="/")
    return save_arrays(path, config_hash, centroids=repertoire.centroids[0], fitnesses=repertoire.fitnesses,
                       descriptors=repertoire.descriptors, spread=spread, reassessed_spread=reassessed_spread,
                       **{f"genotype/{k}": v for k, v in flat.items()})


def load_repertoires(path: Path, config_hash: str) -> dict[str, Any] | None:
    """The arrays written by ``save_repertoires`` with the genotypes as a nested
    parameter dict, or ``None`` when missing or computed under another config."""
    arrays = load_arrays(path, config_hash)
    if arrays is None:
        return None
    genotype = {k[len("genotype/"):]: v for k, v in arrays.items() if k.startswith("genotype/")}
    out = {k: v for k, v in arrays.items() if not k.startswith("genotype/")}
    out["genotypes"] = traverse_util.unflatten_dict(genotype, sep="/")
    return out
