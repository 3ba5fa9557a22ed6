"""The QDT experiment on one environment (Sections 4.4.4 and 4.5.1-4.5.5): the accuracy
experiment of the repertoires and of the policies the zone selection keeps, the datasets
from their episodes, each QDT (and each pruned dataset's, for the generalisation
experiment) trained on a budget of gradient steps, then conditioned on goals and
evaluated in closed loop.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import jax
import jax.numpy as jnp
import numpy as np

from qdnb.chapters.ch4_qdt.results import EnvironmentResult
from qdnb.chapters.ch4_qdt.settings import CLAIM_SOURCES
from qdnb.chapters.ch4_reproducibility import ReproducibilityConfig
from qdnb.core import dryrun
from qdnb.core.loops import map_concurrently
from qdnb.core.sharding import device_memory_bytes
from qdnb.envs.player import Player
from qdnb.models.qdt.data import (
    NAIVE,
    PRUNINGS,
    SOURCES,
    Selection,
    Trajectories,
    naive_episodes_per_policy,
    prune,
    record,
    removed_region,
    seed_repertoire,
    select_policies,
)
from qdnb.models.qdt.evaluate import (
    Targets,
    demonstrator_targets,
    goal_scores,
    imitation,
    play,
    rollout_chunks,
)
from qdnb.models.qdt.model import QDT, init_params
from qdnb.models.qdt.train import conditioning_gap, fit, make_train_step
from qdnb.nets.mlp import MLP
from qdnb.nets.transformer import make_optimizer
from qdnb.qd.cvt import cvt_centroids
from qdnb.qd.low_spread import accuracy

if TYPE_CHECKING:
    from qdnb.chapters.ch4_qdt.settings import QDTConfig, QDTTask


def untrained_run(cfg: QDTConfig, num_goals: int, num_zones: int) -> dict[str, Any]:
    """The record of a QDT that could not be trained, its dataset empty (at `tiny`, a
    generalisation pruning can remove every trajectory of a repertoire that sits in
    one region): the shapes of a trained one's, its scores NaN, ``dataset_size`` 0
    and ``best_step`` 0, so that tables show the gap and the claims count it as not
    holding."""
    evaluations = np.arange(cfg.eval_every, cfg.train_steps + 1, cfg.eval_every)
    nan = lambda *shape: np.full(shape, np.nan)
    return {
        "steps": evaluations,
        "avg_distance_curve": nan(evaluations.size),
        "max_fitness_curve": nan(evaluations.size),
        "loss": nan(evaluations.size),
        "best_step": 0,
        "avg_distance": np.nan,
        "avg_spread": np.nan,
        "distance": nan(num_goals),
        "spread": nan(num_goals),
        "dataset_size": 0,
        "seconds": 0.0,
        "heldout_mse": np.nan,
        "shuffled_mse": np.nan,
        "imitation": nan(num_zones),
    }


def qdt_model(cfg: QDTConfig, env) -> QDT:
    """The chapter's QDT for ``env`` (Table 4.3 at ``paper``), with the config's reading
    of the head, the initialisation and the BD's scaling."""
    return QDT(
        env.action_size,
        env.episode_length,
        cfg.embed_dim,
        cfg.num_layers,
        cfg.num_heads,
        cfg.dropout,
        head=cfg.head,
        init_scheme=cfg.init_scheme,
        bd_box=(tuple(env.descriptor_low), tuple(env.descriptor_high)) if cfg.bd_scaling else None,
    )


def num_seeds_of(repertoires: dict[str, Any]) -> int:
    return min(int(np.shape(r["fitnesses"])[0]) for r in repertoires.values())


DRY_RUN_GOALS = 10  # at most, of a QDT evaluation's goals: 100 of the 1,000 paper rollouts


def goals_in_a_dry_run(num_goals: int) -> int:
    """The goals a dry run plays: the largest divisor of ``num_goals`` not above
    ``DRY_RUN_GOALS`` (its scores are repeated for the others)."""
    return max(d for d in range(1, DRY_RUN_GOALS + 1) if num_goals % d == 0)


