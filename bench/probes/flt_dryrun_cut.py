"""Does a cut batch stand for the whole one in the FLT's paper dry run?

A CPU dry run of Chapter 5 at ``paper`` trains the FLTs on ``DRY_RUN_EPISODES`` episodes
a batch and counts each step ``batch_size / DRY_RUN_EPISODES`` times
(``qdnb.models.lenia.flt.dry_run_batch``).  This times two training steps of the paper
FLT (the thesis's; ``--variant``: ours) at several batch sizes with the notebook's own
loop (``flt.train``, ``step_seconds``: the first step compiles, the second is the rate)
and writes, for each, the seconds of a full batch's step that the cut projects
(``steady_s * batch_size / batch``) beside the full batch's own.  The system is any
sampled one: a step's cost does not depend on its parameters.

    python bench/probes/flt_dryrun_cut.py [--batches 4 8 32] [--variant]

The cut in force is ``DRY_RUN_EPISODES``, chosen from this benchmark's numbers.

Writes ``bench/results/flt_dryrun_cut.json`` (``--variant``: ``..._variant.json``).
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path

import jax

from qdnb.book.provenance import write_result
from qdnb.book.registry import config
from qdnb.models.lenia import flow_lenia as fl
from qdnb.models.lenia.flt import make_model, train


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--batches", type=int, nargs="+", default=[4, 8, 32])
    parser.add_argument("--variant", action="store_true", help="our FLT, not the thesis's")
    args = parser.parse_args()
    cfg = config("ch5_flow_lenia", "paper")
    flt_cfg = cfg.variant if args.variant else cfg.flt
    full = flt_cfg.batch_size
    system = fl.sample_system(jax.random.PRNGKey(0), cfg.world)
    rows = []
    for batch in args.batches:
        run_cfg = dataclasses.replace(flt_cfg, batch_size=batch, train_steps=2)
        seconds: list[float] = []
        began = time.perf_counter()
        train(
            make_model(cfg.world, run_cfg),
            run_cfg,
            cfg.world,
            system,
            jax.random.PRNGKey(1),
            progress=False,
            step_seconds=seconds,
        )
        row = {
            "batch": batch,
            "first_step_s": seconds[0],  # compilation included
            "steady_s": seconds[1],
            "projected_full_batch_step_s": seconds[1] * full / batch,
            "wall_s": time.perf_counter() - began,
        }
        print(row, flush=True)
        rows.append(row)
    name = "flt_dryrun_cut_variant.json" if args.variant else "flt_dryrun_cut.json"
    write_result(
        Path(__file__).parents[1] / "results" / name,
        {
            "benchmark": "flt_dryrun_cut",
            "model": "ours (variant)" if args.variant else "the thesis's FLT",
            "full_batch": full,
            "devices": jax.device_count(),
            "results": rows,
        },
    )


if __name__ == "__main__":
    main()
