"""Playing the QDT in the environment (Algorithm 8's evaluation loop, Figure 4.6).

The QDT is conditioned on a goal descriptor and fed the first observation; the
action it predicts at the ``O_t`` token is played, and the trajectory grows
one timestep at a time.  ``play`` unrolls every (goal, episode) pair of a batch
at once in one ``lax.scan`` over time; with ``cached=True`` (the default) each
step feeds only the new tokens through the transformer, reusing the keys and
values of the earlier ones; with ``cached=False`` it recomputes the whole
prefix every step (the reference the cache is tested and timed against).
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from qdnb.core.evaluation import Evaluation
from qdnb.envs.base import Env
from qdnb.envs.rollout import tally_evaluation, tally_start, tally_step
from qdnb.models.qdt.model import QDT
from qdnb.qd.low_spread import spread


def play(
    env: Env,
    model: QDT,
    params: Any,
    goals: jax.Array,
    key: jax.Array,
    num_episodes: int,
    cached: bool = True,
) -> Evaluation:
    """Condition the QDT on each goal ``(G, d)`` for ``num_episodes`` episodes from
    different initial states; leaves of the result have shape ``(G, E, ...)``
    (``trajectory`` holds the actions played, ``(G, E, T, A)``).  The fitness is
    read as ``evaluate_policies`` reads it (``env.fitness_mode``)."""
    if model.max_steps < env.episode_length:
        raise ValueError(
            f"the QDT knows {model.max_steps} timesteps, the episodes last {env.episode_length}"
        )
    g = goals.shape[0]
    n = g * num_episodes
    bd = jnp.repeat(goals, num_episodes, axis=0)
    states = jax.vmap(env.reset)(jax.random.split(key, n))
    step_env = jax.vmap(env.step)
    horizon = env.episode_length

    if cached:
        memory = model.apply(params, n, method=QDT.init_cache)

        def first(obs, memory):
            return model.apply(params, bd, obs, memory, method=QDT.prefill)

        def next_action(t, prev_action, obs, memory):
            return model.apply(params, bd, prev_action, obs, t, memory, method=QDT.decode_step)
    else:  # the whole trajectory so far, padded to full length (causality hides the padding)
        memory = (
            jnp.zeros((n, horizon, env.observation_size)),
            jnp.zeros((n, horizon, env.action_size)),
        )

        def full(t, obs, memory):
            obs_buf, act_buf = memory
            obs_buf = obs_buf.at[:, t].set(obs)
            action = model.apply(params, bd, obs_buf, act_buf)[:, t]
            return action, (obs_buf, act_buf.at[:, t].set(action))

        first = lambda obs, memory: full(0, obs, memory)
        next_action = lambda t, prev_action, obs, memory: full(t, obs, memory)

    tally_steps = jax.vmap(lambda tally, nxt: tally_step(env, tally, nxt)[0])

    def advance(states, tallies, action):
        nxt = step_env(states, action)
        return nxt, tally_steps(tallies, nxt)

    action0, memory = first(states.obs, memory)
    states, tallies = advance(states, jax.vmap(lambda s: tally_start(env, s))(states), action0)

    def body(carry, t):
        states, tallies, prev_action, memory = carry
        action, memory = next_action(t, prev_action, states.obs, memory)
        return (*advance(states, tallies, action), action, memory), action

    (_, tallies, _, _), actions = jax.lax.scan(
        body, (states, tallies, action0, memory), jnp.arange(1, horizon)
    )
    actions = jnp.concatenate([action0[None], actions]).swapaxes(0, 1)
    return jax.tree.map(
        lambda x: x.reshape((g, num_episodes) + x.shape[1:]),
        tally_evaluation(env, tallies, actions),
    )


def goal_scores(goals: jax.Array, ev: Evaluation) -> dict[str, np.ndarray]:
    """Per goal: mean distance between the goal and the achieved descriptors
    (Section 4.5.2), spread of the achieved descriptors (Eq. 4.1) and mean fitness."""
    distance = jnp.mean(jnp.linalg.norm(ev.descriptor - goals[:, None, :], axis=-1), axis=1)
    return {
        "distance": np.asarray(distance),
        "spread": np.asarray(jax.vmap(spread)(ev.descriptor)),
        "fitness": np.asarray(jnp.mean(ev.fitness, axis=1)),
    }
