"""QD-PG (Chapter 3, Algorithm 4): MAP-Elites whose mutations are policy gradients.

Each iteration ``batch_size`` actors (N in the thesis: 4 on Point-Maze, 10 on the
ants) are drawn from a MAP-Elites grid and improved by TD3 actor steps: half of
them, chosen at random, against a *quality* critic trained on the environment's
rewards (Q-PG), the other half against a *diversity* critic trained on novelty
rewards (D-PG).  The novelty reward of a transition is the mean distance of its
state descriptor to its K nearest neighbours in an archive of state descriptors
(Section 3.6.3; Eq. 3.5 prints their sum: ``novelty_reduction="sum"``),
recomputed from the current archive for every sampled batch.  Both critics (TD3
twin pairs with targets) are shared by the whole population and trained on one
replay buffer of every transition.  Every updated actor plays one episode and is
inserted by MAP-Elites' rule; its transitions go to the buffer and its state
descriptors, filtered by novelty, to the FIFO archive (Section 3.6.3).

``update`` selects the variant of Table 3.1:

- ``"alternate"``: QD-PG, half quality and half diversity updates;
- ``"sum"``: QD-PG Sum, one critic on the sum of both rewards for every actor;
- ``"diversity"``: D-PG, diversity updates only;
- ``"quality"``: Q-PG, quality updates only.

``coupling`` says how the critics meet the actors (measured side by side in
``bench/probes/qdpg_coupling.py``):

- ``"thesis"`` (QD-PG): "Every time a policy gradient is computed, QD-PG also
  updates the corresponding critic", the critics being "shared among the
  population (as in CEM)" (Section 3.5).  Read with the thesis's implementation
  (Section 3.6.3: one actor per MPI worker, the critics shared) and with CEM-RL,
  which trains its shared critic with the actor being improved as the TD3 target
  policy: every actor takes its TD3 steps on its own replay batches, each critic
  step's TD target uses the actor being improved (its target copy, started from
  the parent and soft-updated after each of its steps, as CEM-RL's), and each
  critic's gradient is averaged over the actors it drives, as an MPI TD3
  averages its workers'.  An iteration is ``num_critic_steps`` such critic steps
  with an actor step after every ``policy_delay`` of them (TD3's delayed policy
  update, Table 3.2), so a mutation takes ``num_critic_steps // policy_delay``
  policy-gradient steps (``num_pg_steps`` is not used).  There are no greedy
  actors.
- ``"greedy"``: the book's earlier reading, kept for the A/B.  Each critic
  trains ``num_critic_steps`` steps against its own greedy TD3 actor (one actor
  step per ``policy_delay`` critic steps, as in PGA-ME), an actor that is never
  played; the population's ``num_pg_steps`` mutation steps only read the
  critics.
- ``"qdax"``: QDax's QD-PG (an "updated version" of the paper's, in its own
  words): ``"greedy"``, and each critic's greedy actor is also emitted beside
  the mutated offspring (``batch_size`` minus one per critic in use are
  mutated), plays its episode, feeds the buffer and the archive and competes
  for a cell like any offspring.

Which state descriptor a transition carries: ``psi(s_t)``, that of the state
the transition starts from, as Section 3.6.3 writes the stored transition
``(s_t, a_t, r_t, s_{t+1}, psi(s_t))`` (and as QDax's QD-PG scores
``state_desc``); the archive receives the same ``psi(s_t)``.  The target critic
moves after every critic step (Table 3.2's target update interval of 1).  The
population's policy-gradient steps use their own fresh optimiser and rate
(``TD3Config.mutation_lr``; QDax: 1e-3 against 3e-4 for critics and greedy
actors).  The novelty rewards of all the batches of an iteration are computed in
one pass before its gradient steps: the archive does not change during them.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import jax
import jax.numpy as jnp
import optax
from flax import struct

from qdnb.core.evaluation import Evaluation
from qdnb.core.tree import concat, stack
from qdnb.envs.rollout import evaluate_policies
from qdnb.qd import repertoire as rep_lib
from qdnb.qd.algorithms import PolicyMapElites
from qdnb.qd.novelty import REDUCTIONS, SEARCHES, NoveltyArchive
from qdnb.rl.buffer import ReplayBuffer
from qdnb.rl.td3 import TD3, TD3Config, TD3State

UPDATES = ("alternate", "sum", "diversity", "quality")
COUPLINGS = ("thesis", "greedy", "qdax")


def update_kinds(key: jax.Array, num_actors: int, update: str) -> jax.Array:
    """Per actor, True for a diversity update and False for a quality one.

    ``"alternate"``: a random half (``num_actors // 2``, the choice redrawn every
    iteration) gets diversity updates, the rest quality ones.  ``"sum"`` and
    ``"quality"`` use the first critic for everyone, ``"diversity"`` the second.
    """
    if update == "alternate":
        return jax.random.permutation(key, num_actors) < num_actors // 2
    return jnp.full((num_actors,), update == "diversity")


def pick(flags: jax.Array, if_true: Any, if_false: Any) -> Any:
    """Per entry of ``flags``, the tree ``if_true`` or ``if_false`` (stacked on a new
    leading axis): each actor's critic."""
    return jax.vmap(lambda f: jax.tree.map(lambda a, b: jnp.where(f, a, b), if_true, if_false))(
        flags
    )


