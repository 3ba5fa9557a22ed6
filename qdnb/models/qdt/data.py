"""Datasets for the Quality-Diversity Transformer (Section 4.4.4 and 4.5.3).

1. ``select_policies`` (Section 4.4.4): split the descriptor space into zones (a
   CVT), let every stored policy play a few episodes, and keep, for each zone,
   the policy whose episodes land in its own zone most often.
2. ``record``: the kept policies play episodes whose observations, actions,
   achieved descriptor and fitness form the dataset (``Trajectories``); the
   conditioning BD of a trajectory is the descriptor it achieved.
3. Pruned datasets for the generalisation experiment: a random fraction of the
   trajectories (interpolation), or every trajectory whose achieved descriptor
   falls in removed regions, "tiles" or "upper" (extrapolation).
"""

from __future__ import annotations

import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from qdnb.core import dryrun
from qdnb.envs.player import Player
from qdnb.qd.cvt import nearest
from qdnb.qd.metrics import grid_cell
from qdnb.qd.repertoire import Repertoire

SOURCES = ("ME", "ME-LS", "PGA-ME", "PGA-ME-LS")  # repertoires a QDT is trained from
NAIVE = "Naive"  # QDT(Naive): every ME-LS policy, no selection
PRUNINGS = ("50%", "30%", "10%", "tiles", "upper")


def seed_repertoire(arrays: dict[str, Any], index: int) -> Repertoire:
    """Seed ``index`` of a stack of repertoires loaded by ``load_repertoires``."""
    return Repertoire(
        genotypes=jax.tree.map(lambda x: jnp.asarray(x[index]), arrays["genotypes"]),
        fitnesses=jnp.asarray(arrays["fitnesses"][index]),
        descriptors=jnp.asarray(arrays["descriptors"][index]),
        centroids=jnp.asarray(arrays["centroids"]),
    )


# ----- Section 4.4.4: one consistent policy per zone -----


@struct.dataclass
class Selection:
    """The outcome of the zone selection: for each kept policy its repertoire
    ``cell``, its ``zone``, the fraction ``hit_rate`` of its selection episodes
    that landed in that zone, and its mean ``fitness`` over them.  ``all_*`` hold
    the same for every stored policy that played (``all_cells``)."""

    cells: np.ndarray
    zones: np.ndarray
    hit_rate: np.ndarray
    fitness: np.ndarray
    all_cells: np.ndarray
    all_hit_rate: np.ndarray
    all_fitness: np.ndarray


def zone_of(zones: jax.Array, descriptors: jax.Array) -> np.ndarray:
    """Index of the nearest zone centroid of each descriptor (any leading shape)."""
    d = np.asarray(descriptors)
    return np.asarray(nearest(jnp.asarray(zones), jnp.asarray(d.reshape(-1, d.shape[-1])))).reshape(
        d.shape[:-1]
    )


def select_policies(
    repertoire: Repertoire, zones: jax.Array, player: Player, num_episodes: int, key: jax.Array
) -> Selection:
    """Section 4.4.4: every stored policy plays ``num_episodes`` episodes; its zone
    is the zone of its stored descriptor; in each zone the policy whose episodes
    land in that zone most often is kept (ties: the higher mean fitness, then
    the lower cell index).  Zones without any stored policy keep nothing."""
    cells = np.flatnonzero(np.asarray(repertoire.filled))
    if cells.size == 0:
        raise ValueError("the repertoire is empty")
    genotypes = jax.tree.map(lambda x: x[cells], repertoire.genotypes)
    ev = player.episodes(num_episodes)(genotypes, key)
    home = zone_of(zones, np.asarray(repertoire.descriptors)[cells])
    hit_rate = np.mean(zone_of(zones, ev.descriptor) == home[:, None], axis=1)
    fitness = np.asarray(jnp.mean(ev.fitness, axis=1))
    order = np.lexsort((np.arange(cells.size), -fitness, -hit_rate, home))  # by zone, best first
    first = order[np.r_[True, home[order][1:] != home[order][:-1]]]
    return Selection(
        cells=cells[first],
        zones=home[first],
        hit_rate=hit_rate[first],
        fitness=fitness[first],
        all_cells=cells,
        all_hit_rate=hit_rate,
        all_fitness=fitness,
    )


# ----- the trajectories -----


@struct.dataclass
class Trajectories:
    """A QDT dataset: ``N`` episodes of ``T`` steps.  ``bd`` is the descriptor each
    episode achieved (its conditioning BD), ``valid`` marks the steps played
    before the episode ended, ``policy`` the repertoire cell that played it."""

    bd: jax.Array  # (N, d)
    obs: jax.Array  # (N, T, O)
    actions: jax.Array  # (N, T, A)
    valid: jax.Array  # (N, T)
    fitness: jax.Array  # (N,)
    policy: jax.Array  # (N,)

    @property
    def size(self) -> int:
        return int(self.bd.shape[0])

    def subset(self, keep: np.ndarray) -> "Trajectories":
        index = (
            np.flatnonzero(np.asarray(keep)) if np.asarray(keep).dtype == bool else np.asarray(keep)
        )
        return jax.tree.map(lambda x: x[index], self)


