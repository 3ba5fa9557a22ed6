"""Run manifests: what was run, how, where, and what came out.

Every notebook run writes ``data/runs/<scale>/<notebook>/summary.json`` through
``Run.finish``; all writes here are atomic (temporary file, then rename).
"""

from __future__ import annotations

import hashlib
import json
import os
import platform
import subprocess
import time
from importlib import metadata
from pathlib import Path
from typing import Any

from qdnb.book import registry, verdicts
from qdnb.core import checkpoint, paths, sharding
from qdnb.core.config import check_scale, config_dict, config_hash
from qdnb.core.io import atomic_write_bytes, atomic_write_json, to_jsonable

PACKAGES = ("jax", "jaxlib", "brax", "flax", "optax", "orbax-checkpoint")


def versions() -> dict[str, str]:
    out = {"python": platform.python_version()}
    for name in PACKAGES:
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            out[name] = "not installed"
    return out


# what every bench result file records of where and when it was measured
RESULT_PROVENANCE = ("device", "commit", "date", "versions")


def write_result(path: Path, record: dict[str, Any], keep_provenance: bool = False) -> dict:
    """Write a ``bench/`` script's result file: its ``record`` (the question, the settings
    and the answers) after the provenance every result carries, ``RESULT_PROVENANCE``: the
    device (processor included), the commit of the code that ran, the UTC date and time,
    and the packages' versions, as of this write (a resumable script that reloads its file
    and adds a part records the run that wrote last).  With ``keep_provenance`` the
    record's own provenance stays where it has one (a check appended to a measurement
    leaves the measurement's).  Written atomically, so a reader never meets half a file.
    Returns what it wrote."""
    fresh = {
        "device": device(),
        "commit": git_sha(),
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "versions": versions(),
    }
    full = {**fresh, **record} if keep_provenance else {**fresh, **_without_provenance(record)}
    full = to_jsonable(full)
    atomic_write_bytes(Path(path), (json.dumps(full, indent=1) + "\n").encode())
    return full


def _without_provenance(record: dict[str, Any]) -> dict[str, Any]:
    return {k: v for k, v in record.items() if k not in RESULT_PROVENANCE}


def processor() -> str:
    """The host's processor model (Linux's ``/proc/cpuinfo``; else ``platform``'s): XLA's
    CPU code, and so timings and the last digits of results, differ by processor."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown processor"


def device() -> str:
    import jax

    d = jax.devices()[0]
    kind = getattr(d, "device_kind", d)
    cores = f"{os.cpu_count()} CPU cores, {processor()}"
    return f"{d.platform}: {kind} x{jax.device_count()} ({cores})"


def devices() -> dict[str, Any]:
    """The accelerator a run used: platform, kind, how many devices (all processes'
    and this process's), how many processes, and how the host device count was chosen
    (``sharding.device_choice``)."""
    import jax

    d = jax.devices()[0]
    return {
        "platform": d.platform,
        "kind": str(getattr(d, "device_kind", d)),
        "count": jax.device_count(),
        "local_count": jax.local_device_count(),
        "process_count": jax.process_count(),
        "chosen_by": sharding.device_choice().get("chosen_by", "unknown"),
    }


def device_text() -> str:
    """The devices in a sentence, for a page's provenance line: "2 CPU devices (one per
    core of 2)", "1 GPU (NVIDIA H100)"."""
    info = devices()
    n, platform = info["count"], info["platform"]
    if platform == "cpu":
        how = info["chosen_by"]
        if how.startswith("default"):
            how = f"one per core of {sharding.cores()}"
        return f"{n} CPU device{'s' * (n > 1)} ({how})"
    name = {"gpu": "GPU", "tpu": "TPU"}.get(platform, platform)
    return f"{n} {name}{'s' * (n > 1)} ({info['kind']})"


def git_sha() -> str:
    """The commit the code was run from, with ``-dirty`` when tracked files differ
    (``QDNB_GIT_SHA`` overrides it, for copies of the tree without ``.git``)."""
    if os.environ.get("QDNB_GIT_SHA"):
        return os.environ["QDNB_GIT_SHA"]
    try:
        sha = subprocess.run(
            ["git", "rev-parse", "HEAD"], cwd=paths.ROOT, capture_output=True, text=True, check=True
        ).stdout.strip()
        dirty = (
            subprocess.run(["git", "diff", "--quiet", "HEAD", "--"], cwd=paths.ROOT).returncode != 0
        )
        return sha + ("-dirty" if dirty else "")
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


CHECKPOINT_MODES = ("resume", "fresh", "off")
# XLA's GPU kernels are not all deterministic (scatter-adds and reductions use atomics);
# `--deterministic` makes them so, at a cost in speed.  CPU runs are deterministic anyway.
DETERMINISTIC_FLAG = "--xla_gpu_deterministic_ops=true"


