"""Episodes for the book's videos: played and recorded, then, for the robot tasks
(Ant-Maze, Ant-Trap, Ant-Omni, Halfcheetah-Uni), drawn from their real model.

``episode_states`` plays policies for one episode each, as ``evaluate_policies`` does, and
keeps what ``read`` takes of the state at every step (the simulator's generalised
positions ``q`` by default; ``episode_path`` keeps a Point-Maze episode's state
descriptors), held once an episode has ended; ``watched_episodes`` adds what each episode
measured (its behaviour descriptor), so that an episode shown beside the descriptor it
reached is played once; ``replay_states`` plays recorded actions instead. ``render`` draws
the states with MuJoCo's own ``Renderer`` on the MuJoCo model brax built the task from
(``env.brax_env.sys.mj_model``: the robot, the floor and, in the mazes, the walls, as they
collide), off-screen through EGL (``MUJOCO_GL=egl``, set by ``qdnb``'s import: Mesa's
software rasteriser draws it on a machine with no display or GPU). The choice over brax's
``brax.io.image`` (pytinyrenderer, another package to pin, flat shading) is that this
draws the model the simulation ran, with its materials and lights, and needs nothing
beyond the MuJoCo brax already installs; ``bench/video.py`` measures it. Without a working
OpenGL, ``renderer_missing`` says why and the pages skip their robot videos, saying so.
"""

from __future__ import annotations

import copy
import functools
from dataclasses import dataclass
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np

from qdnb.envs.base import Env
from qdnb.envs.rollout import tally_start, tally_step


def robot_q(state) -> jax.Array:
    """The simulator's generalised positions ``q`` of a brax task's state."""
    return state.core.q


def episode_states(
    env: Env,
    policy_apply,
    params: Any,
    keys: jax.Array,
    length: int | None = None,
    read: Callable[[Any], jax.Array] = robot_q,
) -> tuple[np.ndarray, np.ndarray]:
    """Episodes of policies ``params`` (a leading batch axis), each from the initial state
    its row of ``keys`` draws (``env.reset``), for ``length`` steps (the episode's own when
    ``None``), as ``evaluate_policies`` plays them, in one compiled call: ``read`` of every
    state ``(n, steps + 1, ...)`` (``q`` by default), the reset state's first, held at the
    last once an episode has ended, and whether each state is still ``alive``
    ``(n, steps + 1)``."""
    steps = env.episode_length if length is None else length
    qs, alive, _ = _states(env, lambda p, obs, t: policy_apply(p, obs), params, keys, steps, read)
    return qs, alive


def watched_episodes(
    env: Env, policy_apply, params: Any, keys: jax.Array
) -> tuple[np.ndarray, np.ndarray]:
    """``episode_states`` of whole episodes with what each one measured: ``q`` at every
    state ``(n, steps + 1, ...)`` and each episode's behaviour descriptor ``(n, d)`` as
    ``evaluate_policies`` computes it from the same initial states (its tally), in the
    same compiled call: an episode shown with the descriptor it reached is played once."""
    act = lambda p, obs, t: policy_apply(p, obs)
    qs, _, descriptors = _states(env, act, params, keys, env.episode_length, robot_q)
    return qs, descriptors


def episode_path(env: Env, policy_apply, params: Any, key: jax.Array) -> np.ndarray:
    """One episode of one policy (``params`` without a batch axis) from the initial state
    ``key`` draws: its state descriptors ``(episode_length + 1, d)`` (``episode_states``
    with ``read`` the state descriptor), what a Point-Maze video draws."""
    batch = jax.tree.map(lambda x: jnp.asarray(x)[None], params)
    path, _ = episode_states(env, policy_apply, batch, key[None], read=lambda s: s.state_descriptor)
    return path[0]


