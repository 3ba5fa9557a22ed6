"""The Flow Lenia Transformer (Section 5.3.1) and the Chapter 5 experiment helpers:
output shapes and ranges, causality, cached against uncached unrolls, a training
step lowering the loss, determinism, the surprise-search descriptors on
hand-made patterns, and config errors.  A 16x16 world with 2 kernels keeps it fast."""

import dataclasses
import time

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from qdnb.chapters import ch5_flow_lenia as chapter
from qdnb.chapters.ch5_flow_lenia import (
    HeldOut,
    SearchResult,
    SurpriseSearch,
    SystemCriteria,
    centre_of_mass,
    evaluate,
    experiment,
    pattern_descriptors,
    pick_system,
    spearman,
    world_statistics,
)
from qdnb.core.claims import FAILS, HOLDS
from qdnb.core.paths import NOTEBOOKS
from qdnb.models.lenia import flow_lenia as fl
from qdnb.models.lenia.flt import (
    FLT,
    FLTConfig,
    init_params,
    loss_fn,
    make_model,
    make_train_step,
    next_frame,
    perturbed,
    train,
    unroll,
)
from qdnb.nets.transformer import make_optimizer
from qdnb.qd.repertoire import Repertoire

WORLD = fl.FlowLeniaConfig(
    height=16, width=16, kernels=2, patch_size=5, steps=6, radius_scale=16 / 128
)
CFG = FLTConfig(
    embed_dim=16, num_layers=2, num_heads=2, features=(4, 8), batch_size=2, train_steps=3
)


@pytest.fixture(scope="module")
def system():
    return fl.sample_system(jax.random.PRNGKey(1), WORLD)


@pytest.fixture(scope="module")
def episodes(system):
    return fl.frames(fl.simulate_system(system, jax.random.PRNGKey(2), WORLD, 3))


@pytest.fixture(
    scope="module",
    params=[
        {},
        {"skip": True},
        {"head": "residual"},  # ours, beyond the thesis: its last layer moved off zero
        {"head": "mass", "skip": True},
    ],
    ids=["token-only", "skip", "residual", "mass-skip"],
)
def model_params(request):
    model = make_model(WORLD, dataclasses.replace(CFG, **request.param))
    params = init_params(model, jax.random.PRNGKey(0))
    if "head" in request.param:  # an untrained residual head is persistence: move it
        params = shaken(params, jax.random.PRNGKey(3), 0.05)
    return model, params


def test_shapes_and_ranges(model_params, episodes):
    model, params = model_params
    pred = model.apply(params, episodes[:, :-1])
    assert pred.shape == (3, WORLD.steps, 16, 16, 1 + WORLD.kernels)
    assert bool(jnp.all(pred[..., 0] >= 0.0))  # matter is non-negative
    assert bool(jnp.all((pred[..., 1:] >= 0.0) & (pred[..., 1:] <= 1.0)))  # kernel weights
    assert unroll(model, params, episodes[:, 0]).shape == pred.shape


def test_a_later_frame_never_changes_an_earlier_prediction(model_params, episodes):
    model, params = model_params
    inputs = episodes[:1, :-1]
    base = model.apply(params, inputs)
    for k in (1, 3, WORLD.steps - 1):
        changed = inputs.at[:, k].add(jax.random.uniform(jax.random.PRNGKey(k), inputs.shape[2:]))
        pred = model.apply(params, changed)
        np.testing.assert_array_equal(np.asarray(pred[:, :k]), np.asarray(base[:, :k]))
        assert (
            float(jnp.max(jnp.abs(pred[:, k] - base[:, k]))) > 1e-6
        )  # frame k does inform x_{k+1}


def test_cached_unroll_matches_full_recomputation(model_params, episodes):
    model, params = model_params
    cached = unroll(model, params, episodes[:, 0])
    full = unroll(model, params, episodes[:, 0], cached=False)
    np.testing.assert_allclose(np.asarray(cached), np.asarray(full), atol=1e-5)
    # the first prediction only sees x_0: it is the teacher-forced one
    np.testing.assert_allclose(
        np.asarray(cached[:, 0]), np.asarray(model.apply(params, episodes[:, :-1])[:, 0]), atol=1e-5
    )


