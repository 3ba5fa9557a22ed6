"""Chapter 3's readings of QD-PG at Table 3.2's budget: the A/B of bench/qdpg_ab.py, the
QDax peer and the published paper-scale Point-Maze run, as the page's tables.
"""

from __future__ import annotations

import json
import math
from typing import Any

import numpy as np

from qdnb.core import paths
from qdnb.core.claims import finite_mean
from qdnb.core.names import mean_sd, number_text

# bench/qdpg_ab.py's rule: a reading of QD-PG exits Point-Maze's trap when at least three
# quarters of its seeds (3 of 4; 5 of 6 once a reading one seed from that gets two more) reach
# the exit zone within 10^6 steps (a diverged seed does not); fewer than 4 seeds call nothing
READING_EXITS_SHARE = 0.75
READING_MIN_SEEDS = 4


def exits_needed(num_seeds: int) -> int:
    """Seeds of ``num_seeds`` that must reach the exit zone for a reading to exit."""
    return math.ceil(READING_EXITS_SHARE * num_seeds)


AB_RESULTS = paths.ROOT / "bench" / "results" / "qdpg_ab.json"
PEER_RESULTS = paths.ROOT / "bench" / "results" / "qdax_qdpg.json"
PUBLISHED_POINTMAZE = paths.DATA / "published" / "paper" / "ch3_pointmaze" / "pointmaze-paper.json"
# the A/B's variants as the page names them (bench/qdpg_ab.py's VARIANTS, in its order, then
# its DIAGNOSTICS: run outside the early stop, to say which difference made a reading exit)
READINGS = {
    "thesis-adam": "QD-PG, Adam (the A/B's base)",
    "sum": "Eq. 3.5's sum of the K distances",
    "thesis-sgd": "QD-PG, SGD 6·10⁻³ (Table 3.2)",
    "qdax-novelty": "QDax's novelty (mean squared distance, K = 5)",
    "qdax-greedy": "QDax's greedy actors, played",
    "exploration-noise": "the population plays with noise 0.1",
    "squared-k10": "diagnostic: QDax's squared distance at K = 10",
}


def read_json(path) -> dict | None:
    """A results file computed outside the page, or ``None`` if it is not there."""
    return json.loads(path.read_text()) if path.exists() else None


def _numbers(rows: list[dict], key: str) -> np.ndarray:
    """``key`` of each row as floats, NaN where a results file holds ``None`` (a diverged
    seed's numbers)."""
    return np.array([np.nan if r[key] is None else r[key] for r in rows], float)


def _steps(values: list) -> str:
    hits = [v for v in values if v is not None]
    return ", ".join(number_text(v) for v in hits) or "∞"  # (never)


def reading_rows(ab: dict, peer: dict | None = None) -> list[dict[str, Any]]:
    """The A/B's table: per variant run so far (and QDax's own QD-PG), how many seeds
    reached the exit zone and when, the final performance, where the episodes ended,
    coverage, NaN and wall time; a diverged seed is in no mean."""
    rows = []
    for variant, label in READINGS.items():
        mine = [r for r in ab.get("rows", []) if r["variant"] == variant]
        if not mine:
            continue
        lost = [r for r in mine if r["diverged"]]
        rows.append(
            {
                "reading": label,
                "seeds in the exit zone": f"{sum(r['reached_exit'] for r in mine)}/{len(mine)}",
                "steps to the exit zone": _steps([r["steps_to_exit"] for r in mine]),
                "final performance": mean_sd(_numbers(mine, "final_performance")),
                "episodes ending above the upper wall": (
                    f"{np.mean([r['share_above_upper_wall'] for r in mine]):.1%}"
                ),
                # (every seed diverged: "—")
                "coverage": number_text(finite_mean(_numbers(mine, "coverage")), 2),
                "diverged (iteration)": ", ".join(str(r["diverged"]["iteration"]) for r in lost)
                or "none",
                "minutes a pair of seeds": (
                    f"{np.mean([r['pair_wall_seconds'] for r in mine]) / 60:.0f}"
                ),
            }
        )
    if peer and peer.get("rows"):
        p = peer["rows"]
        rows.append(
            {
                "reading": "QDax 0.5.0's own QD-PG (its example's settings)",
                "seeds in the exit zone": f"{sum(r['reached_exit'] for r in p)}/{len(p)}",
                "steps to the exit zone": _steps([r["steps_to_exit"] for r in p]),
                "final performance": mean_sd(np.array([r["final_performance"] for r in p])),
                "episodes ending above the upper wall": "",
                "coverage": f"{np.mean([r['coverage'] for r in p]):.2f} (of its 1,024 cells)",
                "diverged (iteration)": "",
                "minutes a pair of seeds": f"{2 * np.mean([r['wall_seconds'] for r in p]) / 60:.0f}"
                " (one at a time)",
            }
        )
    return rows


