"""RND (qdnb/rl/rnd.py) and P3S-TD3 (qdnb/rl/p3s.py), the Chapter 3 baselines built on TD3."""

from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from qdnb.core.tree import stack
from qdnb.envs import make_env
from qdnb.envs.base import Env, EnvState
from qdnb.nets.mlp import MLP
from qdnb.qd.algorithms import run_seeds
from qdnb.rl.buffer import ReplayBuffer
from qdnb.rl.p3s import (
    GuidedTD3,
    P3SConfig,
    P3SState,
    P3STD3Agent,
    adapt_beta,
    policy_distance,
    select_best,
)
from qdnb.rl.rnd import RNDAgent, RNDConfig, RNDState, RunningMoments, forward_filter
from qdnb.rl.td3 import TD3Config, TD3State


@dataclass(frozen=True)
class Bandit(Env):
    """A one-step task: reward -(a - 0.5)^2, then a terminal state; the state
    descriptor of the state reached is the action taken."""

    episode_length: int = 2
    observation_size: int = 1
    action_size: int = 1
    descriptor_size: int = 1
    descriptor_low: tuple[float, ...] = (-1.0,)
    descriptor_high: tuple[float, ...] = (1.0,)

    def reset(self, key):
        z = jnp.zeros((1,))
        return EnvState(z, z, jnp.zeros(()), jnp.zeros((), bool), z, jnp.zeros((), jnp.int32))

    def step(self, state, action):
        reward = -jnp.sum((action - 0.5) ** 2)
        return EnvState(action, state.obs, reward, jnp.ones((), bool), action, state.steps + 1)


TINY_TD3 = TD3Config(critic_hidden=(16,), batch_size=16)
FAST_TD3 = TD3Config(critic_hidden=(32, 32), batch_size=32, critic_lr=3e-3, actor_lr=3e-3)
TINY_RND = RNDConfig(hidden=(16,), embedding_size=8)


def _policy(hidden=8, action_size=2):
    return MLP((hidden, action_size), activation="relu")


# --- RND -------------------------------------------------------------------------


def test_running_moments_and_the_intrinsic_return_by_hand():
    m = RunningMoments.create()
    np.testing.assert_allclose([m.mean, m.var, m.count], [0.0, 1.0, 1e-4])
    m = m.update(jnp.array([1.0, 2.0, 3.0]), jnp.array([True, True, True]))
    m = m.update(jnp.array([4.0, 100.0]), jnp.array([True, False]))  # 100 is padding
    # the prior (mean 0, variance 1, count 1e-4) then 1, 2, 3, 4: mean 2.5, variance 1.25
    n, eps = 4.0, 1e-4
    mean = 10.0 / (n + eps)
    var = (eps * (1.0 + mean**2) + np.sum((np.arange(1, 5) - mean) ** 2)) / (n + eps)
    np.testing.assert_allclose([m.mean, m.var, m.count], [mean, var, n + eps], rtol=1e-5)
    np.testing.assert_allclose([m.mean, m.var], [2.5, 1.25], rtol=1e-3)
    # per dimension, rows masked out
    m2 = RunningMoments.create((2,)).update(
        jnp.array([[0.0, 10.0], [2.0, 30.0], [9.0, 9.0]]), jnp.array([True, True, False])
    )
    np.testing.assert_allclose(m2.mean, [1.0, 20.0], rtol=1e-3)
    np.testing.assert_allclose(m2.var, [1.0, 100.0], rtol=1e-3)
    # R <- 0.5 R + r at valid steps, carried from one call (episode) to the next
    carry, returns = forward_filter(
        jnp.array([0.0, 2.0]),
        jnp.array([[1.0, 2.0, 4.0], [1.0, 1.0, 1.0]]),
        jnp.array([[True, True, False], [True, True, True]]),
        0.5,
    )
    np.testing.assert_allclose(returns, [[1.0, 2.5, 2.5], [2.0, 2.0, 2.0]])
    np.testing.assert_allclose(carry, [2.5, 2.0])