def test_loss_is_eq_5_3_up_to_a_constant(model_params, episodes):
    model, params = model_params
    pred = model.apply(params, episodes[:, :-1])
    a, p = episodes[:, 1:, ..., :1], episodes[:, 1:, ..., 1:]
    per_step = jnp.sum((a - pred[..., :1]) ** 2, axis=(2, 3, 4)) + jnp.sum(
        (p - pred[..., 1:]) ** 2, axis=(2, 3, 4)
    )
    eq53 = jnp.mean(per_step)  # mean over t (and episodes) of the squared norms
    cells = 16 * 16 * (1 + WORLD.kernels)
    assert float(loss_fn(model, params, episodes)) == pytest.approx(float(eq53) / cells, rel=1e-5)
    # the per-modality ablation: each modality's mean squared error, summed
    both = jnp.mean((a - pred[..., :1]) ** 2) + jnp.mean((p - pred[..., 1:]) ** 2)
    assert float(loss_fn(model, params, episodes, per_modality=True)) == pytest.approx(
        float(both), rel=1e-5
    )


def test_one_training_step_lowers_the_loss_on_a_fixed_batch(model_params, episodes):
    model, params = model_params
    optimizer = make_optimizer(1e-3)
    step = jax.jit(make_train_step(model, optimizer))
    before = float(loss_fn(model, params, episodes))
    new_params, _, reported = step(params, optimizer.init(params), episodes, None)
    assert float(reported) == pytest.approx(before, rel=1e-6)
    assert float(loss_fn(model, new_params, episodes)) < before


def test_training_is_deterministic_and_tracks_the_mean_frame(system):
    model = make_model(WORLD, CFG)
    a = train(model, CFG, WORLD, system, jax.random.PRNGKey(5), progress=False)
    b = train(model, CFG, WORLD, system, jax.random.PRNGKey(5), progress=False)
    np.testing.assert_array_equal(a.losses, b.losses)
    assert (
        a.losses.shape == (CFG.train_steps,) and a.episodes_seen == CFG.train_steps * CFG.batch_size
    )
    assert a.mean_frames.shape == (WORLD.steps + 1, 16, 16, 1 + WORLD.kernels)
    # the mean frame at t = 0 is the mean initial state: matter only on the patch, total mass ~
    # patch area / 2
    assert float(a.mean_frames[0, ..., 0].sum()) == pytest.approx(25 * 0.5, rel=0.3)
    assert float(a.mean_frames[0, 0, 0, 0]) == 0.0
    assert a.max_drift < 1e-5
    # a time budget stops after the first step past it; the mean frame is over the episodes seen
    short = train(model, CFG, WORLD, system, jax.random.PRNGKey(5), progress=False, max_seconds=0.0)
    assert short.losses.shape == (1,) and short.episodes_seen == CFG.batch_size
    assert short.losses[0] == a.losses[0]
    assert float(short.mean_frames[0, ..., 0].sum()) == pytest.approx(25 * 0.5, rel=0.3)


def test_evaluate_scores_the_baselines_frame_by_frame(model_params, system):
    model, params = model_params
    mean_frames = np.zeros((WORLD.steps + 1, 16, 16, 1 + WORLD.kernels), np.float32)
    began = time.perf_counter()
    out = evaluate(
        model, params, WORLD, system, mean_frames, jax.random.PRNGKey(3), episodes=5, batch=2
    )
    assert 0.0 < out.seconds <= time.perf_counter() - began  # its own wall time, nothing else
    for name in ("flt", "persistence", "mean_frame"):
        assert out.errors[name]["A"].shape == (5, WORLD.steps)
    truth = out.truth  # the first three episodes
    # an all-zero mean frame scores the mean square of the truth; persistence scores the change
    # since x_0
    np.testing.assert_allclose(
        out.errors["mean_frame"]["A"][:3],
        np.mean(truth[:, 1:, ..., :1] ** 2, axis=(2, 3, 4)),
        rtol=1e-5,
    )
    np.testing.assert_allclose(
        out.errors["persistence"]["A"][:3],
        np.mean((truth[:, 1:, ..., :1] - truth[:, :1, ..., :1]) ** 2, axis=(2, 3, 4)),
        rtol=1e-5,
    )
    # one step of persistence: each true frame against the next
    np.testing.assert_allclose(
        out.errors["copy_previous"]["A"][:3],
        np.mean((truth[:, 1:, ..., :1] - truth[:, :-1, ..., :1]) ** 2, axis=(2, 3, 4)),
        rtol=1e-5,
    )
    assert out.drift.shape == (5,) and out.drift.max() < 1e-5


