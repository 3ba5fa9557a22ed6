"""Execute notebooks with papermill and build the book with Jupyter Book.

``python -m qdnb list | run NOTEBOOK... --scale S --seed N | book --scale S``.
Executed copies go to ``data/runs/<scale>/<notebook>/<notebook>.ipynb``, never
into ``notebooks/``.  An execution is recorded with a fingerprint of everything
it depended on (the notebook, the ``qdnb`` sources, the lock file, the scale and
the seed); ``book`` reuses an executed copy only when that fingerprint matches
and the execution succeeded, and re-executes otherwise.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path
from typing import Iterator

from qdnb.book import appendix, code_pages, pagecheck, publish, registry, scorecard
from qdnb.book.provenance import CHECKPOINT_MODES, DETERMINISTIC_FLAG
from qdnb.core import paths, sharding
from qdnb.core.config import SCALES, check_scale
from qdnb.core.io import atomic_write_bytes, atomic_write_json, load_summary
from qdnb.core.names import machine_text


class NotebookFailed(RuntimeError):
    """A notebook raised during execution; the message names it and the cell."""


def notebook_names() -> list[str]:
    """The registered chapters' notebooks present in ``notebooks/``, in book order."""
    return [c.name for c in registry.CHAPTERS if c.notebook.exists()]


def check_notebooks(names: list[str]) -> list[str]:
    valid = notebook_names()
    unknown = [n for n in names if n not in valid]
    if unknown:
        raise ValueError(
            f"unknown notebook(s) {', '.join(map(repr, unknown))}; valid notebooks: "
            f"{', '.join(valid)}"
        )
    return names


def process_id() -> int:
    """This process's rank when launched as one of several (SLURM's ``SLURM_PROCID``
    or ``JAX_PROCESS_ID``), else 0."""
    return int(os.environ.get("JAX_PROCESS_ID") or os.environ.get("SLURM_PROCID") or 0)


def executed_path(name: str, scale: str) -> Path:
    """Where the executed notebook goes: the run directory, or on a cluster, for
    processes other than 0, its ``process-<i>/`` (each process keeps its own log)."""
    rank = process_id()
    where = paths.run_dir(scale, name)
    return (where if rank == 0 else where / f"process-{rank}") / f"{name}.ipynb"


def fingerprint(name: str, scale: str, seed: int) -> str:
    """Hash of what an execution depends on: the notebook, every ``qdnb`` source
    file, the lock file, the scale, the seed and the host device count its kernel
    will ask for (a loop's rounding may depend on it)."""
    devices = sharding.plan_host_devices(dict(os.environ))[0]["requested"]
    h = hashlib.sha256(f"{name}|{scale}|{seed}".encode())
    if devices != 1:  # one device: the fingerprint it always had
        h.update(f"|host devices {devices}".encode())
    files = [registry.chapter(name).notebook, paths.ROOT / "requirements.lock"]
    files += sorted((paths.ROOT / "qdnb").rglob("*.py"))
    for f in files:
        if f.exists():
            h.update(str(f.relative_to(paths.ROOT)).encode())
            h.update(f.read_bytes())
    return h.hexdigest()


# XLA options of the kernels that execute the notebooks, per scale.  `tiny` only checks that
# every path runs, on a few episodes: it is compilation-bound (Chapter 4 compiles ten Brax
# loops), and XLA's CPU backend at optimisation level 0 compiles a Brax rollout 2.5 times
# faster (3.3 s against 8.2 s here) for code that runs slower, which `tiny` barely runs.
# `small` and `paper` keep XLA's defaults.  The flags a run used are in its summary.json.
KERNEL_XLA_FLAGS = {"tiny": "--xla_backend_optimization_level=0"}


