"""What every search in the book shares: an ``Evaluation`` of a batch of
candidates, and the ``Algorithm`` protocol its loops (``run_seeds``,
``scan_in_chunks``) drive."""

from __future__ import annotations

from typing import Any, Protocol

import jax
from flax import struct


@struct.dataclass
class Evaluation:
    """What one episode (or a batch of them, with leading axes) returns.

    ``fitness`` is the episode return plus the environment's constant
    ``fitness_shift`` (or its best reward, for environments whose
    ``fitness_mode`` is ``"max_reward"``), ``descriptor`` the behaviour descriptor,
    ``length`` the number of steps before the episode ended.  ``trajectory`` is
    ``None`` unless asked for: then a dict of per-step ``obs``, ``action``,
    ``reward``, ``next_obs``, ``done``, ``state_descriptor``,
    ``next_state_descriptor`` and ``valid``: a transition
    ``(s_t, a_t, r_t, s_{t+1})`` carries ``psi(s_t)``, the descriptor of the
    state it starts from, as QD-PG stores it (Section 3.6.3), and
    ``psi(s_{t+1})``, the point the step reached (a path drawn from these ends
    where the episode's final descriptor is).
    """

    fitness: jax.Array
    descriptor: jax.Array
    length: jax.Array
    trajectory: Any = None
    extra: Any = None  # anything else a scoring function reports (QDax's ``extra_scores``)


class Algorithm(Protocol):
    """A search as a pair of pure functions, ready for ``jit``, ``vmap`` over seeds
    and ``lax.scan``: ``init(key) -> (state, evaluation)`` and ``step(state) ->
    (state, evaluation)``, with ``metrics(state)`` the scalars logged each step.
    The MAP-Elites family also has ``start(key) -> state`` (nothing evaluated yet),
    so that a whole run is one compiled loop of ``step``.  ``split`` (optional; default
    ``"seeds"``) says what ``run_seeds`` splits over several devices when they do not
    divide its seeds evenly: ``"population"`` for searches whose cost is a large
    population's episodes (``qdnb.core.sharding.seed_slots``)."""

    def init(self, key: jax.Array) -> tuple[Any, Evaluation]: ...

    def step(self, state: Any) -> tuple[Any, Evaluation]: ...

    def metrics(self, state: Any) -> dict[str, jax.Array]: ...
