"""Chapter 5's surprise search (Section 5.3.2): MAP-Elites over initial states with the
FLT's final-frame error as fitness and two descriptors of the final pattern.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from functools import cached_property
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from qdnb.core.evaluation import Evaluation
from qdnb.core.loops import scan_in_chunks
from qdnb.models.lenia import flow_lenia as fl
from qdnb.models.lenia.flt import (
    FLT,
    frame_errors,
    unroll,
)
from qdnb.qd import repertoire as rep_lib
from qdnb.qd.cvt import grid_centroids
from qdnb.qd.map_elites import MapElites
from qdnb.qd.variation import gaussian_mutation


def spearman(x: np.ndarray, y: np.ndarray) -> float:
    """Spearman's rank correlation (no ties expected: continuous values)."""
    rank = lambda v: np.argsort(np.argsort(v))
    return float(np.corrcoef(rank(x), rank(y))[0, 1])


def centre_of_mass(A: jax.Array, torus: bool = False) -> jax.Array:
    """Centre of mass of ``A`` ``(H, W, C)`` in cells: the mass-weighted mean position,
    or on a torus the circular mean per axis."""
    mass = jnp.sum(A, axis=-1)
    total = jnp.maximum(jnp.sum(mass), 1e-12)
    centre = []
    for axis, size in ((0, A.shape[0]), (1, A.shape[1])):
        profile = jnp.sum(mass, axis=1 - axis) / total
        if torus:
            angle = 2 * jnp.pi * jnp.arange(size) / size
            mean = jnp.arctan2(jnp.sum(profile * jnp.sin(angle)), jnp.sum(profile * jnp.cos(angle)))
            centre.append(jnp.mod(mean, 2 * jnp.pi) * size / (2 * jnp.pi))
        else:
            centre.append(jnp.sum(profile * jnp.arange(size)))
    return jnp.stack(centre)


def signed(d: jax.Array, size: int, torus: bool) -> jax.Array:
    """A signed offset ``d`` along an axis of ``size`` cells: itself, or on a torus the
    shortest one, in ``[-size / 2, size / 2)``."""
    return (d + size / 2) % size - size / 2 if torus else d


def offsets(point: jax.Array, height: int, width: int, torus: bool = False) -> jax.Array:
    """Signed offsets from ``point`` to every cell (the shortest ones on a torus), ``(H, W, 2)``."""
    rows = signed(jnp.arange(height)[:, None] - point[0], height, torus)
    cols = signed(jnp.arange(width)[None, :] - point[1], width, torus)
    return jnp.stack(jnp.broadcast_arrays(rows, cols), axis=-1)


def pattern_descriptors(A0: jax.Array, AT: jax.Array, torus: bool = False) -> jax.Array:
    """Two simple descriptors of the final pattern, in units of the grid side:
    the displacement of the centre of mass between ``A0`` and ``AT`` and the
    spatial spread of ``AT`` (mass-weighted root-mean-square distance to its
    centre of mass), on a walled grid or a torus.  ``(2,)``."""
    h, w = AT.shape[:2]
    c0, cT = centre_of_mass(A0, torus), centre_of_mass(AT, torus)
    displacement = jnp.hypot(signed(cT[0] - c0[0], h, torus), signed(cT[1] - c0[1], w, torus))
    mass = jnp.sum(AT, axis=-1)
    d2 = jnp.sum(offsets(cT, h, w, torus) ** 2, axis=-1)
    spread = jnp.sqrt(jnp.sum(mass * d2) / jnp.maximum(jnp.sum(mass), 1e-12))
    return jnp.stack([displacement, spread]) / max(h, w)


@dataclass(frozen=True)
class SearchResult:
    """The surprise search's outcome: the final ``repertoire``; ``history``, per
    evaluation (the random initial batch first), ``surprise``, ``descriptors`` (raw)
    and ``drift``; every elite replayed once more with another key, per cell (NaN or
    zero where empty): its surprise, the true final frame ``A^T`` and the FLT's."""

    repertoire: rep_lib.Repertoire
    history: dict[str, np.ndarray]
    batch_size: int
    replayed: np.ndarray  # (cells,)
    final_truth: np.ndarray  # (cells, H, W)
    final_flt: np.ndarray  # (cells, H, W)
    seconds: float

    @property
    def filled(self) -> np.ndarray:
        return np.asarray(self.repertoire.filled)

    @property
    def elites(self) -> np.ndarray:
        """The filled cells' indices."""
        return np.flatnonzero(self.filled)

    @property
    def elite_surprise(self) -> np.ndarray:
        """The stored surprise of every cell (meaningless where empty)."""
        return np.asarray(self.repertoire.fitnesses)

    @property
    def evaluations(self) -> int:
        return len(self.history["surprise"])

    @property
    def random_batch(self) -> np.ndarray:
        """The surprise of the first, random, batch of initial states."""
        return self.history["surprise"][: self.batch_size]

    @property
    def best(self) -> float:
        return float(np.nanmax(self.history["surprise"]))

    @property
    def replay_gap(self) -> float:
        """The largest difference between an elite's stored and replayed surprise."""
        e = self.elites
        return float(np.max(np.abs(self.replayed[e] - self.elite_surprise[e])))

    @cached_property
    def correlations(self) -> dict[str, float]:
        """Spearman's rank correlation of every evaluation's surprise with each descriptor."""
        desc, surprise = self.history["descriptors"], self.history["surprise"]
        names = ("centre-of-mass displacement", "spread")
        return {name: spearman(desc[:, i], surprise) for i, name in enumerate(names)}

    def extremes(self, k: int = 3) -> dict[str, np.ndarray]:
        """The cells of the ``k`` most and the ``k`` least surprising elites (never the
        same elite twice)."""
        surprise = np.where(self.filled, self.elite_surprise, np.inf)
        order = np.argsort(surprise)[: self.elites.size]  # filled cells, least first
        most = order[::-1][:k]
        least = np.array([c for c in order if c not in most][:k], dtype=int)
        return {"most surprising": most, "least surprising": least}


