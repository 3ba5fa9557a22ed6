"""The paper dry run: loops cut to their first steps at real shapes, the projection
arithmetic, the refusals, and a whole notebook's dry run at `tiny`."""

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from qdnb.book import dryrun_report as report
from qdnb.core import dryrun
from qdnb.core.loops import scan_in_chunks


@pytest.fixture
def records(tmp_path, monkeypatch):
    """A dry run in this process; returns a function reading what it recorded."""
    path = tmp_path / "loops.jsonl"
    monkeypatch.setenv(dryrun.ENV, str(path))
    read = lambda: report.read_records(path)
    read.path = path
    return read


def test_loops_meet_the_dry_run_at_one_seam(tmp_path, monkeypatch):
    """``driver()``: outside a dry run the loop, the one-shot calls and the seeds run as
    given; inside, a loop runs its first steps at full-length shapes, and seeds side by
    side run as one (spread to all) unless all of them would be quick."""
    monkeypatch.delenv(dryrun.ENV, raising=False)
    full = dryrun.driver()
    assert full is dryrun.FULL_RUN and full.concurrent
    assert full.loop("loop", None, None, 5, lambda: "the loop as written") == "the loop as written"
    assert full.call("start", lambda a: a + 1, 1) == 2
    assert full.seeds("seeds", jnp.arange(3), lambda k: 2 * k, spread=None).tolist() == [0, 2, 4]

    monkeypatch.setenv(dryrun.ENV, str(tmp_path / "loops.jsonl"))
    dry = dryrun.driver()
    assert isinstance(dry, dryrun.DryRun) and not dry.concurrent
    never = lambda: pytest.fail("the full loop ran in a dry run")  # noqa: E731
    carry, out = dry.loop("count", lambda c: (c + 1, c), jnp.int32(0), 5, never)
    assert int(carry) == dryrun.KEEP_STEPS and out.shape == (5,)

    def run(keys):  # one loop per seed, side by side
        c, _ = dryrun.driver().loop("seeds", lambda c: (c + 1, c), jnp.zeros(len(keys)), 4, never)
        return c

    spread = lambda out, n: ("spread", out.shape, n)  # noqa: E731
    monkeypatch.setattr(dryrun, "ALL_SEEDS_S", 0.0)  # every step too slow for all the seeds
    assert dry.seeds("seeds", jnp.arange(3), run, spread) == ("spread", (1,), 3)
    monkeypatch.setattr(dryrun, "ALL_SEEDS_S", 1e9)  # quick: all of them, as the full run
    assert dry.seeds("seeds", jnp.arange(3), run, spread).shape == (3,)


def test_outside_a_dry_run_nothing_is_cut_or_recorded(tmp_path, monkeypatch):
    monkeypatch.delenv(dryrun.ENV, raising=False)
    assert dryrun.active() is None
    assert dryrun.count("episodes", 3000, 10) == 3000
    steps = dryrun.steps("loop", range(7))
    assert list(steps) == list(range(7))
    carry, outs = scan_in_chunks(lambda c: (c + 1, c), jnp.int32(0), 7, 3, progress=False)
    assert int(carry) == 7 and outs.shape == (7,)


def test_a_dry_scan_runs_two_steps_and_returns_outputs_of_full_length(records):
    step = lambda c: (c + 1, {"value": c * 2, "env_steps": jnp.int32(5)})
    carry, outs = scan_in_chunks(step, jnp.int32(0), 1000, 100, desc="counter", progress=False)
    assert int(carry) == dryrun.KEEP_STEPS  # two steps ran, not 1000
    assert outs["value"].shape == (1000,)  # downstream code sees the full run's shapes
    assert int(outs["value"][-1]) == 2  # the last step run, repeated
    (rec,) = records()
    assert rec["kind"] == "scan" and rec["name"] == "counter"
    assert rec["full_steps"] == 1000 and rec["steps_run"] == 2 and len(rec["step_s"]) == 2
    assert rec["compile_s"] > 0 and rec["seconds_per_step"] == min(rec["step_s"])
    assert rec["carry_bytes"] == 4  # one int32
    assert rec["outputs_bytes"] == 1000 * 8  # two int32 per step, at full length
    assert rec["env_steps_per_step"] == 5
    assert rec["peak_rss_bytes"] > 0 and rec["devices"] >= 1
    assert "xla_temp_bytes" in rec


