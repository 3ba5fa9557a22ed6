"""QD-PG (Algorithm 4): state-descriptor archive, novelty rewards, alternating
updates, critic targets, the TD3 baseline and the Chapter 3 configs."""

import dataclasses
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
from jax.flatten_util import ravel_pytree

from qdnb.book.registry import config
from qdnb.chapters.ch3_qdpg import (
    QDPGConfig,
    build_algorithms,
    grid_coverage,
    load_method_result,
    reached_goal,
    run_environment,
    save_method_result,
)
from qdnb.envs import make_env
from qdnb.envs.rollout import evaluate_policies
from qdnb.nets.mlp import MLP
from qdnb.qd.cvt import grid_centroids
from qdnb.qd.novelty import NoveltyArchive, k_smallest, knn_novelty
from qdnb.qd.qdpg import QDPG, update_kinds
from qdnb.rl.agents import TD3Agent
from qdnb.rl.buffer import ReplayBuffer
from qdnb.rl.td3 import TD3Config, td3_target


def brute_force_novelty(queries, reference, k):
    d = np.linalg.norm(
        np.asarray(queries, np.float64)[:, None] - np.asarray(reference, np.float64)[None], axis=-1
    )
    return np.sort(d, axis=1)[:, :k].mean(axis=1)


def test_archive_acceptance_and_fifo_replacement():
    archive = NoveltyArchive.create(capacity=3, dim=2)
    # k = 1: an item enters when its distance to the nearest archived item is > 0.5.
    items = jnp.array([[0.0, 0.0], [0.2, 0.0], [1.0, 0.0], [1.0, 0.3], [3.0, 0.0], [5.0, 0.0]])
    archive = archive.add(items, threshold=0.5, k=1)
    # [0.2, 0] is 0.2 from [0, 0] and [1, 0.3] is 0.3 from [1, 0]: both refused.
    # [5, 0] enters the full archive and replaces the oldest entry, [0, 0].
    np.testing.assert_allclose(archive.data, [[5.0, 0.0], [1.0, 0.0], [3.0, 0.0]])
    assert int(archive.num_added) == 4 and int(archive.size) == 3
    # Items flagged invalid are skipped even when novel.
    again = archive.add(
        jnp.array([[9.0, 9.0], [20.0, 0.0]]), 0.5, 1, valid=jnp.array([False, True])
    )
    np.testing.assert_allclose(again.data, [[5.0, 0.0], [20.0, 0.0], [3.0, 0.0]])


def test_novelty_matches_brute_force_on_large_archives():
    # 10,000 references take the blockwise k-smallest path; ties and duplicates included.
    key = jax.random.PRNGKey(0)
    reference = jnp.round(jax.random.uniform(key, (10_000, 2)) * 50) / 50  # many exact duplicates
    queries = jax.random.uniform(jax.random.PRNGKey(1), (300, 2))
    np.testing.assert_allclose(
        knn_novelty(queries, reference, 10),
        brute_force_novelty(queries, reference, 10),
        rtol=1e-5,
        atol=1e-7,
    )
    values = jax.random.normal(jax.random.PRNGKey(2), (7, 3_333))  # not a multiple of the block
    np.testing.assert_allclose(
        k_smallest(values, 10), np.sort(np.asarray(values), axis=1)[:, :10], rtol=1e-6
    )
    small_rows = jax.random.normal(
        jax.random.PRNGKey(3), (7, 2_000)
    )  # the small archive's size: blockwise too
    np.testing.assert_allclose(
        k_smallest(small_rows, 10), np.sort(np.asarray(small_rows), axis=1)[:, :10], rtol=1e-6
    )
    archive = NoveltyArchive.create(10_000, 2).replace(
        data=reference, num_added=jnp.asarray(10_000, jnp.int32)
    )
    np.testing.assert_allclose(
        archive.novelty(queries, 10), brute_force_novelty(queries, reference, 10), rtol=1e-5
    )


def test_update_kinds_give_each_actor_one_kind():
    for n in (4, 5, 10):
        kinds = [np.asarray(update_kinds(jax.random.PRNGKey(i), n, "alternate")) for i in range(20)]
        assert all(k.sum() == n // 2 for k in kinds)  # exactly half diversity, the rest quality
        assert len({tuple(k) for k in kinds}) > 1  # the choice is redrawn
    assert not update_kinds(jax.random.PRNGKey(0), 4, "quality").any()
    assert not update_kinds(jax.random.PRNGKey(0), 4, "sum").any()
    assert update_kinds(jax.random.PRNGKey(0), 4, "diversity").all()


@pytest.fixture(scope="module")
def maze():
    return make_env("pointmaze", episode_length=10)


def small_qdpg(env, update="alternate", **kw):
    kw = {"archive_threshold": 1e-4, **kw}
    return QDPG(
        env=env,
        network=MLP((8, env.action_size), activation="relu"),
        batch_size=4,
        iso_sigma=0.0,
        line_sigma=0.0,
        centroids=grid_centroids((5, 5), (-1, -1), (1, 1)),
        update=update,
        td3_config=TD3Config(batch_size=16, critic_hidden=(8,), actor_lr=1e-2),
        num_critic_steps=4,
        num_pg_steps=3,
        buffer_size=1000,
        archive_size=64,
        **kw,
    )


def test_each_actor_is_updated_against_the_critic_of_its_kind(maze):
    algo = small_qdpg(maze)
    state, _ = algo.init(jax.random.PRNGKey(0))
    state = state.replace(
        d_critic=algo.td3.init(jax.random.PRNGKey(9))
    )  # two clearly different critics
    parents = jax.tree.map(lambda x: x[:4], state.repertoire.genotypes)
    parents = jax.tree.map(
        lambda x: jnp.broadcast_to(x[:1], x.shape), parents
    )  # four copies of one actor
    diversity = jnp.array([True, False, False, True])
    key = jax.random.PRNGKey(3)
    out = algo.mutate(state, parents, diversity, key)
    keys = jax.random.split(key, 4)
    one = lambda t, i: jax.tree.map(lambda x: x[i], t)
    for i in range(4):
        critic = (state.d_critic if diversity[i] else state.q_critic).critic
        other = (state.q_critic if diversity[i] else state.d_critic).critic
        expected = algo.td3.policy_gradient_steps(
            one(parents, i), critic, state.buffer, keys[i], algo.num_pg_steps
        )
        wrong = algo.td3.policy_gradient_steps(
            one(parents, i), other, state.buffer, keys[i], algo.num_pg_steps
        )
        for a, b, c in zip(
            jax.tree.leaves(one(out, i)), jax.tree.leaves(expected), jax.tree.leaves(wrong)
        ):
            np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6)
        assert any(
            not np.allclose(a, c)
            for a, c in zip(jax.tree.leaves(one(out, i)), jax.tree.leaves(wrong))
        )


