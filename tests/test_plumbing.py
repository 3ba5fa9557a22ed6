import json
import re
import subprocess
import sys
import tomllib

import nbformat
import pytest
from notebook_runs import write_notebook

from qdnb.book import registry, runner, thesis
from qdnb.book.provenance import Run
from qdnb.core import paths
from qdnb.core.config import config_hash
from qdnb.core.io import atomic_write_json, load_arrays, save_arrays, to_jsonable

ROOT = paths.ROOT


def test_unknown_scale_or_chapter_lists_valid_names():
    with pytest.raises(ValueError, match="valid scales: tiny, small, paper"):
        registry.config("ch2_primer", "huge")
    with pytest.raises(ValueError, match="valid chapters: ch2_primer"):
        registry.config("ch9", "tiny")


def test_configs_are_frozen_and_hash_stably():
    cfg = registry.config("ch2_primer", "tiny")
    with pytest.raises(Exception):
        cfg.batch_size = 3
    assert config_hash(cfg) == config_hash(registry.config("ch2_primer", "tiny"))
    assert config_hash(cfg) != config_hash(registry.config("ch2_primer", "small"))


def test_cli_rejects_bad_names_before_running_anything():
    for args, expected in [
        (["run", "nope", "--scale", "tiny"], "valid notebooks: ch2_primer"),
        (["run", "ch2_primer", "--scale", "huge"], "valid scales: tiny, small, paper"),
        (["book", "--scale", "huge"], "valid scales"),
    ]:
        proc = subprocess.run(
            [sys.executable, "-m", "qdnb", *args], cwd=ROOT, capture_output=True, text=True
        )
        assert proc.returncode == 2, proc.stderr
        assert expected in proc.stderr
    out = subprocess.run(
        [sys.executable, "-m", "qdnb", "list"], cwd=ROOT, capture_output=True, text=True
    )
    assert "ch2_primer" in out.stdout and "tiny small paper" in out.stdout


def test_kernels_get_their_scales_xla_flags(tmp_path, monkeypatch):
    monkeypatch.delenv("XLA_FLAGS", raising=False)
    src = write_notebook(
        tmp_path / "flags.ipynb", "import os\nprint(repr(os.environ.get('XLA_FLAGS')))"
    )
    printed = {}
    for s in ("tiny", "small"):
        out = runner.execute(
            src, tmp_path / s / "flags.ipynb", {"scale": s}, "flags", progress=False
        )
        printed[s] = nbformat.read(out, as_version=4).cells[-1].outputs[0]["text"].strip()
    assert printed == {"tiny": repr(runner.KERNEL_XLA_FLAGS["tiny"]), "small": "None"}
    out = runner.execute(
        src, tmp_path / "det" / "flags.ipynb", {"scale": "small"}, "flags", False, "off", True
    )
    flags = nbformat.read(out, as_version=4).cells[-1].outputs[0]["text"].strip()
    assert flags == repr(runner.DETERMINISTIC_FLAG)


def test_a_failing_notebook_names_the_cell_and_leaves_the_partial_copy(tmp_path):
    src = write_notebook(
        tmp_path / "bad.ipynb", "print('before')", "raise RuntimeError('boom ' + scale)"
    )
    out = tmp_path / "out" / "bad.ipynb"
    with pytest.raises(runner.NotebookFailed) as err:
        runner.execute(src, out, {"scale": "small"}, "bad", progress=False)
    message = str(err.value)
    assert "'bad'" in message and "raise RuntimeError" in message and "boom small" in message
    assert out.exists()
    executed = nbformat.read(out, as_version=4)
    before = [c for c in executed.cells if c.source == "print('before')"][0]
    assert before.outputs[0]["text"] == "before\n"  # the cells before the failure ran


def test_atomic_json_and_artifacts(tmp_path):
    path = atomic_write_json(tmp_path / "a" / "x.json", {"v": float("inf"), "t": (1, 2)})
    assert json.loads(path.read_text()) == {"t": [1, 2], "v": "inf"}
    assert not [p for p in path.parent.iterdir() if p.name.endswith(".tmp")]
    import numpy as np

    save_arrays(tmp_path / "r.npz", "abc", f=np.arange(3))
    assert load_arrays(tmp_path / "r.npz", "abc")["f"].tolist() == [0, 1, 2]
    assert load_arrays(tmp_path / "r.npz", "other") is None
    assert load_arrays(tmp_path / "missing.npz", "abc") is None
    assert to_jsonable({"a": np.float32(2.5), "b": np.array([1, 2])}) == {"a": 2.5, "b": [1, 2]}