def test_mass_drift_on_a_hand_made_episode():
    A = jnp.ones((1, 3, 4, 4, 1)).at[0, 1].multiply(1.1).at[0, 2].multiply(0.8)
    assert float(fl.mass_drift(A)[0]) == pytest.approx(0.2, rel=1e-5)


def test_pattern_descriptors_on_hand_made_patterns():
    h = w = 16
    blob = jnp.zeros((h, w, 1)).at[4, 4, 0].set(1.0)
    for torus in (False, True):
        np.testing.assert_allclose(np.asarray(centre_of_mass(blob, torus)), [4.0, 4.0], atol=1e-4)
        moved = jnp.zeros((h, w, 1)).at[4, 7, 0].set(1.0)  # 3 cells to the right
        displacement, spread = np.asarray(pattern_descriptors(blob, moved, torus))
        assert displacement == pytest.approx(3 / 16, abs=1e-4) and spread == pytest.approx(
            0.0, abs=1e-4
        )
        pair = (
            jnp.zeros((h, w, 1)).at[4, 2, 0].set(1.0).at[4, 6, 0].set(1.0)
        )  # two cells, 2 either side of column 4
        displacement, spread = np.asarray(pattern_descriptors(blob, pair, torus))
        assert displacement == pytest.approx(0.0, abs=1e-4) and spread == pytest.approx(
            2 / 16, abs=1e-4
        )
    far = jnp.zeros((h, w, 1)).at[4, 14, 0].set(1.0)
    assert float(pattern_descriptors(blob, far, torus=True)[0]) == pytest.approx(
        6 / 16, abs=1e-4
    )  # across the edge
    assert float(pattern_descriptors(blob, far, torus=False)[0]) == pytest.approx(
        10 / 16, abs=1e-4
    )  # walls: no wrap


def test_surprise_search_keeps_the_most_surprising_per_cell(system):
    model = make_model(WORLD, CFG)
    params = init_params(model, jax.random.PRNGKey(0))
    search = SurpriseSearch(
        model,
        WORLD,
        batch_size=4,
        bins=(3, 3),
        max_displacement=0.5,
        min_spread=0.0,
        max_spread=0.5,
    )
    found = search.run(
        params, system, jax.random.PRNGKey(4), iterations=2, chunk_size=1, progress=False
    )
    repertoire, history = found.repertoire, found.history
    assert history["surprise"].shape == (12,) and history["descriptors"].shape == (12, 2)
    filled = np.asarray(repertoire.filled)
    assert filled.sum() >= 1 and found.evaluations == 12
    # every elite is the best evaluation that landed in its cell
    centroids = np.asarray(repertoire.centroids)
    desc = np.clip(history["descriptors"], 0.0, 0.5)
    cells = np.argmin(((desc[:, None] - centroids[None]) ** 2).sum(-1), axis=1)
    for c in np.flatnonzero(filled):
        assert float(repertoire.fitnesses[c]) == pytest.approx(
            history["surprise"][cells == c].max()
        )
    # genotypes stay valid initial states
    assert (
        float(repertoire.genotypes["a"].min()) >= 0.0
        and float(repertoire.genotypes["a"].max()) <= 1.0
    )
    # the world is deterministic: replayed with another key, each elite scores its stored surprise
    np.testing.assert_allclose(
        found.replayed[found.elites], found.elite_surprise[found.elites], rtol=1e-5
    )
    assert np.isnan(found.replayed[~filled]).all() and found.final_truth.shape == (9, 16, 16)
    again = search.run(
        params, system, jax.random.PRNGKey(4), iterations=2, chunk_size=1, progress=False
    )
    np.testing.assert_array_equal(history["surprise"], again.history["surprise"])


def test_held_out_derived_values_on_hand_made_errors():
    flt = np.array([[0.1, 0.3], [0.2, 0.1], [0.1, 0.5]])  # 3 episodes, T = 2
    errors = {
        "flt": {"A": flt, "frame": flt},
        "persistence": {"A": np.full((3, 2), 0.4), "frame": np.zeros((3, 2))},
        "mean_frame": {"A": np.array([[0, 0.2], [0, 0.2], [0, 0.6]]), "frame": np.zeros((3, 2))},
    }
    held = HeldOut(errors, np.zeros(1), np.zeros(1), np.zeros(3))
    np.testing.assert_allclose(held.median["flt"], [0.1, 0.3])
    assert held.final == {"flt": 0.3, "persistence": 0.4, "mean_frame": 0.2}
    assert not held.beats  # below persistence, not below the mean frame
    assert held.grows == 2 and held.rise == pytest.approx(0.2)
    assert held.share_below("flt", "mean_frame") == pytest.approx(2 / 3)


