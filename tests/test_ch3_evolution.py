"""Chapter 3's evolution page: its configs, the sample-efficiency claim and the
ratios on hand-made results, the summary's schema, and the ES methods in the
chapter's registry."""

import dataclasses

import numpy as np
import pytest

from qdnb.book.registry import config
from qdnb.chapters import ch3_evolution
from qdnb.chapters.ch3_evolution import ENVIRONMENTS, EVOLUTION, Result
from qdnb.chapters.ch3_qdpg import EnvironmentResult, MethodResult, build_algorithms, until_goal


def method(exit_steps, perf=-100.0):
    """A Point-Maze result whose seed s first ended in the exit zone after
    ``exit_steps[s]`` steps (``None``: never), on a run of 4 iterations of 100 steps."""
    n = len(exit_steps)
    descriptors = np.zeros((n, 4, 1, 2))  # the start corner
    cumulative = np.tile(np.arange(1, 5) * 100.0, (n, 1))
    for s, hit in enumerate(exit_steps):
        if hit is not None:
            descriptors[s, int(np.searchsorted(cumulative[s], hit)), 0] = (-0.5, 0.8)  # the exit
    history = {"max_fitness": np.full((n, 4), perf), "descriptors": descriptors}
    return MethodResult(
        history=history,
        grid=None,
        final_performance=np.full(n, perf),
        coverage=np.full(n, 0.2),
        env_steps=cumulative[:, -1],
        cumulative_steps=cumulative,
        seconds=1.0,
        steady_seconds_per_iteration=0.1,
    )


def hand_made(qdpg, es):
    envs = {
        e: EnvironmentResult(None, e, {n: method(es[n]) for n in EVOLUTION}) for e in ENVIRONMENTS
    }
    return Result(
        {e: method(qdpg) for e in ENVIRONMENTS}, {e: "loaded" for e in ENVIRONMENTS}, envs
    )


def test_steps_to_the_exit_zone_are_read_from_the_history():
    r = method([200.0, None])
    np.testing.assert_array_equal(ch3_evolution.steps_to_goal("pointmaze", r), [200.0, np.inf])


def test_a_method_stops_once_every_seed_has_reached_the_goal():
    # Point-Maze: chunks of history shaped iterations x seeds x episodes x 2
    stop = until_goal("pointmaze", 2)
    start, exit_ = np.zeros((2, 2, 3, 2)), np.zeros((2, 2, 3, 2))
    exit_[1, 0, 2] = (-0.5, 0.8)  # seed 0 reaches the exit in the chunk's second iteration
    assert not stop({"descriptors": start}) and not stop({"descriptors": exit_})
    exit_[:] = 0.0
    exit_[0, 1, 0] = (-0.5, 0.8)  # seed 1 later: every seed has now reached it
    assert stop({"descriptors": exit_})
    # Ant-Maze: a best reward above -10 (Table 3.3), here iterations x seeds
    stop = until_goal("antmaze", 2)
    assert not stop({"max_fitness": np.array([[-30.0, -9.0], [-12.0, -20.0]])})
    assert stop({"max_fitness": np.array([[-9.5, -40.0]])})


def test_qdpg_must_be_ten_times_faster_than_the_fastest_es_on_the_mean_and_most_seeds():
    es = {"ME-ES": [400.0, 400.0], "NSR-ES": [None, None], "NSRA-ES": [None, 400.0]}
    assert not ch3_evolution.sample_efficiency(hand_made([100.0, 100.0], es))[1]  # only 4x
    fast = {"ME-ES": [None, None], "NSR-ES": [None, None], "NSRA-ES": [None, None]}
    held = ch3_evolution.sample_efficiency(hand_made([100.0, 200.0], fast))
    assert held[1] and "fastest ES: ME-ES" in held[2]  # never reached: infinitely slower
    assert not ch3_evolution.sample_efficiency(hand_made([100.0, None], fast))[1]  # QD-PG too
    assert ch3_evolution.ratio_to_qdpg(hand_made([100.0, 300.0], es), "pointmaze") == {
        "QD-PG": 1.0,
        "ME-ES": 2.0,
        "NSR-ES": None,
        "NSRA-ES": None,
    }


def test_the_summary_lists_every_method_on_both_environments():
    cfg = config("ch3_evolution", "tiny")
    es = {"ME-ES": [400.0], "NSR-ES": [None], "NSRA-ES": [None]}
    out = ch3_evolution.summary_results(cfg, hand_made([None], es))
    assert out["claims_total"] == 1 and out["claims_held"] == 0
    # QD-PG never reached the goal: the claim, about steps to the goal, cannot show
    (claim,) = out["claims"]
    assert claim["id"] == "ch3_evolution/sample_efficiency" and claim["status"] == "cannot show"
    assert out["headline"].startswith("cannot show:")
    never = {"ME-ES": [None], "NSR-ES": [None], "NSRA-ES": [None]}
    reached = ch3_evolution.summary_results(cfg, hand_made([100.0], never))
    assert reached["claims"][0]["status"] == "holds"  # the ES methods never reach it
    slow = ch3_evolution.summary_results(cfg, hand_made([100.0], es))
    assert slow["claims"][0]["status"] == "fails"  # ME-ES did, not 10x slower
    for env_name in ENVIRONMENTS:
        assert set(out[env_name]) == {"QD-PG", *EVOLUTION}
        assert out[env_name]["ME-ES"]["ran"] and out[env_name]["ME-ES"]["ratio_to_qdpg"] is None
        assert out[env_name]["NSR-ES"]["steps_to_goal"] is None
        assert out[env_name]["QD-PG"]["steps_to_goal_per_seed"] == [None]
    assert out["pointmaze"]["ME-ES"]["steps_to_goal"] == 400.0  # the exit zone
    assert out["antmaze"]["ME-ES"]["steps_to_goal"] is None  # a best reward above -10: never


def test_configs_refuse_bad_values_and_the_registry_builds_each_es():
    for scale in ("tiny", "small", "paper"):
        cfg = config("ch3_evolution", scale)
        assert cfg.tasks == config("ch3_qdpg", scale)
        tasks = cfg.es_tasks()
        assert tasks.pointmaze.num_actors == cfg.num_perturbations
        assert tasks.pointmaze.episode_length == cfg.tasks.pointmaze.episode_length
        ants = cfg.es_tasks("antmaze")
        assert ants.antmaze.num_actors == cfg.ant_perturbations
        assert (
            ants.seeds("antmaze", "ME-ES")
            == cfg.seeds("antmaze")
            == (cfg.ant_seeds or cfg.num_seeds)
        )
    tiny = config("ch3_evolution", "tiny")
    algos = build_algorithms(tiny.es_tasks(), "pointmaze", methods=EVOLUTION)
    assert [a.num_perturbations for a in algos.values()] == [tiny.num_perturbations] * 3
    assert algos["NSRA-ES"].adaptive and not algos["NSR-ES"].adaptive
    with pytest.raises(ValueError, match="even number"):
        dataclasses.replace(tiny, num_perturbations=15)
    with pytest.raises(ValueError, match="unknown methods"):
        dataclasses.replace(tiny, ant_methods=("ES",))
    with pytest.raises(ValueError, match="ant_seeds=0"):
        dataclasses.replace(tiny, ant_seeds=0)
    with pytest.raises(ValueError, match="less than one iteration"):
        dataclasses.replace(tiny, pointmaze_steps=10)
    with pytest.raises(ValueError, match="unknown environment"):
        tiny.methods("anttrap")