def weighted_sum(weights: jax.Array, trees: Any) -> Any:
    """Sum over the leading axis of ``trees`` with ``weights``."""
    return jax.tree.map(lambda g: jnp.tensordot(weights, g, axes=1), trees)


@struct.dataclass
class QDPGState:
    repertoire: rep_lib.Repertoire
    q_critic: TD3State  # quality critic (QD-PG Sum: the critic of the summed rewards)
    d_critic: TD3State  # diversity critic
    buffer: ReplayBuffer
    archive: NoveltyArchive
    key: jax.Array
    # the last iteration's update statistics (``UPDATE_STATISTICS``), for the loop's history
    updates: dict = struct.field(default_factory=dict)


# What each iteration's updates record (the thesis's coupling; the greedy readings record
# the critics' mean losses, the rest 0): each critic's mean loss (the sum of its twin
# heads' mean squared TD errors) and the largest global norm of the gradient it applied,
# and the largest global norm of an actor's policy gradient.  A divergence shows here first.
UPDATE_STATISTICS = (
    "critic_loss_q",
    "critic_loss_d",
    "critic_grad_norm_q",
    "critic_grad_norm_d",
    "actor_grad_norm",
)


def no_statistics() -> dict:
    return {name: jnp.zeros(()) for name in UPDATE_STATISTICS}


