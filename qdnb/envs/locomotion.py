"""Brax locomotion tasks of Chapter 4: Ant-Omni and Halfcheetah-Uni (Section 4.3.1).

Both wrap the current ``brax.envs`` Ant and HalfCheetah (spring backend by
default: the fastest on CPU here; any brax backend can be chosen) into qdnb's
``Env`` interface, with 250-step episodes and the thesis's own fitness and
behaviour descriptor:

- ``ant_omni``: descriptor = final torso (x, y) clipped to the descriptor box
  (``descriptor_low``/``descriptor_high``: [-15, 15]^2 in the thesis, a smaller
  measured box at small scales), fitness -sum_t ||a_t||_2 (Eq. 4.2) for an episode
  that lasts its 250 steps; see the survival reward below for one that ends early.
- ``halfcheetah_uni``: descriptor = fraction of steps each foot (front, back,
  QDax's order) touches the ground, reward = (x_t - x_{t-1}) / dt - ||a_t||_2
  (Eq. 4.3).  A foot touches the ground in a step when it touched it in any of
  the step's 16 physics substeps, as QDax reads brax v1's contact impulse summed
  over the substeps: at the start of a substep (the positions whose contacts that
  substep resolves) the foot's capsule reaches below the floor.  Read once, at the
  end of the step, half of the touches were missed (the feet are in contact a
  median 7 of 16 substeps).  The fraction is QDax's: the mean over the states each
  step starts from, the reset included and the last state not
  (``qdnb.envs.rollout.Tally``).

Where the thesis is silent, the tasks follow the QDax tasks the thesis ran
(``ant_omni`` and ``halfcheetah_uni`` of ``qdax/tasks/brax/v1``, on brax v1's Ant
and Halfcheetah):

- **termination**: an Ant-Omni episode ends when the torso's height leaves the
  healthy band [0.2, 1.0] (brax's ``healthy_z_range``: the ant flipped or
  jumped); its descriptor is then where it was at that step.  Halfcheetah-Uni
  never ends early.
- **survival reward**: brax's Ant, which QDax's ``ant_omni`` keeps (it removes
  only the forward term), pays 1 per step alive.  Without it, termination would
  reward falling: -sum ||a_t|| over fewer steps is a higher fitness, and on the
  spring pipeline more than half of the elites' episodes ended early that way
  (``bench/probes/ant_omni_termination.py``), against the thesis's "an optimal policy
  would simply remain static".  So the step reward is 1 - ||a_t||_2 (what TD3
  learns from, as in QDax) and the fitness takes the constant 250 back
  (``fitness_shift``): Eq. 4.2 exactly for a full episode, Eq. 4.2 minus one per
  step not lived for one that ends early.
- **initial states** (``QDaxReset``): brax v1's ``default_qp``: every limited
  hinge at the middle of its range, then each hinge's angle and velocity moved by
  U(-0.1, 0.1), the free (Ant) or planar (Halfcheetah) root joint at rest, and the
  robot lowered (or raised) so that its lowest point that collides with the floor
  rests on it.  brax 0.14's models instead start from a keyframe in the air (the
  Ant's torso at 0.55 m, the Halfcheetah's at 0.7 m) and drop.
- **the models** (``qdax_ant``, ``qdax_halfcheetah``): brax 0.14's ant.xml and
  half_cheetah.xml, edited towards brax v1's configs (the ones QDax ran):

  - which bodies collide: v1's Halfcheetah collides the floor with the torso
    (both its capsules), the thighs, the shins and the feet, and the two feet with
    each other (9 pairs, against brax 0.14's 5: head, thighs, feet); v1's Ant the
    floor with the torso and the four feet (5 pairs, against 4: the feet);
  - the Halfcheetah's motor gears are v1's [120, 90, 60, 120, 60, 30] (the XML's
    own), not the [120, 90, 60, 120, 100, 100] brax 0.14 sets for its spring
    pipeline;
  - what stays different: the simulator (v1's position-based dynamics, "pbd",
    against 0.14's ``spring``, the fastest pipeline on CPU here), and the Ant's
    masses and gears (v1: 18 kg, gear 350; brax 0.14's ant.xml: 0.9 kg from its
    geoms' density, gear 150): v1's gear on 0.14's light ant would be a different
    robot, so the Ant keeps brax 0.14's.  ``bench/probes/halfcheetah_probe.py`` measures
    what the changes do to the starting policies' descriptors.
- **observations**: the torso's height, orientation and velocities, the joint
  angles and velocities, and not the torso's x, y (brax's
  ``exclude_current_positions_from_observation``): 27 numbers for the Ant,
  17 for the Halfcheetah (brax v1 gives it 18: the pitch as two quaternion
  components instead of one angle).

Chapter 3's ant mazes (``qdnb.envs.mazes``) keep ``BraxTask``'s own Gaussian
reset (``reset_noise`` on positions and velocities), as their reference code does.
"""