def replay_states(env: Env, actions: Any, keys: jax.Array) -> tuple[np.ndarray, np.ndarray]:
    """``episode_states`` of recorded ``actions`` ``(n, T, A)``: row ``i`` played from the
    initial state row ``i`` of ``keys`` draws, action ``t`` at step ``t`` (a model that is
    not a policy network, the QDT say, is watched this way from the actions it played)."""
    actions = jnp.asarray(actions)
    qs, alive, _ = _states(env, lambda a, obs, t: a[t], actions, keys, actions.shape[1], robot_q)
    return qs, alive


def _states(env: Env, act, rows: Any, keys: jax.Array, steps: int, read):
    """``episode_states``' loop: ``act(row, obs, t)`` is row's action at step ``t``;
    ``read`` of every state, whether it is alive, and each episode's behaviour descriptor
    (``evaluate_policies``' tally of the same steps)."""

    def one(row, key):
        def step(carry, t):
            state, alive, tally = carry
            nxt = env.step(state, act(row, state.obs, t))
            alive = alive & ~state.done
            tally, _ = tally_step(env, tally, nxt)
            return (nxt, alive, tally), (read(nxt), alive & ~nxt.done)

        first = env.reset(key)
        init = (first, jnp.ones((), bool), tally_start(env, first))
        (_, _, tally), (qs, alive) = jax.lax.scan(step, init, jnp.arange(steps))
        return (
            jnp.concatenate([read(first)[None], qs]),
            jnp.concatenate([jnp.ones(1, bool), alive]),
            env.behaviour_descriptor(tally.last_sd, tally.sd_sum, tally.length),
        )

    qs, alive, descriptors = jax.device_get(jax.jit(jax.vmap(one))(rows, keys))
    qs, alive = np.array(qs), np.array(alive)
    for q, a in zip(qs, alive):  # the state that ended an episode is its last: hold it
        ended = np.flatnonzero(~a)
        if ended.size:
            q[ended[0] + 1 :] = q[ended[0]]
    return qs, alive, np.asarray(descriptors)


@functools.cache
def renderer_missing() -> str | None:
    """Why robots cannot be drawn here (no OpenGL off screen), or ``None`` when they can
    (asked once a process: the answer does not change while it runs)."""
    try:
        import mujoco

        model = mujoco.MjModel.from_xml_string("<mujoco><worldbody/></mujoco>")
        with mujoco.Renderer(model, 8, 8) as renderer:
            renderer.render()
    except Exception as e:  # a missing library surfaces as one of several errors
        return f"MuJoCo cannot draw off screen ({type(e).__name__}: {str(e)[:120]})"
    return None


RED = np.array([0.85, 0.1, 0.1, 1.0], np.float32)  # a goal, or a promised end
BLUE = np.array([0.1, 0.3, 0.9, 1.0], np.float32)  # the robot, seen from afar


@dataclass(frozen=True)
class Camera:
    """Where the camera looks from: ``distance`` (m) from the point it looks at,
    ``elevation`` and ``azimuth`` (degrees, MuJoCo's convention); ``lookat`` a fixed
    point, or ``None`` to follow the robot's torso (the model's first body: the Ant's
    free joint and the Halfcheetah's planar one place it differently in ``q``)."""

    distance: float = 4.0
    elevation: float = -30.0
    azimuth: float = 90.0
    lookat: tuple[float, float, float] | None = None


def locomotion_camera(env_name: str, points: Any = ()) -> Camera:
    """Chapter 4's view of a robot: Ant-Omni from 55 degrees above the origin, backed away
    until every ``(x, y)`` of ``points`` (goals, stored descriptors) is in view (at least
    2 m around it); Halfcheetah-Uni from the side, following the torso."""
    if env_name == "ant_omni":
        far = np.abs(np.asarray(points, float)).max() if np.size(points) else 0.0
        reach = max(2.0, float(far) + 1.0)
        return Camera(distance=2.4 * reach, elevation=-55.0, azimuth=90.0, lookat=(0.0, 0.0, 0.0))
    if env_name == "halfcheetah_uni":
        return Camera(distance=3.0, elevation=-15.0, azimuth=90.0)
    raise ValueError(f"no camera for {env_name!r}; valid: ant_omni, halfcheetah_uni")


