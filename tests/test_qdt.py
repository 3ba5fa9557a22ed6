"""The Quality-Diversity Transformer (Chapter 4, Algorithm 8): causal masking,
token interleaving and timestep embeddings, the masked loss, training, the
key/value cache against the full forward pass (in the model and in play), the
zone selection rule, the pruned datasets, the config checks and determinism."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from qdnb.book.registry import config
from qdnb.chapters.ch4_qdt import QDTConfig, QDTTask
from qdnb.core.evaluation import Evaluation
from qdnb.envs import make_env
from qdnb.models.qdt.data import (
    Trajectories,
    density,
    prune,
    removed_region,
    removed_tiles,
    removed_upper,
    select_policies,
)
from qdnb.models.qdt.evaluate import cache_bytes, play, rollout_chunks
from qdnb.models.qdt.model import QDT, init_params, scale_to_box, unscale_from_box
from qdnb.models.qdt.train import (
    batch_indices,
    conditioning_gap,
    fit,
    loss_fn,
    make_train_step,
    shuffled_descriptors,
)
from qdnb.nets.transformer import make_optimizer
from qdnb.qd.repertoire import Repertoire

B, T, BD, OBS, ACT = 2, 6, 2, 5, 3


def small_qdt(**kwargs):
    return QDT(
        **{
            "action_size": ACT,
            "max_steps": T,
            "embed_dim": 32,
            "num_layers": 2,
            "num_heads": 4,
            "dropout": 0.0,
            **kwargs,
        }
    )


def inputs(key, batch=B, steps=T):
    k1, k2, k3 = jax.random.split(key, 3)
    return (
        jax.random.normal(k1, (batch, BD)),
        jax.random.normal(k2, (batch, steps, OBS)),
        jax.random.uniform(k3, (batch, steps, ACT), minval=-1.0, maxval=1.0),
    )


def perturbed(params, key, scale=0.1):
    """The parameters plus noise, so that biases and LayerNorm scales are not 0 and 1."""
    leaves, tree = jax.tree.flatten(params)
    keys = jax.random.split(key, len(leaves))
    return jax.tree.unflatten(
        tree, [x + scale * jax.random.normal(k, x.shape) for x, k in zip(leaves, keys)]
    )


@pytest.fixture(scope="module")
def qdt():
    model = small_qdt()
    params = perturbed(init_params(model, jax.random.PRNGKey(0), BD, OBS), jax.random.PRNGKey(1))
    return model, params


@pytest.fixture(scope="module")
def forward(qdt):
    """The full forward pass, compiled once for the shapes of ``inputs``."""
    model, params = qdt
    apply = jax.jit(model.apply)
    return lambda bd, obs, actions: np.asarray(apply(params, bd, obs, actions))


def layer_norm(x, scale, bias):
    x = np.asarray(x, np.float64)
    mean, var = x.mean(-1, keepdims=True), x.var(-1, keepdims=True)
    return (x - mean) / np.sqrt(var + 1e-6) * np.asarray(scale) + np.asarray(bias)


def dense(p, x):
    return np.asarray(x, np.float64) @ np.asarray(p["kernel"], np.float64) + np.asarray(
        p["bias"], np.float64
    )


# ----- the model -----


def test_predictions_are_causal_in_observations_and_actions(forward):
    bd, obs, actions = inputs(jax.random.PRNGKey(2))
    pred = forward(bd, obs, actions)
    assert pred.shape == (B, T, ACT)  # (a linear head: Algorithm 8's Pred_A)
    noise = jax.random.normal(jax.random.PRNGKey(3), (B, ACT))
    for k in range(T):
        # O_k is seen from the prediction of A_k on, never before
        moved = forward(bd, obs.at[:, k, :ACT].add(noise), actions)
        np.testing.assert_allclose(moved[:, :k], pred[:, :k], atol=1e-6)
        assert np.abs(moved[:, k] - pred[:, k]).max() > 1e-3
        # A_k is predicted at O_k, before the A_k token: only A_{k+1}.. see it
        moved = forward(bd, obs, actions.at[:, k].add(noise))
        np.testing.assert_allclose(moved[:, : k + 1], pred[:, : k + 1], atol=1e-6)
        if k < T - 1:
            assert np.abs(moved[:, k + 1 :] - pred[:, k + 1 :]).max() > 1e-3
    # the BD token comes first: every prediction, A_0 included, depends on it
    moved = forward(bd + 1.0, obs, actions)
    assert np.all(np.abs(moved[:, 0] - pred[:, 0]).max(axis=-1) > 1e-3)


def test_tokens_interleave_bd_observation_action_per_timestep(qdt):
    model, params = qdt
    bd, obs, actions = inputs(jax.random.PRNGKey(4))
    tokens = np.asarray(model.apply(params, bd, obs, actions, jnp.arange(T), method=QDT.tokens))
    assert tokens.shape == (B, 3 * T, 32)
    p = params["params"]
    step = np.asarray(p["embed_timestep"]["embedding"], np.float64)[:T]  # (T, D)
    ln = lambda x: layer_norm(x, p["embed_ln"]["scale"], p["embed_ln"]["bias"])
    expected = np.empty((B, 3 * T, 32))
    expected[:, 0::3] = ln(dense(p["embed_bd"], bd)[:, None, :] + step)
    expected[:, 1::3] = ln(dense(p["embed_obs"], obs) + step)
    expected[:, 2::3] = ln(dense(p["embed_action"], actions) + step)
    np.testing.assert_allclose(tokens, expected, atol=1e-5)


def test_the_three_tokens_of_a_timestep_share_its_embedding(qdt):
    model, params = qdt
    p = dict(params["params"])
    for name in ("embed_bd", "embed_obs", "embed_action"):
        p[name] = jax.tree.map(jnp.zeros_like, p[name])
    bd, obs, actions = inputs(jax.random.PRNGKey(5))
    tokens = np.asarray(
        model.apply({"params": p}, bd, obs, actions, jnp.arange(T), method=QDT.tokens)
    )
    expected = layer_norm(
        p["embed_timestep"]["embedding"][:T], p["embed_ln"]["scale"], p["embed_ln"]["bias"]
    )
    for t in range(T):
        for i in range(3):
            np.testing.assert_allclose(
                tokens[:, 3 * t + i], np.broadcast_to(expected[t], (B, 32)), atol=1e-5
            )
    # and the rows differ from one timestep to the next
    assert min(np.abs(expected[t] - expected[u]).max() for t in range(T) for u in range(t)) > 1e-2
    # timesteps given per trajectory pick their own rows
    shifted = np.asarray(
        model.apply({"params": p}, bd, obs, actions, jnp.arange(T)[::-1], method=QDT.tokens)
    )
    np.testing.assert_allclose(shifted[:, 0], np.broadcast_to(expected[T - 1], (B, 32)), atol=1e-5)


def test_prefill_and_decode_steps_reproduce_the_full_forward_pass(qdt, forward):
    model, params = qdt
    bd, obs, actions = inputs(jax.random.PRNGKey(6))
    full = forward(bd, obs, actions)
    cache = model.apply(params, B, method=QDT.init_cache)
    assert len(cache) == 2 and cache[0][0].shape == (B, 3 * T, 4, 8)
    action, cache = model.apply(params, bd, obs[:, 0], cache, method=QDT.prefill)
    np.testing.assert_allclose(action, full[:, 0], atol=1e-5)
    decode = jax.jit(
        lambda *args: model.apply(params, *args, method=QDT.decode_step)
    )  # t traced, as in play
    for t in range(1, T):
        action, cache = decode(bd, actions[:, t - 1], obs[:, t], jnp.int32(t), cache)
        np.testing.assert_allclose(action, full[:, t], atol=1e-5)
    # the cache now holds the keys of every token but the last A: those of the full sequence
    assert np.abs(np.asarray(cache[0][0][:, : 3 * T - 1])).max() > 0
    np.testing.assert_array_equal(np.asarray(cache[0][0][:, 3 * T - 1]), 0.0)


# ----- training -----


def trajectories(key, n=3, steps=T, valid_steps=(T, 4, 2)):
    bd, obs, actions = inputs(key, n, steps)
    valid = jnp.arange(steps)[None, :] < jnp.asarray(valid_steps)[:, None]
    return Trajectories(
        bd=bd,
        obs=obs,
        actions=actions,
        valid=valid,
        fitness=jnp.arange(n, dtype=jnp.float32),
        policy=jnp.arange(n),
    )


def test_loss_is_the_mean_squared_error_over_valid_steps_only(qdt):
    model, params = qdt
    batch = trajectories(jax.random.PRNGKey(7))
    pred = np.asarray(model.apply(params, batch.bd, batch.obs, batch.actions), np.float64)
    err = ((pred - np.asarray(batch.actions, np.float64)) ** 2).mean(-1)  # (N, T)
    valid = np.asarray(batch.valid)
    assert valid.sum() == T + 4 + 2
    expected = err[valid].mean()
    assert abs(expected - err.mean()) > 1e-4  # the mask matters here
    loss_of = jax.jit(lambda b: loss_fn(model, params, b))
    loss = float(loss_of(batch))
    np.testing.assert_allclose(loss, expected, rtol=1e-5)
    # the invalid steps end their trajectories: whatever they hold, the loss is the same
    later = ~valid[:, :, None]
    junk = batch.replace(
        actions=jnp.where(later, 0.9, batch.actions), obs=jnp.where(later, 7.0, batch.obs)
    )
    assert not np.allclose(junk.actions, batch.actions)
    np.testing.assert_allclose(float(loss_of(junk)), loss, rtol=1e-6)
    # whereas a valid step counts
    changed = batch.replace(actions=batch.actions.at[2, 1].set(-batch.actions[2, 1]))
    assert abs(float(loss_of(changed)) - loss) > 1e-4
    # a batch without any valid step gives 0, not nan
    empty = batch.replace(valid=jnp.zeros_like(batch.valid))
    assert float(loss_of(empty)) == 0.0


def test_training_steps_lower_the_loss_on_a_fixed_batch():
    model = small_qdt()
    batch = trajectories(jax.random.PRNGKey(8), n=4, valid_steps=(T, T, 5, 3))
    params = init_params(model, jax.random.PRNGKey(9), BD, OBS)
    optimizer = make_optimizer(1e-3)
    step = make_train_step(model, optimizer)
    opt_state = optimizer.init(params)
    start = float(loss_fn(model, params, batch))
    losses = []
    for i in range(8):
        params, opt_state, loss = step(params, opt_state, batch, jax.random.PRNGKey(i))
        losses.append(float(loss))
    np.testing.assert_allclose(losses[0], start, rtol=1e-5)  # the loss before the first update
    end = float(loss_fn(model, params, batch))
    assert end < 0.9 * start
    assert losses[-1] < losses[0]


def test_fit_is_deterministic_and_keeps_the_best_evaluation():
    model = small_qdt(dropout=0.1)
    data = trajectories(jax.random.PRNGKey(10), n=6, valid_steps=(T, T, 4, 5, 2, T))
    step = make_train_step(model, make_optimizer(1e-3))
    calls = []

    def evaluate(params, step_done):
        calls.append(step_done)
        return {"avg_distance": {2: 2.0, 4: 1.0, 6: 3.0, 8: 1.5}[step_done]}

    run = lambda steps, key=11: fit(
        model,
        data,
        jax.random.PRNGKey(key),
        steps=steps,
        batch_size=4,
        learning_rate=1e-3,
        eval_every=2,
        evaluate=evaluate,
        step=step,
        progress=False,
    )
    a, b = run(8), run(8)
    assert calls == [2, 4, 6, 8] * 2
    assert len(a.losses) == 4 and a.losses == b.losses  # float equality
    assert jax.tree.all(jax.tree.map(lambda x, y: bool(jnp.array_equal(x, y)), a.params, b.params))
    # step 4 evaluated best: its parameters are kept, those a 4-step run ends with
    assert a.best_step == 4 and [e["step"] for e in a.evaluations] == [2, 4, 6, 8]
    four = run(4)
    assert four.losses == a.losses[:2]
    assert jax.tree.all(
        jax.tree.map(lambda x, y: bool(jnp.array_equal(x, y)), a.params, four.params)
    )
    assert run(2, key=12).losses[0] != a.losses[0]  # another key trains differently


def test_every_dataset_gets_the_same_number_of_gradient_steps():
    """The budget is counted in updates: a dataset 10 times larger gets as many steps,
    each on a full batch, and every trajectory is read once a pass."""
    sizes, seen = (3, 8, 80), {}
    for n in sizes:
        data = trajectories(jax.random.PRNGKey(n), n=n, valid_steps=(T,) * n)
        calls = []
        fit(
            small_qdt(),
            data,
            jax.random.PRNGKey(0),
            steps=6,
            batch_size=4,
            learning_rate=1e-3,
            eval_every=3,
            evaluate=lambda params, s: calls.append(s) or {"avg_distance": 0.0},
            progress=False,
        )
        seen[n] = calls
        order = batch_indices(jax.random.PRNGKey(1), n, 4, 0, 40)
        assert order.shape == (40, 4)
        per_pass = max(1, n // 4)
        for p in range(40 // per_pass):  # each pass: distinct trajectories, one permutation
            rows = order[p * per_pass : (p + 1) * per_pass].ravel()
            assert len(set(rows)) == min(n, rows.size) and set(rows) <= set(range(n))
        # a step's batch depends on its number only: resuming at step 7 reads the same
        np.testing.assert_array_equal(batch_indices(jax.random.PRNGKey(1), n, 4, 7, 5), order[7:12])
    assert all(calls == [3, 6] for calls in seen.values())


def test_the_shuffled_descriptor_diagnostic_shows_a_used_conditioning():
    """A hand-made dataset whose actions are set by the BD alone (a = tanh(2 bd) on
    every step, observations pure noise): a tiny QDT trained on it predicts held-out
    actions well from the true BD and badly from a BD shuffled between demonstrators;
    an untrained one shows no gap."""
    key = jax.random.PRNGKey(21)

    def demonstrations(k, per_policy):
        n = 6 * per_policy
        k_bd, k_obs = jax.random.split(k)
        bd = jnp.repeat(jax.random.uniform(k_bd, (6, BD), minval=-1.0, maxval=1.0), per_policy, 0)
        bd = bd + 0.01 * jax.random.normal(k_obs, bd.shape)
        actions = jnp.broadcast_to(jnp.tanh(2 * bd[:, None, :1].repeat(ACT, -1)), (n, T, ACT))
        return Trajectories(
            bd=bd,
            obs=jax.random.normal(k_obs, (n, T, OBS)),
            actions=actions,
            valid=jnp.ones((n, T), bool),
            fitness=jnp.zeros(n),
            policy=jnp.repeat(jnp.arange(6), per_policy),
        )

    train, heldout = demonstrations(key, 8), demonstrations(jax.random.fold_in(key, 1), 2)
    shuffled = shuffled_descriptors(heldout, jax.random.PRNGKey(3))
    policy = np.asarray(heldout.policy)
    source = [int(np.flatnonzero(np.all(np.asarray(heldout.bd) == b, -1))[0]) for b in shuffled.bd]
    assert all(policy[i] != policy[j] for i, j in enumerate(source))  # another demonstrator's BD
    model = small_qdt(embed_dim=16, num_layers=1, num_heads=2)
    res = fit(
        model,
        train,
        jax.random.PRNGKey(4),
        steps=150,
        batch_size=8,
        learning_rate=3e-3,
        eval_every=150,
        evaluate=lambda p, s: {"avg_distance": 0.0},
        progress=False,
    )
    trained = conditioning_gap(model, res.params, heldout, jax.random.PRNGKey(3))
    untrained = conditioning_gap(
        model, init_params(model, jax.random.PRNGKey(4), BD, OBS), heldout, jax.random.PRNGKey(3)
    )
    assert trained["heldout_mse"] < 0.05 and trained["gap"] > 5 * trained["heldout_mse"]
    assert abs(untrained["gap"]) < 0.1 * untrained["heldout_mse"]
    with pytest.raises(ValueError, match="at least two"):
        shuffled_descriptors(heldout.subset(policy == 0), jax.random.PRNGKey(0))
    alone = conditioning_gap(model, res.params, heldout.subset(policy == 0), jax.random.PRNGKey(0))
    assert np.isnan(alone["gap"]) and alone["heldout_mse"] < 0.05  # one demonstrator: no gap


def test_the_labelled_departures_from_algorithm_8():
    """The thesis's linear head predicts outside [-1, 1]; the tanh head cannot; PyTorch's
    initialisation gives the BD embedding a bias, which tells BDs on one ray apart;
    scaling the BD from its box inverts (to float32 rounding); unknown readings are refused."""
    low, high = (-15.0, -15.0), (15.0, 15.0)
    bd = jnp.array([[2.0, 2.0], [8.0, 8.0], [-15.0, 15.0], [0.0, 0.0]])
    eps = 30 * np.finfo(np.float32).eps  # float32 rounding at the box's size (30)
    np.testing.assert_allclose(
        unscale_from_box(scale_to_box(bd, low, high), low, high), bd, rtol=0, atol=4 * eps
    )
    np.testing.assert_array_equal(scale_to_box(bd, low, high)[2:], [[-1.0, 1.0], [0.0, 0.0]])
    bd, obs, actions = inputs(jax.random.PRNGKey(30))
    outs = {}
    for head in ("linear", "tanh"):
        model = small_qdt(head=head)
        params = init_params(model, jax.random.PRNGKey(31), BD, OBS)
        big = jax.tree.map(lambda x: 50 * x, params)
        outs[head] = np.abs(np.asarray(model.apply(big, 10 * bd, obs, actions))).max()
    assert outs["linear"] > 1.0 and outs["tanh"] <= 1.0

    def ray_similarity(init):
        model = small_qdt(init_scheme=init)
        params = init_params(model, jax.random.PRNGKey(32), BD, OBS)
        tokens = model.apply(
            params,
            jnp.array([[2.0, 2.0], [8.0, 8.0]]),
            obs[:1].repeat(2, 0),
            actions[:1].repeat(2, 0),
            jnp.arange(T),
            method=QDT.tokens,
        )
        a, b = np.asarray(tokens[0, 0]), np.asarray(tokens[1, 0])  # the BD tokens of step 0
        return a @ b / np.linalg.norm(a) / np.linalg.norm(b)

    assert ray_similarity("flax") > 0.99 > ray_similarity("torch")
    for bad in ({"head": "softmax"}, {"init_scheme": "xavier"}):
        with pytest.raises(ValueError, match="unknown"):
            init_params(small_qdt(**bad), jax.random.PRNGKey(0), BD, OBS)


def test_fit_and_the_config_reject_bad_settings():
    model = small_qdt()
    data = trajectories(jax.random.PRNGKey(13))
    never = lambda params, step: pytest.fail("evaluated")
    for steps, eval_every in ((3, 2), (0, 1), (2, 0)):
        with pytest.raises(ValueError, match="multiple of eval_every"):
            fit(
                model,
                data,
                jax.random.PRNGKey(0),
                steps=steps,
                batch_size=2,
                learning_rate=1e-3,
                eval_every=eval_every,
                evaluate=never,
                progress=False,
            )
    with pytest.raises(ValueError, match="empty"):
        fit(
            model,
            data.subset(np.zeros(3, bool)),
            jax.random.PRNGKey(0),
            steps=1,
            batch_size=2,
            learning_rate=1e-3,
            eval_every=1,
            evaluate=never,
            progress=False,
        )
    tiny = config("ch4_qdt", "tiny")
    assert isinstance(tiny, QDTConfig) and isinstance(tiny.task("ant_omni"), QDTTask)
    assert tiny.task("halfcheetah_uni") is tiny.halfcheetah_uni
    for bad in ({"train_steps": 3, "eval_every": 2}, {"train_steps": 0}, {"eval_every": 0}):
        with pytest.raises(ValueError, match="multiple of eval_every"):
            dataclasses.replace(tiny, **bad)
    with pytest.raises(ValueError, match="multiple of num_heads"):
        dataclasses.replace(tiny, embed_dim=10, num_heads=4)
    with pytest.raises(ValueError, match="unknown environments"):
        dataclasses.replace(tiny, environments=("ant_omni", "antmaze"))
    with pytest.raises(ValueError, match="unknown environment"):
        tiny.task("pointmaze")
    for bad in (0, tiny.num_seeds + 1):
        with pytest.raises(ValueError, match="full_seeds"):
            dataclasses.replace(tiny, full_seeds=bad)
    with pytest.raises(ValueError, match="unknown scale"):
        config("ch4_qdt", "nope")


# ----- playing the QDT -----


def test_cached_play_matches_the_uncached_reference_on_ant_omni():
    env = make_env("ant_omni", episode_length=12)
    model = QDT(
        action_size=env.action_size,
        max_steps=12,
        embed_dim=32,
        num_layers=2,
        num_heads=4,
        dropout=0.0,
    )
    params = jax.jit(lambda k: init_params(model, k, env.descriptor_size, env.observation_size))(
        jax.random.PRNGKey(14)
    )
    params = perturbed(params, jax.random.PRNGKey(15), scale=0.05)
    goals = jnp.array([[1.0, 2.0], [-3.0, 0.5]])
    g, e = goals.shape[0], 2
    cached = play(env, model, params, goals, jax.random.PRNGKey(16), e, cached=True)
    reference = play(env, model, params, goals, jax.random.PRNGKey(16), e, cached=False)
    for ev in (cached, reference):
        assert ev.trajectory.shape == (g, e, 12, env.action_size)
        assert ev.descriptor.shape == (g, e, env.descriptor_size)
        assert ev.fitness.shape == (g, e) and ev.length.shape == (g, e)
        assert np.all((np.asarray(ev.length) >= 1) & (np.asarray(ev.length) <= 12))
    # the first actions agree to float precision; later ones only drift as the dynamics amplify
    # rounding
    np.testing.assert_allclose(cached.trajectory[:, :, 0], reference.trajectory[:, :, 0], atol=1e-5)
    np.testing.assert_allclose(cached.trajectory, reference.trajectory, atol=1e-3)
    np.testing.assert_allclose(cached.descriptor, reference.descriptor, atol=1e-3)
    np.testing.assert_allclose(cached.fitness, reference.fitness, rtol=1e-3, atol=1e-3)
    np.testing.assert_array_equal(cached.length, reference.length)
    # the goals and the starts matter: the actions are not all the same
    actions = np.asarray(cached.trajectory)
    assert (
        np.abs(actions[0] - actions[1]).max() > 1e-3
        and np.abs(actions[:, 0] - actions[:, 1]).max() > 1e-3
    )
    with pytest.raises(ValueError, match="timesteps"):
        play(
            env, dataclasses.replace(model, max_steps=11), params, goals, jax.random.PRNGKey(16), e
        )
    # the goals played in two groups, one after another: the same episodes
    grouped = play(env, model, params, goals, jax.random.PRNGKey(16), e, chunks=2)
    np.testing.assert_allclose(grouped.trajectory[:, :, 0], cached.trajectory[:, :, 0], atol=1e-5)
    np.testing.assert_allclose(grouped.trajectory, cached.trajectory, atol=1e-3)
    np.testing.assert_allclose(grouped.descriptor, cached.descriptor, atol=1e-3)
    np.testing.assert_array_equal(grouped.length, cached.length)
    with pytest.raises(ValueError, match="chunks must divide the 2 goals, not 3"):
        play(env, model, params, goals, jax.random.PRNGKey(16), e, chunks=3)


def test_rollouts_are_grouped_only_when_their_cache_crowds_the_memory():
    # the paper QDT on Ant-Omni: 4 layers, width 256, 250 timesteps, 100 goals x 10 episodes
    model = QDT(action_size=8, max_steps=250, embed_dim=256, num_layers=4, num_heads=4, dropout=0)
    assert cache_bytes(model, 1000) == 1000 * 2 * 4 * 3 * 250 * 256 * 4  # 6.1 GB
    assert rollout_chunks(model, 100, 10, 80 * 2**30) == 1  # an H100: all at once
    assert rollout_chunks(model, 100, 10, 24 * 2**30) == 2  # 24 GiB: 3.1 GB of cache a group
    assert rollout_chunks(model, 100, 10, 16 * 2**30) == 4  # 16 GiB: 1.5 GB a group
    assert rollout_chunks(model, 7, 10, 2**20) == 7  # never more groups than goals


# ----- the datasets -----


class FakePlayer:
    """Plays the policy whose genotype is ``{"w": [cell]}``: its episodes end at
    ``descriptors[cell]`` with ``fitnesses[cell]``."""

    def __init__(self, descriptors, fitnesses):
        self.descriptors, self.fitnesses = np.asarray(descriptors), np.asarray(fitnesses)
        self.played = []

    def episodes(self, num_episodes):
        assert num_episodes == self.descriptors.shape[1]

        def run(genotypes, key):
            cells = np.asarray(genotypes["w"][:, 0]).astype(int)
            self.played.append(cells)
            return Evaluation(
                fitness=jnp.asarray(self.fitnesses[cells]),
                descriptor=jnp.asarray(self.descriptors[cells]),
                length=jnp.full((cells.size, num_episodes), 10),
            )

        return run


def test_select_policies_keeps_the_most_consistent_policy_of_each_zone():
    zones = jnp.array([[0.0, 0.0], [10.0, 0.0], [0.0, 10.0], [10.0, 10.0]])
    z = np.asarray(zones)
    n = 9
    stored = np.array(
        [
            [0.5, 0.0],
            [0.0, 0.0],
            [1.0, 1.0],
            [9.0, 0.0],
            [10.0, 1.0],
            [11.0, -1.0],
            [10.0, 10.0],
            [9.0, 9.0],
            [0.0, 0.0],
        ]
    )
    fitnesses = np.array(
        [1.0, -np.inf, 0.5, 2.0, 3.0, 10.0, 1.0, 1.0, -np.inf]
    )  # cells 1 and 8 are empty
    # episodes (4 each) land at the centroid of these zones
    lands = np.array(
        [
            [0, 0, 2, 2],  # cell 0, zone 0: hit 0.5, fitness 1
            [0, 0, 0, 0],  # empty
            [0, 0, 0, 1],  # cell 2, zone 0: hit 0.75, fitness 0.5 -> kept (hits first)
            [1, 1, 3, 3],  # cell 3, zone 1: hit 0.5, fitness 2
            [1, 0, 1, 2],  # cell 4, zone 1: hit 0.5, fitness 3 -> kept (tie: fitness)
            [1, 0, 0, 0],  # cell 5, zone 1: hit 0.25, fitness 10
            [3, 3, 3, 3],  # cell 6, zone 3: hit 1, fitness 1 -> kept (tie: lower cell)
            [3, 3, 3, 3],  # cell 7, zone 3: hit 1, fitness 1
            [2, 2, 2, 2],
        ]
    )  # empty; zone 2 has no stored policy and keeps nothing
    episode_fitness = np.array(
        [
            [0.0, 2.0, 1.0, 1.0],
            [9, 9, 9, 9],
            [0.5] * 4,
            [2.0] * 4,
            [1.0, 5.0, 3.0, 3.0],
            [10.0] * 4,
            [1.0] * 4,
            [1.0] * 4,
            [9, 9, 9, 9],
        ]
    )
    player = FakePlayer(z[lands] + 0.1, episode_fitness)
    repertoire = Repertoire(
        genotypes={"w": jnp.arange(n)[:, None] * 1.0},
        fitnesses=jnp.asarray(fitnesses),
        descriptors=jnp.asarray(stored),
        centroids=jnp.asarray(stored) + 0.01,
    )
    sel = select_policies(repertoire, zones, player, 4, jax.random.PRNGKey(0))
    assert len(player.played) == 1
    np.testing.assert_array_equal(player.played[0], [0, 2, 3, 4, 5, 6, 7])  # empty cells never play
    np.testing.assert_array_equal(sel.all_cells, [0, 2, 3, 4, 5, 6, 7])
    np.testing.assert_array_equal(sel.all_hit_rate, [0.5, 0.75, 0.5, 0.5, 0.25, 1.0, 1.0])
    np.testing.assert_allclose(sel.all_fitness, [1.0, 0.5, 2.0, 3.0, 10.0, 1.0, 1.0])
    np.testing.assert_array_equal(sel.cells, [2, 4, 6])
    np.testing.assert_array_equal(sel.zones, [0, 1, 3])
    np.testing.assert_array_equal(sel.hit_rate, [0.75, 0.5, 1.0])
    np.testing.assert_allclose(sel.fitness, [0.5, 3.0, 1.0])
    empty = repertoire.replace(fitnesses=jnp.full((n,), -jnp.inf))
    with pytest.raises(ValueError, match="empty"):
        select_policies(empty, zones, player, 4, jax.random.PRNGKey(0))


def points_dataset(bd):
    n = bd.shape[0]
    return Trajectories(
        bd=jnp.asarray(bd),
        obs=jnp.zeros((n, 2, 1)),
        actions=jnp.zeros((n, 2, 1)),
        valid=jnp.ones((n, 2), bool),
        fitness=jnp.zeros(n),
        policy=jnp.arange(n),
    )


def test_pruned_datasets_keep_fractions_and_drop_regions():
    low, high = np.zeros(2), np.ones(2)
    rng = np.random.default_rng(0)
    bd = rng.uniform(0.02, 0.98, (40, 2)).astype(np.float32)
    bd = bd[np.all(np.abs(bd - 0.5) > 0.02, axis=1)]  # nothing on the middle lines
    n = bd.shape[0]
    data = points_dataset(bd)
    for name, fraction in (("50%", 0.5), ("30%", 0.3), ("10%", 0.1)):
        kept = prune(data, name, low, high, 2, jax.random.PRNGKey(1))
        policy = np.asarray(kept.policy)
        assert kept.size == round(n * fraction) == len(set(policy.tolist()))
        np.testing.assert_array_equal(
            np.asarray(kept.bd), bd[policy]
        )  # whole trajectories, unchanged
        np.testing.assert_array_equal(np.asarray(removed_region(name, bd, low, high, 2)), False)
    half = lambda key: set(np.asarray(prune(data, "50%", low, high, 2, key).policy).tolist())
    assert half(jax.random.PRNGKey(1)) == half(jax.random.PRNGKey(1)) != half(jax.random.PRNGKey(2))
    # tiles=2: the squares (0, 1) and (1, 0) go
    left, bottom = bd[:, 0] < 0.5, bd[:, 1] < 0.5
    in_odd_square = left != bottom
    assert 0 < in_odd_square.sum() < n
    np.testing.assert_array_equal(removed_tiles(bd, low, high, 2), in_odd_square)
    tiles = prune(data, "tiles", low, high, 2, jax.random.PRNGKey(1))
    np.testing.assert_array_equal(np.asarray(tiles.policy), np.flatnonzero(~in_odd_square))
    # on a shifted, scaled space too
    np.testing.assert_array_equal(removed_tiles(bd * 4 - 1, low - 1, high * 3, 2), in_odd_square)
    # upper: the second descriptor above the middle goes
    upper = bd[:, 1] > 0.5
    np.testing.assert_array_equal(removed_upper(bd, low, high), upper)
    np.testing.assert_array_equal(
        np.asarray(prune(data, "upper", low, high, 2, jax.random.PRNGKey(1)).bd), bd[~upper]
    )
    with pytest.raises(ValueError, match="unknown pruning"):
        removed_region("left", bd, low, high, 2)
    with pytest.raises(ValueError, match="unknown pruning"):
        prune(data, "left", low, high, 2, jax.random.PRNGKey(1))
    counts = density(bd, low, high, 2)
    assert counts.shape == (2, 2) and counts.sum() == n
    # rows are the second descriptor
    np.testing.assert_array_equal(
        counts,
        [
            [np.sum(left & bottom), np.sum(~left & bottom)],
            [np.sum(left & ~bottom), np.sum(~left & ~bottom)],
        ],
    )


def test_recorded_datasets_are_the_episodes_the_policies_play():
    """``record`` (a recording Player) gives the same fitness and descriptors as the
    plain Player, one trajectory per (kept policy, episode), labelled with the
    descriptor it achieved, and obs/actions that replay to it."""
    from qdnb.envs.player import Player
    from qdnb.models.qdt.data import record
    from qdnb.nets.mlp import MLP, init_policies

    env = make_env("pointmaze", episode_length=15)
    net = MLP((8, env.action_size))
    params = init_policies(net, jax.random.PRNGKey(0), 4, env.observation_size)
    rep = Repertoire(
        genotypes=params,
        fitnesses=jnp.array([1.0, -jnp.inf, 2.0, 3.0]),
        descriptors=jnp.zeros((4, 2)),
        centroids=jnp.zeros((4, 2)),
    )
    data = record(
        rep, np.array([0, 3]), 3, Player(env, net, chunk=4, record=True), jax.random.PRNGKey(1)
    )
    assert data.size == 6 and data.obs.shape == (6, 15, env.observation_size)
    assert data.actions.shape == (6, 15, env.action_size) and data.valid.shape == (6, 15)
    np.testing.assert_array_equal(data.policy, [0, 0, 0, 3, 3, 3])
    plain = Player(env, net, chunk=4).play(
        jax.tree.map(lambda x: x[np.array([0, 0, 0, 3, 3, 3])], params),
        jax.random.split(jax.random.PRNGKey(1), 6),
    )
    np.testing.assert_allclose(data.bd, plain.descriptor, atol=1e-6)
    np.testing.assert_allclose(data.fitness, plain.fitness, atol=1e-5)
    # the recorded actions are the policy's actions on the recorded observations
    replay = jax.vmap(lambda p, o: net.apply(p, o))(
        jax.tree.map(lambda x: x[data.policy], params), data.obs
    )
    np.testing.assert_allclose(replay, data.actions, atol=1e-5)


def test_repertoires_are_reused_only_under_the_same_config_and_seed(tmp_path, monkeypatch):
    """``load_or_recompute_repertoires`` loads matching files, recomputes (and saves)
    missing ones and those saved under another config, and says which happened."""
    from qdnb.chapters import ch4_qdt as qdt_data
    from qdnb.chapters.ch4_reproducibility import save_repertoires
    from qdnb.core import paths
    from qdnb.core.config import config_hash

    monkeypatch.setattr(paths, "RUNS", tmp_path)
    repro = dataclasses.replace(config("ch4_reproducibility", "tiny"), environments=("ant_omni",))
    stub = Repertoire(
        genotypes={"w": jnp.ones((1, 3, 2))},
        fitnesses=jnp.array([[1.0, -jnp.inf, 2.0]]),
        descriptors=jnp.zeros((1, 3, 2)),
        centroids=jnp.zeros((1, 3, 2)),
    )
    calls = []

    def fake_run_environment(cfg, env_name, key, progress, methods):
        from types import SimpleNamespace

        calls.append(methods)
        one = SimpleNamespace(
            repertoire=stub,
            spread_at_insertion=np.zeros((1, 3)),
            reassessed_spread=np.zeros((1, 3)),
        )
        return SimpleNamespace(methods={m: one for m in methods})

    from qdnb.chapters.ch4_qdt import repertoires

    monkeypatch.setattr(repertoires, "run_chapter4", fake_run_environment)  # where it is read
    good = qdt_data.repertoire_path("tiny", "ant_omni", "ME")
    save_repertoires(good, config_hash(repro), stub, np.zeros((1, 3)), np.zeros((1, 3)))
    save_repertoires(
        qdt_data.repertoire_path("tiny", "ant_omni", "ME-LS"),
        "another-config",
        stub,
        np.zeros((1, 3)),
        np.zeros((1, 3)),
    )
    reps, status = qdt_data.load_or_recompute_repertoires(repro, "tiny", 0, progress=False)
    assert status["ant_omni"]["ME"] == "loaded"
    assert status["ant_omni"]["ME-LS"] == "recomputed: computed under another config"
    assert status["ant_omni"]["PGA-ME"] == status["ant_omni"]["PGA-ME-LS"] == "recomputed: missing"
    assert calls == [("ME-LS", "PGA-ME", "PGA-ME-LS")]  # one run, only what was needed
    np.testing.assert_array_equal(reps["ant_omni"]["PGA-ME"]["fitnesses"], stub.fitnesses)
    _, status = qdt_data.load_or_recompute_repertoires(repro, "tiny", 0, progress=False)
    assert (
        set(status["ant_omni"].values()) == {"loaded"} and len(calls) == 1
    )  # saved the first time


def test_a_qdt_with_no_data_is_recorded_as_untrained_beside_trained_ones():
    from qdnb.chapters.ch4_qdt import QDTRun, untrained_run

    cfg = config("ch4_qdt", "tiny")
    empty = untrained_run(cfg, num_goals=5, num_zones=3)
    trained = dict(empty, avg_distance=0.3, distance=np.full(5, 0.3), dataset_size=12)
    trained["best_step"] = cfg.train_steps
    run = QDTRun.stack([trained, empty])  # the same shapes: seeds stack
    evaluations = cfg.train_steps // cfg.eval_every
    assert run.distance.shape == (2, 5) and run.loss.shape == (2, evaluations)
    assert run.imitation.shape == (2, 3)
    assert np.isnan(run.avg_distance[1]) and run.dataset_size[1] == 0
    assert not np.isnan(run.avg_distance[0])
