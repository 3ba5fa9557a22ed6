"""Chapter 3's policy-gradient baselines (Table 3.4): SAC, RND, CEM-RL, P3S-TD3, AGAC
and DIAYN on the QD-PG page's environments and budgets.

Each baseline is one entry of the chapter's method registry (``ch3_qdpg.METHODS``,
its code in ``qdnb.rl``) and runs through the same ``run_environment`` as QD-PG:
the same tasks, networks, replay-buffer sizes, gradient steps per iteration and
episodes per iteration, so the same environment-step budget.  QD-PG's own result
is read from the QD-PG page's run at the same scale (``load_or_recompute_qdpg``),
or recomputed with that page's keys when it is missing or stale.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import jax

from qdnb.chapters.ch3_qdpg import (
    ENVIRONMENTS,
    EnvironmentResult,
    MethodResult,
    QDPGConfig,
    beats,
    build_algorithms,
    load_or_recompute_qdpg,
    method_summaries,
    per_seed,
    run_environment,
)
from qdnb.chapters.ch3_qdpg import METHODS as CHAPTER_METHODS
from qdnb.chapters.ch3_qdpg import SCALES as QDPG_SCALES
from qdnb.core import claims as claim_records
from qdnb.core.claims import finite_mean
from qdnb.core.config import config_hash
from qdnb.core.io import load_summary

BASELINES = ("SAC", "RND", "CEM-RL", "P3S-TD3", "AGAC", "DIAYN")  # in Table 3.4's order
# this page's methods: their builders in the chapter's method registry
METHODS = {name: CHAPTER_METHODS[name] for name in BASELINES}


@dataclass(frozen=True)
class BaselinesConfig:
    """The baselines page: the QD-PG page's config at the same scale (``tasks``: its
    environments, budgets, networks and QD-PG's own seeds), the seeds of every
    baseline on Point-Maze (``num_seeds``) and on the ant mazes (``ant_seeds``, by
    default the same), and the baselines run on the two ant mazes (all six on
    Point-Maze)."""

    tasks: QDPGConfig
    num_seeds: int
    ant_methods: tuple[str, ...] = BASELINES
    ant_seeds: int | None = None

    def __post_init__(self):
        unknown = set(self.ant_methods) - set(BASELINES)
        if unknown:
            raise ValueError(f"unknown baselines {sorted(unknown)}; valid: {', '.join(BASELINES)}")
        for name in ("num_seeds", "ant_seeds"):
            n = getattr(self, name)
            if n is not None and n < 1:
                raise ValueError(f"{name}={n} must be at least 1")

    def methods(self, env_name: str) -> tuple[str, ...]:
        self.tasks.task(env_name)  # a clear error on an unknown environment
        return BASELINES if env_name == "pointmaze" else self.ant_methods

    def seeds(self, env_name: str) -> int:
        """How many seeds each baseline runs on ``env_name``."""
        if env_name == "pointmaze" or self.ant_seeds is None:
            return self.num_seeds
        return self.ant_seeds

    def baseline_tasks(self, env_name: str = "pointmaze") -> QDPGConfig:
        """The tasks with the baselines' seeds on ``env_name`` (QD-PG's own seeds are
        the QD-PG page's)."""
        return dataclasses.replace(
            self.tasks, num_seeds=self.seeds(env_name), pointmaze_qdpg_seeds=None
        )


Config = BaselinesConfig


@dataclass(frozen=True)
class Result:
    """QD-PG's result per environment (and where it came from) and the baselines'."""

    qdpg: dict[str, MethodResult]
    qdpg_status: dict[str, str]
    baselines: dict[str, EnvironmentResult]

    def methods(self, env_name: str) -> dict[str, MethodResult]:
        """QD-PG first, then the baselines run on ``env_name``."""
        return {"QD-PG": self.qdpg[env_name], **self.baselines[env_name].methods}

    @property
    def by_env(self) -> dict[str, EnvironmentResult]:
        """Every environment's result with QD-PG among its methods."""
        return {
            env_name: dataclasses.replace(res, methods=self.methods(env_name))
            for env_name, res in self.baselines.items()
        }


def run(cfg: BaselinesConfig, scale: str, seed: int, progress: bool = True) -> Result:
    """QD-PG's results (read or recomputed), then every baseline on each environment,
    each environment with the QD-PG page's key (so a baseline's seeds start from the
    same keys as QD-PG's and TD3's there)."""
    qdpg, status = load_or_recompute_qdpg(cfg.tasks, scale, seed, progress)
    baselines = {
        env_name: run_environment(
            cfg.baseline_tasks(env_name),
            env_name,
            jax.random.fold_in(jax.random.PRNGKey(seed), i),
            progress,
            methods=cfg.methods(env_name),
        )
        for i, env_name in enumerate(ENVIRONMENTS)
    }
    return Result(qdpg, status, baselines)


