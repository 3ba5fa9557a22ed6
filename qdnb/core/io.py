"""Files written so that a reader never sees half of one: atomic writes, JSON of
arrays, and ``.npz`` artifacts tagged with the config hash they were computed under.

Plain Python and NumPy: importing it loads no JAX."""

from __future__ import annotations

import json
import math
import os
import tempfile
from pathlib import Path
from typing import Any, BinaryIO, Callable

import numpy as np

from qdnb.core import paths


def atomic_write(path: Path, write: Callable[[BinaryIO], Any]) -> Path:
    """Call ``write`` on a temporary file beside ``path``, then move it into place, so
    that readers see the old file or the new one, never half of one."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            write(f)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def atomic_write_bytes(path: Path, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically (``atomic_write``)."""
    return atomic_write(path, lambda f: f.write(data))


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
    return atomic_write_bytes(
        path, (json.dumps(to_jsonable(obj), indent=2, sort_keys=True) + "\n").encode()
    )


def save_arrays(path: Path, config_hash_: str, **arrays: Any) -> Path:
    """Save named arrays to an ``.npz`` artifact, atomically, tagged with the
    config hash they were computed under.  Uncompressed and streamed to the disk: at
    paper Chapter 4's repertoires (about 18 GB of policies' weights, which zlib barely
    shrinks) would otherwise be compressed for minutes and held in memory whole."""
    tagged = {"config_hash": np.asarray(config_hash_), **arrays}
    return atomic_write(
        path, lambda f: np.savez(f, **{k: np.asarray(v) for k, v in tagged.items()})
    )


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


def load_summary(scale: str, notebook: str) -> dict[str, Any] | None:
    """The ``summary.json`` of a notebook's run at ``scale``, or ``None``."""
    path = paths.run_dir(scale, notebook, create=False) / "summary.json"
    return json.loads(path.read_text()) if path.exists() else None
