"""The "Code behind this page" section: the files a chapter page's results are computed
from and the `bench/` records its settings rest on, listed at the end of the page and
shipped with the book as read-only copies a reader can open.

Nothing here is written by hand: the files are the ones a page's verdicts are digested
over (``verdicts.computation_files``: the notebook's imports, followed transitively), and
the records are the rows of ``bench/README.md`` whose "what rests on it" column names the
page's notebook or chapter module (a test keeps that index complete).
"""

from __future__ import annotations

import ast
import html
import re
import shutil
from dataclasses import dataclass
from pathlib import Path

from qdnb.book import verdicts
from qdnb.core import paths
from qdnb.core.names import number_text

# where the copies go inside the built site (``book/_extra`` is copied to its root)
FOLDER = "code"
BENCH_README = paths.ROOT / "bench" / "README.md"
# the layers a page's imports are grouped by, in reading order: (package, heading)
LAYERS = (
    ("qdnb/chapters/", "The chapter's code"),
    ("qdnb/qd/", "Quality-diversity algorithms"),
    ("qdnb/rl/", "Reinforcement-learning agents"),
    ("qdnb/models/", "Models"),
    ("qdnb/envs/", "Environments"),
    ("qdnb/nets/", "Networks"),
    ("qdnb/core/", "Loops, checkpoints and claims"),
)


@dataclass(frozen=True)
class BenchRecord:
    script: str  # relative to bench/, e.g. "qdpg.py" or "probes/ch4_tests.py"
    question: str
    results: tuple[str, ...]  # files of bench/results/ named in the row that exist
    kind: str  # "standing" or "probe"


def bench_records() -> list[tuple[BenchRecord, str]]:
    """Every row of ``bench/README.md``'s index: the record and its "what rests on it"
    cell."""
    rows = []
    for line in BENCH_README.read_text().splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) != 7 or not cells[1].startswith("`"):
            continue
        script = cells[1].strip("`")
        results = tuple(
            name
            for name in re.findall(r"`([^`/]+\.json)`", cells[3])
            if (paths.ROOT / "bench" / "results" / name).exists()
        )
        kind = "probe" if cells[6].startswith("probe") else "standing"
        rows.append((BenchRecord(script, cells[2], results, kind), cells[4]))
    return rows


def records_behind(name: str) -> list[BenchRecord]:
    """The ``bench/`` records a page's settings or text rest on: the rows whose "what
    rests on it" names its notebook or its chapter's module."""
    marks = (f"notebooks/{name}.ipynb", f"qdnb/chapters/{name}/", f"qdnb/chapters/{name}.py")
    return [record for record, rests in bench_records() if any(m in rests for m in marks)]


def files_behind(name: str) -> list[Path]:
    """The module files a page's results are computed from (its notebook's imports,
    transitively), without the packages' ``__init__`` files."""
    return [
        f for f in verdicts.computation_files(name) if f.suffix == ".py" and f.name != "__init__.py"
    ]


def summary_line(path: Path) -> str:
    """A module's docstring, its first sentence, on one line."""
    doc = ast.get_docstring(ast.parse(path.read_text())) or ""
    first = " ".join(doc.split("\n\n")[0].split())
    return re.split(r"\.\s+(?=[A-Z])", first)[0].rstrip(".")


_E_NUMBER = re.compile(r"(?<![\w.`])\d+(?:\.\d+)?[eE][+-]?\d+(?![\w.`])")
_POWER = re.compile(r"(?<![\w`])10\^(\d+)")


def _prose(text: str) -> str:
    """The README's plain-text numbers as the book writes them: 1e-5 as 10⁻⁵, 10^6 as
    10⁶."""
    text = _E_NUMBER.sub(lambda m: number_text(float(m.group(0))), text)
    return _POWER.sub(lambda m: number_text(10 ** int(m.group(1))), text)


def _copy_name(relative: str) -> str:
    """Where a repository file's copy lies under ``FOLDER``: JSON results as they are,
    source files as highlighted HTML pages."""
    return relative if relative.endswith(".json") else f"{relative}.html"


