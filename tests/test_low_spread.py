import jax
import jax.numpy as jnp
import numpy as np

from qdnb.core.evaluation import Evaluation
from qdnb.envs import make_env
from qdnb.envs.rollout import evaluate_episodes, evaluate_policies
from qdnb.nets.mlp import MLP, init_policies
from qdnb.qd.low_spread import (
    LowSpreadRepertoire,
    LowSpreadScores,
    geometric_median,
    insert_low_spread,
    low_spread_scores,
    mode_cell,
    nearest_cells,
    spread,
)
from qdnb.qd.repertoire import init_repertoire

CENTROIDS = jnp.array([[0.0, 0.0], [10.0, 0.0]])


def test_spread_hand_computed():
    # pairs: (0,0)-(3,0)=3, (0,0)-(0,4)=4, (3,0)-(0,4)=5 -> mean 4
    np.testing.assert_allclose(
        spread(jnp.array([[0.0, 0.0], [3.0, 0.0], [0.0, 4.0]])), 4.0, rtol=1e-6
    )
    np.testing.assert_allclose(spread(jnp.ones((5, 2))), 0.0)
    np.testing.assert_allclose(spread(jnp.ones((1, 2))), 0.0)


def test_mode_cell_and_ties():
    assert int(mode_cell(jnp.array([3, 1, 1, 2, 1]))) == 1
    assert int(mode_cell(jnp.array([4, 2, 2, 4]))) == 4  # tie: the cell reached first


def test_geometric_median():
    # the geometric median of a cross is its centre, whatever the outlier's distance
    pts = jnp.array([[0.0, 0.0], [1.0, 0.0], [-1.0, 0.0], [0.0, 1.0], [0.0, -1.0], [100.0, 0.0]])
    np.testing.assert_allclose(geometric_median(pts, 200), [0.2, 0.0], atol=0.25)
    np.testing.assert_allclose(
        geometric_median(jnp.array([[0.0, 0.0], [0.0, 0.0], [5.0, 5.0]]), 200),
        [0.0, 0.0],
        atol=1e-3,
    )
    # collinear points: the median of the middle
    np.testing.assert_allclose(
        geometric_median(jnp.array([[0.0, 0.0], [1.0, 0.0], [9.0, 0.0]]), 300),
        [1.0, 0.0],
        atol=1e-3,
    )


def test_scores_use_the_mode_cell_and_its_mean_descriptor():
    fit = jnp.array([[1.0, 2.0, 3.0]])
    desc = jnp.array(
        [[[0.0, 1.0], [0.0, -1.0], [10.0, 0.0]]]
    )  # two episodes in cell 0, one in cell 1
    s = low_spread_scores(CENTROIDS, fit, desc)
    np.testing.assert_allclose(s.fitness, [2.0])
    np.testing.assert_array_equal(s.cell, [0])
    np.testing.assert_allclose(s.descriptor, [[0.0, 0.0]])
    np.testing.assert_allclose(s.spread, [(2.0 + 2 * np.hypot(10.0, 1.0)) / 3], rtol=1e-6)


def _lsr():
    return LowSpreadRepertoire.create(init_repertoire(CENTROIDS, {"w": jnp.zeros(2)}))


def _scores(fit, cell, spr):
    fit = jnp.asarray(fit, jnp.float32)
    return LowSpreadScores(
        fit,
        jnp.asarray(cell),
        jnp.asarray(CENTROIDS)[jnp.asarray(cell)],
        jnp.asarray(spr, jnp.float32),
    )


def _genotypes(ids):
    return {"w": jnp.asarray(ids, jnp.float32)[:, None] * jnp.ones((1, 2))}


def test_low_spread_insertion_rules():
    lsr, inserted = insert_low_spread(_lsr(), _genotypes([1]), _scores([5.0], [0], [2.0]))
    assert inserted.tolist() == [True]  # empty cell
    np.testing.assert_allclose(lsr.spreads, [2.0, np.inf])
    cases = [  # (fitness, spread, inserted?) against the incumbent (5.0, 2.0)
        (6.0, 3.0, False),  # better fitness, higher spread
        (4.0, 1.0, False),  # lower spread, worse fitness
        (5.0, 1.0, False),  # equal fitness is not better
        (6.0, 1.0, True),  # both better
    ]
    for fit, spr, expected in cases:
        new, inserted = insert_low_spread(lsr, _genotypes([2]), _scores([fit], [0], [spr]))
        assert bool(inserted[0]) == expected, (fit, spr)
        assert float(new.repertoire.fitnesses[0]) == (fit if expected else 5.0)


