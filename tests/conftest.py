import os

import pytest

# Tests run on CPU, deterministically, whatever the machine has.
os.environ.setdefault("JAX_PLATFORMS", "cpu")
# ...and compile with XLA's CPU optimisation off, as the tiny notebooks' kernels do
# (``runner.KERNEL_XLA_FLAGS``): most unit tests compile far more than they compute.
# Measured with an empty compilation cache: six compile-heavy files alone took 441 s ->
# 333 s; in the whole suite compile-heavy files got faster (test_checkpoint 139 -> 110 s,
# test_sharding 100 -> 59 s) and run-heavy ones slower (test_qdt 74 -> 122 s, test_flt
# 28 -> 63 s), all tests passing either way.  Set an optimisation level in XLA_FLAGS to
# override.
from qdnb.book.runner import KERNEL_XLA_FLAGS  # noqa: E402 (after JAX_PLATFORMS is set)

if "optimization_level" not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = " ".join(
        filter(None, [os.environ.get("XLA_FLAGS"), KERNEL_XLA_FLAGS["tiny"]])
    )


@pytest.fixture
def runs(tmp_path, monkeypatch):
    """The runs and the published runs in a temporary folder: what a test writes
    there stays out of the repository's ``data/``."""
    from qdnb.book import publish
    from qdnb.core import paths

    monkeypatch.setattr(paths, "RUNS", tmp_path / "runs")
    monkeypatch.setattr(publish, "PUBLISHED", tmp_path / "published")
    return tmp_path / "runs"


def pytest_collection_modifyitems(config, items):
    """The notebooks first: `make test` runs two pytest-xdist workers, one file per
    worker at a time in collection order (``--no-loadscope-reorder``), so the
    longest files (the notebook groups of ``notebook_runs``: each runs its pages in
    order on one worker) start at once and the unit tests fill in behind them."""
    items.sort(
        key=lambda item: item.get_closest_marker("notebook") is None
    )  # stable: order kept within each


def pytest_runtest_setup(item):
    """A notebook that nbmake runs in place (as a reader would, from a fresh kernel)
    writes its run into a temporary directory, not over the runner's run of it."""
    if item.path.suffix == ".ipynb":
        import tempfile

        item._qdnb_runs = (os.environ.get("QDNB_RUNS"), tempfile.mkdtemp(prefix="qdnb-nbmake-"))
        os.environ["QDNB_RUNS"] = item._qdnb_runs[1]


def pytest_runtest_teardown(item):
    if item.path.suffix == ".ipynb":
        import shutil

        previous, runs = item._qdnb_runs
        shutil.rmtree(runs, ignore_errors=True)
        if previous is None:
            os.environ.pop("QDNB_RUNS", None)
        else:
            os.environ["QDNB_RUNS"] = previous
