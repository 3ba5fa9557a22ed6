"""The evolution strategies of Chapter 3's Table 3.3 (qdnb/qd/es.py): the ES core on
hand-made and toy inputs, NSR(A)-ES's score mix and weight rule, ME-ES's
explore/exploit schedule, and every method under ``run_seeds``."""

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from qdnb.envs import make_env
from qdnb.nets.mlp import MLP
from qdnb.qd import repertoire as rep_lib
from qdnb.qd.algorithms import run_seeds
from qdnb.qd.es import (
    MEES,
    NSRAES,
    NSRES,
    OpenAIES,
    antithetic_noise,
    centred_ranks,
    es_gradient,
    es_update,
    mees_schedule,
    mirrored_gradient,
    mirrored_half,
    nsr_scores,
    nsra_adapt,
)

SMALL = dict(num_perturbations=8, noise_table_size=4096)  # a tiny population and table


def _env(episode_length=10):
    return make_env("pointmaze", episode_length=episode_length)


def _net():
    return MLP((8, 2), activation="relu")


def test_centred_ranks_by_hand():
    np.testing.assert_allclose(centred_ranks(jnp.array([3.0, 1.0, 2.0])), [0.5, -0.5, 0.0])
    np.testing.assert_allclose(
        centred_ranks(jnp.array([10.0, -1.0, 4.0, 7.0, 0.0])), [0.5, -0.5, 0.0, 0.25, -0.25]
    )
    with pytest.raises(ValueError, match="at least 2"):
        centred_ranks(jnp.array([1.0]))


def test_antithetic_pairs_fresh_and_from_a_table():
    table = jax.random.normal(jax.random.key(1), (500,))
    for noise in (
        antithetic_noise(jax.random.key(0), 6, 4),
        antithetic_noise(jax.random.key(0), 6, 4, table),
    ):
        assert noise.shape == (6, 4)
        np.testing.assert_array_equal(noise[3:], -noise[:3])  # eps_{i + n/2} = -eps_i
    # table rows are windows of consecutive table entries
    half = np.asarray(mirrored_half(jax.random.key(2), 6, 4, table))
    t = np.asarray(table)
    for row in half:
        starts = [o for o in range(len(t) - 3) if np.array_equal(t[o : o + 4], row)]
        assert starts, "a perturbation is not a window of the table"
    with pytest.raises(ValueError, match="even"):
        antithetic_noise(jax.random.key(0), 5, 4)
    with pytest.raises(ValueError, match="shorter"):
        mirrored_half(jax.random.key(0), 4, 8, table[:5])


