"""Chapter 5's evaluation: held-out episodes from fresh initial states, the FLT unrolled
from the first frame against the persistence and mean-frame predictors, and the
diagnosis of its errors; which model (the thesis's FLT or our variant) predicts better
(``best_model``), the one the surprise search scores with.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from functools import cached_property
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from qdnb.core import dryrun
from qdnb.models.lenia import flow_lenia as fl
from qdnb.models.lenia.flt import (
    FLT,
    dry_run_batch,
    frame_errors,
    unroll,
)

# the predictors Figure 5.5 compares, each ``(model, params, episodes, mean_frames) -> frames 1..T``
METHODS = {
    "flt": lambda model, params, truth, mean_frames: unroll(model, params, truth[:, 0]),
    "persistence": lambda model, params, truth, mean_frames: jnp.broadcast_to(
        truth[:, :1], truth[:, 1:].shape
    ),
    "mean_frame": lambda model, params, truth, mean_frames: jnp.broadcast_to(
        mean_frames[1:], truth[:, 1:].shape
    ),
}


@dataclass(frozen=True)
class HeldOut:
    """The evaluation on held-out episodes (Section 5.4): ``errors[predictor]["A" |
    "frame"]`` ``(episodes, T)`` for the predictions of ``x_1 .. x_T`` (the predictors
    of ``METHODS``, ``"flt_teacher_forced"``, the FLT fed the true frames, and
    ``"copy_previous"``, one step of persistence: each true frame copied to the next);
    ``truth`` and ``flt`` the first three episodes' frames; ``drift`` every episode's
    mass drift (episodes on axis 0 everywhere); ``seconds`` the evaluation's wall time."""

    errors: dict[str, dict[str, np.ndarray]]
    truth: np.ndarray
    flt: np.ndarray
    drift: np.ndarray
    seconds: float = 0.0

    @cached_property
    def median(self) -> dict[str, np.ndarray]:
        """Per predictor, the median over episodes of the error on ``A`` at each timestep."""
        return {name: np.median(e["A"], axis=0) for name, e in self.errors.items()}

    @property
    def final(self) -> dict[str, float]:
        """Per predictor, the median final-frame error on ``A``."""
        return {name: float(m[-1]) for name, m in self.median.items()}

    @property
    def beats(self) -> bool:
        """The chapter's check: the FLT's median final-frame error is below both baselines'."""
        final = self.final
        return final["flt"] < final["persistence"] and final["flt"] < final["mean_frame"]

    @property
    def grows(self) -> int:
        """Episodes whose FLT error on ``A`` is larger at ``t = T`` than at ``t = 1``."""
        a = self.errors["flt"]["A"]
        return int(np.sum(a[:, -1] > a[:, 0]))

    @property
    def error_grows(self) -> bool:
        """Section 5.4's claim on one model: its median error on ``A`` larger at ``T`` than
        at ``t = 1``, and larger at ``T`` in most episodes too."""
        median = self.median["flt"]
        return bool(median[-1] > median[0] and self.grows > len(self.drift) / 2)

    @property
    def rise(self) -> float:
        """The median rise of the FLT's error on ``A`` from ``t = 1`` to ``t = T``."""
        a = self.errors["flt"]["A"]
        return float(np.median(a[:, -1] - a[:, 0]))

    def share_below(self, a: str, b: str) -> float:
        """The share of episodes whose final-frame error on ``A`` is lower for ``a`` than ``b``."""
        return float(np.mean(self.errors[a]["A"][:, -1] < self.errors[b]["A"][:, -1]))


def evaluate(
    model: FLT,
    params: Any,
    world: fl.FlowLeniaConfig,
    system: fl.System,
    mean_frames: np.ndarray,
    key: jax.Array,
    episodes: int,
    batch: int = 16,
) -> HeldOut:
    """Simulate ``episodes`` held-out episodes and score the three predictors frame
    by frame: ``errors[predictor]["A" | "frame"]`` ``(episodes, T)`` for the
    predictions of ``x_1 .. x_T`` (``frame_errors``), plus two one-step predictors:
    ``"flt_teacher_forced"``, the FLT fed the true frames (as in training), and
    ``"copy_previous"``, each true frame copied to the next; ``truth`` and ``flt`` hold the
    first three episodes' frames for the figures, ``drift`` every episode's mass drift."""
    if episodes < 1 or batch < 1:
        raise ValueError(f"episodes and batch must be positive, got {episodes} and {batch}")
    start = time.perf_counter()
    mean_frames = jnp.asarray(mean_frames)
    parts: dict[str, list] = {
        "flt": [],
        "persistence": [],
        "mean_frame": [],
        "flt_teacher_forced": [],
        "copy_previous": [],
    }
    truth_kept, flt_kept, drifts = [], [], []
    # a dry run plays the first batches (qdnb.core.dryrun), on a CPU of a cut size
    # (``dry_run_batch``: each counts for the whole batch); the others repeat their scores
    cut = dry_run_batch("held-out episodes per batch (side by side)", batch)
    played = cut.kept
    with cut.counted():
        batches = dryrun.steps("held-out episodes", range(0, episodes, batch), unit="batch")
        for i, first in enumerate(batches):  # ``first``: not the timer's ``start``
            n = min(played, episodes - first)
            truth = fl.frames(fl.simulate_system(system, jax.random.fold_in(key, i), world, played))
            truth = truth[:n]
            drifts.append(np.asarray(fl.mass_drift(truth[..., :1])))
            later = truth[:, 1:]
            preds = {
                name: predict(model, params, truth, mean_frames)
                for name, predict in METHODS.items()
            }
            for name, p in preds.items():
                parts[name].append(frame_errors(p, later))
            parts["flt_teacher_forced"].append(
                frame_errors(model.apply(params, truth[:, :-1]), later)
            )
            parts["copy_previous"].append(frame_errors(truth[:, :-1], later))
            pred = preds["flt"]
            if sum(len(x) for x in truth_kept) < 3:  # keep the first three episodes for the figures
                truth_kept.append(np.asarray(truth[:3]))
                flt_kept.append(np.asarray(pred[:3]))
            batches.step_done(parts["flt"][-1], parts["flt_teacher_forced"][-1])
    # every episode's, or the dry run's first ones repeated
    every = lambda xs: np.concatenate(xs)[np.arange(episodes) % sum(len(x) for x in xs)]
    errors = {
        name: {q: every([np.asarray(p[q]) for p in ps]) for q in ("A", "frame")}
        for name, ps in parts.items()
    }
    return HeldOut(
        errors,
        np.concatenate(truth_kept)[:3],
        np.concatenate(flt_kept)[:3],
        every(drifts),
        time.perf_counter() - start,
    )