def _rnd_state(agent, key):
    """An RND state holding only what the bonus needs (fixed input statistics)."""
    k_t, k_p = jax.random.split(key)
    d = agent.env.descriptor_size
    predictor = agent.predictor_network.init(k_p, jnp.zeros(d))
    moments = RunningMoments(jnp.zeros(d), jnp.full((d,), 0.25), jnp.asarray(100.0))
    return RNDState(
        td3=None,
        buffer=None,
        target=agent.target_network.init(k_t, jnp.zeros(d)),
        predictor=predictor,
        predictor_opt=agent.predictor_optimizer.init(predictor),
        input_moments=moments,
        return_moments=RunningMoments(jnp.zeros(()), jnp.asarray(4.0), jnp.asarray(10.0)),
        intrinsic_return=jnp.zeros(1),
        performance=jnp.zeros(()),
        key=key,
    )


def test_the_bonus_falls_on_a_repeated_state_and_stays_high_elsewhere():
    agent = RNDAgent(
        env=make_env("pointmaze", episode_length=10),
        network=_policy(),
        rnd_config=RNDConfig(hidden=(32, 32), embedding_size=16, predictor_lr=3e-3),
        buffer_size=100,
    )
    state = _rnd_state(agent, jax.random.PRNGKey(0))
    seen, unseen = jnp.array([[0.3, -0.4]]), jnp.array([[-0.6, 0.8]])
    # whitened inputs: (x - 0) / sqrt(0.25), clipped to [-5, 5]
    np.testing.assert_allclose(agent.whiten(state.input_moments, seen), [[0.6, -0.8]], rtol=1e-6)
    np.testing.assert_allclose(agent.whiten(state.input_moments, 10 * seen), [[5.0, -5.0]])
    err = lambda s, x: float(agent.prediction_error(s.target, s.predictor, s.input_moments, x)[0])
    x = agent.whiten(state.input_moments, seen)
    by_hand = np.sum(
        (
            agent.predictor_network.apply(state.predictor, x)
            - agent.target_network.apply(state.target, x)
        )
        ** 2
    )
    np.testing.assert_allclose(err(state, seen), by_hand, rtol=1e-5)
    # the normalised reward divides by the intrinsic return's standard deviation, sqrt(4)
    np.testing.assert_allclose(
        agent.intrinsic_reward(state, seen)[0], err(state, seen) / 2.0, rtol=1e-5
    )
    batch = {"reward": jnp.array([-1.0]), "next_state_descriptor": seen}
    np.testing.assert_allclose(
        agent.total_reward(state, batch)[0], -1.0 + 0.5 * err(state, seen) / 2.0, rtol=1e-5
    )

    before_seen, before_unseen = err(state, seen), err(state, unseen)
    rows = jnp.tile(seen, (64, 1))
    train = jax.jit(agent.train_predictor)
    for i in range(15):
        state = train(state, rows, jnp.ones(64, bool), jax.random.PRNGKey(i))
    after_seen, after_unseen = err(state, seen), err(state, unseen)
    assert after_seen < 0.1 * before_seen
    assert after_unseen > 0.3 * before_unseen
    assert after_unseen > 10 * after_seen
    # padding rows (valid False) teach the predictor nothing
    frozen = train(state, jnp.tile(unseen, (64, 1)), jnp.zeros(64, bool), jax.random.PRNGKey(99))
    assert err(frozen, unseen) == pytest.approx(after_unseen)


