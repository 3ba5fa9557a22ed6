"""DIAYN, "Diversity is All You Need" (Eysenbach et al., 2018, arXiv:1802.06070), the
unsupervised skill-discovery baseline of Table 3.4.

Followed (Algorithm 1): a skill z is drawn from a uniform p(z) over ``num_skills``
skills for each episode; the skill-conditioned policy pi(a | s, z) and its twin critics
Q(s, z, a) see the observation with the one-hot z appended, and are trained by SAC
(``qdnb.rl.sac``: its ``update`` is reused as is) on the pseudo-reward

    r = log q_phi(z | s') - log p(z)                       (Section 3.2, Algorithm 1)

where the discriminator q_phi (an MLP classifier, softmax over skills) is trained by
cross-entropy to recognise the skill from the state it reached.  The environment's
reward is ignored, as in the paper.  The discriminator and the SAC update share each
replay batch, one step each per gradient step, the reward computed with the current
discriminator (rewards are recomputed at sample time, never stored).  The buffer stores
each transition's skill index and the descriptor of s' beside it; the one-hot is
appended to the observations at sample time (50 one-hot columns stored twice per
transition would make the rows ten times wider).

Choices for the thesis's tasks: the discriminator sees the state *descriptor* (the x-y
position, Section 3.6.1) of s', ``next_state_descriptor``, rescaled from the
environment's descriptor bounds to [-1, 1], rather than the whole observation (as the
thesis reads DIAYN in Section 3.7: skills discriminated by where they go, which on
Ant-Trap is not what the reward measures).
Table 3.4's performance of DIAYN is that of its best skill (DIAYN has no single policy):
each iteration's first episode is greedy (tanh of the mean) for skill ``iteration mod
num_skills``, so the skills take turns at a greedy evaluation within the same episode
budget as every method, and ``max_fitness`` is the maximum over skills of each one's
latest greedy return (skills not yet evaluated count as -inf; skill 0 is evaluated by
``init``).  A skill's value can be up to ``num_skills`` iterations old: evaluating every
skill each iteration would cost ``num_skills`` extra episodes.

Defaults (the paper's experiments, as set in the authors' code, github.com/ben-eysenbach/sac,
``examples/mujoco_all_diayn.py``): 50 skills, discriminator hidden layers (300, 300),
learning rate 3e-4 (Adam), a fixed entropy coefficient alpha = 0.1 (``scale_entropy``;
``alpha_lr = 0`` keeps it fixed: the paper does not tune the temperature).  The
discriminator always uses Adam; the SAC networks, gamma, tau, batch size and optimiser
come from the task's ``td3_config`` (the paper's code: batch 128, tau 0.01).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import jax
import jax.numpy as jnp
import optax
from flax import struct

from qdnb.core.evaluation import Evaluation
from qdnb.envs.base import Env
from qdnb.envs.rollout import evaluate_policies
from qdnb.nets.mlp import MLP
from qdnb.rl.buffer import ReplayBuffer
from qdnb.rl.sac import SAC, SACState, check_agent_fields, gaussian_actor, repeat, sample_batches
from qdnb.rl.td3 import TD3Config


def diayn_reward(logits: jax.Array, skill: jax.Array) -> jax.Array:
    """r = log q(z | s') - log p(z), p uniform: log softmax(logits)[z] + log K, for one-hot
    ``skill`` (K = its last axis).  Positive when the discriminator beats chance."""
    num_skills = skill.shape[-1]
    return jnp.sum(jax.nn.log_softmax(logits) * skill, axis=-1) + math.log(num_skills)


def discriminator_loss(logits: jax.Array, skill: jax.Array) -> jax.Array:
    """Cross-entropy -mean log q(z | s') of the true skills (one-hot ``skill``)."""
    return -jnp.mean(jnp.sum(jax.nn.log_softmax(logits) * skill, axis=-1))


@struct.dataclass
class DIAYNState:
    sac: SACState
    discriminator: Any
    discriminator_opt: Any
    buffer: ReplayBuffer
    skill_returns: jax.Array  # (num_skills,) each skill's latest greedy return; -inf before
    iteration: jax.Array  # iterations played (init counts as one): the next greedy skill
    key: jax.Array


@dataclass(frozen=True, eq=False)
class DIAYN:
    """The DIAYN baseline (Table 3.4): skill-conditioned SAC on discriminability rewards.

    Each iteration makes ``num_critic_steps`` gradient steps (a SAC update and a
    discriminator step per replay batch), then plays ``num_episodes`` episodes, all
    stored: the first greedy for the skill whose turn it is, the others sampled from
    the policy, each with a skill drawn uniformly.  The buffer stores the skill and the
    descriptor of s', so that rewards are recomputed with the current discriminator at
    sample time.
    """

    env: Env
    network: MLP
    td3_config: TD3Config = TD3Config()
    num_episodes: int = 4
    num_critic_steps: int = 100
    buffer_size: int = 1_000_000
    num_skills: int = 50
    discriminator_hidden: tuple[int, ...] = (300, 300)
    discriminator_lr: float = 3e-4
    alpha_lr: float = 0.0
    initial_alpha: float = 0.1
    target_entropy_scale: float = 1.0

    def __post_init__(self):
        check_agent_fields(self)
        if self.num_skills < 2:
            raise ValueError(f"num_skills must be >= 2, got {self.num_skills}")
        if not self.discriminator_lr > 0:
            raise ValueError(f"discriminator_lr must be > 0, got {self.discriminator_lr}")

    @property
    def sac(self) -> SAC:
        return SAC(
            gaussian_actor(self.network, self.env.action_size),
            self.env.observation_size + self.num_skills,
            self.env.action_size,
            self.td3_config,
            self.alpha_lr,
            self.initial_alpha,
            self.target_entropy_scale,
        )

    @property
    def discriminator(self) -> MLP:
        return MLP(
            tuple(self.discriminator_hidden) + (self.num_skills,),
            activation="relu",
            final_activation=None,
        )

    @property
    def discriminator_optimizer(self):
        return optax.adam(self.discriminator_lr)

    # -- the discriminator --------------------------------------------------------------

    def logits(self, discriminator: Any, descriptor: jax.Array) -> jax.Array:
        """q_phi's logits for state descriptors, rescaled from the environment's bounds
        to [-1, 1]."""
        low, high = self.env.descriptor_bounds
        return self.discriminator.apply(discriminator, 2 * (descriptor - low) / (high - low) - 1)

    def reward(self, discriminator: Any, descriptor: jax.Array, skill: jax.Array) -> jax.Array:
        """The pseudo-reward of reaching ``descriptor`` under one-hot ``skill``, with the
        current discriminator."""
        return diayn_reward(self.logits(discriminator, descriptor), skill)

    def conditioned(self, batch: dict) -> tuple[dict, jax.Array]:
        """A replay batch for the skill-conditioned SAC: the one-hot of its stored skill
        index appended to ``obs`` and ``next_obs``; and that one-hot."""
        z = jax.nn.one_hot(batch["skill"].astype(jnp.int32), self.num_skills)
        cat = lambda x: jnp.concatenate([x, z], axis=-1)
        return {**batch, "obs": cat(batch["obs"]), "next_obs": cat(batch["next_obs"])}, z

    def discriminator_step(
        self, discriminator: Any, opt_state: Any, descriptor: jax.Array, skill: jax.Array
    ) -> tuple[Any, Any, jax.Array]:
        """One Adam step of the cross-entropy of q_phi(z | descriptor); returns the loss."""
        loss, grads = jax.value_and_grad(
            lambda p: discriminator_loss(self.logits(p, descriptor), skill)
        )(discriminator)
        updates, opt_state = self.discriminator_optimizer.update(grads, opt_state)
        return optax.apply_updates(discriminator, updates), opt_state, loss

    # -- training and playing -----------------------------------------------------------

    def train(self, state: DIAYNState, key: jax.Array) -> DIAYNState:
        """``num_critic_steps`` gradient steps, each on its own replay batch: the SAC
        update on the batch's fresh pseudo-rewards, then a discriminator step."""
        sac = self.sac
        k_batch, k_steps = jax.random.split(key)
        batches = sample_batches(
            state.buffer, k_batch, self.num_critic_steps, self.td3_config.batch_size
        )

        def one(carry, inputs):
            sac_state, disc, disc_opt = carry
            batch, k = inputs
            batch, z = self.conditioned(batch)
            descriptor = batch["next_state_descriptor"]
            reward = jax.lax.stop_gradient(self.reward(disc, descriptor, z))
            sac_state, _ = sac.update(sac_state, {**batch, "reward": reward}, k)
            disc, disc_opt, _ = self.discriminator_step(disc, disc_opt, descriptor, z)
            return (sac_state, disc, disc_opt), None

        (sac_state, disc, disc_opt), _ = jax.lax.scan(
            one,
            (state.sac, state.discriminator, state.discriminator_opt),
            (batches, jax.random.split(k_steps, self.num_critic_steps)),
        )
        return state.replace(sac=sac_state, discriminator=disc, discriminator_opt=disc_opt)

    def _policy(self, params: dict, obs: jax.Array, key: jax.Array) -> jax.Array:
        return self.sac.rollout_action(params, jnp.concatenate([obs, params["skill"]]), key)

    def _play(self, state: DIAYNState, key: jax.Array) -> tuple[DIAYNState, Evaluation]:
        """One batch of episodes: the first greedy for skill ``iteration mod num_skills``,
        the others sampled, with uniform skills; every transition stored with its skill."""
        n, k_skills = self.num_episodes, self.num_skills
        k_skill, k_eval = jax.random.split(key)
        turn = state.iteration % k_skills
        skills = jax.random.randint(k_skill, (n,), 0, k_skills).at[0].set(turn)
        one_hot = jax.nn.one_hot(skills, k_skills)
        params = {"actor": repeat(state.sac.actor, n), "greedy": jnp.arange(n) == 0}
        ev = evaluate_policies(
            self.env, self._policy, {**params, "skill": one_hot}, k_eval, True, stochastic=True
        )
        traj = ev.trajectory
        traj = {**traj, "skill": jnp.broadcast_to(skills[:, None], traj["reward"].shape)}
        return state.replace(
            buffer=state.buffer.add_episodes(traj, 1),
            skill_returns=state.skill_returns.at[turn].set(ev.fitness[0]),
            iteration=state.iteration + 1,
        ), ev

    def _buffer(self) -> ReplayBuffer:
        """An empty buffer of ``create``'s transitions plus two fields per row: the
        descriptor of s' and the skill's index."""
        env = self.env
        fields = ReplayBuffer.create(1, env.observation_size, env.action_size).fields + (
            ("next_state_descriptor", (env.descriptor_size,)),
            ("skill", ()),
        )
        width = sum(math.prod(shape) for _, shape in fields)
        zero = jnp.zeros((), jnp.int32)
        return ReplayBuffer(jnp.zeros((self.buffer_size, width)), zero, zero, fields)

    def init(self, key: jax.Array) -> tuple[DIAYNState, Evaluation]:
        k_sac, k_disc, k_play, key = jax.random.split(key, 4)
        disc = self.discriminator.init(k_disc, jnp.zeros((self.env.descriptor_size,)))
        state = DIAYNState(
            sac=self.sac.init(k_sac),
            discriminator=disc,
            discriminator_opt=self.discriminator_optimizer.init(disc),
            buffer=self._buffer(),
            skill_returns=jnp.full((self.num_skills,), -jnp.inf),
            iteration=jnp.zeros((), jnp.int32),
            key=key,
        )
        return self._play(state, k_play)

    def step(self, state: DIAYNState) -> tuple[DIAYNState, Evaluation]:
        key, k_train, k_play = jax.random.split(state.key, 3)
        state = self.train(state.replace(key=key), k_train)
        return self._play(state, k_play)

    def metrics(self, state: DIAYNState) -> dict[str, jax.Array]:
        return {"max_fitness": jnp.max(state.skill_returns)}
