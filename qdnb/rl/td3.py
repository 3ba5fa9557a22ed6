"""TD3 (Section 2.3.5; Fujimoto et al., 2018): twin critics, target policy
smoothing, delayed actor updates.

Pure functions over a ``TD3State`` pytree.  The pieces PGA-ME needs are
separate: ``train_critic`` trains the shared critic (and its greedy actor) on
replay batches and ``policy_gradient_steps`` improves any actor against it.

Target networks follow QDax's PGA-ME and QD-PG emitters (the code Chapters 3
and 4 build on) and Table 3.2's "target update interval 1": the target critic
moves after every ``target_update_interval``-th critic step, the target actor
after every actor step (one actor step per ``policy_delay`` critic steps).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable

import flax.linen as nn
import jax
import jax.numpy as jnp
import optax
from flax import struct

from qdnb.nets.mlp import MLP


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
    target_update_interval: int = 1  # critic steps between soft updates of the target critic
    mutation_lr: float | None = None  # policy-gradient mutations (PGA-ME, QD-PG); None: actor_lr

    def __post_init__(self):
        if self.optimizer not in ("adam", "sgd"):
            raise ValueError(f"unknown optimizer {self.optimizer!r}; valid: adam, sgd")
        if self.policy_delay < 1 or self.target_update_interval < 1:
            raise ValueError(
                f"policy_delay and target_update_interval must be >= 1, got "
                f"{self.policy_delay} and {self.target_update_interval}"
            )


class TwinCritic(nn.Module):
    """Two independent Q networks on (observation, action)."""

    hidden: tuple[int, ...]

    @nn.compact
    def __call__(self, obs: jax.Array, action: jax.Array) -> tuple[jax.Array, jax.Array]:
        x = jnp.concatenate([obs, action], axis=-1)
        q1 = MLP(self.hidden + (1,), activation="relu", final_activation=None, name="q1")(x)
        q2 = MLP(self.hidden + (1,), activation="relu", final_activation=None, name="q2")(x)
        return q1[..., 0], q2[..., 0]


def td3_target(
    reward: jax.Array, terminal: jax.Array, next_q1: jax.Array, next_q2: jax.Array, gamma: float
) -> jax.Array:
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

    @property
    def mutation_optimizer(self):
        lr = self.config.mutation_lr
        return self._optimizer(self.config.actor_lr if lr is None else lr)

    def init(self, key: jax.Array) -> TD3State:
        k_a, k_c = jax.random.split(key)
        actor = self.actor.init(k_a, jnp.zeros((self.observation_size,)))
        critic = self.critic.init(
            k_c, jnp.zeros((self.observation_size,)), jnp.zeros((self.action_size,))
        )
        return TD3State(
            actor,
            actor,
            critic,
            critic,
            self.actor_optimizer.init(actor),
            self.critic_optimizer.init(critic),
            jnp.zeros((), jnp.int32),
        )

    def target(
        self, critic_target: Any, actor_target: Any, batch: dict, key: jax.Array
    ) -> jax.Array:
        """TD3 target with target-policy smoothing: clipped Gaussian noise on the
        target actor's action."""
        cfg = self.config
        next_action = self.actor.apply(actor_target, batch["next_obs"])
        noise = jnp.clip(
            cfg.policy_noise * jax.random.normal(key, next_action.shape),
            -cfg.noise_clip,
            cfg.noise_clip,
        )
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

    def critic_grads(
        self, critic: Any, critic_target: Any, actor_target: Any, batch: dict, key: jax.Array
    ) -> tuple[jax.Array, Any]:
        """The loss and gradient of one critic step whose TD target is computed by
        ``critic_target`` with ``actor_target`` as the target policy."""
        y = jax.lax.stop_gradient(self.target(critic_target, actor_target, batch, key))
        return jax.value_and_grad(self.critic_loss)(critic, batch, y)

    def apply_critic_grads(self, state: TD3State, grads: Any) -> TD3State:
        """One optimiser step of the critic, then a soft update (rate ``tau``) of the
        target critic when the step count is a multiple of ``target_update_interval``."""
        cfg = self.config
        updates, critic_opt = self.critic_optimizer.update(grads, state.critic_opt)
        critic = optax.apply_updates(state.critic, updates)
        steps = state.steps + 1
        move = steps % cfg.target_update_interval == 0
        target = jax.tree.map(
            lambda t, p: jnp.where(move, (1 - cfg.tau) * t + cfg.tau * p, t),
            state.critic_target,
            critic,
        )
        return state.replace(
            critic=critic, critic_opt=critic_opt, critic_target=target, steps=steps
        )

    def critic_step(
        self, state: TD3State, batch: dict, key: jax.Array
    ) -> tuple[TD3State, jax.Array]:
        """One critic update against the state's own target actor (``apply_critic_grads``)."""
        loss, grads = self.critic_grads(
            state.critic, state.critic_target, state.actor_target, batch, key
        )
        return self.apply_critic_grads(state, grads), loss

    def actor_step(self, state: TD3State, obs: jax.Array) -> TD3State:
        """One step of the greedy actor against the current critic, then a soft
        update of the target actor."""
        tau = self.config.tau
        grads = jax.grad(self.actor_loss)(state.actor, state.critic, obs)
        updates, actor_opt = self.actor_optimizer.update(grads, state.actor_opt)
        actor = optax.apply_updates(state.actor, updates)
        target = jax.tree.map(lambda t, p: (1 - tau) * t + tau * p, state.actor_target, actor)
        return state.replace(actor=actor, actor_opt=actor_opt, actor_target=target)

    def policy_gradient_steps(
        self, actor: Any, critic: Any, buffer, key: jax.Array, num_steps: int
    ) -> Any:
        """Improve one actor with ``num_steps`` steps of the mutation optimiser
        (fresh state, rate ``mutation_lr``), each on its own replay batch, against
        a fixed critic: the policy-gradient variation of PGA-ME and QD-PG."""
        opt = self.mutation_optimizer

        def one(carry, k):
            params, opt_state = carry
            obs = buffer.sample(k, self.config.batch_size)["obs"]
            grads = jax.grad(self.actor_loss)(params, critic, obs)
            updates, opt_state = opt.update(grads, opt_state)
            return (optax.apply_updates(params, updates), opt_state), None

        (actor, _), _ = jax.lax.scan(
            one, (actor, opt.init(actor)), jax.random.split(key, num_steps)
        )
        return actor

    def train_critic(
        self,
        state: TD3State,
        buffer,
        key: jax.Array,
        num_steps: int,
        reward_fn: Callable[[dict], jax.Array] | None = None,
    ) -> tuple[TD3State, jax.Array]:
        """``num_steps`` critic steps on replay batches, with one greedy-actor step
        after every ``policy_delay`` of them (on the last of their batches);
        returns the mean critic loss.

        Every batch is drawn up front (``num_steps`` batches of ``batch_size``);
        ``reward_fn(batches)``, when given, replaces their rewards in one call
        (leaves with leading axes ``(num_steps, batch_size)``: QD-PG's fresh
        novelty rewards, Eq. 3.5, for the whole iteration in one pass).  The
        delay is a fixed loop structure, not a branch, so that a ``vmap`` over
        seeds runs the actor step only when it is due.
        """
        delay = self.config.policy_delay
        if num_steps % delay:
            raise ValueError(f"num_steps={num_steps} must be a multiple of policy_delay={delay}")
        k_batch, k_noise = jax.random.split(key)
        batches = buffer.sample(k_batch, num_steps * self.config.batch_size)
        batches = jax.tree.map(
            lambda x: x.reshape((num_steps, self.config.batch_size) + x.shape[1:]), batches
        )
        if reward_fn is not None:
            batches = {**batches, "reward": reward_fn(batches)}
        blocks = jax.tree.map(
            lambda x: x.reshape((num_steps // delay, delay) + x.shape[1:]),
            (batches, jax.random.split(k_noise, num_steps)),
        )

        def block(s, inputs):
            s, losses = jax.lax.scan(lambda s, bk: self.critic_step(s, *bk), s, inputs)
            return self.actor_step(s, inputs[0]["obs"][-1]), losses

        state, losses = jax.lax.scan(block, state, blocks)
        return state, jnp.mean(losses)
