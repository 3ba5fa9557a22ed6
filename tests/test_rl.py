import jax
import jax.numpy as jnp
import numpy as np
import pytest

from qdnb.nets.mlp import MLP
from qdnb.rl.buffer import ReplayBuffer
from qdnb.rl.td3 import TD3, TD3Config, td3_target


def _transitions(values):
    v = jnp.asarray(values, jnp.float32)
    n = v.shape[0]
    return {
        "obs": jnp.tile(v[:, None], (1, 2)),
        "action": v[:, None],
        "reward": v,
        "next_obs": jnp.tile(v[:, None] + 1, (1, 2)),
        "terminal": jnp.zeros(n),
    }


def test_replay_buffer_wraps_around_and_skips_invalid():
    buf = ReplayBuffer.create(capacity=4, observation_size=2, action_size=1)
    buf = buf.add(_transitions([1, 2, 3]))
    assert int(buf.size) == 3 and int(buf.position) == 3
    buf = buf.add(_transitions([4, 5, 6]), valid=jnp.array([True, False, True]))
    # 4 goes to slot 3, 6 wraps around to slot 0 (overwriting 1); 5 is skipped
    np.testing.assert_array_equal(buf.data["reward"], [6, 2, 3, 4])
    assert int(buf.size) == 4 and int(buf.position) == 1
    sample = buf.sample(jax.random.PRNGKey(0), 100)
    assert set(np.asarray(sample["reward"]).tolist()) <= {2.0, 3.0, 4.0, 6.0}
    np.testing.assert_array_equal(sample["obs"][:, 0], sample["reward"])  # rows stay together
    with pytest.raises(ValueError, match="capacity"):
        buf.add(_transitions([1, 2, 3, 4, 5]))


def test_td3_target_hand_checked():
    y = td3_target(
        reward=jnp.array([1.0, 0.5, -1.0]),
        terminal=jnp.array([0.0, 1.0, 0.0]),
        next_q1=jnp.array([10.0, 10.0, -2.0]),
        next_q2=jnp.array([8.0, 12.0, -3.0]),
        gamma=0.9,
    )
    # 1 + 0.9 * min(10, 8); terminal: reward only; -1 + 0.9 * min(-2, -3)
    np.testing.assert_allclose(y, [1 + 0.9 * 8, 0.5, -1 + 0.9 * -3], rtol=1e-6)


def test_td3_target_uses_smoothed_clipped_target_actions():
    td3 = TD3(
        MLP((4, 1)),
        observation_size=2,
        action_size=1,
        config=TD3Config(critic_hidden=(8,), policy_noise=0.0),
    )
    state = td3.init(jax.random.PRNGKey(0))
    batch = _transitions([0.5, -0.5])
    y = td3.target(state.critic_target, state.actor_target, batch, jax.random.PRNGKey(1))
    a = td3.actor.apply(state.actor_target, batch["next_obs"])
    q1, q2 = td3.critic.apply(state.critic_target, batch["next_obs"], a)
    np.testing.assert_allclose(y, batch["reward"] + 0.99 * np.minimum(q1, q2), rtol=1e-5)


def test_td3_learns_a_one_step_bandit():
    """Reward = -(a - 0.5)^2 and terminal transitions: the critic learns it and
    the actor's action moves to 0.5."""
    cfg = TD3Config(
        critic_hidden=(32, 32), batch_size=64, critic_lr=3e-3, actor_lr=3e-3, policy_delay=2
    )
    td3 = TD3(MLP((16, 1)), observation_size=1, action_size=1, config=cfg)
    state = td3.init(jax.random.PRNGKey(0))
    key = jax.random.PRNGKey(1)
    actions = jax.random.uniform(key, (512, 1), minval=-1, maxval=1)
    data = {
        "obs": jnp.zeros((512, 1)),
        "action": actions,
        "reward": -((actions[:, 0] - 0.5) ** 2),
        "next_obs": jnp.zeros((512, 1)),
        "terminal": jnp.ones(512),
    }
    buf = ReplayBuffer.create(512, 1, 1).add(data)

    state, losses = jax.jit(lambda s, k: td3.train_critic(s, buf, k, 1500))(state, key)
    action = float(td3.actor.apply(state.actor, jnp.zeros(1))[0])
    assert abs(action - 0.5) < 0.1
    q1, _ = td3.critic.apply(state.critic, jnp.zeros((1, 1)), jnp.array([[0.5]]))
    assert abs(float(q1[0])) < 0.05  # the best action's value, 0
    # the PGA-ME variation moves a fresh actor towards the same optimum against the trained critic
    fresh = td3.actor.init(jax.random.PRNGKey(7), jnp.zeros(1))
    improved = td3.policy_gradient_steps(fresh, state.critic, buf, jax.random.PRNGKey(2), 50)
    before = abs(float(td3.actor.apply(fresh, jnp.zeros(1))[0]) - 0.5)
    after = abs(float(td3.actor.apply(improved, jnp.zeros(1))[0]) - 0.5)
    assert after < before