def _href(relative: str) -> str:
    """The link, from a chapter page, to the shipped copy of a repository file."""
    return f"../{FOLDER}/{_copy_name(relative)}"


def _link(relative: str, label: str | None = None) -> str:
    """An inline link to the shipped copy; a module's first docstring sentence is its
    tooltip."""
    label = html.escape(label or relative)
    tip = summary_line(paths.ROOT / relative) if relative.endswith(".py") else ""
    title = f' title="{html.escape(tip)}"' if tip else ""
    return f'<a href="{_href(relative)}"{title}><code>{label}</code></a>'


def section(name: str) -> str:
    """The page's closing "Code behind this page" section (Markdown with inline links)."""
    files = [str(f.relative_to(paths.ROOT)) for f in files_behind(name)]
    lines = [
        "## Code behind this page",
        "",
        "*The files this page's results are computed from, as this book ships them (a "
        "change to any of them marks the page's published verdicts stale), and the "
        "measurements in `bench/` its settings rest on. Each link opens a read-only copy.*",
        "",
    ]
    for prefix, heading in LAYERS:
        group = [f for f in files if f.startswith(prefix)]
        if group:
            shown = ", ".join(_link(f, f.removeprefix(prefix)) for f in group)
            lines.append(f"- **{heading}** (`{prefix}`): {shown}")
    records = records_behind(name)
    if records:
        lines += ["", "**Measurements behind its settings** (`bench/`, results in JSON):", ""]
        for r in records:
            results = ", ".join(_link(f"bench/results/{f}", f) for f in r.results) or "no file"
            lines.append(
                f"- {_link('bench/' + r.script, r.script)} ({r.kind}) → {results}: "
                f"{_prose(r.question)}"
            )
    else:
        lines += ["", "*No `bench/` record: this page's settings cite none.*"]
    return "\n".join(lines)


def shipped_files(names: list[str]) -> list[str]:
    """Every repository file the pages ``names`` link to (relative paths)."""
    found: set[str] = set()
    for name in names:
        found |= {str(f.relative_to(paths.ROOT)) for f in files_behind(name)}
        for r in records_behind(name):
            found.add(f"bench/{r.script}")
            found |= {f"bench/results/{f}" for f in r.results}
    return sorted(found)


def _highlighted(relative: str) -> str:
    """A source file as a standalone HTML page: highlighted, with line numbers."""
    from pygments import highlight
    from pygments.formatters import HtmlFormatter
    from pygments.lexers import get_lexer_for_filename

    formatter = HtmlFormatter(linenos="table", cssclass="source")
    source = (paths.ROOT / relative).read_text()
    body = highlight(source, get_lexer_for_filename(relative, source), formatter)
    css = formatter.get_style_defs(".source")
    return (
        '<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8">'
        f"<title>{html.escape(relative)}</title>"
        f"<style>body{{font-family:sans-serif;margin:1.5em}}{css}"
        ".source pre{font-size:13px;line-height:1.35}</style></head><body>"
        f'<h1 style="font-size:1.1em"><code>{html.escape(relative)}</code></h1>'
        "<p>A read-only copy of the repository's file, as this book was built from it.</p>"
        f"{body}</body></html>\n"
    )


def write_copies(names: list[str], extra: Path) -> list[str]:
    """Ship the files the pages ``names`` link to under ``extra/code`` (Python files as
    highlighted HTML pages, JSON results as they are); returns their relative paths."""
    out = extra / FOLDER
    shutil.rmtree(out, ignore_errors=True)
    files = shipped_files(names)
    for relative in files:
        dest = out / _copy_name(relative)
        dest.parent.mkdir(parents=True, exist_ok=True)
        if dest.name == Path(relative).name:  # a result, as it is
            shutil.copyfile(paths.ROOT / relative, dest)
        else:
            dest.write_text(_highlighted(relative))
    return files
