from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from qdnb.envs import make_env
from qdnb.envs.base import Env, EnvState
from qdnb.nets.mlp import MLP, tanh_gaussian_log_prob, tanh_gaussian_sample
from qdnb.qd.algorithms import run_seeds
from qdnb.rl.agac import (
    AGACAgent,
    AGACConfig,
    agac_advantage,
    gae,
    gaussian_kl,
    ppo_clip_loss,
)


@dataclass(frozen=True)
class Bandit(Env):
    """A one-step bandit: reward -(a - 0.5)^2, then the episode ends (a true terminal:
    the scan runs two steps, the second one invalid)."""

    episode_length: int = 2
    observation_size: int = 1
    action_size: int = 1
    descriptor_size: int = 1
    descriptor_low: tuple[float, ...] = (-1.0,)
    descriptor_high: tuple[float, ...] = (1.0,)

    def reset(self, key):
        return EnvState(
            core=jnp.zeros(1),
            obs=jnp.ones(1),
            reward=jnp.zeros(()),
            done=jnp.zeros((), bool),
            state_descriptor=jnp.zeros(1),
            steps=jnp.zeros((), jnp.int32),
        )

    def step(self, state, action):
        return EnvState(
            core=action,
            obs=jnp.ones(1),
            reward=-jnp.sum((action - 0.5) ** 2),
            done=jnp.ones((), bool),
            state_descriptor=action,
            steps=state.steps + 1,
        )


def test_gae_hand_checked_with_terminal_and_truncation():
    gamma, lam = 0.9, 0.8
    # episode 0: ends on a true terminal at t=1 (t=2 is past its end);
    # episode 1: cut by the time limit at t=2 (bootstraps on V(s_3) = 10).
    reward = np.array([[1.0, 2.0, 5.0], [1.0, -1.0, 0.5]])
    value = np.array([[0.5, 1.0, 7.0], [2.0, 1.0, 3.0]])
    next_value = np.array([[1.0, 9.0, 7.0], [1.0, 3.0, 10.0]])
    terminal = np.array([[0, 1, 0], [0, 0, 0]], bool)
    done = np.array([[0, 1, 1], [0, 0, 1]], bool)
    valid = np.array([[1, 1, 0], [1, 1, 1]], bool)
    adv = gae(reward, value, next_value, terminal, done, valid, gamma, lam)

    d01 = 2.0 - 1.0  # terminal: no bootstrap
    d00 = 1.0 + gamma * 1.0 - 0.5
    d12 = 0.5 + gamma * 10.0 - 3.0  # truncation: bootstrap on V(next_obs)
    d11 = -1.0 + gamma * 3.0 - 1.0
    d10 = 1.0 + gamma * 1.0 - 2.0
    a11 = d11 + gamma * lam * d12
    expected = np.array(
        [
            [d00 + gamma * lam * d01, d01, 0.0],
            [d10 + gamma * lam * a11, a11, d12],
        ]
    )
    np.testing.assert_allclose(adv, expected, rtol=1e-6)


def test_agac_advantage_adds_the_discrepancy():
    advantage = jnp.array([1.0, -2.0, 0.5])
    log_pi = jnp.array([-1.0, -0.5, -3.0])
    log_pi_adv = jnp.array([-2.0, -0.5, -1.0])  # discrepancy: 1, 0, -2
    out = agac_advantage(advantage, log_pi, log_pi_adv, 0.1)
    np.testing.assert_allclose(out, [1.1, -2.0, 0.3], rtol=1e-6)


def test_ppo_clipped_loss_hand_checked():
    ratio = np.array([1.5, 0.5, 0.5, 1.1, 3.0])
    advantage = jnp.array([1.0, 1.0, -1.0, -2.0, 100.0])
    mask = jnp.array([1, 1, 1, 1, 0], bool)  # the last row does not count
    log_pi_old = jnp.array([-1.0, 0.3, -2.0, 0.0, 1.0])
    log_pi = log_pi_old + jnp.log(ratio)
    loss = ppo_clip_loss(log_pi, log_pi_old, advantage, mask, clip=0.2)
    # min(1.5, 1.2) = 1.2; min(0.5, 0.8) = 0.5; min(-0.5, -0.8) = -0.8; min(-2.2, -2.2)
    np.testing.assert_allclose(loss, -(1.2 + 0.5 - 0.8 - 2.2) / 4, rtol=1e-5)


def test_gaussian_kl_is_the_kl_of_the_squashed_policies():
    """Closed-form KL of the pre-squash Gaussians = Monte-Carlo mean of
    log pi(a) - log pi_adv(a) over squashed samples a ~ pi (the sampled bonus)."""
    mean_p, log_std_p = jnp.array([0.3, -0.2]), jnp.array([-0.5, 0.1])
    mean_q, log_std_q = jnp.array([-0.1, 0.4]), jnp.array([0.0, -0.3])
    keys = jax.random.split(jax.random.PRNGKey(0), 100_000)
    actions, logp = jax.vmap(lambda k: tanh_gaussian_sample(mean_p, log_std_p, k))(keys)
    logq = tanh_gaussian_log_prob(mean_q, log_std_q, actions)
    kl = gaussian_kl(mean_p, log_std_p, mean_q, log_std_q)
    np.testing.assert_allclose(jnp.mean(logp - logq), kl, rtol=0.03)
    assert float(gaussian_kl(mean_p, log_std_p, mean_p, log_std_p)) == pytest.approx(0.0)


