"""The book's claims scorecard and each chapter page's "at a glance" box.

Both are read from the runs' ``summary.json`` (``results["claims"]``, see
``qdnb.core.claims``): every scale this machine holds a run of, computed here or
imported from a published archive, and for a scale whose page did not run here, the
verdicts published in the repository (``qdnb.book.verdicts``), with where, when and
from which commit, marked stale when the chapter's code or config has changed since.
Nothing here computes a result.
"""

from __future__ import annotations

import html
from typing import Any

from qdnb.book import publish, registry, verdicts
from qdnb.core.claims import CANNOT_SHOW, FAILS, HOLDS
from qdnb.core.config import SCALES
from qdnb.core.io import load_summary
from qdnb.core.names import machine_text, markdown_words

# what each scale is for, in a sentence (the chapter boxes and the intro)
SCALE_MEANING = {
    "tiny": "a code-path check: every loop runs a few iterations, in minutes; the numbers "
    "are not evidence, and claims are not expected to show",
    "small": "a laptop run (at most 25 minutes per notebook on 2 CPU cores), budgets, widths "
    "and spaces shrunk by the rule in the page's scale cell; claims should show qualitatively",
    "paper": "the thesis's budgets, widths and spaces; the thesis's numbers should show",
}
# (no-break spaces: a status never wraps in a narrow column)
SYMBOL = {HOLDS: "✓\u00a0holds", FAILS: "✗\u00a0fails", CANNOT_SHOW: "—\u00a0cannot\u00a0show"}
NOT_RUN = "not run"
# at tiny a check ran its code path; its numbers are no verdict, so none is printed
RAN = "ran (no verdict at\u00a0`tiny`)"
STALE = "\u00a0(stale)"


def status_text(claim: dict[str, str], scale: str, summary: dict | None = None) -> str:
    """A claim's status as a reader sees it: ✓ / ✗ / — at a scale that is evidence,
    marked stale when its published run no longer describes the code; "ran" at
    ``tiny``."""
    stale = scale not in verdicts.NO_VERDICT and (summary or {}).get("stale")
    return verdict(claim["status"], scale) + (STALE if stale else "")


def verdict(ok: bool | str, scale: str) -> str:
    """A check's verdict where a page prints one, in its text or a table: ✓ holds, ✗ fails
    or — cannot show (``ok``: a bool or a status); at ``tiny``, "ran": no verdict."""
    if scale in verdicts.NO_VERDICT:
        return RAN
    return SYMBOL[ok if isinstance(ok, str) else (HOLDS if ok else FAILS)]


def verdict_column(table, scale: str, column: str = "holds"):
    """``table`` (a DataFrame of checks) with its ``column`` of bools or statuses as a
    "verdict" column of ``verdict`` texts."""
    out = table.copy()
    texts = [verdict(v if isinstance(v, str) else bool(v), scale) for v in out[column]]
    out[column] = texts  # the book's tables show a cell's `code` spans as code
    return out.rename(columns={column: "verdict"})


def held_text(held: int, total: int, scale: str, noun: str = "claims") -> str:
    """The sentence over a page's table of checks: "**3/4 claims hold at scale `small`**",
    at ``tiny`` that they ran with no verdict."""
    if scale in verdicts.NO_VERDICT:
        return f"**{total} {noun} checked at scale `{scale}`**, as code paths: no verdict"
    return f"**{held}/{total} {noun} hold at scale `{scale}`**"


def summaries(scales: tuple[str, ...] = SCALES) -> dict[str, dict[str, dict | None]]:
    """``{scale: {notebook: summary or None}}`` for every registered chapter: the run on
    this machine, else the published verdicts (``verdicts.as_summary``), else ``None``."""
    out: dict[str, dict[str, dict | None]] = {}
    for s in scales:
        out[s] = {}
        for c in registry.CHAPTERS:
            summary = load_summary(s, c.name)
            if summary is None:
                record = verdicts.published(s, c.name)
                summary = verdicts.as_summary(record) if record else None
            out[s][c.name] = summary
    return out


def provenance_note(summary: dict) -> str:
    """For published verdicts: where, when, from which commit, and whether stale (or,
    for a run from before code digests were recorded, that it cannot be told)."""
    pub = summary.get("published")
    if not pub:
        return ""
    note = (
        f"published run ({markdown_words(str(pub.get('host')))}, "
        f"{str(pub.get('published_at'))[:10]}, `{str(summary.get('git_sha'))[:8]}`)"
    )
    stale = summary.get("stale") or []
    if stale:
        return note + f"; **stale**: {'; '.join(stale)}"
    if summary.get("code_digest") is None:
        return note + "; its code was not recorded: whether it is current cannot be told"
    return note


def claims_of(summary: dict | None) -> list[dict[str, str]] | None:
    """A run's claim records; ``None`` when there is no run or it predates them."""
    if summary is None:
        return None
    return summary.get("results", {}).get("claims")


def _table_text(text: str) -> str:
    """``text`` safe inside a Markdown table's cell (HTML escaped, no bare ``|``)."""
    return html.escape(text, quote=False).replace("|", "&#124;")


def _cell(claim: dict[str, str] | None, summary: dict | None, scale: str, first: bool) -> str:
    """A claim's cell at ``scale``; the first of a page's claims also says where a
    published run came from."""
    if summary is None:
        return NOT_RUN
    if claim is None:
        return "ran before claims were itemised"
    numbers = _table_text(claim["numbers"])
    note = provenance_note(summary) if first else ""
    note = f"<br>{note}" if note else ""
    status = status_text(claim, scale, summary)
    return f'{status}<br><span class="qdnb-numbers">{numbers}{note}</span>'


