"""SAC, the Soft Actor-Critic baseline of Table 3.4 (Haarnoja et al., 2018, "Soft
Actor-Critic Algorithms and Applications", arXiv:1812.05905: the version with twin
critics and automatic temperature tuning).

Followed: a tanh-squashed Gaussian actor (``GaussianMLP``); two Q networks
(``TwinCritic``, shared with TD3) and their Polyak-averaged targets; the critics'
entropy-regularised target (J_Q of Section 4.2, the soft value V(s') inlined)

    y = r + gamma (1 - terminal) (min_i Q'_i(s', a') - alpha log pi(a'|s')),  a' ~ pi(.|s'),

the reparameterised actor objective J_pi (Section 4.2) ``E[alpha log pi(a|s) - min_i
Q_i(s, a)]``, and automatic temperature tuning (J(alpha), Section 5)
``E[-alpha (log pi(a|s) + H_target)]`` with ``H_target = -dim(A)``, written on ``log
alpha`` as in the authors' code (same sign, so every step goes the same way).  One
``update`` is one gradient step of Algorithm 1: critics, then actor, then temperature,
then targets.

Simplified, and why: SAC has no target actor and no policy delay, so TD3Config's
``policy_noise``, ``noise_clip`` and ``policy_delay`` are unused (its ``gamma``, ``tau``,
learning rates, batch size, critic sizes, optimiser and ``target_update_interval`` are
used, so that every Chapter 3 method reads one table).  The critic loss is the sum of
the two mean squared errors, TD3's (twice the paper's 1/2-weighted loss: the same steps
under Adam, doubled ones under SGD).  The temperature always uses Adam (the paper's
optimiser) whatever the networks'.  There is no warm-up of uniformly random actions:
the initial policy's unit-scale Gaussian already explores.

``SACAgent`` (the ``Algorithm`` of Table 3.4) is built like ``TD3Agent``; ``DIAYN``
(``qdnb.rl.diayn``) reuses ``SAC`` as its learner.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import jax
import jax.numpy as jnp
import optax
from flax import struct

from qdnb.core.evaluation import Evaluation
from qdnb.envs.base import Env
from qdnb.envs.rollout import evaluate_policies
from qdnb.nets.mlp import MLP, GaussianMLP, tanh_gaussian_sample
from qdnb.rl.buffer import ReplayBuffer
from qdnb.rl.td3 import TD3Config, TwinCritic, td3_target


def sac_target(
    reward: jax.Array,
    terminal: jax.Array,
    next_q1: jax.Array,
    next_q2: jax.Array,
    next_log_prob: jax.Array,
    alpha: jax.Array | float,
    gamma: float,
) -> jax.Array:
    """y = r + gamma (1 - terminal) (min(Q1', Q2') - alpha log pi(a'|s')): TD3's clipped
    double-Q target on the soft values Q_i' - alpha log pi (the same min, shifted)."""
    soft = alpha * next_log_prob
    return td3_target(reward, terminal, next_q1 - soft, next_q2 - soft, gamma)


def sac_actor_objective(
    log_prob: jax.Array, q1: jax.Array, q2: jax.Array, alpha: jax.Array | float
) -> jax.Array:
    """J_pi: mean of alpha log pi(a|s) - min(Q1, Q2)(s, a), a ~ pi(.|s) (minimised)."""
    return jnp.mean(alpha * log_prob - jnp.minimum(q1, q2))


def temperature_loss(log_alpha: jax.Array, log_prob: jax.Array, target_entropy: float) -> jax.Array:
    """J(alpha) on log alpha: -log_alpha * mean(log pi + H_target), the log-probabilities
    held fixed.  Its gradient -(mean log pi + H_target) = entropy - H_target is negative,
    so alpha rises, when the policy's entropy -log pi is below the target."""
    return -log_alpha * jnp.mean(jax.lax.stop_gradient(log_prob + target_entropy))


