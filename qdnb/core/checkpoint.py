"""Checkpoints of long loops, so that a crashed or pre-empted run resumes where it stopped.

A run activates a ``CheckpointPolicy`` (``activate``; the book's ``Run`` does it for
every notebook): from then on every loop of ``scan_in_chunks`` saves its whole state
(the carry: algorithm state, optimiser states, PRNG keys, buffers, archives,
counters; and the outputs so far) every ``every_chunks`` chunks, every
``every_seconds`` seconds and at its end, with ``orbax-checkpoint``, keeping the last
``keep``; a loop that has run less than ``min_seconds`` is not saved (recomputing it
is cheaper).  A loop started again with the same policy restores the latest
checkpoint and runs only what is left: its results equal an uninterrupted run's bit
for bit, since the same compiled chunks run on the same state.

Checkpoints live under ``<run dir>/checkpoints/<loop>-<config hash>-seed<seed>/``.
A checkpoint is loaded only when its loop, config hash, seed, code version, step
count and state structure all match; anything else is left alone and the reason
is logged.  A checkpoint that cannot be read (truncated mid-write) is skipped for
the one before it.
"""

from __future__ import annotations

import hashlib
import json
import re
import shutil
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np


@dataclass(frozen=True)
class CheckpointPolicy:
    """Where and how often loops save.  ``version`` names the code and its
    dependencies (a checkpoint of another version is never loaded); ``resume``
    false starts every loop afresh, removing this run's own checkpoints of it."""

    directory: Path
    config_hash: str
    seed: int
    version: str
    every_chunks: int = 50
    every_seconds: float = 600.0
    keep: int = 2
    resume: bool = True
    min_seconds: float = 20.0  # loops shorter than this are not checkpointed

    def __post_init__(self):
        if self.every_chunks < 1 or self.every_seconds <= 0 or self.keep < 1:
            raise ValueError(
                "every_chunks and keep must be positive integers and every_seconds positive, "
                f"got {self.every_chunks}, {self.keep} and {self.every_seconds}"
            )


_lock = threading.Lock()
_active: CheckpointPolicy | None = None
_seen: dict[str, int] = {}  # loop name -> how many loops of that name started
_resumed: list[dict[str, Any]] = []  # the loops of this run restored from a checkpoint
_cost = {"saves": 0, "seconds": 0.0}  # what saving has cost this run


def activate(policy: CheckpointPolicy | None) -> None:
    """Make ``policy`` the one every loop uses from now on (``None``: no checkpoints).
    A process-wide setting, as a notebook's cells share no context otherwise."""
    global _active
    with _lock:
        _active = policy
        _seen.clear()
        _resumed.clear()
        _cost.update(saves=0, seconds=0.0)
    if policy is not None and not policy.resume:
        clear_run(policy)


def clear_run(policy: CheckpointPolicy) -> None:
    """Remove every checkpoint of ``policy``'s config hash and seed, at the start of a
    fresh run: a fresh run killed part-way must not leave older checkpoints of the
    loops it had not reached, for a later resumed run to pick up."""
    parent = Path(policy.directory)
    pattern = f"*-{policy.config_hash[:12]}-seed{policy.seed}"
    removed = [d for d in sorted(parent.glob(pattern)) if d.is_dir()] if parent.exists() else []
    for directory in removed:
        shutil.rmtree(directory)
    if removed:
        log(f"starting afresh: {len(removed)} earlier checkpoint directories of this run removed")


def active() -> CheckpointPolicy | None:
    return _active


def cost() -> dict[str, float]:
    """How many checkpoints this run saved and the seconds it spent saving them."""
    with _lock:
        return {"saves": _cost["saves"], "seconds": round(_cost["seconds"], 2)}


def resumed() -> list[dict[str, Any]]:
    """The loops of the active run that resumed from a checkpoint: name and step."""
    with _lock:
        return [dict(r) for r in _resumed]


def log(message: str) -> None:
    print(f"checkpoints: {message}", file=sys.stderr, flush=True)


