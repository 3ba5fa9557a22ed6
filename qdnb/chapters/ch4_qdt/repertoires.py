"""The Chapter 4 repertoires the QDT's datasets come from: the reproducibility page's run
at the same scale, or recomputed.
"""

from __future__ import annotations

from typing import Any

import jax

from qdnb.chapters.ch4_reproducibility import (
    ReproducibilityConfig,
    load_repertoires,
    save_repertoires,
)
from qdnb.chapters.ch4_reproducibility import run_environment as run_chapter4
from qdnb.core import paths
from qdnb.core.config import config_hash
from qdnb.core.io import load_summary
from qdnb.models.qdt.data import SOURCES


def repertoire_path(scale: str, env_name: str, method: str):
    return paths.run_dir(scale, "ch4_reproducibility") / f"repertoire_{env_name}_{method}.npz"


def load_or_recompute_repertoires(
    repro_cfg: ReproducibilityConfig, scale: str, seed: int, progress: bool = True
) -> tuple[dict, dict]:
    """``repertoires[env][method]`` (the arrays of ``load_repertoires``, stacked over
    the Chapter 4 seeds) and ``status[env][method]``: ``"loaded"``, or why it was
    recomputed.  Recomputation runs the Chapter 4 code with the Chapter 4
    notebook's keys (so it gives the same repertoires) and saves them there."""
    digest = config_hash(repro_cfg)
    summary = load_summary(scale, "ch4_reproducibility")
    seed_differs = summary is not None and summary.get("seed") != seed
    repertoires: dict[str, dict[str, Any]] = {}
    status: dict[str, dict[str, str]] = {}
    for i, env_name in enumerate(repro_cfg.environments):
        repertoires[env_name], status[env_name] = {}, {}
        missing = []
        for method in SOURCES:
            path = repertoire_path(scale, env_name, method)
            loaded = None if seed_differs else load_repertoires(path, digest)
            if loaded is not None:
                repertoires[env_name][method] = loaded
                status[env_name][method] = "loaded"
            else:
                missing.append(method)
                status[env_name][method] = (
                    "recomputed: the Chapter 4 run used another seed"
                    if seed_differs
                    else "recomputed: missing"
                    if not path.exists()
                    else "recomputed: computed under another config"
                )
        if missing:
            # the key ch4_reproducibility.run_environments(repro_cfg, PRNGKey(seed)) gives it
            key = jax.random.fold_in(jax.random.PRNGKey(seed), i)
            out = run_chapter4(repro_cfg, env_name, key, progress, methods=tuple(missing))
            for method in missing:
                r = out.methods[method]
                path = save_repertoires(
                    repertoire_path(scale, env_name, method),
                    digest,
                    r.repertoire,
                    r.spread_at_insertion,
                    r.reassessed_spread,
                )
                repertoires[env_name][method] = load_repertoires(path, digest)
    return repertoires, status
