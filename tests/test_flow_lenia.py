"""Flow Lenia (Sections 5.2 and 5.3): growth, kernels, mass conservation, the flow of
a uniform field, parameters moving with matter, softmax sampling, the fast
reintegration against the reference and against float64 overlap areas,
determinism and config errors.  Small grids and few kernels keep it fast."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from qdnb.lenia.flow_lenia import (
    FlowLeniaConfig,
    State,
    affinity,
    displacement,
    flow,
    growth,
    initial_state,
    kernel_fields,
    reintegrate,
    reintegrate_reference,
    sample_system,
    simulate_batch,
    step,
)

CFG = FlowLeniaConfig(height=32, width=32, kernels=3, patch_size=12, steps=50)
BATCH = 3


@pytest.fixture(scope="module")
def episodes():
    return simulate_batch(jax.random.PRNGKey(0), CFG, BATCH)


def random_fields(key, cfg, saturate=True):
    """Random matter (a quarter of the cells empty), parameters and displacements in
    [-D, D], some exactly at the bound or zero."""
    ka, kz, kp, kd, ks = jax.random.split(key, 5)
    shape = (cfg.height, cfg.width)
    A = jax.random.uniform(ka, shape + (1,)) * (jax.random.uniform(kz, shape + (1,)) > 0.25)
    P = jax.random.uniform(kp, shape + (cfg.kernels,))
    bound = cfg.max_displacement
    disp = jax.random.uniform(kd, shape + (1, 2), minval=-bound, maxval=bound)
    if saturate:
        choice = jax.random.randint(ks, disp.shape, 0, 6)
        disp = jnp.select([choice == 0, choice == 1, choice == 2], [bound, -bound, 0.0], disp)
    return A, P, disp


def test_growth_on_hand_checked_points():
    mu, sigma = 0.3, 0.05
    assert float(growth(jnp.float32(mu), mu, sigma)) == pytest.approx(1.0)
    assert float(growth(jnp.float32(mu + sigma), mu, sigma)) == pytest.approx(2 * np.exp(-0.5) - 1, abs=1e-6)
    assert float(growth(jnp.float32(mu - 2 * sigma), mu, sigma)) == pytest.approx(2 * np.exp(-2) - 1, abs=1e-6)
    assert float(growth(jnp.float32(1.0), mu, sigma)) == pytest.approx(-1.0, abs=1e-6)
    assert float(growth(jnp.float32(0.0), 0.5, 0.001)) == -1.0


def test_kernels_sum_to_one_and_follow_the_ring_formula():
    height = width = 32
    R, r = jnp.float32(10.0), jnp.array([0.8])
    a, b, w = jnp.array([[0.2, 0.5, 0.8]]), jnp.array([[1.0, 0.3, 0.6]]), jnp.array([[0.1, 0.2, 0.15]])
    K = np.asarray(kernel_fields(R, r, a, b, w, height, width))[..., 0]
    # float64 formula on the torus
    i = np.minimum(np.arange(height), height - np.arange(height))
    dist = np.sqrt(i[:, None] ** 2 + i[None, :] ** 2) / 8.0
    rings = (np.asarray(b[0]) * np.exp(-((dist[..., None] - np.asarray(a[0])) ** 2) / (2 * np.asarray(w[0]) ** 2)))
    expected = np.where(dist <= 1, rings.sum(-1), 0.0)
    np.testing.assert_allclose(K, expected / expected.sum(), rtol=1e-5, atol=1e-9)
    assert K[0, 9] == 0.0 and K[0, 8] > 0  # radius r R = 8
    np.testing.assert_array_equal(K, K.T)

    sample = jax.jit(sample_system, static_argnames="cfg")
    for seed in range(3):
        system = sample(jax.random.PRNGKey(seed), CFG)
        fields = jnp.fft.irfft2(system.kernels_fft, s=(CFG.height, CFG.width), axes=(0, 1))
        np.testing.assert_allclose(np.sum(fields, axis=(0, 1)), 1.0, atol=1e-5)
        assert float(jnp.min(fields)) > -1e-6

    # R r < 1 with rings far from the centre: the kernel is the centre cell alone
    tiny = kernel_fields(jnp.float32(2.0), jnp.array([0.2]), jnp.array([[1.0, 1.0, 1.0]]),
                         jnp.array([[0.5, 0.5, 0.5]]), jnp.array([[0.01, 0.01, 0.01]]), 16, 16)
    assert float(tiny[0, 0, 0]) == 1.0 and float(jnp.sum(tiny)) == 1.0


def test_initial_state_is_a_centred_patch():
    cfg = FlowLeniaConfig(height=33, width=40, kernels=4, patch_size=11)
    state = initial_state(jax.random.PRNGKey(1), cfg)
    assert state.A.shape == (33, 40, 1) and state.P.shape == (33, 40, 4)
    inside = np.zeros((33, 40), bool)
    inside[11:22, 14:25] = True
    A, P = np.asarray(state.A[..., 0]), np.asarray(state.P)
    assert np.all(A[~inside] == 0) and np.all(P[~inside] == 0)
    assert np.all((A[inside] > 0) & (A[inside] < 1)) and np.all((P[inside] >= 0) & (P[inside] < 1))


def test_mass_is_conserved_over_50_steps(episodes):
    _, ep = episodes
    assert ep.A.shape == (BATCH, CFG.steps + 1, CFG.height, CFG.width, 1)
    mass = np.asarray(ep.A, np.float64).sum(axis=(2, 3, 4))
    np.testing.assert_allclose(mass / mass[:, :1], 1.0, rtol=0, atol=1e-5)
    assert np.all(np.asarray(ep.A) >= 0)
    # not vacuous: matter moved
    assert np.all(np.abs(np.asarray(ep.A[:, -1] - ep.A[:, 0])).max(axis=(1, 2, 3)) > 1e-2)


def test_parameters_move_with_matter(episodes):
    _, ep = episodes
    A, P = np.asarray(ep.A[..., 0]), np.asarray(ep.P)
    empty = A == 0
    assert empty.any()
    assert np.all(P[empty] == 0)
    # P only copies vectors: every non-zero vector of the last frame is an initial one
    for b in range(BATCH):
        initial = {row.tobytes() for row in P[b, 0].reshape(-1, CFG.kernels)}
        last = P[b, -1].reshape(-1, CFG.kernels)
        assert all(row.tobytes() in initial for row in last if row.any())


def test_a_uniform_field_stays_still():
    cfg = FlowLeniaConfig(height=32, width=32, kernels=3, patch_size=12)
    system = sample_system(jax.random.PRNGKey(3), cfg)
    h = jnp.array([0.2, 0.7, 0.4])
    state = State(A=jnp.full((32, 32, 1), 0.3), P=jnp.broadcast_to(h, (32, 32, 3)))
    F = flow(affinity(system, state), state.A, cfg)
    assert float(jnp.max(jnp.abs(F))) < 1e-4
    run = jax.jit(step, static_argnames="cfg")
    for i in range(5):
        state = run(system, state, jax.random.PRNGKey(i), cfg)
    np.testing.assert_allclose(state.A, 0.3, atol=1e-6)
    np.testing.assert_array_equal(state.P, np.broadcast_to(h, (32, 32, 3)))


def test_flow_follows_the_affinity_gradient_then_diffuses():
    """Little matter (alpha ~ 0): F = grad U, by Sobel filters (8 x the slope);
    matter above theta_A (alpha = 1): F = -grad A."""
    cols = jnp.arange(32, dtype=jnp.float32)
    wave = jnp.sin(2 * jnp.pi * cols / 32)
    U = jnp.broadcast_to(wave[None, :, None], (32, 32, 1))
    F = flow(U, jnp.zeros((32, 32, 1)), CFG)
    slope = 8 * jnp.sin(2 * jnp.pi / 32) * jnp.cos(2 * jnp.pi * cols / 32)  # central differences x 8
    np.testing.assert_allclose(F[..., 0, 1], jnp.broadcast_to(slope, (32, 32)), atol=1e-5)
    np.testing.assert_allclose(F[..., 0, 0], 0.0, atol=1e-6)
    A = 1.5 + 0.1 * U
    F = flow(U, A, CFG)
    np.testing.assert_allclose(F[..., 0, 1], -0.1 * jnp.broadcast_to(slope, (32, 32)), atol=1e-5)


def test_matter_moves_by_its_displacement():
    """A blob displaced by whole cells (2 down, 1 left) keeps its shape's centre of
    mass exactly 2 rows down and 1 column left (rows are axis 0, columns axis 1)."""
    A = jnp.zeros((32, 32, 1)).at[10:15, 12:20, 0].set(jax.random.uniform(jax.random.PRNGKey(0), (5, 8)))
    P = jnp.zeros((32, 32, 3))
    disp = jnp.broadcast_to(jnp.array([2.0, -1.0]), (32, 32, 1, 2))
    new_a, _ = jax.jit(reintegrate, static_argnames="cfg")(A, P, disp, jax.random.PRNGKey(1), CFG)
    rows, cols = np.meshgrid(np.arange(32), np.arange(32), indexing="ij")

    def centre(a):
        a = np.asarray(a[..., 0], np.float64)
        return np.array([(a * rows).sum(), (a * cols).sum()]) / a.sum()

    np.testing.assert_allclose(centre(new_a) - centre(A), [2.0, -1.0], atol=1e-4)


def test_fast_reintegration_equals_the_reference():
    fast = jax.jit(reintegrate, static_argnames="cfg")
    ref = jax.jit(reintegrate_reference, static_argnames="cfg")
    for seed in range(2):
        A, P, disp = random_fields(jax.random.PRNGKey(seed), CFG)
        key = jax.random.PRNGKey(100 + seed)
        a1, p1 = fast(A, P, disp, key, CFG)
        a2, p2 = ref(A, P, disp, key, CFG)
        np.testing.assert_allclose(a1, a2, atol=1e-5, rtol=0)
        np.testing.assert_array_equal(p1, p2)
        assert float(jnp.sum(a1)) == pytest.approx(float(jnp.sum(A)), rel=1e-6)


def test_reintegration_matches_float64_overlap_areas():
    """Independent check: A'(p) = sum_q A(q) |square(q + disp(q), s) inside cell p| / (2s)^2
    on the torus, in float64, over every pair of cells."""
    cfg = FlowLeniaConfig(height=12, width=13, kernels=2, patch_size=4)
    A, P, disp = random_fields(jax.random.PRNGKey(7), cfg)
    new_a, _ = jax.jit(reintegrate, static_argnames="cfg")(A, P, disp, jax.random.PRNGKey(0), cfg)
    a, d = np.asarray(A[..., 0], np.float64), np.asarray(disp[..., 0, :], np.float64)
    s = cfg.s

    def axis_overlap(p, centre, size):  # (cells p) x (senders) along one axis
        delta = (p[:, None] - centre[None, :] + size / 2) % size - size / 2
        return np.maximum(np.minimum(s, delta + 0.5) - np.maximum(-s, delta - 0.5), 0.0)

    rows, cols = np.meshgrid(np.arange(12), np.arange(13), indexing="ij")
    over_y = axis_overlap(np.arange(12), (rows + d[..., 0]).ravel(), 12)  # (12, senders)
    over_x = axis_overlap(np.arange(13), (cols + d[..., 1]).ravel(), 13)  # (13, senders)
    expected = np.einsum("ys,xs,s->yx", over_y, over_x, a.ravel()) / (2 * s) ** 2
    np.testing.assert_allclose(new_a[..., 0], expected, atol=2e-6)


def test_parameters_are_drawn_with_softmax_probabilities():
    """Two cells send matter m1 and m2 to the cell between them (no flow): it takes
    the first one's parameters with probability exp(m1) / (exp(m1) + exp(m2))."""
    cfg = FlowLeniaConfig(height=12, width=12, kernels=2, patch_size=4)
    A = jnp.zeros((12, 12, 1)).at[5, 5, 0].set(30.0).at[5, 7, 0].set(5.0)
    P = jnp.zeros((12, 12, 2)).at[5, 5].set(1.0).at[5, 7].set(0.5)
    disp = jnp.zeros((12, 12, 1, 2))
    share = (0.15 / 1.3) * (1.0 / 1.3)  # the neighbour's cell covers 0.15 x 1 of the square
    m1, m2 = 30.0 * share, 5.0 * share
    keys = jax.random.split(jax.random.PRNGKey(0), 4000)
    _, new_p = jax.jit(jax.vmap(lambda k: reintegrate(A, P, disp, k, cfg)))(keys)
    got = new_p[:, 5, 6, 0]
    assert set(np.unique(np.asarray(got))) <= {0.5, 1.0}
    expected = np.exp(m1) / (np.exp(m1) + np.exp(m2))  # 0.90 (proportional to matter: 0.86)
    assert float(jnp.mean(got == 1.0)) == pytest.approx(expected, abs=0.02)
    # the senders' own cells each receive only from themselves
    assert np.all(np.asarray(new_p[:, 5, 5, 0]) == 1.0) and np.all(np.asarray(new_p[:, 5, 7, 0]) == 0.5)


