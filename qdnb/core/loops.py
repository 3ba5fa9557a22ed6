"""Long loops as jitted ``lax.scan`` chunks, with a progress bar between chunks and
checkpoints under the active ``CheckpointPolicy``; independent runs side by side in
threads."""

from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np
from tqdm import tqdm

from qdnb.core import checkpoint, dryrun


def scan_in_chunks(
    step: Callable[[Any], tuple[Any, Any]],
    carry: Any,
    num_steps: int,
    chunk_size: int,
    desc: str | None = None,
    progress: bool = True,
    chunk_seconds: list[float] | None = None,
    on_chunk: Callable[[int], None] | None = None,
    stop: Callable[[Any], bool] | None = None,
) -> tuple[Any, Any]:
    """Apply ``carry, out = step(carry)`` ``num_steps`` times, or fewer when ``stop``
    says so.

    Each chunk of ``chunk_size`` steps is one jitted ``lax.scan`` (compiled once);
    the host only wakes up between chunks to move the progress bar.  When
    ``chunk_size`` does not divide ``num_steps``, every chunk runs one program
    whose steps past ``num_steps`` are skipped (a ``lax.cond``), rather than
    compiling a second program for the shorter last chunk.  Returns the
    final carry and the per-step outputs stacked along a leading axis.  When
    ``chunk_seconds`` is a list, the wall time of each chunk (the first one
    includes compilation) is appended to it; ``on_chunk(steps_done)`` is called
    after each chunk (and its checkpoint).  ``stop(chunk_outputs)`` is called with each
    chunk's outputs (stacked as returned) in order, and a true answer ends the loop
    after that chunk: the outputs then stop there (an early stop, such as a goal
    reached; ``stop`` may keep state across calls).

    Under an active ``checkpoint.CheckpointPolicy`` a loop with a ``desc`` saves its
    carry and outputs so far (every ``every_chunks`` chunks, every
    ``every_seconds`` and at the end) and, started again, resumes from its latest
    checkpoint, its progress bar starting there; the results equal an
    uninterrupted run's bit for bit.  A loop that stopped early saves its last
    checkpoint there, and a resumed one replays its restored outputs through ``stop``.

    The loop runs under ``qdnb.core.dryrun.driver()``: as written here, or, in a dry
    run, its first steps only.
    """
    if num_steps < 1 or chunk_size < 1:
        raise ValueError(
            f"num_steps and chunk_size must be positive, got {num_steps} and {chunk_size}"
        )
    run = lambda: _run_chunks(
        step, carry, num_steps, chunk_size, desc, progress, chunk_seconds, on_chunk, stop
    )
    return dryrun.driver().loop(desc, step, carry, num_steps, run)


def _run_chunks(
    step: Callable[[Any], tuple[Any, Any]],
    carry: Any,
    num_steps: int,
    chunk_size: int,
    desc: str | None,
    progress: bool,
    chunk_seconds: list[float] | None,
    on_chunk: Callable[[int], None] | None,
    stop: Callable[[Any], bool] | None,
) -> tuple[Any, Any]:
    """``scan_in_chunks``'s loop: every chunk run, saved and reported."""
    shape: list[Any] = []  # the per-step outputs' shapes, traced once if needed

    def output_shape() -> Any:
        if not shape:
            shape.append(jax.eval_shape(lambda c: step(c)[1], carry))
        return shape[0]

    if num_steps % chunk_size == 0:

        @jax.jit
        def chunk(c):
            return jax.lax.scan(lambda c, _: step(c), c, None, length=chunk_size)

        run = lambda n, c: chunk(c)
    else:
        out_shape = output_shape()
        skip = lambda c: (c, jax.tree.map(lambda s: jnp.zeros(s.shape, s.dtype), out_shape))

        def masked(c, n):
            return jax.lax.scan(
                lambda c, i: jax.lax.cond(i < n, step, skip, c), c, jnp.arange(chunk_size)
            )

        chunk = jax.jit(masked)

        def run(n: int, c: Any):
            c, out = chunk(c, n)
            return c, jax.tree.map(lambda x: x[:n], out)

    saver = None
    if checkpoint.active() is not None and desc:
        out_shape = output_shape()
        saver = checkpoint.for_loop(
            desc,
            {
                "num_steps": num_steps,
                "chunk_size": chunk_size,
                "structure": checkpoint.structure((carry, out_shape)),
            },
        )
    outputs, done = [], 0
    if saver is not None:
        template = lambda steps: {
            "carry": carry,
            "outputs": jax.tree.map(lambda s: np.zeros((steps,) + s.shape, s.dtype), out_shape),
        }
        restored = saver.restore(template)
        if restored is not None:
            done, state, _ = restored
            carry, outputs = state["carry"], [state["outputs"]]
            checkpoint.log(f"{saver.name!r} resumed at step {done} of {num_steps}")
    stopped = bool(outputs) and stop is not None and bool(stop(outputs[0]))
    chunks = 0
    with tqdm(
        total=num_steps, initial=done, desc=desc, disable=not progress, mininterval=1.0
    ) as bar:
        while done < num_steps and not stopped:
            n = min(chunk_size, num_steps - done)
            start = time.perf_counter()
            carry, out = run(n, carry)
            jax.block_until_ready(carry)
            if chunk_seconds is not None:
                chunk_seconds.append(time.perf_counter() - start)
            outputs.append(out)
            done += n
            chunks += 1
            bar.update(n)
            stopped = stop is not None and bool(stop(out))
            if saver is not None and saver.due(chunks, last=done == num_steps or stopped):
                so_far = jax.tree.map(lambda *xs: jnp.concatenate(xs), *outputs)
                outputs = [so_far]
                saver.save(done, {"carry": carry, "outputs": so_far}, final=done == num_steps)
            if on_chunk is not None:
                on_chunk(done)
    return carry, jax.tree.map(lambda *xs: jnp.concatenate(xs), *outputs)


def map_concurrently(
    fn: Callable[[str], Any], names: tuple[str, ...] | list[str], concurrent: bool = True
) -> dict[str, Any]:
    """``{name: fn(name)}``, the calls in one thread each unless ``concurrent`` is
    false.  For runs that share nothing (one per environment): XLA compiles and
    runs small programs on about one core each, so two such runs on two cores take
    little longer than one.  Each run's numbers do not depend on the threads."""
    if not concurrent or not dryrun.driver().concurrent:  # a dry run times each loop alone
        return {name: fn(name) for name in names}
    with ThreadPoolExecutor(max_workers=max(1, len(names))) as pool:
        futures = {name: pool.submit(fn, name) for name in names}
        return {name: f.result() for name, f in futures.items()}
