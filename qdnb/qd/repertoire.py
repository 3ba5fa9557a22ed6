"""The MAP-Elites repertoire (Algorithm 1): one elite per cell of a tessellation."""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
from flax import struct

from qdnb.qd.cvt import nearest


@struct.dataclass
class Repertoire:
    """Elites stored per cell.  Empty cells have fitness ``-inf``.

    ``genotypes`` is any pytree whose leaves have a leading axis of size
    ``num_cells``; ``descriptors`` are the descriptors the elites were inserted with.
    """

    genotypes: Any
    fitnesses: jax.Array
    descriptors: jax.Array
    centroids: jax.Array

    @property
    def filled(self) -> jax.Array:
        return self.fitnesses > -jnp.inf

    @property
    def num_cells(self) -> int:
        return self.centroids.shape[0]


def init_repertoire(centroids: jax.Array, genotype_example: Any) -> Repertoire:
    """An empty repertoire whose genotypes have the structure of ``genotype_example``
    (one genotype, without batch axis)."""
    n = centroids.shape[0]
    genotypes = jax.tree.map(
        lambda x: jnp.zeros((n,) + jnp.shape(x), jnp.asarray(x).dtype), genotype_example
    )
    return Repertoire(
        genotypes=genotypes,
        fitnesses=jnp.full((n,), -jnp.inf),
        descriptors=jnp.zeros_like(centroids),
        centroids=centroids,
    )


def batch_winners(cells: jax.Array, fitnesses: jax.Array, num_cells: int) -> jax.Array:
    """Mask of the candidates that are the best of their cell within the batch.

    Ties are broken by the lowest batch index, so exactly one candidate per
    occupied cell wins; candidates with non-finite fitness never win.
    """
    valid = jnp.isfinite(fitnesses)
    fit = jnp.where(valid, fitnesses, -jnp.inf)
    best = jax.ops.segment_max(fit, cells, num_segments=num_cells)
    is_best = valid & (fit == best[cells])
    index = jnp.arange(fitnesses.shape[0])
    first = jax.ops.segment_min(
        jnp.where(is_best, index, fitnesses.shape[0]), cells, num_segments=num_cells
    )
    return is_best & (index == first[cells])


def write_cells(
    repertoire: Repertoire,
    mask: jax.Array,
    cells: jax.Array,
    genotypes: Any,
    fitnesses: jax.Array,
    descriptors: jax.Array,
) -> Repertoire:
    """Write the masked candidates into their cells (at most one per cell)."""
    target = jnp.where(mask, cells, repertoire.num_cells)  # out of range: dropped
    put = lambda old, new: old.at[target].set(new, mode="drop")
    return repertoire.replace(
        genotypes=jax.tree.map(put, repertoire.genotypes, genotypes),
        fitnesses=put(repertoire.fitnesses, fitnesses),
        descriptors=put(repertoire.descriptors, descriptors),
    )


def insert(
    repertoire: Repertoire, genotypes: Any, fitnesses: jax.Array, descriptors: jax.Array
) -> tuple[Repertoire, jax.Array]:
    """Batch insertion of MAP-Elites.

    Each cell keeps the best of its incumbent and of every candidate of the
    batch that falls into it (a candidate must be strictly better than the
    incumbent).  Returns the new repertoire and the mask of inserted candidates.
    """
    cells = nearest(repertoire.centroids, descriptors)
    winners = batch_winners(cells, fitnesses, repertoire.num_cells)
    inserted = winners & (fitnesses > repertoire.fitnesses[cells])
    return write_cells(repertoire, inserted, cells, genotypes, fitnesses, descriptors), inserted


def sample(repertoire: Repertoire, key: jax.Array, num: int) -> Any:
    """Uniform selection: ``num`` elites drawn with replacement among filled cells."""
    p = repertoire.filled / jnp.maximum(jnp.sum(repertoire.filled), 1)
    idx = jax.random.choice(key, repertoire.num_cells, shape=(num,), p=p)
    return jax.tree.map(lambda x: x[idx], repertoire.genotypes)
