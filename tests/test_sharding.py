"""Every local device: a loop of each kind (``bench/probes/devices_probe.py``: the GA, Novelty
Search, MAP-Elites and PGA-ME on Point-Maze, a Brax MAP-Elites loop, QD-PG, ME-ES, the FLT's
and the QDT's training steps) on 1 device and, twice, on 2 (CPU devices forced by
``XLA_FLAGS``, each run in its own process; the second 2-device run loads the programs the
first compiled, from a compilation cache of the test's own).

- Same seed, same numbers at a device count: the two 2-device runs agree bit for bit.
- Across counts, bit for bit where each device computes its share as one device computes
  it: the primer's loops and PGA-ME (the seeds split), the Brax loop at `tiny` (its
  population split; at `small`, with three seeds, ME-LS's is not: bench/scale_out.py).
- Across counts, to a stated tolerance where the program differs: the QDT's loss and
  gradients (a split sum); QD-PG and ME-ES, whose seeds split over the devices run a
  one-seed program per device (QD-PG's three seeds padded to four): their initial batch
  is identical, later iterations follow a slightly different rounding that RL and ES
  amplify (the book says which counts give identical numbers).
- The FLT trains on Flow Lenia episodes simulated in its training program: a batch split
  over the devices rounds differently from step 1 (3.6e-7 at `tiny`) and the dynamics
  amplify it to order one by step 50, so only the first step is compared.
"""

import os
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np

from qdnb.core import sharding
from qdnb.core.paths import ROOT

LEARNING_RATE = 1e-3  # the probe's QDT step


def probe(tmp_path, runs: dict[str, int], cache) -> list[dict]:
    """Run ``bench/probes/devices_probe.py`` once per entry of ``runs`` (its name: its
    device count), side by side, their compiled programs kept in (and read from) the
    folder ``cache``; the results in ``runs``' order."""
    procs = []
    for name, n in runs.items():
        env = dict(os.environ, JAX_PLATFORMS="cpu", JAX_COMPILATION_CACHE_DIR=str(cache))
        env["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"] = "0"
        env["XLA_FLAGS"] = sharding.with_device_count(env.get("XLA_FLAGS", ""), n)
        env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(ROOT), env.get("PYTHONPATH")]))
        out = tmp_path / f"{name}.npz"
        cmd = [sys.executable, str(ROOT / "bench" / "probes" / "devices_probe.py"), str(out)]
        procs.append((subprocess.Popen(cmd, env=env, stderr=subprocess.PIPE, text=True), out))
    results = []
    for proc, out in procs:
        _, err = proc.communicate(timeout=1200)
        assert proc.returncode == 0, err[-2000:]
        results.append(dict(np.load(out)))
    return results


def test_same_numbers_at_a_device_count_and_across_counts(tmp_path):
    # one device and two side by side; then two again, from the programs the first two-device
    # run compiled (its own process: the same executables run again, not recompiled, which
    # took a third of this test's time)
    cache = tmp_path / "xla"
    one, two = probe(tmp_path, {"one": 1, "two": 2}, cache)
    (again,) = probe(tmp_path, {"again": 2}, cache)
    assert [int(r.pop("devices")) for r in (one, two, again)] == [1, 2, 2]
    assert one.keys() == two.keys() == again.keys()
    for key in two:  # the same seed on the same machine: the same numbers
        np.testing.assert_array_equal(two[key], again[key], err_msg=key)
    for key in one:
        if key.startswith(
            ("GA/", "NS/", "ME/", "PGA-ME/", "ME-brax/")
        ):  # the same computation per policy
            np.testing.assert_array_equal(one[key], two[key], err_msg=key)
        elif key.startswith(("QD-PG/", "QD-PG-3-seeds/", "ME-ES/")):  # first batch the same
            np.testing.assert_array_equal(one[key][:, 0], two[key][:, 0], err_msg=key)
            np.testing.assert_allclose(one[key], two[key], rtol=0.05, atol=0.05, err_msg=key)
        elif key.startswith(("QDT/loss", "QDT/step_loss", "QDT/grad")):  # a split sum
            np.testing.assert_allclose(one[key], two[key], rtol=1e-4, atol=1e-7, err_msg=key)
        elif key == "FLT/mean_frames":  # the first step to rounding; then Flow Lenia's chaos
            np.testing.assert_allclose(one[key][:2], two[key][:2], atol=1e-5, err_msg=key)
        elif key == "FLT/losses":
            assert np.all(np.isfinite(two[key])) and one[key].shape == two[key].shape
        else:  # one Adam step: lr * g / |g| moves a near-zero gradient by up to lr either way
            np.testing.assert_allclose(one[key], two[key], atol=2 * LEARNING_RATE, err_msg=key)


