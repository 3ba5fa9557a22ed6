"""Algorithm 8: the Quality-Diversity Transformer, a causal GPT over the
interleaved trajectory ``(BD, O_0, A_0, BD, O_1, A_1, ..., BD, O_T, A_T)``.

Each modality has its own linear embedding; the learned embedding of timestep
``t`` is added to the three tokens of that timestep (one timestep embedding per
timestep, not per token), then a layer normalisation.  A pre-norm GPT-2 stack
with causal self-attention (Eq. 2.2) follows, with ReLU feed-forward layers
(Table 4.3), and the action ``A_t`` is read from the hidden state at the
``O_t`` token, so it depends on the target BD, ``O_0..O_t`` and ``A_0..A_{t-1}``.

Attention takes an optional key/value cache, so that an episode is played one
timestep at a time at the cost of the new tokens only (``prefill`` and
``decode_step``); the full forward pass (training) and the cached passes share
the same parameters and give the same outputs.
"""

from __future__ import annotations

import math
from typing import Any

import jax
import jax.numpy as jnp
from flax import linen as nn

TOKENS_PER_STEP = 3  # BD, O_t, A_t
OBS_OFFSET = 1  # the O_t token of timestep t sits at position 3t + 1

# (keys, values) per layer, each (batch, 3T, heads, head_dim)
Cache = tuple[tuple[jax.Array, jax.Array], ...]


def causal_mask(num_new: int, cache_length: int, start: jax.Array | int) -> jax.Array:
    """``mask[i, j]``: whether the new token ``i`` (at position ``start + i``)
    may attend to position ``j`` of the (cached) sequence, i.e. ``j <= start + i``."""
    return jnp.arange(cache_length)[None, :] <= (start + jnp.arange(num_new))[:, None]


class CausalSelfAttention(nn.Module):
    num_heads: int
    dropout: float

    @nn.compact
    def __call__(self, x: jax.Array, cache: tuple[jax.Array, jax.Array] | None, start: jax.Array | int,
                 deterministic: bool):
        b, n, d = x.shape
        if d % self.num_heads:
            raise ValueError(f"embedding size {d} is not a multiple of num_heads {self.num_heads}")
        head = d // self.num_heads
        q, k, v = jnp.split(nn.Dense(3 * d, name="qkv")(x).reshape(b, n, 3 * self.num_heads, head), 3, axis=2)
        if cache is None:  # the whole sequence at once (training)
            keys, values = k, v
        else:  # write the new tokens' keys and values at their positions
            keys = jax.lax.dynamic_update_slice(cache[0], k.astype(cache[0].dtype), (0, start, 0, 0))
            values = jax.lax.dynamic_update_slice(cache[1], v.astype(cache[1].dtype), (0, start, 0, 0))
        mask = causal_mask(n, keys.shape[1], start)
        logits = jnp.einsum("bqhd,bkhd->bhqk", q, keys) / math.sqrt(head)
        weights = jax.nn.softmax(jnp.where(mask, logits, -jnp.inf), axis=-1)
        weights = nn.Dropout(self.dropout)(weights, deterministic=deterministic)
        out = jnp.einsum("bhqk,bkhd->bqhd", weights, values).reshape(b, n, d)
        out = nn.Dropout(self.dropout)(nn.Dense(d, name="proj")(out), deterministic=deterministic)
        return out, (keys, values)


class Block(nn.Module):
    """Pre-norm GPT-2 block: ``x + attn(LN(x))``, then ``x + MLP(LN(x))``."""

    num_heads: int
    dropout: float

    @nn.compact
    def __call__(self, x, cache, start, deterministic):
        d = x.shape[-1]
        attended, cache = CausalSelfAttention(self.num_heads, self.dropout, name="attn")(
            nn.LayerNorm(name="ln_attn")(x), cache, start, deterministic)
        x = x + attended
        h = nn.Dense(4 * d, name="fc")(nn.LayerNorm(name="ln_mlp")(x))
        h = nn.Dense(d, name="fc_out")(nn.relu(h))
        return x + nn.Dropout(self.dropout)(h, deterministic=deterministic), cache


def run_blocks(blocks, x, caches, start, deterministic):
    """Apply ``blocks`` in order, each with its own cache (``None`` for a full pass);
    returns the output and the new caches.  Shared by the QDT and the FLT."""
    new_caches = []
    for block, cache in zip(blocks, caches):
        x, cache = block(x, cache, start, deterministic)
        new_caches.append(cache)
    return x, tuple(new_caches)


