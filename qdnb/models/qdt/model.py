"""Algorithm 8: the Quality-Diversity Transformer, a causal GPT over the
interleaved trajectory ``(BD, O_0, A_0, BD, O_1, A_1, ..., BD, O_T, A_T)``.

Each modality has its own linear embedding; the learned embedding of timestep
``t`` is added to the three tokens of that timestep (one timestep embedding per
timestep, not per token), then a layer normalisation.  A pre-norm GPT-2 stack
with causal self-attention (Eq. 2.2) follows, with ReLU feed-forward layers
(Table 4.3), and the action ``A_t`` is read from the hidden state at the
``O_t`` token, so it depends on the target BD, ``O_0..O_t`` and ``A_0..A_{t-1}``,
through Algorithm 8's linear prediction layer.

Three labelled departures, each off by default and measured against the thesis's
reading in ``bench/qdt.py``: ``head="tanh"`` (the Decision Transformer's action head,
which keeps actions in [-1, 1]), ``init_scheme="torch"`` (PyTorch's default initialisation of
the QDT's own layers: uniform weights and biases of bound 1/sqrt(fan-in), unit-normal
timestep embeddings) and ``bd_box`` (the target BD scaled from its box to [-1, 1]
before its embedding; the thesis feeds it raw).  Why they matter: the BD token is
LayerNorm(W bd + b + e_t), and LayerNorm forgets a token's scale, so with Flax's zero
bias two BDs on one ray from the origin, (2, 2) and (8, 8), start as nearly the same
token; a random bias or a box-centred BD tells them apart from the first step.

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
HEADS = ("linear", "tanh")  # Algorithm 8's Pred_A; the Decision Transformer's
INITS = ("flax", "torch")  # Flax's defaults; PyTorch's, for the QDT's own layers


def scale_to_box(bd: jax.Array, low, high) -> jax.Array:
    """``bd`` mapped affinely from the box ``[low, high]`` to ``[-1, 1]``."""
    low, high = jnp.asarray(low, jnp.float32), jnp.asarray(high, jnp.float32)
    return 2.0 * (bd - low) / (high - low) - 1.0


def unscale_from_box(u: jax.Array, low, high) -> jax.Array:
    """The inverse of ``scale_to_box``."""
    low, high = jnp.asarray(low, jnp.float32), jnp.asarray(high, jnp.float32)
    return low + (u + 1.0) * (high - low) / 2.0


def _torch_uniform(bound: float):
    return lambda key, shape, dtype=jnp.float32: jax.random.uniform(
        key, shape, dtype, -bound, bound
    )


class TorchDense(nn.Module):
    """A linear layer initialised as PyTorch's ``nn.Linear``: weights and bias uniform
    in ``[-1/sqrt(fan_in), 1/sqrt(fan_in)]`` (parameters named as ``nn.Dense``'s)."""

    features: int

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        init = _torch_uniform(1.0 / float(x.shape[-1]) ** 0.5)
        kernel = self.param("kernel", init, (x.shape[-1], self.features))
        return x @ kernel + self.param("bias", init, (self.features,))


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
    head: str = "linear"
    init_scheme: str = "flax"
    bd_box: tuple[tuple[float, ...], tuple[float, ...]] | None = None  # (low, high)

    def setup(self):
        if self.head not in HEADS:
            raise ValueError(f"unknown action head {self.head!r}; valid: {', '.join(HEADS)}")
        if self.init_scheme not in INITS:
            raise ValueError(
                f"unknown initialisation {self.init_scheme!r}; valid: {', '.join(INITS)}"
            )
        if self.init_scheme == "torch":
            dense = TorchDense
            embed_init = nn.initializers.normal(1.0)  # nn.Embedding's
        else:
            dense, embed_init = nn.Dense, nn.linear.default_embed_init
        self.embed_bd = dense(self.embed_dim)
        self.embed_obs = dense(self.embed_dim)
        self.embed_action = dense(self.embed_dim)
        self.embed_timestep = nn.Embed(self.max_steps, self.embed_dim, embedding_init=embed_init)
        self.embed_ln = nn.LayerNorm()
        self.drop = nn.Dropout(self.dropout)
        self.blocks = [Block(self.num_heads, self.dropout) for _ in range(self.num_layers)]
        self.ln_final = nn.LayerNorm()
        self.predict_action = dense(self.action_size)

    def condition(self, bd: jax.Array) -> jax.Array:
        """The BD as the embedding sees it: raw (the thesis), or scaled from ``bd_box``."""
        return bd if self.bd_box is None else scale_to_box(bd, *self.bd_box)

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
                self.embed_bd(self.condition(bd)) + step,
                self.embed_obs(obs) + step,
                self.embed_action(actions) + step,
            ],
            axis=2,
        )  # (B, T, 3, D)
        return self.embed_ln(stacked.reshape(obs.shape[0], -1, self.embed_dim))

    def transformer(self, x, caches, start, deterministic, queries=None):
        x, caches = run_blocks(
            self.blocks,
            self.drop(x, deterministic=deterministic),
            caches,
            start,
            deterministic,
            queries,
        )
        return self.ln_final(x), caches

    def predict(self, hidden: jax.Array) -> jax.Array:
        """Algorithm 8's linear ``Pred_A``, or (``head="tanh"``) the Decision
        Transformer's, squashed to the actions' [-1, 1]."""
        out = self.predict_action(hidden)
        return jnp.tanh(out) if self.head == "tanh" else out

    def __call__(self, bd, obs, actions, deterministic: bool = True):
        t = obs.shape[1]
        x = self.tokens(bd, obs, actions, jnp.arange(t))
        # the last layer computes the O_t tokens only: the actions are read there
        queries = (OBS_OFFSET, TOKENS_PER_STEP)
        hidden, _ = self.transformer(x, (None,) * self.num_layers, 0, deterministic, queries)
        return self.predict(hidden)

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
            jnp.stack(
                [self.embed_bd(self.condition(bd)) + step, self.embed_obs(obs0) + step], axis=1
            )
        )
        hidden, cache = self.transformer(x, cache, 0, True)
        return self.predict(hidden[:, -1]), cache

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
                    self.embed_bd(self.condition(bd)) + step,
                    self.embed_obs(obs) + step,
                ],
                axis=1,
            )
        )
        hidden, cache = self.transformer(x, cache, TOKENS_PER_STEP * t - 1, True)
        return self.predict(hidden[:, -1]), cache


def init_params(model: QDT, key: jax.Array, descriptor_size: int, observation_size: int) -> Any:
    t = 2
    return model.init(
        key,
        jnp.zeros((1, descriptor_size)),
        jnp.zeros((1, t, observation_size)),
        jnp.zeros((1, t, model.action_size)),
    )
