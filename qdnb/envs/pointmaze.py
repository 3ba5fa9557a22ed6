"""Point-Maze: the deceptive maze of Figure 1.4, in pure JAX.

A point moves in the arena ``[-1, 1]^2``; each action in ``[-1, 1]^2`` is scaled by
0.1.  Two thin horizontal walls make the reward deceptive: the goal sits in the
top-left corner behind both of them, and following the reward (minus the distance
to the goal) leads into dead ends below the walls.

Walls follow QDax's Point-Maze (``qdax/environments/pointmaze.py``, the task
the thesis ran): a move whose vertical part crosses a wall's face (at an x
inside the wall) keeps its horizontal part and stops on that face, so the point
slides along the wall; then the arena clips it.  One case the reference leaves
open is closed here: a move that enters a wall through its 0.01-thick end
(which the reference lets through) drops its horizontal part.  The point never crosses a wall
(`tests/test_pointmaze.py` checks both).
"""

from __future__ import annotations

from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from qdnb.envs.base import Env, EnvState

# (x_min, x_max, y_min, y_max) of each wall, thickness 0.01.
WALLS = (
    (-1.0, 0.5, 0.20, 0.21),
    (-0.5, 1.0, -0.50, -0.49),
)
GOAL = (-0.5, 0.8)
GOAL_HALF_SIDE = 0.05


def stop_on_faces(p: jax.Array, q: jax.Array) -> jax.Array:
    """The end of the move ``p -> q`` once walls stop its vertical part: if the
    segment crosses a wall's lower face going up (or its upper face going
    down) at an x within the wall, the end's y is set to that face and its x is
    kept (QDax's collision rule, for every wall).  A wall that meets the
    arena's border extends beyond it, as in the reference, so that a move
    leaving the arena cannot pass round the wall's end before the clip."""
    y = q[1]
    dy = jnp.where(q[1] == p[1], 1.0, q[1] - p[1])
    for x0, x1, lo, hi in WALLS:
        x0, x1 = (-jnp.inf if x0 <= -1.0 else x0), (jnp.inf if x1 >= 1.0 else x1)
        for face, crossing in ((lo, (p[1] <= lo) & (q[1] > lo)), (hi, (p[1] >= hi) & (q[1] < hi))):
            x_at_face = p[0] + (face - p[1]) / dy * (q[0] - p[0])
            y = jnp.where(crossing & (x_at_face >= x0) & (x_at_face <= x1), face, y)
    return jnp.stack([q[0], y])


def inside_a_wall(p: jax.Array) -> jax.Array:
    """Whether ``p`` lies strictly inside a wall."""
    return jnp.any(
        jnp.stack(
            [(p[0] > x0) & (p[0] < x1) & (p[1] > lo) & (p[1] < hi) for x0, x1, lo, hi in WALLS]
        )
    )


def crosses_an_end(p: jax.Array, q: jax.Array) -> jax.Array:
    """Whether the segment ``p -> q`` enters a wall through its end inside the
    arena (crossing the line x = end strictly between the wall's faces)."""
    hits = []
    dx = jnp.where(q[0] == p[0], 1.0, q[0] - p[0])
    for x0, x1, lo, hi in WALLS:
        for end in [e for e in (x0, x1) if -1.0 < e < 1.0]:
            y_at_end = p[1] + (end - p[0]) / dx * (q[1] - p[1])
            crossing = ((p[0] <= end) & (q[0] > end)) | ((p[0] >= end) & (q[0] < end))
            hits.append(crossing & (y_at_end > lo) & (y_at_end < hi))
    return jnp.any(jnp.stack(hits))


def move(p: jax.Array, action: jax.Array, step_size: float = 0.1) -> jax.Array:
    """One move of the point: scaled action, walls, then arena clipping."""
    q = stop_on_faces(p, p + step_size * jnp.clip(action, -1.0, 1.0))
    q = jnp.where(crosses_an_end(p, q), jnp.stack([p[0], q[1]]), q)
    return jnp.clip(q, -1.0, 1.0)


def maze_regions(points, tolerance: float = 1e-6) -> dict:
    """Boolean masks of ``points`` (... x 2, NumPy) in the maze's regions:
    below the lower wall, between the walls, the right-hand passage past the
    upper wall's end (between the walls, x > its end) and above the upper wall
    (where the goal is).  A point stopped on a wall's face lies on that face's
    side (on the upper wall's lower face: between the walls); ``tolerance``
    absorbs float32 positions on a face."""
    points = np.asarray(points)
    x, y = points[..., 0], points[..., 1]
    (_, upper_x1, upper_lo, upper_hi), (_, _, lower_lo, lower_hi) = WALLS
    between = (y > lower_hi - tolerance) & (y < upper_lo + tolerance)
    return {
        "below the lower wall": y < lower_lo + tolerance,
        "between the walls": between,
        "right-hand passage (x > 0.5, between the walls)": between & (x > upper_x1),
        "above the upper wall": y > upper_hi - tolerance,
    }


FACE_OFFSET = 1e-3  # how far off its face a stopped point's behaviour descriptor is put


def off_the_faces(p: jax.Array, tolerance: float = 1e-6) -> jax.Array:
    """``p`` (last axis: x, y) with every point that lies on a wall's face moved
    ``FACE_OFFSET`` off it, to the side it is on (a point stopped on a wall's lower
    face stays below the wall).  A face can lie on a grid's cell edge (the upper
    wall's lower face, y = 0.2, is one of the 5 x 5 grid's): without this, float
    rounding decides whether a point stopped under the wall is filed in the cell
    above it."""
    x, y = p[..., 0], p[..., 1]
    for x0, x1, lo, hi in WALLS:
        along = (x >= x0) & (x <= x1)
        y = jnp.where(along & (jnp.abs(y - lo) < tolerance), lo - FACE_OFFSET, y)
        y = jnp.where(along & (jnp.abs(y - hi) < tolerance), hi + FACE_OFFSET, y)
    return jnp.stack([x, y], axis=-1)


def reachable(points) -> np.ndarray:
    """Whether each point (NumPy, last axis: x, y) can be reached: in the arena and
    not strictly inside a wall (the maze is connected)."""
    points = np.asarray(points)
    x, y = points[..., 0], points[..., 1]
    inside = np.zeros(points.shape[:-1], bool)
    for x0, x1, lo, hi in WALLS:
        inside |= (x > x0) & (x < x1) & (y > lo) & (y < hi)
    return (np.abs(x) <= 1.0) & (np.abs(y) <= 1.0) & ~inside


def in_goal(p: jax.Array) -> jax.Array:
    """Whether each position (last axis: x, y) lies in the goal square."""
    return jnp.all(jnp.abs(p - jnp.asarray(GOAL)) <= GOAL_HALF_SIDE, axis=-1)


@dataclass(frozen=True)
class PointMaze(Env):
    """Point-Maze (Sections 1.5 and 3.6.1).

    Observation = position, behaviour descriptor = final position (moved 10^-3 off
    a wall's face it stopped on, to its side: ``off_the_faces``), state
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

    def behaviour_descriptor(self, last_state_descriptor, state_descriptor_sum, length):
        del state_descriptor_sum, length
        return off_the_faces(last_state_descriptor)

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
