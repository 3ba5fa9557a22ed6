"""Reading a dry run's report (``qdnb.book.dryrun_report``): the per-chapter and per-loop
tables of the book's "Running at paper scale" page, and the terminal's."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from qdnb.book import publish, registry
from qdnb.core import paths
from qdnb.core.names import machine_text, markdown_words


def gigabytes(n: float) -> str:
    return f"{n / 1e9:.3g} GB" if n >= 1e8 else f"{n / 1e6:.2g} MB"


def hours(h: float | None) -> str:
    if h is None:
        return "not measured"
    if h >= 1000:
        return f"{h:,.0f} h"
    return f"{h:.3g} h" if h >= 0.1 else f"{h * 60:.2g} min"


def book_order() -> list[str]:
    return [c.name for c in registry.CHAPTERS if c.notebook.exists()]


def in_book_order(report: dict[str, Any]) -> list[tuple[str, dict[str, Any]]]:
    return [(n, report["notebooks"][n]) for n in book_order() if n in report["notebooks"]]


def chapter_rows(report: dict[str, Any]) -> list[dict[str, str]]:
    """One row per notebook: what its run at the report's scale needs."""
    rows = []
    for name, nb in in_book_order(report):
        t = nb["totals"]
        gpu = (
            "no rate measured"
            if not t["loops_with_gpu_rate"]
            else f"{hours(t['gpu_hours_measured'])} ({t['loops_with_gpu_rate']} of "
            f"{t['loops']} loops measured)"
        )
        rows.append(
            {
                "page": registry.chapter(name).short,
                "dry run": {"ok": "ran", "cut off": "CUT OFF"}.get(nb["status"], "FAILED")
                + f", {t['loops']} loop{'' if t['loops'] == 1 else 's'}",
                "time on this CPU": hours(t["cpu_hours"])
                + (
                    f" (and {t['loops_not_run_here']} loops it cannot run)"
                    if t.get("loops_not_run_here")
                    else ""
                ),
                "time on one H100": gpu,
                "memory: device (largest loop) · host (peak) · disk": (
                    f"{gigabytes(t['peak_device_bytes'])}"
                    + ("" if t["fits_gpu"] else " (over 80 GB)")
                    + f" · {gigabytes(t['peak_rss_bytes'])}"
                    + f" · {gigabytes(t['checkpoint_bytes'] + t['dataset_bytes'])}"
                ),
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
        length = sum(loop["full_steps"] for loop in loops)
        rows.append(
            {
                "loop": markdown_words(name) + (f" (×{runs:g})" if runs != 1 else ""),
                "length": f"{length:,} {unit}{'' if length == 1 else 's'}",
                "compile · step": f"{first['compile_s']:.1f} s · "
                + (
                    "—"
                    if first.get("seconds_per_step") is None
                    else f"{first['seconds_per_step']:.3g} s"
                ),
                "this CPU": "not run here"
                if first["kind"] == "skipped"
                else hours(sum(loop["cpu_hours"] or 0.0 for loop in loops)),
                "one H100": hours(None if None in gpu else sum(gpu)),
                "memory: state · device": gigabytes(max(loop["state_bytes"] for loop in loops))
                + " · "
                + gigabytes(max(loop["device_bytes"] for loop in loops)),
            }
        )
    return rows


def published_rows(scale: str, where: Path | None = None) -> list[dict[str, str]]:
    """One row per run published at ``scale`` (``data/published``): computed in full
    elsewhere, where, when and in how long."""
    rows = []
    for archive in publish.archives(scale, where):
        try:
            manifest, _ = publish.read_archive(archive)
        except publish.ArchiveError as err:
            rows.append({"notebook": f"`{archive.parent.name}`", "ran on": f"unreadable: {err}"})
            continue
        run = manifest["run"]
        devices = run.get("devices") or {}
        rows.append(
            {
                "notebook": f"`{manifest['notebook']}`",
                "ran on": f"{devices.get('count', '?')} × {devices.get('kind', run.get('device'))}",
                "when": manifest["published_at"].replace("T", " ").rstrip("Z") + " UTC",
                "wall time": f"{run['wall_time_s']:.0f} s",
                "code": f"`{str(run.get('git_sha'))[:8]}`",
                "archive": f"`{paths.shown(archive)}`",
            }
        )
    return rows


def page_markdown(report: dict[str, Any] | None, published: list[dict[str, str]] = ()) -> str:
    """The body of the book's "Running at paper scale" page, from the report."""
    if not report or not report.get("notebooks"):
        return (
            "No dry run has been recorded yet: `python -m qdnb dryrun all` writes "
            "`bench/results/paper_dryrun.json`, which this page shows."
        )
    first = next(iter(report["notebooks"].values()))["ran_on"]
    machines = {nb["ran_on"].get("machine") for nb in report["notebooks"].values()}
    where = first.get("machine") if len(machines) == 1 else "several machines"
    missing = [n for n in book_order() if n not in report["notebooks"]]
    rows = chapter_rows(report)
    parts = [
        "## What each chapter needs",
        "",
        f"Dry run at `{report['scale']}` on {first['cpu_count']} CPU cores "
        f"({machine_text(first['device'])}, {where}); {report['wall_s'] / 60:.0f} minutes "
        "for the notebooks below (each notebook's machine, code version and date are in its "
        "section).",
        "",
        markdown_table([{k: v for k, v in r.items() if k != "command"} for r in rows]),
        "",
        "Each notebook runs alone at this scale with:",
        "",
        "```bash",
        *(r["command"].strip("`") for r in rows),
        "```",
    ]
    if missing:
        parts += ["", f"Not in this dry run yet: {', '.join(f'`{n}`' for n in missing)}."]
    if published:
        parts += [
            "",
            "## Runs made in full at this scale",
            "",
            "Computed elsewhere and published (`python -m qdnb publish`); "
            f"`make book SCALE={report['scale']}` imports each one in place of running its "
            "notebook, and its page says where and when it ran.",
            "",
            markdown_table([{k: v for k, v in r.items() if k != "archive"} for r in published]),
        ]
        archives = [r["archive"] for r in published if "archive" in r]
        if archives:
            parts += ["", "Their archives: " + ", ".join(archives) + "."]
    parts += ["", "## Loop by loop"]
    for name, nb in in_book_order(report):
        ran = nb["ran_on"]
        git = str(ran["git"])
        sha, dirty = git.removesuffix("-dirty"), git.endswith("-dirty")
        parts += [
            "",
            f"### {registry.chapter(name).title}",
            "",
            f"Ran {ran['date']} on {markdown_words(ran.get('machine', 'an unrecorded machine'))}, "
            f"commit `{sha[:8]}`{' with uncommitted changes' if dirty else ''}, "
            f"{nb['wall_s']:.0f} s.",
            "",
        ]
        if nb["error"]:  # in sight, not folded
            parts += ["```text", nb["error"].strip(), "```", ""]
        parts += ["````{admonition} Its loops, one by one", ":class: dropdown", ""]
        skipped = {
            loop["name"]: loop["reason"] for loop in nb["loops"] if loop["kind"] == "skipped"
        }
        if skipped:
            parts += [
                "Not run on this machine: "
                + "; ".join(
                    f"{markdown_words(k)}: {markdown_words(why)}" for k, why in skipped.items()
                )
                + ".",
                "",
            ]
        if nb["cuts"]:
            cut = "; ".join(
                f"{markdown_words(c['name'])}: {c['kept']:,} of {c['full']:,}" for c in nb["cuts"]
            )
            parts += [f"Counts cut: {cut}.", ""]
        parts.append(markdown_table(loop_rows(nb)))
        rates = sorted({loop["gpu_rate_source"] for loop in nb["loops"] if loop["gpu_rate_source"]})
        if rates:
            parts += ["", "GPU rates: " + "; ".join(markdown_words(r) for r in rates) + "."]
        parts += ["````"]
    return "\n".join(parts) + "\n"
