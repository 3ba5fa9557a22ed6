"""Supervised training of the QDT (Algorithm 8's training loop, Section 4.5.1).

Minibatches of whole trajectories, one causal forward pass each, mean-squared
error between the predicted and the dataset's actions over every valid step of
every trajectory.  Every ``eval_every`` epochs the QDT is played on the
evaluation goals; the parameters of the best evaluation are kept (the thesis
selects each QDT "according to its best training epoch").
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
    best_epoch: int
    losses: list[float]  # mean training loss of every epoch
    evaluations: list[dict[str, Any]] = field(default_factory=list)  # {"epoch", **scores}


def fit(
    model: QDT,
    data: Trajectories,
    key: jax.Array,
    epochs: int,
    batch_size: int,
    learning_rate: float,
    eval_every: int,
    evaluate: Callable[[Any, int], dict[str, Any]],
    step=None,
    progress: bool = True,
    desc: str = "QDT",
    program: str | None = None,
    full_size: int | None = None,
    evaluation_share: float = 1.0,
) -> TrainResult:
    """Train on ``data`` for ``epochs`` epochs and call ``evaluate(params, epoch)``
    after every ``eval_every`` epochs; ``evaluate`` returns scores with an
    ``avg_distance`` (lower is better).  ``program`` names the compiled evaluation
    that fits share (a dry run times it once: ``qdnb.core.dryrun.timed``); ``full_size``
    the dataset's size in the full run, where a dry run recorded fewer episodes (its
    training's length is counted at that size); ``evaluation_share`` the full
    evaluation's work over what a dry run's ``evaluate`` does (its time is counted that
    many times).

    An epoch is a pass over a fresh permutation in minibatches of ``batch_size``
    trajectories, the last partial one dropped; a dataset smaller than a batch
    fills one batch by repeating its permutation.  Every batch thus has one
    shape, and ``step`` (from ``make_train_step``) compiles once for all the
    datasets of an environment when it is shared."""
    if epochs < 1 or eval_every < 1 or epochs % eval_every:
        raise ValueError(
            f"epochs ({epochs}) must be a positive multiple of eval_every ({eval_every})"
        )
    if data.size == 0:
        raise ValueError("the dataset is empty")
    k_init, k_train = jax.random.split(key)
    params = init_params(model, k_init, data.bd.shape[-1], data.obs.shape[-1])
    optimizer = make_optimizer(learning_rate)
    step = step or make_train_step(model, optimizer)
    opt_state = optimizer.init(params)
    result = TrainResult(params=params, best_epoch=0, losses=[])
    best, start = np.inf, 0
    saver = checkpoint.for_loop(
        desc,
        {
            "epochs": epochs,
            "batch_size": batch_size,
            "eval_every": eval_every,
            "data": checkpoint.digest(data),
            "learning_rate": learning_rate,
            "structure": checkpoint.structure((params, opt_state)),
        },
    )
    if saver is not None:  # the state after some epochs: resume from there
        restored = saver.restore(lambda _: (params, opt_state, k_train, params))
        if restored is not None:
            start, (params, opt_state, k_train, result.params), extra = restored
            best, result.best_epoch = extra["best"], extra["best_epoch"]
            result.losses, result.evaluations = extra["losses"], extra["evaluations"]
            checkpoint.log(f"{saver.name!r} resumed after epoch {start} of {epochs}")
    epochs_run = range(start + 1, epochs + 1)
    dry = dryrun.active() is not None
    if dry:  # one epoch, cut to its first batches, and one evaluation: qdnb.core.dryrun
        epochs_run = epochs_run[:1]
        first = jax.tree.map(lambda x: x[np.resize(np.arange(data.size), batch_size)], data)
        steps_per_epoch = max(1, (full_size or data.size) // batch_size)
        if dryrun.too_big_here(
            f"{desc} training", step, params, opt_state, first, k_train,
            full_steps=epochs * steps_per_epoch,
        ):  # fmt: skip
            scores = dryrun.timed(f"{desc} rollouts", epochs // eval_every, evaluate, params, 0,
                                  same_as=program, share=evaluation_share)  # fmt: skip
            result.evaluations.append({"epoch": 0, **scores})
            result.losses.append(float("nan"))
            return result
    bar = tqdm(epochs_run, desc=desc, disable=not progress, leave=True, initial=start, total=epochs)
    for epoch in bar:
        k_perm, k_drop, k_train = jax.random.split(k_train, 3)
        order = np.asarray(jax.random.permutation(k_perm, data.size))
        if data.size < batch_size:  # one batch, the permutation repeated: every batch has one shape
            order = np.resize(order, batch_size)
        batches = order[: order.size // batch_size * batch_size].reshape(-1, batch_size)
        losses = []
        full = epochs * max(1, (full_size or data.size) // batch_size) if dry else None
        steps = dryrun.steps(f"{desc} training", range(len(batches)), full=full)
        for i in steps:
            batch = jax.tree.map(lambda x: x[batches[i]], data)
            params, opt_state, loss = step(params, opt_state, batch, jax.random.fold_in(k_drop, i))
            losses.append(loss)
            steps.step_done(loss)
        result.losses.append(float(jnp.mean(jnp.stack(losses))))
        if epoch % eval_every == 0 or dry:
            scores = dryrun.timed(
                f"{desc} rollouts", epochs // eval_every, evaluate, params, epoch,
                same_as=program, share=evaluation_share,
            )  # fmt: skip
            result.evaluations.append({"epoch": epoch, **scores})
            if scores["avg_distance"] < best:
                best, result.best_epoch, result.params = scores["avg_distance"], epoch, params
            bar.set_postfix(loss=f"{result.losses[-1]:.4f}", dist=f"{scores['avg_distance']:.3g}")
        if saver is not None and saver.due(epoch - start, last=epoch == epochs):
            extra = {
                "best": float(best),
                "best_epoch": result.best_epoch,
                "losses": result.losses,
                "evaluations": result.evaluations,
            }
            state = (params, opt_state, k_train, result.params)
            saver.save(epoch, state, extra, final=epoch == epochs)
    return result