def test_search_result_extremes_and_correlations_on_a_hand_made_repertoire():
    fitnesses = jnp.array([0.5, -jnp.inf, 0.9, 0.1, 0.7])
    repertoire = Repertoire(
        {"a": jnp.zeros((5, 1))}, fitnesses, jnp.zeros((5, 2)), jnp.zeros((5, 2))
    )
    history = {
        "surprise": np.array([1.0, 2.0, 3.0, 4.0]),
        "descriptors": np.array([[0.1, 4.0], [0.2, 3.0], [0.3, 2.0], [0.4, 1.0]]),
    }
    replayed = np.array([0.5, np.nan, 0.8, 0.1, 0.7], np.float32)
    found = SearchResult(repertoire, history, 2, replayed, None, None, 0.0)
    picks = found.extremes(2)
    assert list(picks["most surprising"]) == [2, 4] and list(picks["least surprising"]) == [3, 0]
    assert list(found.extremes(3)["least surprising"]) == [3]  # never the same elite twice
    assert found.replay_gap == pytest.approx(0.1, abs=1e-6)
    assert found.correlations == {"centre-of-mass displacement": 1.0, "spread": -1.0}
    assert list(found.random_batch) == [1.0, 2.0] and found.best == 4.0
    assert spearman(np.array([1.0, 5.0, 2.0]), np.array([0.0, 9.0, 3.0])) == pytest.approx(1.0)


def test_run_calls_the_notebook_stages_in_order_with_its_keys(monkeypatch):
    calls = []

    def record(name, value=None):
        def stage(*args, **kwargs):
            keys = [a for a in args if isinstance(a, jax.Array) and a.shape == (2,)]
            calls.append((name, [np.asarray(k).tolist() for k in keys]))
            return value if value is not None else dataclasses.make_dataclass("S", [])()

        return stage

    trained = dataclasses.make_dataclass("T", ["params", "mean_frames"])(None, None)
    held_out = dataclasses.make_dataclass("H", ["final"])({"flt": 0.1})
    choice = dataclasses.make_dataclass("C", ["system"])(None)
    search = dataclasses.make_dataclass("R", [("run", object)])(record("search"))
    for name, value in (
        ("random_gallery", None),
        ("pick_system", choice),
        ("compare_p0", None),
        ("make_model", None),
        ("train", trained),
        ("evaluate", held_out),
        ("diagnose", None),
    ):
        monkeypatch.setattr(experiment, name, record(name, value))  # where ``run`` reads them
    monkeypatch.setattr(experiment, "surprise_search", lambda cfg, model: search)
    key = jax.random.PRNGKey(7)
    result = chapter.run(config_for_run(), key, progress=False)
    keys = jax.random.split(key, 5)
    g, p, t, e, s = (np.asarray(k).tolist() for k in keys)
    replay = np.asarray(jax.random.fold_in(keys[3], 2)).tolist()
    assert calls == [
        ("random_gallery", [g]),
        ("pick_system", [p]),
        ("compare_p0", [p]),
        ("make_model", []),
        ("train", [t]),
        ("evaluate", [e]),
        ("diagnose", [e, replay]),
        ("make_model", []),  # our variant (tiny has one): the same training and held-out keys
        ("train", [t]),
        ("evaluate", [e]),
        ("search", [s]),
    ]
    assert isinstance(result, chapter.Result)
    # the notebook draws the same five keys in the same order
    setup = (NOTEBOOKS / "ch5_flow_lenia.ipynb").read_text()
    assert "k_gallery, k_pick, k_train, k_eval, k_search = jax.random.split(key, 5)" in setup


def config_for_run():
    from qdnb.book.registry import config

    return config("ch5_flow_lenia", "tiny")