def test_critic_targets_on_a_hand_checked_batch(maze):
    algo = small_qdpg(maze, update="alternate", archive_k=2)
    archive = NoveltyArchive.create(4, 2).replace(
        data=jnp.array([[0.0, 0.0], [1.0, 0.0], [0.0, 2.0], [5.0, 5.0]]),
        num_added=jnp.asarray(4, jnp.int32),
    )
    batch = {
        "obs": jnp.zeros((2, 2)),
        "action": jnp.zeros((2, 2)),
        "next_obs": jnp.array([[0.1, 0.2], [0.3, -0.4]]),
        "reward": jnp.array([-1.0, -2.0]),
        "terminal": jnp.array([0.0, 1.0]),
        "state_descriptor": jnp.array([[0.0, 1.0], [1.0, 1.0]]),
    }
    # Novelty with K = 2: (0,1) is 1 from (0,0), 1 from (0,2), sqrt2 from (1,0) -> 1.0;
    # (1,1) is 1 from (1,0), sqrt2 from (0,0) and from (0,2) -> (1 + sqrt2) / 2.
    novelty = np.array([1.0, (1.0 + np.sqrt(2.0)) / 2])
    np.testing.assert_allclose(algo.critic_rewards(archive, batch, "diversity"), novelty, rtol=1e-6)
    np.testing.assert_allclose(algo.critic_rewards(archive, batch, "quality"), [-1.0, -2.0])
    np.testing.assert_allclose(
        algo.critic_rewards(archive, batch, "sum"), novelty + [-1.0, -2.0], rtol=1e-6
    )
    td3 = algo.td3
    state = td3.init(jax.random.PRNGKey(0))
    key = jax.random.PRNGKey(1)
    for kind, r in (("quality", np.array([-1.0, -2.0])), ("diversity", novelty)):
        y = td3.target(
            state.critic_target,
            state.actor_target,
            {**batch, "reward": algo.critic_rewards(archive, batch, kind)},
            key,
        )
        # The same smoothed target action, by hand: y = r + gamma * (1 - terminal) * min(Q1', Q2').
        a = td3.actor.apply(state.actor_target, batch["next_obs"])
        noise = jnp.clip(0.2 * jax.random.normal(key, a.shape), -0.5, 0.5)
        q1, q2 = td3.critic.apply(
            state.critic_target, batch["next_obs"], jnp.clip(a + noise, -1, 1)
        )
        hand = r + 0.99 * np.array([1.0, 0.0]) * np.minimum(q1, q2)
        np.testing.assert_allclose(y, hand, rtol=1e-5)
        np.testing.assert_allclose(
            y, td3_target(jnp.asarray(r), batch["terminal"], q1, q2, 0.99), rtol=1e-5
        )


def test_qdpg_iterates_and_ablations_train_only_their_critics(maze):
    for update, trains_q, trains_d in (
        ("alternate", True, True),
        ("quality", True, False),
        ("diversity", False, True),
        ("sum", True, False),
    ):
        algo = small_qdpg(maze, update)
        state, ev0 = algo.init(jax.random.PRNGKey(0))
        new, ev = jax.jit(algo.step)(state)
        changed = lambda a, b: any(
            not np.array_equal(x, y) for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b))
        )
        assert changed(state.q_critic.critic, new.q_critic.critic) == trains_q, update
        assert changed(state.d_critic.critic, new.d_critic.critic) == trains_d, update
        # Every valid transition of both evaluations is in the buffer, with its state descriptor.
        n_valid = int(ev0.length.sum() + ev.length.sum())
        assert int(new.buffer.size) == n_valid
        assert "state_descriptor" in new.buffer.data
        np.testing.assert_allclose(
            new.buffer.data["state_descriptor"][: int(ev0.length[0])],
            ev0.trajectory["state_descriptor"][0, : int(ev0.length[0])],
        )
        assert 0 < int(new.archive.size) <= n_valid
        assert float(algo.metrics(new)["coverage"]) > 0


def test_td3_agent_explores_around_its_greedy_episode(maze):
    agent = TD3Agent(
        env=maze,
        network=MLP((8, 2), activation="relu"),
        td3_config=TD3Config(batch_size=16, critic_hidden=(8,)),
        num_episodes=3,
        num_critic_steps=4,
        exploration_noise=0.3,
        buffer_size=1000,
    )
    state, ev = agent.init(jax.random.PRNGKey(0))
    actions = np.asarray(ev.trajectory["action"])
    greedy = jax.vmap(lambda o: agent.network.apply(state.td3.actor, o))(ev.trajectory["obs"][0])
    np.testing.assert_allclose(actions[0], greedy, rtol=1e-5, atol=1e-6)  # episode 0: no noise
    others = jax.vmap(jax.vmap(lambda o: agent.network.apply(state.td3.actor, o)))(
        ev.trajectory["obs"][1:]
    )
    assert not np.allclose(actions[1:], others)  # the others explore
    assert np.all(np.abs(actions) <= 1.0)
    assert float(agent.metrics(state)["max_fitness"]) == float(ev.fitness[0])
    new, _ = jax.jit(agent.step)(state)
    assert int(new.buffer.size) > int(state.buffer.size)


def test_exploration_noise_zero_is_the_deterministic_rollout(maze):
    net = MLP((8, 2))
    params = jax.vmap(lambda k: net.init(k, jnp.zeros(2)))(
        jax.random.split(jax.random.PRNGKey(0), 3)
    )
    a = evaluate_policies(maze, net.apply, params, jax.random.PRNGKey(1))
    b = evaluate_policies(maze, net.apply, params, jax.random.PRNGKey(1), exploration_noise=0.0)
    np.testing.assert_array_equal(a.fitness, b.fitness)


