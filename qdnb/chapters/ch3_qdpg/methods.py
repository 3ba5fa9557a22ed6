"""Chapter 3's methods: the registry of every algorithm the chapter's pages run (QD-PG, its
ablations, TD3, PGA-ME, the RL baselines and the evolution strategies), built for a
task.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Callable

from qdnb.core.evaluation import Algorithm
from qdnb.qd.es import MEES, NSRAES, NSRES
from qdnb.qd.pga import PGAMapElites
from qdnb.qd.qdpg import QDPG
from qdnb.rl.agac import AGACAgent, AGACConfig
from qdnb.rl.agents import TD3Agent
from qdnb.rl.cemrl import CEMRLAgent
from qdnb.rl.diayn import DIAYN
from qdnb.rl.p3s import P3STD3Agent
from qdnb.rl.rnd import RNDAgent
from qdnb.rl.sac import SACAgent

if TYPE_CHECKING:
    from qdnb.chapters.ch3_qdpg.settings import QDPGConfig, QDPGTask


def _qdpg(update: str) -> Callable[[QDPGConfig, QDPGTask, dict], Algorithm]:
    def build(cfg: QDPGConfig, task: QDPGTask, parts: dict) -> Algorithm:
        return QDPG(
            **parts["shared"],
            update=update,
            td3_config=parts["td3"],
            num_critic_steps=task.num_critic_steps,
            num_pg_steps=task.num_pg_steps,
            buffer_size=task.buffer_size,
            archive_size=task.archive_size,
            archive_threshold=task.archive_threshold,
            archive_k=cfg.archive_k,
        )

    return build


def _pga_me(cfg: QDPGConfig, task: QDPGTask, parts: dict) -> Algorithm:
    return PGAMapElites(
        **parts["shared"],
        td3_config=parts["td3"],
        num_critic_steps=task.num_critic_steps,
        num_pg_steps=task.num_pg_steps,
        buffer_size=task.buffer_size,
    )


def _replay_agent(cls: type, **settings: Callable[[QDPGConfig, QDPGTask], Any]):
    """A replay-buffer agent (TD3 and the off-policy baselines): the task's network,
    TD3 settings, episodes and gradient steps per iteration and buffer size, and
    ``settings``, each read from the config and the task."""

    def build(cfg: QDPGConfig, task: QDPGTask, parts: dict) -> Algorithm:
        return cls(
            env=parts["env"],
            network=parts["network"],
            td3_config=parts["td3"],
            num_episodes=task.num_actors,
            num_critic_steps=task.num_critic_steps,
            buffer_size=task.buffer_size,
            **{name: value(cfg, task) for name, value in settings.items()},
        )

    return build


_exploration_noise = lambda cfg, task: cfg.exploration_noise  # noqa: E731
_td3 = _replay_agent(TD3Agent, exploration_noise=_exploration_noise)
_sac = _replay_agent(SACAgent)
_diayn = _replay_agent(DIAYN)
_rnd = _replay_agent(RNDAgent, exploration_noise=_exploration_noise)
# one learner per episode; the critic steps are shared among the learners
_p3s_td3 = _replay_agent(P3STD3Agent, exploration_noise=_exploration_noise)
# episode 0 plays the mean actor (its performance), the others the CEM population
_cem_rl = _replay_agent(CEMRLAgent, num_actor_steps=lambda cfg, task: task.num_pg_steps)


def _agac(cfg: QDPGConfig, task: QDPGTask, parts: dict) -> Algorithm:
    # on-policy: no replay buffer nor critic steps; its bonus decays over the run's iterations
    return AGACAgent(
        env=parts["env"],
        network=parts["network"],
        num_episodes=task.num_actors,
        config=AGACConfig(gamma=cfg.discount),
        num_iterations=task.num_iterations,
    )


def _evolution_strategy(cls: type) -> Callable[[QDPGConfig, QDPGTask, dict], Algorithm]:
    """An ES method whose generation is ``task.num_actors`` perturbations (the chapter's
    evolution page sets it), with its archive exactly as long as the run's descriptors
    (the reference codes keep them all: ME-ES one per generation, QDax's archive of
    ``total_generations``; NS-ES the meta-population's first ``M``, then one per
    generation) and, for ME-ES, the task's grid."""

    def build(cfg: QDPGConfig, task: QDPGTask, parts: dict) -> Algorithm:
        extra = {"centroids": parts["shared"]["centroids"]} if cls is MEES else {}
        entries = task.num_iterations
        if issubclass(cls, NSRES):
            entries += NSRES.meta_population_size - 1
        return cls(
            env=parts["env"],
            network=parts["network"],
            num_perturbations=task.num_actors,
            archive_size=max(cls.k, entries),
            **extra,
        )

    return build


# name -> builder(cfg, task, shared parts): adding a method is one entry (and its code)
METHODS: dict[str, Callable[[QDPGConfig, QDPGTask, dict], Algorithm]] = {
    "QD-PG": _qdpg("alternate"),
    "QD-PG Sum": _qdpg("sum"),
    "D-PG": _qdpg("diversity"),
    "Q-PG": _qdpg("quality"),
    "TD3": _td3,
    "PGA-ME": _pga_me,
    "SAC": _sac,
    "RND": _rnd,
    "CEM-RL": _cem_rl,
    "P3S-TD3": _p3s_td3,
    "AGAC": _agac,
    "DIAYN": _diayn,
    "ME-ES": _evolution_strategy(MEES),
    "NSR-ES": _evolution_strategy(NSRES),
    "NSRA-ES": _evolution_strategy(NSRAES),
}
QDPG_METHODS = ("QD-PG", "QD-PG Sum", "D-PG", "Q-PG", "TD3", "PGA-ME")  # the QD-PG page's methods
