"""QD-PG (Chapter 3, Algorithm 4): MAP-Elites whose mutations are policy gradients.

Each iteration ``batch_size`` actors (N in the thesis: 4 on Point-Maze, 10 on the
ants) are drawn from a MAP-Elites grid and improved by TD3 actor steps: half of
them, chosen at random, against a *quality* critic trained on the environment's
rewards (Q-PG), the other half against a *diversity* critic trained on novelty
rewards (D-PG).  The novelty reward of a transition is the mean distance of its
state descriptor to its K nearest neighbours in an archive of state descriptors
(Eq. 3.5), recomputed from the current archive for every sampled batch.  Both
critics (TD3 twin pairs with targets) are shared by the whole population and
trained on one replay buffer of every transition.  Every updated actor plays one
episode and is inserted by MAP-Elites' rule; its transitions go to the buffer and
its state descriptors, filtered by novelty, to the FIFO archive (Section 3.6.3).

``update`` selects the variant of Table 3.1:

- ``"alternate"``: QD-PG, half quality and half diversity updates;
- ``"sum"``: QD-PG Sum, one critic on the sum of both rewards for every actor;
- ``"diversity"``: D-PG, diversity updates only;
- ``"quality"``: Q-PG, quality updates only.

The TD3 baseline (``TD3Agent``) trains a single actor on the same buffer rules.

Which state descriptor a transition carries: ``psi(s_t)``, that of the state
the transition starts from, as Section 3.6.3 writes the stored transition
``(s_t, a_t, r_t, s_{t+1}, psi(s_t))`` (and as QDax's QD-PG scores
``state_desc``); the archive receives the same ``psi(s_t)``.  Each critic's TD3
target uses the critic's own greedy actor (one actor step per ``policy_delay``
critic steps), as in PGA-ME; the target critic moves after every critic step
(Table 3.2's target update interval of 1).  The actors of the population only
read the critics; their policy-gradient steps use their own optimiser and rate
(``TD3Config.mutation_lr``; QDax: 1e-3 against 3e-4 for critics and greedy
actors).  The novelty rewards of all ``num_critic_steps`` batches of an
iteration are computed in one pass before the critic steps: the archive does not
change during them.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import jax
import jax.numpy as jnp
from flax import struct

from qdnb.core.evaluation import Evaluation
from qdnb.qd import repertoire as rep_lib
from qdnb.qd.algorithms import PolicyMapElites
from qdnb.qd.novelty import NoveltyArchive
from qdnb.rl.buffer import ReplayBuffer
from qdnb.rl.td3 import TD3, TD3Config, TD3State

UPDATES = ("alternate", "sum", "diversity", "quality")


def update_kinds(key: jax.Array, num_actors: int, update: str) -> jax.Array:
    """Per actor, True for a diversity update and False for a quality one.

    ``"alternate"``: a random half (``num_actors // 2``, the choice redrawn every
    iteration) gets diversity updates, the rest quality ones.  ``"sum"`` and
    ``"quality"`` use the first critic for everyone, ``"diversity"`` the second.
    """
    if update == "alternate":
        return jax.random.permutation(key, num_actors) < num_actors // 2
    return jnp.full((num_actors,), update == "diversity")


@struct.dataclass
class QDPGState:
    repertoire: rep_lib.Repertoire
    q_critic: TD3State  # quality critic (QD-PG Sum: the critic of the summed rewards)
    d_critic: TD3State  # diversity critic
    buffer: ReplayBuffer
    archive: NoveltyArchive
    key: jax.Array


@dataclass(frozen=True, eq=False)
class QDPG(PolicyMapElites):
    """QD-PG (Algorithm 4) and its ablations (Table 3.1), on a MAP-Elites grid
    (``centroids``: the grid's cell centres).  ``batch_size`` is the number of
    actors updated and evaluated per iteration."""

    update: str = "alternate"
    td3_config: TD3Config = TD3Config()
    num_critic_steps: int = 100
    num_pg_steps: int = 100
    buffer_size: int = 1_000_000
    archive_size: int = 10_000
    archive_threshold: float = 1e-4
    archive_k: int = 10
    collect_transitions: bool = True

    def __post_init__(self):
        if self.update not in UPDATES:
            raise ValueError(f"unknown update {self.update!r}; valid: {', '.join(UPDATES)}")

    # QD-PG evaluates its initial batch in ``init`` (run_seeds then compiles init and step)
    start = None
    # a few actors and much dense work (critics, policy gradients, novelty): over several
    # devices, split (padded) seeds, never a population (bench/scale_out.py: 0.80-0.83x of
    # one device when its population was split)
    split = "seeds"

    @property
    def td3(self) -> TD3:
        return TD3(self.network, self.env.observation_size, self.env.action_size, self.td3_config)

    def novelty_reward(self, archive: NoveltyArchive, batch: dict) -> jax.Array:
        """Fresh diversity rewards of a replay batch (Eq. 3.5)."""
        return archive.novelty(batch["state_descriptor"], self.archive_k)

    def critic_rewards(self, archive: NoveltyArchive, batch: dict, critic: str) -> jax.Array:
        """The rewards a critic trains on: the environment's (``"quality"``), the
        fresh novelty rewards (``"diversity"``) or their sum (``"sum"``)."""
        if critic == "quality":
            return batch["reward"]
        novelty = self.novelty_reward(archive, batch)
        return novelty if critic == "diversity" else batch["reward"] + novelty

    def _record(self, buffer: ReplayBuffer, archive: NoveltyArchive, ev: Evaluation):
        t = ev.trajectory
        sd = t["state_descriptor"].reshape(-1, t["state_descriptor"].shape[-1])
        archive = archive.add(sd, self.archive_threshold, self.archive_k, t["valid"].reshape(-1))
        return buffer.add_episodes(ev.trajectory, ev.fitness.ndim), archive

    def init(self, key: jax.Array) -> tuple[QDPGState, Evaluation]:
        k_init, k_eval, k_q, k_d, key = jax.random.split(key, 5)
        params = self.random_policies(k_init)
        repertoire, ev = self.evaluate_and_insert(self.empty_archive(params), params, k_eval)
        env = self.env
        buffer = ReplayBuffer.create(
            self.buffer_size, env.observation_size, env.action_size, env.descriptor_size
        )
        archive = NoveltyArchive.create(self.archive_size, env.descriptor_size)
        buffer, archive = self._record(buffer, archive, ev)
        return QDPGState(
            repertoire, self.td3.init(k_q), self.td3.init(k_d), buffer, archive, key
        ), ev

    def train_critics(self, state: QDPGState, key: jax.Array) -> tuple[TD3State, TD3State]:
        """Train the critics the variant uses for ``num_critic_steps`` steps each
        (the others stay as they are)."""
        td3, k_q, k_d = self.td3, *jax.random.split(key)
        rewards = lambda critic: lambda batch: self.critic_rewards(state.archive, batch, critic)
        q_critic, d_critic = state.q_critic, state.d_critic
        if self.update in ("alternate", "quality", "sum"):
            kind = "sum" if self.update == "sum" else "quality"
            q_critic, _ = td3.train_critic(
                q_critic, state.buffer, k_q, self.num_critic_steps, rewards(kind)
            )
        if self.update in ("alternate", "diversity"):
            d_critic, _ = td3.train_critic(
                d_critic, state.buffer, k_d, self.num_critic_steps, rewards("diversity")
            )
        return q_critic, d_critic

    def mutate(self, state: QDPGState, parents: Any, diversity: jax.Array, key: jax.Array) -> Any:
        """``num_pg_steps`` TD3 actor steps for every parent, each against the
        critic its update kind names."""
        td3 = self.td3

        def one(actor, use_d, k):
            critic = jax.tree.map(
                lambda q, d: jnp.where(use_d, d, q), state.q_critic.critic, state.d_critic.critic
            )
            return td3.policy_gradient_steps(actor, critic, state.buffer, k, self.num_pg_steps)

        return jax.vmap(one)(parents, diversity, jax.random.split(key, self.batch_size))

    def step(self, state: QDPGState) -> tuple[QDPGState, Evaluation]:
        key, k_sel, k_kind, k_pg, k_critic, k_eval = jax.random.split(state.key, 6)
        parents = rep_lib.sample(state.repertoire, k_sel, self.batch_size)
        diversity = update_kinds(k_kind, self.batch_size, self.update)
        offspring = self.mutate(state, parents, diversity, k_pg)
        q_critic, d_critic = self.train_critics(state, k_critic)
        repertoire, ev = self.evaluate_and_insert(state.repertoire, offspring, k_eval)
        buffer, archive = self._record(state.buffer, state.archive, ev)
        return QDPGState(repertoire, q_critic, d_critic, buffer, archive, key), ev

    def metrics(self, state: QDPGState) -> dict[str, jax.Array]:
        return {**super().metrics(state), "archive_size": state.archive.size}