def test_configs_and_helpers():
    for scale in ("tiny", "small", "paper"):
        cfg = config("ch3_qdpg", scale)
        assert all(cfg.task(e).num_iterations >= 1 for e in ("pointmaze", "antmaze", "anttrap"))
    paper = config("ch3_qdpg", "paper")
    assert paper.pointmaze.num_steps == 1_000_000 and paper.antmaze.num_steps == 100_000_000
    assert (
        paper.pointmaze.num_critic_steps == 4 * 200 and paper.antmaze.num_pg_steps == 300
    )  # ratio x length
    assert paper.pointmaze.optimizer == "sgd" and paper.antmaze.bins == 7
    assert paper.pointmaze.num_pg_steps == 400  # a mutation's steps: the thesis coupling's 800 / 2
    # small: Table 3.2 whole on Point-Maze, fewer environment steps (its rule: the notebook)
    small = config("ch3_qdpg", "small")
    assert dataclasses.replace(small.pointmaze, num_steps=1_000_000) == paper.pointmaze
    assert small.seeds("pointmaze", "QD-PG") >= 4
    with pytest.raises(ValueError, match="less than one iteration"):
        dataclasses.replace(paper, pointmaze=dataclasses.replace(paper.pointmaze, num_steps=100))
    with pytest.raises(ValueError, match="unknown methods"):
        dataclasses.replace(paper, ant_methods=("QD-PG", "PPO"))  # SAC is one since issue 18
    with pytest.raises(ValueError, match="unknown environment"):
        paper.task("halfcheetah")
    with pytest.raises(ValueError, match="unknown update"):
        small_qdpg(make_env("pointmaze", episode_length=5), update="both")
    with pytest.raises(ValueError, match="unknown optimizer"):
        TD3Config(optimizer="rmsprop")
    assert isinstance(paper, QDPGConfig)
    env = make_env("pointmaze")
    d = np.array(
        [[[[-0.5, 0.8], [0.9, 0.9]]], [[[0.0, 0.0], [0.1, 0.1]]]]
    )  # seeds x iterations x episodes x 2
    np.testing.assert_array_equal(reached_goal(d), [True, False])
    np.testing.assert_allclose(
        grid_coverage(d, env, 2), [2 / 4, 1 / 4]
    )  # (0,0) and (0.1,0.1) share a cell
    algos = build_algorithms(config("ch3_qdpg", "tiny"), "pointmaze", env)
    assert set(algos) == {"QD-PG", "QD-PG Sum", "D-PG", "Q-PG", "TD3", "PGA-ME"}


def test_qdpg_on_point_maze_runs_on_its_own_seed_count():
    """``pointmaze_qdpg_seeds`` gives QD-PG on Point-Maze its own seeds; every
    other method (and QD-PG elsewhere) keeps ``num_seeds``; a count below one is
    refused."""
    tiny = config("ch3_qdpg", "tiny")
    cfg = dataclasses.replace(tiny.with_pointmaze_iterations(2), pointmaze_qdpg_seeds=2)
    assert cfg.pointmaze.num_iterations == 2 and cfg.pointmaze.num_steps == 2 * 4 * 200
    assert cfg.seeds("pointmaze", "QD-PG") == 2 and cfg.seeds("pointmaze", "TD3") == 1
    assert cfg.seeds("antmaze", "QD-PG") == 1 and tiny.seeds("pointmaze", "QD-PG") == 1
    assert (
        cfg.with_seeds(3).seeds("pointmaze", "QD-PG") == 3
        and cfg.with_seeds(3).seeds("pointmaze", "TD3") == 3
    )
    out = run_environment(
        cfg, "pointmaze", jax.random.PRNGKey(0), progress=False, methods=("QD-PG", "TD3")
    )
    assert out.methods["QD-PG"].final_performance.shape == (2,)
    assert out.methods["TD3"].final_performance.shape == (1,)
    assert out.methods["QD-PG"].history["descriptors"].shape[:2] == (2, 2)
    with pytest.raises(ValueError, match="pointmaze_qdpg_seeds=0 must be at least 1"):
        dataclasses.replace(tiny, pointmaze_qdpg_seeds=0)


def test_a_saved_method_result_loads_back_under_its_config_only(tmp_path):
    """What the baselines page reads of the QD-PG page's run: every array of the
    result but the policies, and nothing under another config hash."""
    cfg = config("ch3_qdpg", "tiny").with_pointmaze_iterations(2)
    for name in ("QD-PG", "TD3"):  # with a grid, and without
        r = run_environment(cfg, "pointmaze", jax.random.PRNGKey(0), False, (name,)).methods[name]
        path = save_method_result(tmp_path / f"{name}.npz", "abc", r)
        back = load_method_result(path, "abc")
        assert load_method_result(path, "other") is None
        assert load_method_result(tmp_path / "missing.npz", "abc") is None
        assert set(back.history) == set(r.history) and back.seconds == pytest.approx(r.seconds)
        for k in r.history:
            np.testing.assert_array_equal(back.history[k], r.history[k])
        for field in ("final_performance", "coverage", "env_steps", "cumulative_steps"):
            np.testing.assert_array_equal(getattr(back, field), getattr(r, field))
        np.testing.assert_array_equal(back.exit_steps, r.exit_steps)
        if r.grid is None:
            assert back.grid is None
        else:
            assert set(back.grid) == set(r.grid) - {"genotypes"}
            np.testing.assert_array_equal(back.grid["fitnesses"], r.grid["fitnesses"])