def test_a_failing_loop_is_recorded_with_its_name_and_error(records):
    def bad(c):
        return c @ jnp.ones((3, 2)), c  # (4,) @ (3, 2): a shape error

    with pytest.raises(TypeError):
        scan_in_chunks(bad, jnp.ones(4), 10, 5, desc="broken loop", progress=False)
    (rec,) = records()
    assert rec["kind"] == "failed" and rec["name"] == "broken loop"
    assert "TypeError" in rec["error"]
    summary = report.summarise("nb", records(), [])
    assert summary["failed_loops"] == [{"name": "broken loop", "error": rec["error"]}]


def test_a_python_loop_runs_its_first_iterations_and_counts_are_cut(records):
    steps = dryrun.steps("training", range(50), full=5000)
    seen = []
    for i in steps:
        seen.append(i)
        steps.step_done(jnp.ones(3) * i)
    assert seen == [0, 1]
    with dryrun.repeats(3):
        assert dryrun.count("seeds", 3, 1) == 1
        dryrun.timed("rollouts", 20, lambda: jnp.zeros(2))
    assert dryrun.count("small enough", 2, 5) == 2  # nothing to cut: not recorded
    loop, cut, call = records()
    assert loop["name"] == "training" and loop["full_steps"] == 5000 and loop["steps_run"] == 2
    assert loop["repeats"] == 1
    assert cut == {**cut, "kind": "cut", "name": "seeds", "full": 3, "kept": 1, "repeats": 3}
    assert call["kind"] == "call" and call["full_steps"] == 20 and call["repeats"] == 3
    assert call["memory_factor"] == 1  # one after another: the memory is not held three times


def test_a_slow_first_iteration_is_the_only_one_and_its_time_the_rate(records, monkeypatch):
    monkeypatch.setattr(dryrun, "SLOW_LOOP_S", 0.0)
    steps = dryrun.steps("FLT", range(50), full=20000)
    seen = []
    for i in steps:
        seen.append(i)
        steps.step_done(jnp.ones(3))
    (loop,) = records()
    assert seen == [0] and loop["steps_run"] == 1 and loop["compile_s"] == 0.0
    assert loop["seconds_per_step"] == loop["step_s"][0] == steps.seconds_per_step


def test_a_program_compiled_first_then_a_share_of_its_work_timed(records, monkeypatch):
    """The QDT's evaluation in a dry run: its program compiled ahead of time from shapes
    (compile seconds apart), then a tenth of the goals played and timed ten times."""
    program = jax.jit(lambda x: jnp.sin(x) * 2)
    monkeypatch.delenv(dryrun.ENV)
    assert dryrun.compiled("rollouts: compilation", program, jnp.ones(3)) is program
    monkeypatch.setenv(dryrun.ENV, str(records.path))
    shape = jax.ShapeDtypeStruct((3,), jnp.float32)
    executable = dryrun.compiled("rollouts: compilation", program, shape)
    clock = iter([0.0, 0.5])  # the call takes half a second
    monkeypatch.setattr(dryrun.time, "perf_counter", lambda: next(clock))
    out = dryrun.timed("rollouts", 4, executable, jnp.ones(3), share=10.0)
    np.testing.assert_allclose(out, 2 * np.sin(np.ones(3)), rtol=1e-6)
    compile_rec, call = records()
    assert compile_rec["kind"] == "compile" and compile_rec["full_steps"] == 0
    assert compile_rec["compile_s"] >= 0 and "xla_temp_bytes" in compile_rec
    assert call["seconds_per_step"] == pytest.approx(5.0) and call["share"] == 10.0
    assert report.project(call)["cpu_hours"] == pytest.approx(4 * 5.0 / 3600)


def test_calls_of_one_program_are_timed_once(records):
    calls = []
    fn = lambda x: calls.append(x) or jnp.ones(2) * x
    first = dryrun.timed("rollouts a", 20, fn, 1.0, same_as="test program")
    again = dryrun.timed("rollouts b", 20, fn, 2.0, same_as="test program")
    assert calls == [1.0] and again is first  # the second call ran nothing
    a, b = records()
    assert a["steps_run"] == 1 and b["steps_run"] == 0
    assert b["seconds_per_step"] == a["seconds_per_step"] and b["full_steps"] == 20