@dataclass(frozen=True)
class SurpriseSearch:
    """MAP-Elites (``qdnb.qd.map_elites.MapElites``) over initial states ``(patch_a, patch_p)``
    of the FLT's system (``patch_p`` one vector or one per cell, by the world's ``p0``); fitness =
    surprise, the FLT's final-frame MSE on ``A``;
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
        states = jax.vmap(lambda a, p: fl.place_patch(a, p, self.world))(
            genotypes["a"], genotypes["p"]
        )
        # left split over the devices: the FLT's unroll and the descriptors run split too
        truth = fl.frames(fl.rollout_batch(system, states, key, self.world, split=True))
        pred = unroll(self.model, params, truth[:, 0])
        surprise = frame_errors(pred[:, -1], truth[:, -1])["A"]
        torus = self.world.border == "torus"
        desc = jax.vmap(lambda a0, aT: pattern_descriptors(a0, aT, torus))(
            truth[:, 0, ..., :1], truth[:, -1, ..., :1]
        )
        return surprise, desc, truth[:, -1], pred[:, -1], fl.mass_drift(truth[..., :1])

    def random_genotypes(self, key: jax.Array, n: int | None = None) -> dict[str, jax.Array]:
        """``n`` (default ``batch_size``) initial states as in training
        (``flow_lenia.initial_patches``): the matter patch and the parameters by the
        world's ``p0`` rule."""
        a, p = jax.vmap(fl.initial_patches, in_axes=(0, None))(
            jax.random.split(key, self.batch_size if n is None else n), self.world
        )
        return {"a": a, "p": p}

    def map_elites(self, params: Any, system: fl.System) -> MapElites:
        """The search as a ``MapElites``: its scoring function plays the system and
        scores the FLT's surprise (descriptors clipped to the grid's box; the raw
        ones and the mass drift ride in ``Evaluation.extra``), its variation is the
        clipped Gaussian mutation."""
        low, high = self.world.h_range

        def score(genotypes: Any, key: jax.Array) -> Evaluation:
            surprise, desc, _, _, drift = self.evaluate(params, system, genotypes, key)
            clipped = jnp.clip(desc, jnp.array(self.low), jnp.array(self.high))
            length = jnp.full(surprise.shape, self.world.steps)
            return Evaluation(
                fitness=surprise,
                descriptor=clipped,
                length=length,
                extra={"descriptors": desc, "drift": drift},
            )

        def mutate(parents: Any, key: jax.Array) -> Any:
            children = gaussian_mutation(parents, key, self.sigma)
            return {"a": jnp.clip(children["a"], 0.0, 1.0), "p": jnp.clip(children["p"], low, high)}

        return MapElites(
            centroids=grid_centroids(self.bins, self.low, self.high),
            batch_size=self.batch_size,
            scoring_fn=score,
            init_fn=self.random_genotypes,
            variation_fn=mutate,
        )

    def run(
        self,
        params: Any,
        system: fl.System,
        key: jax.Array,
        iterations: int,
        chunk_size: int = 5,
        progress: bool = True,
    ) -> SearchResult:
        """``iterations`` MAP-Elites iterations after a random initial batch, then every
        elite replayed with another key (``fold_in(key, 1)``): the world is
        deterministic, so what MAP-Elites keeps must be the initial state's surprise,
        not a lucky simulation's."""
        if iterations < 0:
            raise ValueError(f"iterations must be non-negative, got {iterations}")
        start = time.perf_counter()
        me = self.map_elites(params, system)
        state, evs = scan_in_chunks(
            me.step, jax.jit(me.start)(key), iterations + 1, chunk_size, "surprise search", progress
        )
        history = {"surprise": evs.fitness, **evs.extra}
        history = {k: np.asarray(v).reshape((-1,) + v.shape[2:]) for k, v in history.items()}
        repertoire = state.repertoire
        cells = repertoire.fitnesses.shape[0]
        replayed = np.full(cells, np.nan, np.float32)
        shape = (cells, self.world.height, self.world.width)
        final_truth, final_flt = np.zeros(shape, np.float32), np.zeros(shape, np.float32)
        elites = np.flatnonzero(np.asarray(repertoire.filled))
        # the elites replayed in batches of the search's size (the last one padded with its
        # first elite), by the search's jitted evaluation: the same program, the same rounding
        evaluate = jax.jit(self.evaluate)
        for i in range(0, elites.size, self.batch_size):
            part = elites[i : i + self.batch_size]
            padded = np.concatenate([part, np.full(self.batch_size - part.size, part[0])])
            genotypes = jax.tree.map(lambda x: x[padded], repertoire.genotypes)
            surprise, _, truth, pred, _ = evaluate(
                params, system, genotypes, jax.random.fold_in(key, 1)
            )
            n = part.size
            replayed[part] = np.asarray(surprise)[:n]
            final_truth[part] = np.asarray(truth[:n, ..., 0])
            final_flt[part] = np.asarray(pred[:n, ..., 0])
        seconds = time.perf_counter() - start
        return SearchResult(
            repertoire, history, self.batch_size, replayed, final_truth, final_flt, seconds
        )
