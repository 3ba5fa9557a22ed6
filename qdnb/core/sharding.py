"""Every local device: a population's batch axis, or the seeds' axis, spread over a
one-axis mesh; and, on CPU, one XLA host device per core.

**Host devices.**  XLA runs a batched rollout on one thread of a CPU; split over one
host device per core it runs on all of them (``bench/scale_out.py``).  So importing
``qdnb`` (``configure_host_devices``, before JAX starts its backends) asks XLA for
``default_host_devices()`` CPU devices: one per core this process may use, at most
``HOST_DEVICE_CAP``.  ``QDNB_DEVICES=N`` sets the count (``1`` turns splitting off;
``python -m qdnb run|book --devices N`` sets it for the kernels); a
``--xla_force_host_platform_device_count`` in the user's own ``XLA_FLAGS`` wins over
both.  GPUs and TPUs are untouched: the flag only shapes the CPU platform, and
``jax.devices()`` lists the accelerators when there are some.  ``device_choice()``
says how the count was chosen (``summary.json`` records it).

``shard_batch(tree)`` constrains the leading axis of every leaf (a population of
policies, their keys, a minibatch of trajectories) to be split over all devices of
``mesh()`` (the ``"batch"`` axis); what is not constrained (repertoires, archives,
buffers, parameters of a model) XLA keeps replicated, and it gathers the results
where a replicated computation needs them.  Inside ``jit`` only, under ``vmap`` too
(the seeds' axis stays unsplit).  With one device it returns its input untouched: the
single-device program is the one it was before, at no cost.

Many hosts: ``initialize_distributed()`` joins the cluster when the usual variables
are set (SLURM, or ``JAX_COORDINATOR_ADDRESS``); ``jax.devices()`` then lists every
host's devices and the same mesh spans them.
"""

from __future__ import annotations

import contextvars
import os
import re
import sys
from functools import lru_cache
from typing import Any, Callable

BATCH = "batch"

# At most this many host devices by default.  Measured on 2 cores (bench/scale_out.py):
# more devices than cores is slower (4 forced devices ran ME-LS at 0.82-0.95x the rate of
# 2, QD-PG at 0.5x); past 8 a `small` population's share per device gets small (QD-PG's 8
# actors, a batch of 16 Flow Lenia episodes) while the gathers between devices grow.
# Above 2 cores the cap is a judgement, not a measurement.
HOST_DEVICE_CAP = 8
DEVICE_COUNT_FLAG = "--xla_force_host_platform_device_count"
_ADDED = "QDNB_HOST_DEVICES_FLAG"  # the flag qdnb added, so that a child can tell it from a user's
_choice: dict[str, Any] = {}


def cores() -> int:
    """The CPU cores this process may run on (its affinity mask, else all of them)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1


def device_memory_bytes() -> int:
    """The memory one computation of this process may fill: an accelerator's own
    (``bytes_limit``), else the host's (the CPU devices share it)."""
    import jax

    device = jax.local_devices()[0]
    if device.platform != "cpu":
        limit = (device.memory_stats() or {}).get("bytes_limit")
        if limit:
            return int(limit)
    return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")


def default_host_devices(num_cores: int | None = None) -> int:
    """One host device per core, at most ``HOST_DEVICE_CAP``."""
    return max(1, min(cores() if num_cores is None else num_cores, HOST_DEVICE_CAP))


def requested_devices(value: str | None, num_cores: int | None = None) -> int:
    """The device count ``QDNB_DEVICES`` (or ``--devices``) asks for, checked: a positive
    integer no larger than the cores this process has; ``None`` or ``""`` gives the
    default.  Raises ``ValueError`` naming the value and what is valid."""
    num_cores = cores() if num_cores is None else num_cores
    if value is None or str(value).strip() == "":
        return default_host_devices(num_cores)
    try:
        n = int(str(value).strip())
    except ValueError:
        n = 0
    if n < 1:
        raise ValueError(
            f"QDNB_DEVICES must be a positive integer (1 runs everything on one device; "
            f"unset, one per core), got {value!r}"
        )
    if n > num_cores:
        raise ValueError(
            f"QDNB_DEVICES={n} asks for more devices than this machine's {num_cores} CPU "
            f"cores: host devices beyond the cores share them and run slower; use 1 to "
            f"{num_cores}, or force it with XLA_FLAGS={DEVICE_COUNT_FLAG}={n}"
        )
    return n


