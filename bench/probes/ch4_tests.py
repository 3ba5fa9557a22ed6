"""What Chapter 4's test episodes cost at `small`, and what the same tests cost played leaner.

The reproducibility page at `small` took 1,122 s (issue 49); its tests of the final
repertoires (the accuracy experiment, the reassessment, the representatives' episodes)
took 46-117 s per method and robot of it, about as many episodes as the training's.  This
script replays those tests on the page's own `small` repertoires (``data/runs/small/
ch4_reproducibility/repertoire_*.npz``, 3 seeds) and counts and times them two ways:

- ``page``: as the page runs them today: per seed, every goal plays its nearest policy over
  ``accuracy_episodes`` episodes, even when several goals share that policy; the player
  pads every call to its chunk of ``env_batch`` (64) episodes.
- ``lean``: the same tests, with a policy nearest to several goals played once (its
  episodes measured against each of those goals: each goal's estimate is still the mean
  over ``accuracy_episodes`` episodes of its nearest policy, Section 4.5.2) and the player's
  chunk at ``--chunk`` episodes, so less of each call is padding.

Each measured phase (one method on one robot, both ways) builds its own player, so its
seconds include that player's first call (compiling and playing one chunk: 14-24 s); the page
compiles one player per robot.

First the player's seconds per episode at chunks of 16, 32 and 64 (one robot at a time,
after its compilation): a smaller chunk is only worth taking if an episode costs no more.

Each run is kept in the file under its ``--label``: ``eager player (before)`` padded,
sliced and stitched the chunks as device arrays, ``host player`` does it on the host (an
episode count that changes between calls no longer compiles new small XLA programs).

The rule, written before the runs: the page takes ``lean`` (with the smallest chunk whose
seconds per episode are within 10 % of the 64-episode chunk's) if it plays at least 25 %
fewer episodes; the claims are then re-read from a fresh `small` run.

Outcome (2026-12-07): ``lean`` played 32 % fewer episodes at the 64-episode chunk and the
page took it, then gave it back before publishing anything.  The rule had missed what it
costs: each goal's estimate is unchanged, but the claims compare the *mean over goals*, and
goals that share a policy then share its noise, so that mean rests on far fewer independent
episodes exactly where the Low-Spread repertoires have few filled cells (about 17 episodes a
seed instead of 125 for ME-LS on Ant-Omni).  The thesis plays 10 episodes for each goal.  Bought:
the whole page went from 1,122 s to 1,096 s, within one run's noise.  The host player stays
(fewer compilations, the same numbers).

    python bench/probes/ch4_tests.py [--chunks 16 32 64] [--label 'host player']

Writes bench/results/ch4_tests.json.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import jax
import numpy as np

OUT = Path(__file__).parents[1] / "results" / "ch4_tests.json"
PER_EPISODE_TOLERANCE = 1.10  # a smaller chunk's seconds per episode, at most this x the largest's
MIN_SAVING = 0.25  # lean must play at least this share fewer episodes


def timed(f, *args):
    start = time.perf_counter()
    out = jax.block_until_ready(f(*args))
    return out, time.perf_counter() - start


def chunk_rates(cfg, env_name, chunks, repeats=3):
    """Seconds per episode of the page's player at each chunk size (a compiled call)."""
    from qdnb.envs.player import Player
    from qdnb.nets.mlp import MLP

    env = cfg.make_env(env_name)
    network = MLP(cfg.policy_hidden + (env.action_size,))
    params = network.init(jax.random.PRNGKey(0), np.zeros((1, env.observation_size)))
    out = {}
    for chunk in chunks:
        player = Player(env, network, chunk=chunk, name=f"bench {chunk}")
        genotypes = jax.tree.map(lambda x: np.broadcast_to(x, (chunk,) + x.shape), params)
        keys = jax.random.split(jax.random.PRNGKey(1), chunk)
        _, compile_and_run = timed(player.play, genotypes, keys)
        seconds = [timed(player.play, genotypes, keys)[1] for _ in range(repeats)]
        out[chunk] = {
            "first_call_seconds": round(compile_and_run, 2),
            "seconds_per_chunk": round(float(np.median(seconds)), 3),
            "seconds_per_episode": float(np.median(seconds)) / chunk,
        }
        print(env_name, chunk, out[chunk], flush=True)
    return out


def shared_accuracy(repertoire, goals, evaluate_fn, key):
    """``lean``'s accuracy experiment: a policy nearest to several goals is played once
    and its episodes are measured against each of them (the page's ``accuracy`` plays
    each goal's own episodes)."""
    from qdnb.qd.low_spread import Accuracy, spread

    d2 = np.sum((goals[:, None, :] - np.asarray(repertoire.descriptors)[None]) ** 2, axis=-1)
    chosen = np.argmin(np.where(np.asarray(repertoire.filled)[None], d2, np.inf), axis=1)
    cells, policy_of_goal = np.unique(chosen, return_inverse=True)
    ev = evaluate_fn(jax.tree.map(lambda x: x[cells], repertoire.genotypes), key)
    reached = ev.descriptor[policy_of_goal.reshape(-1)]  # (G, E, d)
    distance = np.mean(np.linalg.norm(reached - np.asarray(goals)[:, None], axis=-1), axis=1)
    return Accuracy(distance=distance, spread=jax.vmap(spread)(reached), chosen=chosen)


