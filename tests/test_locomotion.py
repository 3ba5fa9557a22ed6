"""Brax tasks of Chapter 4: descriptors, fitness, contacts, resets."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from qdnb.envs import make_env
from qdnb.envs.rollout import evaluate_policies


@pytest.fixture(scope="module")
def ant():
    return make_env("ant_omni", episode_length=12)


@pytest.fixture(scope="module")
def cheetah():
    return make_env("halfcheetah_uni", episode_length=12)


def test_resets_are_deterministic_and_differ_by_key(ant, cheetah):
    for env in (ant, cheetah):
        reset = jax.jit(env.reset)
        a, b, c = (
            reset(jax.random.PRNGKey(0)),
            reset(jax.random.PRNGKey(0)),
            reset(jax.random.PRNGKey(1)),
        )
        np.testing.assert_array_equal(a.obs, b.obs)
        assert not np.allclose(a.obs, c.obs)
        assert a.obs.shape == (env.observation_size,)


def test_ant_omni_descriptor_and_fitness(ant):
    def policy(params, obs):  # a fixed open-loop-ish policy: actions of varying size
        return jnp.tanh(params * jnp.ones(ant.action_size) + 0.1 * obs[: ant.action_size])

    params = jnp.array([0.0, 0.5, 3.0])
    ev = jax.jit(lambda p, k: evaluate_policies(ant, policy, p, k, return_trajectory=True))(
        params, jax.random.PRNGKey(0)
    )
    assert ev.descriptor.shape == (3, 2)
    assert np.all(np.abs(ev.descriptor) <= 15.0)
    actions = np.clip(np.asarray(ev.trajectory["action"]), -1, 1)
    np.testing.assert_allclose(ev.fitness, -np.linalg.norm(actions, axis=-1).sum(axis=1), rtol=1e-5)
    # the descriptor is where the torso ended: the last state descriptor
    np.testing.assert_allclose(
        ev.descriptor, np.asarray(ev.trajectory["next_state_descriptor"])[:, -1], rtol=1e-6
    )
    assert np.all(np.asarray(ev.length) == 12)


def test_halfcheetah_contacts_are_real(cheetah):
    step = jax.jit(cheetah.step)
    sys = cheetah.brax_env.sys
    still = cheetah.reset(jax.random.PRNGKey(0))
    for _ in range(20):  # let it settle on the ground with no torque: it rests on its back foot
        still = step(still, jnp.zeros(cheetah.action_size))
    np.testing.assert_array_equal(still.state_descriptor, [0.0, 1.0])

    lifted_q = still.core.q.at[1].add(1.0)  # root z one metre up
    air = still.replace(core=cheetah.brax_env.pipeline_init(lifted_q, jnp.zeros(sys.qd_size())))
    air = step(air, jnp.zeros(cheetah.action_size))
    np.testing.assert_array_equal(air.state_descriptor, [0.0, 0.0])


def test_a_foot_that_touches_only_mid_step_touched_in_that_step():
    from qdnb.envs.locomotion import touched_in_step

    # 16 substeps, feet (front, back): the front foot touches in substeps 6 to 8 only, the
    # back foot never; read at the step's end (the last substep), neither would touch
    trace = np.zeros((16, 2), np.float32)
    trace[6:9, 0] = 1.0
    np.testing.assert_array_equal(touched_in_step(jnp.asarray(trace)), [1.0, 0.0])
    np.testing.assert_array_equal(trace[-1], [0.0, 0.0])
    np.testing.assert_array_equal(touched_in_step(jnp.ones((16, 2))), [1.0, 1.0])


def test_halfcheetah_reads_contacts_in_every_substep_as_the_simulator_sees_them(cheetah):
    """The step's contacts are the OR of brax's own contact distances (``contact.get``)
    at the start of each substep, and catch touches that the state at the step's end
    does not show."""
    from brax import contact

    sys, pipeline = cheetah.brax_env.sys, cheetah.brax_env._pipeline
    feet = cheetah._feet
    state = cheetah.reset(jax.random.PRNGKey(2))
    act = jax.random.uniform(jax.random.PRNGKey(3), (40, cheetah.action_size), minval=-1, maxval=1)

    @jax.jit
    def substep(ps, action):  # brax's contacts at the substep's start, then the substep
        c = contact.get(sys, ps.x)
        touching = [jnp.any((c.dist < 0) & ((c.geom1 == g) | (c.geom2 == g))) for g in feet]
        return jnp.stack(touching), pipeline.step(sys, ps, action)

    def by_hand(ps, action):  # substep by substep
        touching = []
        for _ in range(cheetah.brax_env._n_frames):
            touched, ps = substep(ps, action)
            touching.append(np.asarray(touched))
        return np.any(touching, axis=0), ps

    step = jax.jit(cheetah.step)
    mid_step_only = 0
    for action in act:
        expected, ps = by_hand(state.core, action)
        state = step(state, action)
        np.testing.assert_array_equal(state.state_descriptor, expected.astype(np.float32))
        np.testing.assert_allclose(state.core.x.pos, ps.x.pos, atol=1e-5)
        at_end = np.asarray(cheetah.foot_contacts(state.core))
        assert np.all(at_end <= state.state_descriptor + 1.0)  # sanity of the 0/1 values
        mid_step_only += int(np.sum((state.state_descriptor == 1.0) & (at_end == 0.0)))
    assert mid_step_only > 0


def test_halfcheetah_descriptor_averages_the_states_each_step_starts_from(cheetah):
    """QDax's window: the reset state's contacts and those of the steps but the last."""

    def policy(params, obs):
        del obs
        return params * jnp.ones(cheetah.action_size)

    ev = jax.jit(lambda p, k: evaluate_policies(cheetah, policy, p, k, return_trajectory=True))(
        jnp.array([0.0, 1.0]), jax.random.PRNGKey(3)
    )
    assert ev.descriptor.shape == (2, 2)
    assert np.all((ev.descriptor >= 0) & (ev.descriptor <= 1))
    np.testing.assert_allclose(
        ev.descriptor, np.asarray(ev.trajectory["state_descriptor"]).mean(axis=1), rtol=1e-6
    )


def test_the_models_collide_and_start_as_brax_v1s(ant, cheetah):
    import mujoco

    def names(env, geoms):
        model = env.brax_env.sys.mj_model
        return {mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_GEOM, int(g)) for g in geoms}

    from qdnb.envs.locomotion import floor_colliders

    assert names(cheetah, floor_colliders(cheetah.brax_env.sys.mj_model)) == {
        "torso", "head", "bthigh", "bshin", "bfoot", "fthigh", "fshin", "ffoot"
    }  # fmt: skip
    assert names(ant, floor_colliders(ant.brax_env.sys.mj_model)) == {
        "torso_geom", "left_foot_geom", "right_foot_geom", "third_foot_geom", "fourth_foot_geom"
    }  # fmt: skip
    np.testing.assert_array_equal(cheetah.brax_env.sys.actuator.gear, [120, 90, 60, 120, 60, 30])
    for env in (ant, cheetah):  # every reset rests on the floor
        states = jax.vmap(env.reset)(jax.random.split(jax.random.PRNGKey(0), 32))
        lowest = jax.vmap(env.lowest_point)(states.core.q)
        np.testing.assert_allclose(lowest, 0.0, atol=1e-5)


def test_halfcheetah_reward_is_forward_speed_minus_action_norm(cheetah):
    state = cheetah.reset(jax.random.PRNGKey(5))
    action = jnp.array([0.5, -0.5, 0.2, 0.0, 0.3, -2.0])  # the last one is clipped to -1
    nxt = jax.jit(cheetah.step)(state, action)
    forward = (nxt.core.x.pos[0, 0] - state.core.x.pos[0, 0]) / cheetah.brax_env.dt
    expected = forward - np.linalg.norm(np.clip(np.asarray(action), -1, 1))
    np.testing.assert_allclose(nxt.reward, expected, rtol=1e-5)
    assert int(nxt.steps) == 1 and not bool(nxt.done)


def test_loading_models_from_threads_leaves_stdout_and_stderr_alone():
    import os
    from concurrent.futures import ThreadPoolExecutor

    before = [os.fstat(fd) for fd in (1, 2)]
    with ThreadPoolExecutor(4) as pool:
        list(pool.map(lambda name: make_env(name), ["ant_omni", "halfcheetah_uni"] * 2))
    after = [os.fstat(fd) for fd in (1, 2)]
    assert [(s.st_dev, s.st_ino) for s in after] == [(s.st_dev, s.st_ino) for s in before]


def test_ant_omni_ends_when_the_torso_leaves_its_healthy_band(ant):
    sys = ant.brax_env.sys
    zero = jnp.zeros(ant.action_size)
    step = jax.jit(ant.step)
    at_height = lambda z: ant.state_at(sys.init_q.at[2].set(z), jnp.zeros(sys.qd_size()))
    assert bool(ant.healthy(at_height(0.75).core))
    assert not bool(ant.healthy(at_height(0.1).core))  # lying on the floor
    assert not bool(ant.healthy(at_height(1.5).core))  # in the air
    assert not bool(step(at_height(0.75), zero).done)  # standing: the episode goes on
    assert bool(
        step(at_height(1.5), zero).done
    )  # one step later it is still above 1.0: the episode ends
    # in a rollout, the steps after the end do not count
    from qdnb.envs.rollout import tally_start, tally_step

    start = at_height(1.5)
    tally, _ = tally_step(ant, tally_start(ant, start), step(start, zero))
    assert not bool(tally.alive) and int(tally.length) == 1


def test_ant_omni_survival_reward_makes_an_early_end_cost_one_per_step_not_lived(ant):
    """QDax's Ant pays 1 per step alive; the fitness takes the full episode's 12 back:
    Eq. 4.2 for a full episode, and an episode that ends after 1 step of action a
    scores -||a|| - 11 (falling is never cheaper than standing still)."""
    from qdnb.envs.rollout import tally_evaluation, tally_start, tally_step

    sys = ant.brax_env.sys
    action = jnp.full(ant.action_size, 0.5)  # ||a|| = sqrt(8) / 2
    step = jax.jit(ant.step)
    standing = ant.state_at(sys.init_q, jnp.zeros(sys.qd_size()))
    np.testing.assert_allclose(step(standing, action).reward, 1.0 - np.sqrt(2.0), rtol=1e-6)

    flying = ant.state_at(sys.init_q.at[2].set(1.5), jnp.zeros(sys.qd_size()))
    tally = tally_start(ant, flying)
    state = flying
    for _ in range(ant.episode_length):  # the steps after the first do not count
        state = step(state, action)
        tally, _ = tally_step(ant, tally, state)
    ev = tally_evaluation(ant, jax.tree.map(lambda x: x[None], tally))
    assert int(ev.length[0]) == 1
    np.testing.assert_allclose(ev.fitness[0], -np.sqrt(2.0) - (ant.episode_length - 1), rtol=1e-6)
    assert (
        float(ev.fitness[0]) < 0.0
    )  # standing still with no torque for the whole episode scores 0


def test_resets_follow_brax_v1_uniform_joint_noise_with_the_root_at_rest(ant, cheetah):
    for env, root_q, root_qd in ((ant, 7, 6), (cheetah, 3, 3)):
        sys = env.brax_env.sys
        states = jax.vmap(env.reset)(jax.random.split(jax.random.PRNGKey(0), 256))
        dq = np.asarray(states.core.q) - np.asarray(env._rest_q)
        qd = np.asarray(states.core.qd)
        # the root at rest: only its height moves (to rest on the floor)
        np.testing.assert_allclose(np.delete(dq[:, :root_q], env.root_z, axis=1), 0.0, atol=1e-6)
        np.testing.assert_allclose(qd[:, :root_qd], 0.0, atol=1e-6)
        for x in (dq[:, root_q:], qd[:, root_qd:]):
            assert np.all(np.abs(x) <= 0.1 + 1e-6)
            assert np.abs(x).max() > 0.09  # uniform on [-0.1, 0.1]: its edges are reached ...
            assert (
                abs(np.mean(np.abs(x)) - 0.05) < 0.005
            )  # ... and E|U| = 0.05 (a Gaussian of sd 0.1 gives 0.08)
        # brax v1's default angles: the middle of each limited hinge's range
        model = sys.mj_model
        hinges = (model.jnt_type == 3) & (model.jnt_limited != 0)
        np.testing.assert_allclose(
            env._rest_q[model.jnt_qposadr[hinges]], model.jnt_range[hinges].mean(1), rtol=1e-6
        )


def test_ant_omni_observes_neither_x_nor_y(ant):
    sys = ant.brax_env.sys
    here = ant.state_at(sys.init_q, jnp.zeros(sys.qd_size()))
    there = ant.state_at(sys.init_q.at[:2].set(jnp.array([3.0, -4.0])), jnp.zeros(sys.qd_size()))
    assert ant.observation_size == 27
    np.testing.assert_allclose(here.obs, there.obs, atol=1e-6)
    np.testing.assert_allclose(there.state_descriptor, [3.0, -4.0], atol=1e-5)


def test_a_bounded_box_clips_descriptors_and_holds_cells_and_goals():
    from qdnb.qd.cvt import cvt_centroids

    env = make_env(
        "ant_omni", episode_length=12, descriptor_low=(-2.5, -2.5), descriptor_high=(2.5, 2.5)
    )
    np.testing.assert_allclose(
        env.behaviour_descriptor(jnp.array([4.0, -1.0]), None, 12), [2.5, -1.0]
    )
    centroids = np.asarray(
        cvt_centroids(jax.random.PRNGKey(0), 16, env.descriptor_low, env.descriptor_high, 2000, 5)
    )
    assert np.all(np.abs(centroids) <= 2.5) and np.abs(centroids).max() > 1.0
    with pytest.raises(ValueError, match="low < high"):
        make_env("ant_omni", descriptor_low=(1.0, 1.0), descriptor_high=(0.0, 2.0))