from __future__ import annotations

import contextlib
import importlib.util
import io
import os
import threading
import warnings
import xml.etree.ElementTree as ElementTree
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from qdnb.envs.base import Env, EnvState

_QUIET_LOCK = threading.Lock()


@contextlib.contextmanager
def _quiet():
    """Silence what brax and MuJoCo print while loading a model: brax's notice
    that it is no longer maintained, its failed optional ``warp`` import, and
    MuJoCo's (C-level) deprecation warning about the model's ``settotalmass``.
    Exceptions still propagate.  The swap of the process's file descriptors is
    serialised, so that models loaded from several threads at once cannot leave
    stdout or stderr pointing at ``/dev/null``."""
    with (
        _QUIET_LOCK,
        warnings.catch_warnings(),
        contextlib.redirect_stdout(io.StringIO()),
        contextlib.redirect_stderr(io.StringIO()),
    ):
        warnings.filterwarnings("ignore", message="Brax System", category=UserWarning)
        saved = [os.dup(fd) for fd in (1, 2)]
        null = os.open(os.devnull, os.O_WRONLY)
        try:
            for fd in (1, 2):
                os.dup2(null, fd)
            yield
        finally:
            for fd, old in zip((1, 2), saved):
                os.dup2(old, fd)
                os.close(old)
            os.close(null)


def _brax_env(name: str, backend: str, **kwargs):
    with _quiet():
        from brax import envs

        return envs.get_environment(name, backend=backend, **kwargs)


def brax_asset(name: str) -> Path:
    """Path of one of brax's model files, found without importing brax (whose
    import prints notices)."""
    return Path(importlib.util.find_spec("brax").origin).parent / "envs" / "assets" / name


def with_collision_bits(xml: str, contype: dict[str, int], conaffinity: dict[str, int]) -> str:
    """An MJCF model with the given bits OR-ed into the named geoms' ``contype`` and
    ``conaffinity`` (MuJoCo collides two geoms when one's contype shares a bit with
    the other's conaffinity); a name the model lacks is an error."""
    root = ElementTree.fromstring(xml)
    geoms = {g.get("name"): g for g in root.iter("geom")}
    for attribute, bits in (("contype", contype), ("conaffinity", conaffinity)):
        for name, bit in bits.items():
            if name not in geoms:
                raise ValueError(f"the model has no geom {name!r}")
            geom = geoms[name]
            geom.set(attribute, str(int(geom.get(attribute, "0")) | bit))
    return ElementTree.tostring(root, encoding="unicode")


def brax_env_from_xml(name: str, backend: str, xml: str, keep_actuators: bool = True, **kwargs):
    """brax's environment ``name`` (its observation, ``n_frames`` and pipeline) on
    the system loaded from ``xml`` (an edit of its own model), with what its
    constructor changed for ``backend`` carried over: the simulation options (time
    step, solver) and, if ``keep_actuators``, the actuators (the gears it sets)."""
    env = _brax_env(name, backend, **kwargs)
    with _quiet():
        from brax.io import mjcf

        sys = mjcf.loads(xml)
    carried = {"opt": env.sys.opt}
    if keep_actuators:
        carried["actuator"] = env.sys.actuator
    env.sys = sys.tree_replace(carried)
    return env


def floor_colliders(mj_model) -> np.ndarray:
    """The geoms that collide with the floor (the model's plane)."""
    floor = int(np.flatnonzero(mj_model.geom_type == 0)[0])
    contype, conaffinity = mj_model.geom_contype, mj_model.geom_conaffinity
    hits = (contype & conaffinity[floor]) | (conaffinity & contype[floor])
    return np.flatnonzero((hits != 0) & (np.arange(mj_model.ngeom) != floor))


