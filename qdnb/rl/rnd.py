"""RND (Burda, Edwards, Storkey and Klimov, 2018, "Exploration by Random Network
Distillation") on a TD3 agent: the Chapter 3 baseline that "adds an exploration
bonus used as an intrinsic reward" (Section 3.6.2, Tables 3.1 and 3.4).

A fixed, randomly initialised *target* network f and a trained *predictor* f_hat
map a state to an embedding; the predictor is regressed onto the target on the
states the agent visits, so its error is small where the agent has often been and
large elsewhere.  The intrinsic reward of a transition (s, a, s') is that error at
the state it reaches (the paper's i_t = ||f_hat(s_{t+1}) - f(s_{t+1})||^2), and the
TD3 critic (with its greedy actor) learns the return of r_ext + beta * r_int.

Followed from the paper:

- the predictor's inputs are normalised by running per-dimension mean and
  standard deviation and clipped to [-5, 5] (Section 2.4, "observation
  normalization");
- the intrinsic reward is divided by a running estimate of the standard
  deviation of the intrinsic *return*: a per-episode-slot discounted sum of the
  intrinsic rewards, never reset at episode ends (the paper's non-episodic
  intrinsic return, Section 2.3; its code's ``RewardForwardFilter``), whose
  running mean and variance are kept in the state;
- the predictor trains on the newest experience only, the transitions the agent
  has just played, with Adam at rate 1e-4, 4 epochs of 4 minibatches each
  keeping a random quarter of its transitions (Table 5: "proportion of
  experience used for training predictor 0.25");
- a total reward r_ext + beta * r_int with beta = 1/2: the paper weighs
  advantages 2 (extrinsic) to 1 (intrinsic), Table 5.

Adapted to an off-policy agent on low-dimensional states:

- RND reads the *state descriptor* (the x-y position) rather than the raw
  observation: on Point-Maze the two coincide, and on the ant mazes the
  descriptor is the space whose exploration the chapter measures (and QD-PG
  rewards novelty in), so every exploration baseline is rewarded for novelty in
  the same space.  The reward is computed at the state a transition *reaches*,
  as in the paper, so the buffer stores each transition's
  ``next_state_descriptor`` (an extra field of the ``ReplayBuffer`` rows).
- The intrinsic rewards of the replayed transitions are recomputed with the
  current predictor and statistics for every critic batch (through
  ``TD3.train_critic(..., reward_fn=...)``, as QD-PG's fresh novelty rewards): a
  bonus stored at collection time would go stale as the predictor learns.
- One TD3 critic on the summed reward, episodic for both parts, where the paper
  has two value heads (an episodic extrinsic one, a non-episodic intrinsic one):
  TD3 has one critic, and the tasks' terminal states end the episode anyway.
- Multilayer perceptrons for the paper's Atari convolutional networks: the
  target is a ReLU torso (``hidden``) and a linear embedding layer; the
  predictor the same torso and three embedding-wide layers (the paper's
  predictor has two more fully connected layers than its target).  The
  paper's embedding of 512 is for pixels; a 2-D descriptor gets 64 by default.
- The paper's extrinsic reward clipping (Atari) is not used: the tasks' rewards
  are already bounded.  The bonus is the squared norm of the error where the
  released code averages it over the embedding: a constant factor, which the
  normalisation by the intrinsic return's standard deviation removes.
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
from qdnb.nets.mlp import MLP
from qdnb.rl.buffer import ReplayBuffer
from qdnb.rl.td3 import TD3, TD3Config, TD3State

_EPS = 1e-8  # keeps a zero variance from dividing by zero


@dataclass(frozen=True)
class RNDConfig:
    """RND's own settings (the thesis gives none; the paper's where it has one).

    - ``intrinsic_weight`` (beta = 0.5): total reward r_ext + beta * r_int; the
      paper's advantage coefficients are 2 (extrinsic) and 1 (intrinsic), Table 5.
    - ``predictor_lr`` (1e-4): Adam's rate for the predictor, Table 5.
    - ``intrinsic_gamma`` (0.99): discount of the intrinsic return whose standard
      deviation normalises the intrinsic reward (gamma_I), Table 5.
    - ``input_clip`` (5.0): whitened predictor/target inputs clipped to [-5, 5],
      Section 2.4.
    - ``predictor_epochs`` (4) and ``num_minibatches`` (4): passes and minibatches
      over the newest experience, Table 5 (PPO's "optimization epochs" and
      "number of minibatches", which the predictor shares).
    - ``predictor_proportion`` (0.25): share of each minibatch the predictor
      trains on, Table 5.
    - ``hidden`` ((64, 64)) and ``embedding_size`` (64): our MLP analogue of the
      paper's convolutional torso and its 512-wide embedding (its appendix and
      released code), sized for 2-D descriptors; the predictor adds two
      embedding-wide layers, as the paper's does.
    """

    intrinsic_weight: float = 0.5
    predictor_lr: float = 1e-4
    intrinsic_gamma: float = 0.99
    input_clip: float = 5.0
    predictor_epochs: int = 4
    num_minibatches: int = 4
    predictor_proportion: float = 0.25
    hidden: tuple[int, ...] = (64, 64)
    embedding_size: int = 64

    def __post_init__(self):
        checks = [
            ("intrinsic_weight", self.intrinsic_weight >= 0, ">= 0"),
            ("predictor_lr", self.predictor_lr > 0, "> 0"),
            ("intrinsic_gamma", 0 <= self.intrinsic_gamma < 1, "in [0, 1)"),
            ("input_clip", self.input_clip > 0, "> 0"),
            ("predictor_epochs", self.predictor_epochs >= 1, ">= 1"),
            ("num_minibatches", self.num_minibatches >= 1, ">= 1"),
            ("predictor_proportion", 0 < self.predictor_proportion <= 1, "in (0, 1]"),
            ("embedding_size", self.embedding_size >= 1, ">= 1"),
        ]
        for name, ok, rule in checks:
            if not ok:
                raise ValueError(f"RNDConfig.{name}={getattr(self, name)!r} must be {rule}")


@struct.dataclass
class RunningMoments:
    """Running mean and variance of a stream of batches (per entry of ``shape``),
    merged batch by batch (Chan et al.'s parallel update, as the paper's
    ``RunningMeanStd``; it also starts from mean 0, variance 1 and a count of 1e-4)."""

    mean: jax.Array
    var: jax.Array
    count: jax.Array

    @classmethod
    def create(cls, shape: tuple[int, ...] = ()) -> "RunningMoments":
        return cls(jnp.zeros(shape), jnp.ones(shape), jnp.asarray(1e-4))

    def update(self, x: jax.Array, mask: jax.Array) -> "RunningMoments":
        """Merge the rows of ``x`` (leading axis) where ``mask`` holds."""
        w = mask.astype(jnp.float32).reshape(mask.shape + (1,) * (x.ndim - 1))
        n = jnp.sum(mask.astype(jnp.float32))
        batch_mean = jnp.sum(w * x, axis=0) / jnp.maximum(n, 1.0)
        batch_var = jnp.sum(w * (x - batch_mean) ** 2, axis=0) / jnp.maximum(n, 1.0)
        total = self.count + n
        delta = batch_mean - self.mean
        mean = self.mean + delta * n / total
        m2 = self.var * self.count + batch_var * n + delta**2 * self.count * n / total
        return RunningMoments(mean, m2 / total, total)


def forward_filter(
    carry: jax.Array, rewards: jax.Array, valid: jax.Array, gamma: float
) -> tuple[jax.Array, jax.Array]:
    """The paper's running intrinsic return, per episode slot: R <- gamma R + r at
    every valid step (``rewards``/``valid``: ``(slots, time)``), never reset
    between episodes.  Returns the final ``carry`` and R after every step."""

    def one(ret, inputs):
        r, v = inputs
        ret = jnp.where(v, gamma * ret + r, ret)
        return ret, ret

    carry, returns = jax.lax.scan(one, carry, (rewards.T, valid.T))
    return carry, returns.T


@struct.dataclass
class RNDState:
    td3: TD3State
    buffer: ReplayBuffer
    target: Any  # the fixed random network f
    predictor: Any  # the trained predictor f_hat
    predictor_opt: Any
    input_moments: RunningMoments  # of the descriptors fed to f and f_hat
    return_moments: RunningMoments  # of the intrinsic returns
    intrinsic_return: jax.Array  # (num_episodes,): each episode slot's running intrinsic return
    performance: jax.Array  # fitness of the last greedy episode
    key: jax.Array


def replay_buffer_with_next_descriptor(
    capacity: int, observation_size: int, action_size: int, descriptor_size: int
) -> ReplayBuffer:
    """An empty ``ReplayBuffer`` whose rows also hold each transition's
    ``next_state_descriptor`` (the state RND rewards reaching)."""
    base = ReplayBuffer.create(capacity, observation_size, action_size)
    fields = base.fields + (("next_state_descriptor", (descriptor_size,)),)
    width = base.storage.shape[1] + descriptor_size
    return ReplayBuffer(jnp.zeros((capacity, width)), base.position, base.size, fields)


@dataclass(frozen=True, eq=False)
class RNDAgent:
    """TD3 with RND's intrinsic reward (Table 3.4's RND).

    Each iteration the critic (and, every ``policy_delay`` steps, the greedy
    actor) trains for ``num_critic_steps`` steps on replay batches whose rewards
    are r_ext + beta * r_int, r_int recomputed for each batch; then the actor plays
    ``num_episodes`` episodes, the first greedy (its performance), the others with
    Gaussian exploration noise, all of them stored; then the input and return
    statistics take in those episodes and the predictor trains on them.
    """

    env: Env
    network: MLP
    td3_config: TD3Config = TD3Config()
    rnd_config: RNDConfig = RNDConfig()
    num_episodes: int = 4
    num_critic_steps: int = 100
    exploration_noise: float = 0.1
    buffer_size: int = 1_000_000

    def __post_init__(self):
        if self.num_episodes < 1:
            raise ValueError(f"num_episodes={self.num_episodes} must be at least 1")
        delay = self.td3_config.policy_delay
        if self.num_critic_steps < 1 or self.num_critic_steps % delay:
            raise ValueError(
                f"num_critic_steps={self.num_critic_steps} must be a positive multiple of "
                f"policy_delay={delay}"
            )
        if self.exploration_noise < 0:
            raise ValueError(f"exploration_noise={self.exploration_noise} must be >= 0")
        per_iteration = self.num_episodes * self.env.episode_length
        if self.buffer_size < per_iteration:
            raise ValueError(
                f"buffer_size={self.buffer_size} must hold one iteration's transitions "
                f"({self.num_episodes} episodes x {self.env.episode_length} steps)"
            )

    @property
    def td3(self) -> TD3:
        return TD3(self.network, self.env.observation_size, self.env.action_size, self.td3_config)

    @property
    def target_network(self) -> MLP:
        cfg = self.rnd_config
        return MLP(
            tuple(cfg.hidden) + (cfg.embedding_size,), activation="relu", final_activation=None
        )

    @property
    def predictor_network(self) -> MLP:
        cfg = self.rnd_config
        return MLP(
            tuple(cfg.hidden) + (cfg.embedding_size,) * 3, activation="relu", final_activation=None
        )

    @property
    def predictor_optimizer(self):
        return optax.adam(self.rnd_config.predictor_lr)

    # --- the bonus ---------------------------------------------------------------

    def whiten(self, moments: RunningMoments, descriptors: jax.Array) -> jax.Array:
        """Observation normalisation: (x - mean) / std, clipped to [-c, c]."""
        c = self.rnd_config.input_clip
        z = (descriptors - moments.mean) / jnp.sqrt(moments.var + _EPS)
        return jnp.clip(z, -c, c)

    def prediction_error(
        self, target: Any, predictor: Any, moments: RunningMoments, descriptors: jax.Array
    ) -> jax.Array:
        """||f_hat(x) - f(x)||^2 of each whitened descriptor (the raw bonus)."""
        x = self.whiten(moments, descriptors)
        f = jax.lax.stop_gradient(self.target_network.apply(target, x))
        return jnp.sum((self.predictor_network.apply(predictor, x) - f) ** 2, axis=-1)

    def intrinsic_reward(self, state: RNDState, descriptors: jax.Array) -> jax.Array:
        """The normalised intrinsic reward: the prediction error divided by the
        running standard deviation of the intrinsic return."""
        error = self.prediction_error(
            state.target, state.predictor, state.input_moments, descriptors
        )
        return error / jnp.sqrt(state.return_moments.var + _EPS)

    def total_reward(self, state: RNDState, batch: dict) -> jax.Array:
        """r_ext + beta * r_int of replayed transitions, r_int at the state reached."""
        r_int = self.intrinsic_reward(state, batch["next_state_descriptor"])
        return batch["reward"] + self.rnd_config.intrinsic_weight * r_int

    # --- training the predictor --------------------------------------------------

    def train_predictor(
        self, state: RNDState, descriptors: jax.Array, valid: jax.Array, key: jax.Array
    ) -> RNDState:
        """Adam steps of the predictor's regression onto the target on a batch of
        descriptors (rows; ``valid`` masks padding): ``predictor_epochs`` passes,
        each over ``num_minibatches`` minibatches of which a random
        ``predictor_proportion`` is kept."""
        cfg = self.rnd_config
        n = descriptors.shape[0]
        per_minibatch = max(1, n // cfg.num_minibatches)
        kept = max(1, round(cfg.predictor_proportion * per_minibatch))
        keys = jax.random.split(key, cfg.predictor_epochs)
        # a fresh permutation per epoch; the first `kept` rows of each of its minibatches
        idx = jax.vmap(lambda k: jax.random.permutation(k, n))(keys)
        idx = idx[:, : cfg.num_minibatches * per_minibatch].reshape(
            cfg.predictor_epochs * cfg.num_minibatches, per_minibatch
        )[:, :kept]
        opt = self.predictor_optimizer

        def loss(predictor, rows):
            err = self.prediction_error(
                state.target, predictor, state.input_moments, descriptors[rows]
            )
            mask = valid[rows].astype(jnp.float32)
            return jnp.sum(mask * err) / jnp.maximum(jnp.sum(mask), 1.0)

        def one(carry, rows):
            params, opt_state = carry
            grads = jax.grad(loss)(params, rows)
            updates, opt_state = opt.update(grads, opt_state)
            return (optax.apply_updates(params, updates), opt_state), None

        (predictor, opt_state), _ = jax.lax.scan(one, (state.predictor, state.predictor_opt), idx)
        return state.replace(predictor=predictor, predictor_opt=opt_state)

    def _observe(self, state: RNDState, trajectory: dict, key: jax.Array) -> RNDState:
        """Take in the episodes just played: input statistics, then their intrinsic
        rewards (current predictor) into the running returns and their
        statistics, then the predictor's training on them."""
        sd = trajectory["next_state_descriptor"]
        valid = trajectory["valid"]
        flat_sd, flat_valid = sd.reshape((-1, sd.shape[-1])), valid.reshape(-1)
        state = state.replace(input_moments=state.input_moments.update(flat_sd, flat_valid))
        error = self.prediction_error(state.target, state.predictor, state.input_moments, sd)
        carry, returns = forward_filter(
            state.intrinsic_return, error, valid, self.rnd_config.intrinsic_gamma
        )
        state = state.replace(
            intrinsic_return=carry,
            return_moments=state.return_moments.update(returns.reshape(-1), flat_valid),
        )
        return self.train_predictor(state, flat_sd, flat_valid, key)

    # --- the Algorithm -----------------------------------------------------------

    def _play(self, td3_state: TD3State, buffer: ReplayBuffer, key: jax.Array):
        actors = jax.tree.map(
            lambda x: jnp.repeat(x[None], self.num_episodes, axis=0), td3_state.actor
        )
        noise = jnp.full((self.num_episodes,), self.exploration_noise).at[0].set(0.0)
        ev = evaluate_policies(self.env, self.network.apply, actors, key, True, noise)
        return buffer.add_episodes(ev.trajectory, ev.fitness.ndim), ev

    def init(self, key: jax.Array) -> tuple[RNDState, Evaluation]:
        k_td3, k_target, k_pred, k_eval, k_obs, key = jax.random.split(key, 6)
        env = self.env
        dummy = jnp.zeros((env.descriptor_size,))
        td3_state = self.td3.init(k_td3)
        predictor = self.predictor_network.init(k_pred, dummy)
        buffer = replay_buffer_with_next_descriptor(
            self.buffer_size, env.observation_size, env.action_size, env.descriptor_size
        )
        buffer, ev = self._play(td3_state, buffer, k_eval)
        state = RNDState(
            td3=td3_state,
            buffer=buffer,
            target=self.target_network.init(k_target, dummy),
            predictor=predictor,
            predictor_opt=self.predictor_optimizer.init(predictor),
            input_moments=RunningMoments.create((env.descriptor_size,)),
            return_moments=RunningMoments.create(),
            intrinsic_return=jnp.zeros((self.num_episodes,)),
            performance=ev.fitness[0],
            key=key,
        )
        return self._observe(state, ev.trajectory, k_obs), ev

    def step(self, state: RNDState) -> tuple[RNDState, Evaluation]:
        key, k_train, k_eval, k_obs = jax.random.split(state.key, 4)
        td3_state, _ = self.td3.train_critic(
            state.td3,
            state.buffer,
            k_train,
            self.num_critic_steps,
            reward_fn=lambda batches: self.total_reward(state, batches),
        )
        buffer, ev = self._play(td3_state, state.buffer, k_eval)
        state = state.replace(td3=td3_state, buffer=buffer, performance=ev.fitness[0], key=key)
        return self._observe(state, ev.trajectory, k_obs), ev

    def metrics(self, state: RNDState) -> dict[str, jax.Array]:
        return {"max_fitness": state.performance}