def test_a_player_times_its_simulation_once(records):
    from qdnb.envs.player import Player
    from qdnb.envs.pointmaze import PointMaze
    from qdnb.nets.mlp import MLP, init_policies

    env = PointMaze(episode_length=5)
    network = MLP((4, env.action_size))
    player = Player(env, network, chunk=4, name="test episodes")
    params = init_policies(network, jax.random.PRNGKey(0), 10, env.observation_size)
    keys = jax.random.split(jax.random.PRNGKey(1), 10)
    first = player.play(params, keys)
    second = player.play(params, keys)
    assert first.fitness.shape == second.fitness.shape == (10,)  # the full run's shapes
    a, b = records()
    assert a["name"] == b["name"] == "test episodes (4 per chunk)"
    assert a["full_steps"] == 3 and a["steps_run"] == 2  # 10 episodes: three chunks of 4
    assert b["steps_run"] == 0 and b["seconds_per_step"] == a["seconds_per_step"]


def small_map_elites():
    from qdnb.envs.pointmaze import PointMaze
    from qdnb.nets.mlp import MLP
    from qdnb.qd.algorithms import PolicyMapElites
    from qdnb.qd.cvt import grid_centroids

    env = PointMaze(episode_length=10)
    return PolicyMapElites(
        env=env,
        network=MLP((4, env.action_size)),
        batch_size=8,
        iso_sigma=0.05,
        line_sigma=0.1,
        centroids=grid_centroids((4, 4), env.descriptor_low, env.descriptor_high),
    )


def test_cheap_seeds_side_by_side_are_all_run(records, monkeypatch):
    """A dry run of ``run_seeds`` whose seeds' steps are cheap runs them all at once, as
    the full run does (one seed is tried first and not recorded); the start, which
    compiles, is not a step and does not make them slow."""
    from qdnb.qd.algorithms import run_seeds

    monkeypatch.setattr(dryrun, "ALL_SEEDS_S", 0.05)  # above 3 steps, below a compilation

    keys = jax.random.split(jax.random.PRNGKey(0), 3)
    states, _, history = run_seeds(small_map_elites(), keys, 30, 10, progress=False, desc="ME")
    assert history["max_fitness"].shape[:2] == (3, 31)
    first, loop = records()  # the start (compiled and run once), then the loop
    assert first["kind"] == "call" and first["name"] == "ME: start"
    assert first["full_steps"] == 1 and first["repeats"] == 1
    assert loop["name"] == "ME" and loop["repeats"] == 1 and loop["memory_factor"] == 1
    assert loop["full_steps"] == 31 and loop["steps_run"] == 2


def test_slow_seeds_side_by_side_run_one_and_count_for_all(records, monkeypatch):
    """When all the seeds' steps would be slow, one seed stands for all: its time and
    memory count once per seed and every seed's slot gets its results (the shapes
    downstream code expects)."""
    from qdnb.qd.algorithms import run_seeds

    monkeypatch.setattr(dryrun, "ALL_SEEDS_S", 0.0)  # every step of all seeds counts as slow
    monkeypatch.setattr(dryrun, "SLOW_STEP_S", 0.0)
    keys = jax.random.split(jax.random.PRNGKey(0), 3)
    states, _, history = run_seeds(small_map_elites(), keys, 30, 10, progress=False, desc="ME")
    assert history["max_fitness"].shape[:2] == (3, 31)
    assert jax.tree.leaves(states)[0].shape[0] == 3
    np.testing.assert_array_equal(history["max_fitness"][0], history["max_fitness"][2])
    cut, first, loop = records()
    assert first["name"] == "ME: start" and first["repeats"] == 3
    assert cut["name"] == "ME: seeds side by side" and (cut["full"], cut["kept"]) == (3, 1)
    assert loop["name"] == "ME" and loop["repeats"] == 3 and loop["memory_factor"] == 3
    assert loop["full_steps"] == 31 and loop["steps_run"] == 1  # a slow first step runs alone
    one = report.project({**loop, "memory_factor": 1, "state_factor": 1})
    assert report.project(loop)["device_bytes"] == pytest.approx(3 * one["device_bytes"])


