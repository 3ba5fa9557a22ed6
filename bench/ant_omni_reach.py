"""The pilot that fixes Chapter 4's `small` descriptor spaces (issue 15), run once,
never on the runs the notebooks evaluate (its seeds are its own).

1. **Reach.**  Every method of the chapter (ME, ME-LS, PGA-ME, PGA-ME-LS,
   ME-Sampling) on Ant-Omni at the scale's budget, cells and seeds, on the
   thesis's [-15, 15]^2 box.  The final positions of all their elites, pooled,
   give the box: ``b`` = the 95th percentile of max(|x|, |y|), rounded up to
   0.5 m (``qdnb.chapters.ch4_reproducibility.reach_bound``), the thesis's own rule
   ("methods ... tend to produce solutions within this range") at this budget.
2. **Cells.**  On that box (Ant-Omni) and on [0, 1]^2 (Halfcheetah-Uni), every
   method at each candidate cell count (16 and up, in increasing order; a count
   at which one method falls short ends the sweep, as more cells only lower
   coverage); the count is the largest whose coverage reaches 60 % for every
   method on the mean over seeds (``cells_for_coverage``).

The chosen values are then written by hand into the chapter's ``SCALES``
(``qdnb/chapters/ch4_reproducibility/settings.py``) (they are not
read back from this file at run time).  Writes ``bench/results/ant_omni_reach.json``.

    python bench/ant_omni_reach.py [--scale small] [--cells 32 64 128]

3. **Levers** (``--levers``, issue 49: what lets the Low-Spread repertoires travel).
   On the chosen box and cell count, every method at the scale's budget and at each
   lever moved alone: the evaluations per candidate ``E`` (2, and 8, nearer the
   thesis's "usually 10"; the episodes an iteration stay ``env_batch``, so a smaller E
   is more candidates, a larger one fewer), the iterations (x3) and the episodes an
   iteration (x2).  Per setting and method: coverage per seed, reach (q50, q95 of
   max(|x|, |y|) over the elites' descriptors), seconds.  A lever is worth its price
   when it lifts every method's mean coverage to 60 %; the cheapest such setting (in
   environment steps, then seconds) is the one to take by the page's time rule.
   Writes ``bench/results/ant_omni_levers.json``.

    python bench/ant_omni_reach.py --levers [--scale small]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

from qdnb.core.sharding import BRAX_CPU_FLAGS, add_xla_flags

if "--xla-default" not in sys.argv:
    add_xla_flags(BRAX_CPU_FLAGS)  # as the Chapter 4 notebook runs its Brax loops

import jax
import numpy as np

from qdnb.book.provenance import write_result
from qdnb.book.registry import config
from qdnb.chapters.ch4_reproducibility import (
    COVERAGE_TARGET,
    METHODS,
    ONE_EPISODE,
    REACH_QUANTILE,
    build_algorithms,
    cells_for_coverage,
    fitness_offset,
    reach_bound,
)
from qdnb.nets.mlp import MLP
from qdnb.qd.algorithms import run_seeds
from qdnb.qd.cvt import cvt_centroids

PILOT_SEED = 1_000  # not a seed any notebook runs


def final_repertoires(cfg, env_name: str, methods, key):
    """``{method: elites}`` (leaves stacked over seeds) and the seconds each took."""
    env = cfg.make_env(env_name)
    network = MLP(cfg.policy_hidden + (env.action_size,))
    k_cvt, k_run = jax.random.split(key)
    centroids = cvt_centroids(
        k_cvt,
        cfg.num_cells,
        env.descriptor_low,
        env.descriptor_high,
        cfg.cvt_samples,
        cfg.cvt_iterations,
    )
    algorithms = build_algorithms(
        cfg, env, network, centroids, fitness_offset(env_name, cfg.episode_length)
    )
    seeds = jax.random.split(k_run, cfg.num_seeds)
    out, seconds = {}, {}
    for name in methods:
        start = time.time()
        states, _, _ = run_seeds(
            algorithms[name],
            seeds,
            cfg.num_iterations,
            cfg.chunk_size,
            desc=f"{env_name} {name} ({cfg.num_cells} cells)",
            keep_evaluations=False,
        )
        out[name] = jax.device_get(algorithms[name].elites(states.repertoire))
        seconds[name] = round(time.time() - start, 1)
    return out, seconds


LEVERS = {  # name: the settings it changes from the scale's config
    "scale": {},
    "E=2": {"num_episodes": 2},
    "E=8": {"num_episodes": 8},
    "iterations x3": {"num_iterations": "x3"},
    "episodes an iteration x2": {"env_batch": "x2"},
}


def levers(base, scale: str, key, out_path: Path) -> None:
    """Part 3 of the docstring: each lever moved alone, Ant-Omni, every method."""
    out = json.loads(out_path.read_text()) if out_path.exists() else {}
    out.update(
        benchmark="Chapter 4 Ant-Omni: what lets the Low-Spread repertoires travel",
        scale=scale,
        pilot_seed=PILOT_SEED,
        box=base.ant_omni_box,
        cells=base.num_cells,
        rule={"coverage_target": COVERAGE_TARGET},
    )
    out.setdefault("settings", {})
    for i, (name, change) in enumerate(LEVERS.items()):
        if name in out["settings"]:
            continue  # resumable: a setting already measured is kept
        resolved = {
            k: (getattr(base, k) * int(v[1:]) if isinstance(v, str) else v)
            for k, v in change.items()
        }
        cfg = dataclasses.replace(base, **resolved)
        # E changes nothing for the one-episode methods: they are measured once, at "scale"
        methods = [m for m in METHODS if set(change) != {"num_episodes"} or m not in ONE_EPISODE]
        reps, seconds = final_repertoires(cfg, "ant_omni", methods, jax.random.fold_in(key, 10 + i))
        entry = {}
        for method, rep in reps.items():
            filled = np.asarray(rep.filled)
            entry[method] = {
                "coverage": filled.mean(axis=-1).tolist(),
                "mean": float(filled.mean()),
                **reach(rep),
                "seconds": seconds[method],
            }
        out["settings"][name] = {
            "changes": resolved,
            "env_steps": (cfg.num_iterations + 1) * cfg.env_batch * cfg.episode_length,
            "methods": entry,
        }
        print(name, {m: round(v["mean"], 3) for m, v in entry.items()}, flush=True)
        write_result(out_path, out)
    print("wrote", out_path)


def reach(rep) -> dict[str, float]:
    """Quantiles of max(|x|, |y|) over the filled cells' descriptors (all seeds pooled)."""
    r = np.max(np.abs(np.asarray(rep.descriptors)), axis=-1)[np.asarray(rep.filled)]
    return {
        "reach_q50": float(np.quantile(r, 0.5)),
        "reach_q95": float(np.quantile(r, REACH_QUANTILE)),
        "reach_max": float(r.max()),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scale", default="small")
    parser.add_argument("--cells", type=int, nargs="+", default=[16, 32, 64])
    parser.add_argument(
        "--out", type=Path, default=Path(__file__).parent / "results" / "ant_omni_reach.json"
    )
    parser.add_argument(
        "--xla-default", action="store_true", help="keep XLA's CPU defaults (BRAX_CPU_FLAGS off)"
    )
    parser.add_argument("--levers", action="store_true", help="part 3 only (see above)")
    args = parser.parse_args()
    base = config("ch4_reproducibility", args.scale)
    key = jax.random.PRNGKey(PILOT_SEED)
    if args.levers:
        name = "ant_omni_levers" + ("" if args.scale == "small" else f"_{args.scale}") + ".json"
        return levers(base, args.scale, key, Path(__file__).parent / "results" / name)
    out = {
        "benchmark": "Chapter 4 small descriptor spaces: reach and cell counts",
        "scale": args.scale,
        "pilot_seed": PILOT_SEED,
        "budget": {
            "num_seeds": base.num_seeds,
            "iterations": base.num_iterations + 1,
            "env_batch": base.env_batch,
            "num_episodes": base.num_episodes,
            "episode_length": base.episode_length,
        },
        "rule": {"reach_quantile": REACH_QUANTILE, "coverage_target": COVERAGE_TARGET},
    }

    # 1. reach, on the thesis's box
    wide = dataclasses.replace(base, ant_omni_box=15.0)
    elites, seconds = final_repertoires(wide, "ant_omni", METHODS, jax.random.fold_in(key, 0))
    pooled, per_method = [], {}
    for name, rep in elites.items():
        d = np.asarray(rep.descriptors)[np.asarray(rep.filled)]
        pooled.append(d)
        per_method[name] = {"elites": int(d.shape[0]), **reach(rep), "seconds": seconds[name]}
    bound = reach_bound(np.concatenate(pooled))
    out["reach"] = {
        "cells": wide.num_cells,
        "box": 15.0,
        "methods": per_method,
        "ant_omni_box": bound,
    }
    print(json.dumps(out["reach"], indent=1), flush=True)

    # 2. cell counts, on the bounded box
    out["cells"] = {}
    for env_name in ("ant_omni", "halfcheetah_uni"):
        coverage, entry = {}, {}
        for i, k in enumerate(sorted(args.cells)):
            cfg = dataclasses.replace(base, ant_omni_box=bound, num_cells=k)
            reps, seconds = final_repertoires(
                cfg, env_name, METHODS, jax.random.fold_in(key, 1 + i)
            )
            coverage[k] = np.stack(
                [np.mean(np.asarray(r.filled), axis=-1) for r in reps.values()]
            )  # (methods, seeds)
            entry[str(k)] = {
                name: {"coverage": c.tolist(), "mean": float(c.mean()), "seconds": seconds[name]}
                for name, c in zip(reps, coverage[k])
            }
            print(env_name, k, {m: round(v["mean"], 3) for m, v in entry[str(k)].items()})
            if coverage[k].mean(axis=-1).min() < COVERAGE_TARGET:
                break  # more cells would only cover less
        out["cells"][env_name] = {"by_cells": entry, "num_cells": cells_for_coverage(coverage)}
        print(env_name, json.dumps(out["cells"][env_name], indent=1), flush=True)
    out["num_cells"] = min(
        c["num_cells"] for c in out["cells"].values()
    )  # one count for both environments
    write_result(args.out, out)
    print("wrote", args.out)


if __name__ == "__main__":
    main()
