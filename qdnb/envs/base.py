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
    # How an episode's fitness is read from its rewards: "return" (their sum) or
    # "max_reward" (the best single reward, Ant-Maze's performance, Section 3.6.1).
    fitness_mode: str = "return"
    # A constant added to an episode's return to give its fitness ("return" mode only):
    # Ant-Omni's survival reward, paid to TD3 at every step, is taken back from the fitness,
    # so that a full episode's fitness is exactly the thesis's Eq. 4.2.
    fitness_shift: float = 0.0

    def reset(self, key: jax.Array) -> EnvState:
        raise NotImplementedError

    def step(self, state: EnvState, action: jax.Array) -> EnvState:
        raise NotImplementedError

    def behaviour_descriptor(
        self, last_state_descriptor: jax.Array, state_descriptor_sum: jax.Array, length: jax.Array
    ) -> jax.Array:
        """Behaviour descriptor of an episode, from the state descriptor of its last
        step, the sum of its state descriptors over the steps taken and the number
        of those steps (final-state and time-averaged descriptors alike, with no
        stored trajectory).  The default is the final state descriptor.
        """
        del state_descriptor_sum, length
        return last_state_descriptor

    @property
    def descriptor_bounds(self) -> tuple[jax.Array, jax.Array]:
        return jnp.asarray(self.descriptor_low), jnp.asarray(self.descriptor_high)