def test_es_gradient_matches_the_true_gradient_of_a_quadratic():
    """f(theta) = -||theta - t||^2, grad f = -2 (theta - t).  The antithetic
    estimator with raw scores is unbiased (Gaussian smoothing adds a constant
    to a quadratic): the mean of 20 estimates of n = 1000 perturbations in 20
    dimensions is within 5% of the gradient in norm (cosine > 0.99); with
    centred ranks (Eq. ES-2) the direction is kept (cosine > 0.95)."""
    dim, n, sigma = 20, 1000, 0.1
    theta = jax.random.normal(jax.random.key(0), (dim,))
    target = jax.random.normal(jax.random.key(1), (dim,))
    f = lambda x: -jnp.sum((x - target) ** 2, axis=-1)
    true = -2.0 * (theta - target)

    def estimates(key):
        noise = antithetic_noise(key, n, dim)
        scores = f(theta + sigma * noise)
        raw = es_gradient(noise, scores, sigma)
        pairwise = mirrored_gradient(noise[: n // 2], scores, sigma)
        return raw, pairwise, es_gradient(noise, centred_ranks(scores), sigma)

    raw, pairwise, ranked = jax.vmap(estimates)(jax.random.split(jax.random.key(2), 20))
    np.testing.assert_allclose(pairwise, raw, rtol=1e-4, atol=1e-4)  # the same sum, by pairs
    cos = lambda a, b: float(a @ b / (jnp.linalg.norm(a) * jnp.linalg.norm(b)))
    mean_raw = raw.mean(0)
    assert cos(mean_raw, true) > 0.99
    assert abs(float(jnp.linalg.norm(mean_raw) / jnp.linalg.norm(true)) - 1.0) < 0.05
    assert cos(ranked.mean(0), true) > 0.95


def test_es_update_ascends_a_toy_function_and_decays_weights():
    dim, n, sigma = 10, 100, 0.05
    target = jnp.linspace(-1.0, 1.0, dim)
    f = lambda x: -jnp.sum((x - target) ** 2, axis=-1)
    opt = optax.adam(0.05)

    def generation(carry, key):
        theta, state = carry
        noise = antithetic_noise(key, n, dim)
        g = es_gradient(noise, centred_ranks(f(theta + sigma * noise)), sigma)
        return es_update(opt, theta, state, g, 0.0), None

    theta0 = jnp.zeros(dim)
    (theta, _), _ = jax.lax.scan(
        generation, (theta0, opt.init(theta0)), jax.random.split(jax.random.key(0), 200)
    )
    assert float(f(theta)) > 0.01 * float(f(theta0))  # 100 times closer to the optimum
    # no signal: the L2 decay alone pulls theta towards 0
    theta1 = jnp.ones(dim)
    moved, _ = es_update(opt, theta1, opt.init(theta1), jnp.zeros(dim), 0.005)
    assert bool(jnp.all(moved < theta1))


def test_nsr_score_mix_on_hand_made_ranks():
    fitness = jnp.array([3.0, 1.0, 2.0])  # centred ranks [0.5, -0.5, 0]
    novelty = jnp.array([1.0, 2.0, 3.0])  # centred ranks [-0.5, 0, 0.5]
    np.testing.assert_allclose(nsr_scores(fitness, novelty, 0.5), [0.0, -0.25, 0.25])
    np.testing.assert_allclose(nsr_scores(fitness, novelty, 1.0), [0.5, -0.5, 0.0])
    np.testing.assert_allclose(nsr_scores(fitness, novelty, 0.0), [-0.5, 0.0, 0.5])
    np.testing.assert_allclose(nsr_scores(fitness, novelty, 0.8), [0.3, -0.4, 0.1])


def test_nsra_weight_rule_on_a_hand_made_sequence():
    """Eq. NS-3 with delta = 0.05 and t_max = 3: +delta (capped at 1) on every
    new best, -delta (floored at 0) after 3 generations without one."""
    fitnesses = [1.0, 1.0, 0.5, 1.0, 1.0, 1.0, 0.9, 2.0, 2.0]
    expected = [
        (1.0, 1.0, 0),  # new best, w stays capped at 1
        (1.0, 1.0, 1),
        (1.0, 1.0, 2),
        (0.95, 1.0, 0),  # third generation without improvement
        (0.95, 1.0, 1),
        (0.95, 1.0, 2),
        (0.90, 1.0, 0),
        (0.95, 2.0, 0),  # new best
        (0.95, 2.0, 1),
    ]
    w, best, count = jnp.asarray(1.0), jnp.asarray(-jnp.inf), jnp.asarray(0)
    for f, (w_exp, best_exp, count_exp) in zip(fitnesses, expected):
        w, best, count = nsra_adapt(w, best, count, jnp.asarray(f), 0.05, 3)
        assert (float(w), float(best), int(count)) == pytest.approx((w_exp, best_exp, count_exp))
    # the floor at 0
    w, best, count = nsra_adapt(jnp.asarray(0.02), jnp.asarray(5.0), jnp.asarray(2), 1.0, 0.05, 3)
    assert float(w) == 0.0 and int(count) == 0


def test_mees_schedule_alternates_explore_and_exploit():
    """QDax's MEESEmitter: a new parent every num_optimizer_steps generations;
    explore for num_optimizer_steps generations, then exploit as long."""
    gens = jnp.arange(12)
    new_parent, explore = mees_schedule(gens, 3)
    assert np.asarray(new_parent).tolist() == [g % 3 == 0 for g in range(12)]
    assert np.asarray(explore).tolist() == [True] * 3 + [False] * 3 + [True] * 3 + [False] * 3
    _, explore_only = mees_schedule(gens, 3, use_explore=True, use_exploit=False)
    _, exploit_only = mees_schedule(gens, 3, use_explore=False, use_exploit=True)
    assert bool(jnp.all(explore_only)) and not bool(jnp.any(exploit_only))


def test_mees_parent_choice_explore_and_exploit():
    """QDax's parent sampling on a hand-made grid of 4 cells (3 filled):
    explore takes the filled cell most novel w.r.t. the archive; exploit takes
    the fittest cell, or, on heads of a fair coin, the fittest of the last
    offspring added to the grid (none yet: always the grid)."""
    algo = MEES(
        env=_env(),
        network=_net(),
        bins=2,
        k=2,
        archive_size=16,
        exploit_num_cell_sample=1,
        explore_num_cell_sample=1,
        **SMALL,
    )
    d = algo.num_parameters
    state = algo.start(jax.random.key(0))
    genotypes = jnp.arange(1.0, 4.0)[:, None] * jnp.ones((3, d))  # rows of 1s, 2s, 3s
    descriptors = jnp.array([[-0.5, -0.5], [0.5, -0.5], [-0.5, 0.5]])  # cells 0, 1, 2
    repertoire, _ = rep_lib.insert(
        state.repertoire, genotypes, jnp.array([1.0, 5.0, 3.0]), descriptors
    )
    archive = state.archive.add(jnp.array([[-0.5, -0.4], [0.5, -0.4], [0.0, -0.5]]), -jnp.inf, 2)
    state = state.replace(repertoire=repertoire, archive=archive)
    keys = jax.random.split(jax.random.key(1), 64)
    pick = jax.jit(jax.vmap(algo.sample_parent, in_axes=(None, 0, None)))

    explore, found = pick(state, keys, True)
    assert bool(jnp.all(found)) and bool(jnp.all(explore[:, 0] == 3.0))  # the cell far from A
    exploit, found = pick(state, keys, False)
    assert bool(jnp.all(found)) and bool(jnp.all(exploit[:, 0] == 2.0))  # the fittest cell
    last = state.replace(
        last_genotypes=state.last_genotypes.at[0].set(7.0),
        last_fitnesses=state.last_fitnesses.at[0].set(0.0),
    )
    exploit, _ = pick(last, keys, False)
    assert set(np.unique(exploit[:, 0]).tolist()) == {2.0, 7.0}  # the coin: grid or last added


@pytest.mark.parametrize(
    "cls, extra",
    [
        (OpenAIES, {}),
        (NSRES, dict(meta_population_size=3, k=3, archive_size=16)),
        (NSRAES, dict(meta_population_size=3, k=3, archive_size=16, stagnation=1)),
        (MEES, dict(num_optimizer_steps=3, bins=4, k=3, archive_size=16)),
    ],
)
def test_each_method_runs_under_run_seeds(cls, extra):
    env = _env()
    algo = cls(env=env, network=_net(), **SMALL, **extra)
    states, _, history = run_seeds(
        algo, jax.random.split(jax.random.key(0), 2), num_iterations=3, chunk_size=2, progress=False
    )
    assert history["max_fitness"].shape == (2, 4)
    assert np.all(np.isfinite(history["max_fitness"]))
    # every step plays episodes_per_step episodes, init included
    assert history["fitnesses"].shape == (2, 4, algo.episodes_per_step)
    assert np.all(history["env_steps"] <= algo.episodes_per_step * env.episode_length)
    assert np.all(history["env_steps"] >= algo.episodes_per_step)
    if cls is NSRAES:  # stagnation=1: w leaves 1 as soon as a generation fails to improve
        w = history["reward_weight"]
        assert np.all((w >= 0) & (w <= 1)) and np.any(w < 1)
    if cls is MEES:
        # generations 0-3 ran (init and 3 steps); Adam restarted with the new parent
        # of generation 3 (a new parent every 3 generations): one step since
        assert np.all(states.generation == 4)
        assert np.all(states.opt_state[0].count == 1)
        assert np.all(states.archive.num_added == 4)  # every offspring's descriptor
        assert np.all(history["num_elites"] >= 1)


def test_openai_es_improves_the_return_on_a_short_point_maze():
    env = _env(episode_length=20)
    algo = OpenAIES(
        env=env,
        network=_net(),
        num_perturbations=64,
        sigma=0.05,
        learning_rate=0.05,
        weight_decay=0.0,
        noise_table_size=1 << 16,
    )

    @jax.jit
    def run(key):
        state, first = algo.init(key)
        _, returns = jax.lax.scan(lambda s, _: algo.step(s), state, None, length=15)
        return first.fitness[1:].mean(), returns.fitness[-1, 1:].mean()

    first, last = run(jax.random.key(0))
    # the population's mean return (-30 at the start) gains more than 3 in 15 generations
    assert float(last) > float(first) + 3.0


@pytest.mark.parametrize(
    "cls, kwargs, message",
    [
        (OpenAIES, dict(num_perturbations=7), "even"),
        (OpenAIES, dict(num_perturbations=0), "even"),
        (OpenAIES, dict(sigma=0.0), "sigma"),
        (OpenAIES, dict(learning_rate=-1.0), "learning_rate"),
        (OpenAIES, dict(weight_decay=-0.1), "weight_decay"),
        (OpenAIES, dict(noise_table_size=10), "noise_table_size"),
        (NSRES, dict(meta_population_size=0), "meta_population_size"),
        (NSRES, dict(k=20, archive_size=10), "archive_size"),
        (NSRES, dict(reward_weight=1.5), "reward_weight"),
        (NSRAES, dict(weight_delta=0.0), "weight_delta"),
        (NSRAES, dict(stagnation=0), "stagnation"),
        (MEES, dict(num_optimizer_steps=0), "num_optimizer_steps"),
        (MEES, dict(use_explore=False, use_exploit=False), "use_explore"),
        (MEES, dict(exploit_num_cell_sample=6), "exploit_num_cell_sample"),
        (MEES, dict(bins=2, explore_num_cell_sample=5), "explore_num_cell_sample"),
    ],
)
def test_bad_configurations_raise(cls, kwargs, message):
    with pytest.raises(ValueError, match=message):
        cls(env=_env(), network=_net(), **kwargs)
