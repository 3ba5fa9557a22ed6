"""The peer: QDax 0.5.0's own QD-PG on its own Point-Maze, at the settings of its
``examples/qdpg.ipynb`` (environment ``pointmaze``, descriptors in its [-1, 1]^2): does
it reach the exit zone, after how many environment steps, on how many of 4 seeds, in
what wall time on this machine's cores.

The project never imports QDax: this script runs in a scratch environment of its own,
outside the project, e.g.

    python3.11 -m venv /tmp/qdaxenv
    /tmp/qdaxenv/bin/pip install qdax==0.5.0 jax==0.4.28 jaxlib==0.4.28 brax==0.10.4 \\
        flax==0.8.5
    /tmp/qdaxenv/bin/python bench/probes/qdax_qdpg.py [--seeds 0 1 2 3] [--iterations 100]

The example's settings: episodes of 250 steps; each iteration 34 quality-PG, 33
diversity-PG and 33 isoline (GA) offspring (100 episodes, 25,000 steps); 1,024 CVT
cells; 256 x 256 policies and critics; Adam at 3e-4 (critics, greedy actors) and 1e-3
(mutations); 300 critic steps and 100 policy-gradient steps an iteration; batch 256;
archive of 10,000 state descriptors, acceptance threshold 0.1; novelty the mean squared
distance to K = 5 neighbours; 100 iterations (2.5 * 10^6 steps).

The exit zone is QDax's (the 0.1-wide square at (-0.5, 0.8)), where an episode ends: a
seed reaches it at the first iteration whose grid holds a solution whose final position
lies in it (an episode that ends there scores about -24, so it takes its cell).
Resumable: a seed already in ``bench/results/qdax_qdpg.json`` is skipped, and a seed
under way saves its state every 10 iterations (``data/runs/bench/qdax_qdpg/seed<N>.pkl``,
about 400 MB with its replay buffers) and goes on from there when run again: a seed takes
one to two hours on 2 cores.
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import pickle
import platform
import statistics
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

RESULTS = Path(__file__).parents[1] / "results" / "qdax_qdpg.json"
CHECKPOINTS = Path(__file__).parents[2] / "data" / "runs" / "bench" / "qdax_qdpg"
SAVE_EVERY = 10
SETTINGS = dict(
    env_name="pointmaze",
    episode_length=250,
    policy_hidden_layer_sizes=(256, 256),
    iso_sigma=0.005,
    line_sigma=0.05,
    num_init_cvt_samples=50_000,
    num_centroids=1024,
    min_descriptor=-1.0,
    max_descriptor=1.0,
    quality_pg_batch_size=34,
    diversity_pg_batch_size=33,
    ga_batch_size=33,
    replay_buffer_size=1_000_000,
    critic_hidden_layer_size=(256, 256),
    critic_learning_rate=3e-4,
    greedy_learning_rate=3e-4,
    policy_learning_rate=1e-3,
    noise_clip=0.5,
    policy_noise=0.2,
    discount=0.99,
    reward_scaling=1.0,
    transitions_batch_size=256,
    soft_tau_update=0.005,
    num_critic_training_steps=300,
    num_pg_training_steps=100,
    policy_delay=2,
    archive_acceptance_threshold=0.1,
    archive_max_size=10_000,
    num_nearest_neighb=5,
    novelty_scaling_ratio=1.0,
)
ZONE_CENTRE, ZONE_HALF = (-0.5, 0.8), 0.05


def one_seed(seed: int, iterations: int) -> dict:
    import qdax
    import qdax.tasks.brax.v1 as environments
    from qdax.core.containers.archive import score_euclidean_novelty
    from qdax.core.containers.mapelites_repertoire import compute_cvt_centroids
    from qdax.core.emitters.dpg_emitter import DiversityPGConfig
    from qdax.core.emitters.qdpg_emitter import QDPGEmitter, QDPGEmitterConfig
    from qdax.core.emitters.qpg_emitter import QualityPGConfig
    from qdax.core.map_elites import MAPElites
    from qdax.core.neuroevolution.buffers.buffer import QDTransition
    from qdax.core.neuroevolution.networks.networks import MLP
    from qdax.tasks.brax.v1.env_creators import scoring_function_brax_envs

    s = SETTINGS
    env = environments.create(s["env_name"], episode_length=s["episode_length"])
    batch = s["quality_pg_batch_size"] + s["diversity_pg_batch_size"] + s["ga_batch_size"]
    policy = MLP(
        layer_sizes=s["policy_hidden_layer_sizes"] + (env.action_size,),
        kernel_init=jax.nn.initializers.lecun_uniform(),
        final_activation=jnp.tanh,
    )
    key = jax.random.key(seed)
    key, k_init = jax.random.split(key)
    params = jax.vmap(policy.init)(
        jax.random.split(k_init, batch), jnp.zeros((batch, env.observation_size))
    )

    def play_step(env_state, policy_params, key):
        actions = policy.apply(policy_params, env_state.obs)
        nxt = env.step(env_state, actions)
        transition = QDTransition(
            obs=env_state.obs,
            next_obs=nxt.obs,
            rewards=nxt.reward,
            dones=nxt.done,
            actions=actions,
            truncations=nxt.info["truncation"],
            state_desc=env_state.info["state_descriptor"],
            next_state_desc=nxt.info["state_descriptor"],
        )
        return nxt, policy_params, key, transition

    offset = environments.reward_offset[s["env_name"]]

    def metrics(repertoire):
        empty = repertoire.fitnesses == -jnp.inf
        d = repertoire.descriptors.reshape(-1, 2)
        in_zone = (
            (jnp.abs(d[:, 0] - ZONE_CENTRE[0]) <= ZONE_HALF)
            & (jnp.abs(d[:, 1] - ZONE_CENTRE[1]) <= ZONE_HALF)
            & ~empty.reshape(-1)
        )
        return {
            "max_fitness": jnp.max(repertoire.fitnesses),
            "coverage": jnp.mean(1.0 - empty),
            "qd_score": jnp.sum(repertoire.fitnesses, where=~empty)
            + offset * s["episode_length"] * jnp.sum(1.0 - empty),
            "exit_in_grid": jnp.any(in_zone),
        }

    td3 = dict(
        batch_size=s["transitions_batch_size"],
        critic_hidden_layer_size=s["critic_hidden_layer_size"],
        critic_learning_rate=s["critic_learning_rate"],
        actor_learning_rate=s["greedy_learning_rate"],
        policy_learning_rate=s["policy_learning_rate"],
        noise_clip=s["noise_clip"],
        policy_noise=s["policy_noise"],
        discount=s["discount"],
        reward_scaling=s["reward_scaling"],
        replay_buffer_size=s["replay_buffer_size"],
        soft_tau_update=s["soft_tau_update"],
        num_critic_training_steps=s["num_critic_training_steps"],
        num_pg_training_steps=s["num_pg_training_steps"],
        policy_delay=s["policy_delay"],
    )
    emitter = QDPGEmitter(
        config=QDPGEmitterConfig(
            qpg_config=QualityPGConfig(env_batch_size=s["quality_pg_batch_size"], **td3),
            dpg_config=DiversityPGConfig(
                env_batch_size=s["diversity_pg_batch_size"],
                archive_acceptance_threshold=s["archive_acceptance_threshold"],
                archive_max_size=s["archive_max_size"],
                **td3,
            ),
            iso_sigma=s["iso_sigma"],
            line_sigma=s["line_sigma"],
            ga_batch_size=s["ga_batch_size"],
        ),
        policy_network=policy,
        env=env,
        score_novelty=jax.jit(
            functools.partial(
                score_euclidean_novelty,
                num_nearest_neighb=s["num_nearest_neighb"],
                scaling_ratio=s["novelty_scaling_ratio"],
            )
        ),
    )
    scoring = functools.partial(
        scoring_function_brax_envs,
        episode_length=s["episode_length"],
        play_reset_fn=jax.jit(env.reset),
        play_step_fn=play_step,
        descriptor_extractor=environments.descriptor_extractor[s["env_name"]],
    )
    key, k_cvt = jax.random.split(key)
    centroids = compute_cvt_centroids(
        num_descriptors=env.descriptor_length,
        num_init_cvt_samples=s["num_init_cvt_samples"],
        num_centroids=s["num_centroids"],
        minval=s["min_descriptor"],
        maxval=s["max_descriptor"],
        key=k_cvt,
    )
    me = MAPElites(scoring_function=scoring, emitter=emitter, metrics_function=metrics)
    start = time.perf_counter()
    key, k_me = jax.random.split(key)
    repertoire, emitter_state, _ = me.init(params, centroids, k_me)

    @jax.jit
    def update(carry, _):
        repertoire, emitter_state, key = carry
        key, sub = jax.random.split(key)
        repertoire, emitter_state, m = me.update(repertoire, emitter_state, sub)
        return (repertoire, emitter_state, key), m

    carry = (repertoire, emitter_state, key)
    what = {"settings": SETTINGS, "iterations": iterations, "qdax": qdax.__version__}
    state = {"history": [], "steps_to_exit": None, "seconds": [], "done": 0, "wall": 0.0}
    saved = checkpoint_path(seed)
    if saved.exists():
        state = pickle.loads(saved.read_bytes())
        if state.pop("what", None) != what:
            raise SystemExit(f"{saved} was written by another run (settings, iterations or QDax)")
        carry = restore(carry, state.pop("carry"))
        print(f"seed {seed}: resumed after iteration {state['done']}", flush=True)
    history, steps_to_exit, seconds = state["history"], state["steps_to_exit"], state["seconds"]
    steps_per_iteration = batch * s["episode_length"]
    start -= state["wall"]  # the wall time of the sessions before this one
    for i in range(state["done"], iterations):
        tick = time.perf_counter()
        carry, m = update(carry, None)
        m = {k: float(v) for k, v in m.items()}
        seconds.append(time.perf_counter() - tick)
        history.append(m)
        if steps_to_exit is None and m["exit_in_grid"]:
            steps_to_exit = (i + 2) * steps_per_iteration  # the initial batch, then i + 1
        print(f"seed {seed} iteration {i + 1}: {m}", flush=True)
        if (i + 1) % SAVE_EVERY == 0 and i + 1 < iterations:
            state.update(done=i + 1, steps_to_exit=steps_to_exit, wall=time.perf_counter() - start)
            save(saved, carry, {**state, "what": what})
    return {
        "seed": seed,
        "reached_exit": steps_to_exit is not None,
        "steps_to_exit": steps_to_exit,
        "final_performance": history[-1]["max_fitness"],
        "coverage": history[-1]["coverage"],
        "wall_seconds": time.perf_counter() - start,
        # the first iteration compiles; the median of the rest is the steady rate
        "seconds_per_iteration_median": statistics.median(seconds[1:] or seconds),
        "iterations": iterations,
        "env_steps": (iterations + 1) * steps_per_iteration,
        "max_fitness_curve": [h["max_fitness"] for h in history],
        "qdax": qdax.__version__,
    }


def leaves(carry) -> list:
    """The carry's arrays on the host, typed random keys as their raw data."""
    out = []
    for leaf in jax.tree_util.tree_leaves(carry):
        dtype = getattr(leaf, "dtype", None)
        if dtype is not None and jnp.issubdtype(dtype, jax.dtypes.prng_key):
            leaf = jax.random.key_data(leaf)
        out.append(jax.device_get(leaf))
    return out


