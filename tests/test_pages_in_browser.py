"""The rendered pages, checked as a reader meets them: the static checks on hand-made
HTML, the browser checks (headless Chromium through Selenium) on hand-made pages with
one fault each, and, once ``make book`` has built it, every page of the book.

The browser tests need Debian's ``chromium`` and ``chromium-driver`` (``.ci/run``
installs them when missing); without them they are skipped, saying why."""

import os
from pathlib import Path

import pytest

from qdnb.book import pagecheck
from qdnb.core import paths

PAGE = """<!DOCTYPE html><html><head><meta charset="utf-8"><style>
body {{ margin: 0; }} article.bd-article {{ width: 700px; }}
.qdnb-table {{ overflow-x: auto; max-width: 100%; }}
div.output {{ overflow-x: auto; }} .narrow {{ width: 600px; }}
</style>{head}</head><body><article class="bd-article">
<p>Prose with <span class="math">\\(x^2\\)</span> rendered.</p>
<div class="cell_output docutils container"><div class="output"><div>
{output}
</div></div></div>
</article></body></html>"""

CLEAN = (
    '<div class="qdnb-table"><table><thead><tr><th>method</th><th>value</th></tr></thead>'
    '<tbody><tr><th>ME</th><td class="num">1.5</td></tr></tbody></table></div>'
    '<div class="qdnb-table qdnb-dump"><table><tr>'
    + "<td>coverage</td>"
    * 40
    + "</tr></table></div>"
    "<p>budget: 10<sup>6</sup> steps, a price of $5, <code>num_seeds</code> = 2, "
    'Ant-Omni, 0.3 ± 0.01, −24 ± 0 (thesis), <span class="math">\\(x_0\\)</span></p>'
)
FAULTS = {
    "js_error": ("<script>const a = 1; const a = 2;</script>", CLEAN, "a JavaScript error"),
    "broken_image": ("", CLEAN + '<img src="missing.png" alt="x">', "a broken image"),
    "wide_figure": ("", '<img style="width:900px" src="ok.png" alt="x">', "wider than the column"),
    "raw_math": ("", "<p>the thesis used $10^6$ steps</p>", "unrendered math"),
    # a table scrolling inside its box is a table wider than the column; a data dump may
    "wide_table": (
        "",
        '<div class="qdnb-table"><table><tr>' + "<td>coverage</td>" * 40 + "</tr></table></div>",
        "a table wider than the column",
    ),
    # an output narrower than the column (a cell's padding) that scrolls its table sideways
    "wide_output": (
        "",
        '</div></div><div class="output narrow"><table><tr>'
        + "<td>coverage</td>" * 12
        + "</tr></table>",
        "an output wider than the column",
    ),
    # a viewer loading its script from a CDN: the book must read offline
    "outside_request": (
        '<script src="https://cdn.example.invalid/three.min.js"></script>',
        CLEAN,
        "a request leaves the machine",
    ),
    "progress_bar": (
        "",
        "<pre>QDT(ME): 100%|██████████| 2/2 [00:08&lt;00:00,  4.46s/it]</pre>",
        "a progress bar",
    ),
}
PNG_1x1 = bytes.fromhex(
    "89504e470d0a1a0a0000000d4948445200000001000000010806000000"
    "1f15c4890000000d49444154789c6360000002000001e221bc330000000049454e44ae426082"
)


def video_tag(constant: bool = False) -> str:
    """A book video (``qdnb.plotting.video``) of a moving square, or of a still one."""
    import numpy as np

    from qdnb.plotting import video

    frames = np.full((20, 40, 60, 3), 255, np.uint8)
    for i in range(20):
        x = 0 if constant else i * 50 // 19
        frames[i, 15:25, x : x + 10] = (220, 30, 30)
    return video.video_html(video.encode(frames, fps=10), video._png(frames[-1]), "a square")


def all_faults() -> dict:
    """``FAULTS`` and a video that shows nothing (made here: it needs the encoder)."""
    return {**FAULTS, "still_video": ("", video_tag(constant=True), "is blank")}


def write_pages(tmp_path: Path, names) -> Path:
    html = tmp_path / "html"
    html.mkdir()
    (html / "ok.png").write_bytes(PNG_1x1)
    (html / "index.html").write_text(PAGE.format(head="", output=CLEAN + video_tag()))
    for name in names:
        head, output, _ = all_faults()[name]
        (html / f"{name}.html").write_text(PAGE.format(head=head, output=output))
    return html


