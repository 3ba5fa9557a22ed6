"""Searching a space of neural-network policies: the algorithms of the book.

Chapters 1-2, under one budget and one variation operator, differing only in
what they select and keep:

- ``GeneticAlgorithm``: a fitness-driven (mu + lambda) evolutionary algorithm
  (Section 2.2.1): keep the ``population_size`` fittest of parents and offspring;
- ``NoveltySearch``: the same loop where the novelty of Eq. 2.5 replaces the
  fitness (Lehman and Stanley, 2011a), with a novelty archive;
- ``PolicyMapElites``: Algorithm 1 (``qdnb.qd.map_elites.MapElites``) over
  policies, uniform selection from a repertoire whose cells each keep their best.

Chapter 4, on MAP-Elites' selection and iso+line variation:

- ``MapElitesSampling`` and ``MapElitesLowSpread`` (Algorithm 6): several
  episodes per candidate, with their own insertion rules (PGA-ME and its
  Low-Spread variant are in ``qdnb.qd.pga``, QD-PG in ``qdnb.qd.qdpg``).

Each has ``init(key) -> (state, evaluation)`` and ``step(state) -> (state,
evaluation)``, pure functions ready for ``jit``, ``vmap`` over seeds and
``lax.scan``.  The MAP-Elites family (and the evolution strategies of
``qdnb.qd.es``) also has ``start(key) -> state``: an empty
archive and the random first batch waiting in the state, so that its first
``step`` is the initial evaluation and the whole run (``run_seeds``) is one
compiled program: each step evaluates the waiting batch, inserts it, updates
(PGA: replay buffer and critic, in QDax's order) and emits the next batch.
"""

from __future__ import annotations

import math
import sys
from dataclasses import dataclass
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from qdnb.core import dryrun, health
from qdnb.core.evaluation import Evaluation
from qdnb.core.loops import scan_in_chunks
from qdnb.core.sharding import over_seeds, seed_slots
from qdnb.core.tree import concat, take
from qdnb.envs.base import Env
from qdnb.envs.rollout import evaluate_episodes, evaluate_policies
from qdnb.nets.mlp import MLP, init_policies
from qdnb.qd import repertoire as rep_lib
from qdnb.qd.low_spread import (
    LowSpreadRepertoire,
    geometric_median,
    insert_low_spread,
    low_spread_scores,
)
from qdnb.qd.map_elites import MapElites
from qdnb.qd.metrics import ExplorationTrack
from qdnb.qd.novelty import NoveltyArchive, knn_novelty
from qdnb.qd.variation import isoline_variation


@dataclass(frozen=True, eq=False)
class PolicySearch:
    """What the three algorithms share: the task, the policy network, the batch
    of offspring evaluated per iteration and the iso+line variation."""

    env: Env
    network: MLP
    batch_size: int
    iso_sigma: float
    line_sigma: float

    # over several devices, when they do not divide the seeds: split each population
    split = "population"

    def evaluate(self, params: Any, key: jax.Array, return_trajectory: bool = False) -> Evaluation:
        return evaluate_policies(self.env, self.network.apply, params, key, return_trajectory)

    def random_policies(self, key: jax.Array) -> Any:
        return init_policies(self.network, key, self.batch_size, self.env.observation_size)

    def vary(self, parents: Any, key: jax.Array) -> Any:
        """Offspring of ``batch_size`` pairs of parents drawn uniformly from ``parents``."""
        k1, k2, k3 = jax.random.split(key, 3)
        n = jax.tree.leaves(parents)[0].shape[0]
        x1 = take(parents, jax.random.randint(k1, (self.batch_size,), 0, n))
        x2 = take(parents, jax.random.randint(k2, (self.batch_size,), 0, n))
        return isoline_variation(x1, x2, k3, self.iso_sigma, self.line_sigma)


@struct.dataclass
class PopulationState:
    population: Any
    fitnesses: jax.Array
    descriptors: jax.Array
    key: jax.Array
    archive: NoveltyArchive | None = None


