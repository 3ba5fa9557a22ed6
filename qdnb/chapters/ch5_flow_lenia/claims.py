"""Chapter 5's claims and summary: the FLT and our variant against the baselines, and the
page's summary.json.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from qdnb.core import claims
from qdnb.models.lenia.flt import TrainResult

if TYPE_CHECKING:
    from qdnb.chapters.ch5_flow_lenia.evaluation import HeldOut
    from qdnb.chapters.ch5_flow_lenia.experiment import Result


def model_results(held: HeldOut, trained: TrainResult, floor: float) -> dict[str, Any]:
    """One model's scores in ``summary.json`` (the thesis's FLT at the top level, ours
    under ``variant``, with the same names)."""
    final = held.final
    return {
        **{
            f"{name}_mse_per_step": [float(x) for x in held.median[name]]
            for name in ("flt", "persistence", "mean_frame", "flt_teacher_forced", "copy_previous")
        },
        "flt_mse_final": final["flt"],
        "persistence_mse_final": final["persistence"],
        "mean_frame_mse_final": final["mean_frame"],
        "flt_below_both_baselines": bool(held.beats),
        "frame_mse_final": {k: float(np.median(e["frame"][:, -1])) for k, e in held.errors.items()},
        "train_loss_final": trained.final_loss,
        "train_episodes": trained.episodes_seen,
        "share_of_episodes_below": {
            "persistence": held.share_below("flt", "persistence"),
            "mean_frame": held.share_below("flt", "mean_frame"),
            "replay_floor": float(np.mean(held.errors["flt"]["A"][:, -1] < floor)),
        },
        "episodes_whose_error_grows": held.grows,
    }


def variant_claims(held: HeldOut) -> list[dict[str, Any]]:
    """Issue 39's claims on our FLT variant: its median final-frame error on ``A`` below
    persistence's and the mean frame's, and its error growing along the episode (its
    median per-timestep error larger at ``T`` than at ``t = 1``, in most episodes too)."""
    final, median = held.final, held.median["flt"]
    episodes = len(held.drift)
    return [
        claims.record(
            "ch5/variant_beats_baselines",
            "Our FLT variant (beyond the thesis), unrolled from the first frame, predicts the "
            "final frame better than persistence and the mean frame (median MSE on A)",
            bool(held.beats),
            f"ours {final['flt']:.4g}, persistence {final['persistence']:.4g}, mean frame "
            f"{final['mean_frame']:.4g} ({episodes} held-out episodes)",
        ),
        claims.record(
            "ch5/variant_error_grows",
            "Our FLT variant's error grows along the episode",
            held.error_grows,
            f"median MSE on A {median[0]:.4g} at t = 1, {median[-1]:.4g} at t = T; larger at T "
            f"in {held.grows} of {episodes} episodes",
        ),
    ]


def summary_results(result: Result) -> dict[str, Any]:
    """The chapter's ``summary.json`` results (the book's status table reads the headline):
    the thesis's FLT's scores at the top level, ours under ``variant`` with the same names."""
    held, diagnosis, search, trained = (
        result.held_out,
        result.diagnosis,
        result.search,
        result.trained,
    )
    final, beats = held.final, held.beats
    index = result.choice.index
    elites = search.elites
    ours = result.variant_held_out
    headline = (
        f"FLT final-frame MSE {final['flt']:.4g} vs persistence "
        f"{final['persistence']:.4g} and mean frame {final['mean_frame']:.4g}: "
        f"{'below' if beats else 'not below'} both"
    )
    if ours is not None:
        headline += f"; our variant {ours.final['flt']:.4g}: " + (
            "below both" if ours.beats else "not below both"
        )
    results = {
        "headline": headline,
        "claims": [
            claims.record(
                "ch5/flt_beats_baselines",
                "The Flow Lenia Transformer, unrolled from the first frame, predicts the final "
                "frame better than persistence and the mean frame (median MSE on A)",
                bool(beats),
                f"FLT {final['flt']:.4g}, persistence {final['persistence']:.4g}, mean frame "
                f"{final['mean_frame']:.4g} ({len(held.drift)} held-out episodes)",
            )
        ]
        + ([] if ours is None else variant_claims(ours)),
        "mass_drift_max": result.mass_drift_max,
        **model_results(held, trained, diagnosis.floor),
        "replay_mse_final": diagnosis.replay,
        "best_predictor_floor_final": diagnosis.floor,
        "system_index": index,
        "system_statistics": {k: float(v[index]) for k, v in result.choice.statistics.items()},
        "world": result.cfg.world.describe(),
        "p0_comparison": result.p0.statistics,
        "within_h_variance_share": diagnosis.within_h,
        "one_step_P_mse": diagnosis.p_errors,
        "surprise_search": {
            "model": result.searched,
            "evaluations": search.evaluations,
            "best_surprise": search.best,
            "median_surprise": float(np.median(search.history["surprise"])),
            "random_median_surprise": float(np.median(search.random_batch)),
            "filled_cells": int(elites.size),
            "spearman": search.correlations,
            "elites_stored_mean": float(search.elite_surprise[elites].mean()),
            "elites_replayed_mean": float(search.replayed[elites].mean()),
            "elites_replay_max_gap": search.replay_gap,
        },
        "wall_time_s": {
            "train": round(trained.seconds, 1),
            "evaluate": round(held.seconds, 1),
            "search": round(search.seconds, 1),
        },
    }
    if ours is not None:
        # its settings are the run's config's (``summary.json``'s ``config.variant``)
        results["variant"] = model_results(ours, result.variant, diagnosis.floor)
        results["wall_time_s"].update(
            train_variant=round(result.variant.seconds, 1),
            evaluate_variant=round(ours.seconds, 1),
        )
    return results
