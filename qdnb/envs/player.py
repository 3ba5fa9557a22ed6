"""Playing stored policies episode after episode, in fixed-size chunks of one
compiled simulation (the tests of Chapter 4's repertoires and the QDT's datasets)."""

from __future__ import annotations

import itertools
from typing import Any

import jax
import numpy as np

from qdnb.core import dryrun
from qdnb.core.evaluation import Evaluation
from qdnb.envs.base import Env
from qdnb.envs.rollout import evaluate_policies
from qdnb.nets.mlp import MLP

_PLAYERS = itertools.count()  # each player's compiled simulation has its own key


class Player:
    """Plays (policy, initial-state key) pairs in fixed-size chunks through one
    compiled simulation, whatever the number of episodes asked for: the tests of
    every repertoire then cost one compilation per environment.  Each episode's
    state-descriptor path comes back as its ``trajectory``; with ``record``, its
    ``obs``, ``action`` and ``valid`` steps instead (the QDT's datasets)."""

    def __init__(
        self, env: Env, network: MLP, chunk: int, record: bool = False, name: str = "episodes"
    ):
        self.chunk, self.name = chunk, name
        self._program = f"{name} #{next(_PLAYERS)}"  # a dry run times its simulation once
        kept = ("obs", "action", "valid") if record else "next_state_descriptor"

        def play(genotypes, keys):
            def one(g, k):
                ev = evaluate_policies(
                    env, network.apply, jax.tree.map(lambda x: x[None], g), k, True
                )
                path = jax.tree.map(
                    lambda x: x[0],
                    {n: ev.trajectory[n] for n in kept} if record else ev.trajectory[kept],
                )
                return ev.fitness[0], ev.descriptor[0], path

            return jax.vmap(one)(genotypes, keys)

        self._play = jax.jit(play)

    def play(self, genotypes: Any, keys: jax.Array) -> Evaluation:
        """Each policy of ``genotypes`` over the episode started by the same row of
        ``keys``.  Padding, slicing and stitching the chunks happen on the host: the
        number of episodes changes from call to call, and device arrays of a new shape
        would each compile their own small XLA programs (hundreds per repertoire)."""
        n = keys.shape[0]
        if jax.dtypes.issubdtype(keys.dtype, jax.dtypes.prng_key):  # typed keys: their data
            keys = jax.random.key_data(keys)  # (the same stream: a typed key wraps it)
        pad = (-n) % self.chunk
        padded = jax.tree.map(
            lambda x: np.concatenate([x, np.repeat(x[:1], pad, axis=0)]),
            jax.device_get((genotypes, keys)),
        )
        name, count = f"{self.name} ({self.chunk} per chunk)", (n + pad) // self.chunk
        # a dry run that timed this compiled simulation on an earlier call counts this
        # call's chunks at that rate and repeats that output: none is played
        done, out = dryrun.reused(self._program, "loop", name, count, unit="chunk")
        if done:
            outs = [out]
        else:
            chunks = dryrun.steps(name, range(0, n + pad, self.chunk), unit="chunk")
            outs = []
            for i in chunks:
                part = self._play(*jax.tree.map(lambda x: x[i : i + self.chunk], padded))
                chunks.step_done(part)
                outs.append(jax.device_get(part))
            if chunks.dry:
                dryrun.remember(self._program, chunks.seconds_per_step, outs[-1])
        # a dry run played the first chunks only: the others repeat them (same shapes)
        outs = [outs[j % len(outs)] for j in range(count)]
        fitness, descriptor, path = (
            jax.tree.map(lambda *xs: np.concatenate(xs)[:n], *parts) for parts in zip(*outs)
        )
        length = (
            np.sum(path["valid"], axis=1)
            if isinstance(path, dict)
            else np.full((n,), path.shape[1])
        )
        return Evaluation(fitness=fitness, descriptor=descriptor, length=length, trajectory=path)

    def episodes(self, num_episodes: int, only: jax.Array | None = None):
        """``evaluate_fn(genotypes, key)``: each of the ``G`` policies over
        ``num_episodes`` episodes from different initial states; leaves ``(G, E, ...)``
        (host arrays).  With a boolean mask ``only``, the other policies are not played
        (zeros)."""

        def evaluate_fn(genotypes: Any, key: jax.Array) -> Evaluation:
            g = jax.tree.leaves(genotypes)[0].shape[0]
            rows = np.arange(g) if only is None else np.flatnonzero(np.asarray(only))
            repeated = jax.tree.map(
                lambda x: np.repeat(np.asarray(x)[rows], num_episodes, axis=0), genotypes
            )
            ev = self.play(repeated, jax.random.split(key, rows.size * num_episodes))

            def full(x):
                out = np.zeros((g, num_episodes) + x.shape[1:], x.dtype)
                out[rows] = x.reshape((rows.size, num_episodes) + x.shape[1:])
                return out

            return jax.tree.map(full, ev)

        return evaluate_fn
