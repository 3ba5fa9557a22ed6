"""Neural networks: deterministic MLP policies with tanh outputs."""

from __future__ import annotations

from typing import Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp


class MLP(nn.Module):
    """A multilayer perceptron; ``tanh`` on the output keeps actions in [-1, 1]."""

    layer_sizes: Sequence[int]
    activation: str = "tanh"
    final_activation: str | None = "tanh"

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        act = getattr(jnp, self.activation) if self.activation != "relu" else nn.relu
        for i, size in enumerate(self.layer_sizes):
            x = nn.Dense(size, kernel_init=nn.initializers.lecun_uniform())(x)
            if i < len(self.layer_sizes) - 1:
                x = act(x)
        if self.final_activation is not None:
            x = (
                jnp.tanh(x)
                if self.final_activation == "tanh"
                else getattr(nn, self.final_activation)(x)
            )
        return x


def init_policies(network: MLP, key: jax.Array, batch: int, observation_size: int):
    """Initial parameters of ``batch`` independent policies (leading axis)."""
    keys = jax.random.split(key, batch)
    dummy = jnp.zeros((observation_size,))
    return jax.vmap(lambda k: network.init(k, dummy))(keys)