def test_a_bench_result_carries_its_provenance_and_keeps_its_own(tmp_path, monkeypatch):
    import numpy as np

    from qdnb.book.provenance import RESULT_PROVENANCE, write_result

    monkeypatch.setenv("QDNB_GIT_SHA", "abc1234")
    path = tmp_path / "r.json"
    written = write_result(path, {"question": "q", "rate": np.float32(2.5)})
    record = json.loads(path.read_text())
    assert record == written and list(record)[: len(RESULT_PROVENANCE)] == list(RESULT_PROVENANCE)
    assert record["commit"] == "abc1234" and record["rate"] == 2.5 and "jax" in record["versions"]
    assert "CPU cores" in record["device"] and record["date"].endswith("UTC")
    # a record that gives a provenance key itself keeps it when asked (a check appended to
    # a measurement); by default a rewrite records the run that wrote it
    monkeypatch.setenv("QDNB_GIT_SHA", "def5678")
    again = write_result(path, {**record, "rate": 3.0}, keep_provenance=True)
    assert again["commit"] == "abc1234" and again["date"] == record["date"]
    assert write_result(path, {**record, "rate": 3.0})["commit"] == "def5678"
    assert write_result(path, {"rate": 3.0})["commit"] == "def5678"


def test_summary_has_the_required_fields(monkeypatch, tmp_path):
    monkeypatch.delenv("QDNB_CHECKPOINTS", raising=False)
    monkeypatch.setattr(paths, "RUNS", tmp_path)
    cfg = registry.config("ch2_primer", "tiny")
    path = Run("test_nb", "tiny", 3, cfg).finish({"x": 1})
    summary = json.loads(path.read_text())
    assert path == tmp_path / "tiny" / "test_nb" / "summary.json"
    for key in [
        "notebook",
        "scale",
        "seed",
        "config",
        "config_hash",
        "versions",
        "device",
        "git_sha",
        "wall_time_s",
        "results",
        "devices",
        "deterministic_gpu_ops",
        "checkpoints",
    ]:
        assert key in summary
    assert summary["devices"]["count"] >= 1 and summary["devices"]["process_count"] == 1
    assert summary["checkpoints"] == {"mode": "resume", "resumed": [], "saves": 0, "seconds": 0.0}
    assert set(summary["versions"]) >= {"python", "jax", "jaxlib", "brax", "flax", "optax"}
    assert summary["seed"] == 3 and summary["config"]["batch_size"] == cfg.batch_size


def test_fingerprint_changes_with_scale_and_seed():
    a = runner.fingerprint("ch2_primer", "tiny", 0)
    assert a == runner.fingerprint("ch2_primer", "tiny", 0)
    assert (
        a
        != runner.fingerprint("ch2_primer", "small", 0)
        != runner.fingerprint("ch2_primer", "tiny", 1)
    )


def test_offline_check_flags_cdn_resources(tmp_path):
    (tmp_path / "a.html").write_text(
        '<script src="https://cdn.example/x.js"></script>'
        '<a href="https://example.org">fine</a>'
        '<link rel="stylesheet" href="//fonts.example/css">'
    )
    (tmp_path / "b.css").write_text("@font-face { src: url('https://fonts.example/f.woff2') }")
    found = runner.external_resources(tmp_path)
    assert len(found) == 3


def test_toc_lists_every_notebook_and_notebooks_are_clean():
    toc = (paths.BOOK / "_toc.yml").read_text()
    appendices = {stem for stem, _ in registry.APPENDICES.values()}  # written by the build
    listed = [n for n in re.findall(r"file: chapters/(\w+)", toc) if n not in appendices]
    assert listed == runner.notebook_names()
    for name in listed:
        nb = nbformat.read(paths.NOTEBOOKS / f"{name}.ipynb", as_version=4)
        params = [c for c in nb.cells if "parameters" in c.metadata.get("tags", [])]
        assert (
            len(params) == 1
            and 'scale = "tiny"' in params[0].source
            and "seed = 0" in params[0].source
        )
        assert all(not c.get("outputs") for c in nb.cells if c.cell_type == "code"), (
            f"{name} has outputs"
        )