def _backends_started() -> bool:
    if "jax" not in sys.modules:
        return False
    try:
        from jax._src import xla_bridge

        return bool(xla_bridge._backends)
    except (ImportError, AttributeError):  # pragma: no cover - another JAX layout
        return False


# XLA's CPU fusion emitters off: Chapter 4's Brax loops run faster on 2 cores
# (bench/qd_throughput.py: ME on Ant-Omni 68.9k against 57.6k env steps/s, 1.2x;
# Halfcheetah-Uni 34.7k against 32.0k, 1.08x), but the QDT's cached rollouts ran 1.75x
# slower (bench/qdt.py: 0.25 against 0.14 s) and one Flow Lenia episode 1.3x slower
# (bench/flow_lenia.py, batch 1), so it is no default: the Chapter 4 reproducibility
# notebook and its benchmarks ask for it.
BRAX_CPU_FLAGS = ("--xla_cpu_use_fusion_emitters=false",)


def add_xla_flags(flags: tuple[str, ...], environ: dict[str, str] | None = None) -> bool:
    """Append ``flags`` to ``XLA_FLAGS`` (``os.environ`` by default), each unless the
    user already set that option; XLA reads them when JAX starts its backends, so
    after that nothing changes and this returns ``False``."""
    env = os.environ if environ is None else environ
    if environ is None and _backends_started():
        return False
    current = env.get("XLA_FLAGS", "").split()
    names = {f.split("=")[0] for f in current}
    env["XLA_FLAGS"] = " ".join(current + [f for f in flags if f.split("=")[0] not in names])
    return True


def plan_host_devices(environ: dict[str, str]) -> tuple[dict[str, Any], str]:
    """What a process about to start with ``environ`` gets: how its host device count
    is chosen (``{"requested", "chosen_by"}``) and the ``XLA_FLAGS`` that ask for it.
    Raises ``ValueError`` for a bad ``QDNB_DEVICES``."""
    flags = environ.get("XLA_FLAGS", "")
    ours = environ.get(_ADDED)
    if ours and ours in flags.split():  # inherited from a qdnb parent process: choose again
        flags = " ".join(f for f in flags.split() if f != ours)
    n = requested_devices(environ.get("QDNB_DEVICES"))
    user = re.search(re.escape(DEVICE_COUNT_FLAG) + r"=(\d+)", flags)
    if user:
        return {"requested": int(user.group(1)), "chosen_by": "XLA_FLAGS (the user's)"}, flags
    how = (
        f"QDNB_DEVICES={environ['QDNB_DEVICES']}"
        if environ.get("QDNB_DEVICES", "").strip()
        else f"default: one per core ({cores()} cores, at most {HOST_DEVICE_CAP})"
    )
    return {"requested": n, "chosen_by": how}, " ".join(
        filter(None, [flags, f"{DEVICE_COUNT_FLAG}={n}"])
    )


def configure_host_devices(environ: dict[str, str] | None = None) -> dict[str, Any]:
    """Ask XLA for the host devices CPU runs use (see the module's docstring), in
    ``environ``'s ``XLA_FLAGS`` (``os.environ`` by default), before JAX starts; returns
    and remembers how the count was chosen (``device_choice``).  Raises ``ValueError``
    for a bad ``QDNB_DEVICES`` before any computation."""
    env = os.environ if environ is None else environ
    choice, flags = plan_host_devices(env)
    if environ is None and _backends_started():
        choice = {"requested": None, "chosen_by": "JAX started before qdnb was imported"}
    else:
        if not choice["chosen_by"].startswith("XLA_FLAGS"):
            env[_ADDED] = flags.split()[-1]
        if flags:
            env["XLA_FLAGS"] = flags
        else:
            env.pop("XLA_FLAGS", None)
    if environ is None:
        _choice.clear()
        _choice.update(choice)
    return choice


