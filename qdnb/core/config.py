"""Scales and config identity, shared by every layer.

``SCALES``: ``tiny`` (CI, minutes on 2 CPU cores), ``small`` (a laptop, at most
25 minutes per notebook) and ``paper`` (one GPU, the thesis's budgets).  A config
is a frozen dataclass; ``config_hash`` names it in file names and manifests.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json

SCALES = ("tiny", "small", "paper")


def check_scale(scale: str) -> str:
    if scale not in SCALES:
        raise ValueError(f"unknown scale {scale!r}; valid scales: {', '.join(SCALES)}")
    return scale


def config_dict(cfg) -> dict:
    return {"type": type(cfg).__name__, **dataclasses.asdict(cfg)}


def config_hash(cfg) -> str:
    """A short, stable hash of a config (its class name and field values)."""
    blob = json.dumps(config_dict(cfg), sort_keys=True, default=list)
    return hashlib.sha256(blob.encode()).hexdigest()[:16]