def sample_batches(buffer: ReplayBuffer, key: jax.Array, num_steps: int, batch_size: int) -> dict:
    """``num_steps`` replay batches at once: leaves shaped ``(num_steps, batch_size, ...)``."""
    flat = buffer.sample(key, num_steps * batch_size)
    return jax.tree.map(lambda x: x.reshape((num_steps, batch_size) + x.shape[1:]), flat)


@struct.dataclass
class SACState:
    actor: Any
    critic: Any
    critic_target: Any
    log_alpha: jax.Array
    actor_opt: Any
    critic_opt: Any
    alpha_opt: Any
    steps: jax.Array


@dataclass(frozen=True, eq=False)
class SAC:
    """SAC's learner for a ``GaussianMLP`` actor over ``observation_size`` inputs.

    ``alpha_lr = 0`` keeps the temperature fixed at ``initial_alpha`` (DIAYN's setting);
    the target entropy is ``-target_entropy_scale * action_size``.
    """

    actor: GaussianMLP
    observation_size: int
    action_size: int
    config: TD3Config = TD3Config()
    alpha_lr: float = 3e-4
    initial_alpha: float = 1.0
    target_entropy_scale: float = 1.0

    @property
    def critic(self) -> TwinCritic:
        return TwinCritic(self.config.critic_hidden)

    @property
    def target_entropy(self) -> float:
        return -self.target_entropy_scale * self.action_size

    def _optimizer(self, learning_rate: float):
        return (optax.adam if self.config.optimizer == "adam" else optax.sgd)(learning_rate)

    @property
    def actor_optimizer(self):
        return self._optimizer(self.config.actor_lr)

    @property
    def critic_optimizer(self):
        return self._optimizer(self.config.critic_lr)

    @property
    def alpha_optimizer(self):
        return optax.adam(self.alpha_lr)

    def init(self, key: jax.Array) -> SACState:
        k_a, k_c = jax.random.split(key)
        actor = self.actor.init(k_a, jnp.zeros((self.observation_size,)))
        critic = self.critic.init(
            k_c, jnp.zeros((self.observation_size,)), jnp.zeros((self.action_size,))
        )
        log_alpha = jnp.log(jnp.asarray(self.initial_alpha, jnp.float32))
        return SACState(
            actor=actor,
            critic=critic,
            critic_target=critic,
            log_alpha=log_alpha,
            actor_opt=self.actor_optimizer.init(actor),
            critic_opt=self.critic_optimizer.init(critic),
            alpha_opt=self.alpha_optimizer.init(log_alpha),
            steps=jnp.zeros((), jnp.int32),
        )

    # -- the policy ---------------------------------------------------------------------

    def sample(self, actor: Any, obs: jax.Array, key: jax.Array) -> tuple[jax.Array, jax.Array]:
        """a ~ pi(.|obs) (reparameterised) and log pi(a|obs)."""
        mean, log_std = self.actor.apply(actor, obs)
        return tanh_gaussian_sample(mean, log_std, key)

    def greedy(self, actor: Any, obs: jax.Array) -> jax.Array:
        """The deterministic action tanh(mean), the one whose return is the performance."""
        return jnp.tanh(self.actor.apply(actor, obs)[0])

    def rollout_action(self, params: dict, obs: jax.Array, key: jax.Array) -> jax.Array:
        """A keyed policy for ``evaluate_policies(..., stochastic=True)``: ``params`` holds
        the ``actor`` and a ``greedy`` flag choosing tanh(mean) or a sample, so that
        greedy and exploring episodes play in one batch."""
        return jnp.where(
            params["greedy"],
            self.greedy(params["actor"], obs),
            self.sample(params["actor"], obs, key)[0],
        )

    # -- the losses ---------------------------------------------------------------------

    def target(
        self, critic_target: Any, actor: Any, alpha: jax.Array, batch: dict, key: jax.Array
    ) -> jax.Array:
        """The entropy-regularised target, a' drawn from the current actor (no target actor)."""
        next_action, next_log_prob = self.sample(actor, batch["next_obs"], key)
        q1, q2 = self.critic.apply(critic_target, batch["next_obs"], next_action)
        return sac_target(
            batch["reward"], batch["terminal"], q1, q2, next_log_prob, alpha, self.config.gamma
        )

    def critic_loss(self, critic: Any, batch: dict, y: jax.Array) -> jax.Array:
        q1, q2 = self.critic.apply(critic, batch["obs"], batch["action"])
        return jnp.mean((q1 - y) ** 2) + jnp.mean((q2 - y) ** 2)

    def actor_loss(
        self, actor: Any, critic: Any, alpha: jax.Array, obs: jax.Array, key: jax.Array
    ) -> tuple[jax.Array, jax.Array]:
        """J_pi and, as auxiliary output, the sampled actions' log pi."""
        action, log_prob = self.sample(actor, obs, key)
        q1, q2 = self.critic.apply(critic, obs, action)
        return sac_actor_objective(log_prob, q1, q2, alpha), log_prob

    # -- the updates --------------------------------------------------------------------

    def update(self, state: SACState, batch: dict, key: jax.Array) -> tuple[SACState, dict]:
        """One gradient step of Algorithm 1 on ``batch``: critics, actor (against the new
        critics), temperature (on the actor's log pi), then a soft update (rate ``tau``) of
        the target critics every ``target_update_interval`` steps.  Returns the losses."""
        cfg = self.config
        k_target, k_actor = jax.random.split(key)
        alpha = jnp.exp(state.log_alpha)

        y = jax.lax.stop_gradient(
            self.target(state.critic_target, state.actor, alpha, batch, k_target)
        )
        critic_loss, grads = jax.value_and_grad(self.critic_loss)(state.critic, batch, y)
        updates, critic_opt = self.critic_optimizer.update(grads, state.critic_opt)
        critic = optax.apply_updates(state.critic, updates)

        (actor_loss, log_prob), grads = jax.value_and_grad(self.actor_loss, has_aux=True)(
            state.actor, critic, alpha, batch["obs"], k_actor
        )
        updates, actor_opt = self.actor_optimizer.update(grads, state.actor_opt)
        actor = optax.apply_updates(state.actor, updates)

        alpha_loss, grad = jax.value_and_grad(temperature_loss)(
            state.log_alpha, log_prob, self.target_entropy
        )
        updates, alpha_opt = self.alpha_optimizer.update(grad, state.alpha_opt)
        log_alpha = optax.apply_updates(state.log_alpha, updates)

        steps = state.steps + 1
        move = steps % cfg.target_update_interval == 0
        critic_target = jax.tree.map(
            lambda t, p: jnp.where(move, (1 - cfg.tau) * t + cfg.tau * p, t),
            state.critic_target,
            critic,
        )
        new = SACState(
            actor, critic, critic_target, log_alpha, actor_opt, critic_opt, alpha_opt, steps
        )
        losses = {"critic": critic_loss, "actor": actor_loss, "alpha": alpha_loss}
        return new, losses

    def train(
        self, state: SACState, buffer: ReplayBuffer, key: jax.Array, num_steps: int
    ) -> tuple[SACState, dict]:
        """``num_steps`` updates, each on its own replay batch; returns the mean losses."""
        k_batch, k_steps = jax.random.split(key)
        batches = sample_batches(buffer, k_batch, num_steps, self.config.batch_size)
        state, losses = jax.lax.scan(
            lambda s, bk: self.update(s, *bk),
            state,
            (batches, jax.random.split(k_steps, num_steps)),
        )
        return state, jax.tree.map(jnp.mean, losses)


