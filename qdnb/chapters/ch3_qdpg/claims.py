"""Chapter 3's claims (Section 3.6), on Point-Maze: QD-PG against TD3 and its ablations, per
seed, and the page's summary.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from qdnb.chapters.ch3_qdpg.methods import QDPG_METHODS
from qdnb.core import claims as claim_records
from qdnb.core.claims import finite_mean
from qdnb.core.names import seeds_text

if TYPE_CHECKING:
    from qdnb.chapters.ch3_qdpg.adaptation import FastAdaptation, HandPath
    from qdnb.chapters.ch3_qdpg.experiment import EnvironmentResult
    from qdnb.chapters.ch3_qdpg.settings import QDPGConfig


def beats(a: np.ndarray, b: np.ndarray) -> bool:
    """Whether the per-seed values ``a`` beat ``b``: on the mean over seeds, and on
    most of the seeds of ``a`` (each against the mean of ``b``).  Diverged seeds (NaN)
    are in no mean, and count as seeds of ``a`` that do not beat it."""
    target = finite_mean(b)
    a = np.asarray(a, float)
    return bool(finite_mean(a) > target and np.mean(np.where(np.isnan(a), False, a > target)) > 0.5)


def per_seed(p: np.ndarray) -> str:
    """A mean over the finite seeds, and every seed when there are several ("diverged"
    for one that went NaN)."""
    each = ", ".join("diverged" if np.isnan(v) else f"{v:.1f}" for v in p)
    seeds = f" (seeds: {each})" if len(p) > 1 else ""
    return f"{finite_mean(p):.1f}{seeds}"


# the stable names of ``claims``'s rows, in order (the book's scorecard matches scales by them)
CLAIM_IDS = ("reaches_exit", "beats_td3", "beats_qpg", "dpg_explores")


def claims(results_by_env: dict[str, EnvironmentResult]) -> list[tuple[str, bool, str]]:
    """The chapter's Point-Maze claims as ``(claim, holds, numbers)``.  A comparison
    holds on the mean over seeds and on most of the seeds of the method it is about."""
    pm = results_by_env["pointmaze"].methods
    perf = lambda name: pm[name].final_performance
    cov = lambda name: finite_mean(pm[name].coverage)

    reached = pm["QD-PG"].reached_exit
    return [
        (
            "QD-PG reaches the exit zone (most seeds)",
            bool(reached.mean() > 0.5),
            f"{reached.sum()} of {seeds_text(len(reached))}",
        ),
        (
            "QD-PG beats TD3 on final performance (mean and most seeds)",
            beats(perf("QD-PG"), perf("TD3")),
            f"{per_seed(perf('QD-PG'))} vs {per_seed(perf('TD3'))}",
        ),
        (
            "QD-PG beats Q-PG on final performance (mean and most seeds)",
            beats(perf("QD-PG"), perf("Q-PG")),
            f"{per_seed(perf('QD-PG'))} vs {per_seed(perf('Q-PG'))}",
        ),
        (
            "D-PG explores: covers more reachable cells than Q-PG and TD3",
            cov("D-PG") > max(cov("Q-PG"), cov("TD3")),
            f"{cov('D-PG'):.2f} vs {cov('Q-PG'):.2f} (Q-PG), {cov('TD3'):.2f} (TD3)",
        ),
    ]


def method_summaries(
    results_by_env: dict[str, EnvironmentResult], expected: tuple[str, ...] = QDPG_METHODS
) -> dict[str, dict[str, Any]]:
    """``summary.json``'s per-environment, per-method entries; a method of ``expected``
    not run at this scale is said to be so (``"ran": False``), not invented."""
    out: dict[str, dict[str, Any]] = {}
    for env_name, res in results_by_env.items():
        out[env_name] = {}
        for name, r in res.methods.items():
            kept = r.final_performance[r.kept]
            entry = {
                "ran": True,
                "final_performance": finite_mean(r.final_performance),
                "final_performance_std": float(kept.std()) if kept.size else None,
                "final_performance_per_seed": [
                    None if np.isnan(v) else float(v) for v in r.final_performance
                ],
                "coverage": finite_mean(r.coverage),
                "env_steps": float(r.env_steps.mean()),
                "run_seconds": round(r.seconds, 1),
                "diverged": [
                    None if d is None else {"iteration": d.iteration, "parts": list(d.parts)}
                    for d in r.diverged
                ],
            }
            if env_name == "pointmaze":
                entry["reached_goal"] = bool(r.reached_exit.any())
                entry["steps_to_exit"] = [None if np.isnan(v) else float(v) for v in r.exit_steps]
            out[env_name][name] = entry
        for name in expected:
            if name not in res.methods:
                out[env_name][name] = {
                    "ran": False,
                    "final_performance": None,
                    "coverage": None,
                    "env_steps": 0,
                }
    return out


def summary_results(
    cfg: QDPGConfig,
    results_by_env: dict[str, EnvironmentResult],
    fast: FastAdaptation,
    hand: HandPath,
) -> dict[str, Any]:
    """The chapter's ``summary.json`` results: the claims, every method's entry
    (``method_summaries``), the fast adaptation, Ant-Maze's steps to goal, Point-Maze's
    time per iteration and the hand-written path's return."""
    held = claims(results_by_env)
    count = sum(ok for _, ok, _ in held)
    pm = results_by_env["pointmaze"].methods
    return {
        "headline": f"{count}/{len(held)} Point-Maze claims hold",
        "claims_held": count,
        "claims_total": len(held),
        "claims": [
            claim_records.record(f"ch3_qdpg/{key}", f"Point-Maze: {text}", ok, numbers)
            for key, (text, ok, numbers) in zip(CLAIM_IDS, held)
        ],
        "num_seeds": cfg.num_seeds,
        "pointmaze_qdpg_seeds": cfg.seeds("pointmaze", "QD-PG"),
        "fast_adaptation": fast.summary(),
        **method_summaries(results_by_env),
        "antmaze_steps_to_goal": results_by_env["antmaze"].methods["QD-PG"].steps_to_goal(),
        "pointmaze_seconds_per_iteration": {
            name: r.steady_seconds_per_iteration for name, r in pm.items()
        },
        "pointmaze_hand_path_return": float(hand.returns.mean()),
    }
