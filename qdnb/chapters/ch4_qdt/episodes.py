"""Episodes to watch: the QDT and the demonstrator it learnt from, on goals the page picks
(it shows the nearest, the median and the farthest).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import jax
import jax.numpy as jnp
import numpy as np

from qdnb.chapters.ch4_qdt.experiment import qdt_model
from qdnb.chapters.ch4_reproducibility import ReproducibilityConfig
from qdnb.envs.rollout import evaluate_policies
from qdnb.models.qdt.data import seed_repertoire
from qdnb.models.qdt.evaluate import play
from qdnb.nets.mlp import MLP
from qdnb.qd.low_spread import nearest_cells

if TYPE_CHECKING:
    from qdnb.chapters.ch4_qdt.results import EnvironmentResult
    from qdnb.chapters.ch4_qdt.settings import QDTConfig


@dataclass(frozen=True)
class GoalEpisodes:
    """One episode per goal of seed 0's QDT(ME-LS) conditioned on it and of its
    ``demonstrator`` (the kept ME-LS policy whose stored BD is nearest the goal, as the
    teachers' accuracy picks it), both from the initial state row ``i`` of ``starts``
    draws: the ``actions`` each played (goals, T, A) and the BDs each ``reached`` (goals,
    d), for ``render.replay_states`` to replay."""

    goals: np.ndarray
    starts: jax.Array
    qdt_actions: np.ndarray
    qdt_reached: np.ndarray
    demonstrator_actions: np.ndarray
    demonstrator_reached: np.ndarray


def goal_episodes(
    cfg: QDTConfig,
    repro_cfg: ReproducibilityConfig,
    res: EnvironmentResult,
    repertoires: dict[str, Any],
    goal_ids: np.ndarray,
    key: jax.Array,
) -> GoalEpisodes:
    """``GoalEpisodes`` of ``res.goals[goal_ids]`` (``repertoires`` as
    ``run_environment`` had them); a ``ValueError`` when ``res`` kept no QDT (a
    dataset that pruning emptied)."""
    if res.watched is None:
        raise ValueError(f"{res.env_name}: seed 0's QDT(ME-LS) was not trained")
    env = repro_cfg.make_env(res.env_name)
    goals = jnp.asarray(res.goals[np.asarray(goal_ids)])
    ev = play(env, qdt_model(cfg, env), res.watched, goals, key, 1)  # starts: split(key, G)
    teachers = seed_repertoire(repertoires["ME-LS"], 0)
    kept = np.zeros(len(teachers.descriptors), bool)  # the cells the QDT's data kept
    kept[np.asarray(res.selection["ME-LS"][0].cells)] = True
    nearest = nearest_cells(teachers.descriptors, goals, jnp.asarray(kept))
    demonstrator = jax.tree.map(lambda x: x[nearest], teachers.genotypes)
    network = MLP(repro_cfg.policy_hidden + (env.action_size,))
    shown = evaluate_policies(env, network.apply, demonstrator, key, return_trajectory=True)
    return GoalEpisodes(  # the same starts: split(key, G)
        np.asarray(goals),
        jax.random.split(key, len(goals)),
        np.asarray(ev.trajectory[:, 0]),
        np.asarray(ev.descriptor[:, 0]),
        np.asarray(shown.trajectory["action"]),
        np.asarray(shown.descriptor),
    )
