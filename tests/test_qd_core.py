import jax
import jax.numpy as jnp
import numpy as np
import pytest

from qdnb.qd.cvt import cvt_centroids, grid_centroids, nearest
from qdnb.qd.metrics import ExplorationTrack, grid_cell, qd_metrics
from qdnb.qd.novelty import NoveltyArchive, knn_novelty
from qdnb.qd.repertoire import init_repertoire, insert, sample
from qdnb.qd.variation import gaussian_mutation, isoline_variation

CENTROIDS = jnp.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])


def genotypes(values):
    return {"w": jnp.asarray(values, jnp.float32)[:, None] * jnp.ones((1, 3))}


def test_insertion_into_empty_cells_and_collisions_within_a_batch():
    rep = init_repertoire(CENTROIDS, {"w": jnp.zeros(3)})
    # candidates 0, 1 and 3 fall in cell 0, candidate 2 in cell 2; cell 1 gets nothing
    desc = jnp.array([[0.1, 0.0], [0.0, 0.1], [0.0, 0.9], [-0.1, 0.0]])
    fit = jnp.array([1.0, 3.0, 2.0, 3.0])
    rep, inserted = insert(rep, genotypes([10, 11, 12, 13]), fit, desc)
    np.testing.assert_array_equal(inserted, [False, True, True, False])  # tie: the lower index wins
    np.testing.assert_array_equal(rep.fitnesses, [3.0, -np.inf, 2.0])
    np.testing.assert_array_equal(rep.genotypes["w"][:, 0], [11, 0, 12])
    np.testing.assert_allclose(rep.descriptors[0], [0.0, 0.1])


def test_insertion_keeps_better_incumbents_and_replaces_worse_ones():
    rep = init_repertoire(CENTROIDS, {"w": jnp.zeros(3)})
    rep, _ = insert(
        rep, genotypes([1, 2]), jnp.array([5.0, 5.0]), jnp.array([[0.0, 0.0], [1.0, 0.0]])
    )
    rep, inserted = insert(
        rep,
        genotypes([3, 4, 5]),
        jnp.array([4.0, 5.0, 6.0]),
        jnp.array([[0.0, 0.0], [1.0, 0.1], [0.9, 0.0]]),
    )
    # equal fitness does not replace; cell 1 gets the best candidate (6.0)
    np.testing.assert_array_equal(inserted, [False, False, True])
    np.testing.assert_array_equal(rep.fitnesses, [5.0, 6.0, -np.inf])
    np.testing.assert_array_equal(rep.genotypes["w"][:, 0], [1, 5, 0])


def test_invalid_fitness_is_never_inserted():
    rep = init_repertoire(CENTROIDS, {"w": jnp.zeros(3)})
    rep, inserted = insert(
        rep, genotypes([1, 2]), jnp.array([jnp.nan, -jnp.inf]), jnp.zeros((2, 2))
    )
    assert not inserted.any() and not rep.filled.any()


def test_uniform_selection_only_returns_elites():
    rep = init_repertoire(CENTROIDS, {"w": jnp.zeros(3)})
    rep, _ = insert(
        rep, genotypes([7, 9]), jnp.array([1.0, 2.0]), jnp.array([[0.0, 0.0], [0.0, 1.0]])
    )
    chosen = np.asarray(sample(rep, jax.random.PRNGKey(0), 200)["w"][:, 0])
    assert set(chosen) == {7.0, 9.0}


def test_metrics_on_a_hand_computed_repertoire():
    rep = init_repertoire(CENTROIDS, {"w": jnp.zeros(3)})
    rep, _ = insert(
        rep, genotypes([1, 2]), jnp.array([-1.0, 3.0]), jnp.array([[0.0, 0.0], [1.0, 0.0]])
    )
    m = qd_metrics(rep, fitness_offset=-2.0)
    np.testing.assert_allclose(m["coverage"], 2 / 3)
    np.testing.assert_allclose(m["qd_score"], (-1.0 + 2.0) + (3.0 + 2.0))
    np.testing.assert_allclose(m["max_fitness"], 3.0)


def test_grid_centroids_and_cells():
    c = grid_centroids((2, 3), (0.0, 0.0), (2.0, 3.0))
    np.testing.assert_allclose(c[:4], [[0.5, 0.5], [0.5, 1.5], [0.5, 2.5], [1.5, 0.5]])
    pts = jnp.array([[0.1, 0.1], [1.9, 2.9], [2.0, 3.0], [1.0, 1.0]])
    np.testing.assert_array_equal(grid_cell(pts, (2, 3), (0, 0), (2, 3)), [0, 5, 5, 4])
    np.testing.assert_array_equal(nearest(c, pts[:2]), [0, 5])


def test_cvt_is_deterministic_for_a_seed_and_inside_bounds():
    a = cvt_centroids(
        jax.random.PRNGKey(0), 32, (-1.0, 0.0), (1.0, 2.0), num_samples=2000, num_iterations=10
    )
    b = cvt_centroids(
        jax.random.PRNGKey(0), 32, (-1.0, 0.0), (1.0, 2.0), num_samples=2000, num_iterations=10
    )
    c = cvt_centroids(
        jax.random.PRNGKey(1), 32, (-1.0, 0.0), (1.0, 2.0), num_samples=2000, num_iterations=10
    )
    np.testing.assert_array_equal(a, b)
    assert not np.allclose(a, c)
    assert a.shape == (32, 2)
    assert (
        np.all(a[:, 0] >= -1)
        and np.all(a[:, 0] <= 1)
        and np.all(a[:, 1] >= 0)
        and np.all(a[:, 1] <= 2)
    )
    # Lloyd's iterations spread the centroids: every centroid is used by some samples
    pts = jax.random.uniform(
        jax.random.PRNGKey(5),
        (5000, 2),
        minval=jnp.array([-1.0, 0.0]),
        maxval=jnp.array([1.0, 2.0]),
    )
    assert len(np.unique(nearest(a, pts))) == 32