def where(scale: str, name: str) -> str:
    """Where a run was computed: here, or the host and date of a published run."""
    record = publish.imported(scale, name)
    if record:
        return f"published run from {record.get('host')}, {record.get('published_at')}"
    return "computed by this build"


def scorecard(by_scale: dict[str, dict[str, dict | None]]) -> str:
    """The intro's table (MyST Markdown): each claim the book checks by scale."""
    scales = list(by_scale)
    lines = [
        "| page | claim | " + " | ".join(f"`{s}`" for s in scales) + " |",
        "|---|---|" + "---|" * len(scales),
    ]
    for chapter in registry.CHAPTERS:
        runs = {s: by_scale[s].get(chapter.name) for s in scales}
        found = {s: {c["id"]: c for c in claims_of(runs[s]) or []} for s in scales}
        rows: dict[str, str] = {}  # id -> text, in the order the runs list them
        for s in scales:
            for claim_id, c in found[s].items():
                rows.setdefault(claim_id, c["claim"])
        link = f"[{chapter.short}](chapters/{chapter.name})"
        if not rows:
            lines.append(
                f"| {link} | *no claim recorded yet* | "
                + " | ".join(NOT_RUN if runs[s] is None else "ran" for s in scales)
                + " |"
            )
        for i, (claim_id, text) in enumerate(rows.items()):
            cells = [_cell(found[s].get(claim_id), runs[s], s, i == 0) for s in scales]
            page = link if i == 0 else ""  # the page once, atop its claims
            lines.append(f"| {page} | {_table_text(text)} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def tally(by_scale: dict[str, dict[str, dict | None]]) -> str:
    """One line per scale: how many claims hold, fail, cannot show; where its runs came from."""
    out = []
    for s, runs in by_scale.items():
        records = [c for r in runs.values() for c in claims_of(r) or []]
        ran = [n for n, r in runs.items() if r is not None]
        if not ran:
            out.append(f"- **`{s}`**: not run on this build's machine, none published.")
            continue
        if s in verdicts.NO_VERDICT:
            out.append(
                f"- **`{s}`** ({SCALE_MEANING[s]}): {len(records)} claim checks ran on "
                f"{len(ran)} of {len(runs)} pages; no verdict is drawn at this scale."
            )
            continue
        counts = {k: sum(c["status"] == k for c in records) for k in (HOLDS, FAILS, CANNOT_SHOW)}
        imported = [n for n in ran if publish.imported(s, n)]
        listed = [n for n in ran if runs[n].get("published")]
        stale = [n for n in listed if runs[n].get("stale")]
        sources = []
        if imported:
            sources.append(f"{len(imported)} of them from published runs imported from elsewhere")
        if listed:
            sources.append(
                f"{len(listed)} of them from verdicts published in the repository"
                + (f", {len(stale)} stale (their code or config changed since)" if stale else "")
            )
        origin = "; " + "; ".join(sources) if sources else ", all computed by this build"
        # (agreeing with the total: "0 of 1 claim holds", "1 of 7 pages have")
        claims = "claim holds" if len(records) == 1 else "claims hold"
        pages = "page has" if len(runs) == 1 else "pages have"
        out.append(
            f"- **`{s}`** ({SCALE_MEANING[s]}): {counts[HOLDS]} of {len(records)} {claims}, "
            f"{counts[FAILS]} fail, {counts[CANNOT_SHOW]} cannot show; {len(ran)} of "
            f"{len(runs)} {pages} results{origin}."
        )
    return "\n".join(out) + "\n"


ADMONITION_CLASS = {"tiny": "warning", "small": "note", "paper": "tip"}


def chapter_box(name: str, scale: str, summary: dict[str, Any] | None) -> str:
    """The box a chapter page opens with: its claims and their status at this page's
    scale, what the scale means, and the run's seed, devices and wall time."""
    # (an info string with backticks would not open a fence)
    title = f"At a glance: this page at scale {scale}"
    lines = [f"````{{admonition}} {title}", f":class: {ADMONITION_CLASS[scale]}"]
    if scale == "tiny":
        lines.append(
            "**Scale `tiny` is a code-path check only: the numbers on this page are not "
            "evidence.** Every loop runs a few iterations, in minutes, and the claims are not "
            "expected to show."
        )
    else:
        lines.append(f"Scale `{scale}`: {SCALE_MEANING[scale]}.")
    if summary is None:
        lines += ["", "This page has no run record (`summary.json`).", "````"]
        return "\n".join(lines)
    devices = summary.get("devices") or {}
    device = (
        f"{devices.get('count')} {devices.get('platform', '').upper()} "
        + ("device" if devices.get("count") == 1 else "devices")
        if devices
        else "unknown devices"
    )
    resumed = (summary.get("checkpoints") or {}).get("resumed") or []
    lines += [
        "",
        f"Seed {summary.get('seed')} · {device} on {machine_text(summary.get('device', '?'))} · "
        f"{summary.get('wall_time_s', 0):.0f} s"
        + (f", {len(resumed)} loop(s) resumed from checkpoints" if resumed else "")
        + f" · {where(scale, name)}, commit `{str(summary.get('git_sha', ''))[:12]}`.",
        "",
    ]
    records = claims_of(summary)
    if records is None:
        headline = summary.get("results", {}).get("headline", "")
        lines += [f"Result: {headline} (claims not itemised by this run; re-run the page)."]
    else:
        lines += ["| claim | status | numbers |", "|---|---|---|"]
        lines += [
            f"| {_table_text(c['claim'])} | {status_text(c, scale)} | {_table_text(c['numbers'])} |"
            for c in records
        ]
    lines.append("````")
    return "\n".join(lines)