def geom_bottoms(mj_model, geoms: np.ndarray, x) -> jax.Array:
    """The height of the lowest point of each of the sphere or capsule ``geoms``
    (MuJoCo ids), for the link transforms ``x`` of a brax state: the centre's
    height, less the capsule's half-length along its axis's vertical part, less
    the radius.  Negative below the floor."""
    from brax import math

    link = mj_model.geom_bodyid[geoms] - 1  # brax's links are the bodies but the world
    half = np.where(mj_model.geom_type[geoms] == 3, mj_model.geom_size[geoms, 1], 0.0)
    # the capsule's axis (its local z) in its body's frame, on the host in float64
    local_axis = np.stack(
        [_rotate_np(np.array([0.0, 0.0, 1.0]), q) for q in mj_model.geom_quat[geoms]]
    )
    rot = x.rot[link]
    centre = x.pos[link] + jax.vmap(math.rotate)(jnp.asarray(mj_model.geom_pos[geoms]), rot)
    axis = jax.vmap(math.rotate)(jnp.asarray(local_axis), rot)
    return centre[:, 2] - jnp.abs(axis[:, 2]) * half - mj_model.geom_size[geoms, 0]


def _rotate_np(v: np.ndarray, q: np.ndarray) -> np.ndarray:
    """``v`` rotated by the unit quaternion ``q`` = (w, x, y, z) (``brax.math.rotate``
    in numpy's float64, for constants of the model)."""
    w, u = q[0], q[1:]
    return v + 2.0 * np.cross(u, np.cross(u, v) + w * v)


def brax_observation_size(brax_env) -> int:
    """The size of a brax env's observation, from the shapes of its reset alone:
    brax's own ``observation_size`` plays a reset eagerly, op by op (about 200
    one-op compilations, 7 to 10 s per robot on 2 CPU cores)."""
    return int(jax.eval_shape(brax_env.reset, jax.random.PRNGKey(0)).obs.shape[-1])


@dataclass(frozen=True, eq=False)
class BraxTask(Env):
    """Shared plumbing: Gaussian resets, step counting, episode length."""

    backend: str = "spring"
    episode_length: int = 250
    reset_noise: float = 0.1
    brax_env: Any = field(default=None, repr=False)

    def _noise_mask(self) -> np.ndarray:
        return np.ones(self.brax_env.sys.q_size(), np.float32)

    def reset(self, key: jax.Array) -> EnvState:
        sys = self.brax_env.sys
        k_q, k_qd = jax.random.split(key)
        q = sys.init_q + self.reset_noise * jnp.asarray(self._noise_mask()) * jax.random.normal(
            k_q, (sys.q_size(),)
        )
        qd = self.reset_noise * jax.random.normal(k_qd, (sys.qd_size(),))
        return self.state_at(q, qd)

    def state_at(self, q: jax.Array, qd: jax.Array) -> EnvState:
        """The state with joint positions ``q`` and velocities ``qd`` (the reset's
        noisy pose, or a chosen start, e.g. to drive a robot at a wall)."""
        pipeline_state = self.brax_env.pipeline_init(q, qd)
        return EnvState(
            core=pipeline_state,
            obs=self._obs(pipeline_state),
            reward=jnp.zeros(()),
            done=jnp.zeros((), bool),
            state_descriptor=self._state_descriptor(pipeline_state),
            steps=jnp.zeros((), jnp.int32),
        )

    def step(self, state: EnvState, action: jax.Array) -> EnvState:
        action = jnp.clip(action, -1.0, 1.0)
        pipeline_state = self.brax_env.pipeline_step(state.core, action)
        return self._next_state(
            state, pipeline_state, action, self._state_descriptor(pipeline_state)
        )

    def _next_state(
        self, state: EnvState, pipeline_state, action: jax.Array, state_descriptor: jax.Array
    ) -> EnvState:
        """The state after one step of ``action`` from ``state`` led the simulator
        to ``pipeline_state``, with the step's ``state_descriptor``."""
        steps = state.steps + 1
        return EnvState(
            core=pipeline_state,
            obs=self._obs(pipeline_state),
            reward=self._reward(state.core, pipeline_state, action),
            done=steps >= self.episode_length,
            state_descriptor=state_descriptor,
            steps=steps,
        )

    def _obs(self, pipeline_state) -> jax.Array:
        return self.brax_env._get_obs(pipeline_state)  # brax's own observation


