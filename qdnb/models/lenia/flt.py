"""The Flow Lenia Transformer (FLT, Section 5.3.1): a causal GPT over the frames of
a Flow Lenia episode, with CNN embeddings in and out.

An episode is the sequence of frames ``x_t = (A^t, P^t)`` stacked along channels
(``(H, W, 1 + |K|)``, ``flow_lenia.frames``).  Each frame is encoded by a CNN into
one token; the learned embedding of timestep ``t`` is added and a causal
transformer (the QDT's pre-norm GPT-2 blocks, ``qdnb.nets.transformer.Block``) runs over
the tokens; a CNN decoder turns the hidden state at token ``t`` into the
prediction of frame ``t + 1``: ``A`` through a softplus (matter is non-negative and
may exceed 1) and ``P`` through a sigmoid (kernel weights live in ``[0, 1]``).

Training is teacher-forced over whole episodes (``loss_fn``, Eq. 5.3).

**Beyond the thesis** (ours, off by default; ``FLTConfig``'s ``head``, ``noise`` and
``pushforward``), from learned simulators of physical fields: a ``"residual"`` head
predicts the change of the input frame (``A`` kept non-negative, ``P`` in ``[0, 1]``;
a zero change returns the input exactly, and the last layer starts at zero, so an
untrained model is persistence); a ``"mass"`` head also rescales ``A`` to the input
frame's total matter, which Flow Lenia conserves; ``noise`` perturbs the
teacher-forced inputs during training (Sanchez-Gonzalez et al. 2020) and
``pushforward`` adds the loss of a second pass fed the model's own one-step
predictions, gradients stopped through them (Brandstetter et al. 2022): both train on
inputs like the ones an unrolled model feeds itself.
Evaluation (``unroll``) starts from ``x_0`` only and feeds every prediction back
as the next input, keeping the keys and values of the earlier tokens (a cache),
so each step costs one token; ``unroll(..., cached=False)`` recomputes the
whole prefix every step and is the reference the cache is tested against.

The encoder has ``len(features)`` stride-2 convolutions (zero padding at walls,
circular on a torus), so ``H`` and ``W`` must be multiples of ``2**len(features)``.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass
from functools import partial
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import linen as nn
from tqdm import tqdm

from qdnb.core import checkpoint, dryrun
from qdnb.core.sharding import put_replicated, shard_batch
from qdnb.models.lenia import flow_lenia as fl
from qdnb.nets.transformer import Block, Cache, make_optimizer, run_blocks


class FrameEncoder(nn.Module):
    """``(N, H, W, C)`` frames to ``(N, D)`` tokens: stride-2 convolutions (``padding``
    ``"CIRCULAR"`` on a torus, zeros ``"SAME"`` at walls), then a dense layer on the
    flattened feature map."""

    features: tuple[int, ...]
    embed_dim: int
    padding: str = "SAME"

    @nn.compact
    def __call__(self, x: jax.Array) -> tuple[jax.Array, list[jax.Array]]:
        """The tokens and the feature map of every resolution (finest first)."""
        maps = []
        for f in self.features:
            x = nn.relu(nn.Conv(f, (3, 3), strides=(2, 2), padding=self.padding)(x))
            maps.append(x)
        return nn.Dense(self.embed_dim)(x.reshape(x.shape[0], -1)), maps


class FrameDecoder(nn.Module):
    """``(N, D)`` hidden states to ``(N, H, W, C)`` frames: a dense layer to the
    coarsest feature map, then stride-2 transposed convolutions back to ``H x W``,
    the last one straight to the frame's channels; softplus on ``A``, sigmoid on
    ``P``.  (A further full-resolution convolution made training 2.5x slower on
    CPU.)"""

    features: tuple[int, ...]
    height: int
    width: int
    channels: int
    head: str = "direct"  # another head: the last layer's raw output, which starts at zero

    @nn.compact
    def __call__(self, h: jax.Array, skips: list[jax.Array] | None = None) -> jax.Array:
        scale = 2 ** len(self.features)
        x = nn.Dense((self.height // scale) * (self.width // scale) * self.features[-1])(h)
        x = nn.relu(x).reshape(-1, self.height // scale, self.width // scale, self.features[-1])
        widths = list(reversed(self.features[:-1])) + [self.channels]
        for level, f in zip(reversed(range(len(self.features))), widths):
            if skips is not None:  # U-Net: the input frame's features at this resolution
                x = jnp.concatenate([x, skips[level]], axis=-1)
            last = level == 0 and self.head != "direct"
            zero = {"kernel_init": nn.initializers.zeros} if last else {}
            x = nn.ConvTranspose(f, (3, 3), strides=(2, 2), padding="SAME", **zero)(x)
            x = nn.relu(x) if level else x
        if self.head != "direct":
            return x
        return jnp.concatenate([nn.softplus(x[..., :1]), nn.sigmoid(x[..., 1:])], axis=-1)


HEADS = ("direct", "residual", "mass")


def next_frame(head: str, change: jax.Array, frame: jax.Array) -> jax.Array:
    """A residual head's prediction from the ``change`` it output and the input
    ``frame`` (``(..., H, W, C)``): ``A + dA`` kept non-negative and ``P + dP`` clipped
    to ``[0, 1]``; with ``"mass"``, ``A`` then rescaled so that its total over the grid
    is the input's (matter conserved exactly).  A zero change returns ``frame``."""
    a = jnp.maximum(frame[..., :1] + change[..., :1], 0.0)
    p = jnp.clip(frame[..., 1:] + change[..., 1:], 0.0, 1.0)
    if head == "mass":
        before = jnp.sum(frame[..., :1], axis=(-3, -2), keepdims=True)
        after = jnp.sum(a, axis=(-3, -2), keepdims=True)
        a = jnp.where(after > 0, a * (before / jnp.where(after > 0, after, 1.0)), a)
    return jnp.concatenate([a, p], axis=-1)


