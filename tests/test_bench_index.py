"""``bench/README.md`` indexes every script and result of ``bench/``, and each chapter page
ends with the files and ``bench/`` records behind it (``qdnb.book.code_pages``), shipped
with the book."""

import re

from qdnb.book import code_pages
from qdnb.book.pagecheck import E_NOTATION, reader_text
from qdnb.book.registry import CHAPTERS
from qdnb.core import paths

BENCH = paths.ROOT / "bench"


def test_every_bench_script_has_a_row_and_every_result_a_producer():
    scripts = {r.script for r, _ in code_pages.bench_records()}
    on_disk = {
        str(p.relative_to(BENCH))
        for pattern in ("*.py", "probes/*.py", "*.sh")
        for p in BENCH.glob(pattern)
    }
    assert on_disk - scripts == set(), "scripts without a row in bench/README.md"
    assert scripts - on_disk == set(), "rows naming a script that does not exist"
    readme = code_pages.BENCH_README.read_text()
    table, _, rest = readme.partition("## Result files without a script")
    named_by_rows = set(re.findall(r"`([^`/]+\.json)`", table))
    named_elsewhere = set(re.findall(r"`([^`/]+\.json)`", rest.split("## Stale")[0]))
    for result in BENCH.joinpath("results").glob("*.json"):
        assert result.name in named_by_rows | named_elsewhere, (
            f"bench/results/{result.name}: no script's row names it, nor the list of "
            "result files without a script"
        )


def test_each_page_lists_its_chapter_code_and_the_records_naming_it():
    qdpg = code_pages.section("ch3_qdpg")
    assert qdpg.startswith("## Code behind this page")
    for file in ("ch3_qdpg/settings.py", "ch3_qdpg/methods.py", "qdpg.py", "td3.py"):
        assert f"<code>{file}</code>" in qdpg
    # the QD-PG page's budget rests on ch3_small_budget.py; no row names the primer
    assert "<code>ch3_small_budget.py</code>" in qdpg and "ch3_small_budget.json" in qdpg
    assert "ant_omni_reach.py" not in qdpg
    assert "No `bench/` record" in code_pages.section("ch2_primer")
    # the presentation layer computes nothing: it is not listed as behind a result
    assert "qdnb/book/" not in qdpg and "plotting/" not in qdpg
    # the README's plain numbers read as the book writes them (its page check refuses 1e-5)
    flt = code_pages.section("ch5_flow_lenia")
    assert "(10⁻⁵)" in flt and not E_NOTATION.search(
        reader_text(f'<article class="bd-article">{flt}')
    )


def test_every_link_of_every_page_opens_a_shipped_copy(tmp_path):
    names = [c.name for c in CHAPTERS]
    shipped = code_pages.write_copies(names, tmp_path)
    assert "qdnb/qd/qdpg.py" in shipped and "bench/results/qdt.json" in shipped
    pages = tmp_path / "chapters"  # where the chapter pages sit beside the copies
    pages.mkdir()
    for name in names:
        for href in re.findall(r'href="([^"]+)"', code_pages.section(name)):
            assert (pages / href).resolve().is_file(), (name, href)
    page = (tmp_path / "code" / "qdnb" / "qd" / "qdpg.py.html").read_text()
    assert "<title>qdnb/qd/qdpg.py</title>" in page and "class QDPG" in re.sub("<[^>]+>", "", page)