def _kernel_path(scale: str, deterministic: bool = False) -> str:
    """A ``python3`` kernel spec that runs this very interpreter (one per scale,
    with that scale's ``KERNEL_XLA_FLAGS``, and ``DETERMINISTIC_FLAG`` when
    ``deterministic``), put first on ``JUPYTER_PATH``, so that a user-level kernel
    of another Python never runs the notebooks."""
    name = scale + ("-deterministic" if deterministic else "")
    kdir = paths.RUNS / ".jupyter" / name / "kernels" / "python3"
    env = {
        "PYTHONPATH": os.pathsep.join(filter(None, [str(paths.ROOT), os.environ.get("PYTHONPATH")]))
    }
    flags = " ".join(
        filter(
            None,
            [
                os.environ.get("XLA_FLAGS"),
                KERNEL_XLA_FLAGS.get(scale),
                DETERMINISTIC_FLAG if deterministic else None,
            ],
        )
    )
    if flags:
        env["XLA_FLAGS"] = flags
    spec = {
        "argv": [sys.executable, "-m", "ipykernel_launcher", "-f", "{connection_file}"],
        "display_name": "Python 3 (qdnb)",
        "language": "python",
        "env": env,
    }
    atomic_write_json(kdir / "kernel.json", spec)
    return str(kdir.parent.parent)


@contextlib.contextmanager
def environ(**values: str) -> Iterator[None]:
    """This process's environment variables set to ``values`` inside (the kernels it
    starts inherit them), and as they were again after."""
    before = {k: os.environ.get(k) for k in values}
    os.environ.update(values)
    try:
        yield
    finally:
        for k, v in before.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def execute(
    source: Path,
    output: Path,
    parameters: dict,
    label: str,
    progress: bool = True,
    checkpoints: str = "resume",
    deterministic: bool = False,
) -> Path:
    """Run ``source`` with papermill into ``output`` (its kernel the one of
    ``parameters["scale"]``); raise ``NotebookFailed`` naming the notebook and the
    failing cell, leaving the partly executed copy.  With ``progress``, the
    notebook's own progress bars (its loops, their rates and ETAs) stream to this
    terminal as the kernel writes them; the executed copy keeps only their last
    state (``tidy_streams``).  ``checkpoints`` is the kernel's ``QDNB_CHECKPOINTS``
    (``resume``, ``fresh`` or ``off``: see ``provenance.checkpoint_mode``);
    ``deterministic`` adds ``DETERMINISTIC_FLAG`` to the kernel's ``XLA_FLAGS``."""
    import papermill as pm

    if checkpoints not in CHECKPOINT_MODES:
        raise ValueError(
            f"checkpoints must be one of {', '.join(CHECKPOINT_MODES)}, got {checkpoints!r}"
        )
    output.parent.mkdir(parents=True, exist_ok=True)
    kernel_path = os.pathsep.join(
        filter(None, [_kernel_path(parameters["scale"], deterministic), os.getenv("JUPYTER_PATH")])
    )
    if progress:
        print(
            f"── {label} ({parameters['scale']}): executing {source.name}",
            file=sys.stderr,
            flush=True,
        )
    try:
        with environ(JUPYTER_PATH=kernel_path, QDNB_CHECKPOINTS=checkpoints):
            pm.execute_notebook(
                str(source),
                str(output),
                parameters=parameters,
                kernel_name="python3",
                cwd=str(source.parent),
                progress_bar=False,
                log_output=False,
                stderr_file=sys.stderr if progress else None,
                # the kernel's own log (its connection notices) is not the chapter's output
                extra_arguments=["--IPKernelApp.log_level=ERROR"],
            )
    except pm.PapermillExecutionError as err:
        first_line = (err.source or "").strip().splitlines()[:1]
        raise NotebookFailed(
            f"notebook {label!r} failed in cell {err.cell_index} (execution count {err.exec_count}"
            f"{', starting ' + repr(first_line[0]) if first_line else ''}): {err.ename}: "
            f"{err.evalue}\n"
            f"partly executed copy left at {output}"
        ) from None
    return output


def _last_write(line: str) -> str:
    """What a terminal shows of a line that carriage returns rewrote (progress bars)."""
    parts = [p for p in line.split("\r") if p.strip()]
    return parts[-1] if parts else ""


# A tqdm bar (``pagecheck.PROGRESS_BAR``), a cursor move of interleaved bars, and the
# checkpoint store's and the loops' divergence notices: terminal output, not the page's (the
# run's checkpoints are in its summary.json and the page's opening box; a diverged seed in
# its results and the page's own report).
_TERMINAL_ONLY = re.compile(
    pagecheck.PROGRESS_BAR.pattern + r"|\x1b\[[0-9;]*[A-Za-z]|^checkpoints: |^diverged: "
)


