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


def evaluate_policies(
    env: Env,
    policy_apply: PolicyApply,
    params: Any,
    key: jax.Array,
    return_trajectory: bool = False,
) -> Evaluation:
    """Evaluate a batch of deterministic policies (leading axis of every leaf of
    ``params``), one episode each, each from its own random initial state.

    One ``lax.scan`` over time whose body steps every environment at once
    (``vmap``), as a bare simulation loop would.  The scan keeps the fixed length
    ``env.episode_length``: once an episode is ``done`` the environment keeps
    stepping but nothing it does counts (an ``alive`` flag masks rewards and
    descriptors), which costs less than freezing the state.  Return, length, the
    sum and the last of the state descriptors are accumulated in the carry;
    per-step arrays, with shape ``(batch, time, ...)``, are only stacked when
    ``return_trajectory`` asks (``valid`` marks the steps taken while alive,
    ``terminal`` the ends that are not the time limit, for bootstrapping).
    """
    batch = jax.tree.leaves(params)[0].shape[0]
    states = jax.vmap(env.reset)(jax.random.split(key, batch))

    def one_env(params, carry):
        state, alive, ret, length, sd_sum, last_sd = carry
        action = policy_apply(params, state.obs)
        nxt = env.step(state, action)
        reward = jnp.where(alive, nxt.reward, 0.0)
        carry = (nxt, alive & ~nxt.done, ret + reward, length + alive,
                 sd_sum + jnp.where(alive, nxt.state_descriptor, 0.0),
                 jnp.where(alive, nxt.state_descriptor, last_sd))
        out = None
        if return_trajectory:
            out = {"obs": state.obs, "action": action, "reward": reward, "next_obs": nxt.obs,
                   "done": nxt.done, "terminal": nxt.done & (nxt.steps < env.episode_length),
                   "state_descriptor": nxt.state_descriptor, "valid": alive}
        return carry, out

    step = jax.vmap(one_env)
    init = (states, ~states.done, jnp.zeros((batch,)), jnp.zeros((batch,), jnp.int32),
            jnp.zeros_like(states.state_descriptor), states.state_descriptor)
    (_, _, ret, length, sd_sum, last_sd), traj = jax.lax.scan(lambda c, _: step(params, c), init, None,
                                                                  length=env.episode_length)
    if return_trajectory:
        traj = jax.tree.map(lambda x: jnp.swapaxes(x, 0, 1), traj)
    return Evaluation(
        fitness=ret,
        descriptor=jax.vmap(env.behaviour_descriptor)(last_sd, sd_sum, length),
        length=length,
        trajectory=traj,
    )


def rollout(env: Env, policy_apply: PolicyApply, params: Any, key: jax.Array,
            return_trajectory: bool = False) -> Evaluation:
    """One episode of one policy: ``evaluate_policies`` on a batch of one."""
    batched = evaluate_policies(env, policy_apply, jax.tree.map(lambda x: x[None], params), key, return_trajectory)
    return jax.tree.map(lambda x: x[0], batched)


def evaluate_episodes(
    env: Env,
    policy_apply: PolicyApply,
    params: Any,
    key: jax.Array,
    num_episodes: int,
    return_trajectory: bool = False,
) -> Evaluation:
    """Evaluate each policy of a batch over ``num_episodes`` episodes from
    different initial states, in one vmapped call (the parameters are shared by
    the episodes, not copied).  Leaves have shape ``(batch, num_episodes, ...)``."""
    keys = jax.random.split(key, num_episodes)
    per_episode = jax.vmap(lambda k: evaluate_policies(env, policy_apply, params, k, return_trajectory))(keys)
    return jax.tree.map(lambda x: jnp.swapaxes(x, 0, 1), per_episode)