def test_the_static_checks_find_raw_math_pandas_indices_cut_cells_and_bars(tmp_path):
    html = write_pages(tmp_path, ["raw_math", "progress_bar"])
    (html / "pandas.html").write_text(
        PAGE.format(
            head="",
            output='<table border="1" class="dataframe"><tbody><tr><th>0</th><td>QD-PG reaches '
            "the goal with 10x fewer...</td></tr></tbody></table>",
        )
    )
    (html / "styler.html").write_text(
        PAGE.format(head="", output='<table id="T_7d481"><tr><td>0.845</td></tr></table>')
    )
    (html / "words.html").write_text(
        PAGE.format(
            head="",
            output="<p>set num_seeds to 4 (ant_omni): 1.2 ± 0.0, 5.25e+05 steps on a 32x32 "
            "grid (a 10·10⁶ step run, lr 3·10⁻⁴, Conv-3x3 stays)</p><figcaption>Loss. "
            "<strong>Degenerate at this scale:</strong> panel 1 is a constant image (0). "
            "(no reason given)</figcaption>",
        )
    )
    # a stray closing tag does not end the reading of the page
    text = pagecheck.reader_text(
        '<article class="bd-article"><p>a</p></span><p>num_seeds</p><code>x_y</code></article>'
    )
    assert "num_seeds" in text and "x_y" not in text
    outputs = pagecheck._Outputs()
    outputs.feed('<div class="cell_output"><p>a</p></span><p>$10^6$</p></div><p>$x^2$</p>')
    assert ["".join(o["text"]) for o in outputs.outputs] == ["a$10^6$"]
    problems = pagecheck.static_problems(html)
    assert any(
        "words.html: an identifier in the text" in p and "'num_seeds'" in p for p in problems
    )
    assert any("words.html: an identifier in the text" in p and "'ant_omni'" in p for p in problems)
    assert any("words.html: a zero spread" in p and "1.2 ± 0.0" in p for p in problems)
    assert [p.split(": ")[1] for p in problems if "not as the book writes it" in p] == [
        "a number in e-notation, not as the book writes it",
        "a size as NxN, not as the book writes it",
    ]
    assert any("words.html: a degenerate figure without a note" in p for p in problems)
    assert any("raw_math.html: raw LaTeX" in p and "$10^6$" in p for p in problems)
    assert any("progress_bar.html: a progress bar" in p for p in problems)
    assert any("pandas.html: a pandas table shows its 0, 1, 2" in p for p in problems)
    assert any("pandas.html: a table cell cut to '...'" in p for p in problems)
    assert any("styler.html: a table styled by pandas" in p for p in problems)
    assert not [p for p in problems if p.startswith("index.html")]  # the clean page


browser = pytest.mark.skipif(
    pagecheck.browser_available() is not None, reason=str(pagecheck.browser_available())
)


@browser
def test_the_browser_finds_each_fault_on_its_page_and_none_on_a_clean_one(tmp_path):
    faults = all_faults()
    html = write_pages(tmp_path, list(faults))
    problems = pagecheck.browser_problems(html)
    for name, (_, _, what) in faults.items():
        assert any(p.startswith(f"{name}.html: ") and what in p for p in problems), name
    assert not [p for p in problems if p.startswith("index.html")], problems


# The built book is checked when QDNB_BUILT_BOOK names it (`.ci/run` does, after `make book
# SCALE=tiny`): a book left by an older build is not this code's.
BUILT = Path(os.environ.get("QDNB_BUILT_BOOK", paths.BOOK / "_build" / "html"))


@browser
@pytest.mark.skipif(
    "QDNB_BUILT_BOOK" not in os.environ,
    reason="set QDNB_BUILT_BOOK=book/_build/html after `make book` (.ci/run does)",
)
def test_every_page_of_the_built_book_reads_clean_in_a_browser():
    assert (BUILT / "index.html").exists(), f"no built book at {BUILT}"
    # the intro, seven chapters, how to reproduce the book, the references
    assert len(pagecheck.pages(BUILT)) >= 10
    problems = pagecheck.static_problems(BUILT) + pagecheck.browser_problems(BUILT)
    assert problems == []
