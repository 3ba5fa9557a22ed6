"""Dry runs: every long loop of a notebook runs its first step(s) at a scale's real
shapes, its cost is measured, and the rest is skipped.

``python -m qdnb dryrun`` (``qdnb.book.dryrun_report``) executes a notebook with
``QDNB_DRYRUN`` naming a file; from then on, in that kernel (the loops of ``qdnb.core.loops``
and ``qdnb.qd.algorithms.run_seeds`` meet the dry run at one seam, ``driver()``: the
``FullRun`` driver runs them as written, the ``DryRun`` one as below):

- ``scan_in_chunks`` compiles its step as a one-step ``lax.scan`` (the chunk's own
  body), runs it once or twice, and returns the final carry with the step's outputs
  repeated to the loop's full length, so everything downstream (metrics, tables,
  figures) runs on arrays of the real run's shapes;
- a Python loop written ``for i in dryrun.steps(name, range(...))`` runs its first
  ``keep`` iterations, each timed up to ``step_done``;
- ``dryrun.count(what, full, kept)`` cuts a count that changes no shape (episodes
  generated, seeds run one after another) and says so;
- loops run one after another (``map_concurrently``), so that each is timed alone.

Each loop appends one JSON line to that file: its name, the loop's full length, the
steps run, compile seconds, seconds per step, and the sizes of its state (the
carry: what a checkpoint saves), of its outputs at full length and of XLA's
working memory.  Outside a dry run every function here is the identity.
"""

from __future__ import annotations

import contextlib
import json
import os
import resource
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator

import jax
import jax.numpy as jnp
import numpy as np

from qdnb.core import sharding

ENV = "QDNB_DRYRUN"
KEEP_STEPS = 2  # steps a loop runs in a dry run (the first one alone when it is slow)
SLOW_STEP_S = 2.0  # a first step slower than this is not run again (its time is clear)
# a Python loop's first iteration slower than this is its only one: its time, compilation
# included, is the rate (the FLT's paper step: 139 s on 2 CPU cores, 58 s on an H100 of
# which 57 s compiling, where a second step is run)
SLOW_LOOP_S = 100.0
ALL_SEEDS_S = 5.0  # seeds side by side all run when a step of them all would be quicker

_lock = threading.Lock()
_repeat = threading.local()


def active() -> Path | None:
    """The file this process's dry run records to, or ``None`` outside a dry run."""
    where = os.environ.get(ENV)
    return Path(where) if where else None


def tree_bytes(tree: Any) -> int:
    """Bytes of every array of ``tree`` (all shards of a sharded array)."""
    return int(
        sum(np.dtype(x.dtype).itemsize * int(np.prod(x.shape)) for x in jax.tree.leaves(tree))
    )


def peak_rss_bytes() -> int:
    """This process's peak resident memory so far (Linux reports kilobytes)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


def record(kind: str, name: str, **fields: Any) -> None:
    """Append one record to the dry run's file (nothing outside a dry run)."""
    where = active()
    if where is None:
        return
    entry = {
        "kind": kind,
        "name": name,
        "repeats": repeat_factor(),
        "memory_factor": memory_factor(),
        "state_factor": state_factor(),
        **fields,
    }
    # when (the gaps between records are the time no loop accounts for)
    entry.update(peak_rss_bytes=peak_rss_bytes(), devices=jax.device_count(), at=time.time())
    held = getattr(_repeat, "held", None)
    if held is not None:  # inside ``held_back``: written later, or never
        held.append(entry)
        return
    write([entry])


def write(entries: list[dict[str, Any]]) -> None:
    where = active()
    if where is None or not entries:
        return
    with _lock:
        where.parent.mkdir(parents=True, exist_ok=True)
        with where.open("a") as f:
            f.writelines(json.dumps(e, default=float) + "\n" for e in entries)


def repeat_factor() -> float:
    return getattr(_repeat, "factor", 1.0)


def memory_factor() -> float:
    return getattr(_repeat, "memory", 1.0)


def state_factor() -> float:
    return getattr(_repeat, "state", 1.0)


@contextlib.contextmanager
def repeats(
    factor: float, side_by_side: bool = False, shared_state: bool = False
) -> Iterator[None]:
    """Loops recorded inside stand for ``factor`` runs each in the full run, after a
    ``count`` cut: of work run again one after another (seeds in a Python loop), or,
    ``side_by_side``, of independent copies the full run holds at once (seeds under
    ``vmap``), whose memory then counts ``factor`` times too: their working memory, and
    their state and outputs unless they share them (``shared_state``: the perturbations
    of one ES generation, around one set of central parameters)."""
    before = repeat_factor(), memory_factor(), state_factor()
    _repeat.factor = before[0] * factor
    _repeat.memory = before[1] * (factor if side_by_side else 1.0)
    _repeat.state = before[2] * (factor if side_by_side and not shared_state else 1.0)
    try:
        yield
    finally:
        _repeat.factor, _repeat.memory, _repeat.state = before


