"""Supervised training of the QDT (Algorithm 8's training loop, Section 4.5.1).

Minibatches of whole trajectories, one causal forward pass each, mean-squared
error between the predicted and the dataset's actions over every valid step of
every trajectory.  The budget is a number of gradient steps (the thesis's 100
epochs of its 300,000 trajectories in batches of 256 are 117,180 steps); every
``eval_every`` steps the QDT is played on the evaluation goals and the parameters of
the best evaluation are kept (the thesis selects each QDT "according to its best
training epoch", evaluating every 5 epochs).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np
import optax
from tqdm import tqdm

from qdnb.core import checkpoint, dryrun
from qdnb.core.sharding import shard_batch
from qdnb.models.qdt.data import Trajectories
from qdnb.models.qdt.model import QDT, init_params
from qdnb.nets.transformer import make_optimizer


def loss_fn(
    model: QDT, params: Any, batch: Trajectories, key: jax.Array | None = None
) -> jax.Array:
    """Mean over valid steps of the squared error of the predicted actions
    (averaged over action dimensions); dropout is on when a ``key`` is given."""
    rngs = None if key is None else {"dropout": key}
    pred = model.apply(
        params, batch.bd, batch.obs, batch.actions, deterministic=key is None, rngs=rngs
    )
    err = jnp.mean((pred - batch.actions) ** 2, axis=-1)
    valid = batch.valid.astype(err.dtype)
    return jnp.sum(err * valid) / jnp.maximum(jnp.sum(valid), 1.0)


def loss_and_grads(
    model: QDT, params: Any, batch: Trajectories, key: jax.Array | None = None
) -> tuple[jax.Array, Any]:
    """``loss_fn`` and its gradient, the minibatch split over every local accelerator
    (data parallel: each device takes its share of the trajectories, XLA sums the
    gradients across devices; one device computes as before).  On CPU host devices it
    stays whole on one (``shard_batch(dense=True)``): XLA spreads its matmuls over every
    core, and splitting measured slower."""
    batch = shard_batch(batch, dense=True)
    return jax.value_and_grad(lambda p: loss_fn(model, p, batch, key))(params)


def action_mse(model: QDT, params: Any, data: Trajectories, batch_size: int = 64) -> float:
    """``loss_fn`` over every valid step of ``data`` (no dropout), in minibatches of
    ``batch_size`` trajectories: the held-out error of the predicted actions.  The last
    minibatch is filled up with invalid copies, so that every dataset compiles once."""
    total = count = 0.0
    for lo in range(0, data.size, batch_size):
        rows = np.arange(lo, lo + batch_size) % data.size
        batch = jax.tree.map(lambda x: x[rows], data)
        batch = batch.replace(valid=batch.valid & (lo + np.arange(batch_size) < data.size)[:, None])
        valid = float(jnp.sum(batch.valid))
        total += float(_mse(model, params, batch)) * valid
        count += valid
    return total / max(count, 1.0)


@jax.jit(static_argnums=0)
def _mse(model: QDT, params: Any, batch: Trajectories) -> jax.Array:
    return loss_fn(model, params, batch)


def shuffled_descriptors(data: Trajectories, key: jax.Array) -> Trajectories:
    """``data`` with each trajectory's conditioning BD taken from a trajectory of
    another demonstrator (``policy``): the demonstrators are put in a random order,
    their trajectories side by side, and the BDs shifted by the largest demonstrator's
    count, so that no trajectory keeps a BD of its own demonstrator (when no
    demonstrator holds more than half of the data).  What the QDT predicts from these
    and from the true BDs differs only by the conditioning."""
    policies = np.asarray(data.policy)
    names = np.unique(policies)
    if names.size < 2:
        raise ValueError("shuffling the BDs between demonstrators needs at least two of them")
    rank = np.empty(names.size, np.int64)
    rank[np.asarray(jax.random.permutation(key, names.size))] = np.arange(names.size)
    order = np.argsort(rank[np.searchsorted(names, policies)], kind="stable")
    shift = int(np.max(np.unique(policies, return_counts=True)[1]))
    source = np.empty_like(order)
    source[order] = order[(np.arange(order.size) + shift) % order.size]
    return data.replace(bd=data.bd[source])


def conditioning_gap(
    model: QDT, params: Any, heldout: Trajectories, key: jax.Array, batch_size: int = 64
) -> dict[str, float]:
    """Held-out action error with the true BDs and with BDs shuffled between
    demonstrators (``shuffled_descriptors``): a QDT that uses its conditioning predicts
    the demonstrators' actions worse from another demonstrator's BD (``gap`` > 0); one
    that ignores it does as well either way (``gap`` = 0).  NaN with a single
    demonstrator."""
    true = action_mse(model, params, heldout, batch_size)
    if np.unique(np.asarray(heldout.policy)).size < 2:  # nothing to shuffle with
        return {"heldout_mse": true, "shuffled_mse": float("nan"), "gap": float("nan")}
    shuffled = action_mse(model, params, shuffled_descriptors(heldout, key), batch_size)
    return {"heldout_mse": true, "shuffled_mse": shuffled, "gap": shuffled - true}


def make_train_step(model: QDT, optimizer: optax.GradientTransformation):
    """One jitted gradient step on a minibatch: ``(params, opt_state, batch, key)
    -> (params, opt_state, loss)``."""

    @jax.jit
    def step(params, opt_state, batch, key):
        loss, grads = loss_and_grads(model, params, batch, key)
        updates, opt_state = optimizer.update(grads, opt_state, params)
        return optax.apply_updates(params, updates), opt_state, loss

    return step


@dataclass
class TrainResult:
    params: Any  # the parameters of the best evaluation
    best_step: int
    losses: list[float]  # mean training loss over the steps before each evaluation
    evaluations: list[dict[str, Any]] = field(default_factory=list)  # {"step", **scores}


def batch_indices(key: jax.Array, size: int, batch_size: int, first: int, count: int) -> np.ndarray:
    """The trajectories of gradient steps ``first .. first + count - 1``, ``(count,
    batch_size)``.  The dataset is read in passes, each a fresh permutation (pass ``p``
    drawn from ``fold_in(key, p)``) cut into ``size // batch_size`` minibatches, the
    last partial one dropped, as a shuffling data loader does; a dataset smaller than
    a batch fills one batch a pass by repeating its permutation.  A step's batch depends
    only on ``key`` and the step's number, so a resumed run reads the same batches."""
    per_pass = max(1, size // batch_size)
    out, current = np.empty((count, batch_size), np.int64), (-1, None)
    for row, s in enumerate(range(first, first + count)):
        p, i = divmod(s, per_pass)
        if current[0] != p:
            order = np.asarray(jax.random.permutation(jax.random.fold_in(key, p), size))
            current = (p, np.resize(order, max(size, batch_size)))
        out[row] = current[1][i * batch_size : (i + 1) * batch_size]
    return out


def fit(
    model: QDT,
    data: Trajectories,
    key: jax.Array,
    steps: int,
    batch_size: int,
    learning_rate: float,
    eval_every: int,
    evaluate: Callable[[Any, int], dict[str, Any]],
    step=None,
    progress: bool = True,
    desc: str = "QDT",
    program: str | None = None,
    evaluation_share: float = 1.0,
) -> TrainResult:
    """Train on ``data`` for ``steps`` gradient steps on minibatches of ``batch_size``
    trajectories (``batch_indices``) and call ``evaluate(params, step)`` after every
    ``eval_every`` steps; ``evaluate`` returns scores with an ``avg_distance`` (lower is
    better), and the parameters of the best evaluation are kept.  The budget is counted
    in the unit training spends, so every dataset gets the same number of updates
    whatever its size.  ``program`` names the compiled evaluation that ``evaluate``
    runs (a dry run times it once: ``qdnb.core.dryrun.timed``); ``evaluation_share`` the
    full evaluation's work over what a dry run's ``evaluate`` does (its time is counted
    that many times).  Every batch has one shape, so ``step`` (from
    ``make_train_step``) compiles once for all the datasets of an environment when it
    is shared."""
    if steps < 1 or eval_every < 1 or steps % eval_every:
        raise ValueError(
            f"steps ({steps}) must be a positive multiple of eval_every ({eval_every})"
        )
    if data.size == 0:
        raise ValueError("the dataset is empty")
    k_init, k_batches, k_drop = jax.random.split(key, 3)
    params = init_params(model, k_init, data.bd.shape[-1], data.obs.shape[-1])
    optimizer = make_optimizer(learning_rate)
    step = step or make_train_step(model, optimizer)
    opt_state = optimizer.init(params)
    result = TrainResult(params=params, best_step=0, losses=[])
    best, done = np.inf, 0
    saver = checkpoint.for_loop(
        desc,
        {
            "steps": steps,
            "batch_size": batch_size,
            "eval_every": eval_every,
            "data": checkpoint.digest(data),
            "learning_rate": learning_rate,
            "structure": checkpoint.structure((params, opt_state)),
        },
    )
    if saver is not None:  # the state after some evaluations: resume from there
        restored = saver.restore(lambda _: (params, opt_state, result.params))
        if restored is not None:
            done, (params, opt_state, result.params), extra = restored
            best, result.best_step = extra["best"], extra["best_step"]
            result.losses, result.evaluations = extra["losses"], extra["evaluations"]
            checkpoint.log(f"{saver.name!r} resumed after step {done} of {steps}")
    intervals = range(done // eval_every, steps // eval_every)
    dry = dryrun.active() is not None
    if dry:  # the first steps of one interval and one evaluation: qdnb.core.dryrun
        intervals = intervals[:1]
        first = jax.tree.map(lambda x: x[np.resize(np.arange(data.size), batch_size)], data)
        if dryrun.too_big_here(
            f"{desc} training", step, params, opt_state, first, k_drop, full_steps=steps
        ):
            scores = dryrun.timed(f"{desc} rollouts", steps // eval_every, evaluate, params, 0,
                                  same_as=program, share=evaluation_share)  # fmt: skip
            result.evaluations.append({"step": 0, **scores})
            result.losses.append(float("nan"))
            return result
    bar = tqdm(total=steps, initial=done, desc=desc, disable=not progress, leave=True)
    for n in intervals:
        first = n * eval_every
        order = batch_indices(k_batches, data.size, batch_size, first, eval_every)
        losses = []
        timed = dryrun.steps(f"{desc} training", range(eval_every), full=steps)
        for i in timed:
            batch = jax.tree.map(lambda x: x[order[i]], data)
            params, opt_state, loss = step(
                params, opt_state, batch, jax.random.fold_in(k_drop, first + i)
            )
            losses.append(loss)
            timed.step_done(loss)
            bar.update(1)
        done = first + eval_every
        result.losses.append(float(jnp.mean(jnp.stack(losses))))
        scores = dryrun.timed(
            f"{desc} rollouts", steps // eval_every, evaluate, params, done,
            same_as=program, share=evaluation_share,
        )  # fmt: skip
        result.evaluations.append({"step": done, **scores})
        if scores["avg_distance"] < best:
            best, result.best_step, result.params = scores["avg_distance"], done, params
        bar.set_postfix(loss=f"{result.losses[-1]:.4f}", dist=f"{scores['avg_distance']:.3g}")
        if saver is not None and saver.due(n + 1 - intervals.start, last=done == steps):
            extra = {
                "best": float(best),
                "best_step": result.best_step,
                "losses": result.losses,
                "evaluations": result.evaluations,
            }
            saver.save(done, (params, opt_state, result.params), extra, final=done == steps)
    bar.close()
    return result
