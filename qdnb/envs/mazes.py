"""Ant-Maze and Ant-Trap: the Brax Ant among walls (Chapter 3, QD-PG, Section 3.6.1,
Tables 3.3 and 3.4).

Both put the current ``brax.envs`` Ant (spring backend by default, any brax
backend can be chosen with ``backend=``) among static walls, into qdnb's ``Env``
interface.  The observation is brax's Ant observation without the torso's
(x, y) (27 values: joint positions from the torso height on, then all
velocities) with the torso (x, y) appended at the end: 29 values, as in the
thesis.  Both state and behaviour descriptors are the torso (x, y), the
behaviour descriptor read at the episode's last step.  An episode ends early
when the torso leaves the height band [0.2, 5] (the ant has flipped over or was
thrown away); brax's own healthy-z termination, survival reward and control cost
are turned off and replaced by the rewards below.

- ``antmaze``: a 45 x 45 square arena, [-5, 40]^2, whose three inner walls
  make a winding path from the start at the origin to the goal at (35, 0),
  behind the first wall.  Reward at each step = -||goal - torso xy||; the
  performance of an episode is its best reward (``fitness_mode = "max_reward"``)
  and the task counts as solved when it exceeds -10.  Episodes last 3000 steps,
  descriptor bounds are the arena.  The reward is deceptive: the greedy
  direction, straight to the goal, runs into the wall x = 20, and the pocket
  below the wall y = 7.5 is a dead end pointing at the goal.
- ``anttrap``: a U-shaped trap of three walls just in front of the ant, open
  towards it.  Reward = forward speed (x_t - x_{t-1}) / dt, fitness = return over
  1000 steps, descriptor = final (x, y) clipped to [0, 30] x [-8, 8] (the state
  descriptor is clipped the same way).  Running forward, the greedy behaviour,
  ends in the trap.

Walls are capsules of radius 0.5 lying on the floor (axis horizontal at height
0.5), given by the end points of their axis (``ANTMAZE_WALLS``,
``ANTTRAP_WALLS``, also ``env.walls``): a wall's solid part extends 0.5 beyond
its segment on every side.  They are real geoms of the MuJoCo model that brax
loads, so collisions are the simulator's own contacts, filtered with MuJoCo's
contype/conaffinity bits so that only the pairs that matter are simulated:

- in brax's ant.xml, the floor has conaffinity 1 and the four feet contype 1
  (4 foot-floor pairs), every other geom has contype = conaffinity = 0;
- walls get contype 0, conaffinity 2; the torso sphere and the four lower-leg
  capsules ("ankle" geoms, which contain the foot spheres) get contype 2.

So a wall collides with the torso and the lower legs only (5 pairs per wall):
not with the floor or other walls (besides, all of them belong to the world
body, whose geoms MuJoCo never collides with each other), and not with the
upper legs, which lie between the torso and the knees (where the lower legs
start), both kept out of the walls: an upper leg can only graze a wall, by a
few centimetres.  The loaded systems have 4 + 5 x 7 = 39 contacts for Ant-Maze
(7 walls: 4 borders, 3 inner) and 4 + 5 x 3 = 19 for Ant-Trap, against 4 for
the bare Ant (one contact per pair, computed at every physics sub-step by
``brax.contact.get``).  With contype = conaffinity = 1 on every geom, Ant-Maze
would have 242 (the ant's own self-collisions included).  On 2 CPU cores, 64
parallel episodes of random actions run at about 15,000 env steps per second
for the bare Ant (spring), 9,000 for Ant-Trap and 5,000 for Ant-Maze.

The system is loaded from brax's ant.xml with the walls added (``mjcf.loads``),
then given what brax's Ant constructor changes for the chosen backend: its
``opt`` (for spring and positional the time step goes from 0.01 to 0.005, for
mjx the solver options) and its actuators (for positional the gear becomes 200).
Brax's Ant keeps its ``n_frames`` (10 sub-steps for spring and positional, 5
otherwise, so dt = 0.05 either way).
"""

from __future__ import annotations

import xml.etree.ElementTree as ElementTree
from dataclasses import dataclass
from typing import ClassVar

import jax
import jax.numpy as jnp
import numpy as np

from qdnb.envs.base import EnvState
from qdnb.envs.locomotion import (
    BraxTask,
    brax_asset,
    brax_env_from_xml,
    brax_observation_size,
    with_collision_bits,
)

Point = tuple[float, float]
Segment = tuple[Point, Point]

WALL_RADIUS = 0.5
WALL_HEIGHT = 0.5  # height of a wall's axis: its capsule touches the floor
WALL_CONTYPE, WALL_CONAFFINITY = 0, 2
# Geoms of brax's ant.xml that walls collide with: the torso and the lower legs.
WALL_COLLIDERS = (
    "torso_geom",
    "left_ankle_geom",
    "right_ankle_geom",
    "third_ankle_geom",
    "fourth_ankle_geom",
)

ANTMAZE_WALLS: tuple[Segment, ...] = (
    ((-5.0, -5.0), (-5.0, 40.0)),  # borders
    ((40.0, -5.0), (40.0, 40.0)),
    ((-5.0, -5.0), (40.0, -5.0)),
    ((-5.0, 40.0), (40.0, 40.0)),
    ((20.0, -4.5), (20.0, 19.5)),  # the wall between the start and the goal
    ((10.5, 7.5), (19.5, 7.5)),
    ((10.0, 20.25), (10.0, 39.75)),
)

ANTTRAP_WALLS: tuple[Segment, ...] = (
    ((12.0, -2.5), (12.0, 2.5)),  # back of the trap
    ((6.5, 3.0), (12.5, 3.0)),  # its two sides, open towards the ant at the origin
    ((6.5, -3.0), (12.5, -3.0)),
)