@contextlib.contextmanager
def held_back() -> Iterator[list[dict[str, Any]]]:
    """The records made inside are collected in the list it yields, not written: the
    caller then ``write``s them or drops them (a probe it measured something with)."""
    before = getattr(_repeat, "held", None)
    _repeat.held = []
    try:
        yield _repeat.held
    finally:
        _repeat.held = before


@contextlib.contextmanager
def uncut() -> Iterator[None]:
    """``count`` cuts nothing inside."""
    before = getattr(_repeat, "uncut", False)
    _repeat.uncut = True
    try:
        yield
    finally:
        _repeat.uncut = before


def cutting() -> bool:
    """In a dry run, outside ``uncut``: counts may be cut."""
    return active() is not None and not getattr(_repeat, "uncut", False)


def count(what: str, full: int, kept: int = 1) -> int:
    """``full``; in a dry run ``min(full, kept)``, the cut recorded (not inside
    ``uncut``).  Only for counts that change no shape a loop compiles (episodes
    generated, trajectories, seeds run one after another or side by side)."""
    if not cutting() or full <= kept:
        return full
    record("cut", what, full=int(full), kept=int(kept))
    return int(kept)


@dataclass(frozen=True)
class BatchCut:
    """A batch of ``full`` independent copies around one shared state (an ES generation's
    perturbations, a batch of Flow Lenia episodes) as a dry run on a CPU cuts it: it
    plays ``kept`` of them, and every loop recorded inside ``counted()`` stands for the
    ``full / kept`` copies the full run holds side by side (``repeats``)."""

    full: int
    kept: int

    def counted(self) -> contextlib.AbstractContextManager:
        return repeats(self.full / self.kept, side_by_side=True, shared_state=True)


def cut_batch(what: str, full: int, kept: int) -> BatchCut:
    """The ``BatchCut`` of a batch of ``full`` copies: ``kept`` of them (at least one per
    device) in a dry run on a CPU, the cut recorded as ``what`` (``count``); the whole
    batch elsewhere (a GPU runs it all: its rate on a cut batch would not tell) and
    outside a dry run."""
    if jax.default_backend() != "cpu":
        return BatchCut(full, full)
    return BatchCut(full, count(what, full, max(kept, jax.local_device_count())))


def _memory(compiled: Any) -> dict[str, int]:
    """XLA's own account of one compiled program's memory (per device)."""
    try:
        stats = compiled.memory_analysis()
    except Exception:  # a backend without the analysis
        return {}
    if stats is None:
        return {}
    return {
        "xla_argument_bytes": int(stats.argument_size_in_bytes),
        "xla_output_bytes": int(stats.output_size_in_bytes),
        "xla_temp_bytes": int(stats.temp_size_in_bytes),
    }


def host_memory_bytes() -> int:
    return sharding.device_memory_bytes()  # the host's, in a CPU dry run


def compiled(name: str, jitted: Any, *args: Any) -> Any:
    """``jitted`` itself outside a dry run; in one, ``jitted`` compiled ahead of time for
    the shapes of ``args`` (``jax.ShapeDtypeStruct`` leaves will do), its compile seconds
    and memory recorded under ``name`` (a loop of no steps): the calls then timed
    (``timed``) are the program's run alone."""
    if active() is None:
        return jitted
    began = time.perf_counter()
    executable = jitted.lower(*args).compile()
    record("compile", name, full_steps=0, steps_run=0, step_s=[], seconds_per_step=0.0,
           compile_s=time.perf_counter() - began, **_memory(executable))  # fmt: skip
    return executable


def too_big_here(name: str, jitted: Any, *args: Any, full_steps: int = 1) -> bool:
    """In a dry run: compile ``jitted`` for ``args`` and, when XLA's working memory for
    it would not fit this machine's memory, record the loop as not run here (with that
    memory) and return true; the caller then skips its steps.  False outside a dry run."""
    if active() is None:
        return False
    began = time.perf_counter()
    memory = _memory(jitted.lower(*args).compile())
    need, has = sum(memory.values()), host_memory_bytes()
    if need < 0.8 * has:
        return False
    record(
        "skipped",
        name,
        full_steps=int(full_steps),
        compile_s=time.perf_counter() - began,
        reason=f"a step needs {need / 1e9:.0f} GB of working memory on this machine's "
        f"XLA ({jax.default_backend().upper()}), which has {has / 1e9:.0f} GB",
        **memory,
    )
    return True


