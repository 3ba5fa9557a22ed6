"""A replay buffer in device memory: fixed-capacity arrays, circular writes."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
from flax import struct


@struct.dataclass
class ReplayBuffer:
    """Transitions ``obs, action, reward, next_obs, terminal`` in a circular store.

    The fields of a transition are packed side by side in one row of
    ``storage`` (``capacity x width``; ``fields`` names each field's shape), so
    that a sampled transition is one contiguous row: a batch drawn from a large
    buffer costs one random read per transition instead of one per field (about
    8x faster on CPU once the buffer outgrows the caches).  ``data`` gives the
    fields as a dict.  ``position`` is the next slot written; ``size`` the
    number of stored transitions (at most the capacity).
    """

    storage: jax.Array
    position: jax.Array
    size: jax.Array
    fields: tuple = struct.field(pytree_node=False, default=())

    @classmethod
    def create(
        cls, capacity: int, observation_size: int, action_size: int, descriptor_size: int = 0
    ) -> "ReplayBuffer":
        """An empty buffer; with ``descriptor_size`` it also stores each
        transition's ``state_descriptor`` (QD-PG's novelty rewards, Eq. 3.5)."""
        fields = [
            ("obs", (observation_size,)),
            ("action", (action_size,)),
            ("reward", ()),
            ("next_obs", (observation_size,)),
            ("terminal", ()),
        ]
        if descriptor_size:
            fields.append(("state_descriptor", (descriptor_size,)))
        width = sum(math.prod(shape) for _, shape in fields)
        return cls(
            jnp.zeros((capacity, width)),
            jnp.zeros((), jnp.int32),
            jnp.zeros((), jnp.int32),
            tuple(fields),
        )

    @property
    def capacity(self) -> int:
        return self.storage.shape[0]

    def _unpack(self, rows: jax.Array) -> dict:
        out, start = {}, 0
        for name, shape in self.fields:
            width = math.prod(shape)
            out[name] = rows[..., start : start + width].reshape(rows.shape[:-1] + shape)
            start += width
        return out

    @property
    def data(self) -> dict:
        """Every slot's fields, as a dict of arrays with a leading capacity axis."""
        return self._unpack(self.storage)

    def add(self, transitions: dict, valid: jax.Array | None = None) -> "ReplayBuffer":
        """Append a batch of transitions (leading axis ``n <= capacity``); those
        with ``valid`` False are skipped, the others are written in order,
        overwriting the oldest once the buffer is full."""
        n = transitions["reward"].shape[0]
        if n > self.capacity:
            raise ValueError(f"cannot add {n} transitions to a buffer of capacity {self.capacity}")
        valid = jnp.ones((n,), bool) if valid is None else valid
        offset = jnp.cumsum(valid) - 1
        target = jnp.where(
            valid, (self.position + offset) % self.capacity, self.capacity
        )  # out of range: dropped
        rows = jnp.concatenate(
            [
                transitions[name].reshape(n, -1).astype(self.storage.dtype)
                for name, _ in self.fields
            ],
            axis=1,
        )
        storage = self.storage.at[target].set(rows, mode="drop")
        count = jnp.sum(valid).astype(jnp.int32)
        return self.replace(
            storage=storage,
            position=(self.position + count) % self.capacity,
            size=jnp.minimum(self.size + count, self.capacity),
        )

    def add_episodes(self, trajectory: dict, batch_ndim: int) -> "ReplayBuffer":
        """Every valid step of a batch of episodes (``trajectory`` as returned by
        the rollouts: ``batch_ndim`` leading batch axes, then time), with the
        keys this buffer holds."""
        flat = lambda x: x.reshape((-1,) + x.shape[batch_ndim + 1 :]).astype(jnp.float32)
        return self.add(
            {name: flat(trajectory[name]) for name, _ in self.fields},
            trajectory["valid"].reshape(-1),
        )

    def sample(self, key: jax.Array, batch_size: int) -> dict:
        """``batch_size`` transitions drawn uniformly, with replacement, among the stored ones."""
        idx = jax.random.randint(key, (batch_size,), 0, jnp.maximum(self.size, 1))
        return self._unpack(self.storage[idx])
