"""Brax locomotion tasks of Chapter 4: Ant-Omni and Halfcheetah-Uni (Section 4.3.1).

Both wrap the current ``brax.envs`` Ant and HalfCheetah (spring backend by
default: the fastest on CPU here; any brax backend can be chosen) into qdnb's
``Env`` interface, with 250-step episodes and the thesis's own fitness and
behaviour descriptor:

- ``ant_omni``: descriptor = final torso (x, y) clipped to [-15, 15]^2, reward at
  each step = -||a_t||_2, so the fitness is -sum_t ||a_t||_2 (Eq. 4.2).  The
  observation includes the torso position, and the episode never ends early.
- ``halfcheetah_uni``: descriptor = fraction of steps each foot (back, front)
  touches the ground, reward = (x_t - x_{t-1}) / dt - ||a_t||_2 (Eq. 4.3).
  Contacts are the simulator's own: a foot touches the ground when one of its
  contact points with the floor has a negative distance (penetration).

Initial states are the model's initial pose with Gaussian noise (standard
deviation ``reset_noise``) on joint positions and on all velocities (not on the
free joint's orientation quaternion), so episodes of one deterministic policy
differ only by their start.
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
    with _QUIET_LOCK, warnings.catch_warnings(), contextlib.redirect_stdout(io.StringIO()), \
            contextlib.redirect_stderr(io.StringIO()):
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
        q = sys.init_q + self.reset_noise * jnp.asarray(self._noise_mask()) * jax.random.normal(k_q, (sys.q_size(),))
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


@dataclass(frozen=True, eq=False)
class AntOmni(BraxTask):
    """Ant-Omni (Eq. 4.2): go anywhere on the plane, spending little energy."""

    descriptor_size: int = 2
    descriptor_low: tuple[float, ...] = (-15.0, -15.0)
    descriptor_high: tuple[float, ...] = (15.0, 15.0)

    def __post_init__(self):
        env = _brax_env("ant", self.backend, exclude_current_positions_from_observation=False,
                        terminate_when_unhealthy=False)
        object.__setattr__(self, "brax_env", env)
        object.__setattr__(self, "observation_size", env.observation_size)
        object.__setattr__(self, "action_size", env.action_size)

    def _noise_mask(self) -> np.ndarray:
        mask = np.ones(self.brax_env.sys.q_size(), np.float32)
        mask[3:7] = 0.0  # free joint quaternion
        return mask

    def _state_descriptor(self, pipeline_state) -> jax.Array:
        return pipeline_state.x.pos[0, :2]  # torso (x, y)

    def _reward(self, before, after, action) -> jax.Array:
        del before, after
        return -jnp.linalg.norm(action)

    def behaviour_descriptor(self, last_state_descriptor, state_descriptor_sum, length):
        del state_descriptor_sum, length
        return jnp.clip(last_state_descriptor, jnp.asarray(self.descriptor_low), jnp.asarray(self.descriptor_high))


@dataclass(frozen=True, eq=False)
class HalfcheetahUni(BraxTask):
    """Halfcheetah-Uni (Eq. 4.3): run forward fast and cheaply, gaits as descriptors."""

    descriptor_size: int = 2
    descriptor_low: tuple[float, ...] = (0.0, 0.0)
    descriptor_high: tuple[float, ...] = (1.0, 1.0)
    feet: tuple[str, ...] = ("bfoot", "ffoot")

    def __post_init__(self):
        import mujoco

        env = _brax_env("halfcheetah", self.backend, debug=True)  # debug: keep the contacts in the state
        model = env.sys.mj_model
        feet = [mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, name) for name in self.feet]
        if min(feet) < 0:
            raise ValueError(f"halfcheetah model lacks one of the geoms {self.feet}")
        object.__setattr__(self, "brax_env", env)
        object.__setattr__(self, "_feet", np.asarray(feet))
        object.__setattr__(self, "observation_size", env.observation_size)
        object.__setattr__(self, "action_size", env.action_size)

    def foot_contacts(self, pipeline_state) -> jax.Array:
        """(back, front): 1.0 where a contact point of that foot's geom penetrates
        the ground, else 0.0."""
        c = pipeline_state.contact
        touching = c.dist < 0.0
        return jnp.stack([jnp.any(touching & ((c.geom1 == g) | (c.geom2 == g))) for g in self._feet]).astype(jnp.float32)

    def _state_descriptor(self, pipeline_state) -> jax.Array:
        return self.foot_contacts(pipeline_state)

    def _reward(self, before, after, action) -> jax.Array:
        forward = (after.x.pos[0, 0] - before.x.pos[0, 0]) / self.brax_env.dt
        return forward - jnp.linalg.norm(action)

    def behaviour_descriptor(self, last_state_descriptor, state_descriptor_sum, length):
        del last_state_descriptor
        return state_descriptor_sum / jnp.maximum(length, 1)