def scan(
    step: Callable[[Any], tuple[Any, Any]], carry: Any, num_steps: int, name: str | None
) -> tuple[Any, Any]:
    """``scan_in_chunks``'s dry run: the step as a one-step ``lax.scan``, compiled
    ahead of time (its compile seconds), run ``KEEP_STEPS`` times (once when slow);
    returns the last carry and the last step's outputs repeated ``num_steps`` times."""
    name = name or "unnamed loop"
    program = jax.jit(lambda c: jax.lax.scan(lambda c, _: step(c), c, None, length=1))
    seconds, out = [], None
    began = time.perf_counter()
    try:
        compiled = program.lower(carry).compile()
        compile_s = time.perf_counter() - began
        placed = compiled.input_shardings[0][0]  # where the program wants its carry
        for _ in range(min(KEEP_STEPS, num_steps)):
            carry = jax.device_put(carry, placed)  # a step may hand it back placed otherwise
            began = time.perf_counter()
            carry, out = compiled(carry)
            jax.block_until_ready((carry, out))
            seconds.append(time.perf_counter() - began)
            if seconds[0] > SLOW_STEP_S:
                break
    except Exception as err:  # reported with the loop's name, then raised as it was
        record("failed", name, full_steps=int(num_steps), error=f"{type(err).__name__}: {err}")
        raise
    fields = {
        "full_steps": int(num_steps),
        "steps_run": len(seconds),
        "compile_s": compile_s,
        "step_s": seconds,
        "seconds_per_step": min(seconds),
        "carry_bytes": tree_bytes(carry),
        "outputs_bytes": tree_bytes(out) * num_steps,
        **_memory(compiled),
    }
    if isinstance(out, dict) and "env_steps" in out:
        fields["env_steps_per_step"] = float(jnp.sum(out["env_steps"]))
    record("scan", name, **fields)
    outputs = jax.tree.map(lambda x: jnp.repeat(x, num_steps, axis=0), out)
    return carry, outputs


class steps:
    """``for i in steps(name, range(...), unit="epoch")``: every iteration outside a
    dry run; in one, the first ``keep``, each timed from its start to ``step_done``
    (which waits for the arrays it is given).  Recorded at the loop's end with the
    loop's full length (``len(indices)``, or ``full``)."""

    def __init__(
        self,
        name: str,
        indices: Iterable[int],
        full: int | None = None,
        keep: int = KEEP_STEPS,
        unit: str = "step",
    ):
        self.name, self.indices, self.keep, self.unit = name, indices, keep, unit
        self.full = full if full is not None else len(indices)  # type: ignore[arg-type]
        self.seconds: list[float] = []
        self.seconds_per_step = 0.0  # once a dry run's iterations are over
        self._began = 0.0
        self.dry = active() is not None

    def __iter__(self) -> Iterator[int]:
        if not self.dry:
            yield from self.indices
            return
        for n, i in enumerate(self.indices):
            if n >= self.keep:  # (the first iteration compiles: the second is the rate)
                break
            if n == 1 and self.seconds and self.seconds[0] > SLOW_LOOP_S:
                break  # a slow first iteration: its time stands for every one
            self._began = time.perf_counter()
            yield i
        first = self.seconds[0] if self.seconds else 0.0
        later = self.seconds[1:] or self.seconds
        self.seconds_per_step = min(later) if later else 0.0
        record(
            "loop",
            self.name,
            unit=self.unit,
            full_steps=int(self.full),
            steps_run=len(self.seconds),
            step_s=self.seconds,
            # the first step compiles; the later ones are the steady rate
            compile_s=max(0.0, first - min(later)) if later else 0.0,
            seconds_per_step=min(later) if later else 0.0,
        )

    def step_done(self, *arrays: Any) -> None:
        """The current iteration is over once ``arrays`` are computed (dry run only)."""
        if self.dry:
            jax.block_until_ready(arrays)
            self.seconds.append(time.perf_counter() - self._began)


_measured: dict[str, tuple[float, Any]] = {}  # a program's key: its seconds, its output


def reused(same_as: str | None, kind: str, name: str, full_steps: int, **fields: Any):
    """``(True, output)`` when a dry run timed the program ``same_as`` before (``remember``):
    this use of it is recorded at that time, ``full_steps`` times, and is not run; else
    ``(False, None)`` (and always outside a dry run)."""
    if active() is None or same_as is None or same_as not in _measured:
        return False, None
    seconds, out = _measured[same_as]
    record(kind, name, full_steps=int(full_steps), steps_run=0, step_s=[], compile_s=0.0,
           seconds_per_step=seconds, timed_as=same_as, **fields)  # fmt: skip
    return True, out


