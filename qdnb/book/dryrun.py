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
import platform
import shutil
import time
from pathlib import Path
from typing import Any

from qdnb.book import provenance, registry, runner
from qdnb.core import paths
from qdnb.core.config import check_scale
from qdnb.core.dryrun import ENV
from qdnb.core.io import atomic_write_json

GPU_MEMORY_BYTES = 80e9  # one H100
GPU_MACHINE_DISK_BYTES = 64 * 2**30  # the disk of the GPU machines lent to this project
CHECKPOINTS_KEPT = 2  # CheckpointPolicy.keep: a loop's checkpoint folder holds two states


def report_path(scale: str) -> Path:
    return paths.ROOT / "bench" / "results" / f"{scale}_dryrun.json"


def resolve(names: list[str]) -> list[str]:
    """``["all"]``: every notebook in the book's order; otherwise the names, checked
    (an unknown one is refused with the valid names)."""
    if names == ["all"]:
        return runner.notebook_names()
    return runner.check_notebooks(names)


# --- GPU rates measured on an H100 (bench/results/*h100*.json) -----------------------------


def gpu_rates(bench_dir: Path | None = None) -> list[dict[str, Any]]:
    """The rates measured on one GPU that a loop can be projected with: which
    notebook's loops (a name fragment), what is counted (``env_step`` or ``step``), how
    many per second, and where it was measured.  A loop no rate matches has no GPU
    projection (``None``), rather than a guess."""
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
    one GPU from ``rate`` (``None`` without one); bytes of its checkpoint (carry and
    outputs at full length) and of device memory (carry, outputs and XLA's working
    memory, whose per-device figure counts once per device), times the seeds the full
    run holds side by side where the dry run ran one (``memory_factor``)."""
    repeats = loop.get("repeats", 1.0)
    steps = loop["full_steps"]
    per_step = loop.get("seconds_per_step")  # None: not run on this machine ("skipped")
    cpu_s = None if per_step is None else repeats * (loop.get("compile_s", 0.0) + steps * per_step)
    gpu_h = None
    if rate is not None:
        if rate["per"] == "gpu_step":  # a step of all the seeds at once: repeat the rest only
            units = repeats / loop.get("memory_factor", 1.0) * steps
        else:
            units = (
                repeats * steps * (loop["env_steps_per_step"] if rate["per"] == "env_step" else 1)
            )
        gpu_h = units / rate["rate"] / 3600
    scale = loop.get("memory_factor", 1.0)  # seeds side by side, one of them run
    carry, outputs = scale * loop.get("carry_bytes", 0), scale * loop.get("outputs_bytes", 0)
    device = carry + outputs + scale * loop.get("xla_temp_bytes", 0) * loop.get("devices", 1)
    if loop["kind"] == "skipped":  # XLA's CPU plan of a step this machine cannot run: not a GPU's
        device = 0
    return {
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
    checkpoints = CHECKPOINTS_KEPT * sum(loop["checkpoint_bytes"] for loop in loops)
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
    before = {k: os.environ.get(k) for k in (ENV, "QDNB_RUNS")}
    os.environ[ENV] = str(records)
    os.environ["QDNB_RUNS"] = str(where / "runs")  # never the book's data/runs
    start, error = time.time(), None
    try:
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
    finally:
        for k, v in before.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
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
            "ran_on": {
                "machine": platform.processor() or platform.machine(),
                "cpu_count": os.cpu_count(),
                "device": provenance.device_text(),
                "git": provenance.git_sha(),
                "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
            },
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


def resummarise(scale: str = "paper", out: Path | None = None, work: Path | None = None) -> dict:
    """The report again from the dry run's own records (``data/dryrun``), with the GPU
    rates known now (after a GPU session, say), without running anything."""
    out = out or report_path(scale)
    if not out.exists():
        raise ValueError(f"no dry run report at {out}: run `python -m qdnb dryrun` first")
    report = json.loads(out.read_text())
    rates, where = gpu_rates(), (work or paths.DATA / "dryrun") / report["scale"]
    notebooks = {}
    for name, nb in report["notebooks"].items():
        records = read_records(where / name / "loops.jsonl")
        if not records:
            raise ValueError(f"no records of {name}'s dry run under {where}")
        notebooks[name] = {**nb, **summarise(name, records, rates)}
    return write_report(out, report["scale"], report["seed"], notebooks)


# --- reading the report ------------------------------------------------------------------


def gigabytes(n: float) -> str:
    return f"{n / 1e9:.3g} GB" if n >= 1e8 else f"{n / 1e6:.2g} MB"


def hours(h: float | None) -> str:
    if h is None:
        return "not measured"
    return f"{h:.3g} h" if h >= 0.1 else f"{h * 60:.2g} min"


def chapter_rows(report: dict[str, Any]) -> list[dict[str, str]]:
    """One row per notebook: what its run at the report's scale needs."""
    rows = []
    for name, nb in report["notebooks"].items():
        t = nb["totals"]
        gpu = (
            "no rate measured"
            if not t["loops_with_gpu_rate"]
            else f"{hours(t['gpu_hours_measured'])} for {t['loops_with_gpu_rate']} of "
            f"{t['loops']} loops"
        )
        rows.append(
            {
                "notebook": name,
                "dry run": "ran" if nb["status"] == "ok" else "FAILED",
                "loops": str(t["loops"]),
                "hours on this CPU": hours(t["cpu_hours"])
                + (
                    f" (and {t['loops_not_run_here']} loops it cannot run)"
                    if t.get("loops_not_run_here")
                    else ""
                ),
                "hours on one H100": gpu,
                "device memory (largest loop)": gigabytes(t["peak_device_bytes"])
                + ("" if t["fits_gpu"] else " (over 80 GB)"),
                "host memory (dry run's peak)": gigabytes(t["peak_rss_bytes"]),
                "checkpoints + datasets": gigabytes(t["checkpoint_bytes"] + t["dataset_bytes"]),
                "command": f"`{nb['command']}`",
            }
        )
    return rows