@dataclass(frozen=True, eq=False)
class GeneticAlgorithm(PolicySearch):
    """Fitness-only (mu + lambda) GA: the baseline that the deceptive maze traps."""

    population_size: int = 100

    def init(self, key: jax.Array) -> tuple[PopulationState, Evaluation]:
        k_init, k_eval, key = jax.random.split(key, 3)
        params = self.random_policies(k_init)
        ev = self.evaluate(params, k_eval)
        keep = jax.lax.top_k(ev.fitness, self.population_size)[1]
        return PopulationState(take(params, keep), ev.fitness[keep], ev.descriptor[keep], key), ev

    def step(self, state: PopulationState) -> tuple[PopulationState, Evaluation]:
        key, k_vary, k_eval = jax.random.split(state.key, 3)
        offspring = self.vary(state.population, k_vary)
        ev = self.evaluate(offspring, k_eval)
        pool = concat(state.population, offspring)
        fit = jnp.concatenate([state.fitnesses, ev.fitness])
        desc = jnp.concatenate([state.descriptors, ev.descriptor])
        keep = jax.lax.top_k(fit, self.population_size)[1]
        return PopulationState(take(pool, keep), fit[keep], desc[keep], key), ev

    def metrics(self, state: PopulationState) -> dict[str, jax.Array]:
        return {"max_fitness": jnp.max(state.fitnesses)}


@dataclass(frozen=True, eq=False)
class NoveltySearch(PolicySearch):
    """Novelty Search: keep the ``population_size`` most novel of parents and
    offspring, novelty (Eq. 2.5) measured against the archive and the pool; the
    offspring whose novelty exceeds ``archive_threshold`` join the archive."""

    population_size: int = 100
    k: int = 15
    archive_size: int = 5000
    archive_threshold: float = 0.01

    def _most_novel(self, pool, fit, desc, archive, key):
        reference = jnp.concatenate([desc, archive.data])
        valid = jnp.concatenate([jnp.ones(desc.shape[0], bool), archive.valid])
        novelty = knn_novelty(desc, reference, self.k, valid, exclude_self=True)
        keep = jax.lax.top_k(novelty, self.population_size)[1]
        return PopulationState(take(pool, keep), fit[keep], desc[keep], key, archive)

    def init(self, key: jax.Array) -> tuple[PopulationState, Evaluation]:
        k_init, k_eval, key = jax.random.split(key, 3)
        params = self.random_policies(k_init)
        ev = self.evaluate(params, k_eval)
        archive = NoveltyArchive.create(self.archive_size, self.env.descriptor_size)
        archive = archive.add(ev.descriptor, self.archive_threshold, self.k)
        return self._most_novel(params, ev.fitness, ev.descriptor, archive, key), ev

    def step(self, state: PopulationState) -> tuple[PopulationState, Evaluation]:
        key, k_vary, k_eval = jax.random.split(state.key, 3)
        offspring = self.vary(state.population, k_vary)
        ev = self.evaluate(offspring, k_eval)
        archive = state.archive.add(ev.descriptor, self.archive_threshold, self.k)
        pool = concat(state.population, offspring)
        fit = jnp.concatenate([state.fitnesses, ev.fitness])
        desc = jnp.concatenate([state.descriptors, ev.descriptor])
        return self._most_novel(pool, fit, desc, archive, key), ev

    def metrics(self, state: PopulationState) -> dict[str, jax.Array]:
        return {"max_fitness": jnp.max(state.fitnesses), "archive_size": state.archive.size}


@dataclass(frozen=True, eq=False)
class PolicyMapElites(PolicySearch, MapElites):
    """MAP-Elites over policies: the generic ``qdnb.qd.map_elites.MapElites`` whose
    genotypes are network parameters, scored by episodes in ``env`` and varied by
    iso+line.  ``collect_transitions`` keeps the episodes' per-step transitions
    (for a replay buffer)."""

    collect_transitions: bool = False

    def score(self, genotypes: Any, key: jax.Array) -> Evaluation:
        return self.evaluate(genotypes, key, self.collect_transitions)

    def random_genotypes(self, key: jax.Array) -> Any:
        return self.random_policies(key)


@dataclass(frozen=True, eq=False)
class MapElitesSampling(PolicyMapElites):
    """ME-Sampling (Section 4.2): each candidate plays ``num_episodes`` episodes;
    mean fitness, geometric-median descriptor, fitness-only insertion."""

    num_episodes: int = 10

    def evaluate_and_insert(self, archive, genotypes, key):
        ev = evaluate_episodes(
            self.env,
            self.network.apply,
            genotypes,
            key,
            self.num_episodes,
            self.collect_transitions,
        )
        descriptors = jax.vmap(geometric_median)(ev.descriptor)
        archive, _ = rep_lib.insert(archive, genotypes, jnp.mean(ev.fitness, axis=1), descriptors)
        return archive, ev


