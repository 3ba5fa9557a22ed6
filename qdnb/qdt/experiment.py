"""The QDT chapter's experiments on one environment (Sections 4.5.1-4.5.5).

For every full seed (``QDTConfig.full_seeds``): the accuracy experiment of the
four repertoires on the evaluation goals, and of the policies the zone selection
keeps from each (the QDT's demonstrators); the datasets (Section 4.4.4) of ME,
ME-LS, PGA-ME, PGA-ME-LS and Naive; a QDT trained on each (Figure 4.7, Table 4.4,
Figure 4.14); and a QDT trained on each pruned ME-LS dataset (Figures 4.10 and
4.11).  The other seeds do the same for ME and ME-LS only (``CLAIM_SOURCES``, what
the accuracy claim compares).  Everything comes back as numpy arrays; the notebook
draws and tabulates.
"""

from __future__ import annotations

import time
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from qdnb.loops import map_concurrently
from qdnb.qd.cvt import cvt_centroids
from qdnb.qd.low_spread import accuracy
from qdnb.qd.reproducibility import Player
from qdnb.qdt.data import (NAIVE, PRUNINGS, SOURCES, naive_episodes_per_policy, prune, record, removed_region,
                           seed_repertoire, select_policies)
from qdnb.qdt.evaluate import goal_scores, play
from qdnb.qdt.model import QDT
from qdnb.qdt.train import fit, make_optimizer, make_train_step
from qdnb.rl.networks import MLP
from qdnb.scale import QDTConfig, ReproducibilityConfig

DATASETS = SOURCES + (NAIVE,)
CLAIM_SOURCES = ("ME", "ME-LS")  # the accuracy claim: QDT(ME-LS) against the ME repertoire and QDT(ME)


def seeds_with(result: dict[str, Any], part: str, name: str) -> list[Any]:
    """``seed[part][name]`` of every seed of ``run_environment``'s result that has
    it (``part``: "repertoire", "selection", "teachers", "datasets", "qdt" or
    "generalization"); later seeds hold only ``CLAIM_SOURCES`` when
    ``full_seeds`` is below ``num_seeds``."""
    return [s[part][name] for s in result["seeds"] if name in s[part]]


def num_seeds_of(repertoires: dict[str, Any]) -> int:
    return min(int(np.shape(r["fitnesses"])[0]) for r in repertoires.values())


