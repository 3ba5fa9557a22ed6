"""Checkpoints of long loops: a loop interrupted after some chunks and started again
resumes and ends bit for bit where an uninterrupted run ends; a checkpoint cut
mid-write is skipped for the one before; checkpoints of another config, seed or code
version are never loaded; the progress bar starts where the run stopped."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from qdnb.core import checkpoint
from qdnb.core.loops import scan_in_chunks
from qdnb.qd.algorithms import run_seeds


class Stop(Exception):
    pass


def walk(carry):
    """A random walk whose carry holds a PRNG key, an array and a counter."""
    key, x, n = carry
    key, sub = jax.random.split(key)
    x = x + jax.random.normal(sub, x.shape)
    return (key, x, n + 1), {"x": x, "n": n}


START = (jax.random.PRNGKey(3), jnp.zeros(4), jnp.int32(0))


def policy(tmp_path, **kw):
    args = dict(directory=tmp_path, config_hash="abc123", seed=0, version="v1")
    args |= dict(every_chunks=1, min_seconds=0)  # save after every chunk, however short
    return checkpoint.CheckpointPolicy(**(args | kw))


@pytest.fixture(autouse=True)
def no_policy_left():
    yield
    checkpoint.activate(None)


def stop_after(k):
    def on_chunk(done):
        if on_chunk.calls == k - 1:
            raise Stop
        on_chunk.calls += 1

    on_chunk.calls = 0
    return on_chunk


def assert_same(a, b):
    leaves_a, leaves_b = jax.tree.leaves(a), jax.tree.leaves(b)
    assert len(leaves_a) == len(leaves_b)
    for x, y in zip(leaves_a, leaves_b):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


@pytest.mark.parametrize("steps,chunk", [(10, 2), (11, 3)])  # dividing, and a masked last chunk
def test_an_interrupted_loop_resumes_bit_for_bit(tmp_path, steps, chunk, capsys):
    reference = scan_in_chunks(walk, START, steps, chunk, progress=False)
    checkpoint.activate(policy(tmp_path))
    with pytest.raises(Stop):
        scan_in_chunks(walk, START, steps, chunk, "walk", progress=False, on_chunk=stop_after(2))
    checkpoint.activate(policy(tmp_path))  # a new run of the notebook
    capsys.readouterr()
    resumed = scan_in_chunks(walk, START, steps, chunk, "walk", progress=True)
    assert_same(resumed, reference)
    err = capsys.readouterr().err
    assert f"'walk' resumed at step {2 * chunk} of {steps}" in err
    assert checkpoint.resumed() == [{"loop": "walk", "step": 2 * chunk}]  # for summary.json
    assert f"{2 * chunk}/{steps}" in err  # the progress bar starts where the run stopped
    kept = sorted(p.name for p in next(tmp_path.iterdir()).iterdir() if p.name.isdigit())
    assert kept == [str(steps)]  # the finished loop's final state only
    assert checkpoint.cost()["saves"] >= 1 and checkpoint.cost()["seconds"] > 0


def test_a_finished_loop_is_restored_without_running(tmp_path):
    checkpoint.activate(policy(tmp_path))
    first = scan_in_chunks(walk, START, 6, 2, "walk", progress=False)
    checkpoint.activate(policy(tmp_path))
    calls = []
    again = scan_in_chunks(walk, START, 6, 2, "walk", progress=False, on_chunk=calls.append)
    assert_same(again, first) and calls == []
    # a finished loop keeps its final state only, where a running one keeps two
    assert sorted(d.name for d in next(tmp_path.iterdir()).iterdir() if d.name.isdigit()) == ["6"]


def test_a_loop_that_stopped_early_resumes_stopped(tmp_path):
    """A loop its stop rule ended saves its last checkpoint there; started again, it
    replays the restored outputs through the rule and runs nothing more."""
    stop = lambda outs: bool(np.asarray(outs["n"]).max() >= 3)
    checkpoint.activate(policy(tmp_path))
    first = scan_in_chunks(walk, START, 10, 2, "walk", progress=False, stop=stop)
    assert first[1]["n"].tolist() == [0, 1, 2, 3]
    checkpoint.activate(policy(tmp_path))
    calls = []
    again = scan_in_chunks(
        walk, START, 10, 2, "walk", progress=False, on_chunk=calls.append, stop=stop
    )
    assert_same(again, first) and calls == []


def test_a_checkpoint_cut_mid_write_is_skipped_for_the_previous_one(tmp_path, capsys):
    reference = scan_in_chunks(walk, START, 10, 2, progress=False)
    checkpoint.activate(policy(tmp_path))
    with pytest.raises(Stop):
        scan_in_chunks(walk, START, 10, 2, "walk", progress=False, on_chunk=stop_after(3))
    loop_dir = next(tmp_path.iterdir())
    for f in (loop_dir / "6" / "state").rglob("*"):  # the latest: cut every file in half
        if f.is_file():
            f.write_bytes(f.read_bytes()[: f.stat().st_size // 2])
    checkpoint.activate(policy(tmp_path))
    capsys.readouterr()
    resumed = scan_in_chunks(walk, START, 10, 2, "walk", progress=False)
    assert_same(resumed, reference)
    err = capsys.readouterr().err
    assert "step 6 unreadable" in err and "resumed at step 4 of 10" in err


@pytest.mark.parametrize(
    "change,reason",
    [
        ({"config_hash": "fff999"}, "belongs to another config or seed"),
        ({"seed": 1}, "belongs to another config or seed"),
        ({"version": "v2"}, "written by another version 'v1' (this run: 'v2'); not loaded"),
    ],
)
def test_checkpoints_of_another_config_seed_or_version_are_never_loaded(
    tmp_path, change, reason, capsys
):
    checkpoint.activate(policy(tmp_path))
    scan_in_chunks(walk, START, 6, 2, "walk", progress=False)
    checkpoint.activate(policy(tmp_path, **change))
    capsys.readouterr()
    calls = []
    scan_in_chunks(walk, START, 6, 2, "walk", progress=False, on_chunk=calls.append)
    assert calls == [2, 4, 6]  # ran from the start
    err = capsys.readouterr().err
    assert reason in err and "resumed" not in err


def test_another_state_structure_or_length_is_never_loaded(tmp_path, capsys):
    checkpoint.activate(policy(tmp_path))
    scan_in_chunks(walk, START, 6, 2, "walk", progress=False)
    checkpoint.activate(policy(tmp_path))
    capsys.readouterr()
    other = (START[0], jnp.zeros(5), START[2])
    calls = []
    scan_in_chunks(walk, other, 6, 2, "walk", progress=False, on_chunk=calls.append)
    assert calls == [2, 4, 6] and "structure" in capsys.readouterr().err


def test_fresh_removes_this_runs_checkpoints_and_names_reused_in_order_stay_apart(tmp_path):
    checkpoint.activate(policy(tmp_path))
    a = scan_in_chunks(walk, START, 4, 2, "walk", progress=False)
    b = scan_in_chunks(walk, (jax.random.PRNGKey(9),) + START[1:], 4, 2, "walk", progress=False)
    assert sorted(p.name.split("-")[0] for p in tmp_path.iterdir()) == ["walk", "walk_1"]
    checkpoint.activate(policy(tmp_path, resume=False))
    calls = []
    again = scan_in_chunks(walk, START, 4, 2, "walk", progress=False, on_chunk=calls.append)
    assert calls == [2, 4]
    assert_same(again, a)
    assert not np.array_equal(np.asarray(a[0][1]), np.asarray(b[0][1]))


def test_a_fresh_run_clears_every_loop_of_its_own_run_at_its_start_and_no_other(tmp_path):
    checkpoint.activate(policy(tmp_path))
    scan_in_chunks(walk, START, 4, 2, "first", progress=False)
    scan_in_chunks(walk, START, 4, 2, "second", progress=False)
    checkpoint.activate(policy(tmp_path, seed=1))  # another seed's checkpoints stay
    scan_in_chunks(walk, START, 4, 2, "first", progress=False)
    checkpoint.activate(policy(tmp_path, resume=False))  # before any loop has started
    assert sorted(p.name for p in tmp_path.iterdir()) == ["first-abc123-seed1"]


def test_without_a_policy_or_a_name_nothing_is_saved_nor_for_a_short_loop(tmp_path):
    scan_in_chunks(walk, START, 4, 2, "walk", progress=False)
    checkpoint.activate(policy(tmp_path))
    scan_in_chunks(walk, START, 4, 2, None, progress=False)
    assert not tmp_path.exists() or not any(tmp_path.iterdir())
    checkpoint.activate(policy(tmp_path, min_seconds=60))  # a loop of a second is not saved
    scan_in_chunks(walk, START, 4, 2, "walk", progress=False)
    assert checkpoint.cost()["saves"] == 0


def test_bad_policies_raise():
    with pytest.raises(ValueError, match="every_chunks"):
        checkpoint.CheckpointPolicy("d", "h", 0, "v", every_chunks=0)


def interrupted_then_resumed(tmp_path, algorithm, iterations, chunk, stop):
    keys = jax.random.split(jax.random.PRNGKey(5), 2)
    run = lambda **kw: run_seeds(algorithm, keys, iterations, chunk, progress=False, **kw)
    reference = run()
    checkpoint.activate(policy(tmp_path))
    with pytest.raises(Stop):
        run(desc="loop", on_chunk=stop_after(stop))
    checkpoint.activate(policy(tmp_path))
    return reference, run(desc="loop")


def test_map_elites_resumes_bit_for_bit(tmp_path):
    from qdnb.book.registry import config
    from qdnb.chapters import ch2_primer

    cfg = config("ch2_primer", "tiny")
    env, network = ch2_primer.make_task(cfg)
    me = ch2_primer.build_algorithms(cfg, env, network)["ME"]
    reference, resumed = interrupted_then_resumed(tmp_path, me, 6, 2, stop=2)
    assert_same(resumed, reference)


def test_qdpg_with_its_replay_buffer_and_archive_resumes_bit_for_bit(tmp_path):
    from test_qdpg import small_qdpg

    from qdnb.envs import make_env

    algo = small_qdpg(make_env("pointmaze", episode_length=10))
    reference, resumed = interrupted_then_resumed(tmp_path, algo, 4, 1, stop=2)
    assert_same(resumed, reference)


def test_qdt_training_resumes_bit_for_bit(tmp_path):
    from test_qdt import T, small_qdt, trajectories

    from qdnb.models.qdt.train import fit, make_train_step
    from qdnb.nets.transformer import make_optimizer

    model = small_qdt(dropout=0.1)
    data = trajectories(jax.random.PRNGKey(10), n=6, valid_steps=(T, T, 4, 5, 2, T))
    step = make_train_step(model, make_optimizer(1e-3))
    scores = {1: 2.0, 2: 1.0, 3: 3.0, 4: 1.5}

    def evaluate(params, step_done, stop_at=None):
        if step_done == stop_at:
            raise Stop
        d = np.full(3, scores[step_done], np.float32) / 3
        return {"avg_distance": scores[step_done], "distance": d}

    def run(desc=None, stop_at=None):
        return fit(
            model, data, jax.random.PRNGKey(11), 4, 4, 1e-3, 1,
            lambda p, e: evaluate(p, e, stop_at), step=step, progress=False, desc=desc,
        )  # fmt: skip

    reference = run()
    checkpoint.activate(policy(tmp_path))
    with pytest.raises(Stop):
        run("qdt", stop_at=3)  # steps 1 and 2 saved
    checkpoint.activate(policy(tmp_path))
    resumed = run("qdt", stop_at=1)  # resumes after step 2: never evaluates step 1 again
    assert resumed.losses == reference.losses and resumed.best_step == reference.best_step == 2
    assert_same(resumed.params, reference.params)
    assert [e["step"] for e in resumed.evaluations] == [1, 2, 3, 4]
    for a, b in zip(resumed.evaluations, reference.evaluations):
        assert a["avg_distance"] == b["avg_distance"]
        np.testing.assert_array_equal(a["distance"], b["distance"])


def crash_after_saves(monkeypatch, k):
    """Make the process 'crash' right after the k-th checkpoint is written."""
    save = checkpoint.LoopCheckpoints.save
    count = []

    def saving(self, *args, **kwargs):
        save(self, *args, **kwargs)
        count.append(1)
        if len(count) == k:
            raise Stop

    monkeypatch.setattr(checkpoint.LoopCheckpoints, "save", saving)
    return lambda: monkeypatch.setattr(checkpoint.LoopCheckpoints, "save", save)


def test_flt_training_resumes_bit_for_bit(tmp_path, monkeypatch, capsys):
    import dataclasses

    from test_flt import CFG, WORLD

    from qdnb.models.lenia import flow_lenia as fl
    from qdnb.models.lenia.flt import make_model, train

    cfg = dataclasses.replace(CFG, train_steps=5)
    system = fl.sample_system(jax.random.PRNGKey(1), WORLD)
    model = make_model(WORLD, cfg)
    run = lambda: train(model, cfg, WORLD, system, jax.random.PRNGKey(2), progress=False)
    reference = run()
    checkpoint.activate(policy(tmp_path))
    restore = crash_after_saves(monkeypatch, 2)
    with pytest.raises(Stop):
        run()  # saved after steps 1 and 2
    restore()
    checkpoint.activate(policy(tmp_path))
    capsys.readouterr()
    resumed = run()
    assert "'FLT' resumed after step 2 of 5" in capsys.readouterr().err
    for name in ("params", "losses", "mean_frames", "episodes_seen", "max_drift"):
        assert_same(getattr(resumed, name), getattr(reference, name))


def test_a_run_activates_its_checkpoints_as_qdnb_checkpoints_says(monkeypatch, tmp_path):
    from qdnb.book.provenance import Run
    from qdnb.book.registry import config
    from qdnb.core import paths

    monkeypatch.setattr(paths, "RUNS", tmp_path)
    cfg = config("ch2_primer", "tiny")
    for mode, resume in (("resume", True), ("fresh", False)):
        monkeypatch.setenv("QDNB_CHECKPOINTS", mode)
        run = Run("nb", "tiny", 4, cfg)
        active = checkpoint.active()
        assert active.resume is resume and active.seed == 4
        assert active.config_hash == run.config_hash
        assert active.directory == tmp_path / "tiny" / "nb" / "checkpoints"
        run.finish({})
        assert checkpoint.active() is None
    monkeypatch.setenv("QDNB_CHECKPOINT_EVERY_CHUNKS", "7")
    monkeypatch.setenv("QDNB_CHECKPOINT_EVERY_SECONDS", "30")
    Run("nb", "tiny", 0, cfg)
    assert (checkpoint.active().every_chunks, checkpoint.active().every_seconds) == (7, 30.0)
    monkeypatch.setenv("QDNB_CHECKPOINT_EVERY_CHUNKS", "often")
    with pytest.raises(ValueError, match="QDNB_CHECKPOINT_EVERY_CHUNKS must be a number"):
        Run("nb", "tiny", 0, cfg)
    monkeypatch.delenv("QDNB_CHECKPOINT_EVERY_CHUNKS")
    monkeypatch.setenv("QDNB_CHECKPOINTS", "off")
    Run("nb", "tiny", 0, cfg)
    assert checkpoint.active() is None
    monkeypatch.setenv("QDNB_CHECKPOINTS", "sometimes")
    with pytest.raises(ValueError, match="resume, fresh, off"):
        Run("nb", "tiny", 0, cfg)


def test_the_cli_takes_one_checkpoint_flag():
    import subprocess
    import sys

    from qdnb.core.paths import ROOT

    both = [sys.executable, "-m", "qdnb", "run", "ch2_primer", "--fresh", "--resume"]
    proc = subprocess.run(both, cwd=ROOT, capture_output=True, text=True)
    assert proc.returncode == 2 and "not allowed with argument" in proc.stderr


def test_checkpoints_are_versioned_by_the_package_sources_not_the_commit(tmp_path):
    """A checkpoint's code version follows the package's Python sources only: a
    notebook or text change (a new commit) keeps it, an edited module changes it."""
    from qdnb.book.provenance import package_digest

    (tmp_path / "qd").mkdir()
    (tmp_path / "qd" / "a.py").write_text("x = 1\n")
    (tmp_path / "b.py").write_text("y = 2\n")
    before = package_digest(tmp_path)
    (tmp_path / "notes.md").write_text("text that computes nothing\n")
    assert package_digest(tmp_path) == before
    (tmp_path / "qd" / "a.py").write_text("x = 3\n")
    assert package_digest(tmp_path) != before
    (tmp_path / "qd" / "a.py").write_text("x = 1\n")
    assert package_digest(tmp_path) == before
    (tmp_path / "qd" / "a.py").rename(tmp_path / "qd" / "c.py")
    assert package_digest(tmp_path) != before  # a renamed module is another package
