"""The chapters' derived metrics and claim checks, on hand-made results."""

import dataclasses
from types import SimpleNamespace

import numpy as np
import pytest

from qdnb.chapters import ch2_primer
from qdnb.envs.pointmaze import GOAL


def primer_run(reached_per_seed, first_iteration=1):
    """Histories of 2 seeds x 3 evaluations x 2 episodes: a seed that reaches the
    goal does so at ``first_iteration``; every other episode ends at (0, 0)."""
    desc = np.zeros((2, 3, 2, 2), np.float32)
    for seed, reached in enumerate(reached_per_seed):
        if reached:
            desc[seed, first_iteration, 1] = GOAL
    history = {
        "descriptors": desc,
        "coverage": np.full((2, 3), 0.25),
        "min_distance": np.full((2, 3), 0.5),
        "fitnesses": np.arange(12, dtype=float).reshape(2, 3, 2),
    }
    return ch2_primer.MethodRun(history, final=None, seconds=1.0)


def test_primer_metrics_and_claim_on_hand_made_histories():
    cfg = dataclasses.replace(
        ch2_primer.SCALES["tiny"], num_seeds=2, num_iterations=2, batch_size=2
    )
    result = ch2_primer.Result(
        cfg,
        {
            "GA": primer_run([False, False]),
            "NS": primer_run([True, True]),
            "ME": primer_run([True, True], 2),
        },
    )
    m = ch2_primer.method_metrics(result)
    assert m["NS"]["reached_per_seed"].tolist() == [True, True]
    # steps after the evaluation that first reached it: (iteration + 1) x batch x episode length
    assert m["NS"]["steps_to_goal_per_seed"] == [2 * 2 * 200] * 2
    assert m["ME"]["steps_to_goal_per_seed"] == [3 * 2 * 200] * 2
    assert m["GA"]["steps_to_goal_per_seed"] == [None, None]
    assert m["GA"]["best_return_per_seed"].tolist() == [5.0, 11.0]
    claim = ch2_primer.claim(result)
    assert claim["holds"] and claim["headline"] == "goal reached in NS 2/2, ME 2/2, GA 0/2 seeds"
    partly = ch2_primer.Result(cfg, {**result.runs, "ME": primer_run([True, False])})
    assert not ch2_primer.claim(partly)["holds"]
    assert "only partly" in ch2_primer.claim(partly)["verdict"]
    summary = ch2_primer.summary_results(result)
    assert summary["NS"]["seeds_reaching_goal"] == 2 and summary["env_steps"] == cfg.env_steps


def test_qdt_claim_checks_on_hand_made_seeds():
    from qdnb.chapters import ch4_qdt

    def result(*seeds):  # each seed: (QDT(ME-LS), QDT(ME), the ME repertoire) distances
        ls, me_qdt, me_rep = (np.array(v) for v in zip(*seeds))
        return SimpleNamespace(
            qdt={
                "ME-LS": SimpleNamespace(avg_distance=ls),
                "ME": SimpleNamespace(avg_distance=me_qdt),
            },
            repertoire={"ME": ch4_qdt.Scores(np.stack([me_rep, me_rep], 1), np.zeros((3, 2)))},
        )

    res = result((1.0, 2.0, 0.5), (1.0, 3.0, 2.0), (1.0, 0.5, 3.0))
    checks = {c["claim"]: c for c in ch4_qdt.claim_checks({"toy": res})}
    vs_rep = checks["QDT(ME-LS) closer to the goals than ME"]
    vs_qdt = checks["QDT(ME-LS) closer to the goals than QDT (ME)"]
    assert vs_rep["holds"] and vs_rep["seeds where it holds"] == "2/3"  # 1.0 < 1.83 on the mean
    assert vs_qdt["holds"] and vs_qdt["QDT (ME)"] == round(5.5 / 3, 4)
    assert vs_qdt["QDT (ME) range"] == "0.5–3" and vs_rep["ME range"] == "0.5–3"
    worse = result((1.0, 0.9, 0.9), (1.0, 5.0, 5.0), (1.0, 0.8, 0.8))
    assert not any(c["holds"] for c in ch4_qdt.claim_checks({"toy": worse}))  # mean yes, 1/3 seeds


def test_qdt_results_stack_a_quantity_over_the_seeds_that_have_it():
    from qdnb.chapters.ch4_qdt import EnvironmentResult, QDTRun

    def qdt(distance):
        return {
            "steps": np.array([100, 200]),
            **{k: np.zeros(2) for k in ("avg_distance_curve", "max_fitness_curve", "loss")},
            **{k: np.full(3, distance) for k in ("distance", "spread")},
            "best_step": 200,
            "avg_distance": distance,
            "avg_spread": 0.0,
            "dataset_size": 10,
            "seconds": 1.0,
            "heldout_mse": 0.1,
            "shuffled_mse": 0.3,
            "imitation": np.full(4, distance),
        }

    def seed(full, **qdts):
        parts = ("repertoire", "teachers", "selection", "datasets", "generalization")
        return {"qdt": qdts, "full": full} | {p: {} for p in parts}

    seeds = [seed(True, ME=qdt(1.0), Naive=qdt(4.0)), seed(False, ME=qdt(2.0))]  # no Naive QDT
    res = EnvironmentResult.collect(
        "toy", (0.0,), (1.0,), np.zeros((2, 1)), np.zeros((3, 1)), {}, seeds
    )
    assert res.qdt["ME"].avg_distance.tolist() == [1.0, 2.0]
    assert res.qdt["Naive"].avg_distance.tolist() == [4.0]
    assert res.qdt["ME"].distance.shape == (2, 3) and res.qdt["ME"].steps.tolist() == [100, 200]
    assert res.full_seeds == 1 and isinstance(res.qdt["ME"], QDTRun)
    assert (
        res.qdt["ME"].imitation.shape == (2, 4) and res.qdt["ME"].shuffled_mse.tolist() == [0.3] * 2
    )
    assert res.qdt["ME"].avg_distance_removed is None  # only the tiles and upper prunings


def test_qdt_data_floor_selection_summary_and_nearest_half_on_hand_made_values():
    from qdnb.chapters import ch4_qdt
    from qdnb.models.qdt.data import Selection

    goals = np.array([[0.0, 0.0], [1.0, 0.0], [3.0, 0.0], [4.0, 0.0]])
    data = np.array([[0.0, 0.0]])
    assert ch4_qdt.data_floor(goals, data) == pytest.approx((0 + 1 + 3 + 4) / 4)
    res = SimpleNamespace(goals=goals, datasets={"ME-LS": (data,)})
    assert ch4_qdt.nearest_half(res).tolist() == [True, True, False, False]

    def selection(cells, hits):
        cells, hits = np.array(cells), np.array(hits)
        return Selection(cells, cells, hits, hits, cells, hits, hits)

    res = SimpleNamespace(selection={"ME": (selection([1, 2], [1.0, 0.5]), selection([3], [0.0]))})
    entry = ch4_qdt.selection_summary(res)["ME"]
    assert entry["zones_with_data"] == 1.5 and entry["demonstrator_hit_rate"] == 0.375
    assert entry["seeds"] == {"zones_with_data": [2, 1], "demonstrator_hit_rate": [0.75, 0.0]}


def test_qdt_summaries_average_the_finite_values_only(recwarn):
    from qdnb.core.claims import finite_mean

    assert finite_mean([np.nan, 1.0, 3.0]) == 2.0
    assert np.isnan(finite_mean([np.nan, np.nan])) and not recwarn.list  # no warning