@dataclass(frozen=True, eq=False)
class MapElitesLowSpread(PolicyMapElites):
    """MAP-Elites Low-Spread (Algorithm 6): ``num_episodes`` episodes per
    candidate, filed under its most frequent cell, inserted when that cell is
    empty or when it beats the incumbent in fitness *and* spread (Eq. 4.1)."""

    num_episodes: int = 10

    def empty_archive(self, params):
        return LowSpreadRepertoire.create(super().empty_archive(params))

    def elites(self, archive):
        return archive.repertoire

    def evaluate_and_insert(self, archive, genotypes, key):
        ev = evaluate_episodes(
            self.env,
            self.network.apply,
            genotypes,
            key,
            self.num_episodes,
            self.collect_transitions,
        )
        scores = low_spread_scores(self.centroids, ev.fitness, ev.descriptor)
        archive, _ = insert_low_spread(archive, genotypes, scores)
        return archive, ev

    def metrics(self, state):
        filled = state.repertoire.repertoire.filled
        mean_spread = jnp.sum(jnp.where(filled, state.repertoire.spreads, 0.0)) / jnp.maximum(
            jnp.sum(filled), 1
        )
        return {**super().metrics(state), "mean_spread": mean_spread}


def run_seeds(
    algorithm: PolicySearch,
    keys: jax.Array,
    num_iterations: int,
    chunk_size: int,
    track_bins: tuple[int, ...] | None = None,
    target: tuple[float, ...] | None = None,
    progress: bool = True,
    desc: str | None = None,
    keep_evaluations: bool = True,
    chunk_seconds: list[float] | None = None,
    on_chunk: Callable[[int], None] | None = None,
    stop: Callable[[dict[str, Any]], bool] | None = None,
):
    """Run one algorithm for several seeds at once (``vmap`` over ``keys``).

    Over several devices (``qdnb.core.sharding``) the seeds are split when the devices
    divide them evenly; otherwise each seed's population is split, or, for an algorithm
    whose ``split`` is ``"seeds"``, the seeds are padded up to a multiple of the devices
    and split (the extra seeds' results are dropped, and ``stop`` never sees them).

    Besides the algorithm's own metrics, when ``track_bins`` is given every
    evaluated descriptor is tracked on a fixed regular grid of ``track_bins``
    cells over the environment's descriptor bounds (see ``ExplorationTrack``),
    with the smallest distance to ``target``; ``keep_evaluations`` keeps the
    descriptors and fitnesses of every evaluated solution (``chunk_seconds``,
    ``on_chunk``, ``stop`` and checkpoints under ``desc``: see ``scan_in_chunks``; ``stop``
    sees each chunk's history entries shaped ``(iterations, num_seeds, ...)``, and a loop
    it stops returns a shorter history).  ``env_steps`` counts
    the environment steps taken in each iteration.  Returns the final
    states, the tracks (``None`` without ``track_bins``) and a history dict whose
    arrays have shape ``(num_seeds, num_iterations + 1, ...)``; entry 0 is the
    initial batch.
    """
    drive = dryrun.driver()  # every seed's every step, or a dry run's cut: qdnb.core.dryrun
    run = lambda keys: _run_seeds(
        algorithm, keys, drive, num_iterations=num_iterations, chunk_size=chunk_size,
        track_bins=track_bins, target=target, progress=progress, desc=desc,
        keep_evaluations=keep_evaluations, chunk_seconds=chunk_seconds,
        on_chunk=on_chunk, stop=stop,
    )  # fmt: skip
    return drive.seeds(desc or "loop", keys, run, _one_seed_for_all)


