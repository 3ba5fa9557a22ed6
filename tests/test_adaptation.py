"""Fast adaptation by Bayesian optimisation over a repertoire (Section 3.7)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from qdnb.qd.adaptation import bayes_opt, gp_posterior, random_goals, random_search, reach_scores

_centres = (np.arange(10, dtype=np.float32) + 0.5) / 10
GRID = np.stack(np.meshgrid(_centres, _centres, indexing="ij"), -1).reshape(
    -1, 2
)  # 10x10 cells of [0, 1]^2
NUM_GOALS = 20
# One compiled batched search, shared by the tests (compilation dominates their time).
run_many = jax.jit(jax.vmap(bayes_opt, in_axes=(None, None, 0, 0)))


def _toy_scores(goals: np.ndarray) -> np.ndarray:
    """Score = -distance between descriptor and goal: smooth, best at the nearest cell."""
    return -np.linalg.norm(GRID[None] - goals[:, None], axis=-1)


@pytest.fixture(scope="module")
def toy():
    goals = np.random.default_rng(0).uniform(0.0, 1.0, (NUM_GOALS, 2)).astype(np.float32)
    keys = jax.random.split(jax.random.key(1), NUM_GOALS)
    return _toy_scores(goals), keys


# --- Gaussian process -------------------------------------------------------

X = jnp.array([[0.0, 0.0], [0.3, 0.1], [0.6, 0.5], [0.2, 0.9]])
Y = jnp.array([1.0, -2.0, 0.5, 3.0])


def test_gp_interpolates_training_points():
    mean, std = gp_posterior(X, Y, jnp.ones(4, bool), X, length_scale=0.2, noise=1e-6)
    np.testing.assert_allclose(mean, Y, atol=1e-3)
    np.testing.assert_allclose(std, 0.0, atol=2e-2)


def test_gp_returns_to_prior_far_away():
    far = jnp.array([[10.0, 10.0], [-7.0, 3.0]])
    mean, std = gp_posterior(X, Y, jnp.ones(4, bool), far, length_scale=0.2)
    np.testing.assert_allclose(mean, float(jnp.mean(Y)), rtol=1e-5)
    np.testing.assert_allclose(std, float(jnp.std(Y)), rtol=1e-5)
    # no observation at all: the standardised prior (0, 1)
    mean0, std0 = gp_posterior(X, Y, jnp.zeros(4, bool), X, length_scale=0.2)
    np.testing.assert_allclose(mean0, 0.0, atol=1e-7)
    np.testing.assert_allclose(std0, 1.0, atol=1e-7)


def test_gp_matches_float64_reference():
    query = jnp.array([[0.1, 0.1], [0.4, 0.4], [0.5, 0.8]])
    ls, noise = 0.3, 1e-3
    mean, std = gp_posterior(X, Y, jnp.ones(4, bool), query, length_scale=ls, noise=noise)
    x, y, q = np.asarray(X, np.float64), np.asarray(Y, np.float64), np.asarray(query, np.float64)
    kern = lambda a, b: np.exp(-0.5 * ((a[:, None] - b[None]) ** 2).sum(-1) / ls**2)
    mu, sd = y.mean(), y.std()
    k_inv = np.linalg.inv(kern(x, x) + noise * np.eye(4))
    ks = kern(q, x)
    ref_mean = mu + sd * ks @ k_inv @ ((y - mu) / sd)
    ref_std = sd * np.sqrt(1.0 - np.einsum("ij,jk,ik->i", ks, k_inv, ks))
    np.testing.assert_allclose(mean, ref_mean, rtol=1e-4, atol=1e-4)
    np.testing.assert_allclose(std, ref_std, rtol=1e-3, atol=1e-4)


def test_gp_masked_slots_have_no_influence():
    query = jnp.array([[0.1, 0.1], [0.4, 0.4], [0.5, 0.8], [3.0, 3.0]])
    ref = gp_posterior(X[:3], Y[:3], jnp.ones(3, bool), query)
    # the same three observations padded with junk slots (even nan) that are masked out
    x_pad = jnp.concatenate([X[:3], jnp.array([[0.4, 0.4], [jnp.nan, 0.0]])])
    y_pad = jnp.concatenate([Y[:3], jnp.array([100.0, jnp.inf])])
    mask = jnp.array([True, True, True, False, False])
    got = gp_posterior(x_pad, y_pad, mask, query)
    for a, b in zip(got, ref):
        assert np.all(np.isfinite(a))
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6)
    # and unmasking the junk slot at (0.4, 0.4) does change the prediction there
    moved = gp_posterior(x_pad[:4], y_pad[:4], jnp.ones(4, bool), query)
    assert abs(float(moved[0][1] - ref[0][1])) > 1.0


# --- Bayesian optimisation --------------------------------------------------


def test_bo_finds_planted_best_and_beats_random_search(toy):
    scores, keys = toy
    valid = np.ones(100, bool)
    bo = run_many(GRID, valid, scores, keys)  # budget 20
    rs = jax.vmap(random_search, in_axes=(None, 0, 0))(valid, scores, keys)
    bo, rs = jax.tree.map(np.asarray, (bo, rs))
    exact = scores.max(axis=1)
    found = bo["best_score"] == exact
    assert found.mean() >= 0.9
    assert np.all(bo["best_index"][found] == scores.argmax(axis=1)[found])
    bo_regret = np.mean(exact - bo["best_score"])
    rs_regret = np.mean(exact - rs["best_score"])
    assert bo_regret < 0.5 * rs_regret
    assert np.mean(rs["best_score"] == exact) < found.mean()


def test_bo_query_invariants(toy):
    scores, keys = toy
    valid = np.random.default_rng(2).uniform(size=100) < 0.6  # a partly filled grid
    n_valid = int(valid.sum())
    out = jax.tree.map(np.asarray, run_many(GRID, valid, scores, keys))  # budget 20
    for g in range(NUM_GOALS):
        queried = out["queried"][g]
        assert len(set(queried.tolist())) == 20  # never twice
        assert np.all(valid[queried])  # never an empty cell
        np.testing.assert_array_equal(out["observed"][g], scores[g][queried])
        best_so_far = out["best_so_far"][g]
        assert np.all(np.diff(best_so_far) >= 0)
        np.testing.assert_array_equal(best_so_far, np.maximum.accumulate(out["observed"][g]))
        assert out["best_score"][g] == best_so_far[-1] == scores[g][out["best_index"][g]]
    assert np.all(out["num_evaluations"] == 20)
    # the first query is uniformly random among valid cells: several keys, several starts
    assert len(set(out["queried"][:, 0].tolist())) > 5
    assert n_valid > 20


def test_bo_budget_covering_all_valid_solutions_gives_exact_max(toy):
    scores, keys = toy
    valid = np.arange(100) % 7 != 0  # 85 valid
    out = jax.tree.map(np.asarray, bayes_opt(GRID, valid, scores[0], keys[0], budget=100))
    n_valid = int(valid.sum())
    queried = out["queried"]
    assert sorted(queried[:n_valid].tolist()) == np.flatnonzero(valid).tolist()
    assert np.all(queried[n_valid:] == -1) and np.all(np.isneginf(out["observed"][n_valid:]))
    assert out["num_evaluations"] == n_valid
    assert out["best_score"] == scores[0][valid].max()
    # a budget above the number of cells is fine too
    small = bayes_opt(GRID[:5], np.ones(5, bool), scores[0][:5], keys[0], budget=8)
    assert float(small["best_score"]) == scores[0][:5].max()
    assert int(small["num_evaluations"]) == 5


def test_only_queried_scores_matter(toy):
    scores, keys = toy
    valid = np.ones(100, bool)
    out = bayes_opt(GRID, valid, scores[3], keys[3])
    unseen = np.ones(100, bool)
    unseen[np.asarray(out["queried"])] = False
    noise = np.random.default_rng(4).normal(size=100).astype(np.float32) * 10.0
    altered = np.where(unseen, scores[3] + noise, scores[3])
    assert unseen.sum() == 80 and not np.allclose(altered, scores[3])
    again = bayes_opt(GRID, valid, altered, keys[3])
    for name in out:
        np.testing.assert_array_equal(again[name], out[name])


def test_determinism_and_vmap_over_goals_matches_loop(toy):
    scores, keys = toy
    valid = np.ones(100, bool)
    a = bayes_opt(GRID, valid, scores[0], keys[0])
    b = bayes_opt(GRID, valid, scores[0], keys[0])
    for name in a:
        np.testing.assert_array_equal(a[name], b[name])
    # many goals at once (one key), and many keys at once (one goal), against a loop
    same_key = jnp.broadcast_to(keys[0], keys.shape)
    same_goal = np.broadcast_to(scores[0], scores.shape)
    per_goal = jax.tree.map(np.asarray, run_many(GRID, valid, scores, same_key))
    per_key = jax.tree.map(np.asarray, run_many(GRID, valid, same_goal, keys))
    for g in range(5):
        one = bayes_opt(GRID, valid, scores[g], keys[0])
        for name in one:
            np.testing.assert_array_equal(per_goal[name][g], one[name])
        one_key = bayes_opt(GRID, valid, scores[0], keys[g])
        np.testing.assert_array_equal(per_key["queried"][g], one_key["queried"])
    assert len({tuple(np.asarray(q).tolist()) for q in per_goal["queried"][:5]}) > 1


# --- helpers ----------------------------------------------------------------


def test_reach_scores_and_random_goals():
    positions = jnp.array(
        [[[0.0, 0.0], [1.0, 0.0], [2.0, 0.0]], [[0.0, 5.0], [0.0, 4.0], [0.0, 3.0]]]
    )
    np.testing.assert_allclose(
        reach_scores(positions, jnp.array([1.0, 1.0])), [-1.0, -np.sqrt(5.0)], rtol=1e-6
    )
    goals = random_goals(jax.random.key(5), 500, [-5.0, 0.0], [5.0, 40.0])
    assert goals.shape == (500, 2)
    assert float(goals[:, 0].min()) >= -5.0 and float(goals[:, 0].max()) <= 5.0
    assert float(goals[:, 1].min()) >= 0.0 and float(goals[:, 1].max()) <= 40.0
    assert float(goals[:, 1].std()) > 5.0