def test_rnd_learns_a_bandit_and_its_predictor_the_states_it_visits():
    agent = RNDAgent(
        env=Bandit(),
        network=MLP((16, 1), activation="relu"),
        td3_config=FAST_TD3,
        rnd_config=RNDConfig(hidden=(16,), embedding_size=8, intrinsic_weight=0.05),
        num_episodes=8,
        num_critic_steps=40,
        exploration_noise=0.3,
        buffer_size=2000,
    )
    state, ev = jax.jit(agent.init)(jax.random.PRNGKey(1))
    assert int(state.buffer.size) == 8  # one valid transition per episode
    np.testing.assert_allclose(  # the buffer keeps the state each transition reaches
        state.buffer.data["next_state_descriptor"][:8, 0], ev.trajectory["action"][:, 0, 0]
    )
    visited = ev.trajectory["next_state_descriptor"][:, 0]
    err0 = agent.prediction_error(state.target, state.predictor, state.input_moments, visited)
    step = jax.jit(agent.step)
    for _ in range(40):
        state, ev = step(state)
    action = float(agent.network.apply(state.td3.actor, jnp.zeros(1))[0])
    assert abs(action - 0.5) < 0.15
    assert float(state.performance) > -0.03
    err1 = agent.prediction_error(state.target, state.predictor, state.input_moments, visited)
    assert float(jnp.mean(err1)) < float(jnp.mean(err0))
    assert bool(jnp.isfinite(state.return_moments.var)) and float(state.return_moments.var) > 0


# --- P3S-TD3 ---------------------------------------------------------------------


def _constant_actor(network, actions):
    """Parameters of ``MLP((h, a))`` whose output is ``actions`` everywhere."""
    params = network.init(jax.random.PRNGKey(0), jnp.zeros(2))
    params = jax.tree.map(jnp.zeros_like, params)
    bias = jnp.arctanh(jnp.asarray(actions, jnp.float32))
    params["params"]["Dense_1"]["bias"] = bias
    return params


def test_policy_distance_and_the_guided_actor_loss_by_hand():
    net = _policy()
    a, b = _constant_actor(net, [0.5, 0.2]), _constant_actor(net, [-0.1, 0.2])
    obs = jax.random.normal(jax.random.PRNGKey(0), (5, 2))
    # 1/2 * mean over actions of the squared difference: 1/2 * (0.6^2 + 0) / 2
    np.testing.assert_allclose(policy_distance(net, a, b, obs), 0.09, rtol=1e-5)
    td3 = GuidedTD3(net, 2, 2, TINY_TD3, guide=b, guide_weight=3.0)
    critic = td3.init(jax.random.PRNGKey(1)).critic
    q1, _ = td3.critic.apply(critic, obs, jnp.tile(jnp.array([0.5, 0.2]), (5, 1)))
    np.testing.assert_allclose(td3.actor_loss(a, critic, obs), -np.mean(q1) + 3.0 * 0.09, rtol=1e-5)
    plain = GuidedTD3(net, 2, 2, TINY_TD3, guide=b, guide_weight=0.0)
    np.testing.assert_allclose(plain.actor_loss(a, critic, obs), -np.mean(q1), rtol=1e-5)


def test_guidance_pulls_an_actor_toward_the_best_one():
    net = _policy(16)
    cfg = TD3Config(critic_hidden=(16,), batch_size=32, actor_lr=1e-2)
    guide = _constant_actor(net, [0.7, -0.6])
    obs = jax.random.uniform(jax.random.PRNGKey(2), (32, 2), minval=-1, maxval=1)
    start = GuidedTD3(net, 2, 2, cfg).init(jax.random.PRNGKey(3))

    @jax.jit
    def distance_after(weight):
        td3 = GuidedTD3(net, 2, 2, cfg, guide=guide, guide_weight=weight)
        s = jax.lax.fori_loop(0, 30, lambda _, s: td3.actor_step(s, obs), start)
        return policy_distance(net, s.actor, guide, obs)

    d0 = float(policy_distance(net, start.actor, guide, obs))
    free, pulled = float(distance_after(0.0)), float(distance_after(5.0))
    assert pulled < free and pulled < 0.5 * d0


