"""The book's chapters, in reading order: one entry each.

A chapter is a notebook ``notebooks/<name>.ipynb`` and a module
``qdnb.chapters.<name>`` holding its ``Config``, its ``SCALES`` (``tiny``,
``small``, ``paper``), its ``METHODS`` and its experiment.  This registry serves
the runner (``python -m qdnb``), the book's table of contents, the status table
of the intro page and the notebook tests; adding a chapter is one entry here plus
its notebook and module.

Importing it loads no JAX: a chapter's module (and its configs) is imported only
when asked for (``Chapter.module``, ``config``).
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType

from qdnb.core import paths
from qdnb.core.config import check_scale


@dataclass(frozen=True)
class Chapter:
    name: str  # the notebook's stem and the chapter module's name
    title: str  # the page's title, its notebook's heading (the sidebar's entry)
    short: str  # the page in a few words (the scorecard's first column)
    part: str  # the thesis's chapter the page belongs to (the sidebar's group)

    @property
    def notebook(self) -> Path:
        return paths.NOTEBOOKS / f"{self.name}.ipynb"

    @property
    def module(self) -> ModuleType:
        return importlib.import_module(f"qdnb.chapters.{self.name}")

    @property
    def config_class(self) -> type:
        return self.module.Config

    def config(self, scale: str):
        """The chapter's frozen config at ``scale`` (the scale is checked before the
        chapter's module, and JAX with it, is imported)."""
        check_scale(scale)
        return self.module.SCALES[scale]


# the thesis's chapters, as its table of contents names them
BACKGROUND = "Chapters 1–2 · Introduction and background"
QDPG = "Chapter 3 · Diversity Policy Gradient for Sample Efficient QD Optimization"
QDT = "Chapter 4 · Generating Behavior-Conditioned Trajectories with Decision Transformers"
FLT = "Chapter 5 · Deep Learning for Diversity Search in Continuous Cellular Automata"

CHAPTERS: tuple[Chapter, ...] = (
    Chapter(
        "ch2_primer",
        "Chapters 1–2: the deceptive maze",
        "Ch. 1–2: the deceptive maze",
        BACKGROUND,
    ),
    Chapter(
        "ch3_qdpg",
        "Chapter 3: QD-PG — a diversity policy gradient inside MAP-Elites",
        "Ch. 3: QD-PG",
        QDPG,
    ),
    Chapter(
        "ch3_baselines",
        "Chapter 3: the policy-gradient baselines (Table 3.4)",
        "Ch. 3: policy-gradient baselines",
        QDPG,
    ),
    Chapter(
        "ch3_evolution",
        "Chapter 3: the evolutionary competitors (Table 3.3)",
        "Ch. 3: evolution strategies",
        QDPG,
    ),
    Chapter(
        "ch4_reproducibility",
        "Chapter 4: policies that do what they say — MAP-Elites Low-Spread",
        "Ch. 4: MAP-Elites Low-Spread",
        QDT,
    ),
    Chapter("ch4_qdt", "Chapter 4: the Quality-Diversity Transformer", "Ch. 4: the QDT", QDT),
    Chapter("ch5_flow_lenia", "Chapter 5: the Flow Lenia Transformer", "Ch. 5: the FLT", FLT),
)


# each thesis chapter's appendix page (``qdnb.book.appendix``): its file in the book and title
APPENDICES = {
    BACKGROUND: ("ch2_how", "How Chapters 1–2 were run"),
    QDPG: ("ch3_how", "How Chapter 3 was run"),
    QDT: ("ch4_how", "How Chapter 4 was run"),
    FLT: ("ch5_how", "How Chapter 5 was run"),
}


def appendix(part: str) -> tuple[str, str]:
    """The file stem and title of the appendix page of the thesis's chapter ``part``."""
    return APPENDICES[part]


def names() -> list[str]:
    return [c.name for c in CHAPTERS]


def chapter(name: str) -> Chapter:
    for c in CHAPTERS:
        if c.name == name:
            return c
    raise ValueError(f"unknown chapter {name!r}; valid chapters: {', '.join(names())}")


def config(name: str, scale: str):
    """The frozen config of chapter ``name`` at ``scale`` (``tiny``, ``small`` or
    ``paper``); a clear ``ValueError`` on an unknown name or scale, before any compute."""
    return chapter(name).config(scale)


def parts() -> dict[str, list[Chapter]]:
    """The pages grouped by the thesis's chapter (``Chapter.part``), in reading order."""
    grouped: dict[str, list[Chapter]] = {}
    for c in CHAPTERS:
        grouped.setdefault(c.part, []).append(c)
    return grouped


def toc() -> str:
    """The book's ``_toc.yml``: the intro, the pages grouped by the thesis's chapter
    (``Chapter.part``), each group closed by its appendix page, then how to reproduce
    the book, what the ``paper`` scale needs and the references."""
    lines = [
        "# Written by `python -m qdnb book` from qdnb.book.registry.CHAPTERS.",
        "format: jb-book",
        "root: intro",
        "parts:",
    ]
    groups = {
        part: [f"chapters/{c.name}" for c in pages] + [f"chapters/{appendix(part)[0]}"]
        for part, pages in parts().items()
    }
    groups["About this book"] = ["reproducing", "paper_scale", "references"]
    for caption, files in groups.items():
        lines += [f'  - caption: "{caption}"', "    chapters:"]
        lines += [f"      - file: {f}" for f in files]
    return "\n".join(lines) + "\n"