def record(
    repertoire: Repertoire,
    cells: np.ndarray,
    episodes_per_policy: int,
    player: Player,
    key: jax.Array,
) -> Trajectories:
    """Each policy of ``cells`` plays ``episodes_per_policy`` episodes from random
    initial states (``player`` must be built with ``record=True``)."""
    cells = np.asarray(cells)
    full = episodes_per_policy
    # a dry run records about one chunk of episodes, and the full dataset's size
    episodes_per_policy = dryrun.count(
        f"{player.name} per policy", full, max(1, -(-player.chunk // max(cells.size, 1)))
    )
    genotypes = jax.tree.map(
        lambda x: jnp.repeat(x[cells], episodes_per_policy, axis=0), repertoire.genotypes
    )
    ev = player.play(genotypes, jax.random.split(key, cells.size * episodes_per_policy))
    data = Trajectories(
        bd=ev.descriptor,
        obs=ev.trajectory["obs"],
        actions=ev.trajectory["action"],
        valid=ev.trajectory["valid"],
        fitness=ev.fitness,
        policy=jnp.asarray(np.repeat(cells, episodes_per_policy)),
    )
    if dryrun.active() is not None:
        size = dryrun.tree_bytes(data)
        dryrun.record(
            "data",
            f"{player.name}: dataset",
            bytes=size,
            full_bytes=size * full // episodes_per_policy,
        )
    return data


def naive_episodes_per_policy(num_selected: int, episodes_per_policy: int, num_filled: int) -> int:
    """QDT(Naive) plays every stored ME-LS policy; each plays this many episodes so
    that its dataset is about as large as the selected one (at least one)."""
    return max(1, math.ceil(num_selected * episodes_per_policy / num_filled))


# ----- pruned datasets (Section 4.5.3) -----


def removed_tiles(descriptors: np.ndarray, low, high, tiles: int) -> np.ndarray:
    """The "Tiles" region: split the descriptor space into ``tiles x tiles``
    squares and remove every other one, as the dark squares of a checkerboard
    (square ``(i, j)`` removed when ``i + j`` is odd): half the space, in blocks."""
    cell = np.asarray(
        grid_cell(jnp.asarray(descriptors), (tiles, tiles), low, high)
    )  # i * tiles + j
    return (cell // tiles + cell % tiles) % 2 == 1


def removed_upper(descriptors: np.ndarray, low, high) -> np.ndarray:
    """The "Upper part" region: the second descriptor above the middle of its range."""
    return np.asarray(descriptors)[..., 1] > (low[1] + high[1]) / 2


def removed_region(name: str, descriptors: np.ndarray, low, high, tiles: int) -> np.ndarray:
    """Whether each descriptor lies in the region the pruning ``name`` removes
    (nowhere for the random prunings)."""
    if name == "tiles":
        return removed_tiles(descriptors, low, high, tiles)
    if name == "upper":
        return removed_upper(descriptors, low, high)
    if name in PRUNINGS:
        return np.zeros(np.shape(descriptors)[:-1], bool)
    raise ValueError(f"unknown pruning {name!r}; valid: {', '.join(PRUNINGS)}")


def prune(data: Trajectories, name: str, low, high, tiles: int, key: jax.Array) -> Trajectories:
    """The pruned dataset ``name``: ``"50%"``, ``"30%"``, ``"10%"`` keep that
    fraction of the trajectories, drawn uniformly without replacement; ``"tiles"``
    and ``"upper"`` drop every trajectory whose achieved BD is in the removed
    region.  No trajectory is added elsewhere (as in the thesis)."""
    if name.endswith("%") and name in PRUNINGS:
        n = max(1, round(data.size * float(name[:-1]) / 100))
        return data.subset(np.sort(np.asarray(jax.random.permutation(key, data.size))[:n]))
    return data.subset(~removed_region(name, np.asarray(data.bd), low, high, tiles))


def density(descriptors: np.ndarray, low, high, bins: int) -> np.ndarray:
    """Number of trajectories per square of a ``bins x bins`` grid (rows: second
    descriptor), for the density maps of Figures 4.10 and 4.11."""
    d = np.asarray(descriptors)
    hist, _, _ = np.histogram2d(
        d[:, 0], d[:, 1], bins=bins, range=[[low[0], high[0]], [low[1], high[1]]]
    )
    return hist.T
