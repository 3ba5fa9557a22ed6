import jax
import numpy as np

from qdnb.envs import make_env
from qdnb.nets.mlp import MLP
from qdnb.qd.algorithms import GeneticAlgorithm, NoveltySearch, PolicyMapElites, run_seeds
from qdnb.qd.cvt import grid_centroids


def _algorithms():
    env = make_env("pointmaze", episode_length=30)
    common = dict(env=env, network=MLP((4, 2)), batch_size=8, iso_sigma=0.1, line_sigma=0.2)
    return {
        "GA": GeneticAlgorithm(**common, population_size=4),
        "NS": NoveltySearch(**common, population_size=8, k=3, archive_size=32),
        "ME": PolicyMapElites(
            **common, centroids=grid_centroids((4, 4), (-1, -1), (1, 1)), fitness_offset=-100.0
        ),
    }


def test_same_seed_same_numbers_and_other_seed_other_numbers():
    keys = jax.numpy.stack([jax.random.PRNGKey(0), jax.random.PRNGKey(1)])
    for name, algo in _algorithms().items():
        first, second = (
            run_seeds(algo, keys, 4, 4, (4, 4), (-0.5, 0.8), progress=False)[2] for _ in range(2)
        )
        for key in ("descriptors", "fitnesses", "coverage", "min_distance"):
            np.testing.assert_array_equal(first[key], second[key], err_msg=f"{name} {key}")
        assert not np.array_equal(first["descriptors"][0], first["descriptors"][1]), name
        assert first["descriptors"].shape == (2, 5, 8, 2)
        # the exploration metrics never go backwards
        assert np.all(np.diff(first["coverage"], axis=1) >= 0)
        assert np.all(np.diff(first["min_distance"], axis=1) <= 0)


def test_map_elites_repertoire_only_improves():
    algo = _algorithms()["ME"]
    history = run_seeds(
        algo, jax.random.split(jax.random.PRNGKey(0), 1), 8, 4, (4, 4), (-0.5, 0.8), progress=False
    )[2]
    assert np.all(np.diff(history["qd_score"], axis=1) >= 0)
    assert np.all(np.diff(history["max_fitness"], axis=1) >= 0)