def test_world_statistics_on_hand_made_episodes():
    """Two probes of 3 frames on a 2x2 grid: occupancy, diversity across probes and
    the change of the last step, each against a hand computation."""
    still = np.array([[1.0, 0.0], [0.0, 0.0]])
    A = np.zeros((2, 3, 2, 2, 1), np.float32)
    A[0, :, ..., 0] = still  # probe 0 never moves
    A[1, 0, ..., 0] = still
    A[1, 1, ..., 0] = [[0.0, 1.0], [0.0, 0.0]]
    A[1, 2, ..., 0] = [
        [0.0, 0.0],
        [1.0, 0.0],
    ]  # probe 1 ends elsewhere, having moved in its last step
    stats = world_statistics(jnp.asarray(A), window=1)
    energy = 2 / 8  # mean of (A^T)^2 over probes and cells
    assert stats["occupancy"] == pytest.approx(0.25)
    assert stats["diversity"] == pytest.approx(
        np.mean(np.var(A[:, -1, ..., 0], axis=0)) / energy
    )  # (2 x 0.25) / 4
    assert stats["diversity"] == pytest.approx(0.5)
    assert stats["change"] == pytest.approx(
        (2 / 8) / energy
    )  # probe 1's last step moved all its mass: 2 cells of 1
    same = world_statistics(jnp.asarray(np.repeat(A[:1], 2, axis=0)), window=2)
    assert same["diversity"] == 0.0 and same["change"] == 0.0  # identical probes, nothing moves


def test_pick_system_keeps_the_first_system_meeting_every_criterion():
    lax = SystemCriteria(max_growth=1e9, min_diversity=0.0, max_change=1e9)
    choice = pick_system(jax.random.PRNGKey(0), WORLD, candidates=3, probes=2, criteria=lax)
    assert choice.index == 0  # everything qualifies: the first one
    assert set(choice.statistics) == {"occupancy", "diversity", "change", "replay", "sensitivity"}
    assert np.all(choice.statistics["replay"] == 0.0)  # deterministic mixing: replays are identical
    assert all(v.shape == (3,) for v in choice.statistics.values())
    # the P0 comparison measures the kept system on the probes it was chosen on: the row of
    # the world's own rule is the kept candidate's column of the candidates' table
    p0 = chapter.compare_p0(choice, WORLD, jax.random.PRNGKey(1), probes=2, examples=1)
    own = p0.statistics[WORLD.p0]
    assert own == pytest.approx({k: float(v[choice.index]) for k, v in choice.statistics.items()})
    assert set(p0.statistics) == set(chapter.P0_RULES) and p0.finals["cell"].shape[0] == 1
    settled = choice.statistics["change"]
    # only "settled" can fail: the first system settled below a threshold between the candidates'
    # values
    threshold = float(np.sort(settled)[1])
    only = pick_system(
        jax.random.PRNGKey(0),
        WORLD,
        candidates=3,
        probes=2,
        criteria=SystemCriteria(max_growth=1e9, min_diversity=0.0, max_change=threshold),
    )
    assert only.index == int(np.flatnonzero(settled <= threshold)[0])
    strict = pick_system(
        jax.random.PRNGKey(0),
        WORLD,
        candidates=3,
        probes=2,
        criteria=SystemCriteria(max_growth=1e-9, min_diversity=1.0, max_change=1e-12),
    )
    # nothing qualifies: among those meeting the most criteria, the most settled
    count = sum(v.astype(int) for v in strict.passed.values())
    best = np.flatnonzero(count == count.max())
    assert strict.index == int(best[np.argmin(strict.statistics["change"][best])])
    with pytest.raises(ValueError):
        SystemCriteria(min_diversity=2.0)
    with pytest.raises(ValueError):
        pick_system(jax.random.PRNGKey(0), WORLD, candidates=3, probes=1)


def test_config_errors():
    with pytest.raises(ValueError, match="multiple of 2"):
        FLT(10, 16, 3, 6, features=(4, 8)).init(jax.random.PRNGKey(0), jnp.zeros((1, 2, 10, 16, 3)))
    with pytest.raises(ValueError, match="num_heads"):
        FLTConfig(embed_dim=10, num_heads=4)
    with pytest.raises(ValueError, match="train_steps"):
        FLTConfig(train_steps=0)
    with pytest.raises(ValueError, match="features"):
        FLTConfig(features=())
    with pytest.raises(ValueError, match="do not match"):
        fl.place_patch(jnp.zeros((4, 4, 1)), jnp.zeros((5, 5, 2)), WORLD)