def slug(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", name).strip("_") or "loop"


def structure(tree: Any) -> str:
    """A short digest of a pytree's structure, shapes and dtypes."""
    import jax

    leaves, treedef = jax.tree.flatten(tree)
    dtype = lambda x: x.dtype if hasattr(x, "dtype") else np.asarray(x).dtype
    spec = [str(treedef)] + [f"{np.shape(x)}:{dtype(x)}" for x in leaves]
    return hashlib.sha256("|".join(spec).encode()).hexdigest()[:16]


def digest(tree: Any) -> str:
    """A short digest of a pytree's values (and structure): two inputs of a loop that
    differ anywhere get different digests."""
    import jax

    h = hashlib.sha256(structure(tree).encode())
    for leaf in jax.tree.leaves(tree):
        h.update(np.ascontiguousarray(np.asarray(leaf)).tobytes())
    return h.hexdigest()[:16]


class LoopCheckpoints:
    """The checkpoints of one loop of the active run, named ``name`` (the n-th loop of
    that name in the run gets ``#n``, so a name reused in order stays distinct)."""

    def __init__(self, policy: CheckpointPolicy, name: str, identity: dict[str, Any]):
        import orbax.checkpoint as ocp

        self._ocp = ocp
        with _lock:
            count = _seen.get(name, 0)
            _seen[name] = count + 1
        self.name = name if count == 0 else f"{name}#{count}"
        self.policy = policy
        # as JSON gives it back (tuples become lists), to compare with what was saved
        self.meta = json.loads(
            json.dumps(
                {
                    "loop": self.name,
                    "config_hash": policy.config_hash,
                    "seed": policy.seed,
                    "version": policy.version,
                    **identity,
                }
            )
        )
        stem = slug(self.name)
        self.directory = (
            Path(policy.directory) / f"{stem}-{policy.config_hash[:12]}-seed{policy.seed}"
        )
        if not policy.resume and self.directory.exists():
            shutil.rmtree(self.directory)
            log(f"{self.name!r}: starting afresh, its earlier checkpoints removed")
        self._mention_foreign(stem)
        self.manager = ocp.CheckpointManager(
            self.directory,
            options=ocp.CheckpointManagerOptions(
                max_to_keep=policy.keep, enable_async_checkpointing=False, create=True
            ),
        )
        self.started = self.last_save = time.monotonic()

    def _mention_foreign(self, stem: str) -> None:
        parent = Path(self.policy.directory)
        if not parent.exists():
            return
        for other in sorted(parent.glob(f"{stem}-*-seed*")):
            if other != self.directory and re.fullmatch(
                rf"{re.escape(stem)}-[0-9a-f]+-seed-?\d+", other.name
            ):
                log(
                    f"{self.name!r}: {other.name} belongs to another config or seed "
                    f"(this run: config {self.policy.config_hash[:12]}, seed {self.policy.seed}); "
                    "not loaded"
                )

    def restore(self, template: Callable[[int], Any]) -> tuple[int, Any, Any] | None:
        """The latest readable checkpoint of this loop whose identity matches, as
        ``(step, state, extra)`` with ``state`` shaped like ``template(step)`` and
        ``extra`` what ``save`` was given (``None`` if nothing); ``None`` if there is
        none (each checkpoint passed over is logged with the reason and removed)."""
        ocp = self._ocp
        for step in sorted(self.manager.all_steps(), reverse=True):
            why = None
            try:
                meta = self.manager.restore(
                    step, args=ocp.args.Composite(meta=ocp.args.JsonRestore())
                )["meta"]
                mismatch = [k for k, v in self.meta.items() if meta.get(k) != v]
                if mismatch:
                    why = "written by another " + ", ".join(
                        f"{k} {meta.get(k)!r} (this run: {self.meta[k]!r})" for k in mismatch
                    )
                else:
                    state = self.manager.restore(
                        step,
                        args=ocp.args.Composite(state=ocp.args.StandardRestore(template(step))),
                    )["state"]
                    # on the host: the loop's jitted code places it where it runs (over
                    # every device, say), which arrays committed to one device would refuse
                    import jax

                    state = jax.device_get(state)
                    with _lock:
                        _resumed.append({"loop": self.name, "step": step})
                    return step, state, from_json(meta.get("extra"))
            except Exception as err:  # noqa: BLE001 - any unreadable checkpoint is skipped
                why = f"unreadable ({type(err).__name__})"
            # a later save would need its step number: the stale one goes
            self.manager.delete(step)
            log(f"{self.name!r}: step {step} {why}; not loaded, removed")
        return None

    def due(self, chunks_done: int, last: bool = False) -> bool:
        """Whether a save is due after ``chunks_done`` chunks of this run of the loop
        (``last``: the loop's end).  A loop that has run less than ``min_seconds``
        is not saved at all: recomputing it costs less than saving it."""
        if time.monotonic() - self.started < self.policy.min_seconds:
            return False
        return (
            last
            or chunks_done % self.policy.every_chunks == 0
            or time.monotonic() - self.last_save >= self.policy.every_seconds
        )

    def save(self, step: int, state: Any, extra: Any = None, final: bool = False) -> None:
        """Save ``state`` (a pytree of arrays) after ``step`` steps, with ``extra``
        (Python values and numpy arrays: records kept on the host) beside it.  A
        ``final`` save (the loop's end) keeps only itself: a finished loop needs no
        step to fall back on, and at paper Chapter 4's checkpoints would otherwise take
        52 of the GPU machine's 64 GiB of disk (``bench/results/paper_dryrun.json``)."""
        ocp = self._ocp
        start = time.perf_counter()
        meta = {**self.meta, "step": step, "extra": to_json(extra)}
        self.manager.save(
            step,
            args=ocp.args.Composite(
                state=ocp.args.StandardSave(state), meta=ocp.args.JsonSave(meta)
            ),
            force=True,
        )
        self.manager.wait_until_finished()
        if final:
            for earlier in self.manager.all_steps():
                if earlier != step:
                    self.manager.delete(earlier)
        self.last_save = time.monotonic()
        with _lock:
            _cost["saves"] += 1
            _cost["seconds"] += time.perf_counter() - start


def to_json(value: Any) -> Any:
    """``value`` with numpy arrays and scalars as JSON objects that ``from_json`` turns
    back into the same arrays, bit for bit (floats are written at full precision)."""
    if isinstance(value, dict):
        return {str(k): to_json(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [to_json(v) for v in value]
    if isinstance(value, (np.ndarray, np.generic)) or hasattr(value, "__array__"):
        a = np.asarray(value)
        return {"__array__": a.ravel().tolist(), "dtype": str(a.dtype), "shape": list(a.shape)}
    return value


def from_json(value: Any) -> Any:
    if isinstance(value, dict):
        if "__array__" in value:
            return np.asarray(value["__array__"], dtype=value["dtype"]).reshape(value["shape"])
        return {k: from_json(v) for k, v in value.items()}
    if isinstance(value, list):
        return [from_json(v) for v in value]
    return value


def for_loop(name: str | None, identity: dict[str, Any]) -> LoopCheckpoints | None:
    """The checkpoints of a loop named ``name`` under the active policy, or ``None``
    when no policy is active or the loop has no name."""
    policy = _active
    if policy is None or not name:
        return None
    return LoopCheckpoints(policy, name, identity)