def ant_xml_with_walls(walls: tuple[Segment, ...]) -> str:
    """Brax's ant.xml with one capsule geom per wall segment in its worldbody, and
    the contype/conaffinity bits that make walls collide with the torso and the
    lower legs only."""
    xml = with_collision_bits(
        brax_asset("ant.xml").read_text(), {name: WALL_CONAFFINITY for name in WALL_COLLIDERS}, {}
    )
    root = ElementTree.fromstring(xml)
    worldbody = root.find("worldbody")
    for i, ((x0, y0), (x1, y1)) in enumerate(walls):
        ElementTree.SubElement(
            worldbody,
            "geom",
            {
                "name": f"wall_{i}",
                "type": "capsule",
                "size": str(WALL_RADIUS),
                "fromto": f"{x0} {y0} {WALL_HEIGHT} {x1} {y1} {WALL_HEIGHT}",
                "contype": str(WALL_CONTYPE),
                "conaffinity": str(WALL_CONAFFINITY),
                "condim": "3",
                "rgba": "0.7 0.5 0.3 1",
            },
        )
    return ElementTree.tostring(root, encoding="unicode")


def brax_ant_with_walls(walls: tuple[Segment, ...], backend: str = "spring"):
    """A brax Ant environment whose system has the given walls.

    Brax's Ant loads ant.xml itself, so its system is replaced by one loaded with
    the walls, to which what the constructor changed for ``backend`` is carried
    over: the simulation options (time step, solver) and the actuators (gear).
    Brax's observation, ``n_frames`` and pipeline are kept; its reward and
    termination are not used.
    """
    return brax_env_from_xml(
        "ant",
        backend,
        ant_xml_with_walls(walls),
        exclude_current_positions_from_observation=True,
        terminate_when_unhealthy=False,
        healthy_reward=0.0,
        ctrl_cost_weight=0.0,
    )


@dataclass(frozen=True, eq=False)
class _WalledAnt(BraxTask):
    """Shared by Ant-Maze and Ant-Trap: the walled system, the 29-value
    observation, the (x, y) descriptors and the height-band termination."""

    walls: ClassVar[tuple[Segment, ...]] = ()
    descriptor_size: int = 2
    healthy_z: tuple[float, float] = (0.2, 5.0)

    def __post_init__(self):
        env = brax_ant_with_walls(self.walls, self.backend)
        object.__setattr__(self, "brax_env", env)
        object.__setattr__(self, "observation_size", brax_observation_size(env) + 2)
        object.__setattr__(self, "action_size", env.action_size)

    def _noise_mask(self) -> np.ndarray:
        mask = np.ones(self.brax_env.sys.q_size(), np.float32)
        mask[3:7] = 0.0  # free joint quaternion
        return mask

    def step(self, state: EnvState, action: jax.Array) -> EnvState:
        nxt = super().step(state, action)
        z = nxt.core.x.pos[0, 2]
        low, high = self.healthy_z
        return nxt.replace(done=nxt.done | (z < low) | (z > high))

    def _obs(self, pipeline_state) -> jax.Array:
        return jnp.concatenate(
            [self.brax_env._get_obs(pipeline_state), pipeline_state.x.pos[0, :2]]
        )

    def _state_descriptor(self, pipeline_state) -> jax.Array:
        return pipeline_state.x.pos[0, :2]  # torso (x, y)

    def behaviour_descriptor(self, last_state_descriptor, state_descriptor_sum, length):
        del state_descriptor_sum, length
        return jnp.clip(
            last_state_descriptor,
            jnp.asarray(self.descriptor_low),
            jnp.asarray(self.descriptor_high),
        )


@dataclass(frozen=True, eq=False)
class AntMaze(_WalledAnt):
    """Ant-Maze (Section 3.6.1): reach ``goal`` behind a wall; performance = the
    best reward -||goal - torso xy|| of the episode."""

    walls: ClassVar[tuple[Segment, ...]] = ANTMAZE_WALLS
    fitness_mode: ClassVar[str] = "max_reward"
    episode_length: int = 3000
    descriptor_low: tuple[float, ...] = (-5.0, -5.0)
    descriptor_high: tuple[float, ...] = (40.0, 40.0)
    goal: tuple[float, float] = (35.0, 0.0)

    def _reward(self, before, after, action) -> jax.Array:
        del before, action
        return -jnp.linalg.norm(jnp.asarray(self.goal) - after.x.pos[0, :2])


@dataclass(frozen=True, eq=False)
class AntTrap(_WalledAnt):
    """Ant-Trap (Section 3.6.1): run forward, past a U-shaped trap open towards
    the ant; fitness = return of the forward speed."""

    walls: ClassVar[tuple[Segment, ...]] = ANTTRAP_WALLS
    fitness_mode: ClassVar[str] = "return"
    episode_length: int = 1000
    descriptor_low: tuple[float, ...] = (0.0, -8.0)
    descriptor_high: tuple[float, ...] = (30.0, 8.0)

    def _reward(self, before, after, action) -> jax.Array:
        del action
        return (after.x.pos[0, 0] - before.x.pos[0, 0]) / self.brax_env.dt

    def _state_descriptor(self, pipeline_state) -> jax.Array:
        """Torso (x, y) clipped to the descriptor box (Section 3.6.1: the open-ended
        Ant-Trap bounds its state descriptors)."""
        return jnp.clip(
            pipeline_state.x.pos[0, :2],
            jnp.asarray(self.descriptor_low),
            jnp.asarray(self.descriptor_high),
        )
