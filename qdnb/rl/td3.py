"""TD3 (Section 2.3.5; Fujimoto et al., 2018): twin critics, target policy
smoothing, delayed actor and target updates.

Pure functions over a ``TD3State`` pytree.  The pieces PGA-ME needs are
separate: ``critic_step`` trains the shared critic on replay batches and
``policy_gradient_steps`` improves any actor against it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable

import flax.linen as nn
import jax
import jax.numpy as jnp
import optax
from flax import struct

from qdnb.rl.networks import MLP


@dataclass(frozen=True)
class TD3Config:
    gamma: float = 0.99
    tau: float = 0.005
    policy_noise: float = 0.2
    noise_clip: float = 0.5
    policy_delay: int = 2
    critic_lr: float = 3e-4
    actor_lr: float = 3e-4
    batch_size: int = 256
    critic_hidden: tuple[int, ...] = (256, 256)
    optimizer: str = "adam"  # or "sgd" (plain stochastic gradient descent, Table 3.2)

    def __post_init__(self):
        if self.optimizer not in ("adam", "sgd"):
            raise ValueError(f"unknown optimizer {self.optimizer!r}; valid: adam, sgd")


class TwinCritic(nn.Module):
    """Two independent Q networks on (observation, action)."""

    hidden: tuple[int, ...]

    @nn.compact
    def __call__(self, obs: jax.Array, action: jax.Array) -> tuple[jax.Array, jax.Array]:
        x = jnp.concatenate([obs, action], axis=-1)
        q1 = MLP(self.hidden + (1,), activation="relu", final_activation=None, name="q1")(x)
        q2 = MLP(self.hidden + (1,), activation="relu", final_activation=None, name="q2")(x)
        return q1[..., 0], q2[..., 0]


def td3_target(reward: jax.Array, terminal: jax.Array, next_q1: jax.Array, next_q2: jax.Array,
               gamma: float) -> jax.Array:
    """y = r + gamma * (1 - terminal) * min(Q1', Q2') (clipped double Q-learning)."""
    return reward + gamma * (1.0 - terminal) * jnp.minimum(next_q1, next_q2)


@struct.dataclass
class TD3State:
    actor: Any
    actor_target: Any
    critic: Any
    critic_target: Any
    actor_opt: Any
    critic_opt: Any
    steps: jax.Array


@dataclass(frozen=True, eq=False)
class TD3:
    """TD3 for a deterministic ``actor`` network (tanh outputs in [-1, 1])."""

    actor: MLP
    observation_size: int
    action_size: int
    config: TD3Config = TD3Config()

    @property
    def critic(self) -> TwinCritic:
        return TwinCritic(self.config.critic_hidden)

    def _optimizer(self, learning_rate: float):
        return (optax.adam if self.config.optimizer == "adam" else optax.sgd)(learning_rate)

    @property
    def actor_optimizer(self):
        return self._optimizer(self.config.actor_lr)

    @property
    def critic_optimizer(self):
        return self._optimizer(self.config.critic_lr)

    def init(self, key: jax.Array) -> TD3State:
        k_a, k_c = jax.random.split(key)
        actor = self.actor.init(k_a, jnp.zeros((self.observation_size,)))
        critic = self.critic.init(k_c, jnp.zeros((self.observation_size,)), jnp.zeros((self.action_size,)))
        return TD3State(actor, actor, critic, critic, self.actor_optimizer.init(actor),
                        self.critic_optimizer.init(critic), jnp.zeros((), jnp.int32))

    def target(self, critic_target: Any, actor_target: Any, batch: dict, key: jax.Array) -> jax.Array:
        """TD3 target with target-policy smoothing: clipped Gaussian noise on the
        target actor's action."""
        cfg = self.config
        next_action = self.actor.apply(actor_target, batch["next_obs"])
        noise = jnp.clip(cfg.policy_noise * jax.random.normal(key, next_action.shape), -cfg.noise_clip, cfg.noise_clip)
        next_action = jnp.clip(next_action + noise, -1.0, 1.0)
        q1, q2 = self.critic.apply(critic_target, batch["next_obs"], next_action)
        return td3_target(batch["reward"], batch["terminal"], q1, q2, cfg.gamma)

    def critic_loss(self, critic: Any, batch: dict, y: jax.Array) -> jax.Array:
        q1, q2 = self.critic.apply(critic, batch["obs"], batch["action"])
        return jnp.mean((q1 - y) ** 2) + jnp.mean((q2 - y) ** 2)

    def actor_loss(self, actor: Any, critic: Any, obs: jax.Array) -> jax.Array:
        """Deterministic policy gradient objective: maximise Q1(s, pi(s))."""
        q1, _ = self.critic.apply(critic, obs, self.actor.apply(actor, obs))
        return -jnp.mean(q1)

    def critic_step(self, state: TD3State, batch: dict, key: jax.Array) -> tuple[TD3State, jax.Array]:
        """One critic update; the actor and both targets move every
        ``policy_delay`` steps (soft updates with rate ``tau``)."""
        cfg = self.config
        y = jax.lax.stop_gradient(self.target(state.critic_target, state.actor_target, batch, key))
        loss, grads = jax.value_and_grad(self.critic_loss)(state.critic, batch, y)
        updates, critic_opt = self.critic_optimizer.update(grads, state.critic_opt)
        critic = optax.apply_updates(state.critic, updates)

        def delayed(s: TD3State) -> TD3State:
            grads = jax.grad(self.actor_loss)(s.actor, critic, batch["obs"])
            updates, actor_opt = self.actor_optimizer.update(grads, s.actor_opt)
            actor = optax.apply_updates(s.actor, updates)
            soft = lambda t, p: (1 - cfg.tau) * t + cfg.tau * p
            return s.replace(actor=actor, actor_opt=actor_opt,
                             actor_target=jax.tree.map(soft, s.actor_target, actor),
                             critic_target=jax.tree.map(soft, s.critic_target, critic))

        state = state.replace(critic=critic, critic_opt=critic_opt, steps=state.steps + 1)
        state = jax.lax.cond(state.steps % cfg.policy_delay == 0, delayed, lambda s: s, state)
        return state, loss

    def policy_gradient_steps(self, actor: Any, critic: Any, buffer, key: jax.Array, num_steps: int) -> Any:
        """Improve one actor with ``num_steps`` Adam steps (fresh optimiser state),
        each on its own replay batch, against a fixed critic: the policy-gradient
        variation of PGA-ME."""
        opt = self.actor_optimizer

        def one(carry, k):
            params, opt_state = carry
            obs = buffer.sample(k, self.config.batch_size)["obs"]
            grads = jax.grad(self.actor_loss)(params, critic, obs)
            updates, opt_state = opt.update(grads, opt_state)
            return (optax.apply_updates(params, updates), opt_state), None

        (actor, _), _ = jax.lax.scan(one, (actor, opt.init(actor)), jax.random.split(key, num_steps))
        return actor

    def train_critic(self, state: TD3State, buffer, key: jax.Array, num_steps: int,
                     reward_fn: Callable[[dict], jax.Array] | None = None) -> tuple[TD3State, jax.Array]:
        """``num_steps`` critic steps (with the delayed actor/target updates) on
        replay batches; returns the mean critic loss.  ``reward_fn(batch)``, when
        given, replaces each sampled batch's rewards (QD-PG's fresh novelty
        rewards, Eq. 3.5)."""

        def one(s, k):
            k_batch, k_noise = jax.random.split(k)
            batch = buffer.sample(k_batch, self.config.batch_size)
            if reward_fn is not None:
                batch = {**batch, "reward": reward_fn(batch)}
            return self.critic_step(s, batch, k_noise)

        state, losses = jax.lax.scan(one, state, jax.random.split(key, num_steps))
        return state, jnp.mean(losses)