def page_line(line: str) -> bool:
    """Whether a line a cell wrote belongs on the page (not a progress bar or notice)."""
    return bool(line.strip()) and not _TERMINAL_ONLY.search(line)


def tidy_streams(path: Path) -> None:
    """Merge consecutive stdout/stderr outputs of each cell and drop what belongs to the
    terminal only (progress bars, in each state carriage returns rewrote, and the
    checkpoint notices: ``page_line``), dropping an output left empty; tag papermill's
    injected parameters cell ``remove-cell``."""
    import nbformat

    nb = nbformat.read(path, as_version=4)
    for cell in nb.cells:
        if cell.cell_type != "code":
            continue
        tags = cell.metadata.setdefault("tags", [])
        # the page shows the one-line scale/seed/config header instead
        if "injected-parameters" in tags and "remove-cell" not in tags:
            tags.append("remove-cell")
        merged = []
        for out in cell.outputs:
            if (
                out.output_type == "stream"
                and merged
                and merged[-1].output_type == "stream"
                and merged[-1].name == out.name
            ):
                merged[-1].text += out.text
            else:
                merged.append(out)
        kept = []
        for out in merged:
            if out.output_type == "stream":
                lines = [_last_write(line) for line in out.text.split("\n")]
                lines = [line for line in lines if page_line(line)]
                if not lines:
                    continue
                out.text = "\n".join(lines) + "\n"
            kept.append(out)
        cell.outputs = kept
    atomic_write_bytes(path, nbformat.writes(nb).encode())


_WARNING = re.compile(r"\b\w*Warning\b:|^\s*warnings\.warn\(", re.M)


def machine_paths() -> list[str]:
    """Paths of this machine that a rendered page must never show: the repository,
    the interpreter's prefix (the venv) and the home directory."""
    found = {str(paths.ROOT), sys.prefix, os.path.expanduser("~")}
    return sorted(p for p in found if len(p) > 1)


def output_problems(path: Path) -> list[str]:
    """Warnings and machine paths in the outputs of an executed notebook (what the
    book would show); empty when the page is clean."""
    import nbformat

    problems = []
    leaks = machine_paths()
    for i, cell in enumerate(nbformat.read(path, as_version=4).cells):
        for out in cell.get("outputs", []):
            texts = [out.get("text", "")] + [
                v
                for k, v in out.get("data", {}).items()
                if k.startswith("text/") and isinstance(v, str)
            ]
            for text in texts:
                warning = _WARNING.search(text) if out.get("output_type") == "stream" else None
                if warning:
                    problems.append(
                        f"cell {i}: a warning: {warning.group(0)!r}: {text.strip()[:160]!r}"
                    )
                problems += [
                    f"cell {i}: shows the machine path {leak!r}" for leak in leaks if leak in text
                ]
    return problems


def leaked_paths(html_dir: Path) -> list[str]:
    """Rendered pages that show a path of this machine (``machine_paths``)."""
    leaks = machine_paths()
    found = []
    for f in sorted(html_dir.rglob("*.html")):
        text = f.read_text(errors="ignore")
        found += [f"{f.relative_to(html_dir)}: {leak}" for leak in leaks if leak in text]
    return found