def test_the_target_critic_moves_on_every_critic_step_and_the_target_actor_on_actor_steps(maze):
    """Table 3.2's target update interval of 1 (as QDax's emitters): after one
    critic step the target critic has moved by tau toward the new critic, the
    actor and its target have not (policy delay 2); after the second step the
    actor and its target move too."""
    algo = small_qdpg(maze)
    td3 = algo.td3
    state, _ = algo.init(jax.random.PRNGKey(0))
    s0 = state.q_critic
    batch = state.buffer.sample(jax.random.PRNGKey(1), 16)
    s1, _ = td3.critic_step(s0, batch, jax.random.PRNGKey(2))
    tau = td3.config.tau
    for t0, t1, c1 in zip(
        *(jax.tree.leaves(x) for x in (s0.critic_target, s1.critic_target, s1.critic))
    ):
        np.testing.assert_allclose(t1, (1 - tau) * t0 + tau * c1, rtol=1e-5, atol=1e-7)
    assert any(
        not np.array_equal(a, b)
        for a, b in zip(jax.tree.leaves(s0.critic_target), jax.tree.leaves(s1.critic_target))
    )
    # train_critic with 2 steps: two critic steps, then one actor step and one target-actor move.
    s2, _ = td3.train_critic(s0, state.buffer, jax.random.PRNGKey(3), 2)
    assert int(s2.steps) == 2
    assert any(
        not np.array_equal(a, b)
        for a, b in zip(jax.tree.leaves(s0.actor), jax.tree.leaves(s2.actor))
    )
    for a0, ta, a2 in zip(
        *(jax.tree.leaves(x) for x in (s0.actor_target, s2.actor_target, s2.actor))
    ):
        np.testing.assert_allclose(ta, (1 - tau) * a0 + tau * a2, rtol=1e-5, atol=1e-7)
    # With a target update interval of 2, the first step leaves the target critic alone.
    lazy = dataclasses.replace(
        td3, config=dataclasses.replace(td3.config, target_update_interval=2)
    )
    s1_lazy, _ = lazy.critic_step(s0, batch, jax.random.PRNGKey(2))
    for a, b in zip(jax.tree.leaves(s0.critic_target), jax.tree.leaves(s1_lazy.critic_target)):
        np.testing.assert_array_equal(a, b)
    with pytest.raises(ValueError, match="multiple of policy_delay"):
        td3.train_critic(s0, state.buffer, jax.random.PRNGKey(3), 3)


def test_a_transition_carries_the_descriptor_of_the_state_it_starts_from(maze):
    """Section 3.6.3 stores (s_t, a_t, r_t, s_{t+1}, psi(s_t)): on Point-Maze
    psi is the position, so the stored descriptor equals obs, not next_obs, and
    the archive receives the starting position of the episode."""
    net = MLP((8, 2))
    params = jax.vmap(lambda k: net.init(k, jnp.zeros(2)))(
        jax.random.split(jax.random.PRNGKey(0), 2)
    )
    ev = evaluate_policies(maze, net.apply, params, jax.random.PRNGKey(1), return_trajectory=True)
    t = ev.trajectory
    np.testing.assert_array_equal(t["state_descriptor"], t["obs"])
    assert not np.allclose(t["state_descriptor"][:, 1:], t["next_obs"][:, 1:])
    algo = small_qdpg(maze, archive_threshold=-1.0)  # admit everything
    state, ev0 = algo.init(jax.random.PRNGKey(0))
    first = np.asarray(ev0.trajectory["obs"][0, 0])
    np.testing.assert_allclose(state.archive.data[0], first)
    np.testing.assert_allclose(state.buffer.data["state_descriptor"][0], first)
    # A hand-made transition: the diversity reward scores psi(s_t) = (0, 1), not s_{t+1}.
    archive = NoveltyArchive.create(2, 2).replace(
        data=jnp.array([[0.0, 0.0], [0.0, 3.0]]), num_added=jnp.asarray(2, jnp.int32)
    )
    batch = {
        "obs": jnp.array([[0.0, 1.0]]),
        "next_obs": jnp.array([[0.0, 1.1]]),
        "state_descriptor": jnp.array([[0.0, 1.0]]),
        "reward": jnp.zeros(1),
    }
    np.testing.assert_allclose(
        dataclasses.replace(algo, archive_k=1).critic_rewards(archive, batch, "diversity"),
        [1.0],
        rtol=1e-6,
    )


def test_novelty_of_every_batch_of_an_iteration_in_one_pass_is_exact():
    """The critic scores all its batches at once (leading axes, chunked): the
    same values as brute force, batch by batch."""
    reference = jax.random.uniform(jax.random.PRNGKey(0), (500, 2))
    archive = NoveltyArchive.create(600, 2).replace(
        data=jnp.pad(reference, ((0, 100), (0, 0))), num_added=jnp.asarray(500, jnp.int32)
    )
    queries = jax.random.uniform(jax.random.PRNGKey(1), (7, 33, 2))
    got = archive.novelty(queries, 5, chunk=50)  # 231 queries: 5 chunks, the last one padded
    assert got.shape == (7, 33)
    for i in range(7):
        np.testing.assert_allclose(got[i], brute_force_novelty(queries[i], reference, 5), rtol=1e-5)


def test_mutations_use_their_own_learning_rate(maze):
    """QDax's rates: 3e-4 for critics and greedy actors, 1e-3 for mutations."""
    cfg = config("ch3_qdpg", "small")
    algo = build_algorithms(cfg, "pointmaze")["QD-PG"]
    assert algo.td3.config.critic_lr == algo.td3.config.actor_lr == cfg.pointmaze.learning_rate
    assert algo.td3.config.mutation_lr == cfg.pointmaze.mutation_learning_rate
    paper = config("ch3_qdpg", "paper").pointmaze
    assert paper.learning_rate == paper.mutation_learning_rate == 6e-3  # Table 3.2: one rate
    td3 = small_qdpg(maze).td3
    fast = dataclasses.replace(td3, config=dataclasses.replace(td3.config, mutation_lr=1.0))
    state, _ = small_qdpg(maze).init(jax.random.PRNGKey(0))
    actor = td3.init(jax.random.PRNGKey(4)).actor
    slow_out = td3.policy_gradient_steps(
        actor, state.q_critic.critic, state.buffer, jax.random.PRNGKey(5), 1
    )
    fast_out = fast.policy_gradient_steps(
        actor, state.q_critic.critic, state.buffer, jax.random.PRNGKey(5), 1
    )
    # Adam's first step moves each weight by about the learning rate
    step = lambda out: max(
        float(jnp.max(jnp.abs(a - b))) for a, b in zip(jax.tree.leaves(out), jax.tree.leaves(actor))
    )
    assert step(fast_out) > 50 * step(slow_out)


