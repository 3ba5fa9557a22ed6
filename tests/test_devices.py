"""One XLA host device per core: how the count is chosen (``sharding.configure_host_devices``),
what a user's settings do, and the clear errors on a bad count, before any computation."""

import os
import subprocess
import sys

import pytest

from qdnb.book import provenance, runner
from qdnb.core import sharding
from qdnb.core.paths import ROOT

FLAG = sharding.DEVICE_COUNT_FLAG


def test_the_default_is_one_device_per_core_up_to_the_cap():
    assert sharding.default_host_devices(1) == 1
    assert sharding.default_host_devices(2) == 2
    assert sharding.default_host_devices(6) == 6
    assert sharding.default_host_devices(64) == sharding.HOST_DEVICE_CAP == 8


@pytest.mark.parametrize("bad", ["0", "-1", "abc", "1.5", " "])
def test_a_bad_device_count_is_refused_with_what_is_valid(bad):
    if bad.strip() == "":  # blank: the default
        assert sharding.requested_devices(bad, num_cores=4) == 4
        return
    with pytest.raises(ValueError, match="QDNB_DEVICES must be a positive integer"):
        sharding.requested_devices(bad, num_cores=4)


def test_more_devices_than_cores_is_refused():
    assert sharding.requested_devices("4", num_cores=4) == 4
    with pytest.raises(ValueError, match="more devices than this machine's 4 CPU cores"):
        sharding.requested_devices("5", num_cores=4)


def test_configure_adds_the_flag_and_says_why():
    env = {"XLA_FLAGS": "--xla_backend_optimization_level=0"}
    choice = sharding.configure_host_devices(env)
    n = sharding.default_host_devices()
    assert env["XLA_FLAGS"] == f"--xla_backend_optimization_level=0 {FLAG}={n}"
    assert choice == {"requested": n, "chosen_by": choice["chosen_by"]}
    assert choice["chosen_by"].startswith("default: one per core")
    env = {"QDNB_DEVICES": "1"}
    assert sharding.configure_host_devices(env) == {"requested": 1, "chosen_by": "QDNB_DEVICES=1"}
    assert env["XLA_FLAGS"] == f"{FLAG}=1"


def test_a_users_own_xla_flag_wins():
    env = {"XLA_FLAGS": f"{FLAG}=3", "QDNB_DEVICES": "1"}
    choice = sharding.configure_host_devices(env)
    assert choice == {"requested": 3, "chosen_by": "XLA_FLAGS (the user's)"}
    assert env["XLA_FLAGS"] == f"{FLAG}=3"


def test_a_child_process_chooses_again_instead_of_inheriting_qdnbs_flag():
    parent = {}
    sharding.configure_host_devices(parent)
    child = dict(parent, QDNB_DEVICES="1")  # e.g. `python -m qdnb run --devices 1`'s kernel
    assert sharding.configure_host_devices(child)["chosen_by"] == "QDNB_DEVICES=1"
    assert child["XLA_FLAGS"] == f"{FLAG}=1"
    forced = dict(parent)
    forced["XLA_FLAGS"] = sharding.with_device_count(parent["XLA_FLAGS"], 4)
    assert sharding.configure_host_devices(forced)["requested"] == 4  # the user's count wins


def test_chapter_xla_flags_are_added_unless_the_user_set_that_option():
    env = {"XLA_FLAGS": "--xla_force_host_platform_device_count=2"}
    assert sharding.add_xla_flags(sharding.BRAX_CPU_FLAGS, env)
    assert env["XLA_FLAGS"].split() == [
        "--xla_force_host_platform_device_count=2",
        "--xla_cpu_use_fusion_emitters=false",
    ]
    mine = {"XLA_FLAGS": "--xla_cpu_use_fusion_emitters=true"}
    sharding.add_xla_flags(sharding.BRAX_CPU_FLAGS, mine)
    assert mine["XLA_FLAGS"] == "--xla_cpu_use_fusion_emitters=true"  # the user's choice stays
    empty: dict[str, str] = {}
    sharding.add_xla_flags(sharding.BRAX_CPU_FLAGS, empty)
    assert empty["XLA_FLAGS"] == "--xla_cpu_use_fusion_emitters=false"


def test_with_device_count_replaces_any_earlier_count():
    flags = f"--a=1 {FLAG}=2 --b=2"
    assert sharding.with_device_count(flags, 4) == f"--a=1 --b=2 {FLAG}=4"


def test_bad_counts_fail_before_any_computation():
    env = dict(os.environ, QDNB_DEVICES="abc")
    proc = subprocess.run(
        [sys.executable, "-c", "import qdnb"], cwd=ROOT, env=env, capture_output=True, text=True
    )
    assert proc.returncode != 0
    assert "QDNB_DEVICES must be a positive integer" in proc.stderr
    for bad, expected in (("0", "positive integer"), ("100000", "more devices than")):
        proc = subprocess.run(
            [sys.executable, "-m", "qdnb", "run", "ch2_primer", "--devices", bad],
            cwd=ROOT,
            capture_output=True,
            text=True,
        )
        assert proc.returncode == 2 and expected in proc.stderr, proc.stderr


def test_the_provenance_records_how_the_count_was_chosen():
    import jax

    info = provenance.devices()
    assert info["count"] == jax.device_count()
    assert info["chosen_by"] == sharding.device_choice()["chosen_by"]
    assert provenance.device_text().startswith(f"{jax.device_count()} CPU device")


def test_the_fingerprint_names_the_device_count(monkeypatch):
    monkeypatch.setenv("QDNB_DEVICES", "1")
    one = runner.fingerprint("ch2_primer", "tiny", 0)
    if sharding.cores() > 1:
        monkeypatch.setenv("QDNB_DEVICES", "2")
        assert runner.fingerprint("ch2_primer", "tiny", 0) != one


def test_seeds_are_split_only_when_the_devices_divide_them(monkeypatch):
    class Mesh:  # a stand-in for a two-device mesh
        class devices:
            size = 2

    monkeypatch.setattr(sharding, "mesh", lambda: Mesh)
    assert sharding.splits_seeds(2) and sharding.splits_seeds(4)
    assert not sharding.splits_seeds(3) and not sharding.splits_seeds(1)
    monkeypatch.setattr(sharding, "SPLIT_SEEDS", False)
    assert not sharding.splits_seeds(2)
    monkeypatch.setattr(sharding, "mesh", lambda: None)
    monkeypatch.setattr(sharding, "SPLIT_SEEDS", True)
    assert not sharding.splits_seeds(2)