def test_chapter_config_errors():
    from qdnb.book.registry import config
    from qdnb.chapters.ch5_flow_lenia import FlowLeniaChapterConfig, lenia_world

    small = config("ch5_flow_lenia", "small")
    # the patch (40 at 128) and the kernel radii scale with the grid; Table 5.1's ranges stay as
    # printed
    assert (
        small.world.patch_size == 10
        and small.world.radius_scale == 0.25
        and small.world.R_range == (2.0, 25.0)
    )
    assert config("ch5_flow_lenia", "paper").world == fl.FlowLeniaConfig()  # the thesis's world
    with pytest.raises(ValueError, match="at least 64"):
        dataclasses.replace(small, eval_episodes=32)
    with pytest.raises(ValueError, match="steps must be at least 50"):
        FlowLeniaChapterConfig(
            num_seeds=1, world=dataclasses.replace(lenia_world(16), steps=10), flt=CFG
        )


# ----- beyond the thesis (ours): residual and mass-conserving heads, noise, pushforward -----


def shaken(params, key, scale=0.1):
    """``params`` with every leaf moved by Gaussian noise: a model that is not persistence."""
    leaves, treedef = jax.tree.flatten(params)
    keys = jax.random.split(key, len(leaves))
    return jax.tree.unflatten(
        treedef, [x + scale * jax.random.normal(k, x.shape) for x, k in zip(leaves, keys)]
    )


def test_a_zero_change_returns_the_input_frame_exactly(episodes):
    frame = episodes[:, 3]
    for head in ("residual", "mass"):
        out = next_frame(head, jnp.zeros_like(frame), frame)
        np.testing.assert_array_equal(np.asarray(out), np.asarray(frame))
    change = jnp.full_like(frame, -2.0).at[..., 1:].set(2.0)  # below 0 for A, above 1 for P
    out = next_frame("residual", change, frame)
    assert float(out[..., 0].max()) == 0.0 and float(out[..., 1:].min()) == 1.0


def test_an_untrained_residual_flt_is_persistence(episodes):
    for head in ("residual", "mass"):
        model = make_model(WORLD, dataclasses.replace(CFG, head=head))
        params = init_params(model, jax.random.PRNGKey(0))
        inputs = episodes[:, :-1]
        np.testing.assert_array_equal(
            np.asarray(model.apply(params, inputs)), np.asarray(inputs)
        )  # the last layer starts at zero


def test_the_mass_head_conserves_matter_in_every_prediction_and_unroll(episodes):
    model = make_model(WORLD, dataclasses.replace(CFG, head="mass"))
    params = shaken(init_params(model, jax.random.PRNGKey(0)), jax.random.PRNGKey(9))
    inputs = episodes[:, :-1]
    pred = model.apply(params, inputs)
    assert float(jnp.max(jnp.abs(pred - inputs))) > 1e-3  # it does change the frames
    mass = lambda x: jnp.sum(x[..., 0], axis=(-2, -1))
    np.testing.assert_allclose(mass(pred), mass(inputs), rtol=1e-5)
    rolled = unroll(model, params, episodes[:, 0])
    np.testing.assert_allclose(
        mass(rolled), jnp.broadcast_to(mass(episodes[:, :1]), mass(rolled).shape), rtol=1e-4
    )
    residual = make_model(WORLD, dataclasses.replace(CFG, head="residual"))
    drift = jnp.abs(mass(residual.apply(params, inputs)) - mass(inputs)) / mass(inputs)
    assert float(drift.max()) > 1e-3  # the plain residual head does not conserve it


def test_noise_perturbs_the_inputs_only_and_needs_a_key(episodes):
    model = make_model(WORLD, dataclasses.replace(CFG, head="residual"))
    params = shaken(init_params(model, jax.random.PRNGKey(0)), jax.random.PRNGKey(9))
    key = jax.random.PRNGKey(4)
    noisy = perturbed(episodes[:, :-1], jax.random.fold_in(key, 1), 0.05)
    assert float(noisy[..., 0].min()) >= 0.0 and float(noisy[..., 1:].max()) <= 1.0
    assert 0.01 < float(jnp.std(noisy - episodes[:, :-1])) < 0.06
    by_hand = jnp.mean((model.apply(params, noisy) - episodes[:, 1:]) ** 2)  # true targets
    got = loss_fn(model, params, episodes, key, noise=0.05)
    assert float(got) == pytest.approx(float(by_hand), rel=1e-5)
    assert float(got) != pytest.approx(float(loss_fn(model, params, episodes, key)), rel=1e-3)
    with pytest.raises(ValueError, match="noise needs a key"):
        loss_fn(model, params, episodes, noise=0.05)