def test_the_sweep_script_runs_a_tiny_grid_resumes_and_selects(tmp_path):
    """bench/qdpg_sweep.py on its tiny grid (one variant, both methods, two
    seeds): per seed steps to the exit (or None), final performance, coverage;
    a second call skips what is done; the selection follows the stated rule."""
    import importlib.util
    import json
    import sys

    path = Path(__file__).parents[1] / "bench" / "qdpg_sweep.py"
    spec = importlib.util.spec_from_file_location("qdpg_sweep", path)
    sweep = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(sweep)
    out = tmp_path / "sweep.json"
    argv = ["qdpg_sweep.py", "--grid", "tiny", "--only", "base", "--out", str(out)]
    old = sys.argv
    try:
        sys.argv = argv
        sweep.main()
        first = json.loads(out.read_text())
        sweep.main()  # resumes: nothing left to run, same numbers
        again = json.loads(out.read_text())
    finally:
        sys.argv = old
    runs = first["runs"]["base"]
    assert set(runs) == {"QD-PG", "D-PG"} and first["budget_steps"] == 4_000
    for entry in runs.values():
        assert len(entry["final_performance"]) == 2 and len(entry["steps_to_exit"]) == 2
        assert all(s is None or 0 < s <= 4_000 for s in entry["steps_to_exit"])
        assert all(0 < e <= 4_000 for e in entry["env_steps"])
    assert again["runs"] == first["runs"] and first["selected"] == "base"
    assert {"device", "commit", "date", "versions"} <= set(first)  # provenance.write_result
    fake = {
        "a": {
            "QD-PG": {"final_performance": [-50.0], "seconds": 100.0},
            "D-PG": {"final_performance": [-50.0]},
        },
        "b": {
            "QD-PG": {"final_performance": [-20.0], "seconds": 900.0},
            "D-PG": {"final_performance": [-20.0]},
        },
        "c": {"QD-PG": {"final_performance": [-10.0], "seconds": 1.0}},
    }  # D-PG missing: not eligible
    assert sweep.select(fake, None) == "b" and sweep.select(fake, 500.0) == "a"


def test_maze_regions_split_the_maze_at_the_walls():
    """maze_regions on hand-placed points: a point stopped on the upper wall's
    lower face is between the walls, one on its upper face above; the shares of
    bench/probes/qdpg_reach.py are the masks' means."""
    import importlib.util

    from qdnb.envs.pointmaze import maze_regions

    points = np.array(
        [[0.0, -0.9], [0.0, 0.0], [0.8, 0.0], [0.0, 0.20], [0.0, 0.21], [-0.5, 0.8]], np.float32
    )
    masks = maze_regions(points)
    assert masks["below the lower wall"].tolist() == [True, False, False, False, False, False]
    assert masks["between the walls"].tolist() == [False, True, True, True, False, False]
    assert masks["right-hand passage (x > 0.5, between the walls)"].tolist() == [
        False,
        False,
        True,
        False,
        False,
        False,
    ]
    assert masks["above the upper wall"].tolist() == [False, False, False, False, True, True]
    assert maze_regions(points.reshape(2, 3, 2))["between the walls"].shape == (2, 3)

    path = Path(__file__).parents[1] / "bench" / "probes" / "qdpg_reach.py"
    spec = importlib.util.spec_from_file_location("qdpg_reach", path)
    reach = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(reach)
    shares = reach.regions(points)
    assert shares["below the lower wall"] == 1 / 6
    assert shares["between the walls"] == 3 / 6
    assert shares["right-hand passage (x > 0.5, between the walls)"] == 1 / 6
    assert shares["above the upper wall"] == 2 / 6


# ----- issue 35: how the critics meet the actors, the reward's reduction, the wall faces -----


def one_transition_buffer(algo, copies=32):
    """A buffer holding ``copies`` of one transition, so that every replay batch is the
    same whatever the key."""
    buffer = ReplayBuffer.create(100, 2, 2, 2)
    row = {
        "obs": jnp.array([0.1, -0.3]),
        "action": jnp.array([0.5, -0.2]),
        "reward": jnp.asarray(-0.7),
        "next_obs": jnp.array([0.15, -0.32]),
        "terminal": jnp.asarray(0.0),
        "state_descriptor": jnp.array([0.1, -0.3]),
    }
    stacked = jax.tree.map(lambda x: jnp.broadcast_to(x, (copies,) + x.shape), row)
    batch = jax.tree.map(
        lambda x: jnp.broadcast_to(x, (algo.td3_config.batch_size,) + x.shape), row
    )
    return buffer.add(stacked), batch


def test_the_thesis_coupling_trains_each_critic_with_the_actors_being_improved(maze):
    """Two quality actors, two critic steps (policy delay 2), then one actor step each,
    on a buffer of one transition and without target-policy noise: each critic step's
    gradient is the mean of the actors' gradients, each computed with that actor as the
    TD3 target policy; the critic's own greedy actor plays no part."""
    cfg = TD3Config(batch_size=16, critic_hidden=(8,), actor_lr=1e-2, policy_noise=0.0)
    algo = dataclasses.replace(
        small_qdpg(maze, "quality"), td3_config=cfg, num_critic_steps=2, coupling="thesis"
    )
    td3 = algo.td3
    state, _ = algo.init(jax.random.PRNGKey(0))
    buffer, batch = one_transition_buffer(algo)
    state = state.replace(buffer=buffer)
    parents = jax.vmap(lambda k: td3.actor.init(k, jnp.zeros(2)))(
        jax.random.split(jax.random.PRNGKey(5), 2)
    )
    diversity = jnp.array([False, False])
    offspring, q, d, _ = algo.coupled_updates(state, parents, diversity, jax.random.PRNGKey(6))

    one = lambda t, i: jax.tree.map(lambda x: x[i], t)
    key = jax.random.PRNGKey(0)  # no target-policy noise: the key plays no part

    def by_hand(target_policies):
        critic = state.q_critic
        for _ in range(2):
            grads = [
                td3.critic_grads(critic.critic, critic.critic_target, a, batch, key)[1]
                for a in target_policies
            ]
            critic = td3.apply_critic_grads(
                critic, jax.tree.map(lambda *g: sum(g) / len(g), *grads)
            )
        return critic

    expected = by_hand([one(parents, 0), one(parents, 1)])
    for a, b in zip(jax.tree.leaves(q.critic), jax.tree.leaves(expected.critic)):
        np.testing.assert_allclose(a, b, rtol=2e-5, atol=1e-6)
    # the other reading, the critic's own greedy actor as target policy, is another gradient
    grads_of = lambda a: td3.critic_grads(
        state.q_critic.critic, state.q_critic.critic_target, a, batch, key
    )[1]
    ours = ravel_pytree(grads_of(one(parents, 0)))[0]
    greedy = ravel_pytree(grads_of(state.q_critic.actor_target))[0]
    assert float(jnp.linalg.norm(ours - greedy)) > 1e-3 * float(jnp.linalg.norm(ours))
    # the diversity critic is not used by Q-PG and does not move
    for a, b in zip(jax.tree.leaves(d), jax.tree.leaves(state.d_critic)):
        np.testing.assert_array_equal(a, b)
    # each actor then takes one step of the mutation optimiser against the updated critic
    opt = td3.mutation_optimizer
    for i in range(2):
        actor = one(parents, i)
        grads = jax.grad(td3.actor_loss)(actor, expected.critic, batch["obs"])
        updates, _ = opt.update(grads, opt.init(actor))
        hand = optax.apply_updates(actor, updates)
        for a, b in zip(jax.tree.leaves(one(offspring, i)), jax.tree.leaves(hand)):
            np.testing.assert_allclose(a, b, rtol=2e-5, atol=1e-6)


