"""Fast adaptation of a QD repertoire to a new goal (Section 3.7, Figures 3.6-3.7).

After training, QD-PG's MAP-Elites grid holds ``n`` solutions, each with a
behaviour descriptor (on Ant-Maze, the final ``(x, y)`` position).  When the goal
moves, no policy is retrained: a Bayesian optimisation (BO) searches the stored
solutions under a small budget of evaluations (20 in the thesis) and reports the
best score it observed.

The evaluation is abstracted: the caller passes ``scores``, the score of every
stored solution for the current goal (precomputed from one recorded episode per
solution, see :func:`reach_scores`).  Querying index ``i`` "evaluates" solution
``i``; BO only ever reads ``scores[i]`` for the indices it queries.

Choices made here (the thesis does not pin them down):

- **Inputs.** The GP lives on the descriptors, normalised to ``[0, 1]`` per
  dimension, by caller-given ``bounds`` (e.g. the maze's box) or otherwise by
  the min/max of the valid descriptors.
- **Gaussian process.** Squared-exponential (RBF) kernel
  ``k(x, x') = exp(-||x - x'||^2 / (2 l^2))`` with unit signal variance and
  length scale ``l = 0.2`` (a fifth of the normalised range); zero prior mean on
  *standardised* targets (the observed scores minus their mean, over their
  standard deviation), so that far from every observation the posterior returns
  to the mean and spread of what was observed; a small noise ``1e-4`` (in
  standardised units) on the diagonal, which also serves as jitter; exact
  posterior by Cholesky.  Hyper-parameters are fixed, not fitted.
- **Acquisition.** The first query is a uniformly random valid solution; each
  next one maximises the upper confidence bound ``mean + kappa * std``
  (``kappa = 2``) over the valid solutions not yet queried (ties: lowest index).
  A solution is never evaluated twice and empty cells are never queried.
- **Fixed shapes.** Training slots are a ``(budget,)`` buffer with a boolean
  mask of those observed, so the whole search is one ``lax.scan`` of ``budget``
  steps, jittable and ``vmap``-able over keys and over score vectors (goals).
  When the budget exceeds the number of valid solutions, all are evaluated (the
  result is then the exact max) and the extra steps are no-ops.
"""

from __future__ import annotations

from functools import partial
from typing import Sequence

import jax
import jax.numpy as jnp

DEFAULT_LENGTH_SCALE = 0.2


def rbf_kernel(a: jax.Array, b: jax.Array, length_scale: float) -> jax.Array:
    """Squared-exponential kernel matrix between ``a`` (p, d) and ``b`` (q, d)."""
    sq = jnp.sum((a[:, None, :] - b[None, :, :]) ** 2, axis=-1)
    return jnp.exp(-0.5 * sq / length_scale**2)


@jax.jit
def gp_posterior(
    x_train: jax.Array,
    y_train: jax.Array,
    mask: jax.Array,
    x_query: jax.Array,
    length_scale: float = DEFAULT_LENGTH_SCALE,
    noise: float = 1e-4,
) -> tuple[jax.Array, jax.Array]:
    """GP posterior mean and standard deviation at ``x_query`` (q, d), in the
    units of ``y_train`` (Section 3.7).

    ``x_train`` (m, d) and ``y_train`` (m,) are fixed-size buffers of which only
    the slots where ``mask`` (m,) is true are observations; the others (whatever
    they hold, even ``nan``) have no influence.  Targets are standardised over
    the observed slots (population standard deviation; 1 when fewer than two
    distinct values), the GP has a zero prior mean and unit prior variance in
    those units, so with no observation the posterior is the prior ``(0, 1)``
    and far from all observations it returns to (observed mean, observed std).
    """
    mask = mask.astype(bool)
    count = jnp.sum(mask)
    y = jnp.where(mask, y_train, 0.0)
    x = jnp.where(mask[:, None], x_train, 0.0)
    y_mean = jnp.sum(y) / jnp.maximum(count, 1)
    y_var = jnp.sum(jnp.where(mask, (y - y_mean) ** 2, 0.0)) / jnp.maximum(count, 1)
    y_scale = jnp.where(y_var > 1e-12, jnp.sqrt(y_var), 1.0)
    z = jnp.where(mask, (y - y_mean) / y_scale, 0.0)

    # Unobserved slots become independent unit-variance rows with target 0:
    # their weight in the solve is 0 and their cross-covariances are zeroed.
    outer = mask[:, None] & mask[None, :]
    k_train = jnp.where(outer, rbf_kernel(x, x, length_scale), 0.0)
    k_train = k_train + jnp.diag(jnp.where(mask, noise, 1.0))
    k_cross = jnp.where(mask[None, :], rbf_kernel(x_query, x, length_scale), 0.0)  # (q, m)

    chol = jnp.linalg.cholesky(k_train)
    alpha = jax.scipy.linalg.cho_solve((chol, True), z)
    v = jax.scipy.linalg.solve_triangular(chol, k_cross.T, lower=True)  # (m, q)
    mean = k_cross @ alpha
    var = jnp.clip(1.0 - jnp.sum(v**2, axis=0), 0.0, None)
    return y_mean + y_scale * mean, y_scale * jnp.sqrt(var)


def normalise(
    descriptors: jax.Array,
    valid: jax.Array,
    bounds: tuple[Sequence[float], Sequence[float]] | None = None,
) -> jax.Array:
    """Descriptors mapped to ``[0, 1]`` per dimension, by ``bounds = (low, high)``
    or, without bounds, by the min/max over the valid descriptors (a dimension
    of zero range is left unscaled)."""
    if bounds is None:
        low = jnp.min(jnp.where(valid[:, None], descriptors, jnp.inf), axis=0)
        high = jnp.max(jnp.where(valid[:, None], descriptors, -jnp.inf), axis=0)
    else:
        low, high = jnp.asarray(bounds[0], jnp.float32), jnp.asarray(bounds[1], jnp.float32)
    span = high - low
    span = jnp.where(jnp.isfinite(span) & (span > 0), span, 1.0)
    low = jnp.where(jnp.isfinite(low), low, 0.0)
    return (descriptors - low) / span


