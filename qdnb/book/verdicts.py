"""Published verdicts: a page's claims at a scale, kept in the repository so that every
build shows them, with where, when and from which code they were computed.

A run's ``summary.json`` is kilobytes; ``publish_verdicts(scale, notebook)`` copies its
claims and provenance into ``data/published/<scale>/<notebook>/verdicts.json`` (no
executed notebook, no artifact).  The book reads them for a scale whose page did not
run on this machine (a page's own run always takes precedence), and marks them
**stale** when what computed them has changed since: the chapter's config at that scale
(its hash), or its computation's code (``code_digest``: the notebook's code cells and
every ``qdnb`` module they and the chapter's module import, but ``PRESENTATION``'s: the
book's, the figures' and tables', the reader's names; the notebook's prose changes
nothing).  Of a run from before code digests were recorded, the book says that whether
it is current cannot be told.
"""

from __future__ import annotations

import ast
import hashlib
import json
import platform
import time
from pathlib import Path
from typing import Any

import nbformat

from qdnb.book import publish, registry
from qdnb.core import paths
from qdnb.core.config import config_hash
from qdnb.core.io import atomic_write_json

# the scales whose claim checks are code paths, not evidence: no verdict is kept or printed
NO_VERDICT = ("tiny",)
FILE = "verdicts.json"
# modules that present results and compute none: a change there leaves a verdict fresh
# (the book, the figures and tables, the names a reader sees)
PRESENTATION = ("qdnb.book", "qdnb.plotting", "qdnb.core.names")
# what a verdict keeps of its run's summary.json
KEPT = ("seed", "config_hash", "code_digest", "git_sha", "device", "devices", "wall_time_s")


def _module_file(module: str) -> Path | None:
    base = paths.ROOT.joinpath(*module.split("."))
    for candidate in (base.with_suffix(".py"), base / "__init__.py"):
        if candidate.exists():
            return candidate
    return None


def _imported(source: str) -> set[str]:
    """The ``qdnb`` modules a source imports (``from qdnb.a import b`` names ``qdnb.a``
    and, if it is a module, ``qdnb.a.b``)."""
    found = set()
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            found |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
            found.add(node.module)
            found |= {f"{node.module}.{a.name}" for a in node.names}
    return {m for m in found if m.split(".")[0] == "qdnb"}


def _notebook_source(notebook: Path) -> str:
    cells = nbformat.read(notebook, as_version=4).cells
    lines = [
        line
        for c in cells
        if c.cell_type == "code"
        for line in c.source.splitlines()
        if not line.lstrip().startswith(("%", "!"))
    ]
    return "\n".join(lines)


def computation_files(name: str) -> list[Path]:
    """The files a chapter's results depend on: its notebook, its module and every
    ``qdnb`` module they import, transitively (packages' ``__init__`` included), but
    ``PRESENTATION``'s (of the notebook, ``code_digest`` reads the code cells)."""
    notebook = registry.chapter(name).notebook
    return [notebook] + _modules(name, _notebook_source(notebook))


def _modules(name: str, notebook_source: str) -> list[Path]:
    """The module files of ``computation_files``, given the notebook's code."""
    todo = _imported(notebook_source) | {f"qdnb.chapters.{name}"}
    seen: dict[str, Path] = {}
    while todo:
        module = todo.pop()
        if module in seen or module.startswith(PRESENTATION):
            continue
        parts = module.split(".")
        todo |= {".".join(parts[:i]) for i in range(1, len(parts))}  # its packages
        path = _module_file(module)
        if path is None:  # a name imported from a module, not a module
            continue
        seen[module] = path
        todo |= _imported(path.read_text())
    return sorted(set(seen.values()))


def code_digest(name: str) -> str:
    """A digest of ``computation_files(name)``: their paths and contents (the
    notebook's code cells only)."""
    source = _notebook_source(registry.chapter(name).notebook)
    h = hashlib.sha256(source.encode())
    for f in _modules(name, source):
        h.update(str(f.relative_to(paths.ROOT)).encode())
        h.update(f.read_bytes())
    return h.hexdigest()[:16]


def path(scale: str, notebook: str) -> Path:
    """Where the verdicts of ``notebook`` at ``scale`` are kept, beside its archive."""
    return publish.archive_path(scale, notebook).with_name(FILE)


def _record(
    notebook: str, scale: str, summary: dict, published_at: str, host: str | None
) -> dict[str, Any]:
    results = summary.get("results", {})
    return {
        "format": 1,
        "notebook": notebook,
        "scale": scale,
        "published_at": published_at,
        "host": host,
        "run": {k: summary.get(k) for k in KEPT},
        "headline": results.get("headline", ""),
        "claims": results.get("claims"),
    }


def publish_verdicts(scale: str, notebook: str) -> Path:
    """Copy the claims and provenance of the finished run of ``notebook`` at ``scale``
    into the repository (``path``); a clear error when there is no such run."""
    if scale in NO_VERDICT:
        raise ValueError(f"scale {scale!r} checks code paths only: it has no verdicts to publish")
    summary = publish.finished_summary(scale, notebook)
    if summary.get("results", {}).get("claims") is None:
        raise ValueError(f"the run of {notebook!r} at scale {scale!r} itemised no claims")
    imported = publish.imported(scale, notebook)  # computed elsewhere: that host, not this one
    host = imported.get("host") if imported else platform.node()
    now = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
    return atomic_write_json(path(scale, notebook), _record(notebook, scale, summary, now, host))


def published(scale: str, notebook: str) -> dict[str, Any] | None:
    """The verdicts published for ``notebook`` at ``scale``: its ``verdicts.json``, else
    the summary inside a whole run's published archive (``qdnb.book.publish``; one that
    fails its checks gives none: the paper page names it), else ``None``."""
    p = path(scale, notebook)
    if p.exists():
        return json.loads(p.read_text())
    archive = publish.archive_path(scale, notebook)
    if not archive.exists():
        return None
    try:
        manifest, contents = publish.read_archive(archive)
    except publish.ArchiveError:
        return None
    summary = json.loads(contents["summary.json"])
    return _record(notebook, scale, summary, manifest["published_at"], manifest.get("host"))


def stale_reasons(record: dict[str, Any]) -> list[str]:
    """Why published verdicts no longer describe this code (empty: they do)."""
    run, name, scale = record["run"], record["notebook"], record["scale"]
    reasons = []
    if run.get("config_hash") != config_hash(registry.config(name, scale)):
        reasons.append("the chapter's config at this scale changed")
    if run.get("code_digest") is not None and run["code_digest"] != code_digest(name):
        reasons.append("the chapter's code changed")
    return reasons


def as_summary(record: dict[str, Any]) -> dict[str, Any]:
    """Published verdicts in the shape of a run's ``summary.json`` (what the scorecard
    reads), with ``published`` (where and when) and ``stale`` (``stale_reasons``)."""
    return {
        "notebook": record["notebook"],
        "scale": record["scale"],
        **record["run"],
        "results": {"headline": record.get("headline", ""), "claims": record.get("claims")},
        "published": {k: record.get(k) for k in ("published_at", "host")},
        "stale": stale_reasons(record),
    }