def run_environment(cfg: QDTConfig, repro_cfg: ReproducibilityConfig, env_name: str, repertoires: dict[str, Any],
                    key: jax.Array, progress: bool = True) -> dict[str, Any]:
    """Every experiment of the chapter on ``env_name``.  ``repertoires[method]``
    are the Chapter 4 repertoires (stacked over its seeds); QDT seed ``i`` uses
    repertoire seed ``i`` (cycling when the Chapter 4 run has fewer seeds)."""
    task = cfg.task(env_name)
    env = repro_cfg.make_env(env_name)
    network = MLP(repro_cfg.policy_hidden + (env.action_size,))
    low, high = env.descriptor_low, env.descriptor_high
    k_zones, k_goals, k_seeds = jax.random.split(key, 3)
    zones = cvt_centroids(k_zones, task.zones, low, high, cfg.cvt_samples, cfg.cvt_iterations)
    goals = cvt_centroids(k_goals, task.goals, low, high, cfg.cvt_samples, cfg.cvt_iterations)
    player = Player(env, network, chunk=repro_cfg.env_batch)
    recorder = Player(env, network, chunk=repro_cfg.env_batch, record=True)
    model = QDT(env.action_size, env.episode_length, cfg.embed_dim, cfg.num_layers, cfg.num_heads, cfg.dropout)
    play_goals = jax.jit(lambda params, k: play(env, model, params, goals, k, cfg.eval_episodes))
    step = make_train_step(model, make_optimizer(cfg.learning_rate))  # one compilation for every dataset
    removed = {name: removed_region(name, np.asarray(goals), low, high, cfg.tiles) for name in PRUNINGS}

    def train(data, k_train, k_eval, desc):
        def evaluate(params, epoch):
            s = goal_scores(goals, play_goals(params, k_eval))
            return {"avg_distance": float(s["distance"].mean()), "avg_spread": float(s["spread"].mean()),
                    "max_fitness": float(s["fitness"].max()), "distance": s["distance"], "spread": s["spread"]}

        start = time.time()
        res = fit(model, data, k_train, cfg.epochs, cfg.batch_size, cfg.learning_rate, cfg.eval_every, evaluate,
                  step=step, progress=progress, desc=desc)
        best = next(e for e in res.evaluations if e["epoch"] == res.best_epoch)
        return {"epochs": np.array([e["epoch"] for e in res.evaluations]),
                "avg_distance_curve": np.array([e["avg_distance"] for e in res.evaluations]),
                "max_fitness_curve": np.array([e["max_fitness"] for e in res.evaluations]),
                "loss": np.array(res.losses), "best_epoch": res.best_epoch,
                "avg_distance": best["avg_distance"], "avg_spread": best["avg_spread"],
                "distance": best["distance"], "spread": best["spread"], "dataset_size": data.size,
                "seconds": time.time() - start}

    per_seed = []
    num_rep_seeds = num_seeds_of(repertoires)
    for i in range(cfg.num_seeds):
        k_sel, k_rec, k_acc, k_train, k_eval, k_prune = jax.random.split(jax.random.fold_in(k_seeds, i), 6)
        full = i < cfg.num_full_seeds
        sources = SOURCES if full else CLAIM_SOURCES
        reps = {m: seed_repertoire(repertoires[m], i % num_rep_seeds) for m in sources}
        seed: dict[str, Any] = {"repertoire": {}, "selection": {}, "teachers": {}, "datasets": {}, "qdt": {},
                                "generalization": {}, "full": full}
        for m in sources:  # Section 4.5.2: the stored policy nearest to each goal
            acc = accuracy(reps[m], goals, player.episodes(cfg.eval_episodes), k_acc)
            seed["repertoire"][m] = {"distance": np.asarray(acc.distance), "spread": np.asarray(acc.spread),
                                     "filled": int(np.sum(np.asarray(reps[m].filled)))}
        data = {}
        for m in sources:  # Section 4.4.4
            sel = select_policies(reps[m], zones, player, task.selection_episodes, k_sel)
            seed["selection"][m] = sel
            teachers = reps[m].replace(fitnesses=jnp.full_like(reps[m].fitnesses, -jnp.inf).at[sel.cells].set(
                reps[m].fitnesses[sel.cells]))  # only the kept policies: the QDT's demonstrators
            acc = accuracy(teachers, goals, player.episodes(cfg.eval_episodes), k_acc)
            seed["teachers"][m] = {"distance": np.asarray(acc.distance), "spread": np.asarray(acc.spread)}
            data[m] = record(reps[m], sel.cells, task.episodes_per_policy, recorder, k_rec)
        if full:
            every = np.flatnonzero(np.asarray(reps["ME-LS"].filled))
            naive_epp = naive_episodes_per_policy(seed["selection"]["ME-LS"].cells.size, task.episodes_per_policy,
                                                  every.size)
            data[NAIVE] = record(reps["ME-LS"], every, naive_epp, recorder, k_rec)
            seed["naive_episodes_per_policy"] = naive_epp
        for name in data:
            seed["qdt"][name] = train(data[name], k_train, k_eval, f"{env_name} seed {i} QDT({name})")
        pruned = {name: prune(data["ME-LS"], name, low, high, cfg.tiles, jax.random.fold_in(k_prune, j))
                  for j, name in enumerate(PRUNINGS)} if full else {}
        for name in pruned:
            res = train(pruned[name], k_train, k_eval, f"{env_name} seed {i} QDT(ME-LS, {name})")
            if name in ("tiles", "upper"):
                res["avg_distance_removed"] = float(res["distance"][removed[name]].mean())
                res["avg_distance_kept"] = float(res["distance"][~removed[name]].mean())
            seed["generalization"][name] = res
        seed["datasets"] = {name: np.asarray(d.bd) for name, d in {**data, **pruned}.items()}
        per_seed.append(seed)
    return {"env_name": env_name, "low": low, "high": high, "zones": np.asarray(zones), "goals": np.asarray(goals),
            "removed_goals": removed, "seeds": per_seed}


def run_environments(cfg: QDTConfig, repro_cfg: ReproducibilityConfig, repertoires: dict[str, dict[str, Any]],
                     key: jax.Array, progress: bool = True, concurrent: bool = True) -> dict[str, dict[str, Any]]:
    """``run_environment`` for each of ``cfg.environments`` (its key the ``fold_in``
    of the environment's index), in concurrent threads unless ``concurrent`` is
    false; each result also holds its wall time, ``seconds``."""
    def one(env_name: str) -> dict[str, Any]:
        start = time.time()
        out = run_environment(cfg, repro_cfg, env_name, repertoires[env_name],
                              jax.random.fold_in(key, cfg.environments.index(env_name)), progress)
        return {**out, "seconds": time.time() - start}

    return map_concurrently(one, cfg.environments, concurrent)