def _lock() -> dict[str, str]:
    pins = {}
    for line in (ROOT / "requirements.lock").read_text().splitlines():
        line = line.strip()
        if line and not line.startswith("#"):
            name, version = line.split("==")
            pins[name.lower().replace("_", "-")] = version
    return pins


def test_pyproject_lock_and_environment_agree():
    lock = _lock()
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    for dep in project["dependencies"] + project["optional-dependencies"]["cuda"]:
        name, version = re.fullmatch(r"([A-Za-z0-9_.\-]+)(?:\[[^\]]+\])?==(.+)", dep).groups()
        assert lock.get(name.lower().replace("_", "-")) == version, f"{dep} does not match the lock"
    env = (ROOT / "environment.yml").read_text()
    assert "-r requirements.lock" in env and "- -e ." in env
    python = re.search(r"python=(\d+\.\d+)", env).group(1)
    assert project["requires-python"] == f">={python}"
    # any other conda package pinned in environment.yml must match the lock
    for name, version in re.findall(r"^\s*-\s*([A-Za-z0-9_\-]+)=+([\w.]+)\s*$", env, re.M):
        if name != "python":
            assert lock.get(name.lower()) == version
    for name in [
        "jax",
        "jaxlib",
        "brax",
        "flax",
        "optax",
        "papermill",
        "jupyter-book",
        "ipykernel",
        "pytest",
    ]:
        assert name in lock


def test_thesis_tables_are_transcribed():
    t34 = thesis.table("3.4")
    assert len(t34) == 36 and set(t34.environment) == {"Point-Maze", "Ant-Maze", "Ant-Trap"}
    assert t34.query("algorithm == 'QD-PG' and environment == 'Ant-Trap'")["mean"].item() == 1540
    t44 = thesis.table("4.4")
    row = t44.query(
        "method == 'QDT (PGA-ME-LS)' and environment == 'Halfcheetah-Uni' and metric == "
        "'avg_distance'"
    )
    assert abs(row["mean"].item() - 0.0734) < 1e-9  # printed x10^2
    assert (
        len(thesis.table("3.3")) == 5
        and len(thesis.table("4.5")) == 4
        and len(thesis.table("5.1")) == 11
    )
    with pytest.raises(ValueError, match="available"):
        thesis.table("9.9")
    with pytest.raises(ValueError, match="lacks"):
        thesis.comparison([{"quantity": "x"}])


def test_progress_bars_leave_the_page_and_the_rest_stays(tmp_path):
    nb = nbformat.v4.new_notebook()
    nb.cells = [nbformat.v4.new_code_cell("x")]
    nb.cells[0].outputs = [
        nbformat.v4.new_output("stream", name="stderr", text="\rGA:   0%| 0/10"),
        nbformat.v4.new_output("stream", name="stderr", text="\rGA:  50%| 5/10"),
        nbformat.v4.new_output("stream", name="stderr", text="\rGA: 100%| 10/10\n"),
        nbformat.v4.new_output("stream", name="stdout", text="done\n"),
    ]
    path = tmp_path / "nb.ipynb"
    nbformat.write(nb, path)
    runner.tidy_streams(path)
    outputs = nbformat.read(path, as_version=4).cells[0].outputs
    assert [(o.name, o.text) for o in outputs] == [("stdout", "done\n")]


def test_pages_with_warnings_or_machine_paths_are_refused(tmp_path):
    nb = nbformat.v4.new_notebook()
    nb.cells = [
        nbformat.v4.new_code_cell("x"),
        nbformat.v4.new_code_cell("y"),
        nbformat.v4.new_code_cell("z"),
    ]
    nb.cells[0].outputs = [nbformat.v4.new_output("stream", name="stderr", text="42%| 5/12\n")]
    path = tmp_path / "clean.ipynb"
    nbformat.write(nb, path)
    assert runner.output_problems(path) == []
    nb.cells[1].outputs = [
        nbformat.v4.new_output(
            "stream",
            name="stderr",
            text="/x/y.py:3: TqdmExperimentalWarning: Using tqdm.autonotebook.\n",
        )
    ]
    nb.cells[2].outputs = [
        nbformat.v4.new_output("execute_result", data={"text/plain": f"saved in {ROOT}/data/runs"})
    ]
    nbformat.write(nb, path)
    problems = runner.output_problems(path)
    # one problem per machine path the text shows: the clone's, and the home folder's too
    # when the clone lies under it (a newcomer's usual place)
    shown = [p for p in runner.machine_paths() if p in f"saved in {ROOT}/data/runs"]
    assert str(ROOT) in shown
    assert "cell 1: a warning" in problems[0]
    assert problems[1:] == [f"cell 2: shows the machine path {p!r}" for p in shown]


