"""CEM-RL (Pourchot and Sigaud, 2019, "CEM-RL: Combining evolutionary and
gradient-based methods for policy search"), a Chapter 3 baseline (Table 3.4).

A separable cross-entropy method (CEM) searches the actor's flat parameters
(``jax.flatten_util.ravel_pytree``): each generation draws a population from
``N(mu, diag(var))``; half of it takes TD3 actor steps against one shared TD3
critic trained on the shared replay buffer; every member plays an episode
(its transitions feed the buffer); then the best ``K_e`` members move the
distribution (the paper's Eqs. 1 and 2, ``cem_update``):

    mu'  = sum_i lambda_i z_i                                        (Eq. 1)
    var' = sum_i lambda_i (z_i - mu)^2 + epsilon                     (Eq. 2, diagonal)
    lambda_i = log(1 + K_e) - log(i), normalised to sum to 1         (log-rank weights)
    epsilon <- tau epsilon + (1 - tau) epsilon_end                   (noise decay)

with ``z_1..z_K_e`` the elites, best first, and ``mu`` the OLD mean.

Followed: Algorithm 1 of the paper (sample, gradient steps on half the
population, evaluate all, update from the top half); Eqs. 1-2 with the
log-rank weights; the decaying additive noise epsilon; the initial covariance
``Sigma = sigma_init I`` (``sigma_init`` is a variance, as in the authors'
``sepCEM``); a fresh Adam per improved actor (``TD3.policy_gradient_steps``);
the mean of the first distribution is a randomly initialised actor; the first
generation takes no gradient step (Algorithm 1: the step counter starts at 0).

Within the budget (every ``step`` plays exactly ``num_episodes`` episodes):

- Performance.  The paper reports the return of the mean actor ``mu``,
  evaluated outside the budget (the authors' code plays it apart, neither
  counting its steps nor storing its transitions).  Here it is played inside
  the budget: episode 0 of every iteration is ``mu`` itself (greedy, no noise),
  and ``max_fitness`` is its return, the paper's quantity.  The population is
  therefore the ``num_episodes - 1`` other episodes, all drawn from the
  distribution; ``mu``'s return is not ranked in the CEM update (it is no
  sample of the distribution), but its transitions go to the buffer since its
  steps are paid for.  The alternative, ``num_episodes`` samples and the best
  member reported, would report a different (upward-biased) quantity.  The
  reported ``mu`` is the mean this generation sampled from, i.e. the mean
  before this generation's update.
- Gradient steps.  The paper trains, per generation, the critic for as many
  steps as the environment steps of the previous generation, and each improved
  actor for that many steps too.  Here the critic takes the task's
  ``num_critic_steps`` steps and each improved actor ``num_actor_steps``
  (default: ``num_critic_steps``, the paper's ratio).  The paper interleaves
  ``critic block, actor i`` for each improved actor in turn, the critic's
  target policy being actor i as sampled; here the critic trains first, with
  the mean ``mu`` as its target policy (the samples are drawn around it), then
  the improved actors train in parallel against it.  ``TD3.train_critic`` is
  not used because it also trains TD3's own greedy actor, which CEM-RL has no
  use for; the critic steps are ``TD3.critic_step`` (twin critics, target
  smoothing, soft target updates), on replay batches drawn the same way.
- Population sizes.  ``K_e = int(elite_fraction * P)`` elites (at least one)
  and ``int(gradient_fraction * P)`` improved actors, ``P = num_episodes - 1``
  (paper: P = 10, five of each).  At Point-Maze's four actors (Section 3.6.3)
  that is 3 members, one improved and one elite: the budget, not the method,
  is small there.

Not reproduced: the authors' code draws antithetic pairs for an even
population and waits ``start_steps`` environment steps before the first
gradient step (neither is in Algorithm 1); its covariance update carries an
extra ``1 / K_e`` factor that Eq. 2 does not have (Eq. 2 is followed); the
paper's importance-mixing variant is not used (nor in Table 3.4's setting).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import jax
import jax.numpy as jnp
from flax import struct
from jax.flatten_util import ravel_pytree

from qdnb.core.evaluation import Evaluation
from qdnb.envs.base import Env
from qdnb.envs.rollout import evaluate_policies
from qdnb.nets.mlp import MLP
from qdnb.rl.buffer import ReplayBuffer
from qdnb.rl.td3 import TD3, TD3Config, TD3State

# TD3 as the CEM-RL paper (Appendix A) and its code (es_grad.py) set it: both learning rates 1e-3,
# minibatch 100, critic 400/300; the rest (gamma, tau, target noise and clip, delay) is TD3's.
# Chapter 3 passes its own task settings (Table 3.2) instead.
CEMRL_TD3 = TD3Config(actor_lr=1e-3, critic_lr=1e-3, batch_size=100, critic_hidden=(400, 300))


@dataclass(frozen=True)
class CEMConfig:
    """The cross-entropy method's settings; the defaults are the paper's
    (Section 5, experimental setup), equal to the authors' code defaults
    (``es_grad.py`` and ``ES.sepCEM``):

    ============================  ======  ==================================================
    field                         value   source
    ============================  ======  ==================================================
    ``sigma_init``                1e-3    Sigma_init = sigma_init I (a variance); sepCEM
    ``epsilon_init``              1e-3    initial noise epsilon (code: ``damp``)
    ``epsilon_end``               1e-5    its limit (code: ``damp_limit``)
    ``epsilon_decay``             0.95    tau in eps <- tau eps + (1 - tau) eps_end
    ``elite_fraction``            0.5     K_e = pop_size / 2 (code: ``parents``)
    ``gradient_fraction``         0.5     pop_size / 2 actors improved (code: ``n_grad=5``)
    ============================  ======  ==================================================
    """

    sigma_init: float = 1e-3
    epsilon_init: float = 1e-3
    epsilon_end: float = 1e-5
    epsilon_decay: float = 0.95
    elite_fraction: float = 0.5
    gradient_fraction: float = 0.5

    def __post_init__(self):
        if self.sigma_init <= 0:
            raise ValueError(f"sigma_init must be > 0, got {self.sigma_init}")
        if self.epsilon_init < 0 or self.epsilon_end < 0:
            raise ValueError(
                f"epsilon_init and epsilon_end must be >= 0, got "
                f"{self.epsilon_init} and {self.epsilon_end}"
            )
        if not 0.0 <= self.epsilon_decay <= 1.0:
            raise ValueError(f"epsilon_decay must be in [0, 1], got {self.epsilon_decay}")
        if not 0.0 < self.elite_fraction <= 1.0:
            raise ValueError(f"elite_fraction must be in (0, 1], got {self.elite_fraction}")
        if not 0.0 <= self.gradient_fraction <= 1.0:
            raise ValueError(f"gradient_fraction must be in [0, 1], got {self.gradient_fraction}")


def log_rank_weights(num_elites: int) -> jax.Array:
    """lambda_i = log(1 + K_e) - log(i), i = 1..K_e, normalised to sum to 1
    (best elite first)."""
    ranks = jnp.arange(1, num_elites + 1, dtype=jnp.float32)
    weights = jnp.log(1.0 + num_elites) - jnp.log(ranks)
    return weights / jnp.sum(weights)


def decay_epsilon(epsilon: jax.Array, decay: float, epsilon_end: float) -> jax.Array:
    """eps <- tau eps + (1 - tau) eps_end: after n decays,
    eps_end + (eps_0 - eps_end) tau^n."""
    return decay * epsilon + (1.0 - decay) * epsilon_end


def cem_update(
    mean: jax.Array,
    var: jax.Array,
    samples: jax.Array,
    fitnesses: jax.Array,
    num_elites: int,
    epsilon: jax.Array | float,
) -> tuple[jax.Array, jax.Array]:
    """One separable-CEM update of ``N(mean, diag(var))`` from ``samples``
    (``P x d``) and their ``fitnesses`` (``P``, higher is better).

    The ``num_elites`` best samples ``z_1..z_K`` (best first; ties keep the
    sample order) give the new mean (Eq. 1) ``sum_i lambda_i z_i`` and the new
    variances (Eq. 2) ``sum_i lambda_i (z_i - mean)^2 + epsilon``, deviations
    from the OLD mean, with the log-rank weights ``lambda``.  ``var`` is not
    read: Eq. 2 re-estimates the variances from the elites alone (the argument
    keeps the signature a map from one distribution, ``(mean, var)``, to the next).
    """
    elites = samples[jnp.argsort(-fitnesses)[:num_elites]]
    weights = log_rank_weights(num_elites)
    new_mean = weights @ elites
    new_var = weights @ (elites - mean) ** 2 + epsilon
    return new_mean, new_var


@struct.dataclass
class CEMRLState:
    mean: jax.Array  # mu, the mean actor's flat parameters (d,)
    var: jax.Array  # the diagonal of Sigma (d,)
    epsilon: jax.Array  # the noise added to the variances (decays every update)
    td3: TD3State  # the shared critic (its actor and target actor: the mean actor)
    buffer: ReplayBuffer
    performance: jax.Array  # return of the mean actor's last episode
    critic_loss: jax.Array  # mean critic loss of the last iteration (0 before any step)
    key: jax.Array


@dataclass(frozen=True, eq=False)
class CEMRLAgent:
    """The CEM-RL baseline (Table 3.4): a separable CEM over the actor's
    parameters whose first ``num_gradient_members`` samples take TD3 actor steps
    against a shared TD3 critic (module docstring: what is followed, what the
    budget changes).

    Each iteration plays ``num_episodes`` episodes without action noise: the
    mean actor (episode 0, ``max_fitness``), then the ``population_size =
    num_episodes - 1`` members, all stored in the replay buffer.
    ``num_actor_steps`` (``None``: ``num_critic_steps``) is the number of TD3
    actor steps of each improved member.
    """

    env: Env
    network: MLP
    td3_config: TD3Config = CEMRL_TD3
    cem_config: CEMConfig = CEMConfig()
    num_episodes: int = 11  # the mean actor and the paper's population of 10
    num_critic_steps: int = 100
    num_actor_steps: int | None = None
    buffer_size: int = 1_000_000

    def __post_init__(self):
        if self.num_episodes < 2:
            raise ValueError(
                f"num_episodes must be >= 2 (the mean actor and at least one member), "
                f"got {self.num_episodes}"
            )
        if self.num_critic_steps < 1:
            raise ValueError(f"num_critic_steps must be >= 1, got {self.num_critic_steps}")
        if self.num_actor_steps is not None and self.num_actor_steps < 1:
            raise ValueError(f"num_actor_steps must be >= 1, got {self.num_actor_steps}")
        if self.buffer_size < 1:
            raise ValueError(f"buffer_size must be >= 1, got {self.buffer_size}")

    @property
    def td3(self) -> TD3:
        return TD3(self.network, self.env.observation_size, self.env.action_size, self.td3_config)

    @property
    def population_size(self) -> int:
        return self.num_episodes - 1

    @property
    def num_elites(self) -> int:
        return max(1, int(self.cem_config.elite_fraction * self.population_size))

    @property
    def num_gradient_members(self) -> int:
        return int(self.cem_config.gradient_fraction * self.population_size)

    def _unravel(self):
        """The map from a flat parameter vector to the actor's parameter pytree."""
        shapes = jax.eval_shape(
            self.network.init, jax.random.PRNGKey(0), jnp.zeros((self.env.observation_size,))
        )
        return ravel_pytree(jax.tree.map(lambda s: jnp.zeros(s.shape, s.dtype), shapes))[1]

    @property
    def num_params(self) -> int:
        shapes = jax.eval_shape(
            self.network.init, jax.random.PRNGKey(0), jnp.zeros((self.env.observation_size,))
        )
        return sum(math.prod(s.shape) for s in jax.tree.leaves(shapes))

    def sample(self, mean: jax.Array, var: jax.Array, key: jax.Array) -> jax.Array:
        """``population_size`` flat actors drawn from N(mean, diag(var))."""
        noise = jax.random.normal(key, (self.population_size,) + mean.shape)
        return mean + jnp.sqrt(var) * noise

    def apply_gradients(
        self, critic, buffer: ReplayBuffer, samples: jax.Array, key: jax.Array
    ) -> jax.Array:
        """The population with its first ``num_gradient_members`` rows improved by
        TD3 actor steps against ``critic`` (each with a fresh optimiser and its own
        replay batches); the other rows are returned as sampled."""
        n = self.num_gradient_members
        if n == 0:
            return samples
        td3, unravel = self.td3, self._unravel()
        steps = self.num_actor_steps or self.num_critic_steps

        def improve(flat, k):
            actor = td3.policy_gradient_steps(unravel(flat), critic, buffer, k, steps)
            return ravel_pytree(actor)[0]

        improved = jax.vmap(improve)(samples[:n], jax.random.split(key, n))
        return samples.at[:n].set(improved)

    def train_critic(
        self, td3_state: TD3State, mean: jax.Array, buffer: ReplayBuffer, key: jax.Array
    ) -> tuple[TD3State, jax.Array]:
        """``num_critic_steps`` TD3 critic steps (``TD3.critic_step``) on replay
        batches, the mean actor as the target policy; returns the mean loss."""
        td3, cfg, n = self.td3, self.td3_config, self.num_critic_steps
        mean_actor = self._unravel()(mean)
        td3_state = td3_state.replace(actor=mean_actor, actor_target=mean_actor)
        k_batch, k_noise = jax.random.split(key)
        batches = jax.tree.map(
            lambda x: x.reshape((n, cfg.batch_size) + x.shape[1:]),
            buffer.sample(k_batch, n * cfg.batch_size),
        )
        td3_state, losses = jax.lax.scan(
            lambda s, bk: td3.critic_step(s, *bk),
            td3_state,
            (batches, jax.random.split(k_noise, n)),
        )
        return td3_state, jnp.mean(losses)

    def _generation(
        self,
        state: CEMRLState,
        population: jax.Array,
        key: jax.Array,
        td3_state: TD3State,
        critic_loss: jax.Array,
    ) -> tuple[CEMRLState, Evaluation]:
        """Play the mean actor then the population (one batch), store every
        transition, and update the distribution from the population's returns."""
        k_eval, key = jax.random.split(key)
        flat = jnp.concatenate([state.mean[None], population])
        actors = jax.vmap(self._unravel())(flat)
        ev = evaluate_policies(self.env, self.network.apply, actors, k_eval, True)
        buffer = state.buffer.add_episodes(ev.trajectory, ev.fitness.ndim)
        cfg = self.cem_config
        epsilon = decay_epsilon(state.epsilon, cfg.epsilon_decay, cfg.epsilon_end)
        mean, var = cem_update(
            state.mean, state.var, population, ev.fitness[1:], self.num_elites, epsilon
        )
        new_state = CEMRLState(
            mean, var, epsilon, td3_state, buffer, ev.fitness[0], critic_loss, key
        )
        return new_state, ev

    def init(self, key: jax.Array) -> tuple[CEMRLState, Evaluation]:
        """The first generation (Algorithm 1 with no gradient step yet): a random
        mean actor, Sigma = sigma_init I, the population played and ranked."""
        k_td3, k_pop, key = jax.random.split(key, 3)
        env, cfg = self.env, self.cem_config
        td3_state = self.td3.init(k_td3)
        mean = ravel_pytree(td3_state.actor)[0]
        var = jnp.full_like(mean, cfg.sigma_init)
        buffer = ReplayBuffer.create(self.buffer_size, env.observation_size, env.action_size)
        state = CEMRLState(
            mean,
            var,
            jnp.asarray(cfg.epsilon_init, jnp.float32),
            td3_state,
            buffer,
            jnp.zeros(()),
            jnp.zeros(()),
            key,
        )
        return self._generation(state, self.sample(mean, var, k_pop), key, td3_state, jnp.zeros(()))

    def step(self, state: CEMRLState) -> tuple[CEMRLState, Evaluation]:
        """Sample, train the critic, improve half the population, play, update."""
        k_pop, k_critic, k_actor, key = jax.random.split(state.key, 4)
        td3_state, critic_loss = self.train_critic(state.td3, state.mean, state.buffer, k_critic)
        population = self.sample(state.mean, state.var, k_pop)
        population = self.apply_gradients(td3_state.critic, state.buffer, population, k_actor)
        return self._generation(state, population, key, td3_state, critic_loss)

    def metrics(self, state: CEMRLState) -> dict[str, jax.Array]:
        return {"max_fitness": state.performance}