def _run_seeds(
    algorithm: PolicySearch,
    keys: jax.Array,
    drive: dryrun.FullRun,
    num_iterations: int,
    chunk_size: int,
    track_bins: tuple[int, ...] | None,
    target: tuple[float, ...] | None,
    progress: bool,
    desc: str | None,
    keep_evaluations: bool,
    chunk_seconds: list[float] | None,
    on_chunk: Callable[[int], None] | None,
    stop: Callable[[dict[str, Any]], bool] | None,
):
    """``run_seeds``'s run of ``keys`` side by side, its one-shot programs under ``drive``."""
    env = algorithm.env
    low, high = env.descriptor_low, env.descriptor_high
    names: list[str] = []  # the state's parts (qdnb.core.health), seen when tracing

    def record(state, track, ev):
        names[:] = health.part_names(state)
        out = dict(
            algorithm.metrics(state),
            env_steps=jnp.sum(ev.length),
            nan_parts=health.nan_parts(state),
        )
        if track_bins is not None:
            track = track.update(ev.descriptor, track_bins, low, high, target)
            out.update(coverage=track.coverage, min_distance=track.min_distance)
        if keep_evaluations:
            out.update(descriptors=ev.descriptor, fitnesses=ev.fitness)
        return track, out

    def step(carry):
        state, track = carry
        state, ev = algorithm.step(state)
        track, out = record(state, track, ev)
        return (state, track), out

    new_track = lambda: (
        None if track_bins is None else ExplorationTrack.create(math.prod(track_bins))
    )
    # the seeds over the devices when they divide evenly, else each seed's population (or,
    # for an algorithm that prefers it, seeds padded up to a multiple of the devices)
    num_seeds, prefers = len(keys), getattr(algorithm, "split", "seeds")
    stop = stopped_by_nan(stop, num_seeds, names, desc)
    slots = seed_slots(num_seeds, prefers)
    if slots > num_seeds:  # extra seeds, whose results are dropped
        extra = jax.random.split(jax.random.fold_in(keys[0], 0x5EED), slots - num_seeds)
        keys = jnp.concatenate([keys, extra])
        if stop is not None:
            given_stop = stop
            stop = lambda out: given_stop(jax.tree.map(lambda x: x[:, :num_seeds], out))
    split = lambda fn: over_seeds(jax.vmap(fn), slots, prefers)
    mine = lambda tree: tree if slots == num_seeds else jax.tree.map(lambda x: x[:num_seeds], tree)
    if getattr(algorithm, "start", None) is not None:
        # the initial evaluation is the first step: one compiled program for the whole loop
        start = jax.jit(split(lambda k: (algorithm.start(k), new_track())))
        carry = drive.call(f"{desc or 'loop'}: start", start, keys)
        (states, tracks), history = scan_in_chunks(
            split(step),
            carry,
            num_iterations + 1,
            chunk_size,
            desc=desc,
            progress=progress,
            chunk_seconds=chunk_seconds,
            on_chunk=on_chunk,
            stop=stop,
        )
        history = jax.tree.map(lambda h: jnp.swapaxes(h, 0, 1), history)
        return mine(states), mine(tracks), mine(history)

    def init(key):
        state, ev = algorithm.init(key)
        track, out = record(state, new_track(), ev)
        return (state, track), out

    # (a dry run times it: compiled and run once, as in the full run)
    carry, first = drive.call(f"{desc or 'loop'}: initial batch", jax.jit(split(init)), keys)
    if stop is not None and stop(jax.tree.map(lambda f: f[None], first)):
        stop = lambda _: True  # the initial batch already met it: stop after one chunk
    (states, tracks), history = scan_in_chunks(
        split(step),
        carry,
        num_iterations,
        chunk_size,
        desc=desc,
        progress=progress,
        chunk_seconds=chunk_seconds,
        on_chunk=on_chunk,
        stop=stop,
    )
    history = jax.tree.map(
        lambda f, h: jnp.concatenate([f[:, None], jnp.swapaxes(h, 0, 1)], axis=1), first, history
    )
    return mine(states), mine(tracks), mine(history)


def stopped_by_nan(
    stop: Callable[[dict[str, Any]], bool] | None,
    num_seeds: int,
    names: list[str],
    desc: str | None,
) -> Callable[[dict[str, Any]], bool]:
    """``run_seeds``'s stop rule: ``stop``'s, or once every seed has diverged (a NaN in
    its state, ``qdnb.core.health``); each seed that diverges is told on the terminal
    as it does, with its iteration and the parts that hold the NaN."""
    seen = np.zeros(num_seeds, bool)
    done = [0]  # history entries seen so far (entry 0: the initial batch)

    def rule(out: dict[str, Any]) -> bool:  # entries: iterations x seeds x ...
        flags = np.asarray(out["nan_parts"])[:, :num_seeds]
        for i, seed in zip(*np.nonzero(flags.any(axis=2))):
            if not seen[seed]:
                seen[seed] = True
                parts = ", ".join(n for n, b in zip(names, flags[i, seed]) if b)
                print(
                    f"diverged: {desc or 'loop'}: seed {seed} went NaN at iteration "
                    f"{done[0] + i} ({parts}); it is reported as diverged",
                    file=sys.stderr,
                    flush=True,
                )
        done[0] += flags.shape[0]
        given = stop(out) if stop is not None else False  # called every chunk: it keeps state
        return bool(given or seen.all())

    return rule


def _one_seed_for_all(out: Any, num_seeds: int) -> Any:
    """A dry run's one seed standing for ``num_seeds`` (``qdnb.core.dryrun.DryRun.seeds``):
    ``run_seeds``'s results with every seed's slot holding the one seed's.
    """
    states, tracks, history = out
    # every seed's slot holds the one seed's results: the final states as read-only views
    # of it (at paper scale five copies of Chapter 4's states outgrow a 24 GB host), the
    # history as copies (small, and some pages write into it)
    view = lambda x: np.broadcast_to(np.asarray(x), (num_seeds,) + x.shape[1:])
    copies = lambda x: jnp.repeat(x, num_seeds, axis=0)
    return jax.tree.map(view, states), jax.tree.map(view, tracks), jax.tree.map(copies, history)