class QDaxReset:
    """brax v1's reset, which QDax's tasks use (its ``default_qp``): every limited
    hinge joint at the middle of its range, each hinge's angle and velocity moved by
    U(-``reset_noise``, ``reset_noise``), the first ``root_q`` positions and
    ``root_qd`` velocities (the root joint) at rest, and the robot moved along the
    vertical (its root position ``root_z``) until the lowest point of its geoms that
    collide with the floor rests on it."""

    root_q: int
    root_qd: int
    root_z: int

    def _build_reset(self) -> None:
        """The constants of the reset, from the loaded model."""
        model = self.brax_env.sys.mj_model
        q = np.array(self.brax_env.sys.init_q, np.float32)
        hinges = (model.jnt_type == 3) & (model.jnt_limited != 0)
        q[model.jnt_qposadr[hinges]] = model.jnt_range[hinges].mean(axis=1)
        object.__setattr__(self, "_rest_q", q)
        object.__setattr__(self, "_floor_colliders", floor_colliders(model))

    def lowest_point(self, q: jax.Array) -> jax.Array:
        """The height of the lowest point that collides with the floor, at pose ``q``."""
        from brax import kinematics

        sys = self.brax_env.sys
        x, _ = kinematics.forward(sys, q, jnp.zeros(sys.qd_size()))
        return jnp.min(geom_bottoms(sys.mj_model, self._floor_colliders, x))

    def reset(self, key: jax.Array) -> EnvState:
        sys = self.brax_env.sys
        k_q, k_qd = jax.random.split(key)
        u = lambda k, n: jax.random.uniform(
            k, (n,), minval=-self.reset_noise, maxval=self.reset_noise
        )
        q = jnp.asarray(self._rest_q).at[self.root_q :].add(u(k_q, sys.q_size() - self.root_q))
        q = q.at[self.root_z].add(-self.lowest_point(q))
        qd = jnp.zeros(sys.qd_size()).at[self.root_qd :].set(u(k_qd, sys.qd_size() - self.root_qd))
        return self.state_at(q, qd)


def qdax_ant(backend: str):
    """brax's Ant whose torso also collides with the floor, as in brax v1's Ant."""
    xml = with_collision_bits(brax_asset("ant.xml").read_text(), {"torso_geom": 1}, {})
    return brax_env_from_xml(
        "ant",
        backend,
        xml,
        exclude_current_positions_from_observation=True,
        terminate_when_unhealthy=False,  # termination is ours, in ``AntOmni.step``
    )


HALFCHEETAH_FLOOR_COLLIDERS = ("torso", "head", "bthigh", "bshin", "bfoot", "fthigh", "fshin")


def qdax_halfcheetah(backend: str):
    """brax's Halfcheetah with brax v1's colliding bodies (the floor against the
    torso, head, thighs, shins and feet; the two feet against each other) and
    motor gears (the XML's own)."""
    xml = with_collision_bits(
        brax_asset("half_cheetah.xml").read_text(),
        {**{name: 1 for name in HALFCHEETAH_FLOOR_COLLIDERS}, "ffoot": 1, "bfoot": 2},
        {"ffoot": 2},  # bit 2: the back foot's contype meets the front foot's conaffinity
    )
    return brax_env_from_xml("halfcheetah", backend, xml, keep_actuators=False)


