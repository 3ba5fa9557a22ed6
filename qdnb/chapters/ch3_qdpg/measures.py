"""Chapter 3's measures: the exit zone, Point-Maze's reachable cells and the coverage of
them, steps to the goal.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Callable

import jax
import numpy as np

from qdnb.envs.base import Env
from qdnb.envs.pointmaze import in_goal, reachable
from qdnb.qd.metrics import grid_cell

if TYPE_CHECKING:
    from qdnb.chapters.ch3_qdpg.experiment import MethodResult


ANTMAZE_SOLVED = -10.0  # Table 3.3: Ant-Maze is solved when the best reward exceeds this


def until_goal(env_name: str, num_seeds: int) -> Callable[[dict[str, Any]], bool]:
    """A ``run_seeds`` stop rule: true once every one of ``num_seeds`` seeds has reached
    the goal in the history seen so far (Point-Maze: an evaluated episode ended in the
    exit zone; Ant-Maze: the best reward exceeded ``ANTMAZE_SOLVED``), as
    ``steps_to_exit`` and ``MethodResult.steps_to_goal`` read it afterwards."""
    reached = np.zeros(num_seeds, bool)

    def stop(history: dict[str, Any]) -> bool:  # entries: iterations x seeds x ...
        reached[:] |= goal_hits(env_name, history).any(axis=0)
        return bool(reached.all())

    return stop


def goal_hits(env_name: str, history: dict[str, Any]) -> np.ndarray:
    """Whether the goal was reached, per entry of a history's first two axes (seeds x
    iterations in a result, iterations x seeds inside a loop): on Point-Maze an
    evaluated episode ended in the exit zone, on Ant-Maze the best reward exceeded
    ``ANTMAZE_SOLVED`` (Table 3.3)."""
    if env_name == "pointmaze":
        hit = in_exit_zone(np.asarray(history["descriptors"]))
        return hit.reshape(hit.shape[0], hit.shape[1], -1).any(axis=2)
    return np.asarray(history["max_fitness"]) > ANTMAZE_SOLVED


def reachable_cells(env_name: str, env: Env, bins: int) -> np.ndarray:
    """Which cells of the ``bins x bins`` grid hold a reachable point: on Point-Maze,
    a point of a 401 x 401 lattice of the arena outside the walls (``reachable``);
    on the ant mazes every cell counts."""
    if env_name != "pointmaze":
        return np.ones(bins * bins, bool)
    axis = np.linspace(-1.0, 1.0, 401)
    lattice = np.stack(np.meshgrid(axis, axis, indexing="ij"), axis=-1).reshape(-1, 2)
    cells = grid_cell(
        lattice[reachable(lattice)], (bins, bins), env.descriptor_low, env.descriptor_high
    )
    mask = np.zeros(bins * bins, bool)
    mask[np.asarray(cells)] = True
    return mask


def reachable_coverage(filled: np.ndarray, env_name: str, env: Env, bins: int) -> np.ndarray:
    """Per seed (leading axis of ``filled``, seeds x cells), the share of the grid's
    reachable cells (``reachable_cells``) that are filled."""
    mask = reachable_cells(env_name, env, bins)
    return np.asarray(filled)[:, mask].mean(axis=1)


def grid_coverage(
    descriptors: np.ndarray, env: Env, bins: int, env_name: str = "pointmaze"
) -> np.ndarray:
    """The share of the ``bins x bins`` grid's reachable cells reached by any
    evaluated episode, per seed (``descriptors``: seeds x iterations x episodes x 2).
    For TD3, which keeps no grid, this is the grid it would have filled."""
    d = descriptors.reshape(descriptors.shape[0], -1, descriptors.shape[-1])
    cells = np.asarray(grid_cell(d, (bins, bins), env.descriptor_low, env.descriptor_high))
    filled = np.zeros((len(cells), bins * bins), bool)
    for seed, c in enumerate(cells):
        filled[seed, c] = True
    return reachable_coverage(filled, env_name, env, bins)


def in_exit_zone(descriptors: np.ndarray) -> np.ndarray:
    """Whether each Point-Maze final position lies in the exit zone (an episode
    stops there, so an episode that entered the zone ends in it); the shape of
    ``descriptors`` without its last axis."""
    flat = np.asarray(descriptors).reshape(-1, 2)
    return np.asarray(jax.vmap(in_goal)(flat)).reshape(np.shape(descriptors)[:-1])


def reached_goal(descriptors: np.ndarray) -> np.ndarray:
    """Per seed (leading axis), whether any evaluated Point-Maze episode ended in
    the exit zone."""
    return in_exit_zone(descriptors).reshape(np.shape(descriptors)[0], -1).any(axis=1)


def steps_to_exit(result: MethodResult) -> np.ndarray:
    """Per seed, the environment steps a Point-Maze method had used when one of
    its evaluated episodes first ended in the exit zone (``nan`` if none did);
    ``result`` is one method's entry of ``run_environment``."""
    hit = goal_hits("pointmaze", result.history)  # seeds x iterations
    steps = np.asarray(result.cumulative_steps, float)
    return np.where(hit.any(axis=1), steps[np.arange(len(steps)), np.argmax(hit, axis=1)], np.nan)
