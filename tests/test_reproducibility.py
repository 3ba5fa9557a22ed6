"""The Chapter 4 experiment plumbing: config checks, the representative-policy
rule, the chunked player, and the pickle-free repertoire files."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from qdnb.book import registry
from qdnb.chapters.ch4_reproducibility import (
    load_repertoires,
    representative_cells,
    save_repertoires,
)
from qdnb.envs import make_env
from qdnb.envs.player import Player
from qdnb.envs.rollout import rollout
from qdnb.nets.mlp import MLP, init_policies
from qdnb.qd.repertoire import init_repertoire, insert


def test_config_rejects_a_batch_that_does_not_split_into_episodes():
    tiny = registry.config("ch4_reproducibility", "tiny")
    with pytest.raises(ValueError, match="multiple of num_episodes"):
        dataclasses.replace(tiny, env_batch=10, num_episodes=4)
    with pytest.raises(ValueError, match="at least 2"):
        dataclasses.replace(tiny, env_batch=4, num_episodes=4)
    assert tiny.goals("ant_omni") == tiny.ant_omni_goals


def _repertoire():
    centroids = jnp.array([[0.0, 0.0], [3.0, 0.0], [0.0, 5.0], [9.0, 9.0], [1.0, 1.0]])
    rep = init_repertoire(centroids, {"w": jnp.zeros((2,))})
    # cells 0..3 filled, cell 4 empty; distances from the origin 0, 3, 5, 12.7; fitnesses 4, 3, 2, 1
    desc = centroids[:4]
    rep, _ = insert(
        rep, {"w": jnp.arange(8.0).reshape(4, 2)}, jnp.array([4.0, 3.0, 2.0, 1.0]), desc
    )
    return rep


def test_representative_cells_follow_the_stated_rule():
    rep = _repertoire()
    # Ant-Omni: ranked by distance from the start: cells 0, 1, 2, 3; quantiles 0.5, 0.75, 0.95 of 4
    # -> ranks 2, 2, 3
    np.testing.assert_array_equal(representative_cells(rep, "ant_omni"), [2, 2, 3])
    # elsewhere: ranked by fitness: cells 3, 2, 1, 0 -> ranks 2, 2, 3 are cells 1, 1, 0
    np.testing.assert_array_equal(representative_cells(rep, "halfcheetah_uni"), [1, 1, 0])
    np.testing.assert_array_equal(representative_cells(rep, "ant_omni", (0.0, 1.0)), [0, 3])
    empty = init_repertoire(rep.centroids, {"w": jnp.zeros((2,))})
    with pytest.raises(ValueError, match="empty"):
        representative_cells(empty, "ant_omni")


def test_player_matches_evaluate_episodes_and_pads_its_chunks():
    env = make_env("pointmaze", episode_length=20)
    net = MLP((8, env.action_size))
    params = init_policies(net, jax.random.PRNGKey(0), 3, env.observation_size)
    player = Player(
        env, net, chunk=4
    )  # 3 policies x 5 episodes = 15 episodes: 4 chunks, the last padded
    ev = player.episodes(5)(params, jax.random.PRNGKey(1))
    assert (
        ev.fitness.shape == (3, 5)
        and ev.descriptor.shape == (3, 5, 2)
        and ev.trajectory.shape == (3, 5, 20, 2)
    )
    # the final state descriptor of each path is the episode's descriptor (Point-Maze: final
    # position)
    np.testing.assert_allclose(ev.trajectory[:, :, -1], ev.descriptor, atol=1e-6)
    # episode e of policy p is one rollout from key split(key, 15)[5 p + e], whatever the chunking
    keys = jax.random.split(jax.random.PRNGKey(1), 15).reshape(3, 5, -1)
    for p in range(3):
        for e in range(5):
            one = rollout(env, net.apply, jax.tree.map(lambda x: x[p], params), keys[p, e])
            np.testing.assert_allclose(ev.fitness[p, e], one.fitness, rtol=1e-5)
            np.testing.assert_allclose(ev.descriptor[p, e], one.descriptor, rtol=1e-5)
    # its episodes differ by their starts
    assert len(np.unique(np.asarray(ev.fitness))) == 15
    # with a mask, only the chosen policies are played; the others come back as zeros
    masked = player.episodes(5, only=jnp.array([False, True, False]))(params, jax.random.PRNGKey(1))
    assert masked.fitness.shape == (3, 5) and np.all(np.asarray(masked.fitness)[[0, 2]] == 0)
    for e, k in enumerate(
        jax.random.split(jax.random.PRNGKey(1), 5)
    ):  # one policy played: keys split(key, 5)
        one = rollout(env, net.apply, jax.tree.map(lambda x: x[1], params), k)
        np.testing.assert_allclose(masked.fitness[1, e], one.fitness, rtol=1e-5)


def test_repertoires_round_trip_without_pickle(tmp_path):
    net = MLP((4, 2))
    rep = init_repertoire(
        jnp.zeros((3, 2)),
        jax.tree.map(lambda x: x[0], init_policies(net, jax.random.PRNGKey(0), 1, 2)),
    )
    stacked = jax.tree.map(lambda x: jnp.stack([x, x + 1]), rep)  # two seeds
    spread = np.array([[0.1, np.nan, 0.3], [0.2, 0.4, np.nan]])
    path = save_repertoires(tmp_path / "r.npz", "abc", stacked, spread, spread * 2)
    with np.load(path, allow_pickle=False) as data:  # readable with pickling disabled
        assert "genotype/params/Dense_0/kernel" in data.files
    loaded = load_repertoires(path, "abc")
    np.testing.assert_array_equal(loaded["spread"], spread)
    np.testing.assert_array_equal(loaded["fitnesses"], stacked.fitnesses)
    for a, b in zip(jax.tree.leaves(loaded["genotypes"]), jax.tree.leaves(stacked.genotypes)):
        np.testing.assert_array_equal(a, b)
    assert jax.tree.structure(loaded["genotypes"]) == jax.tree.structure(
        jax.device_get(stacked.genotypes)
    )
    assert load_repertoires(path, "another hash") is None


def test_run_environments_rejects_unknown_environments_before_computing():
    from qdnb.chapters.ch4_reproducibility import run_environments

    cfg = dataclasses.replace(
        registry.config("ch4_reproducibility", "tiny"), environments=("ant_omni", "antmaze_typo")
    )
    with pytest.raises(ValueError, match="antmaze_typo"):
        run_environments(cfg, jax.random.PRNGKey(0))


def test_reach_bound_is_the_rounded_up_quantile_of_the_largest_coordinate():
    from qdnb.chapters.ch4_reproducibility import reach_bound

    # 100 points whose larger |coordinate| is 0.1, 0.2, ..., 10.0 (on either axis, either sign)
    r = np.arange(1, 101) / 10.0
    points = np.stack(
        [np.where(np.arange(100) % 2, r, -0.5 * r), np.where(np.arange(100) % 2, 0.3 * r, -r)], 1
    )
    assert (
        reach_bound(points, quantile=0.95, step=0.5) == 10.0
    )  # the 95th percentile, 9.505, rounded up
    assert reach_bound(points, quantile=0.9, step=0.5) == 9.5  # 9.01 -> 9.5
    assert reach_bound(points, quantile=1.0, step=0.5) == 10.0
    assert (
        reach_bound(points, quantile=0.5, step=1.0) == 6.0
    )  # median 5.05, rounded up to a whole metre
    assert (
        reach_bound(np.array([[0.01, 0.0], [np.nan, 1.0]])) == 0.5
    )  # never below one step; NaN rows ignored
    with pytest.raises(ValueError):
        reach_bound(np.zeros((0, 2)))


def test_cells_for_coverage_takes_the_largest_count_that_fills():
    from qdnb.chapters.ch4_reproducibility import cells_for_coverage

    coverage = {
        32: np.array([[0.9, 0.8, 0.85], [0.82, 0.8, 0.9]]),  # (methods, seeds)
        64: np.array(
            [[0.9, 0.9, 0.9], [0.7, 0.8, 0.8]]
        ),  # the second method misses 0.8 on the mean
        128: np.array([[0.5, 0.5, 0.5], [0.3, 0.3, 0.3]]),
    }
    assert cells_for_coverage(coverage) == 32
    assert cells_for_coverage(coverage, target=0.7) == 64
    assert cells_for_coverage(coverage, target=0.95) == 32  # none fills: the smallest count


def test_descriptor_box_is_a_config_of_the_task():
    import dataclasses

    from qdnb.book.registry import config

    paper, small = config("ch4_reproducibility", "paper"), config("ch4_reproducibility", "small")
    assert paper.make_env("ant_omni").descriptor_high == (15.0, 15.0)
    assert (
        small.make_env("ant_omni").descriptor_low == (-small.ant_omni_box,) * 2
        and small.ant_omni_box < 15
    )
    assert small.make_env("halfcheetah_uni").descriptor_high == (1.0, 1.0)
    with pytest.raises(ValueError, match="ant_omni_box"):
        dataclasses.replace(small, ant_omni_box=0.0)
