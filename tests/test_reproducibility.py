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
    # the episode's descriptor is read from the final state descriptor of its path (Point-Maze: the
    # final position, moved off a wall's face to its side)
    final = env.behaviour_descriptor(ev.trajectory[:, :, -1], None, None)
    np.testing.assert_allclose(final, ev.descriptor, atol=1e-6)
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
    # a typed key plays the same episodes as the raw key it wraps
    typed = player.episodes(5)(params, jax.random.wrap_key_data(jax.random.PRNGKey(1)))
    np.testing.assert_array_equal(typed.fitness, ev.fitness)


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
    assert cells_for_coverage(coverage, target=0.8) == 32
    assert cells_for_coverage(coverage) == 64  # the default: 60 % for every method
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


def test_seed_scores_and_claim_checks_on_a_hand_made_result():
    """Two seeds, one 1-D goal at 0: ME-LS delivers 1.0 and 2.0 where it promised
    0.5 and 1.0 (gap 0.5 and 1.0); ME delivers 3.0 and 1.0, promised 0 and 0.5."""
    from types import SimpleNamespace

    from qdnb.chapters.ch4_reproducibility import EnvironmentResult, claim_checks, seed_scores

    def method(distance, promised, spread, coverage, coverage_after):
        rep = SimpleNamespace(descriptors=np.array(promised, np.float32).reshape(2, 1, 1))
        acc = SimpleNamespace(
            distance=np.array(distance, np.float32).reshape(2, 1),
            spread=np.array(spread, np.float32).reshape(2, 1),
            chosen=np.zeros((2, 1), int),
        )
        return SimpleNamespace(
            accuracy=acc,
            repertoire=rep,
            metrics={"coverage": np.array(coverage)},
            metrics_reassessed={"coverage": np.array(coverage_after)},
        )

    res = EnvironmentResult(
        "toy",
        None,
        np.zeros((1, 1), np.float32),
        np.zeros((1, 1), np.float32),
        0.0,
        methods={
            "ME-LS": method([1.0, 2.0], [0.5, 1.0], [0.1, 0.2], [0.5, 0.4], [0.5, 0.2]),
            "ME": method([3.0, 1.0], [0.0, 0.5], [0.3, 0.1], [0.8, 0.8], [0.4, 0.2]),
            "PGA-ME-LS": method([1.0, 1.0], [1.0, 1.0], [0.1, 0.1], [0.5, 0.5], [0.5, 0.5]),
            "PGA-ME": method([2.0, 2.0], [1.0, 1.0], [0.2, 0.2], [0.5, 0.5], [0.25, 0.25]),
        },
    )
    s = seed_scores(res, "ME-LS")
    np.testing.assert_allclose(s["reproduction_gap"], [0.5, 1.0])
    np.testing.assert_allclose(s["avg_promised_distance"], [0.5, 1.0])
    np.testing.assert_allclose(s["coverage_kept"], [1.0, 0.5])
    checks = {c["claim"]: c for c in claim_checks({"toy": res})}
    # distance: 1.5 vs 2.0 on the mean, but 1 seed of 2 only: does not hold
    assert not checks["ME-LS average distance < ME"]["holds"]
    assert checks["ME-LS average distance < ME"]["seeds where it holds"] == "1/2"
    assert checks["ME-LS keeps more coverage than ME on reassessment"]["holds"]  # 0.75 vs 0.375
    assert checks["PGA-ME-LS average spread < PGA-ME"]["holds"]
    assert len(checks) == 6


def test_results_are_frozen():
    from qdnb.chapters.ch4_reproducibility import EnvironmentResult

    res = EnvironmentResult("ant_omni", None, np.zeros((2, 2)), np.zeros((3, 2)), 0.0, {})
    with pytest.raises(dataclasses.FrozenInstanceError):
        res.goals = np.ones((3, 2))


def test_ant_omni_distances_compare_as_shares_of_the_box_when_the_boxes_differ():
    from qdnb.book.registry import config

    small = config("ch4_reproducibility", "small")
    note = dataclasses.replace(small, ant_omni_box=2.5).extent_note("ant_omni", 6.38, 1.568)
    assert note == "as a share of the box's side: thesis 0.21 (of 30 m), this run 0.31 (of 5 m)"
    assert config("ch4_reproducibility", "paper").extent_note("ant_omni", 6.38, 1.5) == ""
    assert small.extent_note("halfcheetah_uni", 0.1, 0.2) == ""  # [0, 1]^2 at every scale