def test_tidying_hides_papermills_injected_cell(tmp_path):
    nb = nbformat.v4.new_notebook()
    nb.cells = [
        nbformat.v4.new_code_cell("scale = 'small'", metadata={"tags": ["injected-parameters"]})
    ]
    path = tmp_path / "nb.ipynb"
    nbformat.write(nb, path)
    runner.tidy_streams(path)
    assert "remove-cell" in nbformat.read(path, as_version=4).cells[0].metadata["tags"]


def test_panel_grid_wraps_panels_into_rows():
    import matplotlib

    matplotlib.use("Agg")
    from qdnb.plotting import panel_grid

    fig, axes = panel_grid(5, ncols=3)
    assert len(axes) == 5 and len(fig.axes) == 6 and not fig.axes[5].get_visible()
    from qdnb.plotting import COLUMN_INCHES

    assert fig.get_size_inches()[0] <= COLUMN_INCHES  # three panels wide, not five
    with pytest.raises(ValueError):
        panel_grid(0)


def test_the_notebooks_progress_bars_stream_to_the_terminal(tmp_path, capfd):
    src = write_notebook(
        tmp_path / "bars.ipynb",
        "from tqdm import tqdm\nfor _ in tqdm(range(3), desc='inner loop'):\n    pass",
    )
    out = runner.execute(
        src, tmp_path / "out" / "bars.ipynb", {"scale": "tiny"}, "bars", progress=True
    )
    assert "inner loop: 100%" in capfd.readouterr().err  # live, in the terminal
    runner.tidy_streams(out)
    assert nbformat.read(out, as_version=4).cells[-1].outputs == []  # never on the page


def test_the_page_keeps_a_cells_text_and_drops_its_bars_and_notices():
    bars = [
        "ant_omni seed 0 QDT(ME): 100%|██████████| 2/2 [00:08<00:00,  4.46s/it, loss=0.48]",
        "halfcheetah_uni seed 0 QDT(ME):   0%|          | 0/2 [00:00<?, ?it/s]",
        "ant_omni seed 0 QDT(ME-LS, 50%):   0%|          | 0/2 [00:00<?, ?it/s]\x1b[A",
        "MAP-Elites: 100%|##########| 16/16 [01:23<00:00]",
        "checkpoints: starting afresh: 23 earlier checkpoint directories of this run removed",
        "   ",
    ]
    assert not any(runner.page_line(line) for line in bars)
    for text in ("Ant-Omni: 16 cells, 50% kept", "loss | 0.48", "done in 12 s (100%)"):
        assert runner.page_line(text)


def test_a_claim_record_says_holds_fails_or_cannot_show():
    from qdnb.core import claims

    assert claims.record("x/a", "A beats B", True, "2 vs 1")["status"] == "holds"
    assert claims.record("x/a", "A beats B", False, "1 vs 2")["status"] == "fails"
    shown = claims.record("x/b", "A is faster", "cannot show", "A never reached the goal")
    assert shown == {
        "id": "x/b",
        "claim": "A is faster",
        "status": "cannot show",
        "numbers": "A never reached the goal",
    }
    assert claims.held([shown, claims.record("x/a", "A beats B", True, "")]) == 1
    with pytest.raises(ValueError, match="holds, fails, cannot show"):
        claims.record("x/a", "A beats B", "maybe", "")


def test_environ_sets_variables_inside_and_restores_them_even_on_error(monkeypatch):
    import os

    from qdnb.book.runner import environ

    monkeypatch.setenv("QDNB_TEST_KEPT", "before")
    monkeypatch.delenv("QDNB_TEST_NEW", raising=False)
    with pytest.raises(RuntimeError):
        with environ(QDNB_TEST_KEPT="inside", QDNB_TEST_NEW="new"):
            assert os.environ["QDNB_TEST_KEPT"] == "inside" and os.environ["QDNB_TEST_NEW"] == "new"
            raise RuntimeError("a kernel died")
    assert os.environ["QDNB_TEST_KEPT"] == "before" and "QDNB_TEST_NEW" not in os.environ
