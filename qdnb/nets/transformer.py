"""The causal transformer both sequence models of the book share (the QDT of
Chapter 4 and the FLT of Chapter 5): a pre-norm GPT-2 block with causal
self-attention (Eq. 2.2), whose attention takes an optional key/value cache so
that a sequence is decoded one step at a time at the cost of the new tokens
only; and the Adam-with-clipping optimiser both train with."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import optax
from flax import linen as nn

# (keys, values) per layer, each (batch, 3T, heads, head_dim)
Cache = tuple[tuple[jax.Array, jax.Array], ...]


# the outputs a pass computes: every ``stride``-th token from ``offset`` (the last layer of a
# training pass needs only the tokens a loss reads: the QDT's O_t tokens)
Queries = tuple[int, int] | None  # (offset, stride)


def causal_mask(num_new: int, cache_length: int, start: jax.Array | int) -> jax.Array:
    """``mask[i, j]``: whether the new token ``i`` (at position ``start + i``)
    may attend to position ``j`` of the (cached) sequence, i.e. ``j <= start + i``."""
    return mask_at(start + jnp.arange(num_new), cache_length)


def mask_at(positions: jax.Array, length: int) -> jax.Array:
    """``mask[i, j]``: whether the query at ``positions[i]`` may attend to position
    ``j`` of a sequence of ``length`` (``j <= positions[i]``)."""
    return jnp.arange(length)[None, :] <= positions[:, None]


class CausalSelfAttention(nn.Module):
    num_heads: int
    dropout: float

    @nn.compact
    def __call__(
        self,
        x: jax.Array,
        cache: tuple[jax.Array, jax.Array] | None,
        start: jax.Array | int,
        deterministic: bool,
        queries: Queries = None,
    ):
        """``queries``: compute the outputs at those tokens only (a full pass: no
        ``cache``), each attending to every token up to its own position."""
        b, n, d = x.shape
        if d % self.num_heads:
            raise ValueError(f"embedding size {d} is not a multiple of num_heads {self.num_heads}")
        head = d // self.num_heads
        q, k, v = jnp.split(
            nn.Dense(3 * d, name="qkv")(x).reshape(b, n, 3 * self.num_heads, head), 3, axis=2
        )
        if cache is None:  # the whole sequence at once (training)
            keys, values = k, v
        else:  # write the new tokens' keys and values at their positions
            keys = jax.lax.dynamic_update_slice(
                cache[0], k.astype(cache[0].dtype), (0, start, 0, 0)
            )
            values = jax.lax.dynamic_update_slice(
                cache[1], v.astype(cache[1].dtype), (0, start, 0, 0)
            )
        if queries is None:
            mask = causal_mask(n, keys.shape[1], start)
        else:
            offset, stride = queries
            q = q[:, offset::stride]
            mask = mask_at(offset + stride * jnp.arange(q.shape[1]), keys.shape[1])
        logits = jnp.einsum("bqhd,bkhd->bhqk", q, keys) / math.sqrt(head)
        weights = jax.nn.softmax(jnp.where(mask, logits, -jnp.inf), axis=-1)
        weights = nn.Dropout(self.dropout)(weights, deterministic=deterministic)
        out = jnp.einsum("bhqk,bkhd->bqhd", weights, values).reshape(b, q.shape[1], d)
        out = nn.Dropout(self.dropout)(nn.Dense(d, name="proj")(out), deterministic=deterministic)
        return out, (keys, values)


class Block(nn.Module):
    """Pre-norm GPT-2 block: ``x + attn(LN(x))``, then ``x + MLP(LN(x))``."""

    num_heads: int
    dropout: float

    @nn.compact
    def __call__(self, x, cache, start, deterministic, queries: Queries = None):
        d = x.shape[-1]
        attended, cache = CausalSelfAttention(self.num_heads, self.dropout, name="attn")(
            nn.LayerNorm(name="ln_attn")(x), cache, start, deterministic, queries
        )
        if queries is not None:  # the residual stream of the queried tokens only
            x = x[:, queries[0] :: queries[1]]
        x = x + attended
        h = nn.Dense(4 * d, name="fc")(nn.LayerNorm(name="ln_mlp")(x))
        h = nn.Dense(d, name="fc_out")(nn.relu(h))
        return x + nn.Dropout(self.dropout)(h, deterministic=deterministic), cache


def run_blocks(blocks, x, caches, start, deterministic, queries: Queries = None):
    """Apply ``blocks`` in order, each with its own cache (``None`` for a full pass);
    returns the output and the new caches.  Shared by the QDT and the FLT.  With
    ``queries``, the last block computes the outputs at those tokens only: the same
    values there (nothing after a token depends on it), a third of the last layer's work
    for the QDT's loss, which reads one token in three."""
    new_caches = []
    for i, (block, cache) in enumerate(zip(blocks, caches)):
        last = i == len(blocks) - 1
        x, cache = block(x, cache, start, deterministic, queries if last else None)
        new_caches.append(cache)
    return x, tuple(new_caches)


def make_optimizer(learning_rate: float) -> optax.GradientTransformation:
    """Adam with gradient clipping (global norm 1), as Decision-Transformer-style
    training does; the learning rate is Table 4.3's."""
    return optax.chain(optax.clip_by_global_norm(1.0), optax.adam(learning_rate))
