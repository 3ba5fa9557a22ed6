"""P3S-TD3 (Jung, Park and Sung, 2020, "Population-Guided Parallel Policy Search
for Reinforcement Learning"): the population-based RL baseline of Chapter 3
(Tables 3.1 and 3.4).

A population of N TD3 learners, each with its own actor, twin critic and
targets, shares one replay buffer; each plays its own episodes.  Every update
period the best learner b is the one with the highest mean return over its
recent episodes, and its policy pi_b is kept as the guide until the next period.
Every other learner's actor minimises the augmented loss

    L(phi_i) = E_s[ -Q1_i(s, pi_i(s)) ] + beta * D(pi_i, pi_b),
    D(pi, pi') = E_s[ 1/2 * mean_j (pi_j(s) - pi'_j(s))^2 ],

a soft pull toward the best policy that leaves each learner free to search
around it (the paper's Eq. for the augmented loss; the distance as the authors'
released code computes it: half the squared action difference averaged over the
action dimensions, so that d_min's scale does not depend on the action size).
The best learner itself trains on the plain TD3 loss.  At the end of each period
beta adapts so that the learners' spread around the guide tracks a target
distance (the paper's rule, kept by the released code):

    d_target = max(rho * D_change, d_min),
    beta <- 2 beta  if D_spread > 1.5 d_target   (and beta < 1000),
    beta <- beta/2  if D_spread < d_target / 1.5 (and beta > 1/1000),

with D_spread the mean over the non-best learners of D(pi_i, pi_b) and D_change
the mean of D(pi_i, pi_i_old), how far each moved during the period.

Mapped onto this book's loop (every method plays ``num_episodes`` episodes per
iteration, as QD-PG):

- ``num_episodes`` learners, each playing one episode per iteration, vmapped
  (training and one ``evaluate_policies`` call for all of them);
- the gradient budget of the paper, one update per environment step of the
  learner (each learner takes ``num_critic_steps // num_episodes`` critic steps,
  rounded down to a multiple of ``policy_delay``, so the population spends the
  TD3 agent's ``num_critic_steps`` in all);
- the best learner's episode is greedy and comes first in the evaluation (it
  defines the performance, the best learner's latest greedy return); the
  others explore with Gaussian noise, as the paper's learners do.  A learner's
  recent returns are those of the episodes it played, greedy while it was the
  best, noisy otherwise.

Simplified, and why:

- D_spread and D_change are measured once, at the end of the period, on one
  replay batch of states, where the released code averages them over every
  training step of the period (same quantities, one estimate instead of many).
- The learners start from independent random initialisations (the released
  code copies one actor into all of them first).
- The update period is counted in iterations: the paper's M = 250 environment
  steps per learner are about one 200-step Point-Maze episode, and less than
  one ant episode, so the best learner is reselected every iteration.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import jax
import jax.numpy as jnp
from flax import struct

from qdnb.core.evaluation import Evaluation
from qdnb.core.tree import take
from qdnb.envs.base import Env
from qdnb.envs.rollout import evaluate_policies
from qdnb.nets.mlp import MLP
from qdnb.rl.buffer import ReplayBuffer
from qdnb.rl.td3 import TD3, TD3Config, TD3State


@dataclass(frozen=True)
class P3SConfig:
    """P3S's own settings (the thesis gives none; the paper's where it has one).

    - ``update_period`` (1 iteration): the paper's M = 250 time steps between
      best-learner selections, about one 200-step episode per learner here.
    - ``num_recent_episodes`` (10): E_r, the recent episodes whose mean return
      ranks a learner (the paper's experimental setup, as we read it).
    - ``initial_beta`` (1.0): beta's starting value (the released code).
    - ``rho`` (2.0) and ``d_min`` (0.05): the target distance
      max(rho * D_change, d_min) (the paper; the released code's defaults are
      rho = 2 and d_min = 0.04, 0.03 in some of its runs).
    - ``beta_bounds`` ((1e-3, 1e3)): beta doubles only below the upper bound and
      halves only above the lower one (the released code).

    M, E_r and d_min are quoted from the paper's text as we recall it; the rule,
    rho, the bounds and beta's start are checked against the released code.
    """

    update_period: int = 1
    num_recent_episodes: int = 10
    initial_beta: float = 1.0
    rho: float = 2.0
    d_min: float = 0.05
    beta_bounds: tuple[float, float] = (1e-3, 1e3)

    def __post_init__(self):
        lo, hi = self.beta_bounds
        checks = [
            ("update_period", self.update_period >= 1, ">= 1"),
            ("num_recent_episodes", self.num_recent_episodes >= 1, ">= 1"),
            ("initial_beta", self.initial_beta > 0, "> 0"),
            ("rho", self.rho >= 0, ">= 0"),
            ("d_min", self.d_min >= 0, ">= 0"),
            ("beta_bounds", 0 < lo <= hi, "(low, high) with 0 < low <= high"),
        ]
        for name, ok, rule in checks:
            if not ok:
                raise ValueError(f"P3SConfig.{name}={getattr(self, name)!r} must be {rule}")


def policy_distance(network: MLP, actor: Any, other: Any, obs: jax.Array) -> jax.Array:
    """D(pi, pi') = E_s[1/2 mean_j (pi_j(s) - pi'_j(s))^2] over a batch of states."""
    diff = network.apply(actor, obs) - network.apply(other, obs)
    return jnp.mean(0.5 * jnp.mean(diff**2, axis=-1))


def adapt_beta(
    beta: jax.Array,
    spread: jax.Array,
    change: jax.Array,
    rho: float,
    d_min: float,
    bounds: tuple[float, float] = (1e-3, 1e3),
) -> jax.Array:
    """P3S's rule: double beta when the spread around the guide exceeds 1.5 times
    the target distance max(rho * change, d_min), halve it when it falls below
    the target over 1.5 (within ``bounds``)."""
    target = jnp.maximum(rho * change, d_min)
    lo, hi = bounds
    beta = jnp.where((spread > 1.5 * target) & (beta < hi), 2.0 * beta, beta)
    return jnp.where((spread < target / 1.5) & (beta > lo), beta / 2.0, beta)


def select_best(recent_returns: jax.Array, num_played: jax.Array) -> jax.Array:
    """The learner whose recent episodes have the highest mean return.

    ``recent_returns`` is ``(learners, E_r)``, a ring of each learner's last
    returns written at column ``episode % E_r``; ``num_played`` episodes have
    been written (the first ``min(num_played, E_r)`` columns hold returns)."""
    size = recent_returns.shape[1]
    filled = jnp.minimum(num_played, size)
    mask = jnp.arange(size) < filled
    means = jnp.sum(jnp.where(mask, recent_returns, 0.0), axis=1) / jnp.maximum(filled, 1)
    return jnp.argmax(means)


@dataclass(frozen=True, eq=False)
class GuidedTD3(TD3):
    """TD3 whose actor loss adds P3S's guidance term ``guide_weight * D(pi, guide)``
    (``guide``: the best learner's actor parameters; a weight of 0 or no guide
    gives plain TD3)."""

    guide: Any = None
    guide_weight: Any = 0.0

    def actor_loss(self, actor: Any, critic: Any, obs: jax.Array) -> jax.Array:
        loss = super().actor_loss(actor, critic, obs)
        if self.guide is None:
            return loss
        guide = jax.lax.stop_gradient(self.guide)
        return loss + self.guide_weight * policy_distance(self.actor, actor, guide, obs)


@struct.dataclass
class P3SState:
    learners: TD3State  # every learner's TD3 state, leading axis num_learners
    buffer: ReplayBuffer  # shared by the learners
    guide: Any  # pi_b: the best learner's actor when it was selected
    old_actors: Any  # every learner's actor at the last selection (for D_change)
    best: jax.Array  # b
    beta: jax.Array
    recent_returns: jax.Array  # (num_learners, num_recent_episodes), a ring
    num_played: jax.Array  # episodes each learner has played
    iteration: jax.Array
    performance: jax.Array  # the best learner's latest greedy return
    key: jax.Array


@dataclass(frozen=True, eq=False)
class P3STD3Agent:
    """P3S-TD3 (Table 3.4): ``num_episodes`` guided TD3 learners on one buffer.

    Each iteration every learner trains (critic steps, and a guided actor step
    every ``policy_delay`` of them), then plays one episode (the best learner
    greedily, first in the evaluation; the others with exploration noise); at
    the end of each update period beta adapts and the best learner and its guide
    are chosen again.
    """

    env: Env
    network: MLP
    td3_config: TD3Config = TD3Config()
    p3s_config: P3SConfig = P3SConfig()
    num_episodes: int = 4
    num_critic_steps: int = 100
    exploration_noise: float = 0.1
    buffer_size: int = 1_000_000

    def __post_init__(self):
        if self.num_episodes < 1:
            raise ValueError(f"num_episodes={self.num_episodes} must be at least 1")
        if self.num_critic_steps < 1:
            raise ValueError(f"num_critic_steps={self.num_critic_steps} must be at least 1")
        if self.exploration_noise < 0:
            raise ValueError(f"exploration_noise={self.exploration_noise} must be >= 0")
        per_iteration = self.num_episodes * self.env.episode_length
        if self.buffer_size < per_iteration:
            raise ValueError(
                f"buffer_size={self.buffer_size} must hold one iteration's transitions "
                f"({self.num_episodes} episodes x {self.env.episode_length} steps)"
            )

    @property
    def num_learners(self) -> int:
        return self.num_episodes

    @property
    def learner_critic_steps(self) -> int:
        """Critic steps of each learner per iteration: its share of
        ``num_critic_steps``, a multiple of ``policy_delay`` (at least one)."""
        delay = self.td3_config.policy_delay
        return max(delay, self.num_critic_steps // self.num_learners // delay * delay)

    @property
    def td3(self) -> TD3:
        return TD3(self.network, self.env.observation_size, self.env.action_size, self.td3_config)

    def guided_td3(self, guide: Any, weight: jax.Array) -> GuidedTD3:
        return GuidedTD3(
            self.network,
            self.env.observation_size,
            self.env.action_size,
            self.td3_config,
            guide=guide,
            guide_weight=weight,
        )

    def _play(self, actors: Any, best: jax.Array, buffer: ReplayBuffer, key: jax.Array):
        """One episode per learner in one call, the best learner's first and greedy;
        returns the buffer, the evaluation and each learner's return (in learner order)."""
        n = self.num_learners
        order = (jnp.arange(n) + best) % n
        noise = jnp.full((n,), self.exploration_noise).at[0].set(0.0)
        ev = evaluate_policies(self.env, self.network.apply, take(actors, order), key, True, noise)
        returns = ev.fitness[(jnp.arange(n) - best) % n]
        return buffer.add_episodes(ev.trajectory, ev.fitness.ndim), ev, returns

    def _record(self, state: P3SState, returns: jax.Array) -> P3SState:
        column = state.num_played % self.p3s_config.num_recent_episodes
        return state.replace(
            recent_returns=state.recent_returns.at[:, column].set(returns),
            num_played=state.num_played + 1,
        )

    def distances(self, state: P3SState, obs: jax.Array) -> tuple[jax.Array, jax.Array]:
        """(D_spread, D_change) over the non-best learners, on the states ``obs``."""
        actors = state.learners.actor
        spread = jax.vmap(lambda a: policy_distance(self.network, a, state.guide, obs))(actors)
        change = jax.vmap(lambda a, o: policy_distance(self.network, a, o, obs))(
            actors, state.old_actors
        )
        others = jnp.arange(self.num_learners) != state.best
        count = max(self.num_learners - 1, 1)
        mean = lambda d: jnp.sum(jnp.where(others, d, 0.0)) / count
        return mean(spread), mean(change)

    def _end_of_period(self, state: P3SState, key: jax.Array) -> P3SState:
        """Adapt beta, select the best learner, snapshot its actor as the guide and
        every actor as the reference of the next D_change; kept only when a
        period ends (a fixed computation, selected, so that it vmaps over seeds)."""
        cfg = self.p3s_config
        obs = state.buffer.sample(key, self.td3_config.batch_size)["obs"]
        spread, change = self.distances(state, obs)
        beta = adapt_beta(state.beta, spread, change, cfg.rho, cfg.d_min, cfg.beta_bounds)
        best = select_best(state.recent_returns, state.num_played)
        actors = state.learners.actor
        new = (beta, best, take(actors, best), actors)
        old = (state.beta, state.best, state.guide, state.old_actors)
        due = state.iteration % cfg.update_period == 0
        beta, best, guide, old_actors = jax.tree.map(lambda a, b: jnp.where(due, a, b), new, old)
        return state.replace(beta=beta, best=best, guide=guide, old_actors=old_actors)

    def init(self, key: jax.Array) -> tuple[P3SState, Evaluation]:
        k_init, k_eval, key = jax.random.split(key, 3)
        env, n, cfg = self.env, self.num_learners, self.p3s_config
        learners = jax.vmap(self.td3.init)(jax.random.split(k_init, n))
        buffer = ReplayBuffer.create(self.buffer_size, env.observation_size, env.action_size)
        buffer, ev, returns = self._play(learners.actor, jnp.zeros((), jnp.int32), buffer, k_eval)
        recent = jnp.zeros((n, cfg.num_recent_episodes)).at[:, 0].set(returns)
        best = select_best(recent, 1)
        state = P3SState(
            learners=learners,
            buffer=buffer,
            guide=take(learners.actor, best),
            old_actors=learners.actor,
            best=best,
            beta=jnp.asarray(cfg.initial_beta, jnp.float32),
            recent_returns=recent,
            num_played=jnp.ones((), jnp.int32),
            iteration=jnp.zeros((), jnp.int32),
            performance=ev.fitness[0],
            key=key,
        )
        return state, ev

    def step(self, state: P3SState) -> tuple[P3SState, Evaluation]:
        key, k_train, k_eval, k_period = jax.random.split(state.key, 4)
        weights = jnp.where(jnp.arange(self.num_learners) == state.best, 0.0, state.beta)

        def train(learner, weight, k):
            guided = self.guided_td3(state.guide, weight)
            return guided.train_critic(learner, state.buffer, k, self.learner_critic_steps)[0]

        learners = jax.vmap(train)(
            state.learners, weights, jax.random.split(k_train, self.num_learners)
        )
        buffer, ev, returns = self._play(learners.actor, state.best, state.buffer, k_eval)
        state = state.replace(
            learners=learners,
            buffer=buffer,
            iteration=state.iteration + 1,
            performance=ev.fitness[0],
            key=key,
        )
        return self._end_of_period(self._record(state, returns), k_period), ev

    def metrics(self, state: P3SState) -> dict[str, jax.Array]:
        return {"max_fitness": state.performance}