def test_best_learner_selection_and_beta_rule_by_hand():
    # ring of 3 recent returns per learner; 2 episodes written so far: columns 0 and 1
    recent = jnp.array([[1.0, 5.0, 100.0], [4.0, 3.0, 0.0], [2.0, 2.0, 0.0]])
    assert int(select_best(recent, 2)) == 1  # means 3, 3.5, 2 (column 2 unwritten)
    assert int(select_best(recent, 3)) == 0  # all columns: 35.3, 2.3, 1.3
    assert int(select_best(recent, 1)) == 1  # column 0 only: 1, 4, 2
    # target distance max(rho * change, d_min) = max(2 * 0.1, 0.05) = 0.2
    rule = lambda beta, spread, change=0.1: float(adapt_beta(beta, spread, change, 2.0, 0.05))
    assert rule(1.0, 0.31) == 2.0  # spread > 1.5 * 0.2
    assert rule(1.0, 0.29) == 1.0  # within [0.2 / 1.5, 1.5 * 0.2]
    assert rule(1.0, 0.14) == 1.0
    assert rule(1.0, 0.13) == 0.5  # spread < 0.2 / 1.5
    assert rule(1.0, 0.05, change=0.0) == 1.0  # d_min = 0.05 is the target
    assert rule(1.0, 0.03, change=0.0) == 0.5
    assert rule(1000.0, 1.0) == 1000.0  # bounds [1e-3, 1e3]
    assert rule(1e-3, 0.0) == pytest.approx(1e-3)
    assert rule(999.0, 1.0) == 1998.0


def test_an_update_period_adapts_beta_and_moves_the_guide_to_the_best_learner():
    net = _policy()
    agent = P3STD3Agent(
        env=make_env("pointmaze", episode_length=10),
        network=net,
        td3_config=TINY_TD3,
        p3s_config=P3SConfig(update_period=2, num_recent_episodes=2),
        num_episodes=3,
        buffer_size=100,
    )
    constant = lambda *actions: stack([_constant_actor(net, a) for a in actions])
    actors = constant([0.5, 0.2], [-0.1, 0.2], [0.5, -0.4])
    buffer = ReplayBuffer.create(100, 2, 2).add(
        {
            "obs": jnp.ones((4, 2)),
            "action": jnp.zeros((4, 2)),
            "reward": jnp.zeros(4),
            "next_obs": jnp.ones((4, 2)),
            "terminal": jnp.zeros(4),
        }
    )
    state = P3SState(
        learners=TD3State(actors, None, None, None, None, None, None),
        buffer=buffer,
        guide=_constant_actor(net, [0.5, 0.2]),  # learner 0's
        old_actors=constant([0.0, 0.0], [-0.1, 0.2], [0.5, -0.4]),  # 1 and 2 have not moved
        best=jnp.asarray(0),
        beta=jnp.asarray(1.0),
        recent_returns=jnp.array([[-5.0, -5.0], [-9.0, -1.0], [-3.0, -4.0]]),
        num_played=jnp.asarray(2),
        iteration=jnp.asarray(1),
        performance=jnp.zeros(()),
        key=jax.random.PRNGKey(0),
    )
    # D_spread over learners 1 and 2: 1/2 * mean((0.6^2, 0)) and 1/2 * mean((0, 0.6^2)), so
    # 0.09; D_change 0 (learner 0, the best, is left out): target d_min = 0.05, 0.09 > 0.075
    spread, change = jax.jit(agent.distances)(state, jnp.zeros((3, 2)))
    np.testing.assert_allclose([spread, change], [0.09, 0.0], atol=1e-6)
    end_of_period = jax.jit(agent._end_of_period)
    mid = end_of_period(state, jax.random.PRNGKey(1))  # iteration 1 of a period of 2
    assert float(mid.beta) == 1.0 and int(mid.best) == 0
    end = end_of_period(state.replace(iteration=jnp.asarray(2)), jax.random.PRNGKey(1))
    assert float(end.beta) == 2.0
    assert int(end.best) == 2  # mean returns -5, -5, -3.5
    np.testing.assert_allclose(net.apply(end.guide, jnp.zeros(2)), [0.5, -0.4], rtol=1e-6)
    np.testing.assert_allclose(
        end.old_actors["params"]["Dense_1"]["bias"], actors["params"]["Dense_1"]["bias"]
    )