def test_phase(cfg, env_name, method, chunk, lean):
    """Episodes played and seconds of one method's tests on one robot, all seeds."""
    from qdnb.chapters.ch4_reproducibility import load_repertoires, representative_cells
    from qdnb.core import paths
    from qdnb.core.config import config_hash
    from qdnb.envs.player import Player
    from qdnb.nets.mlp import MLP
    from qdnb.qd.cvt import cvt_centroids
    from qdnb.qd.low_spread import accuracy, reassess
    from qdnb.qd.repertoire import Repertoire

    run_dir = paths.run_dir("small", "ch4_reproducibility", create=False)
    saved = load_repertoires(run_dir / f"repertoire_{env_name}_{method}.npz", config_hash(cfg))
    if saved is None:
        raise SystemExit(f"no small repertoire for {env_name} {method}: run the page at small")
    env = cfg.make_env(env_name)
    network = MLP(cfg.policy_hidden + (env.action_size,))
    low, high = env.descriptor_low, env.descriptor_high
    # the page's goals: run_environments' key for this robot, run_environment's second split
    env_key = jax.random.fold_in(jax.random.PRNGKey(0), cfg.environments.index(env_name))
    k_goals = jax.random.split(env_key, 6)[1]
    goals = cvt_centroids(
        k_goals, cfg.goals(env_name), low, high, cfg.cvt_samples, cfg.cvt_iterations
    )
    player = Player(env, network, chunk=chunk, name=f"{env_name} tests {chunk}")
    # policies handed to each test's player (the reassessment's are counted from the
    # filled cells below: its player is handed every cell and skips the empty ones)
    played = {"accuracy": 0, "representatives": 0}
    counting = lambda part, f: (
        lambda g, k: (
            played.__setitem__(part, played[part] + jax.tree.leaves(g)[0].shape[0]) or f(g, k)
        )
    )
    start = time.perf_counter()
    for seed in range(cfg.num_seeds):
        rep = Repertoire(
            genotypes=jax.tree.map(lambda x: x[seed], saved["genotypes"]),
            fitnesses=saved["fitnesses"][seed],
            descriptors=saved["descriptors"][seed],
            centroids=saved["centroids"],
        )
        key = jax.random.PRNGKey(seed)
        play_acc = counting("accuracy", player.episodes(cfg.accuracy_episodes))
        run_accuracy = shared_accuracy if lean else accuracy
        jax.block_until_ready(run_accuracy(rep, goals, play_acc, key))
        play_re = player.episodes(cfg.reassess_episodes, only=rep.filled)
        jax.block_until_ready(reassess(rep, play_re, key))
        if seed == 0:
            cells = representative_cells(rep, env_name)
            play_rep = counting("representatives", player.episodes(cfg.representative_episodes))
            jax.block_until_ready(play_rep(jax.tree.map(lambda x: x[cells], rep.genotypes), key))
    seconds = time.perf_counter() - start
    episodes = {
        "accuracy": played["accuracy"] * cfg.accuracy_episodes,
        "reassess": int(np.sum(saved["fitnesses"] > -np.inf)) * cfg.reassess_episodes,
        "representatives": played["representatives"] * cfg.representative_episodes,
    }
    return {"episodes": episodes, "episodes_total": sum(episodes.values()), "seconds": seconds}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--chunks", type=int, nargs="+", default=[16, 32, 64])
    parser.add_argument("--out", type=Path, default=OUT)
    parser.add_argument(
        "--label", default="current", help="the run's name in the file (other runs are kept)"
    )
    args = parser.parse_args()

    from qdnb.book.provenance import device, git_sha, write_result
    from qdnb.chapters.ch4_reproducibility import METHODS, SCALES

    cfg = SCALES["small"]
    rates = {env: chunk_rates(cfg, env, args.chunks) for env in cfg.environments}
    base = {env: rates[env][max(args.chunks)]["seconds_per_episode"] for env in rates}
    ok = [
        c
        for c in sorted(args.chunks)
        if all(rates[e][c]["seconds_per_episode"] <= PER_EPISODE_TOLERANCE * base[e] for e in rates)
    ]
    chunk = ok[0]
    phases = {}
    for env_name in cfg.environments:
        for method in METHODS:
            for name, lean, c in (("page", False, cfg.env_batch), ("lean", True, chunk)):
                row = test_phase(cfg, env_name, method, c, lean)
                phases.setdefault(env_name, {}).setdefault(method, {})[name] = row
                print(env_name, method, name, row, flush=True)
    total = lambda which, k: sum(
        phases[e][m][which][k] for e in phases for m in phases[e]
    )  # fmt: skip
    saving = 1 - total("lean", "episodes_total") / total("page", "episodes_total")
    out = json.loads(args.out.read_text()) if args.out.exists() else {"runs": {}}
    out["runs"][args.label] = {
        "rule": (
            f"lean, at the smallest chunk within {PER_EPISODE_TOLERANCE:g} x the largest "
            f"chunk's seconds per episode, if it plays at least {MIN_SAVING:.0%} fewer "
            "episodes"
        ),
        "chunk_rates": rates,
        "lean_chunk": chunk,
        "phases": phases,
        "episodes": {w: total(w, "episodes_total") for w in ("page", "lean")},
        "seconds": {w: round(total(w, "seconds"), 1) for w in ("page", "lean")},
        "episode_saving": round(saving, 3),
        "choice": "lean" if saving >= MIN_SAVING else "page",
        "device": device(),
        "commit": git_sha(),
        "date": time.strftime("%Y-%m-%d %H:%M"),
    }
    out["benchmark"] = __doc__.splitlines()[0]
    write_result(args.out, out)  # (each run keeps its own device, commit and date)
    print(f"wrote {args.out}: saving {saving:.0%}")


if __name__ == "__main__":
    main()