def text_table(report: dict[str, Any]) -> str:
    rows = chapter_rows(report)
    if not rows:
        return "(no notebook in the report)"
    keys = [k for k in rows[0] if k != "command"]
    width = {k: max(len(k), *(len(r[k]) for r in rows)) for k in keys}
    line = lambda r: "  ".join(r[k].ljust(width[k]) for k in keys)
    return "\n".join([line({k: k for k in keys})] + [line(r) for r in rows])


def markdown_table(rows: list[dict[str, str]]) -> str:
    if not rows:
        return ""
    keys = list(rows[0])
    cell = lambda v: str(v).replace("|", "\\|")
    lines = ["| " + " | ".join(keys) + " |", "|" + "---|" * len(keys)]
    lines += ["| " + " | ".join(cell(r[k]) for k in keys) + " |" for r in rows]
    return "\n".join(lines)


def loop_rows(nb: dict[str, Any]) -> list[dict[str, str]]:
    """One row per loop name: the calls of one loop (the episodes played for each test,
    the trainings of each dataset) summed, in the order they first ran."""
    groups: dict[str, list[dict[str, Any]]] = {}
    for loop in nb["loops"]:
        groups.setdefault(loop["name"], []).append(loop)
    rows = []
    for name, loops in groups.items():
        first, gpu = loops[0], [loop["gpu_hours"] for loop in loops]
        runs = sum(loop["repeats"] for loop in loops)
        unit = first.get("unit", "step")
        rows.append(
            {
                "loop": name + (f" (×{runs:g})" if runs != 1 else ""),
                "length": f"{sum(loop['full_steps'] for loop in loops):,} {unit}s",
                "compile": f"{first['compile_s']:.1f} s",
                "per step": "—"
                if first.get("seconds_per_step") is None
                else f"{first['seconds_per_step']:.3g} s",
                "this CPU": "not run here"
                if first["kind"] == "skipped"
                else hours(sum(loop["cpu_hours"] or 0.0 for loop in loops)),
                "one H100": hours(None if None in gpu else sum(gpu)),
                "state": gigabytes(
                    max(loop.get("carry_bytes", 0) * loop.get("memory_factor", 1) for loop in loops)
                ),
                "device": gigabytes(max(loop["device_bytes"] for loop in loops)),
            }
        )
    return rows


def page_markdown(report: dict[str, Any] | None) -> str:
    """The body of the book's "Running at paper scale" page, from the report."""
    if not report or not report.get("notebooks"):
        return (
            "No dry run has been recorded yet: `python -m qdnb dryrun all` writes "
            "`bench/results/paper_dryrun.json`, which this page shows."
        )
    first = next(iter(report["notebooks"].values()))["ran_on"]
    parts = [
        f"Dry run at `{report['scale']}` on {first['cpu_count']} CPU cores "
        f"({first['device']}), code `{first['git']}`, {first['date']}; "
        f"{report['wall_s'] / 60:.0f} minutes in all.",
        "",
        markdown_table(chapter_rows(report)),
    ]
    for name, nb in report["notebooks"].items():
        parts += ["", f"### {registry.chapter(name).title}", ""]
        if nb["error"]:
            parts += ["```text", nb["error"].strip(), "```", ""]
        skipped = {
            loop["name"]: loop["reason"] for loop in nb["loops"] if loop["kind"] == "skipped"
        }
        if skipped:
            parts += [
                "Not run on this machine: "
                + "; ".join(f"{name}: {why}" for name, why in skipped.items())
                + ".",
                "",
            ]
        if nb["cuts"]:
            cut = "; ".join(f"{c['name']}: {c['kept']:,} of {c['full']:,}" for c in nb["cuts"])
            parts += [f"Counts cut (no shape depends on them): {cut}.", ""]
        parts.append(markdown_table(loop_rows(nb)))
        rates = sorted({loop["gpu_rate_source"] for loop in nb["loops"] if loop["gpu_rate_source"]})
        if rates:
            parts += ["", "GPU rates: " + "; ".join(rates) + "."]
    return "\n".join(parts) + "\n"
