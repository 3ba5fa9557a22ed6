"""PGA-MAP-Elites (Algorithm 5; Nilsson and Cully, 2021) and its Low-Spread
variant (Algorithm 7): MAP-Elites whose batch is half TD3 policy-gradient
offspring against a critic shared by the whole repertoire."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import jax
import jax.numpy as jnp
from flax import struct

from qdnb.core.evaluation import Evaluation
from qdnb.core.tree import concat, take
from qdnb.qd import repertoire as rep_lib
from qdnb.qd.algorithms import MapElitesLowSpread, PolicyMapElites
from qdnb.rl.buffer import ReplayBuffer
from qdnb.rl.td3 import TD3, TD3Config, TD3State


@struct.dataclass
class PGAState:
    repertoire: Any
    td3: TD3State
    buffer: ReplayBuffer
    key: jax.Array
    offspring: Any = None  # the batch the next step evaluates


@dataclass(frozen=True, eq=False)
class PGAMapElites(PolicyMapElites):
    """PGA-MAP-Elites (Algorithm 5; Nilsson and Cully, 2021).

    Each iteration: ``batch_size`` parents are drawn from the repertoire; half
    take ``num_pg_steps`` TD3 actor steps against the shared critic, the others
    iso+line variation, and the greedy TD3 actor completes the batch; the critic
    (with the greedy actor, as TD3) trains for ``num_critic_steps`` steps on the
    replay buffer; every offspring is evaluated, its transitions stored, and
    inserted by the archive's rule.  The greedy actor is offered for insertion
    like any offspring, as in the QDax implementation the thesis ran.
    """

    td3_config: TD3Config = TD3Config()
    num_critic_steps: int = 300
    num_pg_steps: int = 100
    pg_proportion: float = 0.5
    buffer_size: int = 1_000_000
    collect_transitions: bool = True

    @property
    def td3(self) -> TD3:
        return TD3(self.network, self.env.observation_size, self.env.action_size, self.td3_config)

    @property
    def num_pg(self) -> int:
        return int(self.batch_size * self.pg_proportion)

    def start(self, key: jax.Array) -> PGAState:
        k_init, k_td3, key = jax.random.split(key, 3)
        params = self.random_policies(k_init)
        buffer = ReplayBuffer.create(
            self.buffer_size, self.env.observation_size, self.env.action_size
        )
        return PGAState(self.empty_archive(params), self.td3.init(k_td3), buffer, key, params)

    def emit(self, state: PGAState, key: jax.Array) -> Any:
        """Half of the batch from ``num_pg_steps`` actor steps against the critic,
        the rest iso+line, and the greedy actor."""
        k_sel, k_pg, k_vary = jax.random.split(key, 3)
        td3 = self.td3
        parents = rep_lib.sample(self.elites(state.repertoire), k_sel, self.batch_size)
        pg_parents = take(parents, jnp.arange(self.num_pg))
        pg_offspring = jax.vmap(
            lambda actor, k: td3.policy_gradient_steps(
                actor, state.td3.critic, state.buffer, k, self.num_pg_steps
            )
        )(pg_parents, jax.random.split(k_pg, self.num_pg))
        ga_offspring = take(
            self.vary(parents, k_vary), jnp.arange(self.batch_size - self.num_pg - 1)
        )
        greedy = jax.tree.map(lambda x: x[None], state.td3.actor)
        return concat(concat(pg_offspring, ga_offspring), greedy)

    def step(self, state: PGAState) -> tuple[PGAState, Evaluation]:
        """Evaluate and insert the waiting batch, store its transitions, train the
        critic on the buffer, then emit the next batch with that critic (QDax's
        order: the initial batch's transitions train the critic before the first
        policy-gradient offspring)."""
        key, k_eval, k_critic, k_emit = jax.random.split(state.key, 4)
        archive, ev = self.evaluate_and_insert(state.repertoire, state.offspring, k_eval)
        buffer = state.buffer.add_episodes(ev.trajectory, ev.fitness.ndim)
        td3_state, _ = self.td3.train_critic(state.td3, buffer, k_critic, self.num_critic_steps)
        state = PGAState(archive, td3_state, buffer, key)
        return state.replace(offspring=self.emit(state, k_emit)), ev


@dataclass(frozen=True, eq=False)
class PGAMapElitesLowSpread(PGAMapElites, MapElitesLowSpread):
    """PGA-MAP-Elites Low-Spread (Algorithm 7): PGA-ME's variation and critic,
    Low-Spread's ``num_episodes`` evaluations and insertion rule; every
    transition of every episode goes to the replay buffer."""
