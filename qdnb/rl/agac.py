"""AGAC, the Adversarially Guided Actor-Critic baseline of Chapter 3 (Table 3.4).

Flet-Berliac, Ferret, Pietquin, Preux and Geist (2021), "Adversarially Guided
Actor-Critic", ICLR 2021.  AGAC is PPO with a third network, the *adversary*
``pi_adv``, a policy trained to imitate the actor by minimising
``KL(pi_old(.|s) || pi_adv(.|s))``.  The actor is pushed away from what the adversary
predicts by an augmented advantage, and the critic learns the matching augmented
value:

    A_AGAC(s, a) = A_GAE(s, a) + c * (log pi_old(a|s) - log pi_adv(a|s))      (actor)
    V_target(s)  = V_old(s) + A_GAE(s, a) + c * KL(pi_old(.|s) || pi_adv(.|s))  (critic)

with ``c`` annealed linearly to 0 over training.  The actor maximises PPO's clipped
surrogate (Schulman et al., 2017) on ``A_AGAC``; ``A_GAE`` is Schulman et al.'s
(2016) generalised advantage estimate (``gae`` below, a pure function).

Followed: the equations above; the hyper-parameters of the authors' PyTorch
implementation for Point-Maze (``agac_torch/configs/point_maze.yaml`` in
github.com/yfletberliac/adversarially-guided-actor-critic, see ``AGACConfig``):
separate Adam optimisers (eps 1e-5) with gradient-norm clipping for the three
networks, no advantage normalisation, PPO epochs of shuffled minibatches over each
iteration's batch.

Simplified, and why:

- The policy is the book's tanh-squashed Gaussian (``GaussianMLP``, state-dependent
  log-std), not the reference's unsquashed Gaussian with a state-independent
  log-std clipped by the environment: every action stays in [-1, 1] in every
  environment of the book (not all of them clip), the greedy action ``tanh(mean)``
  has the form of the deterministic policies, and nothing is lost: tanh is one
  bijection shared by ``pi`` and ``pi_adv``, so ``KL(pi || pi_adv)`` equals the
  closed-form KL of their pre-squash Gaussians, and the squash corrections cancel
  in ``log pi(a|s) - log pi_adv(a|s)`` and in PPO's ratio.  The entropy bonus (0 by
  default, as in the reference) is the pre-squash Gaussian's.
- Data: each iteration plays exactly ``num_episodes`` episodes in one
  ``evaluate_policies`` call.  The first is greedy (``tanh(mean)``): its return is
  the performance (``max_fitness``), and it is left out of the PPO batch, whose
  data must come from ``pi`` itself; the others sample from ``pi``.  The reference
  updates every 1000 environment steps; here, once per iteration.
- No value clipping (the reference's clip, 1000, never binds); the adversary's loss
  coefficient (4e-5) is dropped: each network has its own Adam, which is invariant
  to the scale of its loss (up to Adam's epsilon).
- ``num_iterations`` sets the annealing horizon of ``c`` (the run's length, which
  the agent cannot know); ``None`` keeps ``c`` constant.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp
import optax
from flax import struct

from qdnb.core.evaluation import Evaluation
from qdnb.envs.base import Env
from qdnb.envs.rollout import evaluate_policies
from qdnb.nets.mlp import MLP, GaussianMLP, tanh_gaussian_log_prob, tanh_gaussian_sample


# --------------------------------------------------------------------------- pure functions
def gae(
    reward: jax.Array,
    value: jax.Array,
    next_value: jax.Array,
    terminal: jax.Array,
    done: jax.Array,
    valid: jax.Array,
    gamma: float,
    lam: float,
) -> jax.Array:
    """Generalised advantage estimates (Schulman et al., 2016, Eq. 16) of a batch of
    episodes, every array with axes ``(batch, time)``:

        delta_t = r_t + gamma * (1 - terminal_t) * V(s_{t+1}) - V(s_t)
        A_t     = delta_t + gamma * lam * (1 - done_t) * A_{t+1}

    An episode cut by the time limit (``done`` but not ``terminal``) bootstraps on
    ``V(s_{t+1})`` in its last ``delta``; no advantage flows back across an episode's
    end.  Steps outside the episode (``valid`` false) get 0.
    """
    f32 = lambda x: jnp.asarray(x, jnp.float32)
    delta = f32(reward) + gamma * (1.0 - f32(terminal)) * f32(next_value) - f32(value)

    def back(next_adv, x):
        d, end, ok = x
        adv = (d + gamma * lam * (1.0 - end) * next_adv) * ok
        return adv, adv

    time_major = (delta.T, f32(done).T, f32(valid).T)
    _, adv = jax.lax.scan(back, jnp.zeros(delta.shape[0]), time_major, reverse=True)
    return adv.T


def agac_advantage(
    advantage: jax.Array, log_pi: jax.Array, log_pi_adv: jax.Array, c: jax.Array | float
) -> jax.Array:
    """AGAC's advantage: ``A_GAE + c * (log pi(a|s) - log pi_adv(a|s))``, the bonus
    for taking an action the adversary did not predict."""
    return advantage + c * (log_pi - log_pi_adv)


def masked_mean(x: jax.Array, mask: jax.Array) -> jax.Array:
    """Mean of ``x`` over the entries where ``mask`` is true (0 if there are none)."""
    mask = jnp.asarray(mask, x.dtype)
    return jnp.sum(x * mask) / jnp.maximum(jnp.sum(mask), 1.0)


def ppo_clip_loss(
    log_pi: jax.Array,
    log_pi_old: jax.Array,
    advantage: jax.Array,
    mask: jax.Array,
    clip: float,
) -> jax.Array:
    """PPO's clipped surrogate, negated to be minimised (Schulman et al., 2017, Eq. 7):
    ``-E[min(rho * A, clip(rho, 1 - eps, 1 + eps) * A)]``, ``rho = pi / pi_old``."""
    ratio = jnp.exp(log_pi - log_pi_old)
    clipped = jnp.clip(ratio, 1.0 - clip, 1.0 + clip)
    return -masked_mean(jnp.minimum(ratio * advantage, clipped * advantage), mask)


def gaussian_kl(
    mean_p: jax.Array, log_std_p: jax.Array, mean_q: jax.Array, log_std_q: jax.Array
) -> jax.Array:
    """KL(p || q) of two diagonal Gaussians, summed over the last axis (also the KL of
    their tanh-squashed versions: KL is invariant under a shared bijection)."""
    var_ratio = jnp.exp(2.0 * (log_std_p - log_std_q))
    gap = ((mean_p - mean_q) * jnp.exp(-log_std_q)) ** 2
    return jnp.sum(log_std_q - log_std_p + 0.5 * (var_ratio + gap - 1.0), axis=-1)


def gaussian_entropy(log_std: jax.Array) -> jax.Array:
    """Entropy of a diagonal Gaussian (the pre-squash one), summed over the last axis."""
    return jnp.sum(log_std + 0.5 * jnp.log(2.0 * jnp.pi * jnp.e), axis=-1)


# --------------------------------------------------------------------------- the agent
@dataclass(frozen=True)
class AGACConfig:
    """AGAC's hyper-parameters.  The thesis gives none; the defaults are the authors'
    Point-Maze settings (``agac_torch/configs/point_maze.yaml`` of their code, the
    continuous-control version of the paper's PPO-based AGAC):

    - ``actor_lr``, ``critic_lr`` 3e-4; ``adversary_lr`` 9e-5 (their config; 0.3 times
      the actor's rate, as in their TensorFlow AGAC);
    - ``gamma`` 0.99, ``gae_lambda`` 0.95, ``clip`` 0.2 (PPO's epsilon);
    - ``agac_c`` 4e-4 (their ``intrinsic_reward_coefficient``), annealed linearly to
      0 over training (the paper; their trainer);
    - ``entropy_coef`` 0.0; ``value_loss_coef`` 0.25; ``max_grad_norm`` 0.5 (per
      network); Adam's ``adam_eps`` 1e-5;
    - ``num_epochs`` 30 passes over each iteration's batch, in minibatches of
      ``minibatch_size`` 512;
    - ``critic_hidden`` ``None``: the critic and the adversary share the policy
      torso's hidden sizes (their ``layers_dim`` = ``adv_layers_dim``).
    """

    actor_lr: float = 3e-4
    critic_lr: float = 3e-4
    adversary_lr: float = 9e-5
    gamma: float = 0.99
    gae_lambda: float = 0.95
    clip: float = 0.2
    agac_c: float = 4e-4
    entropy_coef: float = 0.0
    value_loss_coef: float = 0.25
    max_grad_norm: float = 0.5
    adam_eps: float = 1e-5
    num_epochs: int = 30
    minibatch_size: int = 512
    critic_hidden: tuple[int, ...] | None = None

    def __post_init__(self):
        positive = ("actor_lr", "critic_lr", "adversary_lr", "clip", "max_grad_norm")
        for name in positive:
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        for name in ("gamma", "gae_lambda"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(f"{name} must lie in [0, 1], got {getattr(self, name)}")
        for name in ("agac_c", "entropy_coef", "value_loss_coef", "adam_eps"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")
        if self.num_epochs < 1 or self.minibatch_size < 1:
            raise ValueError(
                f"num_epochs and minibatch_size must be >= 1, got "
                f"{self.num_epochs} and {self.minibatch_size}"
            )


class ValueNet(nn.Module):
    """The critic V(s): an MLP with a scalar output."""

    hidden: tuple[int, ...]

    @nn.compact
    def __call__(self, obs: jax.Array) -> jax.Array:
        return MLP(self.hidden + (1,), activation="relu", final_activation=None)(obs)[..., 0]


@struct.dataclass
class AGACState:
    actor: Any
    critic: Any
    adversary: Any
    actor_opt: Any
    critic_opt: Any
    adversary_opt: Any
    iteration: jax.Array  # PPO updates done so far (anneals c)
    performance: jax.Array  # return of the last greedy episode
    key: jax.Array


@dataclass(frozen=True, eq=False)
class AGACAgent:
    """The AGAC baseline (Table 3.4): actor, critic and adversary, trained on-policy.

    ``network`` is the task's deterministic policy architecture; its hidden sizes are
    the torso of the actor's and the adversary's ``GaussianMLP`` (and of the critic,
    unless ``config.critic_hidden``).  Each iteration plays ``num_episodes`` episodes,
    the first greedy (the performance, left out of training), the others sampled
    from ``pi``, then runs ``num_epochs`` PPO epochs on them.  ``num_iterations``,
    the run's length, is the horizon over which ``c`` decays to 0 (``None``: constant).
    There is no ``num_critic_steps`` nor replay buffer: AGAC is on-policy.
    """

    env: Env
    network: MLP
    num_episodes: int = 8
    config: AGACConfig = AGACConfig()
    num_iterations: int | None = None

    def __post_init__(self):
        if self.num_episodes < 2:
            raise ValueError(
                f"num_episodes must be >= 2 (one greedy episode plus training ones), "
                f"got {self.num_episodes}"
            )
        if self.network.layer_sizes[-1] != self.env.action_size:
            raise ValueError(
                f"network's last layer ({self.network.layer_sizes[-1]}) must be the "
                f"action size ({self.env.action_size})"
            )
        if self.num_iterations is not None and self.num_iterations < 1:
            raise ValueError(f"num_iterations must be >= 1 or None, got {self.num_iterations}")

    # ------------------------------------------------------------------ networks
    @property
    def policy(self) -> GaussianMLP:
        """The architecture of the actor and of the adversary."""
        return GaussianMLP(tuple(self.network.layer_sizes[:-1]), self.env.action_size)

    @property
    def critic(self) -> ValueNet:
        hidden = self.config.critic_hidden
        return ValueNet(tuple(self.network.layer_sizes[:-1]) if hidden is None else hidden)

    def _optimizer(self, learning_rate: float):
        cfg = self.config
        return optax.chain(
            optax.clip_by_global_norm(cfg.max_grad_norm),
            optax.adam(learning_rate, eps=cfg.adam_eps),
        )

    @property
    def optimizers(self):
        cfg = self.config
        return tuple(self._optimizer(lr) for lr in (cfg.actor_lr, cfg.critic_lr, cfg.adversary_lr))

    def agac_coefficient(self, iteration: jax.Array) -> jax.Array:
        """c at an iteration: ``agac_c * (1 - iteration / num_iterations)``, >= 0."""
        if self.num_iterations is None:
            return jnp.asarray(self.config.agac_c, jnp.float32)
        progress = jnp.asarray(iteration, jnp.float32) / self.num_iterations
        return self.config.agac_c * jnp.clip(1.0 - progress, 0.0, 1.0)

    # ------------------------------------------------------------------ acting
    def _act(self, params: tuple, obs: jax.Array, key: jax.Array) -> jax.Array:
        """One action of one episode: ``tanh(mean)`` if the episode is greedy, else a
        sample of ``pi``."""
        actor, greedy = params
        mean, log_std = self.policy.apply(actor, obs)
        action, _ = tanh_gaussian_sample(mean, log_std, key)
        return jnp.where(greedy, jnp.tanh(mean), action)

    def _play(self, actor: Any, key: jax.Array) -> Evaluation:
        n = self.num_episodes
        actors = jax.tree.map(lambda x: jnp.repeat(x[None], n, axis=0), actor)
        greedy = jnp.arange(n) == 0
        return evaluate_policies(self.env, self._act, (actors, greedy), key, True, stochastic=True)

    # ------------------------------------------------------------------ losses
    def actor_loss(self, actor: Any, batch: dict) -> jax.Array:
        """PPO's clipped loss on AGAC's advantage, minus the entropy bonus."""
        mean, log_std = self.policy.apply(actor, batch["obs"])
        log_pi = tanh_gaussian_log_prob(mean, log_std, batch["action"])
        loss = ppo_clip_loss(
            log_pi, batch["log_pi"], batch["advantage"], batch["mask"], self.config.clip
        )
        return loss - self.config.entropy_coef * masked_mean(
            gaussian_entropy(log_std), batch["mask"]
        )

    def critic_loss(self, critic: Any, batch: dict) -> jax.Array:
        """Squared error to AGAC's value target, weighted by ``value_loss_coef``."""
        v = self.critic.apply(critic, batch["obs"])
        return self.config.value_loss_coef * masked_mean((v - batch["target"]) ** 2, batch["mask"])

    def adversary_loss(
        self, adversary: Any, obs: jax.Array, mean: jax.Array, log_std: jax.Array, mask
    ) -> jax.Array:
        """``E_s KL(pi_old(.|s) || pi_adv(.|s))``: the adversary imitates the actor
        that collected the batch (``mean``, ``log_std`` are pi_old's)."""
        adv_mean, adv_log_std = self.policy.apply(adversary, obs)
        return masked_mean(gaussian_kl(mean, log_std, adv_mean, adv_log_std), mask)

    # ------------------------------------------------------------------ training
    def prepare_batch(self, state: AGACState, trajectory: dict) -> dict:
        """Everything PPO needs from the training episodes (the greedy one, episode 0,
        dropped), flattened to one axis: observations, actions, pi_old's log-densities
        and parameters, AGAC's advantages and value targets, and the valid mask."""
        traj = jax.tree.map(lambda x: x[1:], trajectory)
        cfg = self.config
        obs, action = traj["obs"], traj["action"]
        mean, log_std = self.policy.apply(state.actor, obs)
        adv_mean, adv_log_std = self.policy.apply(state.adversary, obs)
        log_pi = tanh_gaussian_log_prob(mean, log_std, action)
        log_pi_adv = tanh_gaussian_log_prob(adv_mean, adv_log_std, action)
        value = self.critic.apply(state.critic, obs)
        next_value = self.critic.apply(state.critic, traj["next_obs"])
        a_gae = gae(
            traj["reward"],
            value,
            next_value,
            traj["terminal"],
            traj["done"],
            traj["valid"],
            cfg.gamma,
            cfg.gae_lambda,
        )
        c = self.agac_coefficient(state.iteration)
        batch = {
            "obs": obs,
            "action": action,
            "log_pi": log_pi,
            "mean": mean,
            "log_std": log_std,
            "advantage": agac_advantage(a_gae, log_pi, log_pi_adv, c),
            "target": value + a_gae + c * gaussian_kl(mean, log_std, adv_mean, adv_log_std),
            "mask": traj["valid"],
        }
        batch = jax.lax.stop_gradient(batch)
        return jax.tree.map(lambda x: x.reshape((-1,) + x.shape[2:]), batch)

    def _minibatch_step(self, state: AGACState, batch: dict) -> AGACState:
        """One gradient step of each of the three networks on one minibatch."""
        opt_actor, opt_critic, opt_adversary = self.optimizers

        def update(opt, params, opt_state, loss_fn):
            grads = jax.grad(loss_fn)(params)
            updates, opt_state = opt.update(grads, opt_state, params)
            return optax.apply_updates(params, updates), opt_state

        actor, actor_opt = update(
            opt_actor, state.actor, state.actor_opt, lambda p: self.actor_loss(p, batch)
        )
        critic, critic_opt = update(
            opt_critic, state.critic, state.critic_opt, lambda p: self.critic_loss(p, batch)
        )
        adversary, adversary_opt = update(
            opt_adversary,
            state.adversary,
            state.adversary_opt,
            lambda p: self.adversary_loss(
                p, batch["obs"], batch["mean"], batch["log_std"], batch["mask"]
            ),
        )
        return state.replace(
            actor=actor,
            critic=critic,
            adversary=adversary,
            actor_opt=actor_opt,
            critic_opt=critic_opt,
            adversary_opt=adversary_opt,
        )

    def update(self, state: AGACState, trajectory: dict, key: jax.Array) -> AGACState:
        """``num_epochs`` epochs over the batch, each a fresh shuffle cut into
        minibatches of (at most) ``minibatch_size``; the last minibatch is padded
        with masked rows, so every shape is static."""
        batch = self.prepare_batch(state, trajectory)
        n = batch["mask"].shape[0]
        size = min(self.config.minibatch_size, n)
        num_minibatches = math.ceil(n / size)
        pad = num_minibatches * size - n
        epochs = self.config.num_epochs

        perms = jax.vmap(lambda k: jax.random.permutation(k, n))(jax.random.split(key, epochs))
        index = jnp.concatenate([perms, jnp.zeros((epochs, pad), perms.dtype)], axis=1)
        kept = jnp.concatenate([jnp.ones((epochs, n), bool), jnp.zeros((epochs, pad), bool)], 1)
        index = index.reshape(epochs * num_minibatches, size)
        kept = kept.reshape(epochs * num_minibatches, size)

        def one(s, inputs):
            idx, ok = inputs
            mb = jax.tree.map(lambda x: x[idx], batch)
            mb["mask"] = mb["mask"] & ok
            return self._minibatch_step(s, mb), None

        state, _ = jax.lax.scan(one, state, (index, kept))
        return state.replace(iteration=state.iteration + 1)

    # ------------------------------------------------------------------ Algorithm
    def init(self, key: jax.Array) -> tuple[AGACState, Evaluation]:
        k_actor, k_critic, k_adv, k_eval, key = jax.random.split(key, 5)
        obs = jnp.zeros((self.env.observation_size,))
        actor = self.policy.init(k_actor, obs)
        critic = self.critic.init(k_critic, obs)
        adversary = self.policy.init(k_adv, obs)
        opt_actor, opt_critic, opt_adversary = self.optimizers
        ev = self._play(actor, k_eval)
        state = AGACState(
            actor=actor,
            critic=critic,
            adversary=adversary,
            actor_opt=opt_actor.init(actor),
            critic_opt=opt_critic.init(critic),
            adversary_opt=opt_adversary.init(adversary),
            iteration=jnp.zeros((), jnp.int32),
            performance=ev.fitness[0],
            key=key,
        )
        return state, ev

    def step(self, state: AGACState) -> tuple[AGACState, Evaluation]:
        """Play ``num_episodes`` episodes with the current policy (the first greedy),
        then one PPO update on the sampled ones; ``performance`` is the greedy
        episode's return (the policy before this update)."""
        key, k_play, k_train = jax.random.split(state.key, 3)
        ev = self._play(state.actor, k_play)
        state = self.update(state, ev.trajectory, k_train)
        return state.replace(performance=ev.fitness[0], key=key), ev

    def metrics(self, state: AGACState) -> dict[str, jax.Array]:
        return {"max_fitness": state.performance}
