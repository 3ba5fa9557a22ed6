"""Running a notebook at tiny scale through the runner (papermill), as `make book`
would, and checking its summary.json (the executed copies are reused by `make book
SCALE=tiny` in CI).  The notebooks are split into ``GROUPS``, one test file each
(``test_notebooks_<group>.py``): pytest-xdist's ``--dist loadfile`` runs a file on one
worker, in order, so a page that reuses another's run (ch4_qdt, ch4_reproducibility's
repertoires; the Chapter 3 pages, QD-PG's results) runs after it on the same worker,
while the groups share the two workers."""

import json
from pathlib import Path

import nbformat

from qdnb.book import runner
from qdnb.core import paths


def write_notebook(path: Path, *cells) -> Path:
    """A notebook with a ``parameters`` cell (``scale = 'tiny'``) and then ``cells`` (a
    source, or a ``(source, tags)`` pair each), on the ``python3`` kernel, at ``path``."""
    nb = nbformat.v4.new_notebook()
    nb.cells = [nbformat.v4.new_code_cell("scale = 'tiny'", metadata={"tags": ["parameters"]})]
    for cell in cells:
        source, tags = cell if isinstance(cell, tuple) else (cell, [])
        nb.cells.append(nbformat.v4.new_code_cell(source, metadata={"tags": tags} if tags else {}))
    nb.metadata["kernelspec"] = {
        "name": "python3",
        "display_name": "Python 3",
        "language": "python",
    }
    path.parent.mkdir(parents=True, exist_ok=True)
    nbformat.write(nb, path)
    return path


GROUPS = {
    "ch3": ("ch3_qdpg", "ch3_baselines", "ch3_evolution"),
    "ch4": ("ch4_reproducibility", "ch4_qdt"),
    "rest": ("ch2_primer", "ch5_flow_lenia"),
}


