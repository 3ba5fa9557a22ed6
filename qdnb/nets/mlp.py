"""Neural networks: deterministic MLP policies with tanh outputs, and a tanh-squashed
Gaussian policy for the stochastic agents of Chapter 3.

The policies' hidden layers use relu, QDax's MLP default, wherever the thesis is
silent on them: the primer's Point-Maze policies (Chapter 2), QD-PG and its
baselines (Chapter 3), and Chapter 4's repertoires (ME, ME-LS, PGA-ME,
PGA-ME-LS, ME-Sampling), which the QDT distils."""

from __future__ import annotations

from typing import Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp


class MLP(nn.Module):
    """A multilayer perceptron: relu hidden layers (QDax's default) and ``tanh`` on
    the output, which keeps actions in [-1, 1]."""

    layer_sizes: Sequence[int]
    activation: str = "relu"
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


class GaussianMLP(nn.Module):
    """A stochastic policy (SAC, DIAYN, AGAC): an MLP torso with ``hidden`` layers, then
    the mean and the log standard deviation (clipped to ``log_std_bounds``) of a
    Gaussian over each of ``action_size`` pre-squashing actions; ``tanh_gaussian_*``
    squash them into [-1, 1]."""

    hidden: Sequence[int]
    action_size: int
    activation: str = "relu"
    log_std_bounds: tuple[float, float] = (-5.0, 2.0)

    @nn.compact
    def __call__(self, x: jax.Array) -> tuple[jax.Array, jax.Array]:
        x = MLP(tuple(self.hidden), self.activation, final_activation=self.activation)(x)
        mean = nn.Dense(self.action_size, kernel_init=nn.initializers.lecun_uniform())(x)
        log_std = nn.Dense(self.action_size, kernel_init=nn.initializers.lecun_uniform())(x)
        return mean, jnp.clip(log_std, *self.log_std_bounds)


def _squash_correction(u: jax.Array) -> jax.Array:
    """log(1 - tanh(u)^2), summed over the action, in the stable form
    2 (log 2 - u - softplus(-2u))."""
    return jnp.sum(2.0 * (jnp.log(2.0) - u - nn.softplus(-2.0 * u)), axis=-1)


def _gaussian_log_prob(u: jax.Array, mean: jax.Array, log_std: jax.Array) -> jax.Array:
    z = (u - mean) * jnp.exp(-log_std)
    return jnp.sum(-0.5 * z**2 - log_std - 0.5 * jnp.log(2.0 * jnp.pi), axis=-1)


def tanh_gaussian_sample(
    mean: jax.Array, log_std: jax.Array, key: jax.Array
) -> tuple[jax.Array, jax.Array]:
    """An action a = tanh(u), u ~ N(mean, exp(log_std)^2) (reparameterised), and its
    log-density log pi(a) = log N(u) - sum log(1 - tanh(u)^2)."""
    u = mean + jnp.exp(log_std) * jax.random.normal(key, mean.shape)
    return jnp.tanh(u), _gaussian_log_prob(u, mean, log_std) - _squash_correction(u)


def tanh_gaussian_log_prob(
    mean: jax.Array, log_std: jax.Array, action: jax.Array, eps: float = 1e-6
) -> jax.Array:
    """log pi(action) of a given squashed action (clipped inside (-1, 1) by ``eps``)."""
    u = jnp.arctanh(jnp.clip(action, -1.0 + eps, 1.0 - eps))
    return _gaussian_log_prob(u, mean, log_std) - _squash_correction(u)