def _pointmaze_agent(**kw):
    env = make_env("pointmaze", episode_length=20)
    return AGACAgent(env, MLP((16, env.action_size), activation="relu"), **kw)


def test_adversary_learns_to_imitate_the_actor():
    agent = _pointmaze_agent()
    k_actor, k_adv, k_obs = jax.random.split(jax.random.PRNGKey(1), 3)
    actor = agent.policy.init(k_actor, jnp.zeros(2))
    adversary = agent.policy.init(k_adv, jnp.zeros(2))
    obs = jax.random.uniform(k_obs, (256, 2), minval=-1.0, maxval=1.0)
    mean, log_std = agent.policy.apply(actor, obs)
    mask = jnp.ones(256, bool)
    loss_fn = jax.jit(lambda p: agent.adversary_loss(p, obs, mean, log_std, mask))
    opt = optax.adam(1e-2)

    @jax.jit
    def train(params):
        def one(carry, _):
            p, s = carry
            updates, s = opt.update(jax.grad(loss_fn)(p), s)
            return (optax.apply_updates(p, updates), s), None

        return jax.lax.scan(one, (params, opt.init(params)), None, length=300)[0][0]

    before = float(loss_fn(adversary))
    after = float(loss_fn(train(adversary)))
    assert before > 0.05 and after < 0.1 * before


def test_greedy_episode_first_and_left_out_of_the_batch():
    agent = _pointmaze_agent(num_episodes=3)
    state, ev = jax.jit(agent.init)(jax.random.PRNGKey(0))
    traj = ev.trajectory
    mean, _ = agent.policy.apply(state.actor, traj["obs"][0])
    np.testing.assert_allclose(traj["action"][0], jnp.tanh(mean), atol=1e-6)
    assert float(ev.fitness[0]) == float(state.performance)
    batch = agent.prepare_batch(state, traj)
    assert batch["obs"].shape == (2 * 20, 2)  # the two sampled episodes only
    np.testing.assert_array_equal(batch["obs"], traj["obs"][1:].reshape(-1, 2))


def test_agac_coefficient_anneals_linearly_to_zero():
    agent = _pointmaze_agent(config=AGACConfig(agac_c=0.4), num_iterations=10)
    c = [float(agent.agac_coefficient(i)) for i in (0, 5, 10, 20)]
    np.testing.assert_allclose(c, [0.4, 0.2, 0.0, 0.0], atol=1e-7)
    assert float(_pointmaze_agent().agac_coefficient(100)) == pytest.approx(4e-4)


def test_learns_a_one_step_bandit():
    env = Bandit()
    cfg = AGACConfig(actor_lr=3e-3, critic_lr=3e-3, adversary_lr=1e-3, num_epochs=10)
    agent = AGACAgent(env, MLP((16, 1), activation="relu"), num_episodes=32, config=cfg)
    state, _ = jax.jit(agent.init)(jax.random.PRNGKey(1))
    first = float(agent.metrics(state)["max_fitness"])
    step = jax.jit(agent.step)
    for _ in range(30):
        state, _ = step(state)
    mean, _ = agent.policy.apply(state.actor, jnp.ones(1))
    # the greedy action starts far from 0.5 (this seed: return about -1) and reaches it
    assert first < -0.3
    assert abs(float(jnp.tanh(mean[0])) - 0.5) < 0.05


def test_jits_and_runs_under_run_seeds():
    agent = _pointmaze_agent(
        num_episodes=4, config=AGACConfig(num_epochs=2, minibatch_size=32), num_iterations=3
    )
    states, _, history = run_seeds(
        agent, jax.random.split(jax.random.PRNGKey(0), 2), 3, chunk_size=2, progress=False
    )
    assert history["max_fitness"].shape == (2, 4)
    assert np.all(np.isfinite(history["max_fitness"]))
    assert np.all(np.asarray(history["env_steps"]) > 0)
    assert np.all(np.asarray(states.iteration) == 3)
    for leaf in jax.tree.leaves((states.actor, states.critic, states.adversary)):
        assert np.all(np.isfinite(leaf))


@pytest.mark.parametrize(
    "kw",
    [
        {"clip": 0.0},
        {"gamma": 1.5},
        {"gae_lambda": -0.1},
        {"num_epochs": 0},
        {"minibatch_size": 0},
        {"agac_c": -1.0},
        {"actor_lr": 0.0},
    ],
)
def test_bad_config_raises(kw):
    with pytest.raises(ValueError):
        AGACConfig(**kw)


def test_bad_agent_raises():
    with pytest.raises(ValueError, match="num_episodes"):
        _pointmaze_agent(num_episodes=1)
    with pytest.raises(ValueError, match="num_iterations"):
        _pointmaze_agent(num_iterations=0)
    env = make_env("pointmaze", episode_length=20)
    with pytest.raises(ValueError, match="action size"):
        AGACAgent(env, MLP((16, 3)))
