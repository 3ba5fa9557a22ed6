"""The small interface every environment of the book implements.

An environment is a frozen dataclass of constants with pure ``reset``/``step``
functions, in the style of gymnax and Brax: ``reset(key) -> EnvState`` and
``step(state, action) -> EnvState``.  On top of the usual observation, reward and
done flag, every state carries a *state descriptor* (Chapter 3, the quantity whose
novelty QD-PG rewards), and every environment says how an episode's *behaviour
descriptor* is read from its trajectory.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
from flax import struct


@struct.dataclass
class EnvState:
    """State of one environment.  ``core`` holds the simulator's own state."""

    core: Any
    obs: jax.Array
    reward: jax.Array
    done: jax.Array
    state_descriptor: jax.Array
    steps: jax.Array


class Env:
    """Interface shared by Point-Maze and the Brax tasks.

    Subclasses define ``observation_size``, ``action_size``, ``descriptor_size``,
    ``episode_length``, ``descriptor_low``/``descriptor_high`` and the three
    functions below.
    """

    observation_size: int
    action_size: int
    descriptor_size: int
    episode_length: int
    descriptor_low: tuple[float, ...]
    descriptor_high: tuple[float, ...]

    def reset(self, key: jax.Array) -> EnvState:
        raise NotImplementedError

    def step(self, state: EnvState, action: jax.Array) -> EnvState:
        raise NotImplementedError

    def behaviour_descriptor(
        self, final_state: EnvState, state_descriptors: jax.Array, valid: jax.Array
    ) -> jax.Array:
        """Behaviour descriptor of an episode.

        ``state_descriptors`` has shape ``(T, d)`` and ``valid`` marks the steps that
        happened before the episode ended.  The default is the final one.
        """
        del state_descriptors, valid
        return final_state.state_descriptor

    @property
    def descriptor_bounds(self) -> tuple[jax.Array, jax.Array]:
        return jnp.asarray(self.descriptor_low), jnp.asarray(self.descriptor_high)
