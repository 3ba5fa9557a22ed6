"""``python -m qdnb dryrun``: a notebook's run at a scale, every long loop cut to its
first step(s) at that scale's shapes (``qdnb.core.dryrun``), with what the whole run
would take: hours on this machine and, where a GPU rate was measured, on one GPU;
memory against a 80 GB GPU; checkpoints against the disk.

Each notebook executes headlessly (papermill) with ``QDNB_DRYRUN`` set, its runs in
``data/dryrun/<scale>/runs`` (never the book's ``data/runs``) and no checkpoints.
A notebook that fails is reported with the cell and the error, and the others still
run.  The report goes to ``bench/results/<scale>_dryrun.json`` and the book's page
"Running at paper scale" shows it.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import time
from pathlib import Path
from typing import Any

from qdnb.book import provenance, publish, registry, runner
from qdnb.book.paper_page import (  # noqa: F401 (the report's readers, beside its writer)
    chapter_rows,
    loop_rows,
    page_markdown,
    text_table,
)
from qdnb.core import paths
from qdnb.core.config import check_scale
from qdnb.core.dryrun import ENV
from qdnb.core.io import atomic_write_json

GPU_MEMORY_BYTES = 80e9  # one H100
GPU_MACHINE_DISK_BYTES = 64 * 2**30  # the disk of the GPU machines lent to this project
# CheckpointPolicy.keep: a running loop's checkpoint folder holds two states, a finished
# loop's its final one (LoopCheckpoints.save(final=True))
CHECKPOINTS_KEPT = 2


def report_path(scale: str) -> Path:
    return paths.ROOT / "bench" / "results" / f"{scale}_dryrun.json"


def resolve(names: list[str]) -> list[str]:
    """``["all"]``: every notebook in the book's order; otherwise the names, checked
    (an unknown one is refused with the valid names)."""
    if names == ["all"]:
        return runner.notebook_names()
    return runner.check_notebooks(names)


# --- GPU rates measured on an H100 (bench/results/*h100*.json) -----------------------------


def gpu_rates(bench_dir: Path | None = None, published: Path | None = None) -> list[dict[str, Any]]:
    """The rates measured on one GPU that a loop can be projected with: which
    notebook's loops (a name fragment), what is counted (``env_step`` or ``step``), how
    many per second, and where it was measured.  A loop no rate matches has no GPU
    projection (``None``), rather than a guess.  With the book's own ``bench/results``
    (the default), or with ``published`` (a folder of runs published at paper), the
    loops of published runs count their measured time (``published_rates``)."""
    with_published = bench_dir is None or published is not None
    bench_dir = bench_dir or paths.ROOT / "bench" / "results"
    rates: list[dict[str, Any]] = []

    def load(name: str) -> dict[str, Any] | None:
        path = bench_dir / name
        return json.loads(path.read_text()) if path.exists() else None

    rollout = load("rollout_h100.json")
    if rollout:
        for row in rollout["results"]:
            rates.append(
                {
                    "notebook": "ch2_primer",
                    "match": "",
                    "per": "env_step",
                    "rate": row["qdnb_steps_per_second"],
                    "batch_env_steps": row["batch"] * row["episode_length"],
                    "source": "rollout_h100.json",
                    "what": f"Point-Maze rollouts of {row['batch']} policies (the environment "
                    "and the policies only: a lower bound on the loop's time)",
                }
            )
    probe = load("me_vs_mels_probe_h100.json")
    if probe:
        for method in ("ME-LS", "ME"):
            if method in probe:
                rates.append(
                    {
                        "notebook": "ch4_reproducibility",
                        "match": f"ant_omni {method}",  # that loop only, not ME-Sampling
                        "exact": True,
                        "per": "env_step",
                        "rate": probe[method]["steps_per_s"],
                        "source": "me_vs_mels_probe_h100.json",
                        "what": f"the whole {method} loop on Ant-Omni",
                    }
                )
    for path in sorted(bench_dir.glob("*_dryrun_gpu*.json")):  # bench/gpu_session.sh's
        gpu_run = json.loads(path.read_text())
        for notebook, nb in gpu_run.get("notebooks", {}).items():
            for loop in nb.get("loops", []):
                if loop["seconds_per_step"] > 0:
                    rates.append(
                        {
                            "notebook": notebook,
                            "match": loop["name"],
                            "exact": True,
                            "per": "gpu_step",
                            # the seconds of one step of every seed the full run holds at once
                            "rate": 1.0 / (loop["seconds_per_step"] * loop.get("memory_factor", 1)),
                            "source": path.name,
                            "what": f"the same loop's dry run on {nb['ran_on']['device']}",
                        }
                    )
    if with_published:
        rates += published_rates(where=published)  # the book's own, or those named
    qdt = load("qdt_h100_paper.json")
    if qdt:
        rates.append(
            {
                "notebook": "ch4_qdt",
                "match": "QDT(",
                "per": "step",
                "rate": 1.0 / qdt["training"]["seconds_per_step"],
                "source": "qdt_h100_paper.json",
                "what": "a QDT training step at paper settings",
            }
        )
        rates.append(
            {
                "notebook": "ch4_qdt",
                "match": "rollouts",
                "per": "step",
                "rate": 1.0 / qdt["rollout"]["cached"]["seconds_per_rollout"],
                "source": "qdt_h100_paper.json",
                "what": "the cached rollouts of every goal",
            }
        )
    return rates


def published_rates(scale: str = "paper", where: Path | None = None) -> list[dict[str, Any]]:
    """A run published at ``scale`` (``data/published``) ran its loops in full
    somewhere: each method's own wall time in its ``summary.json`` stands for that loop."""
    rates = []
    for archive in publish.archives(scale, where):
        try:
            manifest, files = publish.read_archive(archive)
        except publish.ArchiveError:
            continue  # the paper page names it as unreadable
        summary = json.loads(files.get("summary.json", b"{}"))
        for method, result in summary.get("results", {}).items():
            if isinstance(result, dict) and "wall_time_s" in result:
                rates.append(
                    {
                        "notebook": manifest["notebook"],
                        "match": method,
                        "exact": True,
                        "per": "run",
                        "seconds": result["wall_time_s"],
                        "source": archive.name,
                        "what": f"the whole loop, run in full on {summary.get('device')} "
                        f"({manifest['published_at'][:10]})",
                    }
                )
    return rates


