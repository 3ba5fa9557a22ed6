"""MAP-Elites Low-Spread (Algorithm 6) and ME-Sampling (Section 4.2): repertoires
for uncertain domains, where one policy played from several initial states lands
on several behaviour descriptors.

Each candidate is evaluated over ``E`` episodes.  Its *spread* (Eq. 4.1) is the
mean distance between the descriptors of all pairs of its episodes.  Low-Spread
places it in the cell its episodes fall into most often and inserts it when that
cell is empty or when it has a higher mean fitness *and* a lower spread than the
incumbent.  ME-Sampling instead uses the mean fitness, the geometric median of the
descriptors and the usual fitness-only insertion.
"""

from __future__ import annotations

from typing import Any, Callable

import jax
import jax.numpy as jnp
from flax import struct

from qdnb.qd.cvt import nearest
from qdnb.qd.repertoire import Repertoire, batch_winners, init_repertoire, insert, write_cells


def spread(descriptors: jax.Array) -> jax.Array:
    """Eq. 4.1: mean Euclidean distance over all pairs i < j of the ``(E, d)``
    descriptors of one policy's episodes (0 for a single episode)."""
    e = descriptors.shape[0]
    if e < 2:
        return jnp.zeros(())
    diff = descriptors[:, None, :] - descriptors[None, :, :]
    dist = jnp.sqrt(jnp.sum(diff**2, axis=-1))
    upper = jnp.triu(jnp.ones((e, e), bool), k=1)
    return jnp.sum(jnp.where(upper, dist, 0.0)) / (e * (e - 1) / 2)


def mode_cell(cells: jax.Array) -> jax.Array:
    """The most frequent of the ``(E,)`` cells of one policy's episodes; a tie goes
    to the cell reached first (lowest episode index)."""
    counts = jnp.sum(cells[:, None] == cells[None, :], axis=1)
    return cells[jnp.argmax(counts)]


def geometric_median(points: jax.Array, num_iterations: int = 50, eps: float = 1e-8) -> jax.Array:
    """Point minimising the sum of Euclidean distances to ``(E, d)`` points
    (Weiszfeld's iterations from the mean)."""

    def weiszfeld(_, y):
        w = 1.0 / jnp.maximum(jnp.linalg.norm(points - y, axis=-1), eps)
        return jnp.sum(w[:, None] * points, axis=0) / jnp.sum(w)

    return jax.lax.fori_loop(0, num_iterations, weiszfeld, jnp.mean(points, axis=0))


@struct.dataclass
class LowSpreadScores:
    """What Low-Spread insertion needs of a batch of candidates."""

    fitness: jax.Array  # (B,) mean episode return
    cell: jax.Array  # (B,) most frequent cell of the episodes
    descriptor: jax.Array  # (B, d) mean descriptor of the episodes inside that cell
    spread: jax.Array  # (B,) Eq. 4.1


def low_spread_scores(
    centroids: jax.Array, fitnesses: jax.Array, descriptors: jax.Array
) -> LowSpreadScores:
    """Score candidates from their ``(B, E)`` episode returns and ``(B, E, d)``
    episode descriptors.

    The stored descriptor is the mean of the descriptors of the episodes that
    landed in the mode cell: it lies in the cell the candidate is filed under
    (a plain mean over all episodes may not), and it is what the policy reaches
    when it does what it usually does.
    """

    def one(fit, desc):
        cells = nearest(centroids, desc)
        cell = mode_cell(cells)
        in_cell = (cells == cell)[:, None]
        mean_in_cell = jnp.sum(jnp.where(in_cell, desc, 0.0), axis=0) / jnp.sum(in_cell)
        return LowSpreadScores(jnp.mean(fit), cell, mean_in_cell, spread(desc))

    return jax.vmap(one)(fitnesses, descriptors)


@struct.dataclass
class LowSpreadRepertoire:
    """A MAP-Elites repertoire that also stores each elite's spread."""

    repertoire: Repertoire
    spreads: jax.Array

    @classmethod
    def create(cls, repertoire: Repertoire) -> "LowSpreadRepertoire":
        return cls(repertoire, jnp.full(repertoire.fitnesses.shape, jnp.inf))


