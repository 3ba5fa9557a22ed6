"""Published runs: publish then import gives back the same run, without parameter
files or checkpoints; a tampered, incomplete or foreign archive is refused with a
clear error and nothing half-unpacked; an imported run's page carries its banner."""

import io
import tarfile

import nbformat
import pytest
from finished_runs import write_run

from qdnb.book import publish, runner
from qdnb.core import paths


def fake_run(scale="tiny", name="ch2_primer", results=None):
    """A finished run as the runner leaves it, with a parameter file and checkpoints."""
    nb = nbformat.v4.new_notebook()
    nb.cells = [
        nbformat.v4.new_markdown_cell("# The title\n\nThe chapter's introduction."),
        nbformat.v4.new_code_cell("1 + 1"),
    ]
    d = write_run(
        scale,
        name,
        results or {"headline": "it ran"},
        notebook=nb,
        device="gpu: H100 x1",
        devices={"platform": "gpu", "kind": "H100", "count": 1},
        xla_flags="",
        wall_time_s=141.0,
        config_hash="abc",
    )
    (d / "repertoire_ME.npz").write_bytes(b"parameters")
    (d / "checkpoints" / "GA").mkdir(parents=True)
    (d / "checkpoints" / "GA" / "state").write_bytes(b"state")
    return d


def rewrite(archive, change):
    """The archive with its members passed through ``change(name, data) -> [(name, data)]``."""
    with tarfile.open(archive) as tar:
        members = [(m.name, tar.extractfile(m).read()) for m in tar.getmembers()]
    with tarfile.open(archive, "w:gz") as tar:
        for name, data in members:
            for new_name, new_data in change(name, data):
                info = tarfile.TarInfo(new_name)
                info.size = len(new_data)
                tar.addfile(info, io.BytesIO(new_data))


def test_publish_then_import_gives_back_the_run(runs):
    run_dir = fake_run()
    archive = publish.publish("tiny", "ch2_primer")
    assert archive == publish.archive_path("tiny", "ch2_primer")
    with tarfile.open(archive) as tar:
        names = sorted(m.name for m in tar.getmembers())
    assert names == ["ch2_primer.ipynb", "execution.json", "manifest.json", "summary.json"]
    originals = {n: (run_dir / n).read_bytes() for n in names if n != "manifest.json"}
    publish.shutil.rmtree(run_dir)
    target = publish.import_archive(archive)
    assert target == run_dir
    for name, data in originals.items():
        assert (target / name).read_bytes() == data
    record = publish.imported("tiny", "ch2_primer")
    assert record["run"]["git_sha"] == "0123456789abcdef" and record["archive"] == archive.name
    text = publish.banner(record)
    assert "imported" in text and "not computed by this build" in text and "H100" in text


def test_an_existing_run_is_kept_unless_replaced(runs):
    fake_run()
    archive = publish.publish("tiny", "ch2_primer")
    with pytest.raises(publish.ArchiveError, match="already exists"):
        publish.import_archive(archive)
    assert publish.imported("tiny", "ch2_primer") is None
    publish.import_archive(archive, replace=True)
    assert publish.imported("tiny", "ch2_primer") is not None
    assert not (runs / "tiny" / "ch2_primer" / "repertoire_ME.npz").exists()


@pytest.mark.parametrize(
    "change,message",
    [
        (lambda n, d: [(n, d + b" ")] if n == "summary.json" else [(n, d)],
         "altered: summary.json"),
        (lambda n, d: [] if n == "execution.json" else [(n, d)], "missing: execution.json"),
        (lambda n, d: [(n, d), ("extra.txt", b"x")] if n == "summary.json" else [(n, d)],
         "not in the manifest: extra.txt"),
        (lambda n, d: [("../escape.json", d)] if n == "summary.json" else [(n, d)],
         "not a plain file inside the run"),
        (lambda n, d: [] if n == "manifest.json" else [(n, d)], "no manifest.json"),
    ],
)  # fmt: skip
def test_a_tampered_or_incomplete_archive_is_refused_and_nothing_unpacked(runs, change, message):
    fake_run()
    archive = publish.publish("tiny", "ch2_primer")
    publish.shutil.rmtree(runs / "tiny" / "ch2_primer")
    rewrite(archive, change)
    with pytest.raises(publish.ArchiveError, match=message):
        publish.import_archive(archive)
    assert not any((runs / "tiny").iterdir())  # not even a staging directory