def test_displacement_is_bounded_by_reach_minus_s():
    assert CFG.max_displacement == pytest.approx(4.35)
    F = jnp.array([-100.0, -10.0, 0.0, 3.0, 50.0])
    np.testing.assert_allclose(displacement(F, CFG), [-4.35, -2.0, 0.0, 0.6, 4.35], rtol=1e-6)


def test_same_key_same_episode_and_another_key_differs(episodes):
    systems, ep = episodes
    systems2, ep2 = simulate_batch(jax.random.PRNGKey(0), CFG, BATCH)
    for x, y in zip(jax.tree_util.tree_leaves((systems, ep)), jax.tree_util.tree_leaves((systems2, ep2))):
        np.testing.assert_array_equal(x, y)
    _, ep3 = simulate_batch(jax.random.PRNGKey(1), CFG, BATCH)
    assert not np.array_equal(ep.A, ep3.A) and not np.array_equal(ep.P, ep3.P)


@pytest.mark.parametrize(
    "kwargs",
    [
        dict(patch_size=40, height=32, width=32),
        dict(height=0),
        dict(kernels=0),
        dict(steps=-1),
        dict(channels=2),
        dict(height=10, width=10, patch_size=4),  # 2 * reach + 1 = 11 cells do not fit
        dict(s=6.0),  # displacement bound reach - s < 0
        dict(dt=0.0),
        dict(theta_A=-1.0),
        dict(mu_range=(0.5, 0.05)),
        dict(sigma_range=(0.0, 0.2)),
    ],
)
def test_bad_configs_raise(kwargs):
    with pytest.raises(ValueError):
        FlowLeniaConfig(**kwargs)


def test_an_empty_batch_raises():
    with pytest.raises(ValueError):
        simulate_batch(jax.random.PRNGKey(0), CFG, 0)