def test_projection_arithmetic_on_hand_made_rates():
    loop = {
        "kind": "scan",
        "name": "ant_omni ME-LS",
        "repeats": 2.0,
        "full_steps": 1000,
        "compile_s": 36.0,
        "seconds_per_step": 3.6,
        "env_steps_per_step": 250_000.0,
        "carry_bytes": 10**9,
        "outputs_bytes": 2 * 10**9,
        "xla_temp_bytes": 3 * 10**9,
        "devices": 2,
    }
    rate = {"per": "env_step", "rate": 5e6, "source": "x.json", "what": "the loop"}
    p = report.project(loop, rate)
    assert p["cpu_hours"] == pytest.approx(2 * (36 + 3600) / 3600)
    assert p["gpu_hours"] == pytest.approx(2 * 1000 * 250_000 / 5e6 / 3600)
    assert p["checkpoint_bytes"] == 3 * 10**9
    assert p["device_bytes"] == 10**9 + 2 * 10**9 + 2 * 3 * 10**9
    assert report.project(loop)["gpu_hours"] is None  # no rate: no guess
    per_step = {"per": "step", "rate": 4.0, "source": "q.json", "what": "a step"}
    assert report.project(loop, per_step)["gpu_hours"] == pytest.approx(2 * 1000 / 4 / 3600)
    # the same loop's dry run on a GPU: a step there is every seed at once, 0.5 s
    side = {**loop, "memory_factor": 2.0}  # the two repeats are two seeds side by side
    on_gpu = {"per": "gpu_step", "rate": 2.0, "source": "g.json", "what": "the loop"}
    assert report.project(side, on_gpu)["gpu_hours"] == pytest.approx(1000 * 0.5 / 3600)
    assert report.project(loop, on_gpu)["gpu_hours"] == pytest.approx(2 * 1000 * 0.5 / 3600)


def test_a_loop_meets_the_rate_measured_for_it():
    rates = [
        {"notebook": "ch4_reproducibility", "match": "ant_omni ME-LS", "per": "env_step",
         "exact": True, "rate": 5e6, "source": "a", "what": "ME-LS"},
        {"notebook": "ch4_reproducibility", "match": "ant_omni ME", "per": "env_step",
         "exact": True, "rate": 1e6, "source": "a", "what": "ME"},
        {"notebook": "ch2_primer", "match": "", "per": "env_step", "rate": 1e8,
         "batch_env_steps": 200_000, "source": "r", "what": "small"},
        {"notebook": "ch2_primer", "match": "", "per": "env_step", "rate": 6e8,
         "batch_env_steps": 1_600_000, "source": "r", "what": "large"},
    ]  # fmt: skip
    loop = lambda name, steps=None: {"name": name, "env_steps_per_step": steps}
    assert (
        report.matching_rate("ch4_reproducibility", loop("ant_omni ME-LS", 1), rates)["rate"] == 5e6
    )
    assert report.matching_rate("ch4_reproducibility", loop("ant_omni ME", 1), rates)["rate"] == 1e6
    assert report.matching_rate("ch4_reproducibility", loop("halfcheetah_uni ME", 1), rates) is None
    assert (
        report.matching_rate("ch4_reproducibility", loop("ant_omni ME-Sampling", 1), rates) is None
    )
    assert report.matching_rate("ch2_primer", loop("ME", 2_000_000), rates)["what"] == "large"
    assert report.matching_rate("ch2_primer", loop("ME", 150_000), rates)["what"] == "small"
    assert report.matching_rate("ch2_primer", loop("ME"), rates) is None  # steps not counted
    assert report.gpu_rates()  # the committed H100 measurements are read
    exact = {"notebook": "ch2_primer", "match": "ME", "exact": True, "per": "gpu_step",
             "rate": 9.0, "source": "g", "what": "the loop on a GPU"}  # fmt: skip
    assert report.matching_rate("ch2_primer", loop("ME", 2_000_000), rates + [exact]) is exact
    assert report.matching_rate("ch2_primer", loop("MEX", 2_000_000), [exact]) is None


def test_a_gpu_dry_run_gives_its_loops_rates(tmp_path):
    gpu_loop = {"name": "ant_omni ME", "seconds_per_step": 0.25, "memory_factor": 1}
    gpu_run = {"notebooks": {"ch4_reproducibility": {
        "loops": [gpu_loop], "ran_on": {"device": "1 GPU (NVIDIA H100)"}}}}  # fmt: skip
    (tmp_path / "paper_dryrun_gpu.json").write_text(json.dumps(gpu_run))
    (rate,) = report.gpu_rates(tmp_path)
    assert rate["rate"] == 4.0 and rate["per"] == "gpu_step" and "H100" in rate["what"]