def test_a_truncated_archive_is_refused(runs):
    fake_run()
    archive = publish.publish("tiny", "ch2_primer")
    archive.write_bytes(archive.read_bytes()[: archive.stat().st_size // 2])
    with pytest.raises(publish.ArchiveError, match="incomplete|not a readable"):
        publish.import_archive(archive)


def test_nothing_to_publish_says_so(runs):
    with pytest.raises(publish.ArchiveError, match="no finished run"):
        publish.publish("tiny", "ch2_primer")
    with pytest.raises(ValueError, match="valid chapters"):
        publish.publish("tiny", "nope")


def test_an_imported_page_opens_with_its_banner_and_the_status_says_imported(runs, tmp_path):
    fake_run()
    publish.import_archive(publish.publish("tiny", "ch2_primer"), replace=True)
    page = tmp_path / "page.ipynb"
    runner.copy_page("ch2_primer", "tiny", page)
    cells = nbformat.read(page, as_version=4).cells
    assert cells[0].source == "# The title" and "At a glance" in cells[1].source
    assert "published run from" in cells[1].source
    assert "A published run, imported" in cells[2].source
    assert cells[3].source == "The chapter's introduction."
    assert "published run from" in runner.status_table("tiny")
    # a local run: its title, its box, its cells
    (runs / "tiny" / "ch2_primer" / publish.IMPORTED).unlink()
    runner.copy_page("ch2_primer", "tiny", page)
    cells = nbformat.read(page, as_version=4).cells
    assert len(cells) == 5 and "computed by this build" in cells[1].source
    # its last cell: the code behind it (qdnb.book.code_pages)
    assert cells[-1].source.startswith("## Code behind this page")


def test_the_cli_refuses_a_bad_archive_with_a_clear_error(tmp_path):
    import subprocess
    import sys

    bad = tmp_path / "run.tar.gz"
    bad.write_bytes(b"not an archive")
    proc = subprocess.run(
        [sys.executable, "-m", "qdnb", "import", str(bad)],
        cwd=paths.ROOT,
        capture_output=True,
        text=True,
    )
    assert proc.returncode == 2 and "error: run.tar.gz: not a readable archive" in proc.stderr


def test_the_paper_page_lists_published_runs_with_where_and_when(runs):
    from qdnb.book import paper_page

    assert paper_page.published_rows("tiny") == []
    fake_run()
    archive = publish.publish("tiny", "ch2_primer")
    (row,) = paper_page.published_rows("tiny")
    assert row["notebook"] == "`ch2_primer`" and row["wall time"].endswith(" s")
    assert row["when"].endswith("UTC") and archive.name in row["archive"]
    archive.write_bytes(archive.read_bytes()[:100])  # a broken archive is named, not hidden
    (row,) = paper_page.published_rows("tiny")
    assert row["ran on"].startswith("unreadable")


def test_a_published_run_gives_its_loops_their_measured_time(runs):
    from qdnb.book import dryrun_report as dryrun

    fake_run(results={"headline": "it ran", "ME": {"wall_time_s": 36.0}})
    publish.publish("tiny", "ch2_primer")
    (rate,) = dryrun.published_rates("tiny")
    assert rate["notebook"] == "ch2_primer" and rate["match"] == "ME" and "H100" in rate["what"]
    loop = {"kind": "scan", "name": "ME", "full_steps": 1000, "seconds_per_step": 1.0}
    assert dryrun.matching_rate("ch2_primer", loop, [rate]) is rate
    assert dryrun.project(loop, rate)["gpu_hours"] == pytest.approx(0.01)  # 36 s, whole
    assert dryrun.matching_rate("ch2_primer", {**loop, "name": "NS"}, [rate]) is None
