"""Chapter 3's evolutionary competitors (Table 3.3): ME-ES, NSR-ES and NSRA-ES, and
QD-PG's sample efficiency against them.

Each evolution strategy (``qdnb.qd.es``) is one entry of the chapter's method
registry (``ch3_qdpg.METHODS``) and runs through the same ``run_environment`` as
QD-PG, on the QD-PG page's environments, episode lengths and policy networks; a
generation plays ``num_perturbations`` perturbed policies (plus the centre, or the
meta-population's centres, or ME-ES's last offspring, in the same batch), so a
method's budget is ``num_steps`` environment steps spread over
``num_steps // (num_perturbations * episode_length)`` generations, and a method
runs until every one of its seeds has reached the goal or the budget is spent
(checked every ``chunk_size`` generations: ``run_environment``'s ``stop_at_goal``).
Steps to the goal are read from every evaluated episode: on Point-Maze the first environment step
at which an episode ended in the exit zone, on Ant-Maze the first at which the best
reward exceeded -10 (Table 3.3).  QD-PG's own result is the QD-PG page's run at the
same scale (``load_or_recompute_qdpg``).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import jax
import numpy as np

from qdnb.chapters.ch3_qdpg import METHODS as CHAPTER_METHODS
from qdnb.chapters.ch3_qdpg import SCALES as QDPG_SCALES
from qdnb.chapters.ch3_qdpg import (
    EnvironmentResult,
    MethodResult,
    QDPGConfig,
    load_or_recompute_qdpg,
    run_environment,
)
from qdnb.core import claims as claim_records
from qdnb.core import dryrun
from qdnb.core.claims import finite_mean
from qdnb.core.names import number_text

EVOLUTION = ("ME-ES", "NSR-ES", "NSRA-ES")  # in Table 3.3's order
# this page's methods: their builders in the chapter's method registry
METHODS = {name: CHAPTER_METHODS[name] for name in EVOLUTION}
ENVIRONMENTS = ("pointmaze", "antmaze")  # Table 3.3 is Ant-Maze's; Point-Maze is where ES is cheap
FACTOR = 10  # the claim: QD-PG needs at least 10× fewer steps than the fastest ES method


@dataclass(frozen=True)
class EvolutionConfig:
    """The evolution page: the QD-PG page's config at the same scale (``tasks``), the
    seeds of every ES method, their perturbations per generation and budgets on
    Point-Maze and Ant-Maze, and the methods run on Ant-Maze (all three on
    Point-Maze)."""

    tasks: QDPGConfig
    num_seeds: int
    num_perturbations: int
    pointmaze_steps: int
    ant_perturbations: int
    antmaze_steps: int
    ant_methods: tuple[str, ...] = EVOLUTION
    chunk_size: int = 10
    ant_seeds: int | None = None  # seeds on Ant-Maze (None: num_seeds)

    def __post_init__(self):
        unknown = set(self.ant_methods) - set(EVOLUTION)
        if unknown:
            raise ValueError(f"unknown methods {sorted(unknown)}; valid: {', '.join(EVOLUTION)}")
        for name in ("num_seeds", "chunk_size", "ant_seeds"):
            n = getattr(self, name)
            if n is not None and n < 1:
                raise ValueError(f"{name}={n} must be at least 1")
        for name in ("num_perturbations", "ant_perturbations"):
            n = getattr(self, name)
            if n < 2 or n % 2:
                raise ValueError(f"{name}={n} must be an even number >= 2 (antithetic pairs)")
        self.es_tasks()  # a budget of less than one generation is refused there

    def methods(self, env_name: str) -> tuple[str, ...]:
        if env_name not in ENVIRONMENTS:
            raise ValueError(f"unknown environment {env_name!r}; valid: {', '.join(ENVIRONMENTS)}")
        return EVOLUTION if env_name == "pointmaze" else self.ant_methods

    def seeds(self, env_name: str) -> int:
        """How many seeds each ES method runs on ``env_name``."""
        self.methods(env_name)  # a clear error on an unknown environment
        if env_name == "pointmaze" or self.ant_seeds is None:
            return self.num_seeds
        return self.ant_seeds

    def es_tasks(self, env_name: str = "pointmaze") -> QDPGConfig:
        """The QD-PG page's tasks with the ES generations and budgets, on this page's
        seeds for ``env_name``."""
        t = self.tasks
        return dataclasses.replace(
            t,
            num_seeds=self.seeds(env_name),
            pointmaze_qdpg_seeds=None,
            chunk_size=self.chunk_size,
            pointmaze=dataclasses.replace(
                t.pointmaze, num_actors=self.num_perturbations, num_steps=self.pointmaze_steps
            ),
            antmaze=dataclasses.replace(
                t.antmaze, num_actors=self.ant_perturbations, num_steps=self.antmaze_steps
            ),
        )


Config = EvolutionConfig


def steps_to_goal(env_name: str, r: MethodResult) -> np.ndarray:
    """Per seed, the environment steps when the goal was first reached (``inf`` if never):
    the exit zone on Point-Maze, a best reward above -10 on Ant-Maze."""
    if env_name == "pointmaze":
        return np.where(np.isnan(r.exit_steps), np.inf, r.exit_steps)
    return np.asarray(r.steps_to_goal())


@dataclass(frozen=True)
class Result:
    qdpg: dict[str, MethodResult]
    qdpg_status: dict[str, str]
    evolution: dict[str, EnvironmentResult]

    def methods(self, env_name: str) -> dict[str, MethodResult]:
        """QD-PG first, then the ES methods run on ``env_name``."""
        return {"QD-PG": self.qdpg[env_name], **self.evolution[env_name].methods}

    def steps(self, env_name: str) -> dict[str, np.ndarray]:
        return {name: steps_to_goal(env_name, r) for name, r in self.methods(env_name).items()}


def run(cfg: EvolutionConfig, scale: str, seed: int, progress: bool = True) -> Result:
    """QD-PG's results (read or recomputed), then every ES method on each environment
    with the QD-PG page's key for that environment."""
    qdpg, status = load_or_recompute_qdpg(cfg.tasks, scale, seed, progress, ENVIRONMENTS)
    evolution = {}
    for i, env_name in enumerate(("pointmaze", "antmaze")):
        tasks, cut = dry_run_tasks(cfg, env_name)
        with cut.counted():
            evolution[env_name] = run_environment(
                tasks,
                env_name,
                jax.random.fold_in(jax.random.PRNGKey(seed), i),  # i: the QD-PG page's order
                progress,
                methods=cfg.methods(env_name),
                stop_at_goal=True,
            )
    return Result(qdpg, status, evolution)