def test_the_thesis_coupling_drives_each_critic_by_the_actors_of_its_kind(maze):
    """QD-PG: the diversity actors' batches get fresh novelty rewards, the quality
    actors' keep the environment's; both critics move, and a step of the whole loop
    plays exactly batch_size mutated actors."""
    algo = dataclasses.replace(small_qdpg(maze, archive_k=2), coupling="thesis")
    archive = NoveltyArchive.create(4, 2).replace(
        data=jnp.array([[0.0, 0.0], [1.0, 0.0], [0.0, 2.0], [5.0, 5.0]]),
        num_added=jnp.asarray(4, jnp.int32),
    )
    sd = jnp.broadcast_to(jnp.array([0.0, 1.0]), (3, 4, 5, 2))  # steps x actors x batch
    batches = {"state_descriptor": sd, "reward": jnp.full((3, 4, 5), -0.5)}
    diversity = jnp.array([True, False, True, False])
    rewards = np.asarray(algo.actor_rewards(archive, batches, diversity))
    np.testing.assert_allclose(rewards[:, [0, 2]], 1.0, rtol=1e-6)  # novelty of (0, 1): 1.0
    np.testing.assert_allclose(rewards[:, [1, 3]], -0.5)
    state, _ = algo.init(jax.random.PRNGKey(0))
    new, ev = jax.jit(algo.step)(state)
    assert ev.fitness.shape == (algo.batch_size,)
    for old, moved in ((state.q_critic, new.q_critic), (state.d_critic, new.d_critic)):
        assert any(
            not np.array_equal(a, b)
            for a, b in zip(jax.tree.leaves(old.critic), jax.tree.leaves(moved.critic))
        )


def test_qdax_coupling_plays_the_greedy_actors_into_buffer_archive_and_grid(maze):
    """QDax's variant: of batch_size episodes, the last two are the quality and the
    diversity critics' greedy actors (their actions are theirs); every one of their
    steps enters the replay buffer and the archive, and they compete for cells."""
    algo = dataclasses.replace(small_qdpg(maze), coupling="qdax")
    assert algo.num_mutations == algo.batch_size - 2
    state, _ = algo.init(jax.random.PRNGKey(0))
    state = state.replace(d_critic=algo.td3.init(jax.random.PRNGKey(9)))
    new, ev = jax.jit(algo.step)(state)
    apply = algo.network.apply
    for episode, critic in ((-2, state.q_critic), (-1, state.d_critic)):
        length = int(ev.length[episode])
        obs = ev.trajectory["obs"][episode, :length]
        np.testing.assert_allclose(
            ev.trajectory["action"][episode, :length],
            jax.vmap(lambda o: apply(critic.actor, o))(obs),
            rtol=1e-5,
            atol=1e-6,
        )
    # the buffer: the old transitions, then every valid step of the batch, greedy episodes last
    before, added = int(state.buffer.size), int(ev.length.sum())
    assert int(new.buffer.size) == before + added
    last = int(ev.length[-1])
    np.testing.assert_allclose(
        new.buffer.data["obs"][before + added - last : before + added],
        ev.trajectory["obs"][-1, :last],
    )
    # the archive: the whole batch's state descriptors, greedy episodes included, in order
    t = ev.trajectory
    expected = state.archive.add(
        t["state_descriptor"].reshape(-1, 2),
        algo.archive_threshold,
        algo.archive_k,
        t["valid"].reshape(-1),
    )
    np.testing.assert_array_equal(new.archive.data, expected.data)
    # the grid: each cell holds the best of its incumbent and of the batch's episodes in it
    cells = np.asarray(
        jax.vmap(lambda d: jnp.argmin(jnp.sum((algo.centroids - d) ** 2, -1)))(ev.descriptor)
    )
    for i in (-2, -1):
        in_cell = cells == cells[i]
        best = max(float(state.repertoire.fitnesses[cells[i]]), float(ev.fitness[in_cell].max()))
        assert float(new.repertoire.fitnesses[cells[i]]) == pytest.approx(best)
    with pytest.raises(ValueError, match="at least one must be a mutation"):
        dataclasses.replace(algo, batch_size=2)
    with pytest.raises(ValueError, match="unknown coupling"):
        dataclasses.replace(algo, coupling="cem")


