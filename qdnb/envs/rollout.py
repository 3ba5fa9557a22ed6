"""Batched policy evaluation: ``vmap`` over policies, ``lax.scan`` over time."""

from __future__ import annotations

from typing import Any, Callable

import jax
import jax.numpy as jnp
from flax import struct

from qdnb.core.evaluation import Evaluation
from qdnb.core.sharding import shard_batch
from qdnb.envs.base import Env, EnvState

PolicyApply = Callable[[Any, jax.Array], jax.Array]


def evaluate_policies(
    env: Env,
    policy_apply: PolicyApply,
    params: Any,
    key: jax.Array,
    return_trajectory: bool = False,
    exploration_noise: jax.Array | float = 0.0,
    stochastic: bool = False,
) -> Evaluation:
    """Evaluate a batch of policies (leading axis of every leaf of ``params``; each
    deterministic unless ``stochastic``), one episode each, each from its own random
    initial state.

    One ``lax.scan`` over time whose body steps every environment at once
    (``vmap``), as a bare simulation loop would.  The scan keeps the fixed length
    ``env.episode_length``: once an episode is ``done`` the environment keeps
    stepping but nothing it does counts (an ``alive`` flag masks rewards and
    descriptors), which costs less than freezing the state.  Return, length, the
    sum and the last of the state descriptors are accumulated in a ``Tally``;
    per-step arrays, with shape ``(batch, time, ...)``, are only stacked when
    ``return_trajectory`` asks (``valid`` marks the steps taken while alive,
    ``terminal`` the ends that are not the time limit, for bootstrapping).

    ``exploration_noise`` (a scalar or one value per policy) adds Gaussian noise
    of that standard deviation to the actions (TD3's exploration), drawn from a
    key per episode folded with the step number.

    ``stochastic`` policies are keyed: ``policy_apply(params, obs, key)`` samples an
    action with a key of its own at every step (SAC's, DIAYN's and AGAC's actors),
    drawn from the same per-episode key as the exploration noise.
    """
    batch = jax.tree.leaves(params)[0].shape[0]
    k_reset, k_noise = jax.random.split(key)
    states = jax.vmap(env.reset)(
        jax.random.split(k_reset if stochastic or _noisy(exploration_noise) else key, batch)
    )
    sigma = jnp.broadcast_to(jnp.asarray(exploration_noise, jnp.float32), (batch,))
    noise_keys = jax.random.split(k_noise, batch)
    # the population over every local device (nothing changes on one device)
    params, states, sigma, noise_keys = shard_batch((params, states, sigma, noise_keys))

    def one_env(params, sigma, noise_key, carry):
        state, tally = carry
        if stochastic:
            step_key = jax.random.split(jax.random.fold_in(noise_key, state.steps))[1]
            action = policy_apply(params, state.obs, step_key)
        else:
            action = policy_apply(params, state.obs)
        if _noisy(exploration_noise):
            noise = jax.random.normal(jax.random.fold_in(noise_key, state.steps), action.shape)
            action = jnp.clip(action + sigma * noise, -1.0, 1.0)
        nxt = env.step(state, action)
        new_tally, reward = tally_step(env, tally, nxt)
        out = None
        if return_trajectory:
            out = {
                "obs": state.obs,
                "action": action,
                "reward": reward,
                "next_obs": nxt.obs,
                "done": nxt.done,
                "terminal": nxt.done & (nxt.steps < env.episode_length),
                "state_descriptor": state.state_descriptor,
                "next_state_descriptor": nxt.state_descriptor,
                "valid": tally.alive,
            }
        return (nxt, new_tally), out

    step = jax.vmap(one_env)
    init = (states, jax.vmap(lambda s: tally_start(env, s))(states))
    (_, tally), traj = jax.lax.scan(
        lambda c, _: step(params, sigma, noise_keys, c), init, None, length=env.episode_length
    )
    if return_trajectory:
        traj = jax.tree.map(lambda x: jnp.swapaxes(x, 0, 1), traj)
    return tally_evaluation(env, tally, traj)


@struct.dataclass
class Tally:
    """What one episode accumulates while it plays: whether it is still
    ``alive`` (not yet done), its fitness so far, its length, and, for
    ``env.behaviour_descriptor``, the last of its state descriptors and the sum of
    those of the states its steps started from: QDax's window for time-averaged
    descriptors (its transitions carry the state before the step), the reset
    state included and the final state not."""

    alive: jax.Array
    fitness: jax.Array
    length: jax.Array
    sd_sum: jax.Array
    last_sd: jax.Array


def tally_start(env: Env, state: EnvState) -> Tally:
    """The tally of one episode before its first step."""
    fitness = -jnp.inf if env.fitness_mode == "max_reward" else 0.0
    return Tally(
        alive=~state.done,
        fitness=jnp.asarray(fitness, jnp.float32),
        length=jnp.zeros((), jnp.int32),
        sd_sum=jnp.zeros_like(state.state_descriptor),
        last_sd=state.state_descriptor,
    )


def tally_step(env: Env, tally: Tally, nxt: EnvState) -> tuple[Tally, jax.Array]:
    """Count one step of one episode that led to ``nxt``; steps after the episode
    ended count for nothing.  Returns the tally and the (masked) reward."""
    alive = tally.alive
    reward = jnp.where(alive, nxt.reward, 0.0)
    fitness = (
        jnp.where(alive, jnp.maximum(tally.fitness, nxt.reward), tally.fitness)
        if env.fitness_mode == "max_reward"
        else tally.fitness + reward
    )
    return Tally(
        alive=alive & ~nxt.done,
        fitness=fitness,
        length=tally.length + alive,
        sd_sum=tally.sd_sum + jnp.where(alive, tally.last_sd, 0.0),
        last_sd=jnp.where(alive, nxt.state_descriptor, tally.last_sd),
    ), reward


def tally_evaluation(env: Env, tally: Tally, trajectory: Any = None) -> Evaluation:
    """The ``Evaluation`` of a batch of finished tallies."""
    fitness = tally.fitness + env.fitness_shift if env.fitness_mode == "return" else tally.fitness
    return Evaluation(
        fitness=fitness,
        descriptor=jax.vmap(env.behaviour_descriptor)(tally.last_sd, tally.sd_sum, tally.length),
        length=tally.length,
        trajectory=trajectory,
    )


def _noisy(exploration_noise) -> bool:
    """Whether exploration noise is asked for (a traced array always counts)."""
    return not (isinstance(exploration_noise, (int, float)) and exploration_noise == 0.0)


def rollout(
    env: Env,
    policy_apply: PolicyApply,
    params: Any,
    key: jax.Array,
    return_trajectory: bool = False,
) -> Evaluation:
    """One episode of one policy: ``evaluate_policies`` on a batch of one."""
    batched = evaluate_policies(
        env, policy_apply, jax.tree.map(lambda x: x[None], params), key, return_trajectory
    )
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
    per_episode = jax.vmap(
        lambda k: evaluate_policies(env, policy_apply, params, k, return_trajectory)
    )(keys)
    return jax.tree.map(lambda x: jnp.swapaxes(x, 0, 1), per_episode)