def test_p3s_learns_a_bandit_guiding_all_but_the_best():
    agent = P3STD3Agent(
        env=Bandit(),
        network=MLP((16, 1), activation="relu"),
        td3_config=FAST_TD3,
        p3s_config=P3SConfig(num_recent_episodes=3),
        num_episodes=4,
        num_critic_steps=80,
        exploration_noise=0.3,
        buffer_size=2000,
    )
    assert agent.learner_critic_steps == 20
    state, ev = jax.jit(agent.init)(jax.random.PRNGKey(0))
    assert ev.fitness.shape == (4,) and int(state.buffer.size) == 4
    step = jax.jit(agent.step)
    best = int(state.best)
    state, ev = step(state)
    # the best learner's episode comes first and is greedy: its action, without noise
    actor = lambda i: jax.tree.map(lambda x: x[i], state.learners.actor)
    action = agent.network.apply(actor(best), jnp.zeros(1))
    np.testing.assert_allclose(ev.trajectory["action"][0, 0], action, rtol=1e-5)
    np.testing.assert_allclose(ev.fitness[0], -((action[0] - 0.5) ** 2), rtol=1e-5)
    np.testing.assert_allclose(state.recent_returns[best, 1], ev.fitness[0])
    for _ in range(25):
        state, ev = step(state)
    assert int(state.iteration) == 26 and int(state.num_played) == 27
    actor = lambda i: jax.tree.map(lambda x: x[i], state.learners.actor)
    action = float(agent.network.apply(actor(int(state.best)), jnp.zeros(1))[0])
    assert abs(action - 0.5) < 0.15 and float(state.performance) > -0.03
    guide_action = agent.network.apply(state.guide, jnp.zeros(1))
    np.testing.assert_allclose(guide_action[0], action, rtol=1e-5)  # the guide is pi_b
    assert 5e-4 <= float(state.beta) <= 2e3


def test_both_agents_run_under_run_seeds_and_reject_bad_configs():
    env = make_env("pointmaze", episode_length=10)
    common = dict(
        env=env,
        network=_policy(),
        td3_config=TINY_TD3,
        num_episodes=3,
        num_critic_steps=6,
        buffer_size=500,
    )
    for algo in (RNDAgent(**common, rnd_config=TINY_RND), P3STD3Agent(**common)):
        _, _, history = run_seeds(
            algo, jax.random.split(jax.random.PRNGKey(0), 2), 3, 2, progress=False
        )
        assert history["max_fitness"].shape == (2, 4)
        assert bool(jnp.all(jnp.isfinite(history["max_fitness"])))
        assert history["fitnesses"].shape == (2, 4, 3)
        # the performance is the first (greedy) episode of each iteration
        np.testing.assert_allclose(history["max_fitness"], history["fitnesses"][..., 0])
    bad = [
        (RNDAgent, dict(num_critic_steps=5), "policy_delay"),
        (RNDAgent, dict(buffer_size=20), "buffer_size"),
        (P3STD3Agent, dict(num_episodes=0), "num_episodes"),
        (P3STD3Agent, dict(exploration_noise=-1.0), "exploration_noise"),
    ]
    for cls, change, match in bad:
        with pytest.raises(ValueError, match=match):
            cls(**{**common, **change})
    for make, match in [
        (lambda: RNDConfig(predictor_proportion=0.0), "predictor_proportion"),
        (lambda: RNDConfig(intrinsic_gamma=1.0), "intrinsic_gamma"),
        (lambda: RNDConfig(intrinsic_weight=-1.0), "intrinsic_weight"),
        (lambda: P3SConfig(update_period=0), "update_period"),
        (lambda: P3SConfig(beta_bounds=(1.0, 0.5)), "beta_bounds"),
        (lambda: P3SConfig(d_min=-0.1), "d_min"),
    ]:
        with pytest.raises(ValueError, match=match):
            make()