def run_and_check(name: str) -> None:
    """Run notebook ``name`` at tiny scale through the runner and check its summary."""
    # every loop runs (fresh), saving its checkpoints as a reader's run does
    out = runner.run_notebook(name, "tiny", seed=0, progress=False, checkpoints="fresh")
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
    if name == "ch4_reproducibility":
        for env in ("ant_omni", "halfcheetah_uni"):
            for method in ("ME", "ME-LS", "PGA-ME", "PGA-ME-LS", "ME-Sampling"):
                r = summary["results"][env][method]
                assert r["avg_distance"] >= 0.0 and r["avg_spread"] >= 0.0
                assert 0.0 < r["coverage"] <= 1.0 and r["env_steps"] > 0
                assert set(r["reassessed"]) == {"coverage", "max_fitness", "qd_score"}
                assert (
                    r["reassessed"]["coverage"] <= r["coverage"]
                )  # re-insertion can only merge cells
                assert (out.parent / f"repertoire_{env}_{method}.npz").exists()
            bounds = summary["results"]["descriptor_bounds"][env]
            assert all(lo < hi for lo, hi in zip(bounds["low"], bounds["high"]))
    if name == "ch3_qdpg":
        results = summary["results"]
        for env in ("pointmaze", "antmaze", "anttrap"):
            assert set(results[env]) == {"QD-PG", "QD-PG Sum", "D-PG", "Q-PG", "TD3", "PGA-ME"}
            for method, r in results[env].items():
                if r.get("ran", True):
                    assert 0.0 < r["coverage"] <= 1.0 and r["env_steps"] > 0
                    assert isinstance(r["final_performance"], float)
                    assert (env != "pointmaze") or isinstance(r["reached_goal"], bool)
        assert all(results["pointmaze"][m].get("ran", True) for m in results["pointmaze"])
        fast = results["fast_adaptation"]
        assert fast["env"] == "antmaze" and fast["goals"] > 0 and fast["budget"] > 0
        assert fast["mean"] <= 0.0 and fast["std"] >= 0.0
    if name == "ch3_baselines":
        results = summary["results"]
        baselines = ("SAC", "RND", "CEM-RL", "P3S-TD3", "AGAC", "DIAYN")
        for env in ("pointmaze", "antmaze", "anttrap"):
            assert set(results[env]) == {"QD-PG", *baselines}
            for method, r in results[env].items():
                assert {"final_performance", "coverage", "env_steps", "ran"} <= set(r)
                if r["ran"]:
                    assert 0.0 < r["coverage"] <= 1.0 and r["env_steps"] > 0
                    assert isinstance(r["final_performance"], float)
            assert results["qdpg_source"][env].startswith(("loaded", "recomputed"))
        assert all(results["pointmaze"][m]["ran"] for m in baselines)
        assert 0 <= results["claims_held"] <= results["claims_total"] == 6
    if name == "ch3_evolution":
        results = summary["results"]
        for env in ("pointmaze", "antmaze"):
            assert set(results[env]) == {"QD-PG", "ME-ES", "NSR-ES", "NSRA-ES"}
            for method, r in results[env].items():
                assert {"final_performance", "steps_to_goal", "ratio_to_qdpg", "env_steps"} <= set(
                    r
                )
                if r["ran"]:
                    assert isinstance(r["final_performance"], float) and r["env_steps"] > 0
                    assert r["steps_to_goal"] is None or 0 < r["steps_to_goal"] <= r["env_steps"]
        assert all(results["pointmaze"][m]["ran"] for m in ("ME-ES", "NSR-ES", "NSRA-ES"))
        assert results["claims_total"] == 1 and results["claims_held"] in (0, 1)
    if name == "ch4_qdt":
        results = summary["results"]
        for env in ("ant_omni", "halfcheetah_uni"):
            for source in ("ME", "ME-LS", "PGA-ME", "PGA-ME-LS", "Naive"):
                r = results[env][source]
                assert r["avg_distance"] >= 0.0 and r["avg_spread"] >= 0.0
                assert 1 <= r["best_step"] <= summary["config"]["train_steps"]
                assert r["heldout_mse"] >= 0.0
                # the claim's QDTs train on every seed, the others on the full seeds only
                config = summary["config"]
                assert r["seeds"] == (
                    config["num_seeds"] if source in ("ME", "ME-LS") else config["full_seeds"]
                )
            assert set(results["repertoires"][env]) == {"ME", "ME-LS", "PGA-ME", "PGA-ME-LS"}
            gen = results["generalization"][env]
            assert set(gen) == {"50%", "30%", "10%", "tiles", "upper"}
            for pruning in ("tiles", "upper"):
                assert {"avg_distance", "avg_distance_removed", "avg_distance_kept"} <= set(
                    gen[pruning]
                )
            assert set(results["descriptor_bounds"][env]) == {"low", "high"}
            for source in ("ME", "ME-LS", "PGA-ME", "PGA-ME-LS"):
                assert (
                    0 <= results[env][source]["zones_with_data"] <= summary["config"][env]["zones"]
                )
                assert 0.0 <= results[env][source]["demonstrator_hit_rate"] <= 1.0
        assert (
            0 <= results["claims_held"] <= results["claims_total"] == 4
        )  # two comparisons per environment
    if name == "ch5_flow_lenia":
        results = summary["results"]
        steps = summary["config"]["world"]["steps"]
        assert 0.0 <= results["mass_drift_max"] < 1e-4
        for predictor in ("flt", "persistence", "mean_frame"):
            per_step = results[f"{predictor}_mse_per_step"]
            assert len(per_step) == steps and all(v >= 0.0 for v in per_step)
            assert results[f"{predictor}_mse_final"] == per_step[-1]
        assert results["train_loss_final"] > 0.0
        search = results["surprise_search"]
        assert (
            search["evaluations"] > 0
            and search["best_surprise"] >= search["median_surprise"] >= 0.0
        )
        world = results["world"]
        assert set(world) == {"mixing", "p0", "flow_bound", "kernels", "alpha", "border"}
        assert "fixed key" in world["mixing"] and world["border"] == "wall"
        # the default world is deterministic: replays and replayed elites equal the originals
        assert results["replay_mse_final"] == 0.0 and results["best_predictor_floor_final"] == 0.0
        assert search["elites_replay_max_gap"] <= 1e-6
        assert set(results["p0_comparison"]) == {"patch", "cell"}
