"""Each thesis chapter's appendix page, "How Chapter N was run".

A chapter's pages tell its story: the question, the environments and method, the results
against the thesis's numbers, what holds and why.  What a reader needs to trust or rerun
them but not to follow them (the settings each scale uses and the rule that shrinks them,
the sweeps and A/Bs that chose them, the runs' timing and records) is written in the same
notebook, in cells tagged ``appendix``: they run where they stand, with the page's
results, and the book shows them on the chapter's appendix page, under the page's name,
instead of on the page, which links to it.  Nothing is lost and nothing is computed twice.
"""

from __future__ import annotations

import re

import nbformat

from qdnb.book import registry

TAG = "appendix"


def split(nb) -> list:
    """Take the cells tagged ``appendix`` out of ``nb`` (in place) and return them, in
    order."""
    kept, moved = [], []
    for cell in nb.cells:
        (moved if TAG in cell.get("metadata", {}).get("tags", []) else kept).append(cell)
    nb.cells = kept
    return moved


_HEADING = re.compile(r"^(#{1,6}) ", flags=re.M)


def _demoted(cell):
    """A moved markdown cell's headings under its page's section: its top heading at
    level 3, the others kept below it."""
    levels = [len(m.group(1)) for m in _HEADING.finditer(cell.source)]
    if cell.cell_type == "markdown" and levels:
        shift = 3 - min(levels)
        cell.source = _HEADING.sub(
            lambda m: "#" * min(6, len(m.group(1)) + shift) + " ", cell.source
        )
    return cell


def link(chapter: registry.Chapter) -> str:
    """The line a page shows where its appendix material was taken out."""
    stem, title = registry.appendix(chapter.part)
    return (
        f"*The settings this scale uses and the rules that shrink them, the measurements "
        f"that chose them and the run's record are on [{title}]({stem}).*"
    )


def page(part: str, sections: list[tuple[registry.Chapter, list]], scale: str, metadata):
    """The appendix notebook of the thesis's chapter ``part``: for each of its pages that
    moved cells out, a section named after the page, then those cells."""
    stem, title = registry.appendix(part)
    nb = nbformat.v4.new_notebook(metadata=dict(metadata))
    nb.cells = [
        nbformat.v4.new_markdown_cell(
            f"# {title}\n\n"
            f"What the pages of *{part.split(' · ', 1)[-1]}* measured and decided beside "
            f"their results, in this build at scale `{scale}`: the settings each scale "
            "uses and the rule that shrinks them from the thesis's, the sweeps and A/Bs "
            "that chose them, and the runs' records. Each section is computed by the "
            "same run as its page."
        )
    ]
    for chapter, cells in sections:
        nb.cells.append(
            nbformat.v4.new_markdown_cell(
                f"## {chapter.title}\n\nComputed by the run of [its page]({chapter.name})."
            )
        )
        nb.cells += [_demoted(c) for c in cells]
    return nb