@dataclass(frozen=True, eq=False)
class AntOmni(QDaxReset, BraxTask):
    """Ant-Omni (Eq. 4.2): go anywhere on the plane, spending little energy."""

    descriptor_size: int = 2
    descriptor_low: tuple[float, ...] = (-15.0, -15.0)
    descriptor_high: tuple[float, ...] = (15.0, 15.0)
    healthy_z_range: tuple[float, float] = (0.2, 1.0)
    survive_reward: float = 1.0
    root_q: int = 7  # the free joint: position (3) and quaternion (4)
    root_qd: int = 6
    root_z: int = 2

    def __post_init__(self):
        if (
            len(self.descriptor_low) != 2
            or len(self.descriptor_high) != 2
            or not all(lo < hi for lo, hi in zip(self.descriptor_low, self.descriptor_high))
        ):
            raise ValueError(
                f"the descriptor box needs two bounds per axis with low < high, got "
                f"{self.descriptor_low} and {self.descriptor_high}"
            )
        env = qdax_ant(self.backend)
        object.__setattr__(self, "brax_env", env)
        object.__setattr__(self, "observation_size", brax_observation_size(env))
        object.__setattr__(self, "action_size", env.action_size)
        self._build_reset()

    def healthy(self, pipeline_state) -> jax.Array:
        """Whether the torso's height is inside ``healthy_z_range`` (brax's rule)."""
        z = pipeline_state.x.pos[0, 2]
        return (z >= self.healthy_z_range[0]) & (z <= self.healthy_z_range[1])

    def step(self, state: EnvState, action: jax.Array) -> EnvState:
        nxt = super().step(state, action)
        return nxt.replace(done=nxt.done | ~self.healthy(nxt.core))

    def _state_descriptor(self, pipeline_state) -> jax.Array:
        return pipeline_state.x.pos[0, :2]  # torso (x, y)

    @property
    def fitness_shift(self) -> float:
        """The survival reward of a full episode, taken back from the return."""
        return -self.survive_reward * self.episode_length

    def _reward(self, before, after, action) -> jax.Array:
        del before, after
        return self.survive_reward - jnp.linalg.norm(action)

    def behaviour_descriptor(self, last_state_descriptor, state_descriptor_sum, length):
        del state_descriptor_sum, length
        return jnp.clip(
            last_state_descriptor,
            jnp.asarray(self.descriptor_low),
            jnp.asarray(self.descriptor_high),
        )


@dataclass(frozen=True, eq=False)
class HalfcheetahUni(QDaxReset, BraxTask):
    """Halfcheetah-Uni (Eq. 4.3): run forward fast and cheaply, gaits as descriptors."""

    descriptor_size: int = 2
    descriptor_low: tuple[float, ...] = (0.0, 0.0)
    descriptor_high: tuple[float, ...] = (1.0, 1.0)
    feet: tuple[str, ...] = ("ffoot", "bfoot")  # QDax's order: front, back
    root_q: int = 3  # the planar root: x, z, pitch
    root_qd: int = 3
    root_z: int = 1

    def __post_init__(self):
        import mujoco

        env = qdax_halfcheetah(self.backend)
        model = env.sys.mj_model
        feet = [mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, name) for name in self.feet]
        if min(feet) < 0:
            raise ValueError(f"halfcheetah model lacks one of the geoms {self.feet}")
        object.__setattr__(self, "brax_env", env)
        object.__setattr__(self, "_feet", np.asarray(feet))
        object.__setattr__(self, "observation_size", brax_observation_size(env))
        object.__setattr__(self, "action_size", env.action_size)
        self._build_reset()

    def foot_contacts(self, pipeline_state) -> jax.Array:
        """(front, back): 1.0 where that foot reaches below the floor, else 0.0."""
        bottoms = geom_bottoms(self.brax_env.sys.mj_model, self._feet, pipeline_state.x)
        return (bottoms < 0.0).astype(jnp.float32)

    def step(self, state: EnvState, action: jax.Array) -> EnvState:
        """One step of ``n_frames`` physics substeps, played one by one to read each
        foot's contact at the start of every substep: the step's state descriptor is
        1.0 for a foot that touched the floor in any of them."""
        action = jnp.clip(action, -1.0, 1.0)
        sys, pipeline = self.brax_env.sys, self.brax_env._pipeline

        def substep(pipeline_state, _):
            touching = self.foot_contacts(pipeline_state)
            return pipeline.step(sys, pipeline_state, action), touching

        pipeline_state, touching = jax.lax.scan(
            substep, state.core, None, length=self.brax_env._n_frames
        )
        return self._next_state(state, pipeline_state, action, touched_in_step(touching))

    def _state_descriptor(self, pipeline_state) -> jax.Array:
        return self.foot_contacts(pipeline_state)  # a reset state: its contacts now

    def _reward(self, before, after, action) -> jax.Array:
        forward = (after.x.pos[0, 0] - before.x.pos[0, 0]) / self.brax_env.dt
        return forward - jnp.linalg.norm(action)

    def behaviour_descriptor(self, last_state_descriptor, state_descriptor_sum, length):
        del last_state_descriptor
        return state_descriptor_sum / jnp.maximum(length, 1)


def touched_in_step(touching: jax.Array) -> jax.Array:
    """Per foot, 1.0 if it touched in any substep: ``touching`` is ``(substeps, feet)``
    of 0/1 (QDax: the contact impulse summed over the step's substeps is non-zero)."""
    return jnp.max(touching, axis=0)