@dataclass(frozen=True)
class Diagnosis:
    """How much of an episode's ending a predictor can read, and where the FLT stands
    (the notebook's "Reading the check"):

    - ``replay``: the median final-frame MSE on ``A`` between two simulations of the
      same initial states with other keys; half of it (``floor``) is the error of the
      best possible predictor;
    - ``within_h``: the share of the final frames' variance across initial states
      left within one parameter vector ``h`` (8 vectors x 8 matter patches);
    - ``copy_A``: the final-frame error of copying ``A^{T-1}``;
    - ``p_errors``: one step on ``P`` (per cell and channel) for the FLT fed true
      frames, a copy of ``P^t`` and the mean frame."""

    replay: float
    within_h: float
    copy_A: float
    p_errors: dict[str, float]

    @property
    def floor(self) -> float:
        return self.replay / 2


def diagnose(
    model: FLT,
    params: Any,
    mean_frames: np.ndarray,
    world: fl.FlowLeniaConfig,
    system: fl.System,
    key: jax.Array,
    batch: int,
    replay_key: jax.Array,
    vectors: int = 8,
) -> Diagnosis:
    """``Diagnosis`` on ``batch`` episodes drawn as ``evaluate`` draws its first batch
    from ``key`` (replayed with ``replay_key``), and on ``vectors`` parameter vectors
    times ``vectors`` matter patches."""
    first = fl.frames(fl.simulate_system(system, jax.random.fold_in(key, 0), world, batch))
    again = fl.rollout_batch(
        system, fl.State(A=first[:, 0, ..., :1], P=first[:, 0, ..., 1:]), replay_key, world
    )
    final_A = np.asarray(first[:, -1, ..., :1])
    replay = float(np.median(np.mean((np.asarray(again.A[:, -1]) - final_A) ** 2, axis=(1, 2, 3))))
    # the same h for several matter patches: the variance left within one h
    k_h, k_a = jax.random.split(jax.random.fold_in(key, 1))
    patches = jax.vmap(fl.initial_patches, in_axes=(0, None))
    hs = patches(jax.random.split(k_h, vectors), world)[1]
    matter = patches(jax.random.split(k_a, vectors), world)[0]
    finals = np.stack(
        [
            np.asarray(
                fl.rollout_batch(
                    system, jax.vmap(lambda a: fl.place_patch(a, h, world))(matter), k_a, world
                ).A[:, -1, ..., 0]
            )
            for h in hs
        ]
    )  # (h, patch, H, W)
    across = finals.reshape(-1, *finals.shape[2:]).var(axis=0)
    within_h = float(np.mean(finals.var(axis=1)) / np.mean(across))
    before_last = np.asarray(first[:, -2, ..., :1])
    copy_A = float(np.median(np.mean((before_last - final_A) ** 2, axis=(1, 2, 3))))
    # one step on P: the FLT fed true frames, copying x_t, and the mean frame
    p_true = np.asarray(first[:, 1:, ..., 1:])
    p_flt = np.asarray(model.apply(params, first[:, :-1])[..., 1:])
    p_errors = {
        "FLT, one step": float(np.mean((p_flt - p_true) ** 2)),
        "copy of P^t": float(np.mean((np.asarray(first[:, :-1, ..., 1:]) - p_true) ** 2)),
        "mean frame": float(np.mean((mean_frames[None, 1:, ..., 1:] - p_true) ** 2)),
    }
    return Diagnosis(replay, within_h, copy_A, p_errors)


THESIS_FLT, OUR_FLT = "the thesis's FLT", "our FLT variant"


def best_model(thesis: HeldOut, ours: HeldOut | None) -> str:
    """The model whose median final-frame error on ``A`` is lower (the thesis's on a tie
    or without a variant): the one the surprise search scores surprise with."""
    if ours is not None and ours.final["flt"] < thesis.final["flt"]:
        return OUR_FLT
    return THESIS_FLT