def test_pga_me_and_pga_me_ls_iterate_fill_the_buffer_and_train_the_critic():
    from qdnb.envs import make_env
    from qdnb.qd.cvt import grid_centroids
    from qdnb.qd.pga import PGAMapElites, PGAMapElitesLowSpread

    env = make_env("pointmaze", episode_length=20)
    common = dict(
        env=env,
        network=MLP((8, 2)),
        batch_size=6,
        iso_sigma=0.05,
        line_sigma=0.1,
        centroids=grid_centroids((4, 4), (-1, -1), (1, 1)),
        fitness_offset=-100.0,
        td3_config=TD3Config(critic_hidden=(16,), batch_size=8),
        num_critic_steps=4,
        num_pg_steps=3,
        buffer_size=2000,
    )
    for algo, episodes in [
        (PGAMapElites(**common), 1),
        (PGAMapElitesLowSpread(**common, num_episodes=2), 2),
    ]:
        state, ev = jax.jit(algo.init)(jax.random.PRNGKey(0))
        assert int(state.buffer.size) == int(ev.length.sum())  # every valid transition, no more
        assert (
            int(state.td3.steps) == 4
        )  # the initial batch trains the critic before the first emission
        step = jax.jit(algo.step)
        state2, ev2 = step(state)
        assert ev2.fitness.shape == ((6,) if episodes == 1 else (6, 2))
        assert int(state2.buffer.size) == int(ev.length.sum() + ev2.length.sum())
        assert int(state2.td3.steps) == 8  # num_critic_steps more per step
        critic_moved = jax.tree.leaves(
            jax.tree.map(lambda a, b: jnp.abs(a - b).max(), state.td3.critic, state2.td3.critic)
        )
        assert max(float(x) for x in critic_moved) > 0
        assert bool(algo.elites(state2.repertoire).filled.any())


def test_tanh_gaussian_density_integrates_to_one_and_matches_its_samples():
    from qdnb.nets.mlp import GaussianMLP, tanh_gaussian_log_prob, tanh_gaussian_sample

    mean, log_std = jnp.array([0.3]), jnp.array([-0.5])
    grid = jnp.linspace(-1 + 1e-5, 1 - 1e-5, 200_001)[:, None]
    density = jnp.exp(jax.vmap(lambda a: tanh_gaussian_log_prob(mean, log_std, a))(grid))
    mass = np.trapezoid(np.asarray(density, np.float64), np.asarray(grid[:, 0], np.float64))
    np.testing.assert_allclose(mass, 1.0, atol=1e-3)
    action, log_prob = tanh_gaussian_sample(mean, log_std, jax.random.PRNGKey(0))
    assert -1 < float(action[0]) < 1
    np.testing.assert_allclose(log_prob, tanh_gaussian_log_prob(mean, log_std, action), rtol=1e-4)
    net = GaussianMLP((8,), action_size=3, log_std_bounds=(-2.0, 1.0))
    params = net.init(jax.random.PRNGKey(1), jnp.zeros(5))
    m, s = net.apply(params, 100 * jnp.ones((4, 5)))
    assert m.shape == s.shape == (4, 3) and float(s.min()) >= -2 and float(s.max()) <= 1