class QDT(nn.Module):
    """The Quality-Diversity Transformer (Algorithm 8, Table 4.3).

    ``__call__(bd, obs, actions)`` with ``bd (B, d)``, ``obs (B, T, O)`` and
    ``actions (B, T, A)`` returns the predicted actions ``(B, T, A)``: one causal
    pass over the ``3T`` interleaved tokens (teacher forcing)."""

    action_size: int
    max_steps: int
    embed_dim: int = 256
    num_layers: int = 4
    num_heads: int = 8
    dropout: float = 0.1

    def setup(self):
        self.embed_bd = nn.Dense(self.embed_dim)
        self.embed_obs = nn.Dense(self.embed_dim)
        self.embed_action = nn.Dense(self.embed_dim)
        self.embed_timestep = nn.Embed(self.max_steps, self.embed_dim)
        self.embed_ln = nn.LayerNorm()
        self.drop = nn.Dropout(self.dropout)
        self.blocks = [Block(self.num_heads, self.dropout) for _ in range(self.num_layers)]
        self.ln_final = nn.LayerNorm()
        self.predict_action = nn.Dense(self.action_size)

    def tokens(self, bd: jax.Array, obs: jax.Array, actions: jax.Array, timesteps: jax.Array) -> jax.Array:
        """Embed and interleave: ``(B, T, ...)`` inputs give ``(B, 3T, D)`` tokens in
        the order ``BD_t, O_t, A_t`` for each timestep, all three with the
        embedding of ``timesteps[t]`` added."""
        step = self.embed_timestep(timesteps)  # (T, D) or (B, T, D)
        bd = jnp.broadcast_to(bd[:, None, :], obs.shape[:2] + bd.shape[-1:])
        stacked = jnp.stack([self.embed_bd(bd) + step, self.embed_obs(obs) + step,
                             self.embed_action(actions) + step], axis=2)  # (B, T, 3, D)
        return self.embed_ln(stacked.reshape(obs.shape[0], -1, self.embed_dim))

    def transformer(self, x, caches, start, deterministic):
        x, caches = run_blocks(self.blocks, self.drop(x, deterministic=deterministic), caches, start, deterministic)
        return self.ln_final(x), caches

    def head(self, hidden: jax.Array) -> jax.Array:
        return jnp.tanh(self.predict_action(hidden))  # actions live in [-1, 1]

    def __call__(self, bd, obs, actions, deterministic: bool = True):
        t = obs.shape[1]
        x = self.tokens(bd, obs, actions, jnp.arange(t))
        hidden, _ = self.transformer(x, (None,) * self.num_layers, 0, deterministic)
        return self.head(hidden[:, OBS_OFFSET::TOKENS_PER_STEP])

    # ----- cached, one timestep at a time (evaluation) -----

    def init_cache(self, batch: int, dtype=jnp.float32) -> Cache:
        shape = (batch, TOKENS_PER_STEP * self.max_steps, self.num_heads, self.embed_dim // self.num_heads)
        return tuple((jnp.zeros(shape, dtype), jnp.zeros(shape, dtype)) for _ in range(self.num_layers))

    def prefill(self, bd: jax.Array, obs0: jax.Array, cache: Cache):
        """Timestep 0: the tokens ``BD, O_0`` at positions 0 and 1; returns ``A_0``
        and the cache."""
        step = self.embed_timestep(jnp.zeros((), jnp.int32))
        x = self.embed_ln(jnp.stack([self.embed_bd(bd) + step, self.embed_obs(obs0) + step], axis=1))
        hidden, cache = self.transformer(x, cache, 0, True)
        return self.head(hidden[:, -1]), cache

    def decode_step(self, bd: jax.Array, prev_action: jax.Array, obs: jax.Array, t: jax.Array, cache: Cache):
        """Timestep ``t >= 1``: the tokens ``A_{t-1}`` (timestep ``t-1``), ``BD`` and
        ``O_t`` (timestep ``t``) at positions ``3t-1 .. 3t+1``; returns ``A_t``."""
        prev = self.embed_timestep(t - 1)
        step = self.embed_timestep(t)
        x = self.embed_ln(jnp.stack([self.embed_action(prev_action) + prev, self.embed_bd(bd) + step,
                                     self.embed_obs(obs) + step], axis=1))
        hidden, cache = self.transformer(x, cache, TOKENS_PER_STEP * t - 1, True)
        return self.head(hidden[:, -1]), cache


def init_params(model: QDT, key: jax.Array, descriptor_size: int, observation_size: int) -> Any:
    t = 2
    return model.init(key, jnp.zeros((1, descriptor_size)), jnp.zeros((1, t, observation_size)),
                      jnp.zeros((1, t, model.action_size)))
