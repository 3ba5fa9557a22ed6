"""Episodes of the robot tasks (Ant-Maze, Ant-Trap, Ant-Omni, Halfcheetah-Uni) drawn from
their real model, for the book's videos.

``episode_states`` plays one policy for one episode, as ``evaluate_policies`` does, and
keeps the simulator's generalised positions ``q`` at every step; ``render`` draws them with
MuJoCo's own ``Renderer`` on the MuJoCo model brax built the task from
(``env.brax_env.sys.mj_model``: the robot, the floor and, in the mazes, the walls, as
they collide), off-screen through EGL (``MUJOCO_GL=egl``, set by ``qdnb``'s import:
Mesa's software rasteriser draws it on a machine with no display or GPU).  The choice
over brax's ``brax.io.image`` (pytinyrenderer, another package to pin, flat shading) is
that this draws the model the simulation ran, with its materials and lights, and needs
nothing beyond the MuJoCo brax already installs; ``bench/render.py`` measures it.
Without a working OpenGL, ``renderer_missing`` says why and the pages skip their robot
videos, saying so.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from qdnb.envs.base import Env


def episode_states(
    env: Env, policy_apply, params: Any, keys: jax.Array, length: int | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Episodes of policies ``params`` (a leading batch axis), each from the initial state
    its row of ``keys`` draws (``env.reset``), for ``length`` steps (the episode's own when
    ``None``), as ``evaluate_policies`` plays them, in one compiled call: the simulator's
    positions ``q`` ``(n, steps + 1, nq)``, the reset state's first, held at the last once
    an episode has ended, and whether each state is still ``alive`` ``(n, steps + 1)``."""
    steps = env.episode_length if length is None else length

    def one(p, key):
        def step(carry, _):
            state, alive = carry
            nxt = env.step(state, policy_apply(p, state.obs))
            alive = alive & ~state.done
            return (nxt, alive), (nxt.core.q, alive & ~nxt.done)

        first = env.reset(key)
        _, (qs, alive) = jax.lax.scan(step, (first, jnp.ones((), bool)), None, length=steps)
        return (
            jnp.concatenate([first.core.q[None], qs]),
            jnp.concatenate([jnp.ones(1, bool), alive]),
        )

    qs, alive = jax.device_get(jax.jit(jax.vmap(one))(params, keys))
    qs, alive = np.array(qs), np.array(alive)
    for q, a in zip(qs, alive):  # the state that ended an episode is its last: hold it
        ended = np.flatnonzero(~a)
        if ended.size:
            q[ended[0] + 1 :] = q[ended[0]]
    return qs, alive


def renderer_missing() -> str | None:
    """Why robots cannot be drawn here (no OpenGL off screen), or ``None`` when they can."""
    try:
        import mujoco

        model = mujoco.MjModel.from_xml_string("<mujoco><worldbody/></mujoco>")
        with mujoco.Renderer(model, 8, 8) as renderer:
            renderer.render()
    except Exception as e:  # a missing library surfaces as one of several errors
        return f"MuJoCo cannot draw off screen ({type(e).__name__}: {str(e)[:120]})"
    return None


@dataclass(frozen=True)
class Camera:
    """Where the camera looks from: ``distance`` (m) from the point it looks at,
    ``elevation`` and ``azimuth`` (degrees, MuJoCo's convention); ``lookat`` a fixed
    point, or ``None`` to follow the robot's torso (its first three coordinates)."""

    distance: float = 4.0
    elevation: float = -30.0
    azimuth: float = 90.0
    lookat: tuple[float, float, float] | None = None


def render(
    env: Env,
    qs: np.ndarray,
    width: int = 200,
    height: int = 150,
    camera: Camera = Camera(),
    marks: tuple[tuple[float, float], ...] = (),
) -> np.ndarray:
    """The states ``qs`` ``(T, nq)`` of ``env``'s robot as RGB frames ``(T, height,
    width, 3)``, drawn by MuJoCo from ``env.brax_env.sys.mj_model`` (``RuntimeError`` where
    it cannot draw: ``renderer_missing``), with a red disc on the floor at each of
    ``marks`` ``(x, y)`` (where a policy promised to end, say); the discs are drawn, not
    simulated."""
    import mujoco

    why = renderer_missing()
    if why is not None:
        raise RuntimeError(why)
    model = env.brax_env.sys.mj_model
    data = mujoco.MjData(model)
    view = mujoco.MjvCamera()
    view.type = mujoco.mjtCamera.mjCAMERA_FREE
    view.distance, view.elevation, view.azimuth = camera.distance, camera.elevation, camera.azimuth
    frames = np.empty((len(qs), height, width, 3), np.uint8)
    with mujoco.Renderer(model, height, width) as renderer:
        for t, q in enumerate(np.asarray(qs)):
            data.qpos[:] = q
            mujoco.mj_forward(model, data)
            view.lookat[:] = camera.lookat if camera.lookat is not None else data.qpos[:3]
            renderer.update_scene(data, camera=view)
            for x, y in marks:
                scene = renderer.scene
                if scene.ngeom < scene.maxgeom:
                    mujoco.mjv_initGeom(
                        scene.geoms[scene.ngeom],
                        mujoco.mjtGeom.mjGEOM_CYLINDER,
                        np.array([0.2, 0.005, 0.0]),
                        np.array([x, y, 0.005]),
                        np.eye(3).ravel(),
                        np.array([0.85, 0.1, 0.1, 1.0], np.float32),
                    )
                    scene.ngeom += 1
            frames[t] = renderer.render()
    return frames