@dataclass(frozen=True)
class Setting:
    """What the experiments on one environment share: its ``task`` settings, the
    environment, the selection ``zones`` and the evaluation ``goals`` (their own CVTs
    of the BD box ``low``, ``high``), the players of test and of recorded episodes,
    and the key of the goals and of the seeds."""

    task: QDTTask
    env: Any
    zones: jax.Array
    goals: jax.Array
    low: tuple[float, ...]
    high: tuple[float, ...]
    player: Player
    recorder: Player
    k_goals: jax.Array
    k_seeds: jax.Array


def setting(
    cfg: QDTConfig, repro_cfg: ReproducibilityConfig, env_name: str, key: jax.Array
) -> Setting:
    task = cfg.task(env_name)
    env = repro_cfg.make_env(env_name)
    network = MLP(repro_cfg.policy_hidden + (env.action_size,))
    low, high = env.descriptor_low, env.descriptor_high
    k_zones, k_goals, k_seeds = jax.random.split(key, 3)
    zones = cvt_centroids(k_zones, task.zones, low, high, cfg.cvt_samples, cfg.cvt_iterations)
    goals = cvt_centroids(k_goals, task.goals, low, high, cfg.cvt_samples, cfg.cvt_iterations)
    player = Player(env, network, chunk=repro_cfg.env_batch, name=f"{env_name} test episodes")
    recorder = Player(
        env, network, chunk=repro_cfg.env_batch, record=True, name=f"{env_name} dataset episodes"
    )
    return Setting(task, env, zones, goals, low, high, player, recorder, k_goals, k_seeds)


def demonstrations(
    cfg: QDTConfig, where: Setting, repertoire: Any, k_sel: jax.Array, k_rec: jax.Array
) -> tuple[Selection, Trajectories, Trajectories, Targets]:
    """Section 4.4.4 on one repertoire: the zone selection, the dataset its kept
    policies play, ``heldout_episodes`` fresh episodes of each (the held-out error's)
    and each demonstrator's own BD (``demonstrator_targets``, the imitation test's)."""
    task = where.task
    sel = select_policies(repertoire, where.zones, where.player, task.selection_episodes, k_sel)
    data = record(repertoire, sel.cells, task.episodes_per_policy, where.recorder, k_rec)
    heldout = record(
        repertoire, sel.cells, cfg.heldout_episodes, where.recorder, jax.random.fold_in(k_rec, 1)
    )
    targets = demonstrator_targets(data, sel, task.zones, (where.low, where.high))
    return sel, data, heldout, targets