def matching_rate(
    notebook: str, loop: dict[str, Any], rates: list[dict[str, Any]]
) -> dict[str, Any] | None:
    """The first rate of ``notebook`` whose fragment is in the loop's name and whose
    unit the loop counts; among batch sizes, the one nearest the loop's steps."""
    found = [
        r
        for r in rates
        if r["notebook"] == notebook
        and (r["match"] == loop["name"] if r.get("exact") else r["match"] in loop["name"])
        and (r["per"] != "env_step" or loop.get("env_steps_per_step"))
    ]
    if not found:
        return None
    exact = [r for r in found if r.get("exact")]  # the loop itself, measured on a GPU, first
    if exact:
        return exact[0]
    sized = [r for r in found if "batch_env_steps" in r]
    if sized:
        target = loop["env_steps_per_step"]
        return min(sized, key=lambda r: abs(math.log(r["batch_env_steps"] / target)))
    return found[0]


# --- projections -------------------------------------------------------------------------


def project(loop: dict[str, Any], rate: dict[str, Any] | None = None) -> dict[str, Any]:
    """What one recorded loop needs in the full run: hours on this machine (compile
    once, then every step at the measured rate, times the loop's repeats); hours on
    one GPU from ``rate`` (``None`` without one); bytes of its state (the carry), of its
    checkpoint (carry and outputs at full length) and of device memory (carry, outputs
    and XLA's working memory, whose per-device figure counts once per device), times the
    seeds the full run holds side by side where the dry run ran one (``memory_factor``;
    the carry and outputs by ``state_factor``, which copies sharing them leave at 1)."""
    repeats = loop.get("repeats", 1.0)
    steps = loop["full_steps"]
    per_step = loop.get("seconds_per_step")  # None: not run on this machine ("skipped")
    cpu_s = None if per_step is None else repeats * (loop.get("compile_s", 0.0) + steps * per_step)
    gpu_h = None
    if rate is not None and rate["per"] == "run":  # measured whole: compilation included
        gpu_h = rate["seconds"] / 3600
    elif rate is not None:
        if rate["per"] == "gpu_step":  # a step of all the seeds at once: repeat the rest only
            units = repeats / loop.get("memory_factor", 1.0) * steps
        else:
            units = (
                repeats * steps * (loop["env_steps_per_step"] if rate["per"] == "env_step" else 1)
            )
        gpu_h = units / rate["rate"] / 3600
    scale = loop.get("memory_factor", 1.0)  # seeds side by side, one of them run
    state = loop.get("state_factor", scale)  # (an ES generation's perturbations share it)
    carry, outputs = state * loop.get("carry_bytes", 0), state * loop.get("outputs_bytes", 0)
    device = carry + outputs + scale * loop.get("xla_temp_bytes", 0) * loop.get("devices", 1)
    if loop["kind"] == "skipped":  # XLA's CPU plan of a step this machine cannot run: not a GPU's
        device = 0
    return {
        "state_bytes": carry,
        "cpu_hours": None if cpu_s is None else cpu_s / 3600,
        "gpu_hours": gpu_h,
        "gpu_rate_source": None if rate is None else f"{rate['source']}: {rate['what']}",
        "checkpoint_bytes": carry + outputs if loop["kind"] == "scan" else 0,
        "device_bytes": device,
    }


