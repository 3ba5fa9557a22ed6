import jax
import jax.numpy as jnp
import numpy as np
import pytest

from qdnb.core.loops import scan_in_chunks


def test_chunked_scan_equals_one_scan():
    step = lambda c: (c * 1.5 + 1.0, c)
    carry, outs = scan_in_chunks(step, jnp.float32(0.0), 7, 3, progress=False)
    expected, c = [], 0.0
    for _ in range(7):
        expected.append(c)
        c = c * 1.5 + 1.0
    np.testing.assert_allclose(outs, expected, rtol=1e-6)
    np.testing.assert_allclose(carry, c, rtol=1e-6)
    seconds = []
    scan_in_chunks(step, jnp.float32(0.0), 7, 3, progress=False, chunk_seconds=seconds)
    assert len(seconds) == 3 and all(s > 0 for s in seconds)  # chunks of 3, 3 and 1 steps


def test_bad_lengths_are_errors():
    with pytest.raises(ValueError, match="positive"):
        scan_in_chunks(lambda c: (c, c), 0.0, 0, 3)


def test_a_map_elites_run_compiles_its_simulation_once(caplog):
    """The initial evaluation is the loop's first step: the whole run traces the
    environment's step once and compiles one loop program, also when the chunk
    size does not divide the number of iterations."""
    import logging
    from dataclasses import dataclass

    import jax

    from qdnb.envs.pointmaze import PointMaze
    from qdnb.nets.mlp import MLP
    from qdnb.qd.algorithms import PolicyMapElites, run_seeds
    from qdnb.qd.cvt import grid_centroids
    from qdnb.qd.pga import PGAMapElites
    from qdnb.rl.td3 import TD3Config

    traces = []

    @dataclass(frozen=True)
    class CountingMaze(PointMaze):
        def step(self, state, action):
            traces.append(1)
            return super().step(state, action)

    env = CountingMaze(episode_length=20)
    common = dict(
        env=env,
        network=MLP((4, 2)),
        batch_size=8,
        iso_sigma=0.1,
        line_sigma=0.2,
        centroids=grid_centroids((4, 4), (-1, -1), (1, 1)),
    )
    keys = jax.random.split(jax.random.PRNGKey(0), 2)
    for algo in (
        PolicyMapElites(**common),
        PGAMapElites(
            **common,
            td3_config=TD3Config(batch_size=8, critic_hidden=(8,)),
            num_critic_steps=2,
            num_pg_steps=2,
            buffer_size=2000,
        ),
    ):
        traces.clear()
        states, _, history = run_seeds(algo, keys, 4, 5, progress=False)  # 5 evaluations, one chunk
        assert len(traces) == 1, type(algo).__name__
        assert history["coverage"].shape == (2, 5)
        assert np.all(
            np.asarray(history["env_steps"]) == 8 * 20
        )  # the first step is the initial batch

    caplog.set_level(logging.WARNING)
    with jax.log_compiles():
        run_seeds(
            PolicyMapElites(**common), keys, 6, 4, progress=False
        )  # 7 evaluations in chunks of 4: 4 + 3
    compiled = [
        r.getMessage() for r in caplog.records if r.getMessage().startswith("Compiling jit(")
    ]
    loops = [m for m in compiled if m.startswith(("Compiling jit(chunk)", "Compiling jit(masked)"))]
    assert len(loops) == 1, compiled
    assert not any(m.startswith("Compiling jit(init") for m in compiled)


def test_a_remainder_chunk_gives_the_same_numbers_as_one_scan():
    step = lambda c: (c * 1.5 + 1.0, {"c": c, "i": jnp.int32(1)})
    carry, outs = scan_in_chunks(step, jnp.float32(0.0), 7, 5, progress=False)  # 5 + 2, one program
    whole, outs_whole = scan_in_chunks(step, jnp.float32(0.0), 7, 7, progress=False)
    np.testing.assert_array_equal(outs["c"], outs_whole["c"])
    assert outs["i"].shape == (7,)
    np.testing.assert_array_equal(carry, whole)


def test_a_stop_rule_ends_the_loop_after_the_chunk_where_it_holds():
    step = lambda c: (c + 1, c)
    seen = []

    def stop(outs):  # sees each chunk's outputs in order
        seen.append(np.asarray(outs).tolist())
        return bool(np.any(np.asarray(outs) >= 4))

    carry, outs = scan_in_chunks(step, jnp.int32(0), 20, 3, progress=False, stop=stop)
    assert seen == [[0, 1, 2], [3, 4, 5]]  # 4 is in the second chunk: the loop stops there
    np.testing.assert_array_equal(outs, np.arange(6))
    assert int(carry) == 6
    never = lambda outs: False
    carry, outs = scan_in_chunks(step, jnp.int32(0), 7, 3, progress=False, stop=never)
    assert outs.shape == (7,) and int(carry) == 7  # the whole budget, the last chunk masked


def test_map_concurrently_keeps_names_order_and_results_and_raises():
    from qdnb.core.loops import map_concurrently

    f = lambda name: float(jnp.sum(jax.random.normal(jax.random.PRNGKey(len(name)), (100,))))
    names = ("ant_omni", "halfcheetah_uni", "pointmaze")
    together, apart = map_concurrently(f, names), map_concurrently(f, names, concurrent=False)
    assert list(together) == list(names) and together == apart

    def boom(name):
        raise ValueError(f"bad {name}")

    with pytest.raises(ValueError, match="bad "):
        map_concurrently(boom, names)
