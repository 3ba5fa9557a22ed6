"""Small helpers over pytrees of arrays whose leaves share a leading (batch) axis."""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp


def take(tree: Any, idx: Any) -> Any:
    """Rows ``idx`` of every leaf."""
    return jax.tree.map(lambda x: x[idx], tree)


def concat(a: Any, b: Any) -> Any:
    """Two batches end to end."""
    return jax.tree.map(lambda x, y: jnp.concatenate([x, y]), a, b)


def stack(trees: list[Any]) -> Any:
    """Trees of the same structure stacked along a new leading axis."""
    return jax.tree.map(lambda *xs: jnp.stack(xs), *trees)
