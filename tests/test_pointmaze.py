import jax
import jax.numpy as jnp
import numpy as np
import pytest

from qdnb.envs import make_env
from qdnb.envs.pointmaze import GOAL, WALLS, in_goal, inside_a_wall, move
from qdnb.envs.rollout import evaluate_policies, rollout
from qdnb.nets.mlp import MLP, init_policies


def crosses_a_wall(p, q):
    """Independent check: the straight segment p->q passes through a wall's
    y-band at an x inside the wall (walls are horizontal), or ends strictly
    inside a wall (ending on a face is allowed: that is where a blocked move
    stops)."""
    for x0, x1, y0, y1 in WALLS:
        for y in (y0, y1):
            if (p[1] - y) * (q[1] - y) < 0:  # strictly on both sides of the band edge
                t = (y - p[1]) / (q[1] - p[1])
                x = p[0] + t * (q[0] - p[0])
                if x0 <= x <= x1:
                    return True
        if y0 < q[1] < y1 and x0 < q[0] < x1:
            return True
    return False


def test_random_walks_never_cross_walls():
    env = make_env("pointmaze")

    def walk(key):
        state = env.reset(key)

        def body(state, k):
            nxt = env.step(state, jax.random.uniform(k, (2,), minval=-1.0, maxval=1.0))
            return nxt, (state.core, nxt.core)

        return jax.lax.scan(body, state, jax.random.split(key, 400))[1]

    starts, ends = jax.jit(jax.vmap(walk))(jax.random.split(jax.random.PRNGKey(0), 64))
    starts, ends = np.asarray(starts).reshape(-1, 2), np.asarray(ends).reshape(-1, 2)
    assert not any(crosses_a_wall(p, q) for p, q in zip(starts, ends))
    assert np.all(np.abs(ends) <= 1.0)


def test_pushing_straight_up_into_the_first_wall_stops_below_it():
    p = jnp.array([0.0, -0.55])
    for _ in range(20):
        p = move(p, jnp.array([0.0, 1.0]))
    assert float(p[1]) == pytest.approx(-0.50)  # on the wall's lower face (y in [-0.50, -0.49])
    assert float(p[0]) == 0.0


def test_blocked_moves_keep_their_horizontal_part_and_stop_on_the_face():
    """QDax's rule: the move (-0.1, +0.1) from (0, -0.52) crosses the lower
    wall's lower face; the point keeps x - 0.1 and stops at y = -0.50."""
    q = move(jnp.array([0.0, -0.52]), jnp.array([-1.0, 1.0]))
    np.testing.assert_allclose(q, [-0.1, -0.50], atol=1e-6)
    # from above, onto the upper wall's upper face (y in [0.20, 0.21])
    q = move(jnp.array([0.0, 0.25]), jnp.array([0.5, -1.0]))
    np.testing.assert_allclose(q, [0.05, 0.21], atol=1e-6)
    # on the face, sliding along it is free and pushing into it does nothing
    q = move(jnp.array([0.0, -0.50]), jnp.array([1.0, 0.0]))
    np.testing.assert_allclose(q, [0.1, -0.50], atol=1e-6)
    q = move(jnp.array([0.0, -0.50]), jnp.array([0.0, 1.0]))
    np.testing.assert_allclose(q, [0.0, -0.50], atol=1e-6)


def test_entering_a_wall_sideways_drops_the_horizontal_part():
    """Beside the upper wall's end (x = 0.5), inside its y-band: moving left
    would end inside the wall, so only the vertical part is kept."""
    p = jnp.array([0.55, 0.205])
    q = move(p, jnp.array([-1.0, 0.0]))
    np.testing.assert_allclose(q, p, atol=1e-6)
    assert not bool(inside_a_wall(q))
    np.testing.assert_allclose(
        move(jnp.array([0.55, 0.30]), jnp.array([-1.0, 0.0])), [0.45, 0.30], atol=1e-6
    )


def test_the_gap_lets_the_point_through():
    p = jnp.array([-0.8, -0.55])
    for _ in range(3):
        p = move(p, jnp.array([0.0, 1.0]))
    assert p[1] > -0.49