def summarise(
    notebook: str, records: list[dict[str, Any]], rates: list[dict[str, Any]]
) -> dict[str, Any]:
    """One notebook's loops (each with its projection), its cuts and its totals."""
    loops, cuts, data, failed = [], [], [], []
    for rec in records:
        if rec["kind"] == "cut":
            cuts.append(rec)
        elif rec["kind"] == "data":
            data.append(rec)
        elif rec["kind"] == "failed":
            failed.append({"name": rec["name"], "error": rec["error"]})
        else:
            loops.append({**rec, **project(rec, matching_rate(notebook, rec, rates))})
    gpu = [loop["gpu_hours"] for loop in loops]
    cpu_hours = sum(loop["cpu_hours"] or 0.0 for loop in loops)
    # at most: every loop's final state, and the running one's earlier state beside it
    sizes = [loop["checkpoint_bytes"] for loop in loops]
    checkpoints = sum(sizes) + (CHECKPOINTS_KEPT - 1) * max(sizes, default=0)
    peak_device = max([loop["device_bytes"] for loop in loops] or [0])
    dataset_bytes = sum(d["full_bytes"] for d in data)
    totals = {
        "loops": len(loops),
        "cpu_hours": cpu_hours,
        "gpu_hours_measured": sum(g for g in gpu if g is not None),
        "loops_with_gpu_rate": sum(g is not None for g in gpu),
        "cpu_hours_without_gpu_rate": sum(
            loop["cpu_hours"] or 0.0 for loop in loops if loop["gpu_hours"] is None
        ),
        "loops_not_run_here": sum(loop["kind"] == "skipped" for loop in loops),
        "peak_rss_bytes": max([r.get("peak_rss_bytes", 0) for r in records] or [0]),
        "peak_device_bytes": peak_device,
        "fits_gpu": peak_device < GPU_MEMORY_BYTES,
        "checkpoint_bytes": checkpoints,
        "dataset_bytes": dataset_bytes,
        "fits_gpu_machine_disk": checkpoints + dataset_bytes < GPU_MACHINE_DISK_BYTES,
    }
    return {"loops": loops, "failed_loops": failed, "cuts": cuts, "data": data, "totals": totals}


def read_records(path: Path) -> list[dict[str, Any]]:
    if not path.exists():
        return []
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def dry_run_notebook(
    name: str, scale: str, seed: int, progress: bool = True, work: Path | None = None
) -> dict[str, Any]:
    """Execute ``name`` at ``scale`` as a dry run in ``work`` (default
    ``data/dryrun``); returns its records, wall time and, if it failed, the error
    (the cell and the exception)."""
    where = (work or paths.DATA / "dryrun") / scale
    records = where / name / "loops.jsonl"
    records.unlink(missing_ok=True)
    output = where / name / f"{name}.ipynb"
    start, error = time.time(), None
    try:  # the records, and the runs never in the book's data/runs
        with runner.environ(**{ENV: str(records), "QDNB_RUNS": str(where / "runs")}):
            runner.execute(
                registry.chapter(name).notebook,
                output,
                {"scale": scale, "seed": seed},
                f"dry run of {name}",
                progress,
                checkpoints="off",
            )
    except Exception as err:  # a failed cell, or a kernel that died (out of memory, say)
        error = (
            str(err)
            if isinstance(err, runner.NotebookFailed)
            else (
                f"notebook {name!r}: {type(err).__name__}: {err} (the kernel's peak memory: "
                "the last loop's peak_rss_bytes in its records)"
            )
        )
    return {
        "records": read_records(records),
        "wall_s": time.time() - start,
        "error": error,
    }