def insert_low_spread(
    lsr: LowSpreadRepertoire, genotypes: Any, scores: LowSpreadScores
) -> tuple[LowSpreadRepertoire, jax.Array]:
    """Algorithm 6's insertion, for a batch.

    A candidate is *eligible* when its cell is empty or when it has a strictly
    higher fitness and a strictly lower spread than the incumbent.  Among the
    eligible candidates of one cell, the fittest wins (ties: lowest batch index):
    it is the one no other candidate of the batch could displace by the same
    rule, so the batch gives what one-by-one insertion in decreasing-fitness
    order gives.  Returns the new repertoire and the mask of inserted candidates.
    """
    rep = lsr.repertoire
    incumbent_fit = rep.fitnesses[scores.cell]
    incumbent_spread = lsr.spreads[scores.cell]
    empty = ~rep.filled[scores.cell]
    eligible = jnp.isfinite(scores.fitness) & (
        empty | ((scores.fitness > incumbent_fit) & (scores.spread < incumbent_spread))
    )
    inserted = eligible & batch_winners(
        scores.cell, jnp.where(eligible, scores.fitness, -jnp.inf), rep.num_cells
    )
    new_rep = write_cells(rep, inserted, scores.cell, genotypes, scores.fitness, scores.descriptor)
    target = jnp.where(inserted, scores.cell, rep.num_cells)
    return LowSpreadRepertoire(
        new_rep, lsr.spreads.at[target].set(scores.spread, mode="drop")
    ), inserted


def reassess(
    repertoire: Repertoire, evaluate_fn: Callable[[Any, jax.Array], Any], key: jax.Array
) -> tuple[Repertoire, LowSpreadScores]:
    """The reassessment of Table 4.5: play every stored solution again over fresh
    episodes and insert it into an empty repertoire of the same cells.

    ``evaluate_fn(genotypes, key)`` returns an evaluation whose ``fitness`` has
    shape ``(N, E)`` and ``descriptor`` ``(N, E, d)``.  Each solution is filed, as
    in Low-Spread, under its most frequent cell with its mean fitness, and the
    cell keeps the fittest (plain MAP-Elites insertion, the same for every
    algorithm's repertoire).  Empty cells of the original stay out.  Returns the
    new repertoire and the scores of the re-evaluation, cell by cell of the
    original (their ``spread`` is each stored solution's measured spread).
    """
    ev = evaluate_fn(repertoire.genotypes, key)
    scores = low_spread_scores(repertoire.centroids, ev.fitness, ev.descriptor)
    fitness = jnp.where(repertoire.filled, scores.fitness, -jnp.inf)
    empty = init_repertoire(
        repertoire.centroids, jax.tree.map(lambda x: x[0], repertoire.genotypes)
    )
    return insert(empty, repertoire.genotypes, fitness, scores.descriptor)[0], scores


@struct.dataclass
class Accuracy:
    """Per-goal results of the accuracy experiment (Section 4.5.2)."""

    distance: jax.Array  # (G,) mean distance between the goal and the episodes' descriptors
    spread: jax.Array  # (G,) Eq. 4.1 over the episodes
    chosen: jax.Array  # (G,) repertoire cell whose policy was played


def nearest_cells(descriptors: jax.Array, goals: jax.Array, allowed: jax.Array) -> jax.Array:
    """For each goal of ``goals`` ``(G, d)``, the index of the cell, among those
    ``allowed`` ``(N,)`` marks, whose descriptor (``descriptors`` ``(N, d)``) is nearest
    to it (Euclidean)."""
    d2 = jnp.sum((goals[:, None, :] - descriptors[None, :, :]) ** 2, axis=-1)
    return jnp.argmin(jnp.where(allowed[None, :], d2, jnp.inf), axis=1)


def accuracy(
    repertoire: Repertoire,
    goals: jax.Array,
    evaluate_fn: Callable[[Any, jax.Array], Any],
    key: jax.Array,
) -> Accuracy:
    """For each goal descriptor, play the repertoire policy whose stored
    descriptor is nearest to the goal (``evaluate_fn(genotypes, key)`` returns
    ``(G, E)`` fitnesses and ``(G, E, d)`` descriptors) and measure how far its
    episodes end from the goal, and their spread."""
    chosen = nearest_cells(repertoire.descriptors, goals, repertoire.filled)
    ev = evaluate_fn(jax.tree.map(lambda x: x[chosen], repertoire.genotypes), key)
    distance = jnp.mean(jnp.linalg.norm(ev.descriptor - goals[:, None, :], axis=-1), axis=1)
    return Accuracy(distance=distance, spread=jax.vmap(spread)(ev.descriptor), chosen=chosen)
