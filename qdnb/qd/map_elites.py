"""MAP-Elites (Algorithm 1) over any genotype: a grid of cells, each keeping the
best solution whose descriptor falls in it; uniform selection from the filled
cells, a variation operator, a scoring function.

``MapElites`` knows nothing of policies or environments.  It takes three
functions, as QDax's ``MAPElites`` does:

- ``scoring_fn(genotypes, key) -> Evaluation``: fitness and descriptor of a batch
  (``Evaluation.extra`` carries anything else the caller wants logged);
- ``init_fn(key, n) -> genotypes``: the random first batch;
- ``variation_fn(parents, key) -> offspring``: one offspring per parent drawn.

Policy search (``qdnb.qd.algorithms.PolicyMapElites``) is an adapter that
supplies them from an environment and a network; Chapter 5's surprise search
supplies a Flow Lenia simulation and the FLT's error.  Variants change how a
batch is scored and inserted (``evaluate_and_insert``) and what the archive holds
(``empty_archive``, ``elites``).

``start(key)`` is an empty archive with the random batch waiting in the state,
so the first ``step`` is the initial evaluation and a whole run is one compiled
loop of ``step``: evaluate the waiting batch, insert it, emit the next.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable

import jax
from flax import struct

from qdnb.core.evaluation import Evaluation
from qdnb.core.tree import take
from qdnb.qd import repertoire as rep_lib
from qdnb.qd.metrics import qd_metrics


@struct.dataclass
class MapElitesState:
    repertoire: Any  # a Repertoire, or a LowSpreadRepertoire for ME-LS
    key: jax.Array
    offspring: Any = None  # the batch the next step evaluates


@dataclass(frozen=True, eq=False, kw_only=True)
class MapElites:
    """Algorithm 1 with batched selection, variation and insertion."""

    centroids: jax.Array
    batch_size: int
    scoring_fn: Callable[[Any, jax.Array], Evaluation] | None = None
    init_fn: Callable[[jax.Array, int], Any] | None = None
    variation_fn: Callable[[Any, jax.Array], Any] | None = None
    fitness_offset: float = 0.0  # added to fitnesses for the QD score (Eq. 2.3)

    def score(self, genotypes: Any, key: jax.Array) -> Evaluation:
        return self.scoring_fn(genotypes, key)

    def random_genotypes(self, key: jax.Array) -> Any:
        return self.init_fn(key, self.batch_size)

    def vary(self, parents: Any, key: jax.Array) -> Any:
        return self.variation_fn(parents, key)

    def empty_archive(self, genotypes: Any) -> Any:
        return rep_lib.init_repertoire(self.centroids, take(genotypes, 0))

    def elites(self, archive: Any) -> rep_lib.Repertoire:
        return archive

    def evaluate_and_insert(
        self, archive: Any, genotypes: Any, key: jax.Array
    ) -> tuple[Any, Evaluation]:
        """Score the batch, insert by fitness alone (a cell keeps its best)."""
        ev = self.score(genotypes, key)
        archive, _ = rep_lib.insert(archive, genotypes, ev.fitness, ev.descriptor)
        return archive, ev

    def start(self, key: jax.Array) -> MapElitesState:
        """An empty archive and ``batch_size`` random genotypes waiting to be scored."""
        k_init, key = jax.random.split(key)
        genotypes = self.random_genotypes(k_init)
        return MapElitesState(self.empty_archive(genotypes), key, genotypes)

    def init(self, key: jax.Array) -> tuple[MapElitesState, Evaluation]:
        """The state after the initial batch: ``step(start(key))``."""
        return self.step(self.start(key))

    def emit(self, state: MapElitesState, key: jax.Array) -> Any:
        """The next batch: offspring of parents drawn uniformly from the elites."""
        k_sel, k_vary = jax.random.split(key)
        return self.vary(
            rep_lib.sample(self.elites(state.repertoire), k_sel, self.batch_size), k_vary
        )

    def step(self, state: MapElitesState) -> tuple[MapElitesState, Evaluation]:
        key, k_eval, k_emit = jax.random.split(state.key, 3)
        archive, ev = self.evaluate_and_insert(state.repertoire, state.offspring, k_eval)
        state = state.replace(repertoire=archive, key=key)
        return state.replace(offspring=self.emit(state, k_emit)), ev

    def metrics(self, state: MapElitesState) -> dict[str, jax.Array]:
        return qd_metrics(self.elites(state.repertoire), self.fitness_offset)