def test_pushforward_adds_a_pass_on_the_models_own_predictions_gradients_stopped(episodes):
    model = make_model(WORLD, dataclasses.replace(CFG, head="residual"))
    params = shaken(init_params(model, jax.random.PRNGKey(0)), jax.random.PRNGKey(9))
    inputs, targets = episodes[:, :-1], episodes[:, 1:]
    mse = lambda pred: jnp.mean((pred - targets) ** 2)
    first = model.apply(params, inputs)
    own = jnp.concatenate([episodes[:, :1], first[:, :-1]], axis=1)  # x_0, then its own x̂_t
    by_hand = lambda p: mse(model.apply(p, inputs)) + mse(model.apply(p, own))  # own: fixed
    got = loss_fn(model, params, episodes, pushforward=True)
    assert float(got) == pytest.approx(float(by_hand(params)), rel=1e-5)
    grads = jax.grad(lambda p: loss_fn(model, p, episodes, pushforward=True))(params)
    expected = jax.grad(by_hand)(params)  # no gradient through the first pass's outputs
    for g, e in zip(jax.tree.leaves(grads), jax.tree.leaves(expected)):
        np.testing.assert_allclose(np.asarray(g), np.asarray(e), rtol=1e-4, atol=1e-7)
    flowing = jax.grad(
        lambda p: (
            mse(model.apply(p, inputs))
            + mse(
                model.apply(
                    p, jnp.concatenate([episodes[:, :1], model.apply(p, inputs)[:, :-1]], axis=1)
                )
            )
        )
    )(params)
    differ = max(
        float(jnp.max(jnp.abs(g - f)))
        for g, f in zip(jax.tree.leaves(grads), jax.tree.leaves(flowing))
    )
    assert differ > 1e-6  # letting them flow would be another gradient


def test_a_variant_trains_deterministically(system):
    cfg = dataclasses.replace(CFG, head="mass", noise=0.02, pushforward=True)
    model = make_model(WORLD, cfg)
    a = train(model, cfg, WORLD, system, jax.random.PRNGKey(5), progress=False)
    b = train(model, cfg, WORLD, system, jax.random.PRNGKey(5), progress=False)
    np.testing.assert_array_equal(a.losses, b.losses)
    assert np.all(np.isfinite(a.losses))


def test_bad_variant_settings_are_refused():
    with pytest.raises(ValueError, match="head must be one of direct, residual, mass"):
        FLTConfig(head="flow")
    with pytest.raises(ValueError, match="noise must be a non-negative"):
        FLTConfig(noise=-0.1)


def test_the_better_predictor_is_searched_and_our_variant_has_its_own_claims():
    def held(flt_final, flt_first=0.1):
        errors = {
            "flt": {"A": np.array([[flt_first, flt_final]] * 4), "frame": np.zeros((4, 2))},
            "persistence": {"A": np.full((4, 2), 0.4), "frame": np.zeros((4, 2))},
            "mean_frame": {"A": np.full((4, 2), 0.3), "frame": np.zeros((4, 2))},
        }
        return HeldOut(errors, np.zeros(1), np.zeros(1), np.zeros(4))

    thesis, ours = held(0.35), held(0.2)
    assert chapter.best_model(thesis, None) == chapter.THESIS_FLT
    assert chapter.best_model(thesis, ours) == chapter.OUR_FLT
    assert chapter.best_model(ours, thesis) == chapter.THESIS_FLT
    beats, grows = chapter.variant_claims(ours)
    assert beats["id"] == "ch5/variant_beats_baselines" and beats["status"] == HOLDS
    assert grows["id"] == "ch5/variant_error_grows" and grows["status"] == HOLDS
    flat = chapter.variant_claims(held(0.2, flt_first=0.25))  # its error falls along the episode
    assert flat[0]["status"] == HOLDS and flat[1]["status"] == FAILS
    assert chapter.variant_claims(held(0.35))[0]["status"] == FAILS  # above the mean frame