def test_one_device_is_left_untouched(monkeypatch):
    monkeypatch.setattr(sharding, "mesh", lambda: None)
    tree = {"a": jnp.ones((4, 2)), "b": 3.0}
    assert sharding.shard_batch(tree) is tree
    fn = lambda x: x
    assert sharding.over_seeds(fn, 2) is fn


def test_matmul_bound_training_stays_whole_on_cpu_host_devices():
    tree = {"a": jnp.ones((4, 2))}
    if jax.device_count() > 1:  # CPU host devices: the QDT's minibatch is not split
        assert sharding.shard_batch(tree, dense=True) is tree
        split = jax.jit(sharding.shard_batch)(tree)
        assert split["a"].devices() == set(jax.devices())


def test_episodes_read_outside_jit_come_back_whole_on_every_device(monkeypatch):
    """Flow Lenia's episodes are simulated split over the devices and returned replicated
    (eager code scoring split episodes deadlocked XLA:CPU's collectives); a jitted caller
    that keeps them split (the FLT's training step) asks for ``split=True``."""
    from qdnb.models.lenia import flow_lenia as fl

    world = fl.FlowLeniaConfig(height=16, width=16, kernels=2, steps=3, patch_size=4)
    system = fl.sample_system(jax.random.PRNGKey(0), world)
    whole = fl.simulate_system(system, jax.random.PRNGKey(1), world, 4)
    split = fl.simulate_system(system, jax.random.PRNGKey(1), world, 4, split=True)
    np.testing.assert_array_equal(whole.A, split.A)  # the same episodes either way
    assert whole.A.sharding.is_fully_replicated
    if jax.device_count() > 1:
        assert not split.A.sharding.is_fully_replicated
        assert split.A.sharding.shard_shape(split.A.shape)[0] == 4 // jax.device_count()
    monkeypatch.setattr(sharding, "mesh", lambda: None)
    tree = {"a": jnp.ones((4, 2))}
    assert sharding.replicated(tree) is tree  # one device: untouched


def test_a_cluster_is_recognised_from_its_variables():
    assert not sharding.cluster_requested({})
    assert not sharding.cluster_requested({"SLURM_JOB_ID": "7", "SLURM_NTASKS": "1"})
    assert sharding.cluster_requested({"SLURM_JOB_ID": "7", "SLURM_NTASKS": "2"})
    assert sharding.cluster_requested({"JAX_COORDINATOR_ADDRESS": "node0:1234"})
    assert not sharding.cluster_requested({"SLURM_NTASKS": "2"})  # not inside a job


def test_each_process_of_a_cluster_keeps_its_own_executed_notebook(monkeypatch):
    from qdnb.book import runner
    from qdnb.core import paths

    monkeypatch.delenv("JAX_PROCESS_ID", raising=False)
    monkeypatch.delenv("SLURM_PROCID", raising=False)
    main = runner.executed_path("ch2_primer", "tiny")
    assert main == paths.run_dir("tiny", "ch2_primer") / "ch2_primer.ipynb"
    monkeypatch.setenv("SLURM_PROCID", "3")
    assert runner.process_id() == 3
    assert runner.executed_path("ch2_primer", "tiny") == main.parent / "process-3" / main.name