def test_two_candidates_for_one_cell_follow_the_same_rule():
    lsr, _ = insert_low_spread(_lsr(), _genotypes([1]), _scores([5.0], [0], [2.0]))
    # candidate 0 beats the incumbent; candidate 1 is fitter but has a higher spread than the
    # incumbent, so it is not eligible; candidate 2 is eligible and fitter than candidate 0
    new, inserted = insert_low_spread(
        lsr, _genotypes([10, 11, 12]), _scores([6.0, 9.0, 7.0], [0, 0, 0], [1.0, 3.0, 1.5])
    )
    assert inserted.tolist() == [False, False, True]
    assert float(new.repertoire.genotypes["w"][0, 0]) == 12.0 and float(new.spreads[0]) == 1.5
    # in an empty cell every candidate is eligible and the fittest wins
    new, inserted = insert_low_spread(
        _lsr(), _genotypes([10, 11]), _scores([1.0, 2.0], [1, 1], [0.1, 9.0])
    )
    assert inserted.tolist() == [False, True]


def test_multi_episode_evaluation_differs_only_by_initial_state():
    env = make_env("pointmaze")
    net = MLP((8, 2))
    params = init_policies(net, jax.random.PRNGKey(0), 3, env.observation_size)
    ev = evaluate_episodes(env, net.apply, params, jax.random.PRNGKey(1), 4)
    assert ev.fitness.shape == (3, 4) and ev.descriptor.shape == (3, 4, 2)
    assert len(np.unique(np.asarray(ev.fitness[0]))) == 4  # different starts, different episodes
    # episode e of every policy is the batched evaluation with the e-th key
    one = evaluate_policies(env, net.apply, params, jax.random.split(jax.random.PRNGKey(1), 4)[2])
    np.testing.assert_allclose(ev.fitness[:, 2], one.fitness, rtol=1e-6)


def test_reassessment_with_a_stub_scoring_function():
    from qdnb.qd.low_spread import reassess
    from qdnb.qd.repertoire import insert

    centroids = jnp.array([[0.0, 0.0], [10.0, 0.0], [20.0, 0.0]])
    rep = init_repertoire(centroids, {"g": jnp.zeros(())})
    # three elites, one per cell, with genotypes 1, 2, 3
    rep, _ = insert(
        rep, {"g": jnp.array([1.0, 2.0, 3.0])}, jnp.array([10.0, 20.0, 30.0]), centroids
    )

    def stub(
        genotypes, key
    ):  # every solution really lands in cell 0 twice out of three, with fitness g
        del key
        g = genotypes["g"]
        desc = jnp.stack(
            [jnp.zeros((3, 2)), jnp.zeros((3, 2)), jnp.tile(jnp.array([[20.0, 0.0]]), (3, 1))],
            axis=1,
        )
        return Evaluation(
            fitness=jnp.repeat(g[:, None], 3, axis=1), descriptor=desc, length=jnp.full((3, 3), 30)
        )

    new, scores = reassess(rep, stub, jax.random.PRNGKey(0))
    # all three collapse into cell 0, which keeps the fittest (genotype 3, mean fitness 3)
    np.testing.assert_array_equal(new.filled, [True, False, False])
    np.testing.assert_allclose(new.fitnesses[0], 3.0)
    np.testing.assert_allclose(new.genotypes["g"][0], 3.0)
    # descriptors (0,0), (0,0), (20,0): pairwise distances 0, 20, 20, spread 40/3 for every solution
    np.testing.assert_allclose(scores.spread, [40.0 / 3] * 3, rtol=1e-6)


