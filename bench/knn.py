"""Exact k-nearest-neighbour novelty on CPU: a full ``top_k`` against the
blockwise ``k_smallest`` of ``qdnb.qd.novelty``, for the query count of one
QD-PG iteration (100 critic batches of 256) and the archive sizes of `small`
(2,000) and `paper` (10,000); and the chunk of queries ``NoveltyArchive.novelty``
scores at a time, on the queries of one iteration of the thesis's coupling at
`small` (4 diversity actors x 100 critic steps x 256 = 102,400) against a full
archive of 10,000, one such set per device as QD-PG's seeds run.  Writes
``bench/results/knn.json``.

    python bench/knn.py [--repeats 5]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

import jax
import numpy as np

from qdnb.qd.novelty import k_smallest, pairwise_squared_distances


def best_time(fn, x, repeats: int) -> float:
    jax.block_until_ready(fn(x))
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(fn(x))
        times.append(time.perf_counter() - start)
    return min(times)


def chunk_sweep(repeats: int, queries: int = 102_400) -> dict[str, float]:
    """Seconds to score ``queries`` per device against a full archive of 10,000, by chunk."""
    from qdnb.core.sharding import over_seeds
    from qdnb.qd.novelty import NoveltyArchive

    n = len(jax.devices())
    data = jax.random.normal(jax.random.PRNGKey(1), (10_000, 2)) * 0.3
    archive = NoveltyArchive.create(10_000, 2).replace(
        data=data, num_added=jax.numpy.asarray(10_000, jax.numpy.int32)
    )
    q = jax.random.uniform(jax.random.PRNGKey(0), (n, queries, 2), minval=-1, maxval=1)
    out = {}
    for chunk in (64, 128, 256, 1024):
        score = lambda x, chunk=chunk: archive.novelty(x, 10, chunk=chunk)
        out[str(chunk)] = best_time(jax.jit(over_seeds(jax.vmap(score), n, "seeds")), q, repeats)
        print(f"chunk {chunk}: {out[str(chunk)]:.3f} s", flush=True)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--queries", type=int, default=25_600)
    parser.add_argument("--chunk", type=int, default=1024)
    args = parser.parse_args()
    k = 10
    queries = jax.random.uniform(jax.random.PRNGKey(0), (args.queries, 2), minval=-1, maxval=1)
    rows = []
    for size in (2_000, 10_000):
        reference = jax.random.uniform(jax.random.PRNGKey(1), (size, 2), minval=-1, maxval=1)
        ways = {
            "top_k": lambda d: -jax.lax.top_k(-d, k)[0],
            "k_smallest": lambda d: k_smallest(d, k),
        }
        timings, answers = {}, {}
        for name, select in ways.items():
            fn = jax.jit(
                lambda q, select=select: jax.lax.map(
                    lambda c: select(pairwise_squared_distances(c, reference)),
                    q.reshape(-1, args.chunk, 2),
                )
            )
            timings[name] = best_time(fn, queries, args.repeats)
            answers[name] = np.asarray(fn(queries))
        rows.append(
            {
                "archive_size": size,
                "seconds": timings,
                "k_smallest_over_top_k": timings["k_smallest"] / timings["top_k"],
                "same_values": bool(np.allclose(answers["top_k"], answers["k_smallest"])),
            }
        )
        print(rows[-1], flush=True)
    chunks = chunk_sweep(args.repeats)
    out = {
        "device": jax.devices()[0].platform,
        "machine": platform.machine(),
        "cpu_count": os.cpu_count(),
        "queries": args.queries,
        "chunk": args.chunk,
        "k": k,
        "repeats": args.repeats,
        "rows": rows,
        "novelty_chunk_seconds": chunks,
    }
    path = Path(__file__).parent / "results" / "knn.json"
    path.write_text(json.dumps(out, indent=1) + "\n")
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