@partial(jax.jit, static_argnames="budget")
def bayes_opt(
    descriptors: jax.Array,
    valid: jax.Array,
    scores: jax.Array,
    key: jax.Array,
    budget: int = 20,
    length_scale: float = DEFAULT_LENGTH_SCALE,
    kappa: float = 2.0,
    noise: float = 1e-4,
    bounds: tuple[Sequence[float], Sequence[float]] | None = None,
) -> dict[str, jax.Array]:
    """Bayesian optimisation over the stored solutions of a repertoire (Section 3.7).

    ``descriptors`` (n, d), ``valid`` (n,) (false for empty cells), ``scores``
    (n,) the score of each solution for the goal (only queried entries are
    read).  ``length_scale`` is in normalised descriptor units (see
    :func:`normalise`; ``bounds`` as there).  Jitted, ``budget`` static (one
    compilation per budget and repertoire size).

    Returns ``best_score`` and ``best_index`` (of the best observed score),
    ``queried`` (budget,) the indices in query order, ``observed`` (budget,)
    their scores, ``best_so_far`` (budget,) the running max, and
    ``num_evaluations`` = min(budget, valid count).  Steps beyond the valid
    count are no-ops: ``queried`` is -1 and ``observed`` is ``-inf`` there.
    With no valid solution, ``best_score`` is ``-inf`` and ``best_index`` -1.
    """
    valid = valid.astype(bool)
    x = normalise(descriptors, valid, bounds)
    n, d = x.shape
    first = jax.random.categorical(key, jnp.where(valid, 0.0, -jnp.inf))

    def step(carry, t):
        queried_mask, x_train, y_train, obs_mask = carry
        available = valid & ~queried_mask
        mean, std = gp_posterior(x_train, y_train, obs_mask, x, length_scale, noise)
        ucb = jnp.where(available, mean + kappa * std, -jnp.inf)
        idx = jnp.where(t == 0, first, jnp.argmax(ucb))
        ok = jnp.any(available)
        idx = jnp.where(ok, idx, -1)
        safe = jnp.maximum(idx, 0)
        score = jnp.where(ok, scores[safe], -jnp.inf)
        carry = (
            queried_mask.at[safe].set(queried_mask[safe] | ok),
            x_train.at[t].set(x[safe]),
            y_train.at[t].set(score),
            obs_mask.at[t].set(ok),
        )
        return carry, (idx, score)

    init = (
        jnp.zeros((n,), bool),
        jnp.zeros((budget, d), x.dtype),
        jnp.zeros((budget,), jnp.result_type(scores.dtype, jnp.float32)),
        jnp.zeros((budget,), bool),
    )
    _, (queried, observed) = jax.lax.scan(step, init, jnp.arange(budget))
    return _search_result(queried, observed)


def _search_result(queried: jax.Array, observed: jax.Array) -> dict[str, jax.Array]:
    """What a search returns, from the indices it queried (-1: no query) and the
    scores it observed."""
    best = jnp.argmax(observed)
    return {
        "best_score": observed[best],
        "best_index": queried[best],
        "queried": queried,
        "observed": observed,
        "best_so_far": jax.lax.cummax(observed),
        "num_evaluations": jnp.sum(queried >= 0),
    }


@partial(jax.jit, static_argnames="budget")
def random_search(
    valid: jax.Array, scores: jax.Array, key: jax.Array, budget: int = 20
) -> dict[str, jax.Array]:
    """Baseline: ``budget`` distinct valid solutions drawn uniformly at random;
    same outputs as :func:`bayes_opt` (``best_score``, ``best_index``,
    ``queried``, ``observed``, ``best_so_far``, ``num_evaluations``)."""
    valid = valid.astype(bool)
    # A random permutation putting the valid solutions first.
    priority = jnp.where(valid, jax.random.uniform(key, valid.shape), -1.0)
    order = jnp.argsort(-priority)
    order = jnp.pad(order, (0, max(budget - valid.shape[0], 0)), constant_values=0)[:budget]
    ok = jnp.arange(budget) < jnp.sum(valid)
    queried = jnp.where(ok, order, -1)
    observed = jnp.where(ok, scores[order], -jnp.inf)
    return _search_result(queried, observed)


def reach_scores(
    positions: jax.Array, goal: jax.Array, alive: jax.Array | None = None
) -> jax.Array:
    """Ant-Maze score of each stored solution for a goal (Section 3.7): the best
    reward of its episode, ``-min_t ||goal - xy_t||``, from ``positions``
    (n, T, 2) the recorded ``(x, y)`` trajectories; ``alive`` (n, T) masks the
    steps after an episode ended (or pad a short episode by repeating its last
    position)."""
    dist = jnp.linalg.norm(positions - goal, axis=-1)
    if alive is not None:
        dist = jnp.where(alive, dist, jnp.inf)
    return -jnp.min(dist, axis=-1)


def random_goals(
    key: jax.Array, num: int, low: Sequence[float], high: Sequence[float]
) -> jax.Array:
    """``num`` goals drawn uniformly in the box ``[low, high]``, shape (num, d)."""
    low_a, high_a = jnp.asarray(low, jnp.float32), jnp.asarray(high, jnp.float32)
    return jax.random.uniform(key, (num, low_a.shape[0]), minval=low_a, maxval=high_a)
