"""Numerical health (``qdnb.core.health``): a seed that goes NaN is found, named by
iteration and part, stops the loop once all have, and is left out of Chapter 3's means
and claims; QD-PG records its updates' statistics."""

from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from qdnb.chapters.ch3_qdpg import beats, per_seed
from qdnb.core import health
from qdnb.core.evaluation import Evaluation
from qdnb.core.names import mean_sd
from qdnb.envs import make_env
from qdnb.qd.algorithms import run_seeds


@struct.dataclass
class Toy:
    weights: jax.Array  # becomes NaN at the iteration `blow_at`
    count: jax.Array
    blow_at: jax.Array
    grid: jax.Array  # -inf entries, as an empty grid has: not a divergence


@dataclass(frozen=True, eq=False)
class Blows:
    """A loop whose weights turn NaN at a per-seed iteration (never, with ``blow_at < 0``)."""

    env: object
    start = None
    split = "seeds"

    def init(self, key):
        blow_at = jnp.where(jax.random.bits(key) % 2 == 0, 3, -1)
        state = Toy(jnp.ones(2), jnp.zeros((), jnp.int32), blow_at, jnp.full(4, -jnp.inf))
        return state, self.evaluation()

    def evaluation(self):
        return Evaluation(jnp.zeros(1), jnp.zeros((1, 2)), jnp.ones(1, jnp.int32))

    def step(self, state):
        count = state.count + 1
        weights = jnp.where(count == state.blow_at, jnp.nan, state.weights + 1.0)
        return state.replace(weights=weights, count=count), self.evaluation()

    def metrics(self, state):
        return {"weight": state.weights[0]}


def test_nan_parts_names_the_parts_holding_a_nan_not_an_infinity():
    state = Toy(
        jnp.array([1.0, jnp.nan]), jnp.zeros((), jnp.int32), jnp.zeros(()), -jnp.inf * jnp.ones(3)
    )
    assert health.part_names(state) == ("weights", "count", "blow_at", "grid")
    np.testing.assert_array_equal(health.nan_parts(state), [True, False, False, False])
    flags = np.zeros((2, 5, 4), bool)
    flags[1, 3, 0] = flags[1, 4, 0] = flags[1, 4, 3] = True
    div = health.divergences(flags, health.part_names(state))
    assert div[0] is None
    assert div[1] == health.Divergence(3, ("weights",))
    assert div[1].text() == "NaN at iteration 3 in weights"


def test_a_seed_that_goes_nan_is_recorded_and_the_loop_stops_when_all_have(capsys):
    algo = Blows(make_env("pointmaze", episode_length=5))
    keys = jax.random.split(jax.random.PRNGKey(0), 6)
    blows = [bool(jax.random.bits(k) % 2 == 0) for k in keys]
    assert any(blows) and not all(blows)  # both kinds among these seeds
    _, _, history = run_seeds(algo, keys, 12, 4, progress=False)
    assert history["weight"].shape[1] == 13  # some seeds stayed finite: the loop went on
    div = health.divergences(history["nan_parts"], ("weights", "count", "blow_at", "grid"))
    for seed, (d, b) in enumerate(zip(div, blows)):
        assert (d is not None) == b
        if b:
            assert d == health.Divergence(3, ("weights",))
    err = capsys.readouterr().err
    assert err.count("diverged:") == sum(blows) and "went NaN at iteration 3 (weights)" in err
    # every seed blows: the loop stops after the chunk in which the last one did
    only = keys[np.array(blows)]
    _, _, history = run_seeds(algo, only, 40, 4, progress=False)
    assert history["weight"].shape[1] == 5  # the initial batch and the first chunk of 4


def test_diverged_seeds_are_in_no_mean_and_fail_most_seeds():
    qdpg = np.array([-30.0, np.nan, -40.0, np.nan])
    td3 = np.array([-120.0, -130.0])
    # the mean over the finite seeds beats TD3, but only 2 of 4 seeds do: not "most"
    assert not beats(qdpg, td3)
    assert beats(np.array([-30.0, -40.0, np.nan]), td3)  # 2 of 3
    assert per_seed(qdpg) == "-35.0 (seeds: -30.0, diverged, -40.0, diverged)"
    assert mean_sd(qdpg) == "-35.0 ± 5.0 (2 seeds), 2 diverged"
    assert mean_sd(np.array([np.nan, np.nan])) == "diverged"
