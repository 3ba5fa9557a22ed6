"""Which initial parameter map (P^0) and which mixing key: a measured comparison on
the Chapter 5 `small` world, to choose the rules the notebook runs.

The thesis says P^0 is "randomly drawn from uniform distribution for every
position corresponding to matter patch", which reads two ways: one ``h`` vector
for the whole patch (Plantec et al.'s parameter-embedding example) or one per
cell.  For each P^0 rule and each mixing rule (``stoch``: a fixed key, as the
reference code; ``stoch_fresh``: a fresh key every step), ``pick_system`` draws
the same ``--candidates`` systems (Table 5.1) and measures on ``--probes``
episodes each (``qdnb.chapters.ch5_flow_lenia.pick_system``, every statistic over the
mean of the final frames' squared value):

- ``diversity``: how much of the final frame varies across initial states;
- ``change``: the per-step change over the last 5 steps (a settled pattern or not);
- ``replay``: the final frames' squared difference when the same initial states
  are simulated again with other keys (0: an episode is a function of x_0);
- ``sensitivity``: the same when A^0 is perturbed by 1e-3 (0: the ending is a
  smooth function of x_0; about twice ``diversity``: no better than another x_0).

Writes the medians over systems, how many meet all the criteria, the system each
variant keeps, and every system's numbers to ``bench/results/flow_lenia_p0.json``.

    python bench/probes/flow_lenia_p0.py [--scale small] [--candidates 16] [--probes 8]
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path

import jax
import numpy as np

from qdnb.book.provenance import write_result
from qdnb.book.registry import config
from qdnb.chapters.ch5_flow_lenia import pick_system


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scale", default="small")
    parser.add_argument("--candidates", type=int, default=16)
    parser.add_argument("--probes", type=int, default=8)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--out", type=Path, default=Path(__file__).parents[1] / "results" / "flow_lenia_p0.json"
    )
    args = parser.parse_args()
    base = config("ch5_flow_lenia", args.scale).world
    rows = []
    for p0 in ("patch", "cell"):
        for mix in ("stoch", "stoch_fresh"):
            world = dataclasses.replace(base, p0=p0, mix=mix)
            start = time.perf_counter()
            choice = pick_system(jax.random.PRNGKey(args.seed), world, args.candidates, args.probes)
            row = {
                "p0": p0,
                "mix": mix,
                "seconds": round(time.perf_counter() - start, 1),
                "median": {k: round(float(np.median(v)), 4) for k, v in choice.statistics.items()},
                "meet_all_criteria": int(
                    np.sum(np.all(np.stack(list(choice.passed.values())), axis=0))
                ),
                "kept": choice.index,
                "kept_statistics": {
                    k: round(float(v[choice.index]), 4) for k, v in choice.statistics.items()
                },
                "per_system": {
                    k: [round(float(x), 4) for x in v] for k, v in choice.statistics.items()
                },
            }
            print(
                f"P0 {p0:5s} mix {mix:11s}: medians {row['median']}, {row['meet_all_criteria']} of "
                f"{args.candidates} meet the criteria, kept {row['kept']} ({row['seconds']} s)"
            )
            rows.append(row)
    write_result(
        args.out,
        {
            "benchmark": "flow_lenia_p0",
            "scale": args.scale,
            "grid": [base.height, base.width],
            "kernels": base.kernels,
            "candidates": args.candidates,
            "probes": args.probes,
            "seed": args.seed,
            "results": rows,
        },
    )
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
