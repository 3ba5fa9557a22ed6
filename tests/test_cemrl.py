import jax
import jax.numpy as jnp
import numpy as np
import pytest

from qdnb.envs import make_env
from qdnb.nets.mlp import MLP
from qdnb.rl.cemrl import (
    CEMConfig,
    CEMRLAgent,
    cem_update,
    decay_epsilon,
    log_rank_weights,
)
from qdnb.rl.td3 import TD3Config


def _agent(num_episodes=5, **kw):
    env = make_env("pointmaze", episode_length=20)
    return CEMRLAgent(
        env=env,
        network=MLP((8, env.action_size), activation="relu"),
        td3_config=TD3Config(critic_hidden=(16,), batch_size=16, actor_lr=1e-2),
        num_episodes=num_episodes,
        num_critic_steps=4,
        buffer_size=5000,
        **kw,
    )


def test_log_rank_weights_by_hand():
    # K_e = 3: log 4 - log i = log 4, log 2, log 4/3; their sum is log(4 * 2 * 4/3) = log(32/3)
    expected = np.log([4.0, 2.0, 4.0 / 3.0]) / np.log(32.0 / 3.0)
    np.testing.assert_allclose(log_rank_weights(3), expected, rtol=1e-6)
    np.testing.assert_allclose(log_rank_weights(1), [1.0])
    w = np.asarray(log_rank_weights(5))
    assert np.all(np.diff(w) < 0) and abs(w.sum() - 1) < 1e-6  # decreasing with rank


def test_cem_update_on_a_hand_made_elite_set():
    mean = np.array([0.0, 1.0])
    var = np.array([0.5, 0.5])
    samples = np.array([[1.0, 1.0], [-2.0, 0.0], [3.0, 2.0], [0.0, -1.0]])
    fitnesses = np.array([2.0, -5.0, 7.0, 1.0])  # ranks: sample 2, then 0, then 3, then 1
    eps = 1e-3
    new_mean, new_var = cem_update(
        jnp.asarray(mean), jnp.asarray(var), jnp.asarray(samples), jnp.asarray(fitnesses), 2, eps
    )
    # K_e = 2: lambda = (log 3, log 3/2) / log(9/2); elites z_1 = [3, 2], z_2 = [1, 1]
    lam = np.log([3.0, 1.5]) / np.log(4.5)
    elites = samples[[2, 0]]
    np.testing.assert_allclose(new_mean, lam @ elites, rtol=1e-6)
    # deviations from the OLD mean [0, 1]: [3, 1] and [1, 0]
    np.testing.assert_allclose(
        new_var, lam[0] * np.array([9.0, 1.0]) + lam[1] * np.array([1.0, 0.0]) + eps, rtol=1e-6
    )
    # one elite: the best sample itself, its squared deviation plus epsilon
    m1, v1 = cem_update(mean, var, jnp.asarray(samples), jnp.asarray(fitnesses), 1, 0.0)
    np.testing.assert_allclose(m1, [3.0, 2.0])
    np.testing.assert_allclose(v1, [9.0, 1.0])


def test_epsilon_decay():
    eps = jnp.float32(1e-3)
    for _ in range(10):
        eps = decay_epsilon(eps, 0.95, 1e-5)
    # eps_n = eps_end + (eps_0 - eps_end) tau^n
    np.testing.assert_allclose(eps, 1e-5 + (1e-3 - 1e-5) * 0.95**10, rtol=1e-5)
    np.testing.assert_allclose(decay_epsilon(1e-5, 0.95, 1e-5), 1e-5, rtol=1e-6)  # fixed point