def test_summarise_totals_and_the_page():
    loops = [
        {"kind": "scan", "name": "a", "repeats": 1, "full_steps": 10, "steps_run": 2,
         "compile_s": 0.0, "seconds_per_step": 360.0, "carry_bytes": 5, "outputs_bytes": 5,
         "xla_temp_bytes": 90e9, "devices": 1, "peak_rss_bytes": 7},
        {"kind": "loop", "name": "b", "repeats": 1, "full_steps": 10, "steps_run": 2,
         "compile_s": 0.0, "seconds_per_step": 36.0, "peak_rss_bytes": 9},
        {"kind": "cut", "name": "episodes", "full": 3000, "kept": 10},
        {"kind": "data", "name": "dataset", "bytes": 1, "full_bytes": 300},
    ]  # fmt: skip
    s = report.summarise("ch2_primer", loops, [])
    t = s["totals"]
    assert t["loops"] == 2 and t["cpu_hours"] == pytest.approx(1.1)
    assert t["peak_rss_bytes"] == 9 and not t["fits_gpu"]  # 90 GB of working memory
    assert t["checkpoint_bytes"] == report.CHECKPOINTS_KEPT * 10  # scans only
    assert t["dataset_bytes"] == 300 and s["cuts"][0]["kept"] == 10
    fake = {
        "scale": "paper",
        "wall_s": 60.0,
        "notebooks": {
            "ch2_primer": {
                **s,
                "status": "ok",
                "error": None,
                "wall_s": 60.0,
                "command": "python -m qdnb run ch2_primer --scale paper",
                "ran_on": {"cpu_count": 2, "device": "2 CPU devices", "git": "abc", "date": "d"},
            }
        },
    }
    again = {**loops[1], "full_steps": 30}  # a second call of the same loop: one row
    rows = report.loop_rows(report.summarise("ch2_primer", loops + [again], []))
    assert [r["loop"] for r in rows] == ["a", "b (×2)"] and rows[1]["length"] == "40 steps"
    page = report.page_markdown(fake)
    assert "python -m qdnb run ch2_primer --scale paper" in page and "over 80 GB" in page
    assert "episodes: 10 of 3,000" in page
    assert "No dry run" in report.page_markdown(None)
    assert "Not in this dry run yet" in page and "`ch5_flow_lenia`" in page


def test_unknown_notebooks_and_scales_are_refused_with_the_valid_names(capsys):
    from qdnb.__main__ import main

    assert main(["dryrun", "ch9_nothing"]) == 2
    err = capsys.readouterr().err
    assert "unknown notebook" in err and "ch2_primer" in err and "ch5_flow_lenia" in err
    assert main(["dryrun", "ch2_primer", "--scale", "huge"]) == 2
    err = capsys.readouterr().err
    assert "unknown scale 'huge'" in err and "tiny, small, paper" in err


def test_a_failing_notebook_is_reported_and_the_others_still_run(tmp_path, monkeypatch):
    from qdnb.book import runner

    def execute(source, output, parameters, label, progress, checkpoints):
        assert checkpoints == "off" and parameters["scale"] == "tiny"
        if "ch2_primer" in label:
            raise runner.NotebookFailed("notebook 'ch2_primer' failed in cell 7: ValueError: x")

    monkeypatch.setattr(runner, "execute", execute)
    out = tmp_path / "report.json"
    got = report.dry_run(["ch2_primer", "ch3_qdpg"], "tiny", progress=False, out=out, work=tmp_path)
    assert got["notebooks"]["ch2_primer"]["status"] == "failed"
    assert "cell 7" in got["notebooks"]["ch2_primer"]["error"]
    assert got["notebooks"]["ch3_qdpg"]["status"] == "ok"
    assert json.loads(out.read_text())["scale"] == "tiny"