def test_knn_novelty_hand_computed():
    ref = jnp.array([[0.0, 0.0], [3.0, 0.0], [0.0, 4.0], [10.0, 10.0]])
    q = jnp.array([[0.0, 0.0], [3.0, 4.0]])
    # query 0: distances 0, 3, 4, ... -> k=2 mean (0 + 3) / 2; query 1: 3, 4, 5 -> (3 + 4) / 2
    np.testing.assert_allclose(knn_novelty(q, ref, 2), [1.5, 3.5], rtol=1e-6)
    valid = jnp.array([True, False, True, True])
    np.testing.assert_allclose(
        knn_novelty(q, ref, 2, valid), [2.0, 4.0], rtol=1e-6
    )  # (0+4)/2, (3+5)/2
    # queries are the first rows of the reference: a point is not its own neighbour
    np.testing.assert_allclose(
        knn_novelty(ref[:2], ref, 1, exclude_self=True), [3.0, 3.0], rtol=1e-6
    )
    # fewer valid references than k: mean over those there are; none: infinite
    np.testing.assert_allclose(
        knn_novelty(q[:1], ref, 3, jnp.array([False, True, False, False])), [3.0]
    )
    assert np.isinf(knn_novelty(q[:1], ref, 3, jnp.zeros(4, bool))[0])
    with pytest.raises(ValueError, match="smaller than k"):
        knn_novelty(q, ref, 5)


def test_archive_threshold_and_fifo():
    archive = NoveltyArchive.create(capacity=3, dim=1)
    # sequential: 0 enters (empty archive), 0.05 is too close to 0, 1 and 2 enter
    archive = archive.add(jnp.array([[0.0], [0.05], [1.0], [2.0]]), threshold=0.1, k=1)
    assert int(archive.num_added) == 3 and int(archive.size) == 3
    np.testing.assert_allclose(archive.data[:, 0], [0.0, 1.0, 2.0])
    archive = archive.add(jnp.array([[5.0]]), threshold=0.1, k=1)  # overwrites the oldest slot
    np.testing.assert_allclose(archive.data[:, 0], [5.0, 1.0, 2.0])
    np.testing.assert_allclose(archive.novelty(jnp.array([[1.5]]), k=2), [0.5])


def test_isoline_variation():
    x1 = {"a": jnp.zeros((4, 3)), "b": jnp.zeros((4,))}
    x2 = {"a": jnp.ones((4, 3)), "b": jnp.ones((4,))}
    same = isoline_variation(x1, x2, jax.random.PRNGKey(0), 0.0, 0.0)
    np.testing.assert_array_equal(same["a"], x1["a"])
    line = isoline_variation(x1, x2, jax.random.PRNGKey(0), 0.0, 1.0)
    # pure line variation: every parameter of one offspring moves by the same coefficient
    np.testing.assert_allclose(
        line["a"], np.repeat(np.asarray(line["b"])[:, None], 3, axis=1), rtol=1e-6
    )
    g = gaussian_mutation(x1, jax.random.PRNGKey(1), 0.1)
    assert 0.02 < float(jnp.std(g["a"])) < 0.3


def test_exploration_track():
    t = ExplorationTrack.create(4)
    t = t.update(
        jnp.array([[-0.5, -0.5], [0.5, 0.5], [0.4, 0.6]]), (2, 2), (-1, -1), (1, 1), (0.5, 0.5)
    )
    np.testing.assert_array_equal(t.visited, [True, False, False, True])
    np.testing.assert_allclose(t.coverage, 0.5)
    np.testing.assert_allclose(t.min_distance, 0.0)


def test_generic_map_elites_over_a_scoring_function_keeps_the_best_per_cell():
    """MAP-Elites over plain vectors (no environment, no network): descriptor = x,
    fitness = -|x - 0.3|; each of the 4 cells of [0, 1] ends with the best point
    of all those scored in it."""
    from qdnb.core.evaluation import Evaluation
    from qdnb.qd.map_elites import MapElites

    scored = []

    def score(x, key):
        return Evaluation(
            fitness=-jnp.abs(x[:, 0] - 0.3), descriptor=x, length=jnp.ones(x.shape[0])
        )

    me = MapElites(
        centroids=grid_centroids((4,), (0.0,), (1.0,)),
        batch_size=16,
        scoring_fn=score,
        init_fn=lambda key, n: jax.random.uniform(key, (n, 1)),
        variation_fn=lambda parents, key: jnp.clip(
            parents + 0.1 * jax.random.normal(key, parents.shape), 0, 1
        ),
    )
    state = jax.jit(me.start)(jax.random.PRNGKey(0))
    step = jax.jit(me.step)
    for _ in range(10):
        scored.append(np.asarray(state.offspring[:, 0]))
        state, ev = step(state)
        assert ev.fitness.shape == (16,)
    points = np.concatenate(scored)
    rep = state.repertoire
    cells = np.minimum((points * 4).astype(int), 3)
    for c in range(4):
        if (cells == c).any():
            best = points[cells == c][np.argmax(-np.abs(points[cells == c] - 0.3))]
            assert bool(rep.filled[c]) and np.isclose(float(rep.genotypes[c, 0]), best)
    # init is start then one step, and the metrics are the repertoire's
    s1, _ = me.init(jax.random.PRNGKey(1))
    s2, _ = me.step(me.start(jax.random.PRNGKey(1)))
    assert np.array_equal(s1.repertoire.fitnesses, s2.repertoire.fitnesses)
    assert 0 < float(me.metrics(state)["coverage"]) <= 1
