"""Where Chapter 4's fixed cost goes, and whether XLA's optimisation level buys it back.

The reproducibility page at `small` spends about 620 s of its loops on something that does
not grow with the evaluations (10 evaluations took 808 s of loops, 16 took 922 s; issue 49).
This script runs the page's own `run_environment` at `small` on one robot and one seed of
each method, cold (no persistent compilation cache), and reads JAX's compile log: every XLA
compilation with its time, summed by function, beside the wall time of each method's loop
and of its tests (accuracy, reassessment, representative episodes).  It does so for two
XLA settings, each in a fresh process:

- ``page``: what the page runs today (fusion emitters off, ``BRAX_CPU_FLAGS``);
- ``opt0``: the same and ``--xla_backend_optimization_level=0`` (what the `tiny` kernels use),
  which compiles faster and may run slower.

The rule, written before the runs: the page takes ``opt0`` if its projected time at 10
evaluations (each method's fixed seconds + 10 x its seconds an evaluation, on the measured
robot and seed, summed over the methods) is at least 10 % below ``page``'s.

    python bench/probes/ch4_compile.py [--env ant_omni] [--iterations 1 3]

Writes bench/results/ch4_compile.json.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path

SETTINGS = {"page": "", "opt0": "--xla_backend_optimization_level=0"}
OUT = Path(__file__).parents[1] / "results" / "ch4_compile.json"
COMPILED = re.compile(r"Finished XLA compilation of (.+?) in ([\d.]+) sec")


def child(env_name: str, iterations: int, methods: list[str]) -> dict:
    """One process: the page's loop of each method, cold, with the compile log."""
    import logging

    from qdnb.core.sharding import BRAX_CPU_FLAGS, add_xla_flags

    add_xla_flags(BRAX_CPU_FLAGS)
    import dataclasses

    import jax

    from qdnb.chapters.ch4_reproducibility import SCALES, run_environment

    compiles: list[tuple[str, float]] = []

    class Log(logging.Handler):
        def emit(self, record):
            m = COMPILED.search(record.getMessage())
            if m:
                compiles.append((m.group(1), float(m.group(2))))

    for name in ("jax._src.dispatch", "jax._src.interpreters.pxla"):
        logger = logging.getLogger(name)
        logger.setLevel(logging.DEBUG)
        logger.addHandler(Log())
    cfg = dataclasses.replace(SCALES["small"], num_iterations=iterations, num_seeds=1)
    rows = {}
    for method in methods:
        before = len(compiles)
        start = time.time()
        res = run_environment(cfg, env_name, jax.random.PRNGKey(0), False, (method,))
        r = res.methods[method]
        mine = compiles[before:]
        by_function: dict[str, float] = {}
        for fn, seconds in mine:
            by_function[fn] = by_function.get(fn, 0.0) + seconds
        rows[method] = {
            "loop_seconds": round(r.run_seconds, 2),
            "tests_seconds": round(r.seconds - r.run_seconds, 2),
            "wall_seconds": round(time.time() - start, 2),
            "compile_seconds": round(sum(s for _, s in mine), 2),
            "compilations": len(mine),
            "largest_compilations": dict(
                sorted(((k, round(v, 2)) for k, v in by_function.items()), key=lambda kv: -kv[1])[
                    :6
                ]
            ),
        }
    return {"env": env_name, "iterations": iterations, "methods": rows}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--env", default="ant_omni")
    parser.add_argument("--iterations", type=int, nargs="+", default=[1, 3])
    parser.add_argument("--methods", nargs="+", default=["ME", "ME-LS", "PGA-ME-LS"])
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        print(json.dumps(child(args.env, args.iterations[0], args.methods)))
        return

    from qdnb.book.provenance import write_result

    runs = []
    for setting, flags in SETTINGS.items():
        for iterations in args.iterations:
            env = {k: v for k, v in os.environ.items() if k != "JAX_COMPILATION_CACHE_DIR"}
            env["XLA_FLAGS"] = " ".join(filter(None, [os.environ.get("XLA_FLAGS"), flags]))
            cmd = [sys.executable, __file__, "--child", "--env", args.env, "--iterations"]
            cmd += [str(iterations), "--methods", *args.methods]
            start = time.time()
            out = subprocess.run(cmd, env=env, capture_output=True, text=True)
            if out.returncode != 0:
                raise SystemExit(
                    f"{setting} at {iterations} iterations failed:\n{out.stderr[-3000:]}"
                )
            row = json.loads(out.stdout.strip().splitlines()[-1])
            row.update(
                setting=setting, xla_flags=flags, process_seconds=round(time.time() - start, 1)
            )
            runs.append(row)
            print(setting, iterations, {m: r["loop_seconds"] for m, r in row["methods"].items()})
    # an evaluation's cost and the fixed part, per setting and method, from the two counts
    fits = {}
    lo, hi = min(args.iterations), max(args.iterations)
    for setting in SETTINGS:
        a = next(r for r in runs if r["setting"] == setting and r["iterations"] == lo)
        b = next(r for r in runs if r["setting"] == setting and r["iterations"] == hi)
        fits[setting] = {}
        for m in args.methods:
            per_eval = (b["methods"][m]["loop_seconds"] - a["methods"][m]["loop_seconds"]) / (
                hi - lo
            )
            fixed = a["methods"][m]["wall_seconds"] - per_eval * (lo + 1)
            fits[setting][m] = {
                "seconds_an_evaluation": round(per_eval, 2),
                "fixed_seconds": round(fixed, 2),
                "at_10_evaluations": round(fixed + 10 * per_eval, 1),
            }
    totals = {s: round(sum(v["at_10_evaluations"] for v in f.values()), 1) for s, f in fits.items()}
    choice = "opt0" if totals["opt0"] <= 0.9 * totals["page"] else "page"
    write_result(
        OUT,
        {
            "env": args.env,
            "methods": args.methods,
            "runs": runs,
            "fits": fits,
            "projected_at_10_evaluations": totals,
            "rule": "opt0 if its projection is at least 10 % below the page's",
            "choice": choice,
        },
    )
    print(json.dumps({"fits": fits, "totals": totals, "choice": choice}, indent=1))


if __name__ == "__main__":
    main()