def checkpoint_mode() -> str:
    """``QDNB_CHECKPOINTS``: ``resume`` (the default: loops save checkpoints and a run
    started again resumes from them), ``fresh`` (loops save but never resume) or
    ``off`` (no checkpoints)."""
    mode = os.environ.get("QDNB_CHECKPOINTS", "resume")
    if mode not in CHECKPOINT_MODES:
        raise ValueError(
            f"QDNB_CHECKPOINTS must be one of {', '.join(CHECKPOINT_MODES)}, got {mode!r}"
        )
    return mode


def checkpoint_intervals() -> dict[str, float]:
    """``QDNB_CHECKPOINT_EVERY_CHUNKS`` and ``QDNB_CHECKPOINT_EVERY_SECONDS``, where set:
    how often long loops save (defaults: ``CheckpointPolicy``'s)."""
    out: dict[str, float] = {}
    for name, key, kind in (
        ("QDNB_CHECKPOINT_EVERY_CHUNKS", "every_chunks", int),
        ("QDNB_CHECKPOINT_EVERY_SECONDS", "every_seconds", float),
    ):
        if os.environ.get(name):
            try:
                out[key] = kind(os.environ[name])
            except ValueError:
                raise ValueError(f"{name} must be a number, got {os.environ[name]!r}") from None
    return out


def package_digest(root: Path | None = None) -> str:
    """A digest of the ``qdnb`` package's Python sources: what a loop computes with.
    Unlike the commit it ignores notebooks, benches, tests and the book's text, so a
    checkpoint of an hours-long loop survives commits that do not touch the package."""
    root = Path(__file__).resolve().parents[1] if root is None else root
    h = hashlib.sha256()
    for path in sorted(root.rglob("*.py")):
        h.update(str(path.relative_to(root)).encode())
        h.update(path.read_bytes())
    return h.hexdigest()[:16]


def code_version() -> str:
    """What a checkpoint must have been written by to be loaded: this package's
    sources (``package_digest``) and the versions of its numerical dependencies."""
    deps = ", ".join(f"{k} {v}" for k, v in versions().items())
    return f"qdnb sources {package_digest()} ({deps})"


class Run:
    """One execution of a notebook: ``Run(notebook, scale, seed, cfg)`` at the top,
    ``run.finish(results)`` at the end (on a cluster, process 0 writes
    ``summary.json``, the others ``summary.process-<i>.json``).  Creating it joins
    the cluster if there is one and activates the checkpoints of the run's long
    loops (``qdnb.core.checkpoint``) under ``<run dir>/checkpoints/``, as
    ``QDNB_CHECKPOINTS`` says."""

    def __init__(self, notebook: str, scale: str, seed: int, cfg: Any):
        sharding.initialize_distributed()  # one of several processes: join them first
        self.notebook = notebook
        self.scale = check_scale(scale)
        self.seed = int(seed)
        self.config = cfg
        self.dir = paths.run_dir(scale, notebook)
        self.started = time.time()
        # what computed the results, as published verdicts are checked against it (read
        # when the run starts: a commit made while it runs is not its code)
        self.code_digest = verdicts.code_digest(notebook) if notebook in registry.names() else None
        self.git_sha = git_sha()
        self.checkpoints = mode = checkpoint_mode()
        checkpoint.activate(
            None
            if mode == "off"
            else checkpoint.CheckpointPolicy(
                self.dir / "checkpoints",
                self.config_hash,
                self.seed,
                code_version(),
                resume=mode == "resume",
                **checkpoint_intervals(),
            )
        )

    @property
    def config_hash(self) -> str:
        return config_hash(self.config)

    def header(self) -> str:
        """The page's provenance line: scale, seed, config hash and devices."""
        return (
            f"Scale **{self.scale}**, seed **{self.seed}**, config hash `{self.config_hash}`, "
            f"{device_text()}."
        )

    def summary(self, results: dict[str, Any]) -> dict[str, Any]:
        return {
            "notebook": self.notebook,
            "scale": self.scale,
            "seed": self.seed,
            "config": config_dict(self.config),
            "config_hash": self.config_hash,
            "code_digest": self.code_digest,
            "versions": versions(),
            "device": device(),
            "xla_flags": os.environ.get("XLA_FLAGS", ""),
            "devices": devices(),
            "deterministic_gpu_ops": DETERMINISTIC_FLAG in os.environ.get("XLA_FLAGS", ""),
            "checkpoints": {
                "mode": self.checkpoints,
                "resumed": checkpoint.resumed(),
                **checkpoint.cost(),
            },
            "git_sha": self.git_sha,
            "wall_time_s": round(time.time() - self.started, 2),
            "results": results,
        }

    def finish(self, results: dict[str, Any]) -> Path:
        """Write ``summary.json`` for this run and return its path; the run's loops
        are over, so its checkpoints are no longer active."""
        name = "summary.json"
        if not sharding.is_main_process():  # process 0 writes the run's summary
            import jax

            name = f"summary.process-{jax.process_index()}.json"
        path = atomic_write_json(self.dir / name, self.summary(results))
        checkpoint.activate(None)
        return path
