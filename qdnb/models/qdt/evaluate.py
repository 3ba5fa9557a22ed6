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

from dataclasses import dataclass
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from qdnb.core.evaluation import Evaluation
from qdnb.envs.base import Env
from qdnb.envs.rollout import tally_evaluation, tally_start, tally_step
from qdnb.models.qdt.data import Selection, Trajectories
from qdnb.models.qdt.model import QDT, TOKENS_PER_STEP
from qdnb.qd.low_spread import spread

# of the device's memory, for one group of rollouts' cache.  XLA's working memory for the
# rollouts is 1.26 times their cache (compiled for 100 and 200 Ant-Omni rollouts at paper on
# CPU), and the datasets and models share the memory with it
CACHE_SHARE = 1 / 8


def play(
    env: Env,
    model: QDT,
    params: Any,
    goals: jax.Array,
    key: jax.Array,
    num_episodes: int,
    cached: bool = True,
    chunks: int = 1,
) -> Evaluation:
    """Condition the QDT on each goal ``(G, d)`` for ``num_episodes`` episodes from
    different initial states; leaves of the result have shape ``(G, E, ...)``
    (``trajectory`` holds the actions played, ``(G, E, T, A)``).  The fitness is
    read as ``evaluate_policies`` reads it (``env.fitness_mode``).  ``chunks`` (a
    divisor of ``G``) plays the goals in that many groups one after another, each with
    its own cache (``rollout_chunks``): the same episodes from the same initial states,
    in ``1 / chunks`` of the memory."""
    if model.max_steps < env.episode_length:
        raise ValueError(
            f"the QDT knows {model.max_steps} timesteps, the episodes last {env.episode_length}"
        )
    g = goals.shape[0]
    if chunks < 1 or g % chunks:
        raise ValueError(f"chunks must divide the {g} goals, not {chunks}")
    n = g * num_episodes
    bd = jnp.repeat(goals, num_episodes, axis=0)  # a goal's episodes side by side
    states = jax.vmap(env.reset)(jax.random.split(key, n))
    if chunks == 1:
        ev = _unroll(env, model, params, bd, states, cached)
    else:  # contiguous groups of whole goals, one lax.map iteration each
        group = lambda x: x.reshape((chunks, n // chunks) + x.shape[1:])
        ev = jax.lax.map(
            lambda a: _unroll(env, model, params, *a, cached),
            (group(bd), jax.tree.map(group, states)),
        )
        ev = jax.tree.map(lambda x: x.reshape((n,) + x.shape[2:]), ev)
    return jax.tree.map(lambda x: x.reshape((g, num_episodes) + x.shape[1:]), ev)


def _unroll(env: Env, model: QDT, params: Any, bd: jax.Array, states: Any, cached: bool):
    """The episodes of ``bd``'s rows from ``states``, one ``lax.scan`` over time."""
    n = bd.shape[0]
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
    return tally_evaluation(env, tallies, actions)


def cache_bytes(model: QDT, rollouts: int) -> int:
    """The key-value cache of ``rollouts`` episodes played at once (float32)."""
    per_rollout = 2 * model.num_layers * TOKENS_PER_STEP * model.max_steps * model.embed_dim
    return 4 * per_rollout * rollouts


def rollout_chunks(model: QDT, num_goals: int, num_episodes: int, memory_bytes: int) -> int:
    """The fewest groups (a divisor of ``num_goals``) the goals are played in so that
    one group's cache takes at most ``CACHE_SHARE`` of ``memory_bytes`` (the device's):
    one group at ``tiny`` and ``small``, and on a GPU at ``paper``; on a 24 GB CPU at
    ``paper``, the 100 Ant-Omni goals x 10 episodes' 6.1 GB cache goes in 2 groups."""
    for chunks in range(1, num_goals + 1):
        if (
            num_goals % chunks == 0
            and cache_bytes(model, num_goals // chunks * num_episodes) <= CACHE_SHARE * memory_bytes
        ):
            return chunks
    return num_goals


def goal_scores(goals: jax.Array, ev: Evaluation) -> dict[str, np.ndarray]:
    """Per goal: mean distance between the goal and the achieved descriptors
    (Section 4.5.2), spread of the achieved descriptors (Eq. 4.1) and mean fitness."""
    distance = jnp.mean(jnp.linalg.norm(ev.descriptor - goals[:, None, :], axis=-1), axis=1)
    return {
        "distance": np.asarray(distance),
        "spread": np.asarray(jax.vmap(spread)(ev.descriptor)),
        "fitness": np.asarray(jnp.mean(ev.fitness, axis=1)),
    }


# ----- does the QDT imitate its demonstrators? -----


@dataclass(frozen=True)
class Targets:
    """One target per zone: the BD its demonstrator reaches on average over its
    dataset episodes (``padded``, ``(zones, d)``; the box's centre where the zone has
    no demonstrator, ``valid`` false), and the demonstrator's own mean distance to it
    (``distance``, NaN where none): how well the QDT could imitate it."""

    padded: jax.Array
    distance: np.ndarray

    @property
    def valid(self) -> np.ndarray:
        return ~np.isnan(self.distance)


def demonstrator_targets(data: Trajectories, selection: Selection, num_zones: int, box) -> Targets:
    """``Targets`` of the demonstrators ``selection`` kept, from their episodes in
    ``data`` (recorded by ``record`` from ``selection.cells``)."""
    low, high = (np.asarray(b, np.float32) for b in box)
    padded = np.tile((low + high) / 2, (num_zones, 1))
    distance = np.full(num_zones, np.nan)
    bd, policy = np.asarray(data.bd), np.asarray(data.policy)
    for cell, zone in zip(selection.cells, selection.zones):
        mine = bd[policy == cell]
        padded[zone] = mine.mean(axis=0)
        distance[zone] = np.linalg.norm(mine - padded[zone], axis=-1).mean()
    return Targets(jnp.asarray(padded), distance)


def imitation(targets: Targets, ev: Evaluation) -> np.ndarray:
    """Per zone, the mean distance between the target and the BDs the QDT reached
    when conditioned on it (``ev`` from ``play`` on ``targets.padded``); NaN where the
    zone has no demonstrator."""
    d = np.asarray(jnp.mean(jnp.linalg.norm(ev.descriptor - targets.padded[:, None], axis=-1), 1))
    return np.where(targets.valid, d, np.nan)
