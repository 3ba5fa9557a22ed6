"""Published runs: a finished run packed into one archive with a SHA-256 manifest,
and imported elsewhere (another machine's book, a reader without a GPU).

``publish(scale, notebook)`` packs ``data/runs/<scale>/<notebook>/`` (the executed
notebook, ``summary.json``, ``execution.json`` and the artifacts, without parameter
files and checkpoints) into ``data/published/<scale>/<notebook>/<notebook>-<scale>.tar.gz``.
``import_archive(path)`` checks the manifest (every file present, none added, every
checksum right, no path leaving the run directory) before anything is written, unpacks
into a staging directory and moves it into place in one rename, so a refused archive
leaves nothing behind.  An imported run carries ``imported.json``: the book renders it
like a local run, under a banner saying where and when it ran and that it was
imported, not computed here.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import platform
import shutil
import tarfile
import time
from pathlib import Path, PurePosixPath
from typing import Any

from qdnb.book import registry
from qdnb.core import paths
from qdnb.core.config import check_scale
from qdnb.core.io import atomic_write_json
from qdnb.core.names import machine_text

PUBLISHED = paths.DATA / "published"
MANIFEST = "manifest.json"
IMPORTED = "imported.json"
# left out of a published run: parameter files (policies, repertoires) and checkpoints
EXCLUDED_SUFFIXES = (".npz",)
EXCLUDED_DIRS = ("checkpoints",)
# what a published run says of where it ran (from its summary.json)
PROVENANCE = ("seed", "config_hash", "git_sha", "device", "devices", "xla_flags", "wall_time_s")


class ArchiveError(ValueError):
    """An archive that cannot be published or imported, and why."""


def archive_path(scale: str, notebook: str) -> Path:
    return PUBLISHED / scale / notebook / f"{notebook}-{scale}.tar.gz"


def archives(scale: str, where: Path | None = None) -> list[Path]:
    """The archives published at ``scale`` (``archive_path``'s layout), in ``where``
    (default: ``data/published/<scale>``)."""
    return sorted((where or PUBLISHED / scale).glob(f"*/*-{scale}.tar.gz"))


def sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def run_files(run_dir: Path) -> list[Path]:
    """The files of a run that a published archive carries."""
    return sorted(
        f
        for f in run_dir.rglob("*")
        if f.is_file()
        and f.suffix not in EXCLUDED_SUFFIXES
        and f.name != IMPORTED
        and not any(part in EXCLUDED_DIRS for part in f.relative_to(run_dir).parts)
    )


def finished_summary(scale: str, notebook: str) -> dict[str, Any]:
    """The ``summary.json`` of the finished run of ``notebook`` at ``scale`` (its executed
    notebook, summary and execution record there, the execution ``ok``); an
    ``ArchiveError`` saying what is missing and how to make the run otherwise."""
    check_scale(scale)
    registry.chapter(notebook)
    run_dir = paths.run_dir(scale, notebook, create=False)
    needed = [run_dir / f"{notebook}.ipynb", run_dir / "summary.json", run_dir / "execution.json"]
    command = f"`python -m qdnb run {notebook} --scale {scale}`"
    missing = [p.name for p in needed if not p.exists()]
    if missing:
        raise ArchiveError(
            f"no finished run of {notebook!r} at scale {scale!r} to publish (missing: "
            f"{', '.join(missing)}); run {command} first"
        )
    if json.loads(needed[2].read_text()).get("status") != "ok":
        raise ArchiveError(
            f"the run of {notebook!r} at scale {scale!r} did not finish; run {command} again"
        )
    return json.loads(needed[1].read_text())


def publish(scale: str, notebook: str, dest: Path | None = None) -> Path:
    """Pack the finished run of ``notebook`` at ``scale`` into one archive (by default
    ``archive_path``) and return its path."""
    summary = finished_summary(scale, notebook)
    run_dir = paths.run_dir(scale, notebook, create=False)
    files = {str(f.relative_to(run_dir).as_posix()): f.read_bytes() for f in run_files(run_dir)}
    manifest = {
        "format": 1,
        "notebook": notebook,
        "scale": scale,
        "published_at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "host": platform.node(),
        "run": {k: summary.get(k) for k in PROVENANCE},
        "files": {name: sha256(data) for name, data in files.items()},
    }
    dest = Path(dest) if dest is not None else archive_path(scale, notebook)
    dest.parent.mkdir(parents=True, exist_ok=True)
    tmp = dest.with_name(f".{dest.name}.{os.getpid()}.tmp")
    with tarfile.open(tmp, "w:gz") as tar:
        for name, data in [(MANIFEST, json.dumps(manifest, indent=2).encode())] + sorted(
            files.items()
        ):
            info = tarfile.TarInfo(name)
            info.size, info.mode, info.mtime = len(data), 0o644, 0
            tar.addfile(info, io.BytesIO(data))
    os.replace(tmp, dest)
    return dest


def read_archive(archive: Path) -> tuple[dict[str, Any], dict[str, bytes]]:
    """The manifest and files of ``archive``, every check passed; ``ArchiveError``
    otherwise."""
    try:
        tar = tarfile.open(archive, "r:gz")
    except (OSError, tarfile.TarError, EOFError) as err:  # EOFError: cut inside the gzip header
        raise ArchiveError(f"{Path(archive).name}: not a readable archive ({err})") from None
    with tar:
        contents = {}
        try:
            for member in tar.getmembers():
                path = PurePosixPath(member.name)
                if not member.isfile() or path.is_absolute() or ".." in path.parts:
                    raise ArchiveError(
                        f"{Path(archive).name}: {member.name!r} is not a plain file inside the run"
                    )
                contents[member.name] = tar.extractfile(member).read()
        except (OSError, tarfile.TarError, EOFError) as err:
            raise ArchiveError(f"{Path(archive).name}: incomplete archive ({err})") from None
    if MANIFEST not in contents:
        raise ArchiveError(f"{Path(archive).name}: no {MANIFEST}: not a published qdnb run")
    try:
        manifest = json.loads(contents.pop(MANIFEST))
        expected, notebook, scale = manifest["files"], manifest["notebook"], manifest["scale"]
    except (ValueError, KeyError, TypeError) as err:
        raise ArchiveError(f"{Path(archive).name}: unreadable {MANIFEST} ({err})") from None
    check_scale(scale)
    registry.chapter(notebook)
    missing = sorted(set(expected) - set(contents))
    added = sorted(set(contents) - set(expected))
    altered = sorted(n for n in set(expected) & set(contents) if sha256(contents[n]) != expected[n])
    problems = [
        f"{what}: {', '.join(names)}"
        for what, names in (
            ("missing", missing),
            ("not in the manifest", added),
            ("altered", altered),
        )
        if names
    ]
    if problems:
        raise ArchiveError(
            f"{Path(archive).name}: refused, it does not match its manifest ({'; '.join(problems)})"
        )
    if f"{notebook}.ipynb" not in contents or "summary.json" not in contents:
        raise ArchiveError(f"{Path(archive).name}: no executed notebook or summary.json")
    return manifest, contents


def import_archive(archive: Path, replace: bool = False) -> Path:
    """Check ``archive`` and unpack it into ``data/runs/<scale>/<notebook>/`` (all or
    nothing); an existing run there is kept unless ``replace``.  Returns the run
    directory."""
    manifest, contents = read_archive(Path(archive))
    scale, notebook = manifest["scale"], manifest["notebook"]
    target = paths.run_dir(scale, notebook, create=False)
    if target.exists() and any(target.iterdir()) and not replace:
        raise ArchiveError(
            f"a run of {notebook!r} at scale {scale!r} already exists here; import with "
            "--replace to put the published one in its place"
        )
    staging = target.with_name(f".import-{notebook}-{os.getpid()}")
    shutil.rmtree(staging, ignore_errors=True)
    try:
        for name, data in contents.items():
            path = staging / name
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_bytes(data)
        record = {k: v for k, v in manifest.items() if k != "files"}
        record["imported_at"] = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
        record["archive"] = Path(archive).name
        atomic_write_json(staging / IMPORTED, record)
        old = target.with_name(f".replaced-{notebook}-{os.getpid()}")
        if target.exists():
            os.replace(target, old)
        os.replace(staging, target)
        shutil.rmtree(old, ignore_errors=True)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return target


def imported(scale: str, notebook: str) -> dict[str, Any] | None:
    """The import record of the run of ``notebook`` at ``scale``, if it was imported."""
    path = paths.run_dir(scale, notebook, create=False) / IMPORTED
    return json.loads(path.read_text()) if path.exists() else None


def banner(record: dict[str, Any]) -> str:
    """The note an imported run's page opens with."""
    run = record.get("run", {})
    devices = run.get("devices") or {}
    device = (
        f"{devices.get('count')} x {devices.get('kind')} ({devices.get('platform')})"
        if devices
        else machine_text(run.get("device", "unknown"))
    )
    return (
        "```{admonition} A published run, imported: not computed by this build\n"
        ":class: important\n"
        f"This page shows the `{record['scale']}` run of this notebook (seed {run.get('seed')}) "
        f"computed on **{record.get('host', 'an unnamed host')}** ({device}), from commit "
        f"`{str(run.get('git_sha'))[:12]}`, published {record.get('published_at')} and "
        f"imported here {record.get('imported_at')} from `{record.get('archive')}`. Its wall "
        f"time there: {run.get('wall_time_s')} s; its XLA flags: "
        f"`{run.get('xla_flags') or 'none'}`.\n"
        "```"
    )