def device_choice() -> dict[str, Any]:
    """How this process's host device count was chosen (``configure_host_devices``)."""
    return dict(_choice)


def with_device_count(flags: str, n: int) -> str:
    """``flags`` (an ``XLA_FLAGS`` value) asking for ``n`` host devices, any earlier
    count removed (for child processes that must run at a given count)."""
    kept = [f for f in flags.split() if not f.startswith(DEVICE_COUNT_FLAG + "=")]
    return " ".join(kept + [f"{DEVICE_COUNT_FLAG}={n}"])


@lru_cache(maxsize=None)
def _mesh(devices: tuple) -> Any:
    import numpy as np
    from jax.sharding import Mesh

    return Mesh(np.array(devices), (BATCH,))


def mesh() -> Any | None:
    """A one-axis mesh over every device, or ``None`` when there is only one."""
    import jax

    devices = tuple(jax.devices())
    return None if len(devices) == 1 else _mesh(devices)


# What is split, by default (``bench/scale_out.py`` measures the alternatives by turning
# these over): the seeds' axis of a loop, when the devices divide it evenly; the QDT's
# matmul-bound minibatches on CPU host devices (no: measured slower).
SPLIT_SEEDS = True
SPLIT_DENSE_ON_CPU = False

# True while tracing a loop body whose populations stay whole (``over_seeds``: one
# device's share of split seeds, or a "seeds" algorithm whose seeds cannot be split).
_populations_whole = contextvars.ContextVar("qdnb_populations_whole", default=False)


def shard_batch(tree: Any, dense: bool = False) -> Any:
    """``tree`` with the leading axis of every array leaf split over ``mesh()``.

    Populations of policies, batches of episodes and the FLT's minibatches are split
    (``dense=False``).  A minibatch of matmul-bound training (``dense=True``: the QDT's)
    is split only on accelerators: on CPU host devices XLA already spreads a large matmul
    over every core, and splitting it measured half as fast (``bench/scale_out.py``).
    Inside a seeds-split loop (``over_seeds``) nothing is split further."""
    m = mesh()
    if m is None or _populations_whole.get() or (dense and not _splits_dense(m)):
        return tree
    import jax
    from jax.sharding import NamedSharding, PartitionSpec

    arrays = [x for x in jax.tree.leaves(tree) if getattr(x, "ndim", 0)]
    if any(x.shape[0] % m.devices.size for x in arrays):
        return tree  # a batch the devices do not divide (3 policies on 2) stays whole
    return _constrained(tree, NamedSharding(m, PartitionSpec(BATCH)))


def _constrained(tree: Any, where: Any) -> Any:
    """Every array leaf of ``tree`` constrained to the sharding ``where`` (inside ``jit``)."""
    import jax

    return jax.tree.map(
        lambda x: jax.lax.with_sharding_constraint(x, where) if getattr(x, "ndim", 0) else x, tree
    )


def _whole(m: Any) -> Any:
    """Every array whole on every device of the mesh ``m``."""
    from jax.sharding import NamedSharding, PartitionSpec

    return NamedSharding(m, PartitionSpec())


def replicated(tree: Any) -> Any:
    """``tree`` with every array leaf whole on every device of ``mesh()``: what a jitted
    function returns to code that reads it outside ``jit`` (episodes scored by eager
    operations).  Inside ``jit`` only; with one device, or inside a seeds-split loop, it
    returns its input untouched.

    An eager operation on an array split over CPU host devices runs as its own small
    program over the devices, with collectives when it crosses the split; several of
    them dispatched at once can wait on each other in XLA:CPU's rendezvous and abort
    the process after 40 s ("Termination timeout for `all gather`": the FLT's eager
    evaluation of 64 split episodes did, every time).  A replicated array needs no
    collective: each device computes the operation whole."""
    m = mesh()
    if m is None or _populations_whole.get():
        return tree
    return _constrained(tree, _whole(m))


def put_replicated(tree: Any) -> Any:
    """``tree`` placed whole on every device of ``mesh()``, outside ``jit``: a loop's
    initial carry placed where its jitted step hands the carry back, so that the step
    compiles once (a fresh array sits on one device; the step returns it replicated,
    and the second call would compile the step again).  Untouched on one device."""
    m = mesh()
    if m is None:
        return tree
    import jax

    return jax.device_put(tree, _whole(m))