def run_notebook(
    name: str,
    scale: str,
    seed: int = 0,
    reuse: bool = False,
    progress: bool = True,
    checkpoints: str = "resume",
    deterministic: bool = False,
) -> Path:
    """Execute one notebook at ``scale``; with ``reuse``, keep an earlier execution
    whose fingerprint matches; its long loops resume from their checkpoints unless
    ``checkpoints`` says otherwise (``execute``).  Returns the executed copy."""
    check_notebooks([name])
    check_scale(scale)
    out = executed_path(name, scale)
    record_path = out.parent / "execution.json"
    fp = fingerprint(name, scale, seed) + ("-deterministic" if deterministic else "")
    if reuse and (finished_record(name, scale) or {}).get("fingerprint") == fp:
        return out
    record_path.unlink(missing_ok=True)
    (out.parent / publish.IMPORTED).unlink(missing_ok=True)  # computed here from now on
    start = time.time()
    parameters = {"scale": scale, "seed": seed}
    execute(
        registry.chapter(name).notebook, out, parameters, name, progress, checkpoints, deterministic
    )
    tidy_streams(out)
    problems = output_problems(out)
    if problems:
        raise NotebookFailed(
            f"notebook {name!r} ran, but its page would show what a reader must not see:\n  "
            + "\n  ".join(problems[:20])
            + f"\nexecuted copy left at {out}"
        )
    atomic_write_json(
        record_path,
        {
            "fingerprint": fp,
            "status": "ok",
            "seed": seed,
            "execution_wall_time_s": round(time.time() - start, 2),
        },
    )
    return out


def run_notebooks(
    names: list[str],
    scale: str,
    seed: int = 0,
    reuse: bool = False,
    progress: bool = True,
    checkpoints: str = "resume",
    deterministic: bool = False,
) -> list[Path]:
    check_notebooks(names)
    check_scale(scale)
    return [
        run_notebook(n, scale, seed, reuse, progress, checkpoints, deterministic) for n in names
    ]


def status_table(scale: str) -> str:
    """The intro's reproduction status, read from the runs' summaries: the scale this
    build was made at, the claims scorecard over every scale this machine holds a run
    of, and this build's pages (where each ran, how long it took)."""
    by_scale = scorecard.summaries()
    lines = [
        f"```{{admonition}} This build's pages ran at scale {scale}",
        f":class: {scorecard.ADMONITION_CLASS[scale]}",
        f"`{scale}`: {scorecard.SCALE_MEANING[scale]}.",
        "```",
        "",
        scorecard.tally(by_scale),
        "Each claim the book checks, by scale (✓ holds, ✗ fails, — cannot show: the run "
        "could not test it; the numbers behind each verdict beneath it):",
        "",
        scorecard.scorecard(by_scale),
        f"The pages of this build (scale `{scale}`):",
        "",
        "| page | where it ran | seed | devices | wall time |",
        "|---|---|---|---|---|",
    ]
    for chapter in registry.CHAPTERS:
        name = chapter.name
        summary = load_summary(scale, name)  # this build's own run, never a published one
        link = f"[{chapter.title}](chapters/{name})"
        if not chapter.notebook.exists():
            lines.append(f"| {chapter.title} | planned, not yet in the book | — | — | — |")
        elif summary is None:
            lines.append(f"| {link} | no run record (`summary.json`) | — | — | — |")
        else:
            lines.append(
                f"| {link} | {scorecard.where(scale, name)} | {summary['seed']} | "
                f"{machine_text(summary.get('device', '—'))} | {summary['wall_time_s']:.0f} s |"
            )
    return "\n".join(lines) + "\n"


def paper_scale_page() -> str:
    """The body of "Running at paper scale": the committed dry run's report."""
    from qdnb.book import paper_page

    path = paths.ROOT / "bench" / "results" / "paper_dryrun.json"
    report = json.loads(path.read_text()) if path.exists() else None
    return paper_page.page_markdown(report, paper_page.published_rows("paper"))


def copy_mathjax(extra_dir: Path) -> None:
    """MathJax 3, served from the book itself (no CDN).

    It goes to ``book/_extra/_static/mathjax`` (``html_extra_path``), not to
    ``book/_static``, whose every ``.js`` file Jupyter Book would load on every page.
    """
    import mathjax  # the django-static-mathjax distribution

    src = Path(mathjax.__file__).parent / "static" / "mathjax" / "es5"
    dst = extra_dir / "_static" / "mathjax"
    if not (dst / "tex-chtml.js").exists():
        shutil.copytree(src, dst, dirs_exist_ok=True)


_EXTERNAL = [
    re.compile(r"<script[^>]*\ssrc=[\"'](?:https?:)?//", re.I),
    re.compile(r"<link[^>]*\shref=[\"'](?:https?:)?//[^>]*>", re.I),
    re.compile(r"<(?:img|iframe)[^>]*\ssrc=[\"'](?:https?:)?//", re.I),
    re.compile(r"url\(\s*[\"']?(?:https?:)?//", re.I),
]