def checkpoint_path(seed: int) -> Path:
    return CHECKPOINTS / f"seed{seed}.pkl"


def restore(template, saved: list):
    """``template``'s structure (a freshly initialised carry) holding the saved arrays."""
    fresh, treedef = jax.tree_util.tree_flatten(template)
    if len(fresh) != len(saved):
        raise ValueError(f"checkpoint holds {len(saved)} arrays, the carry {len(fresh)}")
    out = []
    for leaf, array in zip(fresh, saved):
        dtype = getattr(leaf, "dtype", None)  # an initial carry may hold Python numbers
        if dtype is not None and jnp.issubdtype(dtype, jax.dtypes.prng_key):
            out.append(jax.random.wrap_key_data(array, impl=jax.random.key_impl(leaf)))
            continue
        if np.shape(leaf) != np.shape(array):
            raise ValueError(f"checkpoint array of shape {np.shape(array)}, carry {np.shape(leaf)}")
        out.append(jnp.asarray(array, dtype=dtype))
    return jax.tree_util.tree_unflatten(treedef, out)


def save(path: Path, carry, state: dict) -> None:
    """Write the checkpoint whole or not at all (a rename after the write)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    tmp.write_bytes(pickle.dumps({**state, "carry": leaves(carry)}))
    tmp.replace(path)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3])
    parser.add_argument("--iterations", type=int, default=100)
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()
    out = json.loads(args.out.read_text()) if args.out.exists() else {"rows": []}
    for seed in args.seeds:
        if any(r["seed"] == seed for r in out["rows"]):
            continue
        out["rows"].append(one_seed(seed, args.iterations))
        out.update(
            settings=SETTINGS,
            device=f"{jax.devices()[0].platform} x{jax.device_count()} "
            f"({os.cpu_count()} CPU cores, {platform.processor() or platform.machine()})",
            versions={"jax": jax.__version__},
            date=time.strftime("%Y-%m-%d"),
        )
        args.out.write_text(json.dumps(out, indent=1) + "\n")
        checkpoint_path(seed).unlink(missing_ok=True)  # only once the row is written
        print(f"seed {seed}: wrote {args.out}", flush=True)


if __name__ == "__main__":
    main()
