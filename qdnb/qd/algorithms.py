"""Searching a space of neural-network policies: the algorithms of the book.

Chapters 1-2, under one budget and one variation operator, differing only in
what they select and keep:

- ``GeneticAlgorithm``: a fitness-driven (mu + lambda) evolutionary algorithm
  (Section 2.2.1): keep the ``population_size`` fittest of parents and offspring;
- ``NoveltySearch``: the same loop where the novelty of Eq. 2.5 replaces the
  fitness (Lehman and Stanley, 2011a), with a novelty archive;
- ``MapElites``: Algorithm 1, uniform selection from a repertoire whose cells each
  keep their best solution.

Chapter 4, on MapElites' selection and iso+line variation:

- ``MapElitesSampling`` and ``MapElitesLowSpread`` (Algorithm 6): several
  episodes per candidate, with their own insertion rules;
- ``PGAMapElites`` (Algorithm 5) and ``PGAMapElitesLowSpread`` (Algorithm 7):
  half the offspring from TD3 policy-gradient steps on a shared critic.

Each has ``init(key) -> (state, evaluation)`` and ``step(state) -> (state,
evaluation)``, pure functions ready for ``jit``, ``vmap`` over seeds and
``lax.scan``.  The MAP-Elites family also has ``start(key) -> state``: an empty
archive and the random first batch waiting in the state, so that its first
``step`` is the initial evaluation and the whole run (``run_seeds``) is one
compiled program: each step evaluates the waiting batch, inserts it, updates
(PGA: replay buffer and critic, in QDax's order) and emits the next batch.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import jax
import jax.numpy as jnp
from flax import struct

from qdnb.envs.base import Env
from qdnb.envs.rollout import Evaluation, evaluate_episodes, evaluate_policies
from qdnb.qd import repertoire as rep_lib
from qdnb.qd.low_spread import LowSpreadRepertoire, geometric_median, insert_low_spread, low_spread_scores
from qdnb.qd.metrics import qd_metrics
from qdnb.qd.novelty import NoveltyArchive, knn_novelty
from qdnb.qd.variation import isoline_variation
from qdnb.rl.buffer import ReplayBuffer
from qdnb.rl.networks import MLP, init_policies
from qdnb.rl.td3 import TD3, TD3Config, TD3State

take = lambda tree, idx: jax.tree.map(lambda x: x[idx], tree)
concat = lambda a, b: jax.tree.map(lambda x, y: jnp.concatenate([x, y]), a, b)


@dataclass(frozen=True, eq=False)
class PolicySearch:
    """What the three algorithms share: the task, the policy network, the batch
    of offspring evaluated per iteration and the iso+line variation."""

    env: Env
    network: MLP
    batch_size: int
    iso_sigma: float
    line_sigma: float

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


@struct.dataclass
class MapElitesState:
    repertoire: Any  # a Repertoire, or a LowSpreadRepertoire for ME-LS
    key: jax.Array
    offspring: Any = None  # the batch the next step evaluates


@dataclass(frozen=True, eq=False)
class MapElites(PolicySearch):
    """MAP-Elites (Algorithm 1) with batched selection, variation and insertion.

    Variants change how a batch is evaluated and inserted
    (``evaluate_and_insert``) and what the archive holds (``empty_archive``,
    ``elites``); selection and variation stay those of MAP-Elites.
    """

    centroids: jax.Array | None = None
    fitness_offset: float = 0.0
    collect_transitions: bool = False  # keep per-step transitions (for a replay buffer)

    def empty_archive(self, params: Any) -> Any:
        return rep_lib.init_repertoire(self.centroids, take(params, 0))

    def elites(self, archive: Any) -> rep_lib.Repertoire:
        return archive

    def evaluate_and_insert(self, archive: Any, genotypes: Any, key: jax.Array) -> tuple[Any, Evaluation]:
        """One episode per candidate, fitness-only insertion."""
        ev = self.evaluate(genotypes, key, self.collect_transitions)
        archive, _ = rep_lib.insert(archive, genotypes, ev.fitness, ev.descriptor)
        return archive, ev

    def start(self, key: jax.Array) -> MapElitesState:
        """An empty archive and ``batch_size`` random policies waiting to be evaluated."""
        k_init, key = jax.random.split(key)
        params = self.random_policies(k_init)
        return MapElitesState(self.empty_archive(params), key, params)

    def init(self, key: jax.Array) -> tuple[MapElitesState, Evaluation]:
        """The state after the initial batch: ``step(start(key))``."""
        return self.step(self.start(key))

    def emit(self, state: MapElitesState, key: jax.Array) -> Any:
        """The next batch: iso+line offspring of parents drawn uniformly from the elites."""
        k_sel, k_vary = jax.random.split(key)
        return self.vary(rep_lib.sample(self.elites(state.repertoire), k_sel, self.batch_size), k_vary)

    def step(self, state: MapElitesState) -> tuple[MapElitesState, Evaluation]:
        key, k_eval, k_emit = jax.random.split(state.key, 3)
        archive, ev = self.evaluate_and_insert(state.repertoire, state.offspring, k_eval)
        state = state.replace(repertoire=archive, key=key)
        return state.replace(offspring=self.emit(state, k_emit)), ev

    def metrics(self, state: MapElitesState) -> dict[str, jax.Array]:
        return qd_metrics(self.elites(state.repertoire), self.fitness_offset)


@dataclass(frozen=True, eq=False)
class MapElitesSampling(MapElites):
    """ME-Sampling (Section 4.2): each candidate plays ``num_episodes`` episodes;
    mean fitness, geometric-median descriptor, fitness-only insertion."""

    num_episodes: int = 10

    def evaluate_and_insert(self, archive, genotypes, key):
        ev = evaluate_episodes(self.env, self.network.apply, genotypes, key, self.num_episodes,
                               self.collect_transitions)
        descriptors = jax.vmap(geometric_median)(ev.descriptor)
        archive, _ = rep_lib.insert(archive, genotypes, jnp.mean(ev.fitness, axis=1), descriptors)
        return archive, ev


@dataclass(frozen=True, eq=False)
class MapElitesLowSpread(MapElites):
    """MAP-Elites Low-Spread (Algorithm 6): ``num_episodes`` episodes per
    candidate, filed under its most frequent cell, inserted when that cell is
    empty or when it beats the incumbent in fitness *and* spread (Eq. 4.1)."""

    num_episodes: int = 10

    def empty_archive(self, params):
        return LowSpreadRepertoire.create(super().empty_archive(params))

    def elites(self, archive):
        return archive.repertoire

    def evaluate_and_insert(self, archive, genotypes, key):
        ev = evaluate_episodes(self.env, self.network.apply, genotypes, key, self.num_episodes,
                               self.collect_transitions)
        scores = low_spread_scores(self.centroids, ev.fitness, ev.descriptor)
        archive, _ = insert_low_spread(archive, genotypes, scores)
        return archive, ev

    def metrics(self, state):
        filled = state.repertoire.repertoire.filled
        mean_spread = jnp.sum(jnp.where(filled, state.repertoire.spreads, 0.0)) / jnp.maximum(jnp.sum(filled), 1)
        return {**super().metrics(state), "mean_spread": mean_spread}


@struct.dataclass
class PGAState:
    repertoire: Any
    td3: TD3State
    buffer: ReplayBuffer
    key: jax.Array
    offspring: Any = None  # the batch the next step evaluates


@dataclass(frozen=True, eq=False)
class PGAMapElites(MapElites):
    """PGA-MAP-Elites (Algorithm 5; Nilsson and Cully, 2021).

    Each iteration: ``batch_size`` parents are drawn from the repertoire; half
    take ``num_pg_steps`` TD3 actor steps against the shared critic, the others
    iso+line variation, and the greedy TD3 actor completes the batch; the critic
    (with the greedy actor, as TD3) trains for ``num_critic_steps`` steps on the
    replay buffer; every offspring is evaluated, its transitions stored, and
    inserted by the archive's rule.  The greedy actor is offered for insertion
    like any offspring, as in the QDax implementation the thesis ran.
    """

    td3_config: TD3Config = TD3Config()
    num_critic_steps: int = 300
    num_pg_steps: int = 100
    pg_proportion: float = 0.5
    buffer_size: int = 1_000_000
    collect_transitions: bool = True

    @property
    def td3(self) -> TD3:
        return TD3(self.network, self.env.observation_size, self.env.action_size, self.td3_config)

    @property
    def num_pg(self) -> int:
        return int(self.batch_size * self.pg_proportion)

    def start(self, key: jax.Array) -> PGAState:
        k_init, k_td3, key = jax.random.split(key, 3)
        params = self.random_policies(k_init)
        buffer = ReplayBuffer.create(self.buffer_size, self.env.observation_size, self.env.action_size)
        return PGAState(self.empty_archive(params), self.td3.init(k_td3), buffer, key, params)

    def emit(self, state: PGAState, key: jax.Array) -> Any:
        """Half of the batch from ``num_pg_steps`` actor steps against the critic,
        the rest iso+line, and the greedy actor."""
        k_sel, k_pg, k_vary = jax.random.split(key, 3)
        td3 = self.td3
        parents = rep_lib.sample(self.elites(state.repertoire), k_sel, self.batch_size)
        pg_parents = take(parents, jnp.arange(self.num_pg))
        pg_offspring = jax.vmap(
            lambda actor, k: td3.policy_gradient_steps(actor, state.td3.critic, state.buffer, k, self.num_pg_steps)
        )(pg_parents, jax.random.split(k_pg, self.num_pg))
        ga_offspring = take(self.vary(parents, k_vary), jnp.arange(self.batch_size - self.num_pg - 1))
        greedy = jax.tree.map(lambda x: x[None], state.td3.actor)
        return concat(concat(pg_offspring, ga_offspring), greedy)

    def step(self, state: PGAState) -> tuple[PGAState, Evaluation]:
        """Evaluate and insert the waiting batch, store its transitions, train the
        critic on the buffer, then emit the next batch with that critic (QDax's
        order: the initial batch's transitions train the critic before the first
        policy-gradient offspring)."""
        key, k_eval, k_critic, k_emit = jax.random.split(state.key, 4)
        archive, ev = self.evaluate_and_insert(state.repertoire, state.offspring, k_eval)
        buffer = state.buffer.add_episodes(ev.trajectory, ev.fitness.ndim)
        td3_state, _ = self.td3.train_critic(state.td3, buffer, k_critic, self.num_critic_steps)
        state = PGAState(archive, td3_state, buffer, key)
        return state.replace(offspring=self.emit(state, k_emit)), ev


@dataclass(frozen=True, eq=False)
class PGAMapElitesLowSpread(PGAMapElites, MapElitesLowSpread):
    """PGA-MAP-Elites Low-Spread (Algorithm 7): PGA-ME's variation and critic,
    Low-Spread's ``num_episodes`` evaluations and insertion rule; every
    transition of every episode goes to the replay buffer."""


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
):
    """Run one algorithm for several seeds at once (``vmap`` over ``keys``).

    Besides the algorithm's own metrics, when ``track_bins`` is given every
    evaluated descriptor is tracked on a fixed regular grid of ``track_bins``
    cells over the environment's descriptor bounds (see ``ExplorationTrack``),
    with the smallest distance to ``target``; ``keep_evaluations`` keeps the
    descriptors and fitnesses of every evaluated solution (``chunk_seconds``: see
    ``scan_in_chunks``).  ``env_steps`` counts
    the environment steps taken in each iteration.  Returns the final
    states, the tracks (``None`` without ``track_bins``) and a history dict whose
    arrays have shape ``(num_seeds, num_iterations + 1, ...)``; entry 0 is the
    initial batch.
    """
    from qdnb.loops import scan_in_chunks
    from qdnb.qd.metrics import ExplorationTrack

    env = algorithm.env
    low, high = env.descriptor_low, env.descriptor_high

    def record(state, track, ev):
        out = dict(algorithm.metrics(state), env_steps=jnp.sum(ev.length))
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

    new_track = lambda: None if track_bins is None else ExplorationTrack.create(math.prod(track_bins))
    if getattr(algorithm, "start", None) is not None:
        # the initial evaluation is the first step: one compiled program for the whole loop
        carry = jax.jit(jax.vmap(lambda k: (algorithm.start(k), new_track())))(keys)
        (states, tracks), history = scan_in_chunks(
            jax.vmap(step), carry, num_iterations + 1, chunk_size, desc=desc, progress=progress,
            chunk_seconds=chunk_seconds,
        )
        return states, tracks, jax.tree.map(lambda h: jnp.swapaxes(h, 0, 1), history)

    def init(key):
        state, ev = algorithm.init(key)
        track, out = record(state, new_track(), ev)
        return (state, track), out

    carry, first = jax.jit(jax.vmap(init))(keys)
    (states, tracks), history = scan_in_chunks(
        jax.vmap(step), carry, num_iterations, chunk_size, desc=desc, progress=progress,
        chunk_seconds=chunk_seconds,
    )
    history = jax.tree.map(
        lambda f, h: jnp.concatenate([f[:, None], jnp.swapaxes(h, 0, 1)], axis=1), first, history
    )
    return states, tracks, history