def hyperparameters(cfg: BaselinesConfig, env_name: str = "pointmaze") -> dict[str, dict]:
    """Per baseline, the settings it runs with on ``env_name`` (its constructor's
    fields but the environment and network, and its TD3 settings where it has them)."""
    algorithms = build_algorithms(
        cfg.baseline_tasks(env_name), env_name, methods=cfg.methods(env_name)
    )
    out = {}
    for name, algo in algorithms.items():
        fields = {"policy network": tuple(algo.network.layer_sizes[:-1])}
        for f in dataclasses.fields(algo):
            value = getattr(algo, f.name)
            if f.name in ("env", "network"):
                continue
            if dataclasses.is_dataclass(value):
                fields |= {f"{f.name}.{k}": v for k, v in dataclasses.asdict(value).items()}
            else:
                fields[f.name] = value
        out[name] = fields
    return out


_SHARED = "the QD-PG page's setting at this scale (Table 3.2 at paper), shared by every method"
_UNUSED = "not used by this method"
# Where each setting of ``hyperparameters`` comes from: by (method, setting), else by setting.
SOURCES: dict[Any, str] = {
    "policy network": _SHARED,
    "num_episodes": "the QD-PG page's actors per iteration: the same step budget",
    "num_critic_steps": "the QD-PG page's gradient steps per iteration",
    "buffer_size": _SHARED,
    **{f"td3_config.{k}": _SHARED for k in ("gamma", "tau", "batch_size", "critic_hidden")},
    **{f"td3_config.{k}": _SHARED for k in ("critic_lr", "actor_lr", "optimizer")},
    **{
        f"td3_config.{k}": "TD3 (Fujimoto et al. 2018), as Table 3.2"
        for k in ("policy_noise", "noise_clip", "policy_delay", "target_update_interval")
    },
    "td3_config.mutation_lr": "the QD-PG page's mutation rate (QDax's policy-gradient rate)",
    **{
        ("SAC", f"td3_config.{k}"): _UNUSED
        for k in ("policy_noise", "noise_clip", "policy_delay", "mutation_lr")
    },
    **{
        ("DIAYN", f"td3_config.{k}"): _UNUSED
        for k in ("policy_noise", "noise_clip", "policy_delay", "mutation_lr")
    },
    ("SAC", "alpha_lr"): "SAC paper (Haarnoja et al. 2018b), Table 1",
    ("SAC", "initial_alpha"): "the authors' code (log alpha starts at 0)",
    ("SAC", "target_entropy_scale"): "SAC paper, Section 5: target entropy -dim(A)",
    ("DIAYN", "num_skills"): "DIAYN paper and code: 50 skills",
    ("DIAYN", "discriminator_hidden"): "DIAYN code (layer size 300)",
    ("DIAYN", "discriminator_lr"): "DIAYN code",
    ("DIAYN", "alpha_lr"): "DIAYN code: a fixed entropy scale (no tuning)",
    ("DIAYN", "initial_alpha"): "DIAYN code: scale_entropy 0.1",
    ("DIAYN", "target_entropy_scale"): _UNUSED + " (alpha is fixed)",
    ("CEM-RL", "num_actor_steps"): "the QD-PG page's policy-gradient steps per iteration",
    ("CEM-RL", "td3_config.policy_delay"): _UNUSED + " (the critic trains first, then the actors)",
    ("CEM-RL", "td3_config.actor_lr"): _UNUSED + " (actors step at mutation_lr)",
    ("CEM-RL", "td3_config.mutation_lr"): "the QD-PG page's mutation rate (CEM-RL paper: 10⁻³)",
    **{
        ("CEM-RL", f"cem_config.{k}"): "CEM-RL paper and code (sepCEM)"
        for k in ("sigma_init", "epsilon_init", "epsilon_end", "epsilon_decay", "elite_fraction")
    },
    ("CEM-RL", "cem_config.gradient_fraction"): "CEM-RL paper: half the population",
    **{
        (
            "AGAC",
            f"config.{k}",
        ): "AGAC authors' Point-Maze config (agac_torch/configs/point_maze.yaml)"
        for k in (
            "actor_lr",
            "critic_lr",
            "adversary_lr",
            "gae_lambda",
            "clip",
            "agac_c",
            "entropy_coef",
            "value_loss_coef",
            "max_grad_norm",
            "adam_eps",
            "num_epochs",
            "minibatch_size",
            "critic_hidden",
        )
    },
    ("AGAC", "config.gamma"): _SHARED,
    "exploration_noise": "the QD-PG page's TD3 exploration noise (TD3 paper: 0.1)",
    (
        "RND",
        "rnd_config.intrinsic_weight",
    ): "RND paper, Table 5: advantage weights 2 (extrinsic), 1",
    **{
        ("RND", f"rnd_config.{k}"): "RND paper, Table 5"
        for k in ("predictor_lr", "intrinsic_gamma", "predictor_epochs", "num_minibatches")
    },
    ("RND", "rnd_config.predictor_proportion"): "RND paper, Table 5",
    ("RND", "rnd_config.input_clip"): "RND paper, Section 2.4 (observation normalisation)",
    **{
        ("RND", f"rnd_config.{k}"): "ours: an MLP for 2-D descriptors (the paper's is a CNN)"
        for k in ("hidden", "embedding_size")
    },
    ("P3S-TD3", "p3s_config.update_period"): "P3S paper: M = 250 steps, about one episode",
    ("P3S-TD3", "p3s_config.num_recent_episodes"): "P3S paper: E_r = 10",
    ("P3S-TD3", "p3s_config.initial_beta"): "P3S authors' code",
    ("P3S-TD3", "p3s_config.rho"): "P3S paper and code",
    ("P3S-TD3", "p3s_config.d_min"): "P3S paper (the authors' code: 0.04)",
    ("P3S-TD3", "p3s_config.beta_bounds"): "P3S authors' code",
    ("AGAC", "num_iterations"): "the run's iterations: AGAC's bonus decays linearly to 0 over them",
}


