"""A loop's numerical health: which parts of an algorithm's state hold a NaN.

Every loop of ``run_seeds`` records, at every iteration and for every seed, whether
each top-level part of the algorithm's state (QD-PG's grid, its two critics, its
buffer, its archive) holds a NaN.  A seed diverges at the first iteration where one
does; from there its numbers mean nothing, so results report it as diverged (the
iteration and the parts) and leave it out of every mean.  The loop stops once every
seed has diverged.  An infinity alone does not count: empty grid cells hold
``-inf`` fitness by design, and a diverging network reaches NaN within a step or two.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np


def part_names(state: Any) -> tuple[str, ...]:
    """The top-level parts of a state: a dataclass's fields, else the whole state."""
    if dataclasses.is_dataclass(state):
        return tuple(f.name for f in dataclasses.fields(state))
    return ("state",)


def nan_parts(state: Any) -> jax.Array:
    """Per part of ``part_names``, whether it holds a NaN (``(parts,)`` booleans)."""
    parts = (
        [getattr(state, n) for n in part_names(state)]
        if dataclasses.is_dataclass(state)
        else [state]
    )

    def has_nan(tree: Any) -> jax.Array:
        leaves = [
            jnp.any(jnp.isnan(x))
            for x in jax.tree.leaves(tree)
            if jnp.issubdtype(jnp.asarray(x).dtype, jnp.inexact)
        ]
        return jnp.any(jnp.stack(leaves)) if leaves else jnp.zeros((), bool)

    return jnp.stack([has_nan(p) for p in parts])


@dataclass(frozen=True)
class Divergence:
    """Where a seed went NaN: the history's iteration (0: the initial batch) and the
    parts of its state that held a NaN then."""

    iteration: int
    parts: tuple[str, ...]

    def text(self) -> str:
        return f"NaN at iteration {self.iteration} in {', '.join(self.parts)}"


def divergences(history_nan_parts: Any, names: tuple[str, ...]) -> list[Divergence | None]:
    """Per seed, its ``Divergence`` (``None`` if it stayed finite), from a history's
    ``nan_parts`` (``(seeds, iterations, parts)``)."""
    flags = np.asarray(history_nan_parts, bool)
    out: list[Divergence | None] = []
    for seed in flags:
        bad = seed.any(axis=1)
        if not bad.any():
            out.append(None)
            continue
        i = int(np.argmax(bad))
        out.append(Divergence(i, tuple(n for n, b in zip(names, seed[i]) if b)))
    return out
