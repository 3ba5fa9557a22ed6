"""Run manifests: what was run, how, where, and what came out.

Every notebook run writes ``data/runs/<scale>/<notebook>/summary.json`` through
``Run.finish``; all writes here are atomic (temporary file, then rename).
"""

from __future__ import annotations

import json
import math
import os
import platform
import subprocess
import tempfile
import time
from importlib import metadata
from pathlib import Path
from typing import Any

import numpy as np

from qdnb import paths
from qdnb.scale import check_scale, config_dict, config_hash

PACKAGES = ("jax", "jaxlib", "brax", "flax", "optax")


def atomic_write_bytes(path: Path, data: bytes) -> Path:
    """Write ``data`` to ``path`` so that readers see the old file or the new one,
    never half of one."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def to_jsonable(obj: Any) -> Any:
    """Arrays, numpy scalars, tuples and non-finite floats turned into plain JSON
    (non-finite floats become the strings "inf", "-inf" and "nan")."""
    if isinstance(obj, dict):
        return {str(k): to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [to_jsonable(v) for v in obj]
    if hasattr(obj, "__array__") and not isinstance(obj, (str, bytes)):
        arr = np.asarray(obj)
        return to_jsonable(arr.tolist()) if arr.ndim else to_jsonable(arr.item())
    if isinstance(obj, float) and not math.isfinite(obj):
        return str(obj)
    return obj


def atomic_write_json(path: Path, obj: Any) -> Path:
    return atomic_write_bytes(path, (json.dumps(to_jsonable(obj), indent=2, sort_keys=True) + "\n").encode())


def save_arrays(path: Path, config_hash_: str, **arrays: Any) -> Path:
    """Save named arrays to an ``.npz`` artifact, atomically, tagged with the
    config hash they were computed under."""
    import io

    buf = io.BytesIO()
    np.savez_compressed(buf, config_hash=np.asarray(config_hash_), **{k: np.asarray(v) for k, v in arrays.items()})
    return atomic_write_bytes(path, buf.getvalue())


def load_arrays(path: Path, config_hash_: str) -> dict[str, np.ndarray] | None:
    """The arrays of an artifact, or ``None`` when it is missing or was computed
    under another config (then the caller recomputes)."""
    path = Path(path)
    if not path.exists():
        return None
    with np.load(path) as data:
        if str(data["config_hash"]) != config_hash_:
            return None
        return {k: data[k] for k in data.files if k != "config_hash"}


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
    return f"{d.platform}: {getattr(d, 'device_kind', d)} x{jax.device_count()} ({os.cpu_count()} CPU cores)"


def git_sha() -> str:
    """The commit the code was run from, with ``-dirty`` when tracked files differ
    (``QDNB_GIT_SHA`` overrides it, for copies of the tree without ``.git``)."""
    if os.environ.get("QDNB_GIT_SHA"):
        return os.environ["QDNB_GIT_SHA"]
    try:
        sha = subprocess.run(["git", "rev-parse", "HEAD"], cwd=paths.ROOT, capture_output=True,
                             text=True, check=True).stdout.strip()
        dirty = subprocess.run(["git", "diff", "--quiet", "HEAD", "--"], cwd=paths.ROOT).returncode != 0
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


def load_summary(scale: str, notebook: str) -> dict[str, Any] | None:
    path = paths.run_dir(scale, notebook, create=False) / "summary.json"
    return json.loads(path.read_text()) if path.exists() else None