def source(method: str, setting: str) -> str:
    """Where ``method``'s ``setting`` comes from (``""`` if nowhere said)."""
    return SOURCES.get((method, setting), SOURCES.get(setting, ""))


def claimed_baselines(result: Result) -> list[str]:
    """The baselines the page's claim compares with: those run on Point-Maze."""
    return [name for name in BASELINES if name in result.methods("pointmaze")]


def claims(result: Result) -> list[tuple[str, bool, str]]:
    """The page's claim on Point-Maze, one row per baseline (``claimed_baselines``):
    QD-PG's final performance beats the baseline's (on the mean over seeds and on most
    of QD-PG's seeds)."""
    pm = result.methods("pointmaze")
    qdpg = pm["QD-PG"].final_performance
    return [
        (
            f"QD-PG beats {name} on Point-Maze's final performance (mean and most seeds)",
            beats(qdpg, pm[name].final_performance),
            f"{per_seed(qdpg)} vs {per_seed(pm[name].final_performance)}",
        )
        for name in claimed_baselines(result)
    ]


def summary_results(cfg: BaselinesConfig, result: Result) -> dict[str, Any]:
    """The page's ``summary.json`` results: the claims, where QD-PG's result came
    from, and ``results[env][method]`` for QD-PG and the six baselines."""
    held = claims(result)
    count = sum(ok for _, ok, _ in held)
    return {
        "headline": f"QD-PG beats {count}/{len(held)} baselines on Point-Maze",
        "claims_held": count,
        "claims_total": len(held),
        "claims": [
            claim_records.record(f"ch3_baselines/{name}", text, ok, numbers)
            for name, (text, ok, numbers) in zip(claimed_baselines(result), held)
        ],
        "num_seeds": {env_name: cfg.seeds(env_name) for env_name in ENVIRONMENTS},
        "qdpg_source": dict(result.qdpg_status),
        **method_summaries(result.by_env, expected=("QD-PG",) + BASELINES),
    }


def qdpg_page_methods(cfg: BaselinesConfig, scale: str, seed: int) -> tuple[dict | None, str]:
    """The QD-PG page's other methods (its ablations, TD3, PGA-ME) as its run's
    ``summary.json`` reports them, ``results[env][method]``, for Table 3.4 complete;
    ``None`` and why when that run is missing, of another seed or of another config."""
    summary = load_summary(scale, "ch3_qdpg")
    if summary is None:
        return None, "no run of the QD-PG page at this scale"
    if summary.get("seed") != seed or summary.get("config_hash") != config_hash(cfg.tasks):
        return None, "the QD-PG page's run used another seed or config"
    results = summary["results"]
    return {
        env_name: {
            name: entry
            for name, entry in results[env_name].items()
            if name != "QD-PG" and entry.get("ran", True)
        }
        for env_name in ENVIRONMENTS
    }, "read from the QD-PG page's run"


def final_table(result: Result) -> dict[str, dict[str, str]]:
    """Per method, per environment: final performance (mean ± std over seeds) and
    coverage of the grid the method's episodes reached."""
    rows: dict[str, dict[str, str]] = {}
    for env_name in ENVIRONMENTS:
        for name, r in result.methods(env_name).items():
            row = rows.setdefault(name, {})
            row[f"{env_name} performance"] = r.performance_text()
            row[f"{env_name} coverage"] = f"{finite_mean(r.coverage):.2f}"
    return rows


def _scale(name: str, num_seeds: int, **kw) -> BaselinesConfig:
    return BaselinesConfig(tasks=QDPG_SCALES[name], num_seeds=num_seeds, **kw)


# The page's configs, one per scale: the QD-PG page's tasks at the same scale (the rule of
# each is in the notebook's scale cell).  small: every baseline on every maze on two seeds,
# at the QD-PG page's budgets (573 s on 2 cores, the seeds split over the cores).
SCALES = {
    "tiny": _scale("tiny", 1, ant_methods=("SAC",)),
    "small": _scale("small", 2),
    "paper": _scale("paper", 5),
}