def check_agent_fields(agent) -> None:
    """The ValueErrors shared by the SAC-based agents (SAC, DIAYN)."""
    positive = ("num_episodes", "num_critic_steps", "buffer_size", "initial_alpha")
    for name in positive:
        if not getattr(agent, name) > 0:
            raise ValueError(f"{name} must be > 0, got {getattr(agent, name)}")
    if agent.alpha_lr < 0:
        raise ValueError(f"alpha_lr must be >= 0 (0: fixed temperature), got {agent.alpha_lr}")
    if agent.network.layer_sizes[-1] != agent.env.action_size:
        raise ValueError(
            f"network's last layer ({agent.network.layer_sizes[-1]}) must be the action size "
            f"({agent.env.action_size})"
        )


def gaussian_actor(network: MLP, action_size: int) -> GaussianMLP:
    """The stochastic actor with the task's policy torso (``network`` minus its output layer)."""
    return GaussianMLP(tuple(network.layer_sizes[:-1]), action_size, network.activation)


def repeat(tree: Any, n: int) -> Any:
    """``n`` copies of every leaf along a new leading axis (one per episode)."""
    return jax.tree.map(lambda x: jnp.repeat(x[None], n, axis=0), tree)


@struct.dataclass
class SACAgentState:
    sac: SACState
    buffer: ReplayBuffer
    performance: jax.Array  # fitness of the last greedy episode
    key: jax.Array