@pytest.mark.notebook
def test_the_primer_dry_run_at_tiny_times_every_loop(tmp_path):
    """The real thing at `tiny`: the notebook runs with each of its three loops cut to
    two steps, every field reported; the book's runs are not touched."""
    out = tmp_path / "tiny_dryrun.json"
    got = report.dry_run(["ch2_primer"], "tiny", progress=False, out=out, work=tmp_path)
    nb = got["notebooks"]["ch2_primer"]
    assert nb["status"] == "ok", nb["error"]
    names = [loop["name"] for loop in nb["loops"]]  # each loop's start, then the loop
    assert names == ["GA: initial batch", "GA", "NS: initial batch", "NS", "ME: start", "ME"]
    starts = [loop for loop in nb["loops"] if loop["kind"] == "call"]
    assert all(s["full_steps"] == 1 and s["seconds_per_step"] > 0 for s in starts)
    for loop in [loop for loop in nb["loops"] if loop["kind"] == "scan"]:
        assert loop["steps_run"] == 2 and loop["full_steps"] in (40, 41)
        assert loop["compile_s"] > 0 and loop["seconds_per_step"] > 0
        assert loop["cpu_hours"] > 0 and loop["device_bytes"] > loop["carry_bytes"] > 0
        assert loop["gpu_hours"] is not None  # Point-Maze rollouts were measured on an H100
    assert (tmp_path / "tiny" / "runs" / "tiny" / "ch2_primer" / "summary.json").exists()
    assert np.isfinite(nb["totals"]["cpu_hours"])


def test_the_es_ant_generations_are_cut_only_in_a_dry_run(tmp_path, monkeypatch):
    """The one population a dry run cuts: Ant-Maze ES perturbations (one paper generation
    is about 20 minutes on two cores), the generations kept, counted 20 times."""
    from qdnb.chapters import ch3_evolution as es

    cfg = es.SCALES["paper"]
    generations = lambda t: t.num_steps // (t.num_actors * t.episode_length)
    monkeypatch.delenv(dryrun.ENV, raising=False)
    tasks, whole = es.dry_run_tasks(cfg, "antmaze")
    assert tasks.antmaze.num_actors == 10_000 and whole.kept == whole.full == 10_000
    monkeypatch.setenv(dryrun.ENV, str(tmp_path / "loops.jsonl"))
    cut_tasks, cut = es.dry_run_tasks(cfg, "antmaze")
    kept = es.DRY_RUN_ANT_PERTURBATIONS
    assert cut_tasks.antmaze.num_actors == cut.kept == kept and cut.full == 10_000
    assert generations(cut_tasks.antmaze) == generations(tasks.antmaze) == 1000
    with cut.counted():  # each loop inside stands for the 10,000 perturbations side by side
        assert dryrun.repeat_factor() == dryrun.memory_factor() == 10_000 / kept
        assert dryrun.state_factor() == 1  # the perturbations share their centre's state
    pointmaze, never = es.dry_run_tasks(cfg, "pointmaze")
    assert pointmaze.pointmaze.num_actors == never.kept == never.full == 10_000


def test_a_step_too_big_for_this_machine_is_reported_not_run(records, monkeypatch):
    """The QDT's paper training step asks XLA on the CPU for about 97 GB: a dry run
    compiles it, records the memory it needs and does not run it."""
    step = jax.jit(lambda x: (x @ x.T).sum())
    x = jnp.ones((64, 64))
    assert not dryrun.too_big_here("fits", step, x, full_steps=10)  # nothing recorded
    monkeypatch.setattr(dryrun, "host_memory_bytes", lambda: 1000)
    assert dryrun.too_big_here("training", step, x, full_steps=10)
    (rec,) = records()
    assert rec["kind"] == "skipped" and rec["name"] == "training" and rec["full_steps"] == 10
    assert "GB of working memory" in rec["reason"]
    p = report.project(rec)
    assert p["cpu_hours"] is None and p["gpu_hours"] is None
    summary = report.summarise("ch4_qdt", records(), [])
    assert summary["totals"]["loops_not_run_here"] == 1
    assert report.loop_rows(summary)[0]["this CPU"] == "not run here"


def test_a_dry_run_stopped_from_outside_is_reported_cut_off_with_its_loops(tmp_path):
    """A session's time limit kills the dry run mid-notebook: no report entry, but the
    loops it reached are in its records; the report rebuilt from them says `cut off`."""
    loop = {"kind": "loop", "name": "FLT", "repeats": 1, "full_steps": 100, "steps_run": 2,
            "compile_s": 0.0, "seconds_per_step": 36.0, "peak_rss_bytes": 9}  # fmt: skip
    where = tmp_path / "tiny" / "ch5_flow_lenia"
    where.mkdir(parents=True)
    (where / "loops.jsonl").write_text(json.dumps(loop) + "\n")
    out = tmp_path / "report.json"
    with pytest.raises(ValueError, match="no dry run report"):
        report.resummarise("tiny", out, work=tmp_path)  # nothing named, nothing to rebuild
    got = report.resummarise("tiny", out, work=tmp_path, names=["ch2_primer", "ch5_flow_lenia"])
    assert list(got["notebooks"]) == ["ch5_flow_lenia"]  # the primer left no records
    nb = got["notebooks"]["ch5_flow_lenia"]
    assert nb["status"] == "cut off" and nb["totals"]["cpu_hours"] == pytest.approx(1.0)
    assert report.chapter_rows(got)[0]["dry run"] == "CUT OFF, 1 loop"
    with pytest.raises(ValueError, match="not paper"):
        report.resummarise("paper", out, work=tmp_path)


