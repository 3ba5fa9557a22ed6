"""Reinforcement-learning agents, the baselines of Chapter 3 (the home of every RL
baseline to come): each an ``Algorithm`` (``init``/``step``/``metrics``) whose
``max_fitness`` is the performance of its last greedy episode."""

from __future__ import annotations

from dataclasses import dataclass

import jax
import jax.numpy as jnp
from flax import struct

from qdnb.core.evaluation import Evaluation
from qdnb.envs.base import Env
from qdnb.envs.rollout import evaluate_policies
from qdnb.nets.mlp import MLP
from qdnb.rl.buffer import ReplayBuffer
from qdnb.rl.td3 import TD3, TD3Config, TD3State


@struct.dataclass
class TD3AgentState:
    td3: TD3State
    buffer: ReplayBuffer
    performance: jax.Array  # fitness of the last greedy episode
    key: jax.Array


@dataclass(frozen=True, eq=False)
class TD3Agent:
    """The TD3 baseline (Table 3.4): one actor and its twin critic.

    Each iteration the critic (and, every ``policy_delay`` steps, the actor)
    trains for ``num_critic_steps`` steps on the replay buffer, then the actor
    plays ``num_episodes`` episodes: the first greedy (its performance), the
    others with Gaussian exploration noise, all of them stored.
    """

    env: Env
    network: MLP
    td3_config: TD3Config = TD3Config()
    num_episodes: int = 4
    num_critic_steps: int = 100
    exploration_noise: float = 0.1
    buffer_size: int = 1_000_000

    @property
    def td3(self) -> TD3:
        return TD3(self.network, self.env.observation_size, self.env.action_size, self.td3_config)

    def _play(self, td3_state: TD3State, buffer: ReplayBuffer, key: jax.Array):
        actors = jax.tree.map(
            lambda x: jnp.repeat(x[None], self.num_episodes, axis=0), td3_state.actor
        )
        noise = jnp.full((self.num_episodes,), self.exploration_noise).at[0].set(0.0)
        ev = evaluate_policies(self.env, self.network.apply, actors, key, True, noise)
        return buffer.add_episodes(ev.trajectory, ev.fitness.ndim), ev

    def init(self, key: jax.Array) -> tuple[TD3AgentState, Evaluation]:
        k_init, k_eval, key = jax.random.split(key, 3)
        env = self.env
        td3_state = self.td3.init(k_init)
        buffer = ReplayBuffer.create(self.buffer_size, env.observation_size, env.action_size)
        buffer, ev = self._play(td3_state, buffer, k_eval)
        return TD3AgentState(td3_state, buffer, ev.fitness[0], key), ev

    def step(self, state: TD3AgentState) -> tuple[TD3AgentState, Evaluation]:
        key, k_train, k_eval = jax.random.split(state.key, 3)
        td3_state, _ = self.td3.train_critic(
            state.td3, state.buffer, k_train, self.num_critic_steps
        )
        buffer, ev = self._play(td3_state, state.buffer, k_eval)
        return TD3AgentState(td3_state, buffer, ev.fitness[0], key), ev

    def metrics(self, state: TD3AgentState) -> dict[str, jax.Array]:
        return {"max_fitness": state.performance}