def external_resources(html_dir: Path) -> list[str]:
    """Resources a rendered page would fetch from the network (scripts, styles,
    fonts, images); plain hyperlinks are allowed."""
    found = []
    for f in sorted(html_dir.rglob("*")):
        if f.suffix not in {".html", ".css"}:
            continue
        text = f.read_text(errors="ignore")
        for pattern in _EXTERNAL:
            for m in pattern.finditer(text):
                tag = m.group(0)
                if tag.lower().startswith("<link") and not re.search(
                    r"rel=[\"'](stylesheet|preload|icon|modulepreload)", tag, re.I
                ):
                    continue
                found.append(f"{f.relative_to(html_dir)}: {tag[:120]}")
    return found


def finished_record(name: str, scale: str) -> dict | None:
    """The execution record of the finished run of ``name`` at ``scale`` that this
    machine holds (computed here, or imported before), or ``None``."""
    out = executed_path(name, scale)
    record_path = out.parent / "execution.json"
    if not (out.exists() and record_path.exists()):
        return None
    record = json.loads(record_path.read_text())
    return record if record.get("status") == "ok" else None


def book_figures(nb) -> None:
    """Each figure a cell displayed with ``qdnb.plotting.show`` becomes a figure of the
    page: the cell's outputs are split so that the figure sits alone in an input-less
    cell whose MyST-NB metadata carries its caption, label and alt text (MyST-NB reads
    them per cell); the other outputs keep their order around it."""
    import nbformat

    from qdnb.plotting import FIGURE_KEY

    cells = []
    for cell in nb.cells:
        outputs = cell.get("outputs", [])
        if cell.cell_type != "code" or not any(
            FIGURE_KEY in o.get("metadata", {}) for o in outputs
        ):
            cells.append(cell)
            continue
        groups: list[tuple[dict | None, list]] = [(None, [])]
        for out in outputs:
            figure = out.get("metadata", {}).get(FIGURE_KEY)
            if figure is not None:
                groups.append((figure, [out]))
                groups.append((None, []))
            else:
                groups[-1][1].append(out)
        cell.outputs = groups[0][1]
        cells.append(cell)
        for figure, group in groups[1:]:
            if not group:
                continue
            # (a code cell with no source is not rendered at all)
            source = f"# {'figure' if figure is not None else 'output'} of the cell above"
            extra = nbformat.v4.new_code_cell(source, metadata={"tags": ["remove-input"]})
            extra.outputs = group
            if figure is not None:
                options = {"caption": figure["caption"]}
                if figure.get("name"):
                    options["name"] = figure["name"]
                extra.metadata["mystnb"] = {"figure": options, "image": {"alt": figure["alt"]}}
            cells.append(extra)
    nb.cells = cells


def copy_page(name: str, scale: str, dest: Path) -> list:
    """The executed notebook as the book's page: after its title, the "at a glance"
    box (``scorecard.chapter_box``: its claims at this scale, the scale's meaning, the
    run's seed, devices and time) and, for an imported run, ``publish.banner``; its
    cells tagged for the appendix are taken out (and returned, for ``appendix.page``),
    a link to the appendix in their place after the introduction; at its end, the files
    and ``bench/`` records behind it (``code_pages.section``)."""
    import nbformat

    source = executed_path(name, scale)
    record = publish.imported(scale, name)
    nb = nbformat.read(source, as_version=4)
    moved = appendix.split(nb)
    box = scorecard.chapter_box(name, scale, load_summary(scale, name))
    opening = [nbformat.v4.new_markdown_cell(box)]
    if record is not None:
        opening.append(nbformat.v4.new_markdown_cell(publish.banner(record)))
    # the box right under the page's title, before the chapter's introduction
    title, _, introduction = nb.cells[0].source.partition("\n")
    if title.startswith("# ") and introduction.strip():
        nb.cells[0].source = title
        opening.append(nbformat.v4.new_markdown_cell(introduction.strip("\n")))
    if moved:
        opening.append(nbformat.v4.new_markdown_cell(appendix.link(registry.chapter(name))))
    nb.cells[1:1] = opening
    nb.cells.append(nbformat.v4.new_markdown_cell(code_pages.section(name)))
    book_figures(nb)
    atomic_write_bytes(dest, nbformat.writes(nb).encode())
    return moved


