"""Variation operators on batches of genotypes (any pytree with a leading batch axis)."""

from __future__ import annotations

from typing import Any

import jax


def _leaf_keys(key: jax.Array, tree: Any) -> Any:
    leaves, treedef = jax.tree.flatten(tree)
    return jax.tree.unflatten(treedef, list(jax.random.split(key, len(leaves))))


def gaussian_mutation(genotypes: Any, key: jax.Array, sigma: float) -> Any:
    """x' = x + sigma * N(0, I)."""
    keys = _leaf_keys(key, genotypes)
    return jax.tree.map(
        lambda x, k: x + sigma * jax.random.normal(k, x.shape, x.dtype), genotypes, keys
    )


def isoline_variation(x1: Any, x2: Any, key: jax.Array, iso_sigma: float, line_sigma: float) -> Any:
    """Iso+line variation (Vassiliades and Mouret, 2018).

    x' = x1 + iso_sigma * N(0, I) + line_sigma * N(0, 1) * (x2 - x1), with one
    line coefficient per offspring shared by all of its parameters.
    """
    k_iso, k_line = jax.random.split(key)
    batch = jax.tree.leaves(x1)[0].shape[0]
    line = jax.random.normal(k_line, (batch,))
    keys = _leaf_keys(k_iso, x1)

    def vary(a, b, k):
        coef = line.reshape((batch,) + (1,) * (a.ndim - 1))
        return a + iso_sigma * jax.random.normal(k, a.shape, a.dtype) + line_sigma * coef * (b - a)

    return jax.tree.map(vary, x1, x2, keys)