def test_cem_alone_maximises_a_quadratic():
    """The CEM loop without RL (sample, rank, cem_update, decay) on
    f(x) = -||x - target||^2 in 6 dimensions: the mean reaches the target."""
    target = jnp.array([1.0, -2.0, 0.5, 3.0, 0.0, -1.0])
    f = lambda x: -jnp.sum((x - target) ** 2, axis=-1)

    def generation(carry, key):
        mean, var, eps = carry
        samples = mean + jnp.sqrt(var) * jax.random.normal(key, (20,) + mean.shape)
        eps = decay_epsilon(eps, 0.95, 1e-5)
        mean, var = cem_update(mean, var, samples, f(samples), 10, eps)
        return (mean, var, eps), f(mean)

    init = (jnp.zeros(6), jnp.ones(6), jnp.float32(1e-3))
    (mean, var, _), scores = jax.lax.scan(
        generation, init, jax.random.split(jax.random.PRNGKey(0), 80)
    )
    assert float(scores[-1]) > -1e-2 and float(scores[-1]) > float(scores[0])
    np.testing.assert_allclose(mean, target, atol=0.05)
    assert float(var.max()) < 1e-2  # the distribution has contracted around it


def test_half_the_population_takes_gradient_steps():
    agent = _agent(num_episodes=5, num_actor_steps=20)  # 4 members, the first 2 improved
    assert (agent.population_size, agent.num_gradient_members, agent.num_elites) == (4, 2, 2)
    state, _ = jax.jit(agent.init)(jax.random.PRNGKey(0))
    td3, _ = agent.train_critic(state.td3, state.mean, state.buffer, jax.random.PRNGKey(1))
    samples = agent.sample(state.mean, state.var, jax.random.PRNGKey(2))
    assert samples.shape == (4, agent.num_params)
    out = jax.jit(agent.apply_gradients)(td3.critic, state.buffer, samples, jax.random.PRNGKey(3))
    np.testing.assert_array_equal(out[2:], samples[2:])  # the others: as sampled
    assert np.all(np.abs(np.asarray(out[:2] - samples[:2])).max(axis=1) > 1e-4)
    # the improved actors score higher under the critic they climbed (the actor loss -Q1)
    obs = state.buffer.sample(jax.random.PRNGKey(4), 256)["obs"]
    unravel = agent._unravel()
    loss = lambda flat: agent.td3.actor_loss(unravel(flat), td3.critic, obs)
    assert all(float(loss(out[i])) < float(loss(samples[i])) for i in range(2))


def test_agent_init_step_jit_and_run_seeds():
    from qdnb.qd.algorithms import run_seeds

    agent = _agent(num_episodes=4)
    state, ev = jax.jit(agent.init)(jax.random.PRNGKey(0))
    assert ev.fitness.shape == (4,)
    assert int(state.buffer.size) == int(ev.length.sum())  # every episode stored, the mean's too
    assert float(state.performance) == float(ev.fitness[0])
    state2, ev2 = jax.jit(agent.step)(state)
    assert ev2.fitness.shape == (4,) and float(state2.performance) == float(ev2.fitness[0])
    assert int(state2.buffer.size) == int(ev.length.sum() + ev2.length.sum())
    assert int(state2.td3.steps) == agent.num_critic_steps
    assert np.isfinite(float(state2.critic_loss)) and float(state2.critic_loss) > 0
    assert float(state2.epsilon) < float(state.epsilon)
    assert not np.allclose(state2.mean, state.mean)

    states, _, history = run_seeds(
        agent, jax.random.split(jax.random.PRNGKey(1), 2), 3, chunk_size=2, progress=False
    )
    assert history["max_fitness"].shape == (2, 4)
    assert np.all(np.isfinite(history["max_fitness"]))
    assert np.all(np.isfinite(states.critic_loss)) and np.all(np.isfinite(states.var))


def test_bad_config_values_raise():
    with pytest.raises(ValueError, match="num_episodes"):
        _agent(num_episodes=1)
    with pytest.raises(ValueError, match="num_actor_steps"):
        _agent(num_actor_steps=0)
    with pytest.raises(ValueError, match="elite_fraction"):
        CEMConfig(elite_fraction=0.0)
    with pytest.raises(ValueError, match="gradient_fraction"):
        CEMConfig(gradient_fraction=1.5)
    with pytest.raises(ValueError, match="sigma_init"):
        CEMConfig(sigma_init=0.0)
    with pytest.raises(ValueError, match="epsilon_decay"):
        CEMConfig(epsilon_decay=1.2)