def test_novelty_reward_sums_or_averages_the_k_distances(maze):
    """Eq. 3.5 sums the K neighbour distances, Section 3.6.3 averages them."""
    archive = NoveltyArchive.create(4, 2).replace(
        data=jnp.array([[0.0, 0.0], [1.0, 0.0], [0.0, 2.0], [5.0, 5.0]]),
        num_added=jnp.asarray(4, jnp.int32),
    )
    batch = {"state_descriptor": jnp.array([[0.0, 1.0], [1.0, 1.0]])}
    mean = [1.0, (1.0 + np.sqrt(2.0)) / 2]
    for reduction, expected in (("mean", mean), ("sum", [2.0, 1.0 + np.sqrt(2.0)])):
        algo = small_qdpg(maze, archive_k=2, novelty_reduction=reduction)
        np.testing.assert_allclose(algo.novelty_reward(archive, batch), expected, rtol=1e-6)
    # with fewer valid entries than K, the sum is over those there are
    few = archive.replace(num_added=jnp.asarray(1, jnp.int32))
    np.testing.assert_allclose(
        few.novelty(batch["state_descriptor"], 2, reduction="sum"), [1.0, np.sqrt(2.0)], rtol=1e-6
    )
    with pytest.raises(ValueError, match="unknown novelty_reduction"):
        small_qdpg(maze, novelty_reduction="median")


def test_a_point_on_a_wall_face_is_filed_on_its_side():
    """The upper wall's lower face (y = 0.2) is an edge of the 5 x 5 grid: a point
    stopped under the wall is filed in the row below it, one on its upper face in
    the row above; the lower wall's faces lie inside a row and stay there."""
    from qdnb.envs.pointmaze import FACE_OFFSET, PointMaze, off_the_faces, reachable
    from qdnb.qd.cvt import nearest

    centroids = grid_centroids((5, 5), (-1, -1), (1, 1))
    row = lambda p: float(centroids[int(nearest(centroids, jnp.asarray([p], jnp.float32))[0]), 1])
    faces = {
        (-0.3, 0.20): (0.20 - FACE_OFFSET, 0.0),  # under the upper wall: the row of y = 0
        (-0.3, 0.21): (0.21 + FACE_OFFSET, 0.4),  # on top of it: the row of y = 0.4
        (0.0, -0.50): (-0.50 - FACE_OFFSET, -0.4),  # under the lower wall
        (0.0, -0.49): (-0.49 + FACE_OFFSET, -0.4),  # on top of it
        (0.8, 0.20): (0.20, None),  # past the upper wall's end: not on a face, unchanged
    }
    for (x, y), (moved, cell_row) in faces.items():
        p = off_the_faces(jnp.array([x, y], jnp.float32))
        assert float(p[0]) == pytest.approx(x) and float(p[1]) == pytest.approx(moved, abs=1e-7)
        if cell_row is not None:
            assert row(p) == pytest.approx(cell_row)
    # an episode that pushes up under the upper wall ends filed below it
    env = PointMaze(episode_length=5)
    state = env.reset(jax.random.PRNGKey(0)).replace(core=jnp.array([-0.3, 0.05]))
    for _ in range(5):
        state = env.step(state, jnp.array([0.0, 1.0]))
    assert float(state.core[1]) == pytest.approx(0.2)
    d = env.behaviour_descriptor(state.state_descriptor, None, None)
    assert row(d) == pytest.approx(0.0)
    # reachability: the walls' insides are not reachable, their faces and the arena are
    assert reachable(np.array([[-0.3, 0.205], [0.0, -0.495]])).tolist() == [False, False]
    assert reachable(np.array([[-0.3, 0.2], [0.0, -0.49], [0.9, 0.9]])).all()


def test_coverage_counts_the_reachable_cells():
    from qdnb.chapters.ch3_qdpg import reachable_cells, reachable_coverage

    env = make_env("pointmaze")
    assert reachable_cells("pointmaze", env, 5).all()  # every cell of the 5 x 5 grid has room
    filled = np.zeros((2, 25), bool)
    filled[0, :5] = True
    np.testing.assert_allclose(reachable_coverage(filled, "pointmaze", env, 5), [0.2, 0.0])


def test_the_coupling_ab_runs_its_variants_picks_by_its_rule_and_resumes(tmp_path, monkeypatch):
    """bench/probes/qdpg_coupling.py at tiny: (a), (b), (c), then (d) on the variant its rule
    picks, each on the same seeds; a second call skips what is done."""
    import importlib.util
    import json
    import sys

    bench = Path(__file__).parents[1] / "bench"
    monkeypatch.syspath_prepend(str(bench))
    spec = importlib.util.spec_from_file_location(
        "qdpg_coupling", bench / "probes" / "qdpg_coupling.py"
    )
    ab = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(ab)
    out = tmp_path / "ab.json"
    argv = ["qdpg_coupling.py", "--scale", "tiny", "--steps", "1600", "--seeds", "2"]
    monkeypatch.setattr(sys, "argv", argv + ["--skip-ratio", "--out", str(out)])
    ab.main()
    first = json.loads(out.read_text())
    ab.main()
    assert json.loads(out.read_text())["runs"] == first["runs"]
    d = f"d-{first['picked_for_d'].split('-')[1]}-sum"
    assert list(first["runs"]) == ["a-greedy", "b-thesis", "c-qdax", d]
    assert first["runs"][d]["overrides"]["novelty_reduction"] == "sum"
    for entry in first["runs"].values():
        assert len(entry["final_performance"]) == 2
        assert all(0 < e <= 1600 for e in entry["env_steps"])
        shares = entry["where_episodes_end"]
        assert all(0 <= v <= 1 for values in shares.values() for v in values)
    fake = {
        "b-thesis": {"reached_exit": 1, "mean_final_performance": -100.0},
        "c-qdax": {"reached_exit": 1, "mean_final_performance": -90.0},
    }
    assert ab.pick(fake) == "c-qdax"  # a tie on the exit: the better mean
    fake["b-thesis"]["reached_exit"] = 2
    assert ab.pick(fake) == "b-thesis"


def test_each_iteration_records_its_updates_statistics(maze):
    from qdnb.qd.qdpg import UPDATE_STATISTICS

    for coupling in ("thesis", "greedy"):
        algo = dataclasses.replace(small_qdpg(maze), coupling=coupling)
        state, _ = algo.init(jax.random.PRNGKey(0))
        assert all(float(state.updates[k]) == 0.0 for k in UPDATE_STATISTICS)
        state, _ = algo.step(state)
        stats = {k: float(v) for k, v in algo.metrics(state).items() if k in UPDATE_STATISTICS}
        assert set(stats) == set(UPDATE_STATISTICS)
        assert stats["critic_loss_q"] > 0 and stats["critic_loss_d"] > 0
        norms = [stats[k] for k in ("critic_grad_norm_q", "critic_grad_norm_d", "actor_grad_norm")]
        # the thesis's coupling measures its gradients; the greedy readings their losses only
        assert all(n > 0 for n in norms) if coupling == "thesis" else all(n == 0 for n in norms)