def test_reset_ranges_and_determinism():
    env = make_env("pointmaze")
    states = jax.vmap(env.reset)(jax.random.split(jax.random.PRNGKey(1), 1000))
    x, y = np.asarray(states.core).T
    assert x.min() >= -0.1 and x.max() <= 0.1 and y.min() >= -1.0 and y.max() <= -0.7
    a, b = env.reset(jax.random.PRNGKey(3)), env.reset(jax.random.PRNGKey(3))
    np.testing.assert_array_equal(a.core, b.core)


def test_reward_and_goal_termination():
    env = make_env("pointmaze")
    state = env.reset(jax.random.PRNGKey(0)).replace(core=jnp.array([-0.5, 0.72]))
    nxt = env.step(state, jnp.array([0.0, 0.5]))  # lands on (-0.5, 0.77): inside the zone
    assert bool(nxt.done) and bool(in_goal(nxt.core))
    np.testing.assert_allclose(nxt.reward, -0.03, atol=1e-6)
    far = env.step(state.replace(core=jnp.array([0.5, -0.9])), jnp.zeros(2))
    assert not bool(far.done)
    np.testing.assert_allclose(
        far.reward, -np.linalg.norm(np.array([0.5, -0.9]) - np.array(GOAL)), rtol=1e-6
    )


def test_episode_ends_at_goal_and_is_frozen_after():
    env = make_env("pointmaze")

    def to_goal(params, obs):  # a hand-written policy: go left, then up through both gaps
        del params
        target = jnp.where(
            obs[1] < -0.45,
            jnp.array([-0.8, -0.4]),
            jnp.where(
                obs[1] < 0.25,
                jnp.where(obs[0] < 0.7, jnp.array([0.8, 0.0]), jnp.array([0.8, 0.4])),
                jnp.array(GOAL),
            ),
        )
        return jnp.clip((target - obs) * 20.0, -1.0, 1.0)

    ev = rollout(env, to_goal, jnp.zeros(()), jax.random.PRNGKey(0), return_trajectory=True)
    assert bool(in_goal(ev.descriptor))
    length = int(ev.length)
    assert 0 < length < env.episode_length
    # the descriptor is the position where the episode ended, not where the point drifted after
    np.testing.assert_allclose(ev.descriptor, np.asarray(ev.trajectory["next_obs"])[length - 1])
    valid = np.asarray(ev.trajectory["valid"])
    assert valid[:length].all() and not valid[length:].any()
    np.testing.assert_allclose(
        ev.fitness, np.asarray(ev.trajectory["reward"])[:length].sum(), rtol=1e-6
    )


def test_batched_evaluation_shapes_and_determinism():
    env = make_env("pointmaze")
    net = MLP((8, 2))
    params = init_policies(net, jax.random.PRNGKey(0), 5, env.observation_size)
    a = evaluate_policies(env, net.apply, params, jax.random.PRNGKey(1))
    b = evaluate_policies(env, net.apply, params, jax.random.PRNGKey(1))
    assert a.fitness.shape == (5,) and a.descriptor.shape == (5, 2)
    np.testing.assert_array_equal(a.fitness, b.fitness)
    np.testing.assert_array_equal(a.descriptor, b.descriptor)


def test_stochastic_policies_get_a_key_per_step_and_per_episode():
    """A keyed policy whose action is its key's uniform draw: actions differ across
    steps and episodes, and the same evaluation key gives the same episodes."""
    env = make_env("pointmaze", episode_length=20)
    draw = lambda params, obs, key: jax.random.uniform(key, (2,), minval=-1, maxval=1) * params
    run = lambda k: evaluate_policies(env, draw, jnp.ones((3,)), k, True, stochastic=True)
    a, b = run(jax.random.PRNGKey(1)), run(jax.random.PRNGKey(1))
    actions = np.asarray(a.trajectory["action"])  # episodes x time x 2
    np.testing.assert_array_equal(actions, np.asarray(b.trajectory["action"]))
    assert len(np.unique(actions[0, :, 0])) == actions.shape[1]  # a new key every step
    assert not np.allclose(actions[0], actions[1])  # and every episode
    still = evaluate_policies(
        env, draw, jnp.zeros((3,)), jax.random.PRNGKey(1), True, stochastic=True
    )
    assert np.all(np.asarray(still.trajectory["action"]) == 0)  # the key reaches the policy only


def test_unknown_environment_is_a_clear_error():
    with pytest.raises(
        ValueError, match="valid names: ant_omni, antmaze, anttrap, halfcheetah_uni, pointmaze"
    ):
        make_env("pointmaz")