@dataclass(frozen=True, eq=False)
class SACAgent:
    """The SAC baseline (Table 3.4): one stochastic actor and its twin critics.

    Each iteration SAC makes ``num_critic_steps`` gradient steps (critics, actor and
    temperature each) on the replay buffer, then plays ``num_episodes`` episodes, all
    stored: the first greedy (tanh of the mean; its return is the performance), the
    others sampled from the policy.

    Defaults (SAC paper, Table 1 unless said): temperature learning rate 3e-4 (Adam, the
    same rate as every network), target entropy -dim(A) (``target_entropy_scale`` 1;
    Section 5), initial temperature 1 (not in the paper: the authors' softlearning code
    starts log alpha at 0).  Network sizes, learning rates, gamma (0.99), tau (0.005),
    batch (256) and the optimiser come from the task's ``td3_config``; buffer 1e6.
    """

    env: Env
    network: MLP
    td3_config: TD3Config = TD3Config()
    num_episodes: int = 4
    num_critic_steps: int = 100
    buffer_size: int = 1_000_000
    alpha_lr: float = 3e-4
    initial_alpha: float = 1.0
    target_entropy_scale: float = 1.0

    def __post_init__(self):
        check_agent_fields(self)

    @property
    def sac(self) -> SAC:
        return SAC(
            gaussian_actor(self.network, self.env.action_size),
            self.env.observation_size,
            self.env.action_size,
            self.td3_config,
            self.alpha_lr,
            self.initial_alpha,
            self.target_entropy_scale,
        )

    def _play(self, sac_state: SACState, buffer: ReplayBuffer, key: jax.Array):
        params = {
            "actor": repeat(sac_state.actor, self.num_episodes),
            "greedy": jnp.arange(self.num_episodes) == 0,
        }
        ev = evaluate_policies(
            self.env, self.sac.rollout_action, params, key, True, stochastic=True
        )
        return buffer.add_episodes(ev.trajectory, 1), ev

    def init(self, key: jax.Array) -> tuple[SACAgentState, Evaluation]:
        k_init, k_eval, key = jax.random.split(key, 3)
        env = self.env
        sac_state = self.sac.init(k_init)
        buffer = ReplayBuffer.create(self.buffer_size, env.observation_size, env.action_size)
        buffer, ev = self._play(sac_state, buffer, k_eval)
        return SACAgentState(sac_state, buffer, ev.fitness[0], key), ev

    def step(self, state: SACAgentState) -> tuple[SACAgentState, Evaluation]:
        key, k_train, k_eval = jax.random.split(state.key, 3)
        sac_state, _ = self.sac.train(state.sac, state.buffer, k_train, self.num_critic_steps)
        buffer, ev = self._play(sac_state, state.buffer, k_eval)
        return SACAgentState(sac_state, buffer, ev.fitness[0], key), ev

    def metrics(self, state: SACAgentState) -> dict[str, jax.Array]:
        return {"max_fitness": state.performance}
