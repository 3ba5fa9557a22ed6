"""Chapter 5's experiments: the system the FLT learns, its evaluation against two
baselines, and the surprise search of Section 5.3.2.

- ``pick_system``: the thesis trains on one Flow Lenia system, varying only the
  initial matter and parameter map (Section 5.3.1, footnote 2), and does not say
  which.  Systems are drawn from Table 5.1 in order and the first whose matter
  stays localised (a creature, not a soup) is kept.  The rule looks at the
  simulations only, never at a predictor's error.
- ``evaluate``: held-out episodes from fresh initial states, the FLT unrolled
  from ``x_0`` alone, and the persistence (every frame is ``x_0``) and mean-frame
  (each frame is the training episodes' mean frame at that timestep) predictors
  on the same episodes.
- ``surprise_search``: MAP-Elites over initial states (matter and parameter
  patches), with the FLT's final-frame error on ``A`` as fitness ("surprise") and
  two descriptors of the final pattern (``pattern_descriptors``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from qdnb.lenia import flow_lenia as fl
from qdnb.lenia.flt import FLT, frame_errors, unroll
from qdnb.loops import scan_in_chunks
from qdnb.qd import repertoire as rep_lib
from qdnb.qd.cvt import grid_centroids
from qdnb.qd.variation import gaussian_mutation


def occupancy(A: jax.Array, threshold: float = 0.01) -> jax.Array:
    """Fraction of cells holding more than ``threshold`` matter, ``A`` ``(..., H, W, C)``."""
    return jnp.mean(jnp.sum(A, axis=-1) > threshold, axis=(-2, -1))


@dataclass
class SystemChoice:
    system: fl.System
    index: int  # which candidate was kept (0 = the first drawn)
    occupancy: np.ndarray  # per candidate: mean final occupancy over the probe episodes
    patch_occupancy: float  # the initial patch's share of the grid


def pick_system(key: jax.Array, world: fl.FlowLeniaConfig, candidates: int = 16, probes: int = 4,
                max_growth: float = 4.0) -> SystemChoice:
    """The first of ``candidates`` random systems (Table 5.1) whose ``probes``
    episodes end, on average, with matter on at most ``max_growth`` times the
    area of the initial patch: a localised creature, not matter spread over the
    grid.  If none qualifies, the most localised one."""
    if candidates < 1 or probes < 1:
        raise ValueError(f"candidates and probes must be positive, got {candidates} and {probes}")
    keys = jax.random.split(key, candidates)
    patch = world.patch_size**2 / (world.height * world.width)
    systems, occ = [], []
    for k in keys:
        k_sys, k_sim = jax.random.split(k)
        systems.append(fl.sample_system(k_sys, world))
        occ.append(float(jnp.mean(occupancy(fl.simulate_system(systems[-1], k_sim, world, probes).A[:, -1]))))
    occ = np.asarray(occ)
    ok = np.flatnonzero(occ <= max_growth * patch)
    index = int(ok[0]) if ok.size else int(np.argmin(occ))
    return SystemChoice(systems[index], index, occ, patch)


def evaluate(model: FLT, params: Any, world: fl.FlowLeniaConfig, system: fl.System, mean_frames: np.ndarray,
             key: jax.Array, episodes: int, batch: int = 16) -> dict[str, Any]:
    """Simulate ``episodes`` held-out episodes and score the three predictors frame
    by frame: ``errors[predictor]["A" | "frame"]`` ``(episodes, T)`` for the
    predictions of ``x_1 .. x_T`` (``frame_errors``), plus ``"flt_teacher_forced"``: the FLT fed
    the true frames (one-step predictions, as in training); ``truth`` and ``flt`` hold the
    first three episodes' frames for the figures, ``drift`` every episode's mass drift."""
    if episodes < 1 or batch < 1:
        raise ValueError(f"episodes and batch must be positive, got {episodes} and {batch}")
    mean_frames = jnp.asarray(mean_frames)
    parts: dict[str, list] = {"flt": [], "persistence": [], "mean_frame": [], "flt_teacher_forced": []}
    truth_kept, flt_kept, drifts = [], [], []
    for i, start in enumerate(range(0, episodes, batch)):
        n = min(batch, episodes - start)
        truth = fl.frames(fl.simulate_system(system, jax.random.fold_in(key, i), world, batch))[:n]
        pred = unroll(model, params, truth[:, 0])
        drifts.append(np.asarray(fl.mass_drift(truth[..., :1])))
        later = truth[:, 1:]
        parts["flt"].append(frame_errors(pred, later))
        parts["flt_teacher_forced"].append(frame_errors(model.apply(params, truth[:, :-1]), later))
        parts["persistence"].append(frame_errors(jnp.broadcast_to(truth[:, :1], later.shape), later))
        parts["mean_frame"].append(frame_errors(jnp.broadcast_to(mean_frames[1:], later.shape), later))
        if sum(len(x) for x in truth_kept) < 3:  # keep the first three episodes for the figures
            truth_kept.append(np.asarray(truth[:3]))
            flt_kept.append(np.asarray(pred[:3]))
    errors = {name: {q: np.concatenate([np.asarray(p[q]) for p in ps]) for q in ("A", "frame")}
              for name, ps in parts.items()}
    return {"errors": errors, "truth": np.concatenate(truth_kept)[:3], "flt": np.concatenate(flt_kept)[:3],
            "drift": np.concatenate(drifts)}


# ----- the surprise search (Section 5.3.2) -----

def torus_centre(A: jax.Array) -> jax.Array:
    """Centre of mass of ``A`` ``(H, W, C)`` on the torus (circular means per axis), in cells."""
    mass = jnp.sum(A, axis=-1)
    total = jnp.maximum(jnp.sum(mass), 1e-12)
    centre = []
    for axis, size in ((0, A.shape[0]), (1, A.shape[1])):
        angle = 2 * jnp.pi * jnp.arange(size) / size
        profile = jnp.sum(mass, axis=1 - axis) / total
        mean = jnp.arctan2(jnp.sum(profile * jnp.sin(angle)), jnp.sum(profile * jnp.cos(angle)))
        centre.append(jnp.mod(mean, 2 * jnp.pi) * size / (2 * jnp.pi))
    return jnp.stack(centre)


def torus_offsets(point: jax.Array, height: int, width: int) -> jax.Array:
    """Shortest signed offsets from ``point`` to every cell on the torus, ``(H, W, 2)``."""
    rows = jnp.arange(height)[:, None] - point[0]
    cols = jnp.arange(width)[None, :] - point[1]
    wrap = lambda d, size: (d + size / 2) % size - size / 2
    return jnp.stack(jnp.broadcast_arrays(wrap(rows, height), wrap(cols, width)), axis=-1)


def pattern_descriptors(A0: jax.Array, AT: jax.Array) -> jax.Array:
    """Two simple descriptors of the final pattern, in units of the grid side:
    the displacement of the centre of mass between ``A0`` and ``AT`` and the
    spatial spread of ``AT`` (mass-weighted root-mean-square distance to its
    centre of mass), both on the torus.  ``(2,)``."""
    h, w = AT.shape[:2]
    size = jnp.array([h, w], jnp.float32)
    c0, cT = torus_centre(A0), torus_centre(AT)
    displacement = jnp.linalg.norm((cT - c0 + size / 2) % size - size / 2)
    mass = jnp.sum(AT, axis=-1)
    d2 = jnp.sum(torus_offsets(cT, h, w) ** 2, axis=-1)
    spread = jnp.sqrt(jnp.sum(mass * d2) / jnp.maximum(jnp.sum(mass), 1e-12))
    return jnp.stack([displacement, spread]) / max(h, w)


@dataclass(frozen=True)
class SurpriseSearch:
    """MAP-Elites (``qdnb.qd.repertoire``) over initial states ``(patch_a, patch_p)``
    of the FLT's system; fitness = surprise, the FLT's final-frame MSE on ``A``;
    descriptors = ``pattern_descriptors`` on a ``bins`` grid over
    ``[0, max_displacement] x [min_spread, max_spread]`` (grid-side units;
    descriptors outside are clipped to the border cells).  Offspring are
    Gaussian mutations (``sigma``) of uniformly drawn elites, clipped to ``[0, 1]``."""

    model: FLT
    world: fl.FlowLeniaConfig
    batch_size: int = 32
    sigma: float = 0.1
    bins: tuple[int, int] = (8, 8)
    max_displacement: float = 0.125
    min_spread: float = 0.05
    max_spread: float = 0.25

    @property
    def low(self) -> tuple[float, float]:
        return (0.0, self.min_spread)

    @property
    def high(self) -> tuple[float, float]:
        return (self.max_displacement, self.max_spread)

    def evaluate(self, params: Any, system: fl.System, genotypes: Any, key: jax.Array):
        """Surprise, descriptors and final frames (truth, FLT) of a batch of genotypes."""
        states = jax.vmap(lambda a, p: fl.place_patch(a, p, self.world))(genotypes["a"], genotypes["p"])
        keys = jax.random.split(key, genotypes["a"].shape[0])
        episodes = jax.vmap(lambda st, k: fl.rollout(system, st, k, self.world))(states, keys)
        truth = fl.frames(episodes)
        pred = unroll(self.model, params, truth[:, 0])
        surprise = frame_errors(pred[:, -1], truth[:, -1])["A"]
        desc = jax.vmap(pattern_descriptors)(truth[:, 0, ..., :1], truth[:, -1, ..., :1])
        return surprise, desc, truth[:, -1], pred[:, -1], fl.mass_drift(truth[..., :1])

    def random_genotypes(self, key: jax.Array) -> dict[str, jax.Array]:
        """Initial states as in training: uniform matter and parameters on the patch."""
        p, n = self.world.patch_size, self.batch_size
        ka, kp = jax.random.split(key)
        low, high = self.world.h_range
        return {"a": jax.random.uniform(ka, (n, p, p, self.world.channels)),
                "p": jax.random.uniform(kp, (n, p, p, self.world.kernels), minval=low, maxval=high)}

    def run(self, params: Any, system: fl.System, key: jax.Array, iterations: int, chunk_size: int = 5,
            progress: bool = True) -> tuple[rep_lib.Repertoire, dict[str, np.ndarray]]:
        """``iterations`` MAP-Elites iterations after a random initial batch: the final
        repertoire and, per evaluation (initial batch first), surprise, descriptors
        and mass drift."""
        if iterations < 0:
            raise ValueError(f"iterations must be non-negative, got {iterations}")
        centroids = grid_centroids(self.bins, self.low, self.high)
        k_init, k_eval, key = jax.random.split(key, 3)
        genotypes = self.random_genotypes(k_init)
        low, high = self.world.h_range

        def insert(repertoire, genotypes, key):
            surprise, desc, _, _, drift = self.evaluate(params, system, genotypes, key)
            clipped = jnp.clip(desc, jnp.array(self.low), jnp.array(self.high))
            repertoire, _ = rep_lib.insert(repertoire, genotypes, surprise, clipped)
            return repertoire, {"surprise": surprise, "descriptors": desc, "drift": drift}

        repertoire, first = jax.jit(insert)(rep_lib.init_repertoire(centroids, jax.tree.map(lambda x: x[0], genotypes)),
                                            genotypes, k_eval)

        def one(carry):
            repertoire, key = carry
            key, k_sel, k_mut, k_eval = jax.random.split(key, 4)
            parents = rep_lib.sample(repertoire, k_sel, self.batch_size)
            children = gaussian_mutation(parents, k_mut, self.sigma)
            children = {"a": jnp.clip(children["a"], 0.0, 1.0), "p": jnp.clip(children["p"], low, high)}
            repertoire, record = insert(repertoire, children, k_eval)
            return (repertoire, key), record

        history = {k: np.asarray(v)[None] for k, v in first.items()}
        if iterations:
            (repertoire, _), records = scan_in_chunks(one, (repertoire, key), iterations, chunk_size,
                                                      "surprise search", progress)
            history = {k: np.concatenate([history[k], np.asarray(records[k])]) for k in history}
        return repertoire, {k: v.reshape((-1,) + v.shape[2:]) for k, v in history.items()}