def run_environment(
    cfg: QDTConfig,
    repro_cfg: ReproducibilityConfig,
    env_name: str,
    repertoires: dict[str, Any],
    key: jax.Array,
    progress: bool = True,
) -> EnvironmentResult:
    """Every experiment of the chapter on ``env_name``.  ``repertoires[method]``
    are the Chapter 4 repertoires (stacked over its seeds); QDT seed ``i`` uses
    repertoire seed ``i`` (cycling when the Chapter 4 run has fewer seeds)."""
    where = setting(cfg, repro_cfg, env_name, key)
    task, env, zones, goals = where.task, where.env, where.zones, where.goals
    player, low, high, k_goals = where.player, where.low, where.high, where.k_goals
    model = qdt_model(cfg, env)
    # a dry run plays some of the goals, each independent of the others, and counts its
    # time for all of them (qdnb.core.dryrun)
    played = dryrun.count(
        f"{env_name} QDT evaluation goals", len(goals), goals_in_a_dry_run(len(goals))
    )
    # the goals played in groups when their rollouts' cache would crowd the device's memory
    chunks = rollout_chunks(model, played, cfg.eval_episodes, device_memory_bytes())
    play_goals = jax.jit(
        lambda params, k: play(
            env, model, params, goals[:played], k, cfg.eval_episodes, chunks=chunks
        )
    )
    shapes = jax.eval_shape(  # (a dry run compiles it before timing it)
        lambda k: (init_params(model, k, env.descriptor_size, env.observation_size), k),
        k_goals,
    )
    play_goals = dryrun.compiled(f"{env_name} QDT rollouts: compilation", play_goals, *shapes)
    # the demonstrators' own BDs, one target per zone (padded: one compilation)
    play_targets = jax.jit(
        lambda params, targets, k: play(env, model, params, targets, k, cfg.eval_episodes)
    )
    step = make_train_step(
        model, make_optimizer(cfg.learning_rate)
    )  # one compilation for every dataset
    removed = {
        name: removed_region(name, np.asarray(goals), low, high, cfg.tiles) for name in PRUNINGS
    }

    def train(data, heldout, targets, k_train, k_eval, desc):
        if data.size == 0:  # a pruning that removed every trajectory: nothing to learn from
            return untrained_run(cfg, len(goals), task.zones)

        def evaluate(params, step_done):
            s = goal_scores(goals[:played], play_goals(params, k_eval))
            s = {k: np.tile(v, len(goals) // played) for k, v in s.items()}  # (a dry run's)
            return {
                "avg_distance": float(s["distance"].mean()),
                "avg_spread": float(s["spread"].mean()),
                "max_fitness": float(s["fitness"].max()),
                "distance": s["distance"],
                "spread": s["spread"],
            }

        start = time.time()
        res = fit(
            model,
            data,
            k_train,
            cfg.train_steps,
            cfg.batch_size,
            cfg.learning_rate,
            cfg.eval_every,
            evaluate,
            step=step,
            progress=progress,
            desc=desc,
            program=f"{env_name} QDT rollouts",
            evaluation_share=len(goals) / played,
        )
        best = next(e for e in res.evaluations if e["step"] == res.best_step)
        gap = conditioning_gap(model, res.params, heldout, k_eval)
        return {
            "steps": np.array([e["step"] for e in res.evaluations]),
            "avg_distance_curve": np.array([e["avg_distance"] for e in res.evaluations]),
            "max_fitness_curve": np.array([e["max_fitness"] for e in res.evaluations]),
            "loss": np.array(res.losses),
            "best_step": res.best_step,
            "avg_distance": best["avg_distance"],
            "avg_spread": best["avg_spread"],
            "distance": best["distance"],
            "spread": best["spread"],
            "dataset_size": data.size,
            "seconds": time.time() - start,
            "heldout_mse": gap["heldout_mse"],
            "shuffled_mse": gap["shuffled_mse"],
            "imitation": imitation(targets, play_targets(res.params, targets.padded, k_eval)),
            "params": res.params,  # (kept for seed 0's QDT(ME-LS) only: the page watches it)
        }

    per_seed = []
    num_rep_seeds = num_seeds_of(repertoires)
    # a dry run trains the first seed only, which stands for all of them (each seed's work
    # is the same); the others repeat its results: qdnb.core.dryrun
    seeds_run = dryrun.count(f"{env_name} QDT seeds", cfg.num_seeds, 1)
    with dryrun.repeats(cfg.num_seeds / seeds_run):
        for i in range(seeds_run):
            k_sel, k_rec, k_acc, k_train, k_eval, k_prune = jax.random.split(
                jax.random.fold_in(where.k_seeds, i), 6
            )
            full = i < cfg.num_full_seeds
            sources = SOURCES if full else CLAIM_SOURCES
            reps = {m: seed_repertoire(repertoires[m], i % num_rep_seeds) for m in sources}
            seed: dict[str, Any] = {
                "repertoire": {},
                "selection": {},
                "teachers": {},
                "datasets": {},
                "qdt": {},
                "generalization": {},
                "full": full,
            }
            for m in sources:  # Section 4.5.2: the stored policy nearest to each goal
                acc = accuracy(reps[m], goals, player.episodes(cfg.eval_episodes), k_acc)
                seed["repertoire"][m] = {
                    "distance": np.asarray(acc.distance),
                    "spread": np.asarray(acc.spread),
                    "filled": int(np.sum(np.asarray(reps[m].filled))),
                }
            data, heldout, targets = {}, {}, {}
            for m in sources:  # Section 4.4.4
                sel, data[m], heldout[m], targets[m] = demonstrations(
                    cfg, where, reps[m], k_sel, k_rec
                )
                seed["selection"][m] = sel
                teachers = reps[m].replace(
                    fitnesses=jnp.full_like(reps[m].fitnesses, -jnp.inf)
                    .at[sel.cells]
                    .set(reps[m].fitnesses[sel.cells])
                )  # only the kept policies: the QDT's demonstrators
                acc = accuracy(teachers, goals, player.episodes(cfg.eval_episodes), k_acc)
                seed["teachers"][m] = {
                    "distance": np.asarray(acc.distance),
                    "spread": np.asarray(acc.spread),
                    "imitation": targets[m].distance,
                }
            if full:  # QDT(Naive): every ME-LS policy; its diagnostics on ME-LS's demonstrators
                every = np.flatnonzero(np.asarray(reps["ME-LS"].filled))
                naive_epp = naive_episodes_per_policy(
                    seed["selection"]["ME-LS"].cells.size, task.episodes_per_policy, every.size
                )
                data[NAIVE] = record(reps["ME-LS"], every, naive_epp, where.recorder, k_rec)
                heldout[NAIVE], targets[NAIVE] = heldout["ME-LS"], targets["ME-LS"]
                seed["naive_episodes_per_policy"] = naive_epp
            for name in data:
                seed["qdt"][name] = train(
                    data[name],
                    heldout[name],
                    targets[name],
                    k_train,
                    k_eval,
                    f"{env_name} seed {i} QDT({name})",
                )
            kept = {name: r.pop("params", None) for name, r in seed["qdt"].items()}
            seed["watched"] = kept.get("ME-LS") if i == 0 else None
            pruned = (
                {
                    name: prune(
                        data["ME-LS"], name, low, high, cfg.tiles, jax.random.fold_in(k_prune, j)
                    )
                    for j, name in enumerate(PRUNINGS)
                }
                if full
                else {}
            )
            for name in pruned:
                res = train(
                    pruned[name],
                    heldout["ME-LS"],
                    targets["ME-LS"],
                    k_train,
                    k_eval,
                    f"{env_name} seed {i} QDT(ME-LS, {name})",
                )
                res.pop("params", None)
                if name in ("tiles", "upper"):
                    res["avg_distance_removed"] = float(res["distance"][removed[name]].mean())
                    res["avg_distance_kept"] = float(res["distance"][~removed[name]].mean())
                seed["generalization"][name] = res
            seed["datasets"] = {name: np.asarray(d.bd) for name, d in {**data, **pruned}.items()}
            per_seed.append(seed)
    per_seed += [per_seed[-1]] * (cfg.num_seeds - seeds_run)
    return EnvironmentResult.collect(
        env_name, low, high, np.asarray(zones), np.asarray(goals), removed, per_seed
    )


def run_environments(
    cfg: QDTConfig,
    repro_cfg: ReproducibilityConfig,
    repertoires: dict[str, dict[str, Any]],
    key: jax.Array,
    progress: bool = True,
    concurrent: bool = True,
) -> dict[str, EnvironmentResult]:
    """``run_environment`` for each of ``cfg.environments`` (its key the ``fold_in``
    of the environment's index), in concurrent threads unless ``concurrent`` is
    false; each result also holds its wall time, ``seconds``."""

    def one(env_name: str) -> EnvironmentResult:
        start = time.time()
        out = run_environment(
            cfg,
            repro_cfg,
            env_name,
            repertoires[env_name],
            jax.random.fold_in(key, cfg.environments.index(env_name)),
            progress,
        )
        return dataclasses.replace(out, seconds=time.time() - start)

    return map_concurrently(one, cfg.environments, concurrent)
