"""Brax locomotion tasks of Chapter 4: Ant-Omni and Halfcheetah-Uni (Section 4.3.1).

Both wrap the current ``brax.envs`` Ant and HalfCheetah (spring backend by
default: the fastest on CPU here; any brax backend can be chosen) into qdnb's
``Env`` interface, with 250-step episodes and the thesis's own fitness and
behaviour descriptor:

- ``ant_omni``: descriptor = final torso (x, y) clipped to the descriptor box
  (``descriptor_low``/``descriptor_high``: [-15, 15]^2 in the thesis, a smaller
  measured box at small scales), fitness -sum_t ||a_t||_2 (Eq. 4.2) for an episode
  that lasts its 250 steps; see the survival reward below for one that ends early.
- ``halfcheetah_uni``: descriptor = fraction of steps each foot (back, front)
  touches the ground, reward = (x_t - x_{t-1}) / dt - ||a_t||_2 (Eq. 4.3).
  Contacts are the simulator's own: a foot touches the ground when one of its
  contact points with the floor has a negative distance (penetration).

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
  (``bench/ant_omni_termination.py``), against the thesis's "an optimal policy
  would simply remain static".  So the step reward is 1 - ||a_t||_2 (what TD3
  learns from, as in QDax) and the fitness takes the constant 250 back
  (``fitness_shift``): Eq. 4.2 exactly for a full episode, Eq. 4.2 minus one per
  step not lived for one that ends early.
- **initial states** (``QDaxReset``): the model's rest pose, each hinge joint's
  angle and velocity moved by U(-0.1, 0.1); the free (Ant) or planar
  (Halfcheetah) root joint starts at rest, where the model puts it.
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
import io
import os
import threading
import warnings
from dataclasses import dataclass, field
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
        steps = state.steps + 1
        return EnvState(
            core=pipeline_state,
            obs=self._obs(pipeline_state),
            reward=self._reward(state.core, pipeline_state, action),
            done=steps >= self.episode_length,
            state_descriptor=self._state_descriptor(pipeline_state),
            steps=steps,
        )

    def _obs(self, pipeline_state) -> jax.Array:
        return self.brax_env._get_obs(pipeline_state)  # brax's own observation


class QDaxReset:
    """brax v1's reset, which QDax's tasks use: the rest pose, with every hinge
    joint's angle and velocity moved by U(-``reset_noise``, ``reset_noise``); the
    first ``root_q`` positions and ``root_qd`` velocities (the root joint) at rest."""

    root_q: int
    root_qd: int

    def reset(self, key: jax.Array) -> EnvState:
        sys = self.brax_env.sys
        k_q, k_qd = jax.random.split(key)
        u = lambda k, n: jax.random.uniform(
            k, (n,), minval=-self.reset_noise, maxval=self.reset_noise
        )
        q = sys.init_q.at[self.root_q :].add(u(k_q, sys.q_size() - self.root_q))
        qd = jnp.zeros(sys.qd_size()).at[self.root_qd :].set(u(k_qd, sys.qd_size() - self.root_qd))
        return self.state_at(q, qd)


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
        env = _brax_env(
            "ant",
            self.backend,
            exclude_current_positions_from_observation=True,
            terminate_when_unhealthy=False,
        )  # termination is ours, in ``step``
        object.__setattr__(self, "brax_env", env)
        object.__setattr__(self, "observation_size", brax_observation_size(env))
        object.__setattr__(self, "action_size", env.action_size)

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
    feet: tuple[str, ...] = ("bfoot", "ffoot")
    root_q: int = 3  # the planar root: x, z, pitch
    root_qd: int = 3

    def __post_init__(self):
        import mujoco

        env = _brax_env(
            "halfcheetah", self.backend, debug=True
        )  # debug: keep the contacts in the state
        model = env.sys.mj_model
        feet = [mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, name) for name in self.feet]
        if min(feet) < 0:
            raise ValueError(f"halfcheetah model lacks one of the geoms {self.feet}")
        object.__setattr__(self, "brax_env", env)
        object.__setattr__(self, "_feet", np.asarray(feet))
        object.__setattr__(self, "observation_size", brax_observation_size(env))
        object.__setattr__(self, "action_size", env.action_size)

    def foot_contacts(self, pipeline_state) -> jax.Array:
        """(back, front): 1.0 where a contact point of that foot's geom penetrates
        the ground, else 0.0."""
        c = pipeline_state.contact
        touching = c.dist < 0.0
        return jnp.stack(
            [jnp.any(touching & ((c.geom1 == g) | (c.geom2 == g))) for g in self._feet]
        ).astype(jnp.float32)

    def _state_descriptor(self, pipeline_state) -> jax.Array:
        return self.foot_contacts(pipeline_state)

    def _reward(self, before, after, action) -> jax.Array:
        forward = (after.x.pos[0, 0] - before.x.pos[0, 0]) / self.brax_env.dt
        return forward - jnp.linalg.norm(action)

    def behaviour_descriptor(self, last_state_descriptor, state_descriptor_sum, length):
        del last_state_descriptor
        return state_descriptor_sum / jnp.maximum(length, 1)
