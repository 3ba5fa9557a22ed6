import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from qdnb.envs import make_env
from qdnb.nets.mlp import MLP, GaussianMLP, tanh_gaussian_sample
from qdnb.rl.buffer import ReplayBuffer
from qdnb.rl.diayn import DIAYN, diayn_reward, discriminator_loss
from qdnb.rl.sac import SAC, SACAgent, sac_actor_objective, sac_target, temperature_loss
from qdnb.rl.td3 import TD3Config


def _sac(**kwargs) -> SAC:
    cfg = TD3Config(critic_hidden=(8,), batch_size=4, gamma=0.9)
    return SAC(GaussianMLP((8,), 1), observation_size=2, action_size=1, config=cfg, **kwargs)


def _batch():
    return {
        "obs": jnp.array([[0.1, 0.2], [0.3, -0.4], [-0.5, 0.6], [0.0, 0.0]]),
        "action": jnp.array([[0.5], [-0.2], [0.9], [0.0]]),
        "reward": jnp.array([1.0, 0.5, -1.0, 0.0]),
        "next_obs": jnp.array([[0.2, 0.2], [0.3, -0.3], [-0.4, 0.6], [0.1, 0.0]]),
        "terminal": jnp.array([0.0, 1.0, 0.0, 0.0]),
    }


def test_sac_target_hand_checked():
    y = sac_target(
        reward=jnp.array([1.0, 0.5, -1.0]),
        terminal=jnp.array([0.0, 1.0, 0.0]),
        next_q1=jnp.array([10.0, 10.0, -2.0]),
        next_q2=jnp.array([8.0, 12.0, -3.0]),
        next_log_prob=jnp.array([-1.0, 3.0, 2.0]),
        alpha=0.5,
        gamma=0.9,
    )
    # 1 + 0.9 (min(10, 8) + 0.5); terminal: reward only; -1 + 0.9 (min(-2, -3) - 0.5 * 2)
    np.testing.assert_allclose(y, [1 + 0.9 * 8.5, 0.5, -1 + 0.9 * -4.0], rtol=1e-6)

    # with networks: a' is the current actor's sample, Q' the target critics'
    sac = _sac()
    state = sac.init(jax.random.PRNGKey(0))
    batch, key, alpha = _batch(), jax.random.PRNGKey(1), 0.3
    y = sac.target(state.critic_target, state.actor, alpha, batch, key)
    mean, log_std = sac.actor.apply(state.actor, batch["next_obs"])
    a, logp = tanh_gaussian_sample(mean, log_std, key)
    q1, q2 = sac.critic.apply(state.critic_target, batch["next_obs"], a)
    q1, q2, logp = (np.asarray(x, np.float64) for x in (q1, q2, logp))
    expected = np.asarray(batch["reward"]) + 0.9 * (1 - np.asarray(batch["terminal"])) * (
        np.minimum(q1, q2) - alpha * logp
    )
    np.testing.assert_allclose(y, expected, rtol=1e-5, atol=1e-6)


def test_temperature_rises_below_the_target_entropy_and_falls_above():
    log_prob = jnp.array([1.0, 2.0, 3.0])  # entropy estimate -2, target -1: too little
    loss, grad = jax.value_and_grad(temperature_loss)(jnp.log(0.5), log_prob, -1.0)
    # -log(0.5) * (mean(log pi) + target) = -log(0.5) * 1; d/dlog_alpha = -(2 - 1)
    np.testing.assert_allclose(loss, -math.log(0.5) * 1.0, rtol=1e-6)
    np.testing.assert_allclose(grad, -1.0, rtol=1e-6)
    _, grad = jax.value_and_grad(temperature_loss)(0.0, -log_prob, -1.0)  # entropy 2 > -1
    np.testing.assert_allclose(grad, 3.0, rtol=1e-6)

    # in a full update: an unreachable target (+10 nats on [-1, 1]) raises alpha by one
    # Adam step (lr), a very low one (-10) lowers it (alpha_lr = 0 keeps it: DIAYN's test)
    batch = _batch()
    for scale, sign in ((-10.0, 1.0), (10.0, -1.0)):
        sac = _sac(alpha_lr=0.01, target_entropy_scale=scale)
        state = sac.init(jax.random.PRNGKey(0))
        new, _ = jax.jit(sac.update)(state, batch, jax.random.PRNGKey(1))
        np.testing.assert_allclose(new.log_alpha - state.log_alpha, sign * 0.01, atol=1e-4)