class FLT(nn.Module):
    """``__call__(inputs)`` with ``inputs (B, T, H, W, C)`` (frames ``x_0 .. x_{T-1}``)
    returns the predictions of ``x_1 .. x_T``, ``(B, T, H, W, C)``, in one causal pass."""

    height: int
    width: int
    channels: int
    max_steps: int  # the number of predicted frames of an episode (T)
    embed_dim: int = 128
    num_layers: int = 2
    num_heads: int = 4
    features: tuple[int, ...] = (16, 32, 64)
    dropout: float = 0.0
    skip: bool = False  # the decoder also sees the input frame's CNN features (U-Net skips)
    padding: str = "SAME"  # the encoder's: "CIRCULAR" for a torus, "SAME" (zeros) for walls
    head: str = "direct"  # the thesis's; "residual" or "mass": ours (``next_frame``)

    def setup(self):
        scale = 2 ** len(self.features)
        if self.height % scale or self.width % scale:
            raise ValueError(
                f"the {self.height}x{self.width} grid is not a multiple of 2**len(features) = "
                f"{scale}"
            )
        if self.embed_dim % self.num_heads:
            raise ValueError(
                f"embed_dim {self.embed_dim} is not a multiple of num_heads {self.num_heads}"
            )
        self.encoder = FrameEncoder(self.features, self.embed_dim, self.padding)
        if self.head not in HEADS:
            raise ValueError(f"head must be one of {', '.join(HEADS)}, got {self.head!r}")
        self.decoder = FrameDecoder(
            self.features, self.height, self.width, self.channels, self.head
        )
        self.embed_timestep = nn.Embed(self.max_steps, self.embed_dim)
        self.embed_ln = nn.LayerNorm()
        self.drop = nn.Dropout(self.dropout)
        self.blocks = [Block(self.num_heads, self.dropout) for _ in range(self.num_layers)]
        self.ln_final = nn.LayerNorm()

    def tokens(
        self, inputs: jax.Array, timesteps: jax.Array
    ) -> tuple[jax.Array, list[jax.Array] | None]:
        """Tokens ``(B, T, D)`` of the frames ``(B, T, H, W, C)``, and their feature maps
        (flattened to ``B T``) when the decoder uses skips."""
        b, t = inputs.shape[:2]
        encoded, maps = self.encoder(inputs.reshape((b * t,) + inputs.shape[2:]))
        tokens = self.embed_ln(encoded.reshape(b, t, -1) + self.embed_timestep(timesteps))
        return tokens, (maps if self.skip else None)

    def transformer(self, x, caches, start, deterministic):
        x, caches = run_blocks(
            self.blocks, self.drop(x, deterministic=deterministic), caches, start, deterministic
        )
        return self.ln_final(x), caches

    def decode(
        self, hidden: jax.Array, maps: list[jax.Array] | None, inputs: jax.Array
    ) -> jax.Array:
        """The frames that follow ``inputs`` ``(B, T, H, W, C)``, from their hidden states."""
        b, t = hidden.shape[:2]
        frames = self.decoder(hidden.reshape(b * t, -1), maps)
        frames = frames.reshape(b, t, self.height, self.width, self.channels)
        return frames if self.head == "direct" else next_frame(self.head, frames, inputs)

    def __call__(self, inputs: jax.Array, deterministic: bool = True) -> jax.Array:
        tokens, maps = self.tokens(inputs, jnp.arange(inputs.shape[1]))
        hidden, _ = self.transformer(tokens, (None,) * self.num_layers, 0, deterministic)
        return self.decode(hidden, maps, inputs)

    def init_cache(self, batch: int, dtype=jnp.float32) -> Cache:
        shape = (batch, self.max_steps, self.num_heads, self.embed_dim // self.num_heads)
        return tuple(
            (jnp.zeros(shape, dtype), jnp.zeros(shape, dtype)) for _ in range(self.num_layers)
        )

    def decode_step(self, frame: jax.Array, t: jax.Array, cache: Cache) -> tuple[jax.Array, Cache]:
        """Feed frame ``x_t`` ``(B, H, W, C)`` (token ``t``) and predict ``x_{t+1}``."""
        tokens, maps = self.tokens(frame[:, None], t[None])
        hidden, cache = self.transformer(tokens, cache, t, True)
        return self.decode(hidden, maps, frame[:, None])[:, 0], cache


@dataclass(frozen=True)
class FLTConfig:
    """The model and its training: ``train_steps`` gradient steps, each on a batch
    of ``batch_size`` episodes simulated on the fly (never the same twice).
    ``per_modality``: an ablation of the loss, ``MSE(A) + MSE(P)`` (each modality
    averaged over its own channels) instead of Eq. 5.3, where ``P``'s ``|K|``
    channels weigh ``|K|`` times ``A``'s one (``loss_fn``)."""

    embed_dim: int = 128
    num_layers: int = 2
    num_heads: int = 4
    features: tuple[int, ...] = (16, 32, 64)
    dropout: float = 0.0
    skip: bool = False
    batch_size: int = 8
    learning_rate: float = 1e-3
    train_steps: int = 1000
    per_modality: bool = False
    # beyond the thesis (ours): the output head, input noise and the pushforward pass
    head: str = "direct"
    noise: float = 0.0
    pushforward: bool = False

    def __post_init__(self):
        for name in ("embed_dim", "num_layers", "num_heads", "batch_size", "train_steps"):
            value = getattr(self, name)
            if not isinstance(value, (int, np.integer)) or value < 1:
                raise ValueError(f"{name} must be a positive integer, got {value!r}")
        if self.embed_dim % self.num_heads:
            raise ValueError(
                f"embed_dim {self.embed_dim} is not a multiple of num_heads {self.num_heads}"
            )
        if not self.features or min(self.features) < 1:
            raise ValueError(
                f"features must be a non-empty tuple of positive widths, got {self.features}"
            )
        if self.head not in HEADS:
            raise ValueError(f"head must be one of {', '.join(HEADS)}, got {self.head!r}")
        if not self.noise >= 0:
            raise ValueError(f"noise must be a non-negative standard deviation, got {self.noise}")
        if not 0.0 <= self.dropout < 1.0 or not self.learning_rate > 0:
            raise ValueError(
                f"dropout must be in [0, 1) and learning_rate positive, got "
                f"{self.dropout} and {self.learning_rate}"
            )


def make_model(world: fl.FlowLeniaConfig, cfg: FLTConfig) -> FLT:
    return FLT(
        world.height,
        world.width,
        world.channels + world.kernels,
        world.steps,
        cfg.embed_dim,
        cfg.num_layers,
        cfg.num_heads,
        cfg.features,
        cfg.dropout,
        cfg.skip,
        "CIRCULAR" if world.border == "torus" else "SAME",
        cfg.head,
    )


def init_params(model: FLT, key: jax.Array) -> Any:
    return model.init(key, jnp.zeros((1, 2, model.height, model.width, model.channels)))


def perturbed(frames: jax.Array, key: jax.Array, noise: float) -> jax.Array:
    """``frames`` plus Gaussian noise of standard deviation ``noise`` on every channel,
    ``A`` kept non-negative and ``P`` in ``[0, 1]``."""
    noisy = frames + noise * jax.random.normal(key, frames.shape, frames.dtype)
    return jnp.concatenate(
        [jnp.maximum(noisy[..., :1], 0.0), jnp.clip(noisy[..., 1:], 0.0, 1.0)], axis=-1
    )


def loss_fn(
    model: FLT,
    params: Any,
    episodes: jax.Array,
    key: jax.Array | None = None,
    per_modality: bool = False,
    noise: float = 0.0,
    pushforward: bool = False,
) -> jax.Array:
    """Eq. 5.3 with teacher forcing: frames ``x_0 .. x_{T-1}`` in, ``x_1 .. x_T``
    predicted, the squared error averaged over episodes, timesteps, cells and
    channels.  Eq. 5.3 sums ``||A_t - Â_t||^2 + ||P_t - P̂_t||^2`` over cells and
    averages over t: this is the same up to the constant factor
    ``1 / (H W (1 + |K|))``, with the same relative weight of ``A`` and ``P``.
    ``per_modality`` (an ablation): ``MSE(A) + MSE(P)`` instead, each averaged
    over its own channels, so that ``A`` weighs as much as all of ``P``.

    Ours, beyond the thesis: ``noise`` (needs ``key``) perturbs the input frames
    ``x_0 .. x_{T-1}`` (``perturbed``), the targets staying the true frames;
    ``pushforward`` adds the same loss for a second pass whose inputs are ``x_0`` and
    the first pass's predictions of ``x_1 .. x_{T-1}``, with their gradients stopped."""
    rngs = None if key is None else {"dropout": key}
    inputs, targets = episodes[:, :-1], episodes[:, 1:]
    if noise > 0:
        if key is None:
            raise ValueError("noise needs a key")
        inputs = perturbed(inputs, jax.random.fold_in(key, 1), noise)

    def loss(pred):
        err = (pred - targets) ** 2
        if per_modality:
            return jnp.mean(err[..., :1]) + jnp.mean(err[..., 1:])
        return jnp.mean(err)

    pred = model.apply(params, inputs, deterministic=key is None, rngs=rngs)
    total = loss(pred)
    if pushforward:  # the model's own predictions in, as an unrolled model sees them
        own = jnp.concatenate([episodes[:, :1], jax.lax.stop_gradient(pred[:, :-1])], axis=1)
        rngs2 = None if key is None else {"dropout": jax.random.fold_in(key, 2)}
        total = total + loss(model.apply(params, own, deterministic=key is None, rngs=rngs2))
    return total


def make_train_step(
    model: FLT,
    optimizer: optax.GradientTransformation,
    per_modality: bool = False,
    noise: float = 0.0,
    pushforward: bool = False,
):
    """``(params, opt_state, episodes, key) -> (params, opt_state, loss)``, not jitted
    (it is called inside ``train``'s jitted loop and jitted by the tests)."""

    def step(params, opt_state, episodes, key):
        loss, grads = jax.value_and_grad(
            lambda p: loss_fn(model, p, episodes, key, per_modality, noise, pushforward)
        )(params)
        updates, opt_state = optimizer.update(grads, opt_state, params)
        return optax.apply_updates(params, updates), opt_state, loss

    return step


@partial(jax.jit, static_argnames=("model", "cached"))
def unroll(model: FLT, params: Any, frame0: jax.Array, cached: bool = True) -> jax.Array:
    """From ``x_0`` ``(B, H, W, C)`` alone, predict ``x_1 .. x_T`` autoregressively,
    each prediction fed back as the next input: ``(B, T, H, W, C)``."""
    steps = model.max_steps
    if cached:

        def body(carry, t):
            frame, cache = carry
            nxt, cache = model.apply(params, frame, t, cache, method=FLT.decode_step)
            return (nxt, cache), nxt

        cache = model.apply(params, frame0.shape[0], method=FLT.init_cache)
        _, preds = jax.lax.scan(body, (frame0, cache), jnp.arange(steps))
    else:
        # the whole prefix every step; the not yet predicted frames are zeros, hidden by causality

        def body(inputs, t):
            nxt = model.apply(params, inputs)[:, t]
            # write x_{t+1} at input position t + 1 (the last prediction has no position: the write
            # is dropped)
            inputs = inputs.at[:, t + 1].set(nxt, mode="drop")
            return inputs, nxt

        inputs = jnp.zeros((frame0.shape[0], steps) + frame0.shape[1:]).at[:, 0].set(frame0)
        _, preds = jax.lax.scan(body, inputs, jnp.arange(steps))
    return preds.swapaxes(0, 1)


def frame_errors(pred: jax.Array, truth: jax.Array) -> dict[str, jax.Array]:
    """Per episode and timestep: the mean squared error on activations ``A``
    (``"A"``, the quantity shown in Figures 5.3 to 5.5) and on the whole frame
    (``"frame"``: ``A`` and ``P``, the loss of Eq. 5.3)."""
    return {
        "A": jnp.mean((pred[..., :1] - truth[..., :1]) ** 2, axis=(-3, -2, -1)),
        "frame": jnp.mean((pred - truth) ** 2, axis=(-3, -2, -1)),
    }


# A paper step of the FLT (32 episodes of 128x128, 64 frames) takes minutes on two CPU
# cores (358 s on an Intel Xeon, 157 s with compilation on an AMD EPYC; ours about twice
# that, its pushforward's second pass): a batch's episodes are independent copies side by
# side, so a dry run on a CPU runs this many of them and counts each step
# ``batch / DRY_RUN_EPISODES`` times, as the ES's perturbations are
# (``qdnb.chapters.ch3_evolution``).  A GPU runs the whole batch.  A step's time grows a
# little faster than its batch (bench/results/flt_dryrun_cut.json, the Xeon: 32.5, 75 and
# 358 s for 4, 8 and 32 episodes): 8 episodes project a full step 16 % short (4: 27 %).
DRY_RUN_EPISODES = 8


def dry_run_batch(what: str, full: int) -> dryrun.BatchCut:
    """A batch of ``full`` episodes as a dry run on a CPU cuts it: ``DRY_RUN_EPISODES``
    (``qdnb.core.dryrun.cut_batch``, the cut recorded as ``what``)."""
    return dryrun.cut_batch(what, full, DRY_RUN_EPISODES)


@dataclass(frozen=True)
class TrainResult:
    params: Any
    losses: np.ndarray  # (train_steps,) teacher-forced loss of every batch
    mean_frames: np.ndarray  # (T + 1, H, W, C) mean frame per timestep over all training episodes
    episodes_seen: int
    max_drift: float  # largest relative change of total mass over all training episodes
    seconds: float = 0.0  # wall time of the training, compilation included

    @property
    def final_loss(self) -> float:
        """The mean training loss over the last twentieth of the steps."""
        return float(np.mean(self.losses[-max(1, len(self.losses) // 20) :]))


def train(
    model: FLT,
    cfg: FLTConfig,
    world: fl.FlowLeniaConfig,
    system: fl.System,
    key: jax.Array,
    progress: bool = True,
    desc: str = "FLT",
    max_seconds: float | None = None,
    step_seconds: list[float] | None = None,
) -> TrainResult:
    """Train the FLT on episodes of ``system``, each batch simulated on the fly from
    fresh random initial states (simulation and gradient step in one jitted call, both
    split over every local device).  Also accumulates the mean frame per timestep of the training
    episodes (the mean-frame baseline).  With ``max_seconds``, training stops
    after the first step that ends past that many seconds (compilation included),
    or after ``cfg.train_steps``, whichever comes first (``bench/flt_sweep.py``
    compares settings at an equal wall-clock budget).  When ``step_seconds`` is a list,
    each step's wall time is appended to it (the first includes compilation).

    The steps run in a Python loop, not a ``lax.scan``: XLA on CPU runs the
    convolutions' gradients about 10x slower inside a loop than as a top-level
    computation, and a step (about half a second) dwarfs the host round-trip."""

    began = time.perf_counter()
    k_init, k_train = jax.random.split(key)
    params = init_params(model, k_init)
    optimizer = make_optimizer(cfg.learning_rate)
    opt_state = optimizer.init(params)
    step = make_train_step(model, optimizer, cfg.per_modality, cfg.noise, cfg.pushforward)
    cut = dry_run_batch(f"{desc}'s episodes per batch (side by side)", cfg.batch_size)
    batch = cut.kept  # the whole batch but in a dry run on a CPU
    keyed = cfg.dropout > 0 or cfg.noise > 0  # a key for the step's randomness

    @jax.jit
    def one(params, opt_state, frame_sum, key):
        k_sim, k_drop = jax.random.split(key)
        # data-parallel over every local device, on CPU host devices too: the convolutions'
        # gradients gain from it (bench/scale_out.py), unlike the QDT's matmuls
        episodes = fl.simulate_system(system, k_sim, world, batch, split=True)
        episodes = shard_batch(fl.frames(episodes))
        params, opt_state, loss = step(params, opt_state, episodes, k_drop if keyed else None)
        drift = jnp.max(fl.mass_drift(episodes[..., :1]))
        return params, opt_state, frame_sum + jnp.sum(episodes, axis=0), loss, drift

    frame_sum = jnp.zeros((world.steps + 1, world.height, world.width, model.channels))
    losses, drifts, start_step = [], [], 0
    saver = checkpoint.for_loop(
        desc if max_seconds is None else None,  # a wall-clock budget is not resumable
        {
            "config": dataclasses.asdict(cfg),
            "world": repr(world),
            "system": checkpoint.digest(system),
            "structure": checkpoint.structure((params, opt_state)),
        },
    )
    if saver is not None:
        restored = saver.restore(
            lambda done: (params, opt_state, frame_sum, *[np.zeros(done, np.float32)] * 2)
        )
        if restored is not None:
            start_step, (params, opt_state, frame_sum, done_losses, done_drifts), _ = restored
            losses, drifts = list(jnp.asarray(done_losses)), list(jnp.asarray(done_drifts))
            checkpoint.log(f"{saver.name!r} resumed after step {start_step} of {cfg.train_steps}")
    # placed as the step hands them back (whole on every device): the step compiles once
    params, opt_state, frame_sum = put_replicated((params, opt_state, frame_sum))
    start = time.perf_counter()
    bar = tqdm(
        range(start_step, cfg.train_steps),
        desc=desc,
        disable=not progress,
        mininterval=1.0,
        initial=start_step,
        total=cfg.train_steps,
    )
    steps = dryrun.steps(desc, bar, full=cfg.train_steps)  # a dry run: the first steps
    with cut.counted():  # a dry run on a CPU steps a cut batch: each step counts as a whole one
        for i in steps:
            began_step = time.perf_counter()
            params, opt_state, frame_sum, loss, drift = one(
                params, opt_state, frame_sum, jax.random.fold_in(k_train, i)
            )
            steps.step_done(loss)
            if step_seconds is not None:
                jax.block_until_ready(params)
                step_seconds.append(time.perf_counter() - began_step)
            losses.append(loss)
            drifts.append(drift)
            if i % 50 == 49 or i == cfg.train_steps - 1:
                bar.set_postfix(loss=f"{float(jnp.mean(jnp.stack(losses[-50:]))):.4g}")
            if (
                max_seconds is not None
                and float(loss) >= 0
                and time.perf_counter() - start > max_seconds
            ):
                break  # float(loss) waits for the step, so the clock counts finished steps
            if saver is not None and saver.due(i + 1 - start_step, last=i + 1 == cfg.train_steps):
                state = (params, opt_state, frame_sum, jnp.stack(losses), jnp.stack(drifts))
                saver.save(i + 1, state, final=i + 1 == cfg.train_steps)
    bar.close()
    seen = len(losses) * batch
    return TrainResult(
        params,
        np.asarray(jnp.stack(losses)),
        np.asarray(frame_sum / seen),
        seen,
        float(jnp.max(jnp.stack(drifts))),
        time.perf_counter() - began,
    )
