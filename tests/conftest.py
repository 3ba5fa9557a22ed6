import os

# Tests run on CPU, deterministically, whatever the machine has.
os.environ.setdefault("JAX_PLATFORMS", "cpu")


def pytest_collection_modifyitems(config, items):
    """The notebooks first: `make test` runs two pytest-xdist workers, one file per
    worker at a time in collection order (``--no-loadscope-reorder``), so the
    longest file (the notebooks, ch4_qdt after the ch4_reproducibility run whose
    repertoires it reuses) starts at once while the other worker takes the unit
    tests."""
    items.sort(key=lambda item: item.get_closest_marker("notebook") is None)  # stable: order kept within each
