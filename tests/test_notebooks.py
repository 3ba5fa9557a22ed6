"""Every notebook at tiny scale, executed by the runner (papermill), as `make book`
would; the executed copies are reused by `make book SCALE=tiny` in CI."""

import json

import pytest

from qdnb import paths, runner


@pytest.mark.notebook
@pytest.mark.parametrize("name", runner.notebook_names())
def test_notebook_runs_at_tiny_scale(name):
    out = runner.run_notebook(name, "tiny", seed=0, progress=False)
    assert out.exists() and out.parent == paths.run_dir("tiny", name)
    summary = json.loads((out.parent / "summary.json").read_text())
    assert summary["notebook"] == name and summary["scale"] == "tiny" and summary["seed"] == 0
    assert summary["results"]
    if name == "ch2_primer":
        for method in ("GA", "NS", "ME"):
            r = summary["results"][method]
            assert 0.0 < r["coverage"] <= 1.0
            assert r["min_distance_to_goal"] >= 0.0
        assert summary["results"]["env_steps"] > 0