def test_the_population_plays_with_exploration_noise_only_when_asked(maze):
    algo = small_qdpg(maze)
    params = algo.random_policies(jax.random.PRNGKey(1))
    key = jax.random.PRNGKey(2)
    plain = evaluate_policies(maze, algo.network.apply, params, key)
    quiet = algo.evaluate(params, key)
    np.testing.assert_array_equal(quiet.descriptor, plain.descriptor)  # the default plays as before
    noisy = dataclasses.replace(algo, exploration_noise=0.1).evaluate(params, key)
    assert not np.allclose(noisy.descriptor, plain.descriptor)


def test_every_reading_the_ab_can_run_has_its_name_on_the_page(monkeypatch):
    """bench/qdpg_ab.py's variants and diagnostics, in its order, are the page's READINGS:
    a row of a reading the page cannot name would be left out of its table."""
    import importlib.util

    from qdnb.chapters import ch3_qdpg as chapter

    bench = Path(__file__).parents[1] / "bench"
    monkeypatch.syspath_prepend(str(bench))
    spec = importlib.util.spec_from_file_location("qdpg_ab", bench / "qdpg_ab.py")
    ab = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(ab)
    assert list(chapter.READINGS) == [*ab.VARIANTS, *ab.DIAGNOSTICS]


def test_the_readings_table_follows_the_rule_and_leaves_diverged_seeds_out():
    from qdnb.chapters import ch3_qdpg as chapter

    def row(variant, seed, exit_steps=None, final=-126.0, diverged=None):
        stats = {k: [1.0, 2.0, 3.0] for k in ("critic_loss_q", "critic_loss_d",
                 "critic_grad_norm_q", "critic_grad_norm_d")}  # fmt: skip
        stats["actor_grad_norm"] = [7.71, 1863.4, 1e6]  # the book's number style
        return {
            "variant": variant,
            "seed": seed,
            "reached_exit": exit_steps is not None,
            "steps_to_exit": exit_steps,
            "final_performance": None if diverged else final,
            "share_above_upper_wall": 0.1,
            "coverage": None if diverged else 0.5,
            "diverged": diverged,
            "statistics_before_divergence": stats if diverged else None,
            "pair_wall_seconds": 1800.0,
        }

    lost = {"iteration": 250, "parts": ["q_critic", "d_critic"]}
    ab = {
        "rows": [row("thesis-adam", s) for s in range(4)]
        + [row("sum", 0, 3.7e5, -30.0), row("sum", 1, 5e5, -40.0), row("sum", 2, 8e5, -35.0)]
        + [row("sum", 3)]
        + [row("thesis-sgd", 0, diverged=lost), row("thesis-sgd", 1, final=-120.0)]
    }
    rows = {r["reading"]: r for r in chapter.reading_rows(ab)}
    assert list(rows) == [chapter.READINGS[v] for v in ("thesis-adam", "sum", "thesis-sgd")]
    assert rows[chapter.READINGS["sum"]]["seeds in the exit zone"] == "3/4"
    assert rows[chapter.READINGS["sum"]]["steps to the exit zone"] == "3.7·10⁵, 5·10⁵, 8·10⁵"
    sgd = rows[chapter.READINGS["thesis-sgd"]]
    assert sgd["final performance"] == "-120.0 (1 seed), 1 diverged"  # not averaged in
    assert sgd["diverged (iteration)"] == "250"
    assert chapter.reading_exits(ab, "sum") and not chapter.reading_exits(ab, "thesis-adam")
    # fewer than 4 seeds call nothing; 2 of 4 is one seed from the verdict: two more seeds,
    # then three quarters of 6 (5) must exit
    two = [row("x", s, 1e5) for s in range(2)]
    assert not chapter.reading_exits({"rows": two}, "x")
    half = {"rows": two + [row("x", 2), row("x", 3)]}
    assert chapter.reading_needs_more_seeds(half, "x") and not chapter.reading_exits(half, "x")
    assert not chapter.reading_needs_more_seeds(ab, "sum")  # 3 of 4: decided
    assert not chapter.reading_needs_more_seeds(ab, "thesis-adam")  # 0 of 4: decided
    four = {"rows": half["rows"] + [row("x", 4, 1e5), row("x", 5, 1e5)]}
    assert not chapter.reading_exits(four, "x")  # 4 of 6 is less than three quarters
    five = {"rows": two + [row("x", 2, 1e5), row("x", 3), row("x", 4, 1e5), row("x", 5, 1e5)]}
    assert chapter.reading_exits(five, "x")  # 5 of 6
    assert not chapter.reading_needs_more_seeds(four, "x")  # 6 seeds: read as they are
    (d,) = chapter.divergence_rows(ab)
    assert d["NaN at iteration"] == 250 and d["parts"] == "quality critic, diversity critic"
    assert d["quality critic loss"] == "1 → 2"  # the first and the last finite iteration
    assert d["actor gradient norm"] == "7.71 → 1,860"  # not 1.86e+03
    peer = {"rows": [{"reached_exit": True, "steps_to_exit": 5e5, "final_performance": -30.0,
                      "coverage": 0.2, "wall_seconds": 600.0}]}  # fmt: skip
    assert chapter.reading_rows(ab, peer)[-1]["seeds in the exit zone"] == "1/1"
    published = {"methods": {"QD-PG": {"seeds": [
        {"final_performance": -24.0, "steps_to_exit": 4e5, "coverage": 0.9},
        {"final_performance": None, "steps_to_exit": None, "coverage": None},
    ], "seconds_per_iteration": 0.2, "wall_seconds": 300.0}}}  # fmt: skip
    (p,) = chapter.published_rows(published)
    assert p["seeds in the exit zone"] == "1/2"
    assert p["final performance"] == "-24.0 (1 seed), 1 diverged"
    assert p["coverage"] == "0.90"  # the diverged seed's None is in no mean
    published["methods"]["QD-PG"]["seeds"][0]["coverage"] = 0.0  # a finite zero is a value
    assert chapter.published_rows(published)[0]["coverage"] == "0.00"
