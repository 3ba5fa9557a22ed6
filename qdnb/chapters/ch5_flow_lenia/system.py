"""Chapter 5's system (Section 5.3.1): the Flow Lenia system the FLT learns, picked from
Table 5.1's draws by its simulations alone, the gallery of random systems and the P0
comparison.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from qdnb.models.lenia import flow_lenia as fl


def occupancy(A: jax.Array, threshold: float = 0.01) -> jax.Array:
    """Fraction of cells holding more than ``threshold`` matter, ``A`` ``(..., H, W, C)``."""
    return jnp.mean(jnp.sum(A, axis=-1) > threshold, axis=(-2, -1))


@dataclass(frozen=True)
class SystemCriteria:
    """What makes a system worth predicting, measured on probe episodes from
    different random initial states (``world_statistics``):

    - **localised**: the final frames hold matter on at most ``max_growth`` times the
      area of the initial patch (a creature, not matter spread over the grid);
    - **diverse**: at least ``min_diversity`` of the final frames' energy varies
      across initial states (the ending depends on ``x_0``; the mean frame cannot
      explain it);
    - **settled**: over the last ``window`` steps the frame changes, per step, by at
      most ``max_change`` of its energy (a stable pattern, not a "boiling" blob).
    """

    max_growth: float = 4.0
    min_diversity: float = 0.25
    max_change: float = 0.1
    window: int = 5

    def __post_init__(self):
        if not (
            self.max_growth > 0
            and 0 <= self.min_diversity <= 1
            and self.max_change > 0
            and self.window >= 1
        ):
            raise ValueError(
                f"invalid system criteria {self}: max_growth and max_change must be positive, "
                f"min_diversity in [0, 1], window at least 1"
            )


def world_statistics(A: jax.Array, window: int = 5) -> dict[str, float]:
    """Statistics of probe episodes ``A`` ``(probes, T + 1, H, W, C)`` of one system:
    ``occupancy`` (mean final occupancy), ``diversity`` (the mean over cells of the
    variance of ``A^T`` across episodes, over the mean of ``(A^T)^2``) and ``change``
    (the mean squared change of one step over the last ``window`` steps, over the
    mean of ``(A^T)^2``)."""
    A = jnp.sum(A, axis=-1)
    final = A[:, -1]
    energy = jnp.maximum(jnp.mean(final**2), 1e-12)
    step = A[:, -window:] - A[:, -window - 1 : -1]
    return {
        "occupancy": float(jnp.mean(occupancy(final[..., None]))),
        "diversity": float(jnp.mean(jnp.var(final, axis=0)) / energy),
        "change": float(jnp.mean(step**2) / energy),
    }


@dataclass(frozen=True)
class SystemChoice:
    system: fl.System
    index: int  # which candidate was kept (0 = the first drawn)
    statistics: dict[str, np.ndarray]  # per candidate: probe_statistics
    passed: dict[str, np.ndarray]  # per candidate: "localised", "diverse", "settled"
    patch_occupancy: float  # the initial patch's share of the grid
    probe_key: jax.Array  # the key of the kept candidate's probes (its statistics' episodes)


def probe_statistics(
    system: fl.System,
    world: fl.FlowLeniaConfig,
    key: jax.Array,
    probes: int = 8,
    window: int = 5,
    perturbation: float = 1e-3,
) -> dict[str, float]:
    """``world_statistics`` of ``probes`` episodes of ``system`` from random initial
    states, and two more, as mean squared changes of the final frames over the
    mean of ``(A^T)^2``: ``replay``, when the same initial states are simulated
    again with other keys (0 when episodes are deterministic), and
    ``sensitivity``, when every ``A^0`` is perturbed by uniform noise of amplitude
    ``perturbation`` on the matter (near 0: the ending is a smooth function of
    ``x_0``; near twice the diversity: as different as another initial state's)."""
    if probes < 2:
        raise ValueError(
            f"probes must be at least 2 (diversity is a variance across them), got {probes}"
        )
    k_sim, k_noise, k_replay = jax.random.split(key, 3)
    episodes = fl.simulate_system(system, k_sim, world, probes)
    row = world_statistics(episodes.A, window)
    x0 = jax.tree.map(lambda x: x[:, 0], episodes)
    final = episodes.A[:, -1]
    energy = jnp.maximum(jnp.mean(final**2), 1e-12)
    replayed = fl.rollout_batch(system, x0, k_replay, world)
    row["replay"] = float(jnp.mean((replayed.A[:, -1] - final) ** 2) / energy)
    noise = perturbation * jax.random.uniform(k_noise, x0.A.shape) * (x0.A > 0)
    nudged = fl.rollout_batch(system, x0.replace(A=x0.A + noise), k_replay, world)
    row["sensitivity"] = float(jnp.mean((nudged.A[:, -1] - final) ** 2) / energy)
    return row


def pick_system(
    key: jax.Array,
    world: fl.FlowLeniaConfig,
    candidates: int = 16,
    probes: int = 8,
    criteria: SystemCriteria = SystemCriteria(),
) -> SystemChoice:
    """The first of ``candidates`` random systems (Table 5.1) whose ``probes``
    episodes meet every one of ``criteria``; if none does, the one meeting the most,
    the most settled among those.  The rule looks at simulations only, never at a
    predictor's error.  ``statistics`` holds every candidate's
    ``probe_statistics``; ``replay`` and ``sensitivity`` are for the record, not
    criteria."""
    if candidates < 1:
        raise ValueError(f"candidates must be positive, got {candidates}")
    patch = world.patch_size**2 / (world.height * world.width)
    systems, rows, probe_keys = [], [], []
    for k in jax.random.split(key, candidates):
        k_sys, k_probe = jax.random.split(k)
        probe_keys.append(k_probe)
        systems.append(fl.sample_system(k_sys, world))
        rows.append(probe_statistics(systems[-1], world, k_probe, probes, criteria.window))
    stats = {name: np.array([r[name] for r in rows]) for name in rows[0]}
    passed = {
        "localised": stats["occupancy"] <= criteria.max_growth * patch,
        "diverse": stats["diversity"] >= criteria.min_diversity,
        "settled": stats["change"] <= criteria.max_change,
    }
    count = sum(v.astype(int) for v in passed.values())
    ok = np.flatnonzero(count == len(passed))
    if ok.size:
        index = int(ok[0])
    else:
        best = np.flatnonzero(count == count.max())
        index = int(best[np.argmin(stats["change"][best])])
    return SystemChoice(systems[index], index, stats, passed, patch, probe_keys[index])


@dataclass(frozen=True)
class Gallery:
    """Random systems (Table 5.1), each from its own random initial state: ``A``
    ``(systems, T + 1, H, W)`` and the largest relative change of mass along them."""

    systems: fl.System
    A: np.ndarray
    drift: float


def random_gallery(key: jax.Array, world: fl.FlowLeniaConfig, systems: int) -> Gallery:
    """``systems`` random systems from random initial states (``flow_lenia.simulate_batch``)."""
    drawn, episodes = fl.simulate_batch(key, world, systems)
    drift = float(np.asarray(fl.mass_drift(episodes.A)).max())
    return Gallery(drawn, np.asarray(episodes.A[..., 0]), drift)


P0_RULES = ("patch", "cell")  # one parameter vector for the whole patch, or one per cell


@dataclass(frozen=True)
class P0Comparison:
    """The two readings of Section 5.3.1's initial parameter map on one system:
    per rule, ``probe_statistics`` and the final frames ``(examples, H, W)`` of the
    same matter patches."""

    statistics: dict[str, dict[str, float]]
    finals: dict[str, np.ndarray]

    @property
    def sensitivity_ratio(self) -> float:
        """How many times more a small nudge of ``A^0`` moves the ending with one
        vector per cell than with one per patch."""
        patch = max(self.statistics["patch"]["sensitivity"], 1e-12)
        return self.statistics["cell"]["sensitivity"] / patch


def compare_p0(
    choice: SystemChoice,
    world: fl.FlowLeniaConfig,
    key: jax.Array,
    probes: int,
    window: int = 5,
    examples: int = 4,
) -> P0Comparison:
    """``probe_statistics`` of the kept system under each rule of ``P0_RULES``, on the
    probes its choice was made on (``choice.probe_key``: the row of the world's own rule
    repeats the kept candidate's statistics), and the final frames of ``examples``
    episodes from the initial keys of ``fold_in(key, 1)``, the same for both rules."""
    statistics, finals = {}, {}
    for rule in P0_RULES:
        w_rule = dataclasses.replace(world, p0=rule)
        statistics[rule] = probe_statistics(choice.system, w_rule, choice.probe_key, probes, window)
        episodes = fl.simulate_system(choice.system, jax.random.fold_in(key, 1), w_rule, examples)
        finals[rule] = np.asarray(episodes.A[:, -1, ..., 0])
    return P0Comparison(statistics, finals)