FLOOR_SCALE = 10  # how much wider the drawn floor is than the model's


def _drawn_model(model):
    """A copy of ``model`` for drawing only, its floor planes ``FLOOR_SCALE`` times wider
    (their checkers as large: the texture repeats as many more times).  Brax's floors
    are 80 m across, and a Halfcheetah running 1,000 steps leaves them: past the edge
    it ran in a grey void under a black band, the floor's end in shadow."""
    import mujoco

    drawn = copy.deepcopy(model)
    for g in np.flatnonzero(drawn.geom_type == mujoco.mjtGeom.mjGEOM_PLANE):
        drawn.geom_size[g, :2] *= FLOOR_SCALE
        material = drawn.geom_matid[g]
        alone = np.sum(drawn.geom_matid == material) == 1  # no wall shares its texture
        if material >= 0 and alone and not drawn.mat_texuniform[material]:
            drawn.mat_texrepeat[material] *= FLOOR_SCALE
    return drawn


def render(
    env: Env,
    qs: np.ndarray,
    width: int = 200,
    height: int = 150,
    camera: Camera = Camera(),
    marks: tuple[tuple[float, float], ...] = (),
    mark_radius: float | None = None,
    torso_mark: bool = False,
) -> np.ndarray:
    """The states ``qs`` ``(T, nq)`` of ``env``'s robot as RGB frames ``(T, height,
    width, 3)``, drawn by MuJoCo from ``env.brax_env.sys.mj_model`` (``RuntimeError`` where
    it cannot draw: ``renderer_missing``), with a red disc on the floor at each of
    ``marks`` ``(x, y)`` (where a policy promised to end, say), of ``mark_radius`` metres
    (by default 4 % of the camera's distance, so a disc keeps its size on screen as the
    camera backs away), and, with ``torso_mark``, a blue one under the torso at every frame
    (where the camera is far enough for the robot to be lost in the maze); the discs are
    drawn, not simulated."""
    import mujoco

    why = renderer_missing()
    if why is not None:
        raise RuntimeError(why)
    model = _drawn_model(env.brax_env.sys.mj_model)
    data = mujoco.MjData(model)
    view = mujoco.MjvCamera()
    view.type = mujoco.mjtCamera.mjCAMERA_FREE
    view.distance, view.elevation, view.azimuth = camera.distance, camera.elevation, camera.azimuth
    radius = 0.04 * camera.distance if mark_radius is None else mark_radius
    if radius <= 0:
        raise ValueError(f"mark_radius must be positive, got {radius}")
    frames = np.empty((len(qs), height, width, 3), np.uint8)
    with mujoco.Renderer(model, height, width) as renderer:
        for t, q in enumerate(np.asarray(qs)):
            data.qpos[:] = q
            mujoco.mj_forward(model, data)
            view.lookat[:] = camera.lookat if camera.lookat is not None else data.xpos[1]
            renderer.update_scene(data, camera=view)
            # (x, y, height, colour): the robot's disc a millimetre above the goals', so it
            # stays in sight where it crosses one
            discs = [(x, y, 0.005, RED) for x, y in marks]
            if torso_mark:
                discs.append((data.xpos[1][0], data.xpos[1][1], 0.006, BLUE))
            for x, y, z, colour in discs:
                scene = renderer.scene
                if scene.ngeom < scene.maxgeom:
                    mujoco.mjv_initGeom(
                        scene.geoms[scene.ngeom],
                        mujoco.mjtGeom.mjGEOM_CYLINDER,
                        np.array([radius, 0.005, 0.0]),
                        np.array([x, y, z]),
                        np.eye(3).ravel(),
                        colour,
                    )
                    scene.ngeom += 1
            frames[t] = renderer.render()
    return frames
