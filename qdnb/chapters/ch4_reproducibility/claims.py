"""The reproducibility page's claims (Section 4.5) and summary: each Low-Spread variant
against its baseline, on spread, distance to the goal and the coverage it keeps.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from qdnb.core import claims as claim_records
from qdnb.core.names import ENV_LABELS

if TYPE_CHECKING:
    from qdnb.chapters.ch4_reproducibility.experiment import EnvironmentResult
    from qdnb.chapters.ch4_reproducibility.settings import ReproducibilityConfig


CLAIM_PAIRS = (("ME-LS", "ME"), ("PGA-ME-LS", "PGA-ME"))  # (Low-Spread variant, its baseline)
# the metrics the claim compares, and the direction that favours the Low-Spread variant
CLAIM_METRICS = (("avg_spread", np.less), ("avg_distance", np.less), ("coverage_kept", np.greater))
# each comparison in the thesis's words (the book's scorecard)
CLAIM_STATEMENTS = {
    "avg_spread": "{ls}'s policies spread less than {base}'s (average spread, Table 4.4)",
    "avg_distance": "{ls} lands closer to requested behaviours than {base} (Table 4.4)",
    "coverage_kept": "{ls} keeps more of its coverage than {base} when re-evaluated (Table 4.5)",
}


def comparisons(results_by_env: dict[str, EnvironmentResult]) -> list[tuple[str, str, str, str]]:
    """The claim's comparisons, in ``claim_checks``'s order: (environment, Low-Spread
    variant, its baseline, metric)."""
    return [
        (env_name, ls, base, metric)
        for env_name in results_by_env
        for ls, base in CLAIM_PAIRS
        for metric, _ in CLAIM_METRICS
    ]


def claim_checks(results_by_env: dict[str, EnvironmentResult]) -> list[dict[str, Any]]:
    """The chapter's claim, comparison by comparison (``comparisons``): each Low-Spread
    variant against its baseline on spread, distance and coverage kept.  A comparison
    holds when it goes the thesis's way on the mean over seeds and on most seeds."""
    checks = []
    for env_name, ls, base, metric in comparisons(results_by_env):
        better = dict(CLAIM_METRICS)[metric]
        scores = results_by_env[env_name].scores
        a, b = scores[ls][metric], scores[base][metric]
        wins = int(np.sum(better(a, b)))
        claim = (
            f"{ls} keeps more coverage than {base} on reassessment"
            if metric == "coverage_kept"
            else f"{ls} average {metric.removeprefix('avg_')} < {base}"
        )
        checks.append(
            {
                "environment": env_name,
                "claim": claim,
                "values (mean)": f"{a.mean():.3f} vs {b.mean():.3f}",
                "seeds where it holds": f"{wins}/{a.size}",
                "holds": bool(better(a.mean(), b.mean()) and wins > a.size / 2),
            }
        )
    return checks


def summary_results(
    cfg: ReproducibilityConfig, results_by_env: dict[str, EnvironmentResult]
) -> dict:
    """The ``results`` of ``summary.json`` (its schema is read by the book and the tests)."""
    checks = claim_checks(results_by_env)
    held, total = sum(c["holds"] for c in checks), len(checks)
    results: dict[str, Any] = {
        "headline": f"{held}/{total} claim comparisons hold",
        "claims_held": held,
        "claims_total": total,
        "claims": [
            claim_records.record(
                f"ch4/{env_name}/{ls}/{metric}",
                f"{ENV_LABELS[env_name]}: {CLAIM_STATEMENTS[metric].format(ls=ls, base=base)}",
                c["holds"],
                f"{c['values (mean)']} (mean); the claim's way on "
                f"{c['seeds where it holds']} seeds",
            )
            for (env_name, ls, base, metric), c in zip(comparisons(results_by_env), checks)
        ],
        "num_seeds": cfg.num_seeds,
        "descriptor_bounds": {
            e: {"low": list(res.env.descriptor_low), "high": list(res.env.descriptor_high)}
            for e, res in results_by_env.items()
        },
    }
    mean = lambda d: {k: float(np.mean(d[k])) for k in ("coverage", "max_fitness", "qd_score")}
    for env_name, res in results_by_env.items():
        results[env_name] = {}
        for name, r in res.methods.items():
            seeds = res.scores[name]
            results[env_name][name] = {
                **{
                    k: float(seeds[k].mean())
                    for k in (
                        "avg_distance",
                        "avg_spread",
                        "avg_promised_distance",
                        "reproduction_gap",
                    )
                },
                **mean(r.metrics),
                "reassessed": mean(r.metrics_reassessed),
                "coverage_kept": float(seeds["coverage_kept"].mean()),
                "env_steps": r.env_steps,
                "run_seconds": round(r.run_seconds, 1),
                "seeds": {k: np.asarray(v).tolist() for k, v in seeds.items()},
            }
    return results