def test_copies_sharing_their_state_count_only_their_working_memory_again(records):
    """An ES generation's perturbations, cut 100-fold: their working memory is counted
    100 times, the central parameters they share (the carry) once."""
    step = lambda c: (c + 1.0, c.sum())
    with dryrun.repeats(100, side_by_side=True, shared_state=True):
        scan_in_chunks(step, jnp.ones(1000), 4, 2, progress=False, desc="ES")
    with dryrun.repeats(100, side_by_side=True):
        scan_in_chunks(step, jnp.ones(1000), 4, 2, progress=False, desc="seeds")
    es, seeds = records()
    assert es["state_factor"] == 1 and es["memory_factor"] == es["repeats"] == 100
    assert seeds["state_factor"] == seeds["memory_factor"] == 100
    shared, copied = report.project(es), report.project(seeds)
    assert shared["checkpoint_bytes"] == pytest.approx(copied["checkpoint_bytes"] / 100)
    # sharing changes the memory counted, not the time: the same record unshared projects
    # the same hours (the two loops above were timed apart, so their hours differ by noise)
    unshared = report.project({**es, "state_factor": es["memory_factor"]})
    assert shared["cpu_hours"] == unshared["cpu_hours"] > 0
    assert unshared["checkpoint_bytes"] == pytest.approx(copied["checkpoint_bytes"])


def test_the_flts_batches_are_cut_on_a_cpu_and_each_step_counts_for_the_whole(records):
    """A paper step of the FLT (32 episodes of 128x128) takes minutes on two cores: a CPU
    dry run trains and scores ``DRY_RUN_EPISODES`` episodes a batch, each step counted
    ``batch / DRY_RUN_EPISODES`` times, the loops' lengths and the scores' shapes kept."""
    from qdnb.chapters.ch5_flow_lenia import evaluate
    from qdnb.models.lenia import flow_lenia as fl
    from qdnb.models.lenia import flt

    kept = flt.DRY_RUN_EPISODES
    batch = 2 * kept
    world = fl.FlowLeniaConfig(height=16, width=16, kernels=2, patch_size=5, steps=4)
    cfg = flt.FLTConfig(
        embed_dim=8, num_layers=1, num_heads=2, features=(4, 8), batch_size=batch, train_steps=50
    )
    system = fl.sample_system(jax.random.PRNGKey(1), world)
    model = flt.make_model(world, cfg)
    trained = flt.train(model, cfg, world, system, jax.random.PRNGKey(2), progress=False)
    assert trained.episodes_seen == len(trained.losses) * kept
    episodes = 2 * batch + 3
    held = evaluate(
        model, trained.params, world, system, trained.mean_frames, jax.random.PRNGKey(3),
        episodes, batch,
    )  # fmt: skip
    a = held.errors["flt"]["A"]
    assert a.shape == (episodes, world.steps)  # the episodes played, repeated
    played = 2 * kept  # two batches: the rest repeat them
    np.testing.assert_array_equal(a[played : 2 * played], a[:played])
    cuts = [r for r in records() if r["kind"] == "cut"]
    assert [(c["full"], c["kept"]) for c in cuts] == [(batch, kept), (batch, kept)]
    training, scoring = [r for r in records() if r["kind"] == "loop"]
    assert training["full_steps"] == 50 and training["repeats"] == 2
    assert training["memory_factor"] == 2 and training["state_factor"] == 1
    assert scoring["full_steps"] == 3 and scoring["repeats"] == 2
    assert report.project(training)["cpu_hours"] == pytest.approx(
        2 * (training["compile_s"] + 50 * training["seconds_per_step"]) / 3600
    )