def _seeds_and_exits(ab: dict, variant: str) -> tuple[int, int]:
    """How many seeds of ``variant`` the A/B has run, and how many reached the exit zone."""
    mine = [r for r in ab.get("rows", []) if r["variant"] == variant]
    return len(mine), sum(r["reached_exit"] for r in mine)


def reading_exits(ab: dict, variant: str) -> bool:
    """Whether ``variant`` exits by the A/B's rule: at least ``READING_MIN_SEEDS`` seeds
    run, and three quarters of them in the exit zone."""
    seeds, reached = _seeds_and_exits(ab, variant)
    return seeds >= READING_MIN_SEEDS and reached >= exits_needed(seeds)


def reading_needs_more_seeds(ab: dict, variant: str) -> bool:
    """The rule's "more seeds if a verdict is one seed from changing": a reading run on
    exactly ``READING_MIN_SEEDS`` seeds whose count of exits is one short of the verdict
    (2 of 4) gets two more, and is then read on 6 (5 of 6 exit)."""
    seeds, reached = _seeds_and_exits(ab, variant)
    return seeds == READING_MIN_SEEDS and reached == exits_needed(seeds) - 1


# QD-PG's state (``QDPGState``'s fields) as a reader names its parts
STATE_PARTS = {
    "repertoire": "repertoire",
    "q_critic": "quality critic",
    "d_critic": "diversity critic",
    "buffer": "replay buffer",
    "archive": "novelty archive",
    "updates": "update statistics",
}


def divergence_rows(ab: dict) -> list[dict[str, Any]]:
    """For every seed of the A/B that went NaN: when, in which parts, and its critics'
    losses and gradient norms over the iterations before (the first and the last)."""
    rows = []
    for r in ab.get("rows", []):
        if not r["diverged"]:
            continue
        before = r["statistics_before_divergence"] or {}
        span = lambda k: " → ".join(number_text(v, 3) for v in (before[k][0], before[k][-2]))  # noqa: E731
        rows.append(
            {
                "reading": READINGS.get(r["variant"], r["variant"]),
                "seed": r["seed"],
                "NaN at iteration": r["diverged"]["iteration"],
                "parts": ", ".join(STATE_PARTS.get(p, p) for p in r["diverged"]["parts"]),
                "quality critic loss": span("critic_loss_q"),
                "diversity critic loss": span("critic_loss_d"),
                "quality critic gradient norm": span("critic_grad_norm_q"),
                "diversity critic gradient norm": span("critic_grad_norm_d"),
                "actor gradient norm": span("actor_grad_norm"),
            }
        )
    return rows


def published_rows(published: dict) -> list[dict[str, Any]]:
    """The published `paper` Point-Maze run (``bench/ch3_pointmaze_paper.py``): per
    method, the seeds in the exit zone and when, the final performance (Table 3.4's
    Point-Maze column) and coverage, NaN and time."""
    rows = []
    for name, m in published["methods"].items():
        seeds = m["seeds"]
        rows.append(
            {
                "method": name,
                "seeds in the exit zone": (
                    f"{sum(s['steps_to_exit'] is not None for s in seeds)}/{len(seeds)}"
                ),
                "steps to the exit zone": _steps([s["steps_to_exit"] for s in seeds]),
                "final performance": mean_sd(_numbers(seeds, "final_performance")),
                "coverage": f"{finite_mean(_numbers(seeds, 'coverage')):.2f}",
                "s per iteration": f"{m['seconds_per_iteration']:.3f}",
                "wall time (min)": f"{m['wall_seconds'] / 60:.1f}",
            }
        )
    return rows
