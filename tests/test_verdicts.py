"""Published verdicts: a page's claims kept in the repository, shown by every build
for a scale it did not run, with where and when, and stale once the chapter's code or
config changes; a page's own run always comes first."""

import json
import shutil

import nbformat
import pytest
from finished_runs import write_run

from qdnb.book import publish, registry, scorecard, verdicts
from qdnb.core import claims, paths
from qdnb.core.config import config_hash


def finished_run(scale="small", name="ch2_primer", **changes):
    """A finished run of ``name`` at ``scale`` as this code would leave it."""
    fields = {
        "device": "cpu: 2 cores",
        "wall_time_s": 612.0,
        "config_hash": config_hash(registry.config(name, scale)),
        "code_digest": verdicts.code_digest(name),
        "results": {
            "headline": "NS reaches the goal",
            "claims": [claims.record("ch2/ns", "NS reaches the goal", True, "2/2 seeds")],
        },
        **changes,
    }
    return write_run(scale, name, **fields)


def test_the_code_of_a_verdict_is_what_computes_not_what_presents():
    files = {str(f.relative_to(paths.ROOT)) for f in verdicts.computation_files("ch4_qdt")}
    assert "notebooks/ch4_qdt.ipynb" in files and "qdnb/chapters/ch4_qdt/experiment.py" in files
    assert "qdnb/qd/map_elites.py" in files  # imported through the chapter's algorithms
    assert not [f for f in files if f.startswith(("qdnb/book/", "qdnb/plotting/"))]
    assert "qdnb/models/lenia/flow_lenia.py" not in files  # another chapter's


def test_the_digest_follows_the_notebooks_code_cells_not_its_prose(tmp_path, monkeypatch):
    shutil.copy(registry.chapter("ch2_primer").notebook, tmp_path / "ch2_primer.ipynb")
    monkeypatch.setattr(paths, "NOTEBOOKS", tmp_path)
    before = verdicts.code_digest("ch2_primer")
    nb = nbformat.read(tmp_path / "ch2_primer.ipynb", as_version=4)
    markdown = next(c for c in nb.cells if c.cell_type == "markdown")
    markdown.source += "\n\nA sentence more."
    nbformat.write(nb, tmp_path / "ch2_primer.ipynb")
    assert verdicts.code_digest("ch2_primer") == before
    code = next(c for c in nb.cells if c.cell_type == "code")
    code.source += "\nx = 1"
    nbformat.write(nb, tmp_path / "ch2_primer.ipynb")
    assert verdicts.code_digest("ch2_primer") != before


def test_published_verdicts_show_in_a_build_that_did_not_run_the_scale(runs):
    finished_run()
    path = verdicts.publish_verdicts("small", "ch2_primer")
    assert path == publish.PUBLISHED / "small" / "ch2_primer" / "verdicts.json"
    record = json.loads(path.read_text())
    assert record["claims"][0]["claim"] == "NS reaches the goal" and record["run"]["seed"] == 0
    assert "ipynb" not in json.dumps(record)  # the verdicts, not the notebook
    shutil.rmtree(runs / "small")  # another machine: no small run, the repository's verdicts
    by_scale = scorecard.summaries()
    shown = by_scale["small"]["ch2_primer"]
    assert shown["published"]["host"] and shown["stale"] == []
    table = scorecard.scorecard(by_scale)
    (row,) = [line for line in table.splitlines() if "NS reaches the goal" in line]
    assert scorecard.SYMBOL["holds"] in row and "published run" in row and "`01234567`" in row
    assert "stale" not in row
    assert "1 of them from verdicts published in the repository" in scorecard.tally(by_scale)


def test_a_verdict_is_stale_once_the_config_or_code_changes_and_a_run_here_comes_first(
    runs, monkeypatch
):
    finished_run(config_hash="an older config")
    verdicts.publish_verdicts("small", "ch2_primer")
    finished_run(name="ch3_evolution", code_digest="an older code")
    verdicts.publish_verdicts("small", "ch3_evolution")
    finished_run(name="ch4_qdt", code_digest=None)  # from before digests were recorded
    verdicts.publish_verdicts("small", "ch4_qdt")
    shutil.rmtree(runs / "small")
    by_scale = scorecard.summaries()
    assert by_scale["small"]["ch2_primer"]["stale"] == [
        "the chapter's config at this scale changed"
    ]
    assert by_scale["small"]["ch3_evolution"]["stale"] == ["the chapter's code changed"]
    assert by_scale["small"]["ch4_qdt"]["stale"] == []
    table = scorecard.scorecard(by_scale)
    (row,) = [
        line for line in table.splitlines() if "NS reaches the goal" in line and "QDT" in line
    ]
    assert "whether it is current cannot be told" in row and "**stale**" not in row
    (row,) = [line for line in table.splitlines() if "evolution strategies" in line]
    assert "✓\u00a0holds\u00a0(stale)" in row and "**stale**: the chapter's code changed" in row
    assert "2 stale" in scorecard.tally(by_scale)
    finished_run(results={"claims": [claims.record("ch2/ns", "NS reaches", False, "0/2")]})
    here = scorecard.summaries()["small"]["ch2_primer"]  # this machine's run comes first
    assert "published" not in here and here["results"]["claims"][0]["status"] == "fails"


def test_a_published_archive_gives_its_verdicts_too_and_a_broken_one_none(runs):
    from test_publish import fake_run

    claim = claims.record("ch2/ns", "NS reaches the goal", True, "5/5 seeds")
    fake_run("paper", results={"headline": "h", "claims": [claim]})
    archive = publish.publish("paper", "ch2_primer")
    fake_run("paper", name="ch3_qdpg", results={"headline": "before claims were itemised"})
    publish.publish("paper", "ch3_qdpg")
    shutil.rmtree(runs / "paper")
    by_scale = scorecard.summaries()
    shown = by_scale["paper"]["ch2_primer"]
    assert shown["published"]["published_at"] and shown["results"]["claims"] == [claim]
    # (fake_run's config hash is not the chapter's; its code was not recorded: no reason)
    assert shown["stale"] == ["the chapter's config at this scale changed"]
    (row,) = [r for r in scorecard.scorecard(by_scale).splitlines() if "Ch. 3: QD-PG" in r]
    assert "*no claim recorded yet*" in row and row.endswith("| ran |")  # a run, no claims
    archive.write_bytes(archive.read_bytes()[:100])  # a broken archive: the paper page names it
    assert scorecard.summaries()["paper"]["ch2_primer"] is None


def test_publishing_the_verdicts_of_a_run_that_did_not_finish_is_refused(runs):
    with pytest.raises(ValueError, match="no finished run of 'ch2_primer' at scale 'small'"):
        verdicts.publish_verdicts("small", "ch2_primer")
    d = finished_run()
    (d / "execution.json").write_text(json.dumps({"status": "failed"}))
    with pytest.raises(ValueError, match="python -m qdnb run ch2_primer --scale small"):
        verdicts.publish_verdicts("small", "ch2_primer")
    with pytest.raises(ValueError, match="unknown chapter"):
        verdicts.publish_verdicts("small", "ch9_nothing")
    finished_run(scale="tiny")
    with pytest.raises(ValueError, match="checks code paths only"):
        verdicts.publish_verdicts("tiny", "ch2_primer")