@dataclass(frozen=True, eq=False)
class QDPG(PolicyMapElites):
    """QD-PG (Algorithm 4) and its ablations (Table 3.1), on a MAP-Elites grid
    (``centroids``: the grid's cell centres).  ``batch_size`` is the number of
    actors updated and evaluated per iteration."""

    update: str = "alternate"
    coupling: str = "thesis"
    novelty_reduction: str = "mean"
    td3_config: TD3Config = TD3Config()
    num_critic_steps: int = 100
    num_pg_steps: int = 100
    buffer_size: int = 1_000_000
    archive_size: int = 10_000
    archive_threshold: float = 1e-4
    archive_k: int = 10
    novelty_search: str = "auto"  # how the archive finds neighbours (NoveltyArchive.novelty)
    # the standard deviation of Gaussian noise on the population's actions as it plays its
    # episodes (0: the actors play deterministically, as QDax's QD-PG; TD3 collects with 0.1)
    exploration_noise: float = 0.0
    collect_transitions: bool = True

    def __post_init__(self):
        for name, value, valid in (
            ("update", self.update, UPDATES),
            ("coupling", self.coupling, COUPLINGS),
            ("novelty_reduction", self.novelty_reduction, REDUCTIONS),
            ("novelty_search", self.novelty_search, SEARCHES),
        ):
            if value not in valid:
                raise ValueError(f"unknown {name} {value!r}; valid: {', '.join(valid)}")
        delay = self.td3_config.policy_delay
        if self.num_critic_steps % delay:
            raise ValueError(
                f"num_critic_steps={self.num_critic_steps} must be a multiple of "
                f"policy_delay={delay}"
            )
        if self.coupling == "qdax" and self.batch_size <= len(self.critics_in_use):
            raise ValueError(
                f"coupling 'qdax' plays {len(self.critics_in_use)} greedy actor(s) among "
                f"batch_size={self.batch_size} episodes: at least one must be a mutation"
            )

    # QD-PG evaluates its initial batch in ``init`` (run_seeds then compiles init and step)
    start = None
    # a few actors and much dense work (critics, policy gradients, novelty): over several
    # devices, split (padded) seeds, never a population (bench/scale_out.py: 0.80-0.83x of
    # one device when its population was split)
    split = "seeds"

    @property
    def td3(self) -> TD3:
        return TD3(self.network, self.env.observation_size, self.env.action_size, self.td3_config)

    @property
    def critics_in_use(self) -> tuple[str, ...]:
        """The critics the variant trains: ``"q"`` (quality, or QD-PG Sum's summed
        rewards) and ``"d"`` (diversity)."""
        return {"alternate": ("q", "d"), "diversity": ("d",)}.get(self.update, ("q",))

    @property
    def num_mutations(self) -> int:
        """The offspring mutated per iteration: ``batch_size``, less the greedy
        actors that ``"qdax"`` plays beside them."""
        greedy = len(self.critics_in_use) if self.coupling == "qdax" else 0
        return self.batch_size - greedy

    def evaluate(self, params: Any, key: jax.Array, return_trajectory: bool = False):
        """The population's episodes, with ``exploration_noise`` on their actions."""
        return evaluate_policies(
            self.env, self.network.apply, params, key, return_trajectory,
            exploration_noise=self.exploration_noise,
        )  # fmt: skip

    def novelty_reward(self, archive: NoveltyArchive, batch: dict) -> jax.Array:
        """Fresh diversity rewards of a replay batch (Eq. 3.5)."""
        return archive.novelty(
            batch["state_descriptor"],
            self.archive_k,
            reduction=self.novelty_reduction,
            search=self.novelty_search,
        )

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
            repertoire, self.td3.init(k_q), self.td3.init(k_d), buffer, archive, key,
            no_statistics(),
        ), ev  # fmt: skip

    # ----- the thesis's coupling: each critic step uses the actor being improved -----

    def actor_rewards(
        self, archive: NoveltyArchive, batches: dict, diversity: jax.Array
    ) -> jax.Array:
        """The rewards each actor's critic steps train on, for ``batches`` with
        leading axes ``(steps, actors, batch)``: the environment's for a quality
        update, fresh novelty rewards for a diversity update, their sum for QD-PG
        Sum.  Novelty is computed only for the actors that use it (with
        ``"alternate"``, the ``actors // 2`` of ``diversity``)."""
        if self.update != "alternate":  # every actor's batches train the same critic
            return self.critic_rewards(archive, batches, self.update)
        # update_kinds gives exactly n // 2 diversity actors: their columns, first
        reward = batches["reward"]
        columns = jnp.argsort(~diversity, stable=True)[: reward.shape[1] // 2]
        novelty = self.novelty_reward(
            archive, {"state_descriptor": batches["state_descriptor"][:, columns]}
        )
        return reward.at[:, columns].set(novelty)

    def coupled_updates(
        self, state: QDPGState, parents: Any, diversity: jax.Array, key: jax.Array
    ) -> tuple[Any, TD3State, TD3State, dict]:
        """The thesis's coupling (module docstring): ``num_critic_steps`` critic
        steps, each a gradient per actor on its own replay batch with that actor
        (its target copy) as the TD3 target policy, averaged over the actors each
        critic drives; after every ``policy_delay`` of them, each actor takes a
        policy-gradient step against its critic (a fresh mutation optimiser per
        actor) and its target copy moves by ``tau``.  Returns the offspring, the two
        critics and the updates' statistics (``UPDATE_STATISTICS``)."""
        td3, cfg = self.td3, self.td3_config
        n, steps, delay = diversity.shape[0], self.num_critic_steps, cfg.policy_delay
        k_batch, k_noise = jax.random.split(key)
        rows = state.buffer.sample(k_batch, steps * n * cfg.batch_size)
        batches = jax.tree.map(lambda x: x.reshape((steps, n, cfg.batch_size) + x.shape[1:]), rows)
        batches = {**batches, "reward": self.actor_rewards(state.archive, batches, diversity)}
        # each critic's share of the actors' gradients: the mean over the actors it drives
        w_q = ~diversity / jnp.maximum(jnp.sum(~diversity), 1)
        w_d = diversity / jnp.maximum(jnp.sum(diversity), 1)
        opt = td3.mutation_optimizer

        def moved(critic: TD3State, weights: jax.Array, grads: Any) -> TD3State:
            """One step on the weighted actors' gradients; unchanged if it drives none."""
            new = td3.apply_critic_grads(critic, weighted_sum(weights, grads))
            return jax.tree.map(lambda a, b: jnp.where(jnp.any(weights > 0), a, b), new, critic)

        def critic_step(carry, inputs):
            q, d, actors, targets, opts = carry
            batch, keys = inputs
            critics = pick(diversity, d.critic, q.critic)
            critic_targets = pick(diversity, d.critic_target, q.critic_target)
            losses, grads = jax.vmap(td3.critic_grads)(
                critics, critic_targets, targets, batch, keys
            )
            stats = (
                jnp.dot(w_q, losses),
                jnp.dot(w_d, losses),
                optax.tree.norm(weighted_sum(w_q, grads)),
                optax.tree.norm(weighted_sum(w_d, grads)),
            )
            return (moved(q, w_q, grads), moved(d, w_d, grads), actors, targets, opts), stats

        def actor_step(carry, obs):
            q, d, actors, targets, opts = carry
            critics = pick(diversity, d.critic, q.critic)
            grads = jax.vmap(jax.grad(td3.actor_loss))(actors, critics, obs)
            updates, opts = jax.vmap(opt.update)(grads, opts)
            actors = optax.apply_updates(actors, updates)
            targets = jax.tree.map(lambda t, p: (1 - cfg.tau) * t + cfg.tau * p, targets, actors)
            return (q, d, actors, targets, opts), jnp.max(jax.vmap(optax.tree.norm)(grads))

        def block(carry, inputs):
            carry, stats = jax.lax.scan(critic_step, carry, inputs)
            carry, actor_norm = actor_step(carry, inputs[0]["obs"][-1])
            return carry, (stats, actor_norm)

        blocks = jax.tree.map(
            lambda x: x.reshape((steps // delay, delay) + x.shape[1:]),
            (batches, jax.random.split(k_noise, (steps, n))),
        )
        carry = (state.q_critic, state.d_critic, parents, parents, jax.vmap(opt.init)(parents))
        (q, d, offspring, _, _), ((loss_q, loss_d, norm_q, norm_d), norm_a) = jax.lax.scan(
            block, carry, blocks
        )
        stats = dict(
            critic_loss_q=jnp.mean(loss_q),
            critic_loss_d=jnp.mean(loss_d),
            critic_grad_norm_q=jnp.max(norm_q),
            critic_grad_norm_d=jnp.max(norm_d),
            actor_grad_norm=jnp.max(norm_a),
        )
        return offspring, q, d, stats

    # ----- the greedy couplings: critics trained against their own greedy actors -----

    def train_critics(self, state: QDPGState, key: jax.Array) -> tuple[TD3State, TD3State, dict]:
        """Train the critics the variant uses for ``num_critic_steps`` steps each,
        with their own greedy actors (the others stay as they are); and the
        statistics of ``UPDATE_STATISTICS`` they give (their mean losses)."""
        td3, k_q, k_d = self.td3, *jax.random.split(key)
        rewards = lambda critic: lambda batch: self.critic_rewards(state.archive, batch, critic)
        q_critic, d_critic, stats = state.q_critic, state.d_critic, no_statistics()
        if "q" in self.critics_in_use:
            kind = "sum" if self.update == "sum" else "quality"
            q_critic, stats["critic_loss_q"] = td3.train_critic(
                q_critic, state.buffer, k_q, self.num_critic_steps, rewards(kind)
            )
        if "d" in self.critics_in_use:
            d_critic, stats["critic_loss_d"] = td3.train_critic(
                d_critic, state.buffer, k_d, self.num_critic_steps, rewards("diversity")
            )
        return q_critic, d_critic, stats

    def mutate(self, state: QDPGState, parents: Any, diversity: jax.Array, key: jax.Array) -> Any:
        """``num_pg_steps`` TD3 actor steps for every parent, each against the
        critic its update kind names (the critics do not change)."""
        td3 = self.td3
        critics = pick(diversity, state.d_critic.critic, state.q_critic.critic)

        def one(actor, critic, k):
            return td3.policy_gradient_steps(actor, critic, state.buffer, k, self.num_pg_steps)

        return jax.vmap(one)(parents, critics, jax.random.split(key, diversity.shape[0]))

    def greedy_actors(self, state: QDPGState) -> Any:
        """The greedy actors of the critics in use, stacked (``"qdax"`` plays them)."""
        critics = {"q": state.q_critic, "d": state.d_critic}
        return stack([critics[c].actor for c in self.critics_in_use])

    def step(self, state: QDPGState) -> tuple[QDPGState, Evaluation]:
        key, k_sel, k_kind, k_pg, k_critic, k_eval = jax.random.split(state.key, 6)
        n = self.num_mutations
        parents = rep_lib.sample(state.repertoire, k_sel, n)
        diversity = update_kinds(k_kind, n, self.update)
        if self.coupling == "thesis":
            offspring, q_critic, d_critic, stats = self.coupled_updates(
                state, parents, diversity, k_pg
            )
        else:
            offspring = self.mutate(state, parents, diversity, k_pg)
            if self.coupling == "qdax":  # emitted before the critics train, as QDax's emitters
                offspring = concat(offspring, self.greedy_actors(state))
            q_critic, d_critic, stats = self.train_critics(state, k_critic)
        repertoire, ev = self.evaluate_and_insert(state.repertoire, offspring, k_eval)
        buffer, archive = self._record(state.buffer, state.archive, ev)
        return QDPGState(repertoire, q_critic, d_critic, buffer, archive, key, stats), ev

    def metrics(self, state: QDPGState) -> dict[str, jax.Array]:
        return {**super().metrics(state), "archive_size": state.archive.size, **state.updates}
