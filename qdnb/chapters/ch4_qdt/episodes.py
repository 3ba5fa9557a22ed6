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
from qdnb.envs.render import watched_episodes
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
    draws, and the BDs each ``reached`` (goals, d): the QDT's ``actions`` (goals, T, A),
    for ``render.replay_states`` to replay (a transformer is watched from the actions it
    played), and the demonstrators' simulator states (goals, T + 1, q), their episodes
    played once (``render.watched_episodes``)."""

    goals: np.ndarray
    starts: jax.Array
    qdt_actions: np.ndarray
    qdt_reached: np.ndarray
    demonstrator_states: np.ndarray
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
    # one compiled program (played eagerly, the QDT's prefill and the resets run op by op)
    ev = jax.jit(play, static_argnums=(0, 1, 5))(
        env, qdt_model(cfg, env), res.watched, goals, key, 1
    )
    teachers = seed_repertoire(repertoires["ME-LS"], 0)
    kept = np.zeros(len(teachers.descriptors), bool)  # the cells the QDT's data kept
    kept[np.asarray(res.selection["ME-LS"][0].cells)] = True
    nearest = nearest_cells(teachers.descriptors, goals, jnp.asarray(kept))
    demonstrator = jax.tree.map(lambda x: x[nearest], teachers.genotypes)
    network = MLP(repro_cfg.policy_hidden + (env.action_size,))
    starts = jax.random.split(key, len(goals))  # the QDT's: play's resets
    states, reached = watched_episodes(env, network.apply, demonstrator, starts)
    return GoalEpisodes(
        np.asarray(goals),
        starts,
        np.asarray(ev.trajectory[:, 0]),
        np.asarray(ev.descriptor[:, 0]),
        states,
        reached,
    )
