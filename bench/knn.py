"""QD-PG's novelty rewards on CPU: brute force against the spatial index of
``qdnb.qd.spatial``, on the archives and queries of a Table 3.2 Point-Maze run.

QD-PG (``POINTMAZE_PAPER``, one seed, the index on) runs a few iterations; after
iterations 5, 15 and 40 its archive and one iteration's queries (the state
descriptors of 800 critic steps x 2 diversity actors x 256 sampled transitions) are
scored both ways on one core's device, as a seed runs.  Per snapshot: seconds by
brute force and by the index (its build, its first pass, the second try and brute
force for the rest), the share of queries each pass leaves, and whether the two ways
give the same bits.  Then the index's window widths (``WIDTHS``: the first pass's
run of three cells, the second try's) are swept on the iteration-40 snapshot: the
first pass fuses into one loop up to about 150 candidates a query and falls off a
cliff beyond (60 x 3: 2.4 s), so the widths are chosen below that.  Writes
``bench/results/knn.json``.

    taskset -c 0 python bench/knn.py [--repeats 3]

(``taskset -c 0``: one core, as each of two seeds side by side has.)
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import jax
import jax.numpy as jnp

from qdnb.book.provenance import write_result
from qdnb.book.registry import config
from qdnb.chapters.ch3_qdpg import build_algorithms
from qdnb.qd import spatial
from qdnb.qd.novelty import NoveltyArchive, reduce_columns

SNAPSHOTS = (5, 15, 40)
WIDTH_SWEEP = ((24, 128), (36, 96), (36, 128), (36, 192), (48, 128), (48, 192))


def best_time(fn, *args, repeats: int) -> float:
    jax.block_until_ready(fn(*args))
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - start)
    return min(times)


def snapshots() -> dict[int, tuple[NoveltyArchive, jax.Array]]:
    """The archive and one iteration's diversity queries after each of ``SNAPSHOTS``."""
    cfg = config("ch3_qdpg", "paper")
    algo = build_algorithms(cfg, "pointmaze", methods=("QD-PG",))["QD-PG"]
    task, n = cfg.pointmaze, cfg.pointmaze.num_actors
    queries = task.num_critic_steps * (n // 2) * cfg.td3_batch_size
    state, _ = jax.jit(algo.init)(jax.random.PRNGKey(0))
    step = jax.jit(algo.step)
    out = {}
    for i in range(1, max(SNAPSHOTS) + 1):
        state, _ = step(state)
        if i in SNAPSHOTS:
            rows = state.buffer.sample(jax.random.PRNGKey(i), queries)
            out[i] = (state.archive, rows["state_descriptor"])
            print(f"iteration {i}: archive {int(state.archive.size)}", flush=True)
    return out


def passes(archive: NoveltyArchive, queries: jax.Array, repeats: int) -> dict:
    """The index's parts, timed apart, and the share of queries each pass leaves."""
    reduce = lambda columns: reduce_columns(columns, "mean")
    build = jax.jit(spatial.GridIndex.build)
    index = build(archive.data, archive.valid)
    chunked = queries.reshape(-1, spatial.CHUNK, 2)
    first = jax.jit(
        lambda q: jax.lax.map(
            lambda c: index.searched(c, 10, reduce, spatial.WIDTHS[0]), q
        ).reshape(-1)
    )
    second = jax.jit(
        lambda q, v: spatial.retried(q, v, index.searched, 10, reduce, spatial.WIDTHS[1])
    )
    after_first = first(chunked)
    after_second = second(queries, after_first)
    return {
        "build_s": best_time(build, archive.data, archive.valid, repeats=repeats),
        "first_pass_s": best_time(first, chunked, repeats=repeats),
        "second_try_s": best_time(second, queries, after_first, repeats=repeats),
        "refused_by_first_pass": float(jnp.mean(jnp.isnan(after_first))),
        "refused_by_second_try": float(jnp.mean(jnp.isnan(after_second))),
    }


def compare(archive: NoveltyArchive, queries: jax.Array, repeats: int) -> dict:
    brute = jax.jit(lambda q: archive.novelty(q, 10, search="brute"))
    index = jax.jit(lambda q: archive.novelty(q, 10, search="index"))
    start = time.perf_counter()
    by_index = jax.block_until_ready(index(queries))
    first_call = time.perf_counter() - start
    by_brute = brute(queries)
    return {
        "archive_size": int(archive.size),
        "queries": int(queries.shape[0]),
        "brute_force_s": best_time(brute, queries, repeats=repeats),
        "index_s": best_time(index, queries, repeats=repeats),
        "index_first_call_s (compiles)": first_call,
        "bit_equal_share": float(jnp.mean(by_index == by_brute)),
        "max_relative_difference": float(
            jnp.max(jnp.abs(by_index - by_brute) / jnp.maximum(by_brute, 1e-30))
        ),
        **passes(archive, queries, repeats),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    snaps = snapshots()
    rows = []
    for it, (archive, queries) in snaps.items():
        rows.append({"iteration": it, **compare(archive, queries, args.repeats)})
        print(json.dumps(rows[-1]), flush=True)
    sweep = []
    archive, queries = snaps[max(SNAPSHOTS)]
    chosen = spatial.WIDTHS
    for widths in WIDTH_SWEEP:
        spatial.WIDTHS = widths
        index = jax.jit(lambda q: archive.novelty(q, 10, search="index"))
        sweep.append({"widths": widths, "index_s": best_time(index, queries, repeats=args.repeats)})
        print(json.dumps(sweep[-1]), flush=True)
    spatial.WIDTHS = chosen
    out = {
        "cores_used": len(os.sched_getaffinity(0)),
        "k": 10,
        "widths": chosen,
        "snapshots": rows,
        "width_sweep_on_iteration_40": sweep,
    }
    path = Path(__file__).parent / "results" / "knn.json"
    write_result(path, out)
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