def test_actor_loss_hand_checked():
    # mean(alpha log pi - min(Q1, Q2)) = mean(0.5*[-1, 2] - [3, -1]) = mean([-3.5, 2])
    np.testing.assert_allclose(
        sac_actor_objective(
            jnp.array([-1.0, 2.0]), jnp.array([3.0, 0.0]), jnp.array([4.0, -1.0]), 0.5
        ),
        -0.75,
        rtol=1e-6,
    )
    sac = _sac()
    state = sac.init(jax.random.PRNGKey(0))
    obs, key = _batch()["obs"], jax.random.PRNGKey(2)
    loss, log_prob = sac.actor_loss(state.actor, state.critic, 0.2, obs, key)
    a, logp = tanh_gaussian_sample(*sac.actor.apply(state.actor, obs), key)
    q1, q2 = sac.critic.apply(state.critic, obs, a)
    expected = np.mean(0.2 * np.asarray(logp) - np.minimum(np.asarray(q1), np.asarray(q2)))
    np.testing.assert_allclose(loss, expected, rtol=1e-5)
    np.testing.assert_allclose(log_prob, logp, rtol=1e-6)


def test_sac_learns_a_one_step_bandit():
    """Reward -(a - 0.5)^2 on terminal transitions: the greedy action tanh(mean) moves to 0.5
    and the temperature falls (the entropy target -1 is far below a wide Gaussian's)."""
    cfg = TD3Config(critic_hidden=(32, 32), batch_size=64, critic_lr=3e-3, actor_lr=3e-3)
    sac = SAC(GaussianMLP((16,), 1), 1, 1, cfg, alpha_lr=3e-3, initial_alpha=0.1)
    actions = jax.random.uniform(jax.random.PRNGKey(1), (512, 1), minval=-1, maxval=1)
    buf = ReplayBuffer.create(512, 1, 1).add(
        {
            "obs": jnp.zeros((512, 1)),
            "action": actions,
            "reward": -((actions[:, 0] - 0.5) ** 2),
            "next_obs": jnp.zeros((512, 1)),
            "terminal": jnp.ones(512),
        }
    )
    state = sac.init(jax.random.PRNGKey(0))
    before = float(sac.greedy(state.actor, jnp.zeros(1))[0])
    state, losses = jax.jit(lambda s, k: sac.train(s, buf, k, 1000))(state, jax.random.PRNGKey(2))
    after = float(sac.greedy(state.actor, jnp.zeros(1))[0])
    assert abs(after - 0.5) < 0.1 < abs(before - 0.5)
    assert float(jnp.exp(state.log_alpha)) < 0.1
    assert int(state.steps) == 1000 and all(np.isfinite(float(v)) for v in losses.values())