def _splits_dense(m: Any) -> bool:
    return SPLIT_DENSE_ON_CPU or m.devices.flat[0].platform != "cpu"


def splits_seeds(num_seeds: int) -> bool:
    """Whether a loop over ``num_seeds`` independent seeds runs its seeds split over the
    devices (``over_seeds``): when there are several and they divide the seeds evenly."""
    m = mesh()
    return SPLIT_SEEDS and m is not None and num_seeds % m.devices.size == 0


SPLITS = ("population", "seeds")


def seed_slots(num_seeds: int, split: str = "population") -> int:
    """How many seeds a loop over ``num_seeds`` runs, given what its algorithm prefers to
    split over the devices when they do not divide its seeds (``split``):

    - ``"population"`` (a population of policies to evaluate: the MAP-Elites family, the
      ES): ``num_seeds``; each seed's population is split instead (``shard_batch``);
    - ``"seeds"`` (a few actors and much dense work, which a population split would
      repeat on every device: QD-PG, the RL agents): padded up to a multiple of
      the devices when that leaves each device fewer seeds than one device would run
      (3 seeds on 2 devices: 4, two per device); the extra seeds' results are dropped.
    """
    if split not in SPLITS:
        raise ValueError(f"split must be one of {', '.join(SPLITS)}, got {split!r}")
    m = mesh()
    if m is None or not SPLIT_SEEDS or split == "population":
        return num_seeds
    d = m.devices.size
    per_device = -(-num_seeds // d)
    return per_device * d if per_device < num_seeds else num_seeds


def over_seeds(fn: Callable[..., Any], num_seeds: int, split: str = "population") -> Callable:
    """``fn`` (a ``vmap`` over seeds: every argument and result leads with the seeds'
    axis) with each device running its share of the seeds, when ``splits_seeds``.  Seeds
    share nothing, so the devices never wait for each other; each runs the same program
    on ``num_seeds / devices`` seeds, and its populations stay whole (``shard_batch``
    does nothing inside).  Otherwise ``fn`` as it is (its populations split), or, for
    an algorithm whose ``split`` is ``"seeds"``, ``fn`` with its populations whole (on
    one device: a split would repeat its dense work on every device)."""
    m, seeds_split = mesh(), splits_seeds(num_seeds)
    if m is None or not (seeds_split or split == "seeds"):
        return fn

    def whole(*args):
        token = _populations_whole.set(True)
        try:
            return fn(*args)
        finally:
            _populations_whole.reset(token)

    if not seeds_split:
        return whole
    import jax
    from jax.sharding import PartitionSpec

    split_spec = PartitionSpec(BATCH)
    return jax.shard_map(whole, mesh=m, in_specs=split_spec, out_specs=split_spec, check_vma=False)


CLUSTER_VARIABLES = ("JAX_COORDINATOR_ADDRESS", "SLURM_NTASKS")


def cluster_requested(environ: dict[str, str] | None = None) -> bool:
    """Whether this process was launched as one of several: ``JAX_COORDINATOR_ADDRESS``
    set (a launch by hand, with ``JAX_NUM_PROCESSES`` and ``JAX_PROCESS_ID``), or a
    SLURM step of more than one task."""
    env = os.environ if environ is None else environ
    if env.get("JAX_COORDINATOR_ADDRESS"):
        return True
    return int(env.get("SLURM_NTASKS", "1") or 1) > 1 and "SLURM_JOB_ID" in env


_initialized = False


def initialize_distributed() -> bool:
    """Join the cluster (``jax.distributed.initialize()``, which reads SLURM's or the
    ``JAX_*`` variables) when ``cluster_requested()``, once, before JAX's first
    computation; returns whether this process is part of a cluster."""
    global _initialized
    if _initialized or not cluster_requested():
        return _initialized
    import jax

    jax.distributed.initialize()
    _initialized = True
    return True


def is_main_process() -> bool:
    """Process 0 writes the summaries and the book; the others only their own logs."""
    import jax

    return jax.process_index() == 0
