"""QD metrics (Section 2.2.2): coverage (Eq. 2.4), QD score (Eq. 2.3), max fitness."""

from __future__ import annotations

from typing import Sequence

import jax
import jax.numpy as jnp
from flax import struct

from qdnb.qd.repertoire import Repertoire


def qd_metrics(repertoire: Repertoire, fitness_offset: float) -> dict[str, jax.Array]:
    """Coverage = filled cells / cells; QD score = sum over elites of
    (fitness - offset), the offset making every elite count positively;
    max fitness over elites (``-inf`` when empty)."""
    filled = repertoire.filled
    return {
        "coverage": jnp.mean(filled),
        "qd_score": jnp.sum(jnp.where(filled, repertoire.fitnesses - fitness_offset, 0.0)),
        "max_fitness": jnp.max(repertoire.fitnesses),
    }


def grid_cell(
    points: jax.Array, bins: Sequence[int], low: Sequence[float], high: Sequence[float]
) -> jax.Array:
    """Flat index of the regular-grid cell of each point (points on the upper edge
    go to the last cell)."""
    low_a, high_a = jnp.asarray(low), jnp.asarray(high)
    bins_a = jnp.asarray(bins)
    rel = (points - low_a) / (high_a - low_a)
    idx = jnp.clip(jnp.floor(rel * bins_a).astype(jnp.int32), 0, bins_a - 1)
    strides = jnp.concatenate([jnp.cumprod(bins_a[::-1])[::-1][1:], jnp.ones(1, jnp.int32)])
    return jnp.sum(idx * strides, axis=-1)


@struct.dataclass
class ExplorationTrack:
    """Where the descriptors of every evaluated solution landed, over a whole run.

    ``visited`` marks the cells of a fixed regular grid reached by at least one
    descriptor; ``min_distance`` is the smallest distance between any descriptor
    and ``target`` (the maze's goal).  Used to compare algorithms that keep
    different kinds of archives on the same footing.
    """

    visited: jax.Array
    min_distance: jax.Array

    @classmethod
    def create(cls, num_cells: int) -> "ExplorationTrack":
        return cls(visited=jnp.zeros((num_cells,), bool), min_distance=jnp.asarray(jnp.inf))

    def update(self, descriptors: jax.Array, bins, low, high, target) -> "ExplorationTrack":
        cells = grid_cell(descriptors, bins, low, high)
        dist = jnp.linalg.norm(descriptors - jnp.asarray(target), axis=-1)
        return self.replace(
            visited=self.visited.at[cells].set(True),
            min_distance=jnp.minimum(self.min_distance, jnp.min(dist)),
        )

    @property
    def coverage(self) -> jax.Array:
        return jnp.mean(self.visited)
