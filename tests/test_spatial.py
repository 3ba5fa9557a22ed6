"""The spatial index behind QD-PG's novelty rewards (``qdnb.qd.spatial``): exact k nearest
neighbours, checked against brute force on the cases that break grids."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from qdnb.qd import spatial
from qdnb.qd.novelty import NoveltyArchive, reduce_columns
from qdnb.qd.spatial import GridIndex, k_smallest_columns

K = 10


def exact_k_nearest(queries, reference, valid, k=K):
    """Sorted squared distances to every valid reference, in float64."""
    q = np.asarray(queries, np.float64)
    r = np.asarray(reference, np.float64)[np.asarray(valid)]
    d = ((q[:, None, :] - r[None]) ** 2).sum(-1)
    d = np.sort(d, axis=1)[:, :k]
    return np.pad(d, ((0, 0), (0, k - d.shape[1])), constant_values=np.inf)


ROWS, QUERIES = 5_000, 800  # every case padded to these: one compilation for all


@jax.jit
def kth_and_mean(reference, valid, queries):
    """The index's k-th nearest squared distance, and its novelty (the mean distance)."""
    index = GridIndex.build(reference, valid)
    kth = index.novelty(queries, K, lambda best: best[-1], chunk=128)
    mean = index.novelty(queries, K, lambda best: reduce_columns(best, "mean"), chunk=128)
    return kth, mean


def check(reference, queries, valid=None):
    m, n = len(reference), len(queries)
    valid = np.ones(m, bool) if valid is None else np.asarray(valid)
    # the padding rows are invalid entries at the origin, and queries whose answers are dropped
    reference = jnp.zeros((ROWS, 2)).at[:m].set(jnp.asarray(reference, jnp.float32))
    valid = jnp.zeros(ROWS, bool).at[:m].set(valid)
    padded = jnp.zeros((QUERIES, 2)).at[:n].set(jnp.asarray(queries, jnp.float32))
    kth, mean = (np.asarray(a)[:n] for a in kth_and_mean(reference, valid, padded))
    want = exact_k_nearest(padded[:n], reference, valid)
    np.testing.assert_allclose(kth, want[:, -1], rtol=1e-5, atol=1e-12)
    distances = np.where(np.isfinite(want), np.sqrt(want), 0.0)
    count = np.isfinite(want).sum(1)
    want_mean = np.where(count > 0, distances.sum(1) / np.maximum(count, 1), np.inf)
    np.testing.assert_allclose(mean, want_mean, rtol=1e-5, atol=1e-7)


def test_the_insertion_network_keeps_the_k_smallest_with_their_ties():
    values = jnp.asarray(np.random.default_rng(0).integers(0, 6, (40, 300)), jnp.float32)
    want = -jax.lax.top_k(-values.T, K)[0]
    np.testing.assert_array_equal(jnp.stack(k_smallest_columns(values, K), 1), want)


def test_random_archives_match_brute_force():
    rng = np.random.default_rng(1)
    for m in (1, 9, 10, 37, 4_000):
        check(rng.normal(size=(m, 2)), rng.normal(size=(300, 2)) * 1.5)


def test_points_on_cell_edges_and_exact_duplicates():
    # a lattice whose points sit on the edges of many levels' cells, each point 3 times
    axis = np.linspace(-1.0, 1.0, 17)
    lattice = np.stack(np.meshgrid(axis, axis), -1).reshape(-1, 2)
    reference = np.concatenate([lattice] * 3)
    more = np.random.default_rng(2).uniform(-1, 1, (200, 2))
    queries = np.concatenate([lattice, lattice + 1e-3, more])
    check(reference, queries)


def test_walls_and_piles_beyond_every_window():
    # states crowded on lines (a wall, an arena edge) and a pile of 300 copies of one state
    # (more than any window holds): the refused queries go to the second try, then brute force
    rng = np.random.default_rng(3)
    wall = np.stack([rng.uniform(-1, 1, 2_500), np.full(2_500, 0.2)], -1)
    edge = np.stack([np.full(1_000, -1.0), rng.uniform(-1, 1, 1_000)], -1)
    pile = np.tile([[0.5, -0.5]], (300, 1))
    spread = rng.uniform(-1, 1, (500, 2))
    reference = np.concatenate([wall, edge, pile, spread])
    queries = np.concatenate([wall[:200], edge[:100], pile[:50], spread[:100] + 0.01])
    assert len(reference) <= ROWS
    assert len(pile) > spatial.WIDTHS[-1]
    check(reference, queries)


def test_invalid_entries_are_never_neighbours_and_an_empty_archive_gives_inf():
    rng = np.random.default_rng(4)
    reference = rng.normal(size=(500, 2))
    valid = np.arange(500) < 120  # an archive not yet full: the rest are zeros or stale
    reference[~valid] = 0.0
    check(reference, rng.normal(size=(100, 2)), valid)
    check(reference, rng.normal(size=(50, 2)), np.arange(500) < 4)  # fewer than k valid
    check(reference, rng.normal(size=(5, 2)), np.zeros(500, bool))  # empty: every distance inf


@pytest.mark.parametrize("reduction", ["mean", "sum", "mean_squared"])
def test_archive_novelty_is_the_same_by_index_and_by_brute_force(reduction):
    rng = np.random.default_rng(5)
    data = np.concatenate([rng.uniform(-1, 1, (6_000, 2)), np.tile([[0.0, 0.2]], (60, 1))])
    archive = NoveltyArchive.create(10_000, 2).replace(
        data=jnp.zeros((10_000, 2)).at[: len(data)].set(data),
        num_added=jnp.asarray(len(data), jnp.int32),
    )
    queries = jnp.asarray(rng.uniform(-1, 1, (3, 700, 2)), jnp.float32)  # any leading axes
    by_index = archive.novelty(queries, K, reduction=reduction, search="index")
    brute = archive.novelty(queries, K, reduction=reduction, search="brute")
    assert by_index.shape == (3, 700)
    np.testing.assert_allclose(by_index, brute, rtol=1e-6)
    with pytest.raises(ValueError, match="unknown search"):
        archive.novelty(queries, K, search="kd-tree")
