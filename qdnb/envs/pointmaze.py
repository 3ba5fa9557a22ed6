"""Point-Maze: the deceptive maze of Figure 1.4, in pure JAX.

A point moves in the arena ``[-1, 1]^2``; each action in ``[-1, 1]^2`` is scaled by
0.1.  Two thin horizontal walls make the reward deceptive: the goal sits in the
top-left corner behind both of them, and following the reward (minus the distance
to the goal) leads into dead ends below the walls.

Walls are solid: a move whose segment touches a wall is replaced by its
horizontal part alone, else its vertical part alone, else no move (the point
slides along walls and never crosses one; `tests/test_pointmaze.py` checks it).
"""

from __future__ import annotations

from dataclasses import dataclass

import jax
import jax.numpy as jnp

from qdnb.envs.base import Env, EnvState

# (x_min, x_max, y_min, y_max) of each wall, thickness 0.01.
WALLS = (
    (-1.0, 0.5, 0.20, 0.21),
    (-0.5, 1.0, -0.50, -0.49),
)
GOAL = (-0.5, 0.8)
GOAL_HALF_SIDE = 0.05


def segment_hits_box(p: jax.Array, q: jax.Array, box: jax.Array) -> jax.Array:
    """Whether the segment ``p -> q`` touches the closed box (slab method)."""
    lo = jnp.stack([box[0], box[2]])
    hi = jnp.stack([box[1], box[3]])
    d = q - p
    still = jnp.abs(d) < 1e-12
    safe_d = jnp.where(still, 1.0, d)
    t_a = (lo - p) / safe_d
    t_b = (hi - p) / safe_d
    t_enter = jnp.where(still, -jnp.inf, jnp.minimum(t_a, t_b))
    t_exit = jnp.where(still, jnp.inf, jnp.maximum(t_a, t_b))
    # An axis without motion must already lie inside the slab.
    inside_still = jnp.where(still, (p >= lo) & (p <= hi), True)
    t0 = jnp.maximum(0.0, jnp.max(t_enter))
    t1 = jnp.minimum(1.0, jnp.min(t_exit))
    return jnp.all(inside_still) & (t0 <= t1)


def segment_hits_walls(p: jax.Array, q: jax.Array) -> jax.Array:
    walls = jnp.asarray(WALLS)
    return jnp.any(jax.vmap(segment_hits_box, in_axes=(None, None, 0))(p, q, walls))


def move(p: jax.Array, action: jax.Array, step_size: float = 0.1) -> jax.Array:
    """One move of the point: scaled action, arena clipping, then walls."""
    q = jnp.clip(p + step_size * jnp.clip(action, -1.0, 1.0), -1.0, 1.0)
    q_x = jnp.stack([q[0], p[1]])
    q_y = jnp.stack([p[0], q[1]])
    return jnp.where(
        ~segment_hits_walls(p, q),
        q,
        jnp.where(~segment_hits_walls(p, q_x), q_x, jnp.where(~segment_hits_walls(p, q_y), q_y, p)),
    )


def in_goal(p: jax.Array) -> jax.Array:
    return jnp.all(jnp.abs(p - jnp.asarray(GOAL)) <= GOAL_HALF_SIDE)


@dataclass(frozen=True)
class PointMaze(Env):
    """Point-Maze (Sections 1.5 and 3.6.1).

    Observation = position, behaviour descriptor = final position, state
    descriptor = position, reward = minus the distance to the goal; reaching the
    goal zone (a square of side 0.1 centred on the goal) ends the episode.
    """

    episode_length: int = 200
    step_size: float = 0.1
    observation_size: int = 2
    action_size: int = 2
    descriptor_size: int = 2
    descriptor_low: tuple[float, ...] = (-1.0, -1.0)
    descriptor_high: tuple[float, ...] = (1.0, 1.0)

    def reset(self, key: jax.Array) -> EnvState:
        kx, ky = jax.random.split(key)
        pos = jnp.stack(
            [
                jax.random.uniform(kx, (), minval=-0.1, maxval=0.1),
                jax.random.uniform(ky, (), minval=-1.0, maxval=-0.7),
            ]
        )
        return EnvState(
            core=pos,
            obs=pos,
            reward=jnp.zeros(()),
            done=jnp.zeros((), dtype=bool),
            state_descriptor=pos,
            steps=jnp.zeros((), dtype=jnp.int32),
        )

    def step(self, state: EnvState, action: jax.Array) -> EnvState:
        pos = move(state.core, action, self.step_size)
        steps = state.steps + 1
        return EnvState(
            core=pos,
            obs=pos,
            reward=-jnp.linalg.norm(pos - jnp.asarray(GOAL)),
            done=in_goal(pos) | (steps >= self.episode_length),
            state_descriptor=pos,
            steps=steps,
        )
