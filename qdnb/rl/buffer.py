"""A replay buffer in device memory: fixed-capacity arrays, circular writes."""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import struct


@struct.dataclass
class ReplayBuffer:
    """Transitions ``obs, action, reward, next_obs, terminal`` in circular arrays.

    ``position`` is the next slot written; ``size`` the number of stored
    transitions (at most the capacity).
    """

    data: dict
    position: jax.Array
    size: jax.Array

    @classmethod
    def create(cls, capacity: int, observation_size: int, action_size: int,
               descriptor_size: int = 0) -> "ReplayBuffer":
        """An empty buffer; with ``descriptor_size`` it also stores each
        transition's ``state_descriptor`` (QD-PG's novelty rewards, Eq. 3.5)."""
        data = {
            "obs": jnp.zeros((capacity, observation_size)),
            "action": jnp.zeros((capacity, action_size)),
            "reward": jnp.zeros((capacity,)),
            "next_obs": jnp.zeros((capacity, observation_size)),
            "terminal": jnp.zeros((capacity,)),
        }
        if descriptor_size:
            data["state_descriptor"] = jnp.zeros((capacity, descriptor_size))
        return cls(data, jnp.zeros((), jnp.int32), jnp.zeros((), jnp.int32))

    @property
    def capacity(self) -> int:
        return self.data["reward"].shape[0]

    def add(self, transitions: dict, valid: jax.Array | None = None) -> "ReplayBuffer":
        """Append a batch of transitions (leading axis ``n <= capacity``); those
        with ``valid`` False are skipped, the others are written in order,
        overwriting the oldest once the buffer is full."""
        n = transitions["reward"].shape[0]
        if n > self.capacity:
            raise ValueError(f"cannot add {n} transitions to a buffer of capacity {self.capacity}")
        valid = jnp.ones((n,), bool) if valid is None else valid
        offset = jnp.cumsum(valid) - 1
        target = jnp.where(valid, (self.position + offset) % self.capacity, self.capacity)  # out of range: dropped
        data = {k: v.at[target].set(transitions[k].reshape((n,) + v.shape[1:]), mode="drop")
                for k, v in self.data.items()}
        count = jnp.sum(valid).astype(jnp.int32)
        return ReplayBuffer(data, (self.position + count) % self.capacity, jnp.minimum(self.size + count, self.capacity))

    def add_episodes(self, trajectory: dict, batch_ndim: int) -> "ReplayBuffer":
        """Every valid step of a batch of episodes (``trajectory`` as returned by
        the rollouts: ``batch_ndim`` leading batch axes, then time), with the
        keys this buffer holds."""
        flat = lambda x: x.reshape((-1,) + x.shape[batch_ndim + 1:]).astype(jnp.float32)
        return self.add({k: flat(trajectory[k]) for k in self.data}, trajectory["valid"].reshape(-1))

    def sample(self, key: jax.Array, batch_size: int) -> dict:
        """``batch_size`` transitions drawn uniformly, with replacement, among the stored ones."""
        idx = jax.random.randint(key, (batch_size,), 0, jnp.maximum(self.size, 1))
        return {k: v[idx] for k, v in self.data.items()}
