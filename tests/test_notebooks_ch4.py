"""Chapter 4's pages at tiny scale, in order: the QDT page distils the reproducibility
page's repertoires (``notebook_runs``)."""

import pytest
from notebook_runs import GROUPS, run_and_check


@pytest.mark.notebook
@pytest.mark.parametrize("name", GROUPS["ch4"])
def test_notebook_runs_at_tiny_scale(name):
    run_and_check(name)
