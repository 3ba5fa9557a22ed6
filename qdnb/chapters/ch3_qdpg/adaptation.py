"""Chapter 3's fast adaptation (Section 3.7): new Ant-Maze goals reached by searching the
final grid, and the hand-made Point-Maze path.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import jax
import jax.numpy as jnp
import numpy as np

from qdnb.chapters.ch3_qdpg.experiment import policy_network
from qdnb.chapters.ch3_qdpg.measures import in_exit_zone
from qdnb.core.tree import take
from qdnb.envs.base import Env
from qdnb.envs.pointmaze import GOAL as POINTMAZE_GOAL
from qdnb.envs.rollout import evaluate_policies
from qdnb.qd.adaptation import bayes_opt, random_goals, random_search, reach_scores

if TYPE_CHECKING:
    from qdnb.chapters.ch3_qdpg.experiment import EnvironmentResult
    from qdnb.chapters.ch3_qdpg.settings import QDPGConfig


@dataclass(frozen=True)
class FastAdaptation:
    """QD-PG's final Ant-Maze grid (seed 0) searched for new goals (Figures 3.6, 3.7):
    ``paths`` (solutions, T, 2) and ``alive`` (solutions, T) of every stored
    solution's episode; per goal, the best score of Bayesian optimisation, the cell of
    the solution that scored it (``bo_pick``, -1 with no stored solution), the best
    score of random search with ``budget`` evaluations, and the exhaustive best."""

    goals: np.ndarray
    budget: int
    descriptors: np.ndarray
    valid: np.ndarray
    paths: np.ndarray
    alive: np.ndarray
    bo_best: np.ndarray
    bo_pick: np.ndarray
    rs_best: np.ndarray
    exhaustive: np.ndarray

    def summary(self) -> dict[str, Any]:
        return {
            "env": "antmaze",
            "goals": int(len(self.goals)),
            "budget": int(self.budget),
            "mean": float(self.bo_best.mean()),
            "std": float(self.bo_best.std()),
            "stored_solutions": int(self.valid.sum()),
        }


def fast_adaptation(cfg: QDPGConfig, antmaze: EnvironmentResult, seed: int) -> FastAdaptation:
    """Section 3.7 on ``antmaze`` (``run_environment``'s result): each stored solution
    of QD-PG's seed-0 grid plays one recorded episode; ``cfg.adaptation_goals``
    random goals are scored by the best reward an episode gets for them
    (``reach_scores``), and Bayesian optimisation over the descriptors picks
    ``cfg.adaptation_budget`` solutions to try for each goal."""
    grid, maze = antmaze.methods["QD-PG"].grid, antmaze.env
    valid = np.isfinite(grid["fitnesses"][0])
    genotypes = take(grid["genotypes"], 0)
    network = policy_network(cfg, "antmaze", maze)
    episode = jax.jit(
        lambda g, k: evaluate_policies(maze, network.apply, g, k, return_trajectory=True)
    )(genotypes, _adaptation_episodes_key(seed))
    paths_xy = np.asarray(episode.trajectory["next_state_descriptor"])
    alive = np.asarray(episode.trajectory["valid"])
    k_goals, k_bo = jax.random.split(jax.random.PRNGKey(seed + 2))
    goals = np.asarray(random_goals(k_goals, cfg.adaptation_goals, (-4.5, -4.5), (39.5, 39.5)))
    scores = jax.vmap(lambda g: reach_scores(paths_xy, g, alive))(goals)  # goals x solutions
    keys = jax.random.split(k_bo, cfg.adaptation_goals)
    bounds = (maze.descriptor_low, maze.descriptor_high)
    bo = jax.vmap(
        lambda s, k: bayes_opt(
            grid["descriptors"][0], valid, s, k, budget=cfg.adaptation_budget, bounds=bounds
        )
    )(scores, keys)
    rs = jax.vmap(lambda s, k: random_search(valid, s, k, budget=cfg.adaptation_budget))(
        scores, keys
    )
    exhaustive = np.max(np.where(valid[None], np.asarray(scores), -np.inf), axis=1)
    return FastAdaptation(
        goals,
        cfg.adaptation_budget,
        np.asarray(grid["descriptors"][0]),
        valid,
        paths_xy,
        alive,
        np.asarray(bo["best_score"]),
        np.asarray(bo["best_index"]),
        np.asarray(rs["best_score"]),
        exhaustive,
    )


def _adaptation_episodes_key(seed: int) -> jax.Array:
    """The key of the one recorded episode each stored solution plays for Section 3.7."""
    return jax.random.PRNGKey(seed + 1)


def adaptation_picks(
    antmaze: EnvironmentResult, fast: FastAdaptation, seed: int, goal_ids: np.ndarray
) -> tuple[Any, jax.Array]:
    """The solutions Bayesian optimisation picked for the goals ``goal_ids`` (a batch of
    policy parameters) and the keys of the initial states their scored episodes started
    from, as ``evaluate_policies`` drew them, so ``render.episode_states`` replays the
    very episodes the scores were read from; a ``ValueError`` for a goal with no pick."""
    cells = fast.bo_pick[np.asarray(goal_ids)]
    if (cells < 0).any():
        raise ValueError(f"goals {np.asarray(goal_ids)[cells < 0]} have no picked solution")
    genotypes = take(antmaze.methods["QD-PG"].grid["genotypes"], 0)
    keys = jax.random.split(_adaptation_episodes_key(seed), len(fast.valid))
    return jax.tree.map(lambda x: x[cells], genotypes), keys[cells]


# ----- the thesis's reference on Point-Maze: a hand-written path -----


def waypoint_policy(params: Any, obs: jax.Array) -> jax.Array:
    """A hand-written Point-Maze path: left through the lower wall's gap, right through
    the upper one, then to the exit (a reference for Table 3.4's returns)."""
    del params
    target = jnp.where(
        obs[1] < -0.45,
        jnp.array([-0.6, -0.42]),
        jnp.where(
            obs[1] < 0.25,
            jnp.where(obs[0] < 0.55, jnp.array([0.65, 0.0]), jnp.array([0.6, 0.3])),
            jnp.asarray(POINTMAZE_GOAL),
        ),
    )
    return jnp.clip((target - obs) * 10.0, -1.0, 1.0)


@dataclass(frozen=True)
class HandPath:
    """``waypoint_policy``'s returns and whether each episode ended in the exit zone."""

    returns: np.ndarray
    exited: np.ndarray


def hand_path(env: Env, key: jax.Array, starts: int = 256) -> HandPath:
    """``waypoint_policy`` on Point-Maze from ``starts`` random starts."""
    out = evaluate_policies(env, waypoint_policy, jnp.zeros((starts,)), key)
    return HandPath(np.asarray(out.fitness), in_exit_zone(np.asarray(out.descriptor)))
