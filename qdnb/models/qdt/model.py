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

from typing import Any

import jax
import jax.numpy as jnp
from flax import linen as nn

from qdnb.nets.transformer import Block, Cache, run_blocks

TOKENS_PER_STEP = 3  # BD, O_t, A_t
OBS_OFFSET = 1  # the O_t token of timestep t sits at position 3t + 1


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

    def tokens(
        self, bd: jax.Array, obs: jax.Array, actions: jax.Array, timesteps: jax.Array
    ) -> jax.Array:
        """Embed and interleave: ``(B, T, ...)`` inputs give ``(B, 3T, D)`` tokens in
        the order ``BD_t, O_t, A_t`` for each timestep, all three with the
        embedding of ``timesteps[t]`` added."""
        step = self.embed_timestep(timesteps)  # (T, D) or (B, T, D)
        bd = jnp.broadcast_to(bd[:, None, :], obs.shape[:2] + bd.shape[-1:])
        stacked = jnp.stack(
            [
                self.embed_bd(bd) + step,
                self.embed_obs(obs) + step,
                self.embed_action(actions) + step,
            ],
            axis=2,
        )  # (B, T, 3, D)
        return self.embed_ln(stacked.reshape(obs.shape[0], -1, self.embed_dim))

    def transformer(self, x, caches, start, deterministic):
        x, caches = run_blocks(
            self.blocks, self.drop(x, deterministic=deterministic), caches, start, deterministic
        )
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
        shape = (
            batch,
            TOKENS_PER_STEP * self.max_steps,
            self.num_heads,
            self.embed_dim // self.num_heads,
        )
        return tuple(
            (jnp.zeros(shape, dtype), jnp.zeros(shape, dtype)) for _ in range(self.num_layers)
        )

    def prefill(self, bd: jax.Array, obs0: jax.Array, cache: Cache):
        """Timestep 0: the tokens ``BD, O_0`` at positions 0 and 1; returns ``A_0``
        and the cache."""
        step = self.embed_timestep(jnp.zeros((), jnp.int32))
        x = self.embed_ln(
            jnp.stack([self.embed_bd(bd) + step, self.embed_obs(obs0) + step], axis=1)
        )
        hidden, cache = self.transformer(x, cache, 0, True)
        return self.head(hidden[:, -1]), cache

    def decode_step(
        self, bd: jax.Array, prev_action: jax.Array, obs: jax.Array, t: jax.Array, cache: Cache
    ):
        """Timestep ``t >= 1``: the tokens ``A_{t-1}`` (timestep ``t-1``), ``BD`` and
        ``O_t`` (timestep ``t``) at positions ``3t-1 .. 3t+1``; returns ``A_t``."""
        prev = self.embed_timestep(t - 1)
        step = self.embed_timestep(t)
        x = self.embed_ln(
            jnp.stack(
                [
                    self.embed_action(prev_action) + prev,
                    self.embed_bd(bd) + step,
                    self.embed_obs(obs) + step,
                ],
                axis=1,
            )
        )
        hidden, cache = self.transformer(x, cache, TOKENS_PER_STEP * t - 1, True)
        return self.head(hidden[:, -1]), cache


def init_params(model: QDT, key: jax.Array, descriptor_size: int, observation_size: int) -> Any:
    t = 2
    return model.init(
        key,
        jnp.zeros((1, descriptor_size)),
        jnp.zeros((1, t, observation_size)),
        jnp.zeros((1, t, model.action_size)),
    )
