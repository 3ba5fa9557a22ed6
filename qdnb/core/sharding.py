"""Every local device: a population's batch axis spread over a one-axis mesh.

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

import os
from functools import lru_cache
from typing import Any

BATCH = "batch"


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


def shard_batch(tree: Any) -> Any:
    """``tree`` with the leading axis of every array leaf split over ``mesh()``."""
    m = mesh()
    if m is None:
        return tree
    import jax
    from jax.sharding import NamedSharding, PartitionSpec

    split = NamedSharding(m, PartitionSpec(BATCH))
    return jax.tree.map(
        lambda x: jax.lax.with_sharding_constraint(x, split) if getattr(x, "ndim", 0) else x, tree
    )


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