# of the 10,000 a paper generation evaluates on Ant-Maze, in a dry run on a CPU: 100 of them
# take about 30 s a generation on two CPU cores (500 took 134-161 s, 200 took 55-65 s; the
# per-policy time grows by a tenth from 500 to 200), enough side by side to keep the cores
# busy.  A GPU evaluates all 10,000: its rate at a tenth of that batch would not tell.
DRY_RUN_ANT_PERTURBATIONS = 100


def dry_run_tasks(cfg: EvolutionConfig, env_name: str) -> tuple[QDPGConfig, dryrun.BatchCut]:
    """``cfg.es_tasks(env_name)`` and its generations' ``BatchCut``.  In a dry run
    (``qdnb.core.dryrun``) at paper scale one Ant-Maze generation (10,000 policies of
    256x256 units, 3,000 steps each) takes about 20 minutes on two CPU cores, three
    methods an hour: there its perturbations, independent episodes side by side, are cut
    to ``DRY_RUN_ANT_PERTURBATIONS`` (the generations kept as many), and each loop's time
    and memory count ``10,000 / 100`` times (the cut's ``counted``).  Point-Maze's are
    never cut, and a GPU cuts nothing."""
    tasks = cfg.es_tasks(env_name)
    if env_name == "pointmaze":
        return tasks, dryrun.BatchCut(cfg.num_perturbations, cfg.num_perturbations)
    cut = dryrun.cut_batch(
        "Ant-Maze ES perturbations per generation (side by side)",
        cfg.ant_perturbations,
        DRY_RUN_ANT_PERTURBATIONS,
    )
    if cut.kept == cut.full:
        return tasks, cut
    t = tasks.antmaze
    ant = dataclasses.replace(t, num_actors=cut.kept, num_steps=t.num_steps * cut.kept // cut.full)
    return dataclasses.replace(tasks, antmaze=ant), cut


def mean_steps(steps: np.ndarray) -> float:
    """The mean over seeds of steps to the goal (``inf`` when a seed never reached it)."""
    return float(np.mean(steps))


def sample_efficiency(result: Result, env_name: str = "pointmaze") -> tuple[str, bool, str]:
    """The claim on ``env_name``: QD-PG reaches the goal with at least ``FACTOR`` times
    fewer environment steps than the fastest ES method, on the mean over seeds and on
    most of QD-PG's seeds (each against the fastest method's mean)."""
    steps = result.steps(env_name)
    qd = steps.pop("QD-PG")
    fastest = min(steps, key=lambda n: mean_steps(steps[n]))
    target = mean_steps(steps[fastest]) / FACTOR
    holds = bool(
        np.isfinite(mean_steps(qd)) and mean_steps(qd) <= target and np.mean(qd <= target) > 0.5
    )
    numbers = (
        f"QD-PG {', '.join(number_text(v, 3) for v in qd)} steps; fastest ES: {fastest}, "
        f"{', '.join(number_text(v, 3) for v in steps[fastest])} (∞: never reached)"
    )
    claim = f"QD-PG reaches the goal with {FACTOR}× fewer steps than the fastest ES method"
    return claim, holds, numbers


def claim_status(result: Result, holds: bool, env_name: str = "pointmaze") -> str:
    """The claim's status: it cannot show when QD-PG missed the goal on a seed (the claim
    compares steps to the goal, and QD-PG then has none), else it holds or fails."""
    if not np.isfinite(result.steps(env_name)["QD-PG"]).all():
        return claim_records.CANNOT_SHOW
    return claim_records.HOLDS if holds else claim_records.FAILS


def ratio_to_qdpg(result: Result, env_name: str) -> dict[str, float | None]:
    """Per method, its mean steps to the goal over QD-PG's (``None`` when either is
    never reached on some seed)."""
    steps = result.steps(env_name)
    qd = mean_steps(steps["QD-PG"])
    return {
        name: (mean_steps(s) / qd if np.isfinite(qd) and np.isfinite(mean_steps(s)) else None)
        for name, s in steps.items()
    }


def summary_results(cfg: EvolutionConfig, result: Result) -> dict[str, Any]:
    """``results[env][method]``: final performance, steps to the goal (``None`` when never
    reached, per seed and mean), ratio to QD-PG, environment steps; the claim."""
    claim, holds, numbers = sample_efficiency(result)
    status = claim_status(result, holds)
    out: dict[str, Any] = {
        "headline": f"{status}: {claim} on Point-Maze",
        "claims": [claim_records.record("ch3_evolution/sample_efficiency", claim, status, numbers)],
        "claims_held": int(holds),
        "claims_total": 1,
        "claim_numbers": numbers,
        "num_seeds": {env_name: cfg.seeds(env_name) for env_name in ENVIRONMENTS},
        "qdpg_source": dict(result.qdpg_status),
    }
    for env_name in ENVIRONMENTS:
        ratios = ratio_to_qdpg(result, env_name)
        out[env_name] = {}
        for name, r in result.methods(env_name).items():
            s = steps_to_goal(env_name, r)
            out[env_name][name] = {
                "ran": True,
                "final_performance": finite_mean(r.final_performance),
                "final_performance_per_seed": [
                    None if np.isnan(v) else float(v) for v in r.final_performance
                ],
                "steps_to_goal": None if not np.isfinite(mean_steps(s)) else mean_steps(s),
                "steps_to_goal_per_seed": [None if not np.isfinite(v) else float(v) for v in s],
                "ratio_to_qdpg": ratios[name],
                "env_steps": float(r.env_steps.mean()),
            }
        for name in EVOLUTION:
            out[env_name].setdefault(
                name,
                {
                    "ran": False,
                    "final_performance": None,
                    "steps_to_goal": None,
                    "ratio_to_qdpg": None,
                    "env_steps": 0,
                },
            )
    return out


def _scale(name: str, **kw) -> EvolutionConfig:
    return EvolutionConfig(tasks=QDPG_SCALES[name], **kw)


# The page's configs, one per scale (the rule of each is in the notebook's scale cell).
SCALES = {
    "tiny": _scale(
        "tiny",
        num_seeds=1,
        num_perturbations=16,
        pointmaze_steps=5 * 16 * 200,
        ant_perturbations=4,
        antmaze_steps=2 * 4 * 50,
        ant_methods=("ME-ES",),
        chunk_size=5,
    ),
    "small": _scale(
        "small",
        num_seeds=4,
        num_perturbations=1000,
        pointmaze_steps=100_000_000,
        ant_perturbations=100,
        antmaze_steps=500_000,  # 10 generations: the page's time (the notebook's scale cell)
        ant_seeds=1,
    ),
    "paper": _scale(
        "paper",
        num_seeds=5,
        num_perturbations=10_000,
        pointmaze_steps=100_000_000,
        ant_perturbations=10_000,
        antmaze_steps=30_000_000_000,
    ),
}
