"""Run manifests: what was run, how, where, and what came out.

Every notebook run writes ``data/runs/<scale>/<notebook>/summary.json`` through
``Run.finish``; all writes here are atomic (temporary file, then rename).
"""

from __future__ import annotations

import os
import platform
import subprocess
import time
from importlib import metadata
from pathlib import Path
from typing import Any

from qdnb.core import paths
from qdnb.core.config import check_scale, config_dict, config_hash
from qdnb.core.io import atomic_write_json

PACKAGES = ("jax", "jaxlib", "brax", "flax", "optax")


def versions() -> dict[str, str]:
    out = {"python": platform.python_version()}
    for name in PACKAGES:
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            out[name] = "not installed"
    return out


def device() -> str:
    import jax

    d = jax.devices()[0]
    kind = getattr(d, "device_kind", d)
    return f"{d.platform}: {kind} x{jax.device_count()} ({os.cpu_count()} CPU cores)"


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


class Run:
    """One execution of a notebook: ``Run(notebook, scale, seed, cfg)`` at the top,
    ``run.finish(results)`` at the end."""

    def __init__(self, notebook: str, scale: str, seed: int, cfg: Any):
        self.notebook = notebook
        self.scale = check_scale(scale)
        self.seed = int(seed)
        self.config = cfg
        self.dir = paths.run_dir(scale, notebook)
        self.started = time.time()

    @property
    def config_hash(self) -> str:
        return config_hash(self.config)

    def summary(self, results: dict[str, Any]) -> dict[str, Any]:
        return {
            "notebook": self.notebook,
            "scale": self.scale,
            "seed": self.seed,
            "config": config_dict(self.config),
            "config_hash": self.config_hash,
            "versions": versions(),
            "device": device(),
            "xla_flags": os.environ.get("XLA_FLAGS", ""),
            "git_sha": git_sha(),
            "wall_time_s": round(time.time() - self.started, 2),
            "results": results,
        }

    def finish(self, results: dict[str, Any]) -> Path:
        """Write ``summary.json`` for this run and return its path."""
        return atomic_write_json(self.dir / "summary.json", self.summary(results))
