"""Environments of the book, behind one registry: ``make_env(name, **kwargs)``."""

from __future__ import annotations

from typing import Callable

from qdnb.envs.base import Env, EnvState
from qdnb.envs.pointmaze import PointMaze


def _ant_omni(**kwargs) -> Env:
    from qdnb.envs.locomotion import AntOmni  # imports brax only when asked for

    return AntOmni(**kwargs)


def _halfcheetah_uni(**kwargs) -> Env:
    from qdnb.envs.locomotion import HalfcheetahUni

    return HalfcheetahUni(**kwargs)


def _antmaze(**kwargs) -> Env:
    from qdnb.envs.mazes import AntMaze

    return AntMaze(**kwargs)


def _anttrap(**kwargs) -> Env:
    from qdnb.envs.mazes import AntTrap

    return AntTrap(**kwargs)


_REGISTRY: dict[str, Callable[..., Env]] = {
    "pointmaze": PointMaze,
    "ant_omni": _ant_omni,
    "halfcheetah_uni": _halfcheetah_uni,
    "antmaze": _antmaze,
    "anttrap": _anttrap,
}


def env_names() -> list[str]:
    return sorted(_REGISTRY)


def make_env(name: str, **kwargs) -> Env:
    """Build a registered environment, e.g. ``make_env("pointmaze", episode_length=200)``."""
    if name not in _REGISTRY:
        raise ValueError(f"unknown environment {name!r}; valid names: {', '.join(env_names())}")
    return _REGISTRY[name](**kwargs)


__all__ = ["Env", "EnvState", "PointMaze", "env_names", "make_env"]
