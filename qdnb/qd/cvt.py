"""Tessellations of the descriptor space: regular grids and CVTs.

A Centroidal Voronoi Tessellation (Vassiliades et al., 2016) places ``k``
centroids so that their Voronoi cells have roughly equal volume; it is computed
here with Lloyd's k-means on uniform samples, all in JAX and fully determined by
the key.
"""

from __future__ import annotations

from typing import Sequence

import jax
import jax.numpy as jnp


def grid_centroids(bins: Sequence[int], low: Sequence[float], high: Sequence[float]) -> jax.Array:
    """Centres of a regular grid with ``bins[i]`` cells along dimension ``i``.

    Row-major order: the last dimension varies fastest.
    """
    if len(bins) != len(low) or len(low) != len(high):
        raise ValueError("bins, low and high must have the same length")
    axes = [lo + (jnp.arange(b) + 0.5) * (hi - lo) / b for b, lo, hi in zip(bins, low, high)]
    mesh = jnp.meshgrid(*axes, indexing="ij")
    return jnp.stack([m.reshape(-1) for m in mesh], axis=-1)


def cvt_centroids(
    key: jax.Array,
    num_centroids: int,
    low: Sequence[float],
    high: Sequence[float],
    num_samples: int = 25_000,
    num_iterations: int = 50,
) -> jax.Array:
    """CVT centroids by k-means (Lloyd) on ``num_samples`` uniform points."""
    if num_samples < num_centroids:
        raise ValueError("num_samples must be at least num_centroids")
    low_a, high_a = jnp.asarray(low, jnp.float32), jnp.asarray(high, jnp.float32)
    points = jax.random.uniform(key, (num_samples, low_a.shape[0]), minval=low_a, maxval=high_a)
    init = points[:num_centroids]

    def lloyd(_, centroids):
        assign = nearest(centroids, points)
        sums = jax.ops.segment_sum(points, assign, num_segments=num_centroids)
        counts = jax.ops.segment_sum(jnp.ones(num_samples), assign, num_segments=num_centroids)
        return jnp.where(counts[:, None] > 0, sums / jnp.maximum(counts, 1.0)[:, None], centroids)

    return jax.lax.fori_loop(0, num_iterations, lloyd, init)


def nearest(centroids: jax.Array, points: jax.Array) -> jax.Array:
    """Index of the nearest centroid of each point (the cell a descriptor falls in)."""
    d2 = (
        jnp.sum(points**2, axis=-1, keepdims=True)
        - 2.0 * points @ centroids.T
        + jnp.sum(centroids**2, axis=-1)[None, :]
    )
    return jnp.argmin(d2, axis=-1)
