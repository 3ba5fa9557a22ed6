import os

# Tests run on CPU, deterministically, whatever the machine has.
os.environ.setdefault("JAX_PLATFORMS", "cpu")


def pytest_collection_modifyitems(config, items):
    """The notebooks first: `make test` runs two pytest-xdist workers, one file per
    worker at a time in collection order (``--no-loadscope-reorder``), so the
    longest file (the notebooks, ch4_qdt after the ch4_reproducibility run whose
    repertoires it reuses) starts at once while the other worker takes the unit
    tests."""
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