def write_appendices(moved: dict[str, list], scale: str, chapters: Path) -> None:
    """Each thesis chapter's appendix page (``appendix.page``) in ``chapters``, from the
    cells its pages moved out (``moved``: by notebook name)."""
    import nbformat

    metadata = nbformat.read(registry.CHAPTERS[0].notebook, as_version=4).metadata
    for part, pages in registry.parts().items():
        sections = [(c, moved[c.name]) for c in pages if moved.get(c.name)]
        nb = appendix.page(part, sections, scale, metadata)
        book_figures(nb)
        dest = chapters / f"{registry.appendix(part)[0]}.ipynb"
        atomic_write_bytes(dest, nbformat.writes(nb).encode())


def build_book(
    scale: str,
    seed: int = 0,
    force: bool = False,
    progress: bool = True,
    checkpoints: str = "resume",
    deterministic: bool = False,
) -> Path:
    """Execute every notebook at ``scale`` (reusing matching executions unless
    ``force``), then render ``book/_build/html``.  Returns the index page."""
    check_scale(scale)
    names = notebook_names()
    for name in names:  # a published run stands in for a run this machine has not made
        archive = publish.archive_path(scale, name)
        if finished_record(name, scale) is None and archive.exists():
            publish.import_archive(archive, replace=True)
            print(f"── {name} ({scale}): imported {archive.name}", file=sys.stderr)
    run_notebooks(
        [n for n in names if publish.imported(scale, n) is None],
        scale,
        seed,
        reuse=not force,
        progress=progress,
        checkpoints=checkpoints,
        deterministic=deterministic,
    )
    if process_id() != 0:  # on a cluster, process 0 renders the book
        return executed_path(names[0], scale)
    chapters = paths.BOOK / "chapters"
    shutil.rmtree(chapters, ignore_errors=True)
    chapters.mkdir(parents=True)
    moved = {name: copy_page(name, scale, chapters / f"{name}.ipynb") for name in names}
    write_appendices(moved, scale, chapters)
    (paths.BOOK / "_status.md").write_text(status_table(scale))
    (paths.BOOK / "_paper_scale.md").write_text(paper_scale_page())
    (paths.BOOK / "_toc.yml").write_text(registry.toc())
    copy_mathjax(paths.BOOK / "_extra")
    code_pages.write_copies(names, paths.BOOK / "_extra")
    exe = Path(sys.executable).parent / "jupyter-book"
    cmd = [
        str(exe) if exe.exists() else "jupyter-book",
        "build",
        str(paths.BOOK),
        "--all",  # a fresh environment: a label that moved between pages is no duplicate
        "--keep-going",
        "-W",
    ]
    proc = subprocess.run(cmd, cwd=paths.ROOT)
    if proc.returncode != 0:
        raise RuntimeError(f"jupyter-book build failed (exit {proc.returncode}): {' '.join(cmd)}")
    html = paths.BOOK / "_build" / "html"
    leaked = leaked_paths(html)
    if leaked:
        raise RuntimeError(
            "the rendered book shows paths of this machine:\n  " + "\n  ".join(leaked[:20])
        )
    shown = pagecheck.static_problems(html)
    if shown:
        raise RuntimeError(
            "the rendered book shows what a reader must not see:\n  " + "\n  ".join(shown[:20])
        )
    external = external_resources(html)
    if external:
        raise RuntimeError(
            "the rendered book would fetch resources from the network:\n  "
            + "\n  ".join(external[:20])
        )
    return html / "index.html"


__all__ = [
    "SCALES",
    "NotebookFailed",
    "build_book",
    "run_notebook",
    "run_notebooks",
    "notebook_names",
    "check_notebooks",
    "execute",
    "fingerprint",
    "external_resources",
]
