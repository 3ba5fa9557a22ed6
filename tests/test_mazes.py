"""Ant-Maze and Ant-Trap of Chapter 3: walls that hold, rewards, descriptors, resets."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from qdnb.envs import make_env
from qdnb.envs.mazes import ANTMAZE_WALLS, ANTTRAP_WALLS, WALL_COLLIDERS, WALL_RADIUS
from qdnb.envs.rollout import evaluate_policies

TORSO_RADIUS = 0.25
PUSH_STEPS = 150


@pytest.fixture(scope="module")
def maze():
    return make_env("antmaze", episode_length=20)


@pytest.fixture(scope="module")
def trap():
    return make_env("anttrap", episode_length=20)


def _driver(env):
    """Jitted: start the ant's torso at (x, y) with velocity v (m/s), step with no
    torque for PUSH_STEPS steps; returns the per-step torso position, reward and
    done flag."""
    sys = env.brax_env.sys

    @jax.jit
    def drive(xy, v):
        q = sys.init_q.at[:2].set(xy)
        qd = jnp.zeros(sys.qd_size()).at[:3].set(v)
        state = env.state_at(q, qd)

        def body(s, _):
            nxt = env.step(s, jnp.zeros(env.action_size))
            return nxt, (nxt.core.x.pos[0], nxt.reward, nxt.done)

        return jax.lax.scan(body, state, None, length=PUSH_STEPS)[1]

    return lambda xy, v: jax.tree.map(
        np.asarray, drive(jnp.asarray(xy, jnp.float32), jnp.asarray(v, jnp.float32))
    )


@pytest.fixture(scope="module")
def maze_drive(maze):
    return _driver(maze)


@pytest.fixture(scope="module")
def trap_drive(trap):
    return _driver(trap)


def test_walls_are_the_specified_segments(maze, trap):
    assert maze.walls == ANTMAZE_WALLS and trap.walls == ANTTRAP_WALLS
    assert len(ANTMAZE_WALLS) == 7 and len(ANTTRAP_WALLS) == 3
    assert maze.goal == (35.0, 0.0)


def test_walls_only_add_torso_and_lower_leg_contacts(maze, trap):
    from brax import contact

    def contacts(env):  # the contacts the pipeline resolves at each physics step
        sys = env.brax_env.sys
        return lambda q: contact.get(sys, env.brax_env.pipeline_init(q, jnp.zeros(sys.qd_size())).x)

    from types import SimpleNamespace

    from qdnb.envs.locomotion import _brax_env

    bare = SimpleNamespace(brax_env=_brax_env("ant", "spring"))  # brax's own Ant
    # one contact per colliding pair: 4 foot-floor pairs, then 5 per wall
    counts = [
        jax.eval_shape(contacts(e), e.brax_env.sys.init_q).dist.shape[0] for e in (bare, maze, trap)
    ]
    assert counts == [4, 4 + 5 * 7, 4 + 5 * 3]
    model = maze.brax_env.sys.mj_model
    assert model.ngeom == bare.brax_env.sys.mj_model.ngeom + 7
    c = jax.jit(contacts(maze))(maze.brax_env.sys.init_q)
    pairs = {
        (model.geom(int(g1)).name, model.geom(int(g2)).name) for g1, g2 in zip(c.geom1, c.geom2)
    }
    assert len(pairs) == 4 + 5 * 7
    # every pair with a wall has the torso or a lower leg on the other side
    partners = {}
    for g1, g2 in pairs:
        for wall, other in ((g1, g2), (g2, g1)):
            if wall.startswith("wall_"):
                partners.setdefault(wall, set()).add(other)
    assert partners == {f"wall_{i}": set(WALL_COLLIDERS) for i in range(7)}
    feet = {f"{leg}_foot_geom" for leg in ("left", "right", "third", "fourth")}
    assert {p for p in pairs if "floor" in p} == {("floor", foot) for foot in feet}


@pytest.mark.parametrize("backend", ["spring", "positional", "generalized", "mjx"])
def test_walled_system_gets_what_brax_ant_constructor_changes(backend):
    from qdnb.envs.locomotion import _brax_env
    from qdnb.envs.mazes import brax_ant_with_walls

    brax_ant = _brax_env("ant", backend)
    ours = brax_ant_with_walls((), backend)
    np.testing.assert_array_equal(ours.sys.opt.timestep, brax_ant.sys.opt.timestep)
    np.testing.assert_array_equal(ours.sys.actuator.gear, brax_ant.sys.actuator.gear)
    assert (
        ours.sys.opt.solver == brax_ant.sys.opt.solver
        and ours.sys.opt.iterations == brax_ant.sys.opt.iterations
    )
    assert ours.dt == pytest.approx(float(brax_ant.dt)) and ours.backend == backend
    # with no wall, the very system brax builds, but for the collision bits (and
    # MuJoCo's sizes, which count the bounding-volume nodes of colliding geoms)
    ours_leaves = jax.tree_util.tree_flatten_with_path(ours.sys)[0]
    for (path, a), b in zip(ours_leaves, jax.tree.leaves(brax_ant.sys)):
        if jax.tree_util.keystr(path) not in (".geom_contype", "._sizes"):
            np.testing.assert_array_equal(a, b, err_msg=jax.tree_util.keystr(path))
    if backend in ("spring", "positional"):  # ant.xml says 0.01
        assert float(ours.sys.opt.timestep) == pytest.approx(0.005)


def test_shapes_and_deterministic_resets(maze, trap):
    for env in (maze, trap):
        reset = jax.jit(env.reset)
        a, b, c = (
            reset(jax.random.PRNGKey(0)),
            reset(jax.random.PRNGKey(0)),
            reset(jax.random.PRNGKey(1)),
        )
        assert env.observation_size == 29 and env.action_size == 8 and env.descriptor_size == 2
        assert a.obs.shape == (29,) and a.state_descriptor.shape == (2,)
        np.testing.assert_array_equal(a.obs, b.obs)
        assert not np.allclose(a.obs, c.obs)
        # the observation ends with the torso (x, y), near the origin at the start
        np.testing.assert_allclose(a.obs[-2:], a.core.x.pos[0, :2], rtol=1e-6)
        assert np.all(np.abs(a.obs[-2:]) < 1.0)
        # brax's observation without (x, y): it starts with the torso height
        np.testing.assert_allclose(a.obs[0], a.core.q[2], rtol=1e-6)


@pytest.mark.parametrize(
    "start, velocity, axis, limit",
    [
        ((17.0, 3.0), (10.0, 0.0, 0.0), 0, 20.0),  # inner wall x = 20, from the start side
        ((15.0, 5.0), (0.0, 10.0, 0.0), 1, 7.5),  # inner wall y = 7.5, from below
        ((0.0, 0.0), (-10.0, 0.0, 0.0), 0, -5.0),  # border x = -5
    ],
)
def test_ant_maze_walls_hold(maze_drive, start, velocity, axis, limit):
    pos = maze_drive(start, velocity)[0][:, axis]
    sign = np.sign(limit - start[axis])
    gap = sign * (limit - pos)  # distance from the torso centre to the wall's axis
    assert np.all(gap > WALL_RADIUS), "the torso went into the wall"
    # it did reach the wall: its surface touched the wall's surface
    assert gap.min() < WALL_RADIUS + TORSO_RADIUS + 0.1


def test_ant_maze_push_goes_further_without_a_wall(maze_drive):
    blocked = maze_drive((17.0, 3.0), (10.0, 0.0, 0.0))[0][:, 0]
    free = maze_drive((22.0, 3.0), (10.0, 0.0, 0.0))[0][:, 0]  # nothing until x = 40
    assert blocked.max() - 17.0 < 2.5
    assert free.max() - 22.0 > 3.5


def test_ant_trap_back_wall_holds_and_the_open_side_does_not(trap_drive):
    pos = trap_drive((9.0, 0.0), (10.0, 0.0, 0.0))[0]
    assert np.all(pos[:, 0] < 12.0 - WALL_RADIUS)
    assert pos[:, 0].max() > 12.0 - WALL_RADIUS - TORSO_RADIUS - 0.1
    assert np.all(np.abs(pos[:, 1]) < 3.0 - WALL_RADIUS)
    outside = trap_drive((9.0, 6.0), (10.0, 0.0, 0.0))[
        0
    ]  # beside the trap: same push, nothing in the way
    assert outside[:, 0].max() > 12.0 + 1.0


def test_rewards(maze, maze_drive, trap, trap_drive):
    pos, reward, _ = maze_drive((17.0, 3.0), (10.0, 0.0, 0.0))
    np.testing.assert_allclose(
        reward, -np.linalg.norm(np.asarray(maze.goal) - pos[:, :2], axis=1), rtol=1e-5
    )
    pos, reward, _ = trap_drive((9.0, 6.0), (10.0, 0.0, 0.0))
    dt = float(trap.brax_env.dt)
    assert dt == pytest.approx(0.05)
    np.testing.assert_allclose(reward[1:], np.diff(pos[:, 0]) / dt, rtol=1e-4, atol=1e-4)
    np.testing.assert_allclose(reward[0], (pos[0, 0] - 9.0) / dt, rtol=1e-4)


def test_episodes_end_outside_the_height_band_or_at_the_time_limit(maze_drive):
    _, _, done = maze_drive((0.0, 0.0), (0.0, 0.0, 0.0))
    assert not done[:19].any() and done[19]  # standing still: only the time limit (20 steps)
    pos, _, done = maze_drive((0.0, 0.0), (0.0, 0.0, 20.0))  # thrown upwards
    first = int(np.argmax(done))
    assert done.any() and first < 19 and pos[first, 2] > 5.0 and np.all(pos[:first, 2] <= 5.0)


def test_ant_maze_fitness_is_the_best_reward(maze):
    assert maze.fitness_mode == "max_reward"

    def policy(params, obs):
        return jnp.tanh(params * jnp.ones(maze.action_size) + 0.1 * obs[: maze.action_size])

    ev = jax.jit(lambda p, k: evaluate_policies(maze, policy, p, k, return_trajectory=True))(
        jnp.array([0.0, 1.0, -2.0]), jax.random.PRNGKey(0)
    )
    valid = np.asarray(ev.trajectory["valid"])
    rewards = np.where(valid, np.asarray(ev.trajectory["reward"]), -np.inf)
    np.testing.assert_allclose(ev.fitness, rewards.max(axis=1), rtol=1e-6)
    assert np.all(ev.fitness > -36.0) and np.all(ev.fitness < -34.0)  # about 35 from the goal
    sd = np.asarray(ev.trajectory["next_state_descriptor"])
    np.testing.assert_allclose(
        np.asarray(ev.trajectory["reward"])[valid],
        -np.linalg.norm(np.asarray(maze.goal) - sd, axis=-1)[valid],
        rtol=1e-5,
    )
    low, high = maze.descriptor_bounds
    assert ev.descriptor.shape == (3, 2) and np.all(
        (ev.descriptor >= low) & (ev.descriptor <= high)
    )
    last = sd[np.arange(3), np.asarray(ev.length) - 1]
    np.testing.assert_allclose(ev.descriptor, np.clip(last, low, high), rtol=1e-6)


def test_ant_trap_descriptors_are_clipped(trap):
    assert trap.fitness_mode == "return"
    low, high = (np.asarray(b) for b in trap.descriptor_bounds)
    state = trap.reset(jax.random.PRNGKey(2))
    core = trap.brax_env.pipeline_init(
        state.core.q.at[:2].set(jnp.array([-3.0, 20.0])), state.core.qd
    )
    np.testing.assert_allclose(trap._state_descriptor(core), [0.0, 8.0])
    np.testing.assert_allclose(
        trap.behaviour_descriptor(jnp.array([40.0, -9.0]), None, None), [30.0, -8.0]
    )
    assert np.all(low == [0.0, -8.0]) and np.all(high == [30.0, 8.0])
