"""The primer and Chapter 5 at tiny scale (``notebook_runs``), and every notebook in
exactly one group."""

import pytest
from notebook_runs import GROUPS, run_and_check

from qdnb.book import runner


@pytest.mark.notebook
@pytest.mark.parametrize("name", GROUPS["rest"])
def test_notebook_runs_at_tiny_scale(name):
    run_and_check(name)


def test_every_notebook_runs_in_exactly_one_group():
    names = [name for group in GROUPS.values() for name in group]
    assert sorted(names) == sorted(runner.notebook_names()) and len(set(names)) == len(names)