def test_diayn_reward_and_loss_hand_checked():
    logits = jnp.array([[2.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    skill = jax.nn.one_hot(jnp.array([0, 2]), 3)
    # log softmax([2, 0, 0])[0] = 2 - log(e^2 + 2); uniform logits: log(1/3) + log 3 = 0
    first = 2.0 - math.log(math.exp(2.0) + 2.0)
    np.testing.assert_allclose(diayn_reward(logits, skill), [first + math.log(3), 0.0], atol=1e-6)
    np.testing.assert_allclose(
        discriminator_loss(logits, skill), -(first + math.log(1 / 3)) / 2, rtol=1e-6
    )


def _diayn(env, **kwargs):
    return DIAYN(
        env=env,
        network=MLP((8, 2), activation="relu"),
        td3_config=TD3Config(critic_hidden=(8,), batch_size=16),
        num_episodes=3,
        num_critic_steps=4,
        buffer_size=1000,
        **{"num_skills": 4, "discriminator_hidden": (16,), **kwargs},
    )


def test_diayn_discriminator_separates_two_skills():
    """Skill 0 ends on the left of the maze, skill 1 on the right: after some steps the
    discriminator tells them apart and the reward approaches its maximum log 2."""
    algo = _diayn(make_env("pointmaze", episode_length=20), num_skills=2, discriminator_lr=1e-2)
    key = jax.random.PRNGKey(0)
    skills = jnp.arange(256) % 2
    centres = jnp.array([[-0.5, 0.3], [0.5, -0.2]])[skills]
    descriptors = centres + 0.1 * jax.random.normal(key, (256, 2))
    one_hot = jax.nn.one_hot(skills, 2)
    disc = algo.discriminator.init(key, jnp.zeros(2))
    opt = algo.discriminator_optimizer.init(disc)

    def one(carry, _):
        disc, opt, loss = algo.discriminator_step(*carry, descriptors, one_hot)
        return (disc, opt), loss

    (disc, _), losses = jax.lax.scan(one, (disc, opt), None, length=100)
    assert float(losses[-1]) < 0.05 < math.log(2) - 0.2 < float(losses[0])
    reward = algo.reward(disc, descriptors, one_hot)
    assert float(jnp.mean(reward)) > math.log(2) - 0.05
    predicted = jnp.argmax(algo.logits(disc, descriptors), axis=-1)
    assert float(jnp.mean(predicted == skills)) == 1.0


@pytest.fixture(scope="module")
def maze():
    return make_env("pointmaze", episode_length=20)


def _run(algo):
    """``run_seeds`` over two seeds for three iterations: final states and history."""
    from qdnb.qd.algorithms import run_seeds

    states, _, history = run_seeds(
        algo, jax.random.split(jax.random.PRNGKey(0), 2), 3, chunk_size=2, progress=False
    )
    assert history["max_fitness"].shape == (2, 4)
    assert np.all(np.isfinite(history["max_fitness"]))
    assert history["fitnesses"].shape == (2, 4, algo.num_episodes)
    # every valid transition stored, num_critic_steps gradient steps per iteration
    np.testing.assert_array_equal(states.buffer.size, history["env_steps"].sum(axis=1))
    np.testing.assert_array_equal(states.sac.steps, 3 * algo.num_critic_steps)
    return states, history


def test_sac_agent_greedy_then_sampled_episodes_and_run_seeds(maze):
    agent = SACAgent(
        env=maze,
        network=MLP((8, 2), activation="relu"),
        td3_config=TD3Config(critic_hidden=(8,), batch_size=16),
        num_episodes=3,
        num_critic_steps=4,
        buffer_size=1000,
    )
    state, ev = jax.jit(agent.init)(jax.random.PRNGKey(0))
    obs, actions = ev.trajectory["obs"], np.asarray(ev.trajectory["action"])
    greedy = jax.vmap(jax.vmap(lambda o: agent.sac.greedy(state.sac.actor, o)))(obs)
    np.testing.assert_allclose(actions[0], greedy[0], rtol=1e-5, atol=1e-6)
    assert not np.allclose(actions[1:], greedy[1:], atol=1e-3)  # the others sample
    assert float(agent.metrics(state)["max_fitness"]) == float(ev.fitness[0])
    assert int(state.buffer.size) == int(ev.length.sum())

    _, history = _run(agent)
    # performance: the greedy (first) episode of the latest iteration
    np.testing.assert_array_equal(history["max_fitness"], history["fitnesses"][..., 0])


def test_diayn_stores_skills_cycles_greedy_skills_and_run_seeds(maze):
    algo = _diayn(maze, num_skills=5)
    states, history = _run(algo)
    # skills 0..3 had their greedy turns (init and three steps), skill 4 not yet
    greedy_returns = history["fitnesses"][..., 0]
    np.testing.assert_array_equal(states.skill_returns[:, :4], greedy_returns)
    assert np.all(states.skill_returns[:, 4] == -np.inf)
    np.testing.assert_array_equal(
        history["max_fitness"], np.maximum.accumulate(greedy_returns, axis=1)
    )
    np.testing.assert_allclose(jnp.exp(states.sac.log_alpha), 0.1, rtol=1e-6)  # fixed alpha
    # the buffer stores each transition's skill and the descriptor of s' (on Point-Maze,
    # the position: the next observation); init's greedy episode, 20 steps (the goal is
    # out of reach), comes first with skill 0
    size = int(states.buffer.size[0])
    data = jax.tree.map(lambda x: np.asarray(x[0, :size]), states.buffer.data)
    assert set(data["skill"].tolist()) <= {0.0, 1.0, 2.0, 3.0, 4.0}
    np.testing.assert_array_equal(data["skill"][:20], 0.0)
    np.testing.assert_allclose(data["next_state_descriptor"], data["next_obs"])
    assert not np.allclose(data["next_state_descriptor"], data["obs"])
    batch, z = algo.conditioned(jax.tree.map(lambda x: x[:3], data))
    np.testing.assert_array_equal(batch["obs"], np.concatenate([data["obs"][:3], z], 1))
    np.testing.assert_array_equal(batch["next_obs"][:, 2:], np.eye(5)[[0, 0, 0]])


def test_bad_configs_raise(maze):
    net = MLP((8, 2), activation="relu")
    with pytest.raises(ValueError, match="num_episodes"):
        SACAgent(maze, net, num_episodes=0)
    with pytest.raises(ValueError, match="initial_alpha"):
        SACAgent(maze, net, initial_alpha=0.0)
    with pytest.raises(ValueError, match="alpha_lr"):
        SACAgent(maze, net, alpha_lr=-1.0)
    with pytest.raises(ValueError, match="action size"):
        SACAgent(maze, MLP((8, 3)))
    with pytest.raises(ValueError, match="num_skills"):
        DIAYN(maze, net, num_skills=1)
    with pytest.raises(ValueError, match="discriminator_lr"):
        DIAYN(maze, net, discriminator_lr=0.0)
    with pytest.raises(ValueError, match="num_critic_steps"):
        DIAYN(maze, net, num_critic_steps=0)
