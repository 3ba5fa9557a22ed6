"""Chapter 3's pages at tiny scale, in order: the baselines and evolution pages read
the QD-PG page's results (``notebook_runs``)."""

import pytest
from notebook_runs import GROUPS, run_and_check


@pytest.mark.notebook
@pytest.mark.parametrize("name", GROUPS["ch3"])
def test_notebook_runs_at_tiny_scale(name):
    run_and_check(name)