def dry_run(
    names: list[str],
    scale: str = "paper",
    seed: int = 0,
    progress: bool = True,
    out: Path | None = None,
    work: Path | None = None,
) -> dict[str, Any]:
    """Dry-run ``names`` (``["all"]``: every notebook) at ``scale``, write the report
    (merged into an existing one of the same scale, notebook by notebook) and return it."""
    check_scale(scale)
    names = resolve(names)
    out = out or report_path(scale)
    rates = gpu_rates()
    report = json.loads(out.read_text()) if out.exists() else {}
    notebooks = report.get("notebooks", {}) if report.get("scale") == scale else {}
    for name in names:
        ran = dry_run_notebook(name, scale, seed, progress, work)
        notebooks[name] = {
            "status": "failed" if ran["error"] else "ok",
            "error": ran["error"],
            "wall_s": ran["wall_s"],
            "command": f"python -m qdnb run {name} --scale {scale}",
            "ran_on": ran_on(),
            **summarise(name, ran["records"], rates),
        }
        report = write_report(out, scale, seed, notebooks)  # after each: a cut-off run keeps it
        if progress:
            t = notebooks[name]["totals"]
            print(
                f"── dry run of {name}: {notebooks[name]['status']} in {ran['wall_s']:.0f} s; "
                f"{t['loops']} loops, {t['cpu_hours']:.1f} h on this machine",
                flush=True,
            )
    return report


def ran_on() -> dict[str, Any]:
    """Where and when a dry run ran."""
    return {
        "machine": provenance.processor(),
        "cpu_count": os.cpu_count(),
        "device": provenance.device_text(),
        "git": provenance.git_sha(),
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
    }


def write_report(out: Path, scale: str, seed: int, notebooks: dict[str, Any]) -> dict[str, Any]:
    report = {
        "benchmark": f"dry run of the notebooks at {scale}",
        "scale": scale,
        "seed": seed,
        "gpu_memory_bytes": GPU_MEMORY_BYTES,
        "gpu_machine_disk_bytes": GPU_MACHINE_DISK_BYTES,
        "disk_free_bytes_here": shutil.disk_usage(paths.ROOT).free,
        "notebooks": {n: notebooks[n] for n in runner.notebook_names() if n in notebooks},
    }
    report["wall_s"] = sum(nb["wall_s"] for nb in report["notebooks"].values())
    atomic_write_json(out, report)
    return report


def resummarise(
    scale: str = "paper",
    out: Path | None = None,
    work: Path | None = None,
    names: list[str] | None = None,
) -> dict:
    """The report again from the dry run's own records (``data/dryrun``), with the GPU
    rates known now (after a GPU session, say), without running anything.  ``names``
    (default: the report's notebooks) may add notebooks the report lacks: a dry run
    stopped from outside (a session's time limit) left its loops' records but no
    report entry; such a notebook is reported ``cut off``, with the loops it reached."""
    out = out or report_path(scale)
    report = json.loads(out.read_text()) if out.exists() else None
    if report is None and not names:
        raise ValueError(f"no dry run report at {out}: run `python -m qdnb dryrun` first")
    if report is not None and report["scale"] != scale:
        raise ValueError(f"{out} is a dry run at {report['scale']}, not {scale}")
    report = report or {"scale": scale, "seed": 0, "notebooks": {}}
    rates, where = gpu_rates(), (work or paths.DATA / "dryrun") / scale
    notebooks = dict(report["notebooks"])  # the others as they are
    for name in resolve(names) if names else list(report["notebooks"]):
        records = read_records(where / name / "loops.jsonl")
        nb = report["notebooks"].get(name)
        if nb is None and records:
            nb = {
                "status": "cut off",
                "error": "stopped from outside before the notebook finished: "
                "the loops it reached are counted, the later ones are missing",
                "wall_s": 0.0,
                "command": f"python -m qdnb run {name} --scale {scale}",
                "ran_on": ran_on(),
            }
        if nb is None:
            continue
        if not records:
            raise ValueError(f"no records of {name}'s dry run under {where}")
        notebooks[name] = {**nb, **summarise(name, records, rates)}
    if not notebooks:
        raise ValueError(f"no records of {', '.join(names or [])} under {where}")
    return write_report(out, scale, report["seed"], notebooks)
