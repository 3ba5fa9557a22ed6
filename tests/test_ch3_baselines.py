"""Chapter 3's baselines page: its configs, its claim on hand-made results, and the
schema of its summary (every baseline on every environment, run or not)."""

import dataclasses

import numpy as np
import pytest

from qdnb.book.registry import config
from qdnb.chapters import ch3_baselines
from qdnb.chapters.ch3_baselines import BASELINES, BaselinesConfig, Result
from qdnb.chapters.ch3_qdpg import ENVIRONMENTS, EnvironmentResult, MethodResult


def method(perf, steps=1000.0):
    perf = np.asarray(perf, float)
    n = len(perf)
    history = {
        "max_fitness": np.tile(perf[:, None], (1, 3)),
        "descriptors": np.zeros((n, 3, 2, 2)),  # the start corner: never the exit zone
        "env_steps": np.full((n, 3), steps / 3),
    }
    return MethodResult(
        history=history,
        grid=None,
        final_performance=perf,
        coverage=np.full(n, 0.2),
        env_steps=np.full(n, steps),
        cumulative_steps=np.cumsum(history["env_steps"], axis=1),
        seconds=1.0,
        steady_seconds_per_iteration=0.1,
    )


def hand_made(qdpg, baselines, ant_methods=BASELINES):
    envs = {}
    for env_name in ENVIRONMENTS:
        names = BASELINES if env_name == "pointmaze" else ant_methods
        envs[env_name] = EnvironmentResult(None, env_name, {n: method(baselines[n]) for n in names})
    return Result(
        {e: method(qdpg) for e in ENVIRONMENTS}, {e: "loaded" for e in ENVIRONMENTS}, envs
    )


def test_qdpg_must_beat_each_baseline_on_the_mean_and_on_most_seeds():
    perf = {name: [-100.0] for name in BASELINES} | {"AGAC": [-30.0], "RND": [-25.0]}
    result = hand_made([-24.0, -40.0, -20.0], perf)  # mean -28: above AGAC's -30 on 2/3 seeds
    held = {c[0].split()[2]: c[1] for c in ch3_baselines.claims(result)}
    assert held == {n: n != "RND" for n in BASELINES}  # RND's -25 beats the mean -28
    lucky = hand_made([-10.0, -50.0, -60.0], {n: [-35.0] for n in BASELINES})  # mean -40
    assert not any(ok for _, ok, _ in ch3_baselines.claims(lucky))
    one_seed = hand_made([-24.0, -50.0, -50.0], {n: [-45.0] for n in BASELINES})  # mean -41.3
    assert not any(ok for _, ok, _ in ch3_baselines.claims(one_seed))  # only 1/3 seeds beat -45


def test_the_summary_lists_every_baseline_on_every_environment():
    cfg = config("ch3_baselines", "tiny")
    result = hand_made([-24.0], {n: [-50.0] for n in BASELINES}, ant_methods=("SAC",))
    out = ch3_baselines.summary_results(cfg, result)
    assert out["claims_total"] == 6 and out["claims_held"] == 6
    assert [c["id"] for c in out["claims"]] == [f"ch3_baselines/{n}" for n in BASELINES]
    assert all(c["status"] == "holds" and "-24.0 vs -50.0" in c["numbers"] for c in out["claims"])
    assert out["qdpg_source"] == {e: "loaded" for e in ENVIRONMENTS}
    for env_name in ENVIRONMENTS:
        assert set(out[env_name]) == {"QD-PG", *BASELINES}
        for name, entry in out[env_name].items():
            ran = env_name == "pointmaze" or name in ("QD-PG", "SAC")
            assert entry["ran"] is ran
            assert {"final_performance", "coverage", "env_steps"} <= set(entry)
            assert (entry["final_performance"] is None) is not ran


def test_configs_share_the_qdpg_pages_tasks_and_refuse_bad_values():
    for scale in ("tiny", "small", "paper"):
        cfg = config("ch3_baselines", scale)
        assert cfg.tasks == config("ch3_qdpg", scale)  # the same budgets as QD-PG's
        assert cfg.methods("pointmaze") == BASELINES
        tasks = cfg.baseline_tasks("pointmaze")
        assert (
            tasks.seeds("pointmaze", "SAC") == cfg.num_seeds
            and tasks.pointmaze == cfg.tasks.pointmaze
        )
        ants = cfg.baseline_tasks("antmaze")
        assert ants.antmaze == cfg.tasks.antmaze
        assert (
            ants.seeds("antmaze", "SAC") == cfg.seeds("antmaze") == (cfg.ant_seeds or cfg.num_seeds)
        )
    tiny = config("ch3_baselines", "tiny")
    with pytest.raises(ValueError, match="unknown baselines"):
        dataclasses.replace(tiny, ant_methods=("SAC", "PPO"))
    with pytest.raises(ValueError, match="num_seeds=0"):
        dataclasses.replace(tiny, num_seeds=0)
    with pytest.raises(ValueError, match="ant_seeds=0"):
        dataclasses.replace(tiny, ant_seeds=0)
    with pytest.raises(ValueError, match="unknown environment"):
        tiny.methods("halfcheetah")
    assert isinstance(tiny, BaselinesConfig)


def test_every_setting_of_every_baseline_says_where_it_comes_from():
    cfg = config("ch3_baselines", "tiny")
    settings = ch3_baselines.hyperparameters(cfg, "pointmaze")
    assert set(settings) == set(BASELINES)
    missing = [
        (m, k) for m, fields in settings.items() for k in fields if not ch3_baselines.source(m, k)
    ]
    assert not missing
    assert settings["SAC"]["num_episodes"] == cfg.tasks.pointmaze.num_actors


def test_the_rest_of_table_3_4_is_read_from_the_qdpg_pages_run_of_this_seed_and_config(
    tmp_path, monkeypatch
):
    import json

    from qdnb.core import paths
    from qdnb.core.config import config_hash

    monkeypatch.setattr(paths, "RUNS", tmp_path)
    cfg = config("ch3_baselines", "tiny")
    assert ch3_baselines.qdpg_page_methods(cfg, "tiny", 0) == (
        None,
        "no run of the QD-PG page at this scale",
    )
    entry = {"ran": True, "final_performance": -129.0, "env_steps": 8000.0}
    results = {e: {"QD-PG": entry, "TD3": entry, "PGA-ME": {"ran": False}} for e in ENVIRONMENTS}
    summary = {"seed": 0, "config_hash": config_hash(cfg.tasks), "results": results}
    (paths.run_dir("tiny", "ch3_qdpg") / "summary.json").write_text(json.dumps(summary))
    others, where = ch3_baselines.qdpg_page_methods(cfg, "tiny", 0)
    assert others == {e: {"TD3": entry} for e in ENVIRONMENTS} and "QD-PG page's run" in where
    assert ch3_baselines.qdpg_page_methods(cfg, "tiny", 1)[0] is None  # another seed
    other_cfg = dataclasses.replace(cfg, tasks=config("ch3_qdpg", "small"))
    assert ch3_baselines.qdpg_page_methods(other_cfg, "tiny", 0)[0] is None  # another config
