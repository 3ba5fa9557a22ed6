"""Evolution strategies with a diversity component: the evolutionary competitors
of Chapter 3 (Table 3.3: ME-ES, NSR-ES, NSRA-ES on Ant-Maze).

Three papers and two code bases, whose notation the equations below keep:

- Salimans et al. (2017), "Evolution strategies as a scalable alternative to
  reinforcement learning": the ES core (``OpenAIES``);
- Conti et al. (2018), "Improving exploration in evolution strategies for deep
  reinforcement learning via a population of novelty-seeking agents" (code:
  ``uber-research/deep-neuroevolution``, ``es_distributed/nses.py``): NSR-ES
  and NSRA-ES (``NSRES``, ``NSRAES``);
- Colas et al. (2020), "Scaling MAP-Elites to deep neuroevolution", as QDax's
  ``MEESEmitter`` implements it (``qdax/core/emitters/mees_emitter.py``, the code
  base the thesis ran): ME-ES (``MEES``).

The ES core.  A policy's parameters are flattened (``ravel_pytree``) into
``theta`` in R^d.  ES ascends the Gaussian smoothing of the fitness F,

    J(theta) = E_eps[F(theta + sigma eps)],  eps ~ N(0, I_d),
    grad J(theta) = (1 / sigma) E_eps[F(theta + sigma eps) eps],           (ES-1)

estimated from ``n`` perturbations drawn in antithetic (mirrored) pairs,
``eps_{i + n/2} = -eps_i`` (``antithetic_noise``), with the fitnesses replaced by
their centred ranks (``centred_ranks``: the lowest gets -0.5, the highest +0.5):

    s_i = rank(F_i) / (n - 1) - 1/2,                                      (ES-2)
    g = 1 / (n sigma) sum_i s_i eps_i                                     (ES-3)

(``es_gradient``; ``mirrored_gradient`` sums it pair by pair from the first
half of the noise; the reference code divides by ``n`` alone, a constant
factor Adam does not see, up to its epsilon).  Adam (Kingma and Ba's
defaults, as the reference code) then takes one ascent step along
``g - lambda theta``, the L2 weight decay ``lambda theta`` of the reference
code, which passes ``-g + l2coeff * theta`` to a minimising Adam
(``es_update``):

    theta <- theta + Adam(g - lambda theta).                              (ES-4)

As in the reference code (``SharedNoiseTable``: 250M Gaussians from seed 123),
the ``eps_i`` are windows of ``d`` consecutive entries, at uniform random
offsets, of a noise table drawn once per run (``noise_table_size`` entries,
from the run's key); ``noise_table_size=None`` draws them afresh each
generation, as QDax does.  Reading the table costs a copy where drawing costs
one Threefry word per entry (about 10% of a Point-Maze generation on CPU).

Novelty (Eq. 2.5, ``qdnb.qd.novelty``).  ``N(b, A)`` is the mean distance of a
behaviour descriptor ``b`` to its ``k`` nearest neighbours in an archive ``A``
of descriptors.

NSR-ES / NSRA-ES (Conti et al., 2018).  A meta-population of ``M``
ES learners; each generation one learner ``m`` is drawn with probability

    P(m) = N(b(theta^m), A) / sum_j N(b(theta^j), A),                     (NS-1)

its perturbations are scored by a mix of their fitness and novelty ranks

    s_i = w R(F_i) + (1 - w) R(N(b_i, A)),                                (NS-2)

(``nsr_scores``; R = Eq. ES-2), it takes the step ES-3/ES-4 (its own Adam), and
the descriptor of its new centre joins ``A``.  NSR-ES keeps ``w = 1/2``.
NSRA-ES starts at ``w = 1`` and adapts it (``nsra_adapt``), each generation,
from the fitness ``f`` of the centre just updated:

    if f > f_best:  w <- min(1, w + delta), f_best <- f, t <- 0
    else:           t <- t + 1;  if t >= t_max:  w <- max(0, w - delta), t <- 0    (NS-3)

(``weight_delta`` = delta, ``stagnation`` = t_max).  The released NS-ES code
has no NSRA-ES; two re-implementations we read (PaddlePaddle's ``esbox``
``NSRAES``, with delta = 0.05 and t_max = 10, and a ``NoveltyAdaptor``) code
this rule but test ``t > t_max``, lowering ``w`` one generation later; here
``t_max`` generations without improvement suffice.

ME-ES (QDax's ``MEESEmitter``).  A MAP-Elites grid and one ES emitter.  The
emitter alternates ``num_optimizer_steps`` generations of novelty gradients
(explore) with as many of fitness gradients (exploit), starting with explore:
at generation ``g``, a new parent is drawn when ``g % num_optimizer_steps == 0``
(and Adam restarts), and the mode is explore when ``(g // num_optimizer_steps)``
is even (``mees_schedule``).  Explore draws the parent uniformly among the
``explore_num_cell_sample`` filled cells most novel w.r.t. the novelty archive;
exploit draws it, with probability 1/2 each, uniformly among the
``exploit_num_cell_sample`` fittest cells of the grid or among the fittest of the
``last_updated_size`` last offspring that entered the grid.  Otherwise the
parent is the previous offspring.  The ES step (ES-1 to ES-4 with the novelty
or the fitness of the perturbations as F) gives the next offspring, which is
evaluated, offered to the grid and whose descriptor joins the novelty archive
(every offspring's, no threshold: QDax's archive is a FIFO of them).

One batch of episodes per ``step``.  ``step`` plays exactly one vmapped batch
(``evaluate_policies``): the centre(s) and the perturbations together.  The
centre cannot be the one the step is about to compute, so each step evaluates
the centre its perturbations were drawn around (ES: ``max_fitness`` is the
return of the centre before this step's update, as CEM-RL's mean actor in
``qdnb.rl.cemrl``; NS-ES: every centre as it stands, the one updated last
step included) or the offspring of the previous step (ME-ES, exactly QDax's
order).  Episodes per step (``episodes_per_step``):

- ``OpenAIES``:  ``num_perturbations + 1`` (the centre, then the perturbations);
- ``NSRES``/``NSRAES``: ``num_perturbations + meta_population_size`` (every
  centre, then the perturbations of the learner drawn);
- ``MEES``: ``num_perturbations + 1`` (the previous offspring, then the
  perturbations of this generation's parent).

``start(key)`` is the state before any episode (random centres, empty archives),
and ``init(key)`` is ``step(start(key))``, so the first generation plays the same
batch as every step; ``run_seeds`` then compiles the whole run, first generation
included, as one program (``qdnb.qd.algorithms``).

Followed: antithetic sampling, centred ranks, the 1/(n sigma) estimator, Adam,
L2 decay on theta (ES-1..4), the noise table; NS-1..3 with one global ``w``
and ``f_best``, one Adam per learner, the initial centres' descriptors seeding
the archive, the reference's defaults; QDax's MEES schedule, parent sampling
and last-updated buffer, its novelty archive (every offspring's descriptor,
novelty as the mean distance to the ``k`` nearest), its defaults.

Simplified (and why):

- One-batch lag in the parent choice.  NS-ES draws the learner from the
  descriptors of the previous batch: the learner updated last generation is
  drawn with the novelty of its centre before that update (the reference
  re-plays every centre before drawing, extra episodes outside the batch).
  ME-ES draws a new parent (once every ``num_optimizer_steps`` generations)
  from the grid before the offspring evaluated in the same batch is inserted
  (QDax inserts it first).  Both keep one evaluation per step.
- One episode per centre descriptor (the NS-ES code averages 5 rollouts), no
  observation normalisation and no action noise (the reference MuJoCo policies
  have both; Point-Maze's observations are positions in [-1, 1]^2).
- Archives are fixed-capacity FIFOs (``archive_size``, default 1000); the
  references grow them for the whole run (QDax sizes it to the number of
  generations): an ``archive_size`` of at least the run's descriptor count
  matches them (the chapter's registry, ``ch3_qdpg.METHODS``, sizes it so).
  Novelty costs grow with the capacity: scoring 1000 perturbations against 1000
  entries takes about 3.5 ms on CPU (most of it ``top_k``), against 10,000
  about 22 ms.
- Parents among "the top k cells" are the ``k`` cells ``lax.top_k`` returns
  (QDax takes every cell scoring at least the k-th score, ties included), and
  an empty last-updated buffer or an empty grid falls back to the grid or to
  the previous offspring (QDax would sample with NaN probabilities there).
- ME-ES reads its perturbations from the noise table too (QDax draws them
  afresh; ``noise_table_size=None`` does that).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import jax
import jax.numpy as jnp
import optax
from flax import struct
from jax.flatten_util import ravel_pytree

from qdnb.core.evaluation import Evaluation
from qdnb.envs.base import Env
from qdnb.envs.rollout import evaluate_policies
from qdnb.nets.mlp import MLP
from qdnb.qd import repertoire as rep_lib
from qdnb.qd.cvt import grid_centroids
from qdnb.qd.novelty import NoveltyArchive

# ---------------------------------------------------------------------------
# The ES core (Salimans et al., 2017): pure functions
# ---------------------------------------------------------------------------


def centred_ranks(x: jax.Array) -> jax.Array:
    """Eq. ES-2: ranks of ``x`` (0 for the lowest) mapped linearly onto
    [-0.5, 0.5]; ties are ranked in index order (as ``argsort``), e.g.
    ``[3, 1, 2] -> [0.5, -0.5, 0]``."""
    n = x.shape[0]
    if n < 2:
        raise ValueError(f"centred ranks need at least 2 values, got {n}")
    order = jnp.argsort(x)  # stable: ties in index order
    ranks = jnp.zeros(n, jnp.int32).at[order].set(jnp.arange(n, dtype=jnp.int32))  # one sort
    return ranks.astype(jnp.float32) / (n - 1) - 0.5


def mirrored_half(key: jax.Array, n: int, dim: int, table: jax.Array | None = None) -> jax.Array:
    """The first half ``eps_1..eps_{n/2}`` of ``n`` antithetic perturbations of
    R^dim (the second half is its negation), shape ``(n / 2, dim)``: standard
    Gaussian draws, or, given a noise ``table`` (Salimans et al.'s shared noise
    table, as in the reference code), ``n / 2`` windows of ``dim`` consecutive
    entries at uniform random offsets."""
    if n < 2 or n % 2:
        raise ValueError(f"antithetic sampling needs an even n >= 2, got {n}")
    if table is None:
        return jax.random.normal(key, (n // 2, dim))
    if table.shape[0] < dim:
        raise ValueError(f"a noise table of {table.shape[0]} entries is shorter than dim={dim}")
    offsets = jax.random.randint(key, (n // 2,), 0, table.shape[0] - dim + 1)
    return jax.vmap(lambda o: jax.lax.dynamic_slice(table, (o,), (dim,)))(offsets)


def antithetic_noise(key: jax.Array, n: int, dim: int, table: jax.Array | None = None) -> jax.Array:
    """``n`` perturbations of R^dim in mirrored pairs, ``eps_{i + n/2} = -eps_i``
    (shape ``(n, dim)``; ``mirrored_half`` draws the first half)."""
    half = mirrored_half(key, n, dim, table)
    return jnp.concatenate([half, -half])


def es_gradient(noise: jax.Array, shaped_scores: jax.Array, sigma: float) -> jax.Array:
    """Eq. ES-3: ``g = 1 / (n sigma) sum_i s_i eps_i`` for perturbations
    ``noise`` (``(n, d)``) and their (shaped) scores ``s`` (``(n,)``)."""
    return shaped_scores @ noise / (noise.shape[0] * sigma)


def mirrored_gradient(half: jax.Array, shaped_scores: jax.Array, sigma: float) -> jax.Array:
    """Eq. ES-3 for antithetic perturbations given by their first half: the sum
    regrouped by pairs, ``1 / (n sigma) sum_{i <= n/2} (s_i - s_{i + n/2}) eps_i``
    (equal to ``es_gradient(antithetic noise, s, sigma)``, without the mirror
    half in memory)."""
    h = half.shape[0]
    return (shaped_scores[:h] - shaped_scores[h:]) @ half / (2 * h * sigma)


def es_update(
    optimizer: optax.GradientTransformation,
    theta: jax.Array,
    opt_state: Any,
    gradient: jax.Array,
    weight_decay: float,
) -> tuple[jax.Array, Any]:
    """Eq. ES-4, one ES step: the ascent direction ``g - lambda theta`` handed,
    negated, to the (minimising) ``optimizer``."""
    updates, opt_state = optimizer.update(weight_decay * theta - gradient, opt_state, theta)
    return optax.apply_updates(theta, updates), opt_state


def nsr_scores(fitness: jax.Array, novelty: jax.Array, reward_weight: jax.Array | float):
    """Eq. NS-2: ``w R(fitness) + (1 - w) R(novelty)`` with R the centred ranks."""
    w = reward_weight
    return w * centred_ranks(fitness) + (1.0 - w) * centred_ranks(novelty)


def nsra_adapt(
    reward_weight: jax.Array,
    best_fitness: jax.Array,
    stagnation_count: jax.Array,
    fitness: jax.Array,
    delta: float,
    stagnation: int,
) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Eq. NS-3, NSRA-ES's weight adaptation after one generation whose updated
    centre scored ``fitness``: an improvement on ``best_fitness`` raises the
    reward weight by ``delta`` (at most 1) and resets the count; otherwise the
    count grows, and ``stagnation`` generations without improvement lower the
    weight by ``delta`` (at least 0) and reset the count.  Returns the new
    weight, best fitness and count."""
    improved = fitness > best_fitness
    count = jnp.where(improved, 0, stagnation_count + 1)
    weight = jnp.where(improved, jnp.minimum(1.0, reward_weight + delta), reward_weight)
    stalled = count >= stagnation
    weight = jnp.where(stalled, jnp.maximum(0.0, weight - delta), weight)
    count = jnp.where(stalled, 0, count)
    return weight, jnp.maximum(best_fitness, fitness), count