def remember(same_as: str, seconds: float, out: Any) -> None:
    """A dry run timed the program ``same_as``: its later uses are counted, not run."""
    _measured[same_as] = (seconds, out)


def timed(
    name: str,
    full_calls: int,
    fn: Callable[..., Any],
    *args: Any,
    same_as: str | None = None,
    share: float = 1.0,
    **kwargs: Any,
) -> Any:
    """``fn(*args, **kwargs)``; in a dry run its wall time is recorded as one call of
    ``full_calls`` the full run makes (a one-shot program: a batch of rollouts), times
    ``share`` where the dry run's ``fn`` does that fraction of a full call's work in
    independent parts (some of the goals).  Calls sharing a ``same_as`` key run one
    compiled program on inputs of the same shapes: in a dry run the first is timed, and
    the later ones are counted at its time and return its output, without running
    (``reused``)."""
    if active() is None:
        return fn(*args, **kwargs)
    done, out = reused(same_as, "call", name, full_calls)
    if done:
        return out
    began = time.perf_counter()
    out = fn(*args, **kwargs)
    jax.block_until_ready(out)
    seconds = (time.perf_counter() - began) * share
    if same_as is not None:
        remember(same_as, seconds, out)
    record("call", name, full_steps=int(full_calls), steps_run=1, step_s=[seconds],
           compile_s=0.0, seconds_per_step=seconds, share=share)  # fmt: skip
    return out


class FullRun:
    """The driver of a loop outside a dry run: every step, every seed, loops side by side.

    A loop asks ``driver()`` for its driver once and hands it what it would run; this
    one runs it as given.  ``DryRun`` is the one seam where a dry run replaces that."""

    concurrent = True  # independent loops may run side by side (``map_concurrently``)

    def loop(
        self,
        name: str | None,
        step: Callable[[Any], tuple[Any, Any]],
        carry: Any,
        num_steps: int,
        run: Callable[[], tuple[Any, Any]],
    ) -> tuple[Any, Any]:
        """``run()``: the loop of ``num_steps`` applications of ``step`` from ``carry``,
        as the caller wrote it (jitted chunks, checkpoints, progress)."""
        return run()

    def call(self, name: str, fn: Callable[..., Any], *args: Any) -> Any:
        """``fn(*args)``: a one-shot program before a loop (its start, a first batch)."""
        return fn(*args)

    def seeds(
        self,
        name: str,
        keys: jax.Array,
        run: Callable[[jax.Array], Any],
        spread: Callable[[Any, int], Any],
    ) -> Any:
        """``run(keys)``: one run per key, side by side (``spread`` is the dry run's)."""
        return run(keys)


class DryRun(FullRun):
    """The driver of a loop in a dry run: its first steps at the run's shapes, timed."""

    concurrent = False  # each loop timed alone

    def loop(self, name, step, carry, num_steps, run):
        """The step as a one-step scan, run once or twice (``scan``), not ``run``."""
        return scan(step, carry, num_steps, name)

    def call(self, name, fn, *args):
        """``fn(*args)``, timed as the one call the full run makes (``timed``)."""
        return timed(name, 1, fn, *args)

    def seeds(self, name, keys, run, spread):
        """One seed first.  When a step of all the seeds would take under
        ``ALL_SEEDS_S``, they then run at once, as in the full run, and that is what is
        recorded; otherwise the one seed stands for all of them (seeds side by side are
        independent copies of the same shapes: its time and memory count once per seed;
        on the QD-PG page five times one seed's step came to a median 1.0 times a step of
        all five, ``bench/results/paper_dryrun_seed_scaling.json``) and ``spread(out,
        num_seeds)`` repeats its results in every seed's slot.  Inside ``uncut``, or for
        one seed, ``run(keys)``."""
        num_seeds = len(keys)
        if num_seeds == 1 or not cutting():
            return run(keys)
        with held_back() as one_seed, repeats(num_seeds, side_by_side=True):
            out = run(keys[:1])
        # the loop's steps (a start, compiled and run once, is not a step)
        steps = [r["seconds_per_step"] for r in one_seed if r["kind"] in ("scan", "loop")]
        if max(steps, default=0.0) * num_seeds <= ALL_SEEDS_S:
            with uncut():
                return run(keys)
        count(f"{name}: seeds side by side", num_seeds, 1)
        write(one_seed)
        return spread(out, num_seeds)


FULL_RUN = FullRun()


def driver() -> FullRun:
    """The driver a loop runs under: ``DryRun`` in a dry run, else ``FULL_RUN``."""
    return DryRun() if active() is not None else FULL_RUN
