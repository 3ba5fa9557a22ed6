"""Every local device: a MAP-Elites loop, a PGA-ME loop and a QDT training step on 1
and on 4 devices (CPU devices forced by ``XLA_FLAGS``, each count in its own process)
agree: the loops bit for bit (each policy's episode is computed as on one device),
the QDT's loss and gradients to float32 rounding (XLA sums the four devices' shares
of the gradient in another order).  One device leaves the program as it was."""

import os
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np

from qdnb.core import sharding
from qdnb.core.paths import ROOT

LEARNING_RATE = 1e-3  # the probe's QDT step


def probe(tmp_path):
    """Run ``bench/devices_probe.py`` on 1 and on 4 devices at once; their results."""
    procs = {}
    for n in (1, 4):
        env = dict(os.environ, JAX_PLATFORMS="cpu")
        flags = [os.environ.get("XLA_FLAGS", ""), f"--xla_force_host_platform_device_count={n}"]
        env["XLA_FLAGS"] = " ".join(filter(None, flags))  # conftest's optimisation level kept
        env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(ROOT), env.get("PYTHONPATH")]))
        out = tmp_path / f"{n}.npz"
        cmd = [sys.executable, str(ROOT / "bench" / "devices_probe.py"), str(out)]
        procs[n] = (subprocess.Popen(cmd, env=env, stderr=subprocess.PIPE, text=True), out)
    results = {}
    for n, (proc, out) in procs.items():
        _, err = proc.communicate(timeout=900)
        assert proc.returncode == 0, err[-2000:]
        results[n] = dict(np.load(out))
    return results[1], results[4]


def test_one_and_four_devices_agree(tmp_path):
    one, four = probe(tmp_path)
    assert int(one.pop("devices")) == 1 and int(four.pop("devices")) == 4
    assert one.keys() == four.keys()
    for key in one:
        if key.startswith(("ME/", "PGA-ME/")):  # the same computation per policy
            np.testing.assert_array_equal(one[key], four[key], err_msg=key)
        elif key.startswith(("QDT/loss", "QDT/step_loss", "QDT/grad")):  # a sharded reduction
            np.testing.assert_allclose(one[key], four[key], rtol=1e-4, atol=1e-7, err_msg=key)
        else:  # one Adam step: lr * g / |g| moves a near-zero gradient by up to lr either way
            np.testing.assert_allclose(one[key], four[key], atol=2 * LEARNING_RATE, err_msg=key)


def test_one_device_is_left_untouched():
    assert jax.device_count() == 1 and sharding.mesh() is None
    tree = {"a": jnp.ones((4, 2)), "b": 3.0}
    assert sharding.shard_batch(tree) is tree


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
