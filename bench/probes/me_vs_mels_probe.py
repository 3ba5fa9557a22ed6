"""Probe for planning Chapter 4: ME vs ME-LS on Ant-Omni with Table 4.1 settings (batch 1000,
[256, 256] policies, 1024 CVT cells, E = 10), each run for a wall-time budget, then the accuracy
experiment (100 CVT goals, 10 episodes) and the reassessment.  Not the chapter notebook: equal
wall time, not equal environment steps.
Usage: python bench/probes/me_vs_mels_probe.py SECONDS OUT.json
(bench/results/me_vs_mels_probe_h100.json: 180 s each on one H100, jax 0.11.2, brax 0.14.2)."""

import sys
import time
from pathlib import Path

import jax

from qdnb.book.provenance import write_result
from qdnb.envs import make_env
from qdnb.envs.rollout import evaluate_episodes
from qdnb.nets.mlp import MLP
from qdnb.qd.algorithms import MapElitesLowSpread, PolicyMapElites
from qdnb.qd.cvt import cvt_centroids
from qdnb.qd.low_spread import accuracy, reassess

budget_s = float(sys.argv[1])
env = make_env("ant_omni")
net = MLP((256, 256, env.action_size))
cent = cvt_centroids(
    jax.random.PRNGKey(0), 1024, env.descriptor_low, env.descriptor_high, 50000, 30
)
goals = cvt_centroids(jax.random.PRNGKey(1), 100, env.descriptor_low, env.descriptor_high, 5000, 30)
common = dict(
    env=env,
    network=net,
    batch_size=1000,
    iso_sigma=0.005,
    line_sigma=0.05,
    centroids=cent,
    fitness_offset=-250 * 3.0,
)
ev_fn = lambda g, k: evaluate_episodes(env, net.apply, g, k, 10)
out = {}
for name, algo, E in [
    ("ME", PolicyMapElites(**common), 1),
    ("ME-LS", MapElitesLowSpread(**common, num_episodes=10), 10),
]:
    t = time.time()
    state, _ = jax.jit(algo.init)(jax.random.PRNGKey(2))
    chunk = jax.jit(
        lambda s: jax.lax.scan(lambda c, _: (algo.step(c)[0], None), s, None, length=5)[0]
    )
    it = 1
    state = chunk(state)
    jax.block_until_ready(state)
    t1 = time.time()
    print(name, "compile+first chunk", round(t1 - t, 1), flush=True)
    it = 5
    while time.time() - t1 < budget_s:
        state = chunk(state)
        jax.block_until_ready(state)
        it += 5
    steps = (it + 1) * 1000 * E * 250
    rep = algo.elites(state.repertoire)
    acc = jax.jit(lambda r, k: accuracy(r, goals, ev_fn, k))(rep, jax.random.PRNGKey(3))
    re = jax.jit(lambda r, k: reassess(r, ev_fn, k)[0])(rep, jax.random.PRNGKey(4))
    out[name] = dict(
        iterations=it,
        env_steps=steps,
        steps_per_s=steps / (time.time() - t1),
        coverage=float(rep.filled.mean()),
        reassessed_coverage=float(re.filled.mean()),
        avg_distance=float(acc.distance.mean()),
        avg_spread=float(acc.spread.mean()),
        max_fitness=float(rep.fitnesses.max()),
    )
    print(name, out[name], flush=True)
write_result(Path(sys.argv[2]), out)
