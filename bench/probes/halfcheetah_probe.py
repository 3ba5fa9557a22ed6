"""How far 256 starting policies spread over Halfcheetah-Uni's descriptor space, for
our task as it was and as it is, beside the numbers QDax's task gave (issue 36).

The policies are initialised as Chapter 4's `small` initialises them (an MLP of
64 x 64, lecun-uniform weights, one episode of 250 steps each, the same keys for
every row).  Rows, each a change on top of the one before:

- ``before``: brax 0.14's Halfcheetah as it comes (its 5 floor pairs, its spring
  gears, dropped from 0.7 m), contact read once at each step's end, tanh hidden
  layers: the task the book ran before this probe;
- ``every substep``: the same, a foot touching in any of the step's 16 substeps;
- ``v1 model``: brax v1's colliding bodies and gears, its resting start pose;
- ``relu``: the same task, relu hidden layers (QDax's MLP default): the book's
  task and policies now.

For each: min / median / max of each foot's contact fraction and the number of
bins of the 4 x 4 grid on [0, 1]^2 hit.  The QDax rows were measured once with
``qdax==0.5.0`` on brax v1 (its ``FeetContactWrapper``) and are copied from the
issue for comparison, marked as such.  Writes ``bench/results/halfcheetah_probe.json``.

    python bench/probes/halfcheetah_probe.py
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from qdnb.book.provenance import write_result
from qdnb.envs.base import EnvState
from qdnb.envs.locomotion import BraxTask, HalfcheetahUni, _brax_env
from qdnb.envs.rollout import evaluate_policies
from qdnb.nets.mlp import MLP, init_policies

NUM_POLICIES, EPISODE_LENGTH, HIDDEN, BINS = 256, 250, (64, 64), 4

QDAX = {  # measured with qdax 0.5.0 on brax v1 (issue 36): min / median / max
    "QDax 0.5.0 on brax v1, tanh": {
        "back": [0.12, 0.29, 0.85],
        "front": [0.02, 0.62, 0.95],
        "bins": 11,
    },
    "QDax 0.5.0 on brax v1, relu": {
        "back": [0.00, 0.22, 0.96],
        "front": [0.00, 0.19, 0.97],
        "bins": 14,
    },
}


@dataclass(frozen=True, eq=False)
class BraxOwnHalfcheetah(HalfcheetahUni):
    """brax 0.14's Halfcheetah as it comes: its own model and keyframe start."""

    at_step_end: bool = True

    def __post_init__(self):
        super().__post_init__()
        env = _brax_env("halfcheetah", self.backend)
        object.__setattr__(self, "brax_env", env)
        object.__setattr__(self, "_rest_q", np.asarray(env.sys.init_q, np.float32))

    def lowest_point(self, q):
        return jnp.zeros(())  # no lowering: the keyframe's height

    def step(self, state: EnvState, action: jax.Array) -> EnvState:
        if self.at_step_end:  # one pipeline step; contacts of the state it ends in
            return BraxTask.step(self, state, action)
        return super().step(state, action)


def probe(env, activation: str, key) -> dict:
    network = MLP(HIDDEN + (env.action_size,), activation=activation)
    params = init_policies(network, key, NUM_POLICIES, env.observation_size)
    run = jax.jit(lambda p, k: evaluate_policies(env, network.apply, p, k))
    start = time.time()
    ev = jax.block_until_ready(run(params, jax.random.fold_in(key, 1)))
    d = np.asarray(ev.descriptor)  # (front, back)
    bins = {tuple(b) for b in np.minimum((d * BINS).astype(int), BINS - 1)}
    q = lambda x: [round(float(v), 3) for v in np.quantile(x, [0.0, 0.5, 1.0])]
    return {
        "back": q(d[:, 1]),
        "front": q(d[:, 0]),
        "bins": len(bins),
        "seconds": round(time.time() - start, 1),
    }


def main() -> None:
    key = jax.random.PRNGKey(0)
    rows = {
        "before: brax 0.14's model, contact at step end, tanh": (
            BraxOwnHalfcheetah(episode_length=EPISODE_LENGTH),
            "tanh",
        ),
        "every substep (brax 0.14's model), tanh": (
            BraxOwnHalfcheetah(episode_length=EPISODE_LENGTH, at_step_end=False),
            "tanh",
        ),
        "every substep, v1 model, tanh": (HalfcheetahUni(episode_length=EPISODE_LENGTH), "tanh"),
        "every substep, v1 model, relu (the book's now)": (
            HalfcheetahUni(episode_length=EPISODE_LENGTH),
            "relu",
        ),
    }
    out = {
        "benchmark": "Halfcheetah-Uni: descriptors of 256 starting policies",
        "policies": NUM_POLICIES,
        "episode_length": EPISODE_LENGTH,
        "hidden": list(HIDDEN),
        "grid": f"{BINS}x{BINS}",
        "ours": {},
        "qdax (copied from issue 36, not run here)": QDAX,
    }
    for name, (env, activation) in rows.items():
        out["ours"][name] = probe(env, activation, key)
        print(f"{name:55s}", out["ours"][name], flush=True)
    path = Path(__file__).parents[1] / "results" / "halfcheetah_probe.json"
    write_result(path, out)
    print("wrote", path)


if __name__ == "__main__":
    main()