def mees_schedule(
    generation: jax.Array | int,
    num_optimizer_steps: int,
    use_explore: bool = True,
    use_exploit: bool = True,
) -> tuple[jax.Array, jax.Array]:
    """QDax's MEES alternation at ``generation`` (0 first): whether a new parent
    is drawn from the grid (every ``num_optimizer_steps`` generations) and
    whether the gradient is novelty's (explore) rather than fitness's.  With
    both modes, explore for ``num_optimizer_steps`` generations, then exploit
    as long, and so on; with one mode, that mode throughout."""
    generation = jnp.asarray(generation)
    new_parent = generation % num_optimizer_steps == 0
    if use_explore and use_exploit:
        explore = (generation // num_optimizer_steps) % 2 == 0
    else:
        explore = jnp.full(generation.shape, use_explore)
    return new_parent, explore


def _novelty_probabilities(novelty: jax.Array) -> jax.Array:
    """Eq. NS-1, with a uniform draw when no novelty is finite and positive
    (an empty archive: every novelty is +inf)."""
    finite = jnp.where(jnp.isfinite(novelty), novelty, 0.0)
    total = jnp.sum(finite)
    return jnp.where(total > 0, finite / jnp.where(total > 0, total, 1.0), 1.0 / novelty.shape[0])


def _pick_among_top(key: jax.Array, scores: jax.Array, k: int) -> tuple[jax.Array, jax.Array]:
    """An index drawn uniformly among the ``k`` highest scores that are not
    ``-inf``, and whether there was any."""
    top, idx = jax.lax.top_k(scores, k)
    ok = top > -jnp.inf
    found = jnp.any(ok)
    p = jnp.where(found, ok / jnp.maximum(jnp.sum(ok), 1), 1.0 / k)
    return idx[jax.random.choice(key, k, p=p)], found


def _where_tree(condition: jax.Array, a: Any, b: Any) -> Any:
    return jax.tree.map(lambda x, y: jnp.where(condition, x, y), a, b)


# ---------------------------------------------------------------------------
# What the three methods share
# ---------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class _EvolutionStrategy:
    """The task, the policy network and the ES core's settings."""

    env: Env
    network: MLP
    num_perturbations: int = 10_000
    sigma: float = 0.02
    learning_rate: float = 0.01
    weight_decay: float = 0.005
    noise_table_size: int | None = 2**21

    # over several devices, when they do not divide the seeds: split each generation's
    # perturbations (bench/scale_out.py)
    split = "population"

    def __post_init__(self):
        n = self.num_perturbations
        if not isinstance(n, int) or n < 2 or n % 2:
            raise ValueError(
                f"num_perturbations must be an even integer >= 2 (antithetic pairs), got {n}"
            )
        if not self.sigma > 0:
            raise ValueError(f"sigma must be > 0, got {self.sigma}")
        if not self.learning_rate > 0:
            raise ValueError(f"learning_rate must be > 0, got {self.learning_rate}")
        if not self.weight_decay >= 0:
            raise ValueError(f"weight_decay must be >= 0, got {self.weight_decay}")
        if self.noise_table_size is not None and self.noise_table_size < self.num_parameters:
            raise ValueError(
                f"noise_table_size ({self.noise_table_size}) must be at least the number of "
                f"policy parameters ({self.num_parameters}), or None for fresh draws"
            )

    @property
    def optimizer(self) -> optax.GradientTransformation:
        return optax.adam(self.learning_rate)

    def _flat_structure(self) -> tuple[int, Any]:
        """The length of the flat parameter vector and the function that unflattens
        it (from the parameters' shapes only)."""
        shapes = jax.eval_shape(
            self.network.init, jax.random.key(0), jnp.zeros((self.env.observation_size,))
        )
        flat, unravel = ravel_pytree(jax.tree.map(lambda s: jnp.zeros(s.shape, s.dtype), shapes))
        return flat.shape[0], unravel

    @property
    def num_parameters(self) -> int:
        """d, the number of policy parameters."""
        return self._flat_structure()[0]

    def _unravel(self, flat: jax.Array) -> Any:
        return self._flat_structure()[1](flat)

    def noise_table(self, key: jax.Array) -> jax.Array:
        """A fresh noise table of ``noise_table_size`` standard Gaussians (empty when
        ``noise_table_size`` is None: perturbations are then drawn afresh)."""
        return jax.random.normal(key, (self.noise_table_size or 0,))

    def random_centre(self, key: jax.Array) -> jax.Array:
        """The flat parameters of a freshly initialised policy."""
        params = self.network.init(key, jnp.zeros((self.env.observation_size,)))
        return ravel_pytree(params)[0]

    def noise(self, key: jax.Array, table: jax.Array, dim: int) -> jax.Array:
        """The first half ``eps_1..eps_{n/2}`` of this generation's antithetic
        perturbations of R^dim (``(n / 2, dim)``): windows of the noise table, or
        fresh draws without one."""
        table = None if self.noise_table_size is None else table
        return mirrored_half(key, self.num_perturbations, dim, table)

    def evaluate(
        self, centres: jax.Array, theta: jax.Array, half: jax.Array, key: jax.Array
    ) -> Evaluation:
        """One episode for each of the flat parameter vectors ``centres`` (``(c, d)``),
        then for each perturbed policy ``theta + sigma eps_i`` of the pairs' ``+`` half
        and ``theta - sigma eps_i`` of their ``-`` half (``n`` episodes), all in one
        vmapped batch of ``c + n`` episodes.

        The perturbed parameters are built leaf by leaf from the unflattened
        ``theta`` and ``half`` (one write of the batch's parameters, where
        perturbing the flat vectors and then unflattening them writes it twice), and
        materialised before the rollout (an optimisation barrier): left to itself,
        XLA may fuse ``theta + sigma eps`` into the rollout's loop and redo it at
        every time step.
        """
        unravel = jax.vmap(self._unravel)
        params = jax.tree.map(
            lambda c, t, e: jnp.concatenate([c, t + self.sigma * e, t - self.sigma * e]),
            unravel(centres),
            self._unravel(theta),
            unravel(half),
        )
        params = jax.lax.optimization_barrier(params)
        return evaluate_policies(self.env, self.network.apply, params, key)

    def ascend(
        self, theta: jax.Array, opt_state: Any, half: jax.Array, shaped_scores: jax.Array
    ) -> tuple[jax.Array, Any]:
        """Eqs. ES-3 and ES-4 from the perturbations' shaped scores."""
        gradient = mirrored_gradient(half, shaped_scores, self.sigma)
        return es_update(self.optimizer, theta, opt_state, gradient, self.weight_decay)

    def init(self, key: jax.Array) -> tuple[Any, Evaluation]:
        """The first generation: ``step(start(key))``."""
        return self.step(self.start(key))


# ---------------------------------------------------------------------------
# OpenAI-ES (Salimans et al., 2017)
# ---------------------------------------------------------------------------


@struct.dataclass
class ESState:
    theta: jax.Array  # the centre's flat parameters (d,)
    opt_state: Any
    fitness: jax.Array  # return of the centre's last episode
    noise_table: jax.Array
    key: jax.Array


@dataclass(frozen=True, eq=False)
class OpenAIES(_EvolutionStrategy):
    """OpenAI-ES (Salimans et al., 2017), Eqs. ES-1 to ES-4.

    Each step plays ``num_perturbations + 1`` episodes: the centre (its return
    is ``max_fitness``), then its antithetic perturbations, whose centred
    fitness ranks give the Adam step.
    """

    @property
    def episodes_per_step(self) -> int:
        return self.num_perturbations + 1

    def start(self, key: jax.Array) -> ESState:
        k_init, k_table, key = jax.random.split(key, 3)
        theta = self.random_centre(k_init)
        table = self.noise_table(k_table)
        return ESState(theta, self.optimizer.init(theta), jnp.asarray(-jnp.inf), table, key)

    def step(self, state: ESState) -> tuple[ESState, Evaluation]:
        key, k_noise, k_eval = jax.random.split(state.key, 3)
        half = self.noise(k_noise, state.noise_table, state.theta.shape[0])
        ev = self.evaluate(state.theta[None], state.theta, half, k_eval)
        theta, opt_state = self.ascend(
            state.theta, state.opt_state, half, centred_ranks(ev.fitness[1:])
        )
        return state.replace(theta=theta, opt_state=opt_state, fitness=ev.fitness[0], key=key), ev

    def metrics(self, state: ESState) -> dict[str, jax.Array]:
        return {"max_fitness": state.fitness}


# ---------------------------------------------------------------------------
# NSR-ES and NSRA-ES (Conti et al., 2018)
# ---------------------------------------------------------------------------


@struct.dataclass
class NSESState:
    thetas: jax.Array  # the M centres (M, d)
    opt_states: Any  # one Adam state per learner (leading axis M)
    fitnesses: jax.Array  # each centre's last return (M,)
    descriptors: jax.Array  # each centre's last descriptor (M, descriptor_size)
    unarchived: jax.Array  # centres changed since their descriptor last joined the archive
    archive: NoveltyArchive
    reward_weight: jax.Array  # w of Eq. NS-2
    best_fitness: jax.Array  # f_best of Eq. NS-3
    stagnation_count: jax.Array  # t of Eq. NS-3
    noise_table: jax.Array
    key: jax.Array


@dataclass(frozen=True, eq=False)
class NSRES(_EvolutionStrategy):
    """NSR-ES (Conti et al., 2018): ``meta_population_size`` ES learners, one
    drawn per generation by novelty (Eq. NS-1) and moved by the mixed fitness
    and novelty ranks of its perturbations (Eq. NS-2, ``w = reward_weight``).

    Each step plays ``num_perturbations + meta_population_size`` episodes: every
    centre (their descriptors, those changed since, join the archive; the best
    of their returns is ``max_fitness``), then the drawn learner's
    perturbations.  ``k`` nearest neighbours for novelty; ``archive_size`` the
    novelty archive's capacity.  ``adaptive`` turns on NSRA-ES's Eq. NS-3
    (``NSRAES``).
    """

    meta_population_size: int = 5
    k: int = 10
    archive_size: int = 1000
    reward_weight: float = 0.5
    adaptive: bool = False
    weight_delta: float = 0.05
    stagnation: int = 10

    def __post_init__(self):
        super().__post_init__()
        if self.meta_population_size < 1:
            raise ValueError(f"meta_population_size must be >= 1, got {self.meta_population_size}")
        if self.k < 1:
            raise ValueError(f"k must be >= 1, got {self.k}")
        if self.archive_size < self.k:
            raise ValueError(f"archive_size ({self.archive_size}) must be >= k ({self.k})")
        if not 0.0 <= self.reward_weight <= 1.0:
            raise ValueError(f"reward_weight must be in [0, 1], got {self.reward_weight}")
        if not 0.0 < self.weight_delta <= 1.0:
            raise ValueError(f"weight_delta must be in (0, 1], got {self.weight_delta}")
        if self.stagnation < 1:
            raise ValueError(f"stagnation must be >= 1, got {self.stagnation}")

    @property
    def episodes_per_step(self) -> int:
        return self.num_perturbations + self.meta_population_size

    def start(self, key: jax.Array) -> NSESState:
        k_init, k_table, key = jax.random.split(key, 3)
        m = self.meta_population_size
        thetas = jax.vmap(self.random_centre)(jax.random.split(k_init, m))
        return NSESState(
            thetas=thetas,
            opt_states=jax.vmap(self.optimizer.init)(thetas),
            fitnesses=jnp.full((m,), -jnp.inf),
            descriptors=jnp.zeros((m, self.env.descriptor_size)),
            unarchived=jnp.ones((m,), bool),
            archive=NoveltyArchive.create(self.archive_size, self.env.descriptor_size),
            reward_weight=jnp.asarray(self.reward_weight, jnp.float32),
            best_fitness=jnp.asarray(-jnp.inf),
            stagnation_count=jnp.zeros((), jnp.int32),
            noise_table=self.noise_table(k_table),
            key=key,
        )

    def step(self, state: NSESState) -> tuple[NSESState, Evaluation]:
        key, k_select, k_noise, k_eval = jax.random.split(state.key, 4)
        m_size = self.meta_population_size
        # Eq. NS-1 on the descriptors of the last batch
        novelty = state.archive.novelty(state.descriptors, self.k)
        m = jax.random.choice(k_select, m_size, p=_novelty_probabilities(novelty))
        theta = state.thetas[m]
        half = self.noise(k_noise, state.noise_table, theta.shape[0])
        ev = self.evaluate(state.thetas, theta, half, k_eval)
        fit_c, desc_c = ev.fitness[:m_size], ev.descriptor[:m_size]
        archive = state.archive.add(desc_c, -jnp.inf, self.k, valid=state.unarchived)
        weight, best, count = state.reward_weight, state.best_fitness, state.stagnation_count
        if self.adaptive:  # Eq. NS-3 on the centre(s) updated since the last batch
            updated = jnp.max(jnp.where(state.unarchived, fit_c, -jnp.inf))
            weight, best, count = nsra_adapt(
                weight, best, count, updated, self.weight_delta, self.stagnation
            )
        # Eq. NS-2, then ES-3/ES-4 with learner m's own Adam
        novelty_p = archive.novelty(ev.descriptor[m_size:], self.k)
        shaped = nsr_scores(ev.fitness[m_size:], novelty_p, weight)
        opt_m = jax.tree.map(lambda x: x[m], state.opt_states)
        theta, opt_m = self.ascend(theta, opt_m, half, shaped)
        new_state = state.replace(
            thetas=state.thetas.at[m].set(theta),
            opt_states=jax.tree.map(lambda x, y: x.at[m].set(y), state.opt_states, opt_m),
            fitnesses=fit_c,
            descriptors=desc_c,
            unarchived=jnp.arange(m_size) == m,
            archive=archive,
            reward_weight=weight,
            best_fitness=best,
            stagnation_count=count,
            key=key,
        )
        return new_state, ev

    def metrics(self, state: NSESState) -> dict[str, jax.Array]:
        return {"max_fitness": jnp.max(state.fitnesses), "reward_weight": state.reward_weight}


@dataclass(frozen=True, eq=False)
class NSRAES(NSRES):
    """NSRA-ES (Conti et al., 2018): NSR-ES whose reward weight starts at 1 and
    adapts by Eq. NS-3 (``weight_delta``, after ``stagnation`` generations
    without a better centre)."""

    reward_weight: float = 1.0
    adaptive: bool = True


# ---------------------------------------------------------------------------
# ME-ES (Colas et al., 2020; QDax's MEESEmitter)
# ---------------------------------------------------------------------------


@struct.dataclass
class MEESState:
    repertoire: rep_lib.Repertoire  # genotypes: flat parameters (num_cells, d)
    archive: NoveltyArchive  # descriptors of every offspring
    offspring: jax.Array  # the last ES offspring, evaluated by the next step (d,)
    opt_state: Any
    last_genotypes: jax.Array  # last offspring that entered the grid (last_updated_size, d)
    last_fitnesses: jax.Array  # their fitnesses (-inf: empty slot)
    last_position: jax.Array  # next slot of that buffer
    generation: jax.Array  # QDax's generation_count
    noise_table: jax.Array
    key: jax.Array


@dataclass(frozen=True, eq=False)
class MEES(_EvolutionStrategy):
    """ME-ES (Colas et al., 2020) as QDax's ``MEESEmitter`` runs it, explore and
    exploit alternating (``use_explore``/``use_exploit`` give QDax's two
    one-mode variants).

    Each step plays ``num_perturbations + 1`` episodes: the previous offspring
    (inserted into the grid, its descriptor into the novelty archive), then the
    perturbations of this generation's parent.  ``max_fitness`` is the grid's
    best fitness.  The grid's cells are ``centroids`` or, when ``None``, a
    regular grid of ``bins`` cells per descriptor dimension over the
    environment's descriptor bounds.
    """

    num_perturbations: int = 1000
    weight_decay: float = 0.02
    centroids: jax.Array | None = None
    bins: int = 10
    num_optimizer_steps: int = 10
    k: int = 10
    archive_size: int = 1000
    last_updated_size: int = 5
    exploit_num_cell_sample: int = 2
    explore_num_cell_sample: int = 5
    use_explore: bool = True
    use_exploit: bool = True

    def __post_init__(self):
        super().__post_init__()
        if self.num_optimizer_steps < 1:
            raise ValueError(f"num_optimizer_steps must be >= 1, got {self.num_optimizer_steps}")
        if not (self.use_explore or self.use_exploit):
            raise ValueError("at least one of use_explore and use_exploit must be True")
        if self.k < 1:
            raise ValueError(f"k must be >= 1, got {self.k}")
        if self.archive_size < self.k:
            raise ValueError(f"archive_size ({self.archive_size}) must be >= k ({self.k})")
        if self.centroids is None and self.bins < 1:
            raise ValueError(f"bins must be >= 1, got {self.bins}")
        if self.last_updated_size < 1:
            raise ValueError(f"last_updated_size must be >= 1, got {self.last_updated_size}")
        num_cells = self.grid.shape[0]
        if not 1 <= self.exploit_num_cell_sample <= min(num_cells, self.last_updated_size):
            raise ValueError(
                f"exploit_num_cell_sample must be in [1, min(num_cells, last_updated_size)] = "
                f"[1, {min(num_cells, self.last_updated_size)}], "
                f"got {self.exploit_num_cell_sample}"
            )
        if not 1 <= self.explore_num_cell_sample <= num_cells:
            raise ValueError(
                f"explore_num_cell_sample must be in [1, {num_cells}], "
                f"got {self.explore_num_cell_sample}"
            )

    @property
    def grid(self) -> jax.Array:
        """The grid's centroids."""
        if self.centroids is not None:
            return jnp.asarray(self.centroids)
        env = self.env
        bins = (self.bins,) * env.descriptor_size
        return grid_centroids(bins, env.descriptor_low, env.descriptor_high)

    @property
    def episodes_per_step(self) -> int:
        return self.num_perturbations + 1

    def start(self, key: jax.Array) -> MEESState:
        k_init, k_table, key = jax.random.split(key, 3)
        theta = self.random_centre(k_init)
        size = self.last_updated_size
        return MEESState(
            repertoire=rep_lib.init_repertoire(self.grid, theta),
            archive=NoveltyArchive.create(self.archive_size, self.env.descriptor_size),
            offspring=theta,
            opt_state=self.optimizer.init(theta),
            last_genotypes=jnp.zeros((size, theta.shape[0])),
            last_fitnesses=jnp.full((size,), -jnp.inf),
            last_position=jnp.zeros((), jnp.int32),
            generation=jnp.zeros((), jnp.int32),
            noise_table=self.noise_table(k_table),
            key=key,
        )

    def sample_parent(
        self, state: MEESState, key: jax.Array, explore: jax.Array
    ) -> tuple[jax.Array, jax.Array]:
        """A parent from the grid (QDax's ``_sample_explore``/``_sample_exploit``)
        and whether there was any to draw."""
        k_coin, k_grid, k_last, k_novel = jax.random.split(key, 4)
        rep = state.repertoire
        # explore: among the most novel filled cells
        novelty = jnp.where(rep.filled, state.archive.novelty(rep.descriptors, self.k), -jnp.inf)
        i_novel, found_novel = _pick_among_top(k_novel, novelty, self.explore_num_cell_sample)
        # exploit: a fair coin between the fittest cells and the fittest last offspring added
        n_fit = self.exploit_num_cell_sample
        i_grid, found_grid = _pick_among_top(k_grid, rep.fitnesses, n_fit)
        i_last, found_last = _pick_among_top(k_last, state.last_fitnesses, n_fit)
        from_last = (jax.random.uniform(k_coin) >= 0.5) & found_last
        exploit = jnp.where(from_last, state.last_genotypes[i_last], rep.genotypes[i_grid])
        parent = jnp.where(explore, rep.genotypes[i_novel], exploit)
        return parent, jnp.where(explore, found_novel, found_grid | from_last)

    def step(self, state: MEESState) -> tuple[MEESState, Evaluation]:
        key, k_parent, k_noise, k_eval = jax.random.split(state.key, 4)
        new_parent, explore = mees_schedule(
            state.generation, self.num_optimizer_steps, self.use_explore, self.use_exploit
        )
        # a new parent every num_optimizer_steps generations (a cond: the grid's
        # novelty is computed only then, unless vmapped, where a cond computes both)
        sampled, found = jax.lax.cond(
            new_parent,
            lambda: self.sample_parent(state, k_parent, explore),
            lambda: (state.offspring, jnp.asarray(False)),
        )
        parent = jnp.where(new_parent & found, sampled, state.offspring)
        opt_state = _where_tree(new_parent, self.optimizer.init(parent), state.opt_state)
        half = self.noise(k_noise, state.noise_table, parent.shape[0])
        ev = self.evaluate(state.offspring[None], parent, half, k_eval)

        # the previous offspring: into the grid, the last-updated buffer and the archive
        repertoire, inserted = rep_lib.insert(
            state.repertoire, state.offspring[None], ev.fitness[:1], ev.descriptor[:1]
        )
        slot = jnp.where(inserted[0], state.last_position, self.last_updated_size)  # else dropped
        last_genotypes = state.last_genotypes.at[slot].set(state.offspring, mode="drop")
        last_fitnesses = state.last_fitnesses.at[slot].set(ev.fitness[0], mode="drop")
        last_position = (state.last_position + inserted[0]) % self.last_updated_size
        archive = state.archive.add(ev.descriptor[:1], -jnp.inf, self.k)

        # the ES step on novelty (explore) or fitness (exploit)
        scores = jax.lax.cond(
            explore,
            lambda: archive.novelty(ev.descriptor[1:], self.k),
            lambda: ev.fitness[1:],
        )
        offspring, opt_state = self.ascend(parent, opt_state, half, centred_ranks(scores))
        new_state = state.replace(
            repertoire=repertoire,
            archive=archive,
            offspring=offspring,
            opt_state=opt_state,
            last_genotypes=last_genotypes,
            last_fitnesses=last_fitnesses,
            last_position=last_position,
            generation=state.generation + 1,
            key=key,
        )
        return new_state, ev

    def metrics(self, state: MEESState) -> dict[str, jax.Array]:
        return {
            "max_fitness": jnp.max(state.repertoire.fitnesses),
            "num_elites": jnp.sum(state.repertoire.filled),
        }
