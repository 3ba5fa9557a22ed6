"""Batched policy evaluation: ``vmap`` over policies, ``lax.scan`` over time."""

from __future__ import annotations

from typing import Any, Callable

import jax
import jax.numpy as jnp
from flax import struct

from qdnb.envs.base import Env

PolicyApply = Callable[[Any, jax.Array], jax.Array]


@struct.dataclass
class Evaluation:
    """What one episode (or a batch of them, with leading axes) returns.

    ``fitness`` is the episode return, ``descriptor`` the behaviour descriptor,
    ``length`` the number of steps before the episode ended.  ``trajectory`` is
    ``None`` unless asked for: then a dict of per-step ``obs``, ``action``,
    ``reward``, ``next_obs``, ``done``, ``state_descriptor`` and ``valid``.
    """

    fitness: jax.Array
    descriptor: jax.Array
    length: jax.Array
    trajectory: Any = None


def rollout(
    env: Env,
    policy_apply: PolicyApply,
    params: Any,
    key: jax.Array,
    return_trajectory: bool = False,
) -> Evaluation:
    """Play one episode of a deterministic policy from a random initial state.

    Once ``done``, the state is frozen and later steps are marked invalid, so the
    scan keeps a fixed length (``env.episode_length``) and stays jittable.
    """
    state = env.reset(key)

    def step(state, _):
        action = policy_apply(params, state.obs)
        nxt = env.step(state, action)
        valid = ~state.done
        nxt = jax.tree.map(lambda old, new: jnp.where(state.done, old, new), state, nxt)
        out = {"valid": valid, "reward": jnp.where(valid, nxt.reward, 0.0),
               "state_descriptor": nxt.state_descriptor}
        if return_trajectory:
            out.update(obs=state.obs, action=action, next_obs=nxt.obs, done=nxt.done)
        return nxt, out

    final, traj = jax.lax.scan(step, state, None, length=env.episode_length)
    descriptor = env.behaviour_descriptor(final, traj["state_descriptor"], traj["valid"])
    return Evaluation(
        fitness=jnp.sum(traj["reward"]),
        descriptor=descriptor,
        length=jnp.sum(traj["valid"]),
        trajectory=traj if return_trajectory else None,
    )


def evaluate_policies(
    env: Env,
    policy_apply: PolicyApply,
    params: Any,
    key: jax.Array,
    return_trajectory: bool = False,
) -> Evaluation:
    """Evaluate a batch of policies (leading axis of every leaf of ``params``),
    one episode each, each from its own random initial state."""
    batch = jax.tree.leaves(params)[0].shape[0]
    keys = jax.random.split(key, batch)
    return jax.vmap(lambda p, k: rollout(env, policy_apply, p, k, return_trajectory))(params, keys)