def test_me_low_spread_and_sampling_run_and_keep_their_invariants():
    from qdnb.qd.algorithms import MapElitesLowSpread, MapElitesSampling, run_seeds
    from qdnb.qd.cvt import grid_centroids

    env = make_env("pointmaze", episode_length=30)
    common = dict(
        env=env,
        network=MLP((4, 2)),
        batch_size=8,
        iso_sigma=0.1,
        line_sigma=0.2,
        centroids=grid_centroids((4, 4), (-1, -1), (1, 1)),
        fitness_offset=-100.0,
    )
    keys = jax.random.split(jax.random.PRNGKey(0), 1)
    ls_state, _, h = run_seeds(
        MapElitesLowSpread(**common, num_episodes=3),
        keys,
        4,
        4,
        (4, 4),
        (-0.5, 0.8),
        progress=False,
    )
    assert h["descriptors"].shape == (1, 5, 8, 3, 2)
    lsr = jax.tree.map(lambda x: x[0], ls_state.repertoire)
    filled = np.asarray(lsr.repertoire.filled)
    assert filled.any() and np.all(np.isfinite(np.asarray(lsr.spreads)[filled]))
    # every stored descriptor lies in the cell it is filed under: no centroid is
    # nearer than its own (a point stopped on a wall face can sit exactly on a
    # cell boundary, so ties count as inside)
    c, d = np.asarray(lsr.repertoire.centroids), np.asarray(lsr.repertoire.descriptors)
    dist = np.linalg.norm(d[:, None, :] - c[None, :, :], axis=-1)
    own = dist[np.arange(16), np.arange(16)]
    assert np.all(own[filled] <= dist.min(axis=1)[filled] + 1e-6)
    sampling_state, _, h = run_seeds(
        MapElitesSampling(**common, num_episodes=3), keys, 4, 4, (4, 4), (-0.5, 0.8), progress=False
    )
    assert np.all(np.diff(h["qd_score"], axis=1) >= 0)


def test_accuracy_plays_the_nearest_stored_policy():
    from qdnb.qd.low_spread import accuracy
    from qdnb.qd.repertoire import insert

    centroids = jnp.array([[0.0, 0.0], [10.0, 0.0], [20.0, 0.0]])
    rep = init_repertoire(centroids, {"g": jnp.zeros(())})
    rep, _ = insert(
        rep,
        {"g": jnp.array([1.0, 3.0])},
        jnp.array([1.0, 1.0]),
        jnp.array([[0.0, 0.0], [20.0, 0.0]]),
    )

    def stub(genotypes, key):  # policy g lands at (g, 0) and (g, 2)
        del key
        g = genotypes["g"]
        desc = jnp.stack(
            [jnp.stack([g, jnp.zeros_like(g)], -1), jnp.stack([g, 2 * jnp.ones_like(g)], -1)],
            axis=1,
        )
        return Evaluation(
            fitness=jnp.zeros((g.shape[0], 2)), descriptor=desc, length=jnp.ones((g.shape[0], 2))
        )

    goals = jnp.array([[1.0, 1.0], [12.0, 0.0], [19.0, 1.0]])
    acc = accuracy(rep, goals, stub, jax.random.PRNGKey(0))
    np.testing.assert_array_equal(acc.chosen, [0, 2, 2])  # cell 1 is empty: never chosen
    # goal (1,1), policy 1 lands on (1,0) and (1,2): distance 1 each; goal (12,0), policy 3:
    # (3,0),(3,2)
    np.testing.assert_allclose(
        acc.distance,
        [1.0, (9.0 + np.hypot(9.0, 2.0)) / 2, (np.hypot(16, 1) + np.hypot(16, 1)) / 2],
        rtol=1e-6,
    )
    np.testing.assert_allclose(acc.spread, [2.0, 2.0, 2.0])


def test_nearest_cells_picks_the_nearest_allowed_cell():
    """The nearest cell of [1, 1] is forbidden, so its goal goes to [0, 0]; ties none."""
    descriptors = jnp.array([[0.0, 0.0], [1.0, 1.0], [5.0, 5.0]])
    allowed = jnp.array([True, False, True])
    goals = jnp.array([[0.9, 0.9], [4.0, 4.0], [1.0, 1.0]])
    assert nearest_cells(descriptors, goals, allowed).tolist() == [0, 2, 0]
