"""Exact nearest-neighbour novelty in a 2-D descriptor space, from a spatial index.

QD-PG scores every state descriptor of an iteration's replay batches against its
archive (Eq. 3.5): at Table 3.2's budget on Point-Maze that is 409,600 queries
against 10,000 entries an iteration, 4 * 10^9 distances by brute force.  The
nearest neighbours of a 2-D point lie close by, so most of those distances are
wasted.  ``GridIndex`` computes the same novelty exactly from a few dozen
candidates a query:

1. **Grids.**  The archive's bounding box is cut into ``side x side`` cells at every
   side of ``SIDES`` (each level's cells half the area of the last's).  At each
   level the entries are sorted by cell, row by row, and a table holds where each
   cell's run starts, so the three cells ``(x, y - 1), (x, y), (x, y + 1)`` are one
   contiguous run.  Built once per call: the archive changes only between iterations.
2. **A level per query.**  A query searches the 3 x 3 cells around its own: three
   runs of at most ``width`` entries each (fixed-size windows, so shapes stay
   static), at the coarsest level where all three fit (the most candidates, the
   widest margin), found by bisection over the levels.
3. **Its k nearest candidates**, by an insertion network over the candidates that
   ends in the novelty itself (``reduce``): one fused pass, no ``lax.top_k`` (which
   pays about a microsecond per row on CPU, too much for 409,600 short rows).
4. **A check.**  Every entry outside the nine cells lies farther from the query than
   the block's boundary (the sides on the box's edge excepted: nothing lies beyond
   them); the answer is exact when the ``k``-th candidate distance is at most that.
5. **Second tries.**  The queries the check refuses (a crowded wall or corner keeps
   the block small) search again with windows of ``WIDTHS[1]``; those still refused
   (a pile of states at one spot) by brute force against the whole archive,
   ``RETRY`` at a time.

Distances are summed one coordinate at a time, as
``qdnb.qd.novelty.pairwise_squared_distances`` sums them, and reduced from the same
sorted ``k`` smallest values, so the novelty equals the brute-force one to a float32
rounding or two (XLA may fuse a multiply-add differently).  Invalid entries (an
archive not yet full) are never neighbours; with fewer than ``k`` valid entries the
missing distances are ``+inf``, as brute force has them.
"""

from __future__ import annotations

import math
from typing import Callable

import jax
import jax.numpy as jnp
from flax import struct

# cells per side, 4 x 4 to 1,024 x 1,024, each level's cells half the area of the last's
SIDES = tuple(sorted({round(2 ** (e / 2)) for e in range(4, 21)}))
# Entries a run of three cells may hold: 108 candidates a query, then 384 for the refused.
# Chosen on Point-Maze archives of a Table 3.2 run, on one CPU core (bench/knn.py).
WIDTHS = (36, 128)
CHUNK = 4096  # queries searched side by side
RETRY = 256  # refused queries searched again side by side

# k sorted squared distances (a list of k arrays) -> one value per query
Reduce = Callable[[list], jax.Array]


def squared_distances(queries: jax.Array, points: jax.Array) -> jax.Array:
    """Squared Euclidean distances ``(queries, points)``, summed one coordinate at a
    time (``novelty.pairwise_squared_distances``'s arithmetic)."""
    squares = [(queries[:, i, None] - points[None, :, i]) ** 2 for i in range(queries.shape[1])]
    return sum(squares[1:], squares[0])


def k_smallest_columns(values: jax.Array, k: int) -> list:
    """The ``k`` smallest entries of each column of ``values`` (``(m, n)``), sorted: a
    list of ``k`` arrays ``(n,)``.  An insertion network of ``2 k m`` minima and
    maxima, unrolled; XLA fuses it with what consumes it into one pass over the
    columns when that is a single array (stacking the ``k`` rows instead costs 4x)."""
    best = [jnp.full(values.shape[1:], jnp.inf, values.dtype)] * k
    for row in values:
        for j in range(k):
            best[j], row = jnp.minimum(best[j], row), jnp.maximum(best[j], row)
    return best


@struct.dataclass
class GridIndex:
    """The archive's entries sorted by cell at every level of ``SIDES``: ``points``
    ``(levels, m + WIDTHS[-1], 2)`` (each level padded so that a window never runs
    off it), and ``before``, per level, the number of entries in the cells before each
    cell in row order (``(sum of (side * side + 1),)``, level after level from
    ``offsets``); ``low`` and ``span`` place the cells, ``num_valid`` counts the entries."""

    points: jax.Array
    before: jax.Array
    low: jax.Array
    span: jax.Array
    num_valid: jax.Array

    @classmethod
    def build(cls, reference: jax.Array, valid: jax.Array) -> "GridIndex":
        """The index of the ``valid`` rows of ``reference`` (``(m, 2)``)."""
        m, d = reference.shape
        if d != 2:
            raise ValueError(f"GridIndex indexes 2-D descriptors, got {d}-D")
        low = jnp.min(jnp.where(valid[:, None], reference, jnp.inf), axis=0)
        high = jnp.max(jnp.where(valid[:, None], reference, -jnp.inf), axis=0)
        empty = ~jnp.isfinite(low)
        low, high = jnp.where(empty, 0.0, low), jnp.where(empty, 1.0, high)
        span = jnp.where(high > low, high - low, 1.0) * (1 + 1e-6)  # the top edge inside
        points, before = [], []
        for side in SIDES:
            xy = cell_xy(reference, low, span / side, side)
            cell = jnp.where(valid, xy[:, 0] * side + xy[:, 1], side * side)  # invalid last
            order = jnp.argsort(cell, stable=True)
            count = jnp.zeros(side * side + 1, jnp.int32).at[cell].add(1)
            points.append(jnp.pad(reference[order], ((0, WIDTHS[-1]), (0, 0))))
            before.append(jnp.cumsum(count) - count)
        return cls(jnp.stack(points), jnp.concatenate(before), low, span, jnp.sum(valid))

    def novelty(self, queries: jax.Array, k: int, reduce: Reduce, chunk: int = CHUNK):
        """``reduce`` of the ``k`` smallest squared distances of each query (``(n, 2)``)
        to the archive's valid entries, exactly: the module's steps 2 to 5."""
        n, d = queries.shape
        chunks = jnp.pad(queries, ((0, (-n) % chunk), (0, 0))).reshape(-1, chunk, d)
        value = jax.lax.map(lambda q: self.searched(q, k, reduce, WIDTHS[0]), chunks)
        value = retried(queries, value.reshape(-1)[:n], self.searched, k, reduce, WIDTHS[1])
        flat = self.points[-1]  # every entry, in the finest level's order
        ok = jnp.arange(flat.shape[0]) < self.num_valid

        def everything(q, k, reduce, width):
            found = brute_force(q, flat, ok, k)
            return reduce([found[:, j] for j in range(k)])

        return retried(queries, value, everything, k, reduce, None)

    def block(self, queries: jax.Array, level: jax.Array, width: int):
        """The 3 x 3 cells around each query at its ``level`` (``(n,)``) as three runs of
        the level's sorted entries (columns ``x - 1, x, x + 1``, each the cells ``y - 1``
        to ``y + 1``): where each starts in ``points`` flattened, its length (0 off the
        grid), and whether all three fit windows of ``width``."""
        sides = jnp.asarray(SIDES)
        side = sides[level][:, None]
        xy = cell_xy(queries, self.low, self.span / side, side)
        x = xy[:, :1] + jnp.arange(-1, 2)[None]  # (n, 3)
        y0, y1 = jnp.maximum(xy[:, 1:] - 1, 0), jnp.minimum(xy[:, 1:] + 2, side)
        offsets = jnp.cumsum(sides * sides + 1) - (sides * sides + 1)
        table = offsets[level][:, None] + x * side
        begin = self.before[table + y0]
        length = jnp.where((x >= 0) & (x < side), self.before[table + y1] - begin, 0)
        rows = level[:, None] * self.points.shape[1] + begin
        return rows, length, jnp.all(length <= width, axis=-1)

    def searched(self, queries: jax.Array, k: int, reduce: Reduce, width: int) -> jax.Array:
        """For ``queries`` (``(n, 2)``): ``reduce`` of the ``k`` smallest squared
        distances to the entries of the 3 x 3 cells around each query at its level, in
        windows of ``width`` (steps 2 and 3), where that answer is exact (step 4), and NaN
        where it is not."""
        n = queries.shape[0]
        # the coarsest level whose runs fit the windows (the most candidates, the widest
        # margin), by bisection: finer levels fit more often (where that fails the level
        # found still fits, or the query goes to its second try)
        low, high = jnp.zeros(n, jnp.int32), jnp.full(n, len(SIDES) - 1, jnp.int32)
        for _ in range(math.ceil(math.log2(len(SIDES)))):
            middle = (low + high) // 2
            fits = self.block(queries, middle, width)[2]
            high, low = jnp.where(fits, middle, high), jnp.where(fits, low, middle + 1)
        rows, length, usable = self.block(queries, low, width)
        flat = self.points.reshape(-1, 2)
        window = lambda at: jax.lax.dynamic_slice(flat, (at, 0), (width, 2))
        points = jax.vmap(jax.vmap(window))(rows).reshape(n, -1, 2)
        ok = (jnp.arange(width) < length[..., None]).reshape(n, -1)
        dist = sum((queries[:, None, i] - points[..., i]) ** 2 for i in range(2))
        dist = jnp.where(ok, dist, jnp.inf)
        # the distance from each query to its block's boundary, on the sides with cells
        # beyond, less a few float32 roundings of the coordinates (no rounding of a
        # cell's edge lets an entry outside the block come closer than the margin)
        side = jnp.asarray(SIDES)[low][:, None]
        cell = self.span / side
        xy = cell_xy(queries, self.low, cell, side)
        below = jnp.where(xy - 1 > 0, queries - (self.low + (xy - 1) * cell), jnp.inf)
        above = jnp.where(xy + 2 < side, self.low + (xy + 2) * cell - queries, jnp.inf)
        slack = 1e-5 * (jnp.max(jnp.abs(self.low)) + jnp.max(self.span))
        margin = jnp.maximum(jnp.min(jnp.minimum(below, above), axis=-1) - slack, 0.0)
        covered = jnp.sum(length, axis=-1) >= self.num_valid  # every entry a candidate
        # the k-th distance may not pass this (-1: no level fits; inf: nothing is outside)
        bound = jnp.where(usable, jnp.where(covered, jnp.inf, margin**2), -1.0)
        if width == WIDTHS[0]:  # every query: the network, fused with the reduction
            best = k_smallest_columns(dist.T, k)
        else:  # the few refused queries
            found = -jax.lax.top_k(-dist, k)[0]
            best = [found[:, j] for j in range(k)]
        # one output (the network and its reduction stay one fused pass): NaN where refused
        return jnp.where(best[-1] <= bound, reduce(best), jnp.nan)


def k_smallest(values: jax.Array, k: int, block: int | None = None) -> jax.Array:
    """The ``k`` smallest entries of each row, in increasing order (exact).

    For long rows, split each row into blocks, keep the ``k`` blocks with the
    smallest minima and take the ``k`` smallest entries among those.  No entry
    outside these blocks can be smaller than all ``k`` block minima kept (each
    is at least its block's minimum), so the values returned are exactly those
    of a full ``top_k``.  The work is about ``m / block`` minima plus
    ``k * block`` candidates per row of ``m``; ``block_size`` picks the size.
    On 2 CPU cores, for 25,600 rows and k = 10, it takes about 0.7x the time
    of a full ``top_k`` on rows of 2,000 and 0.4x on rows of 10,000
    (``bench/knn.py``).  Rows too short to gain go straight to ``top_k``.
    """
    n, m = values.shape
    block = block_size(m, k) if block is None else block
    if m < 4 * k * block:
        return -jax.lax.top_k(-values, k)[0]
    pad = (-m) % block
    blocks = jnp.pad(values, ((0, 0), (0, pad)), constant_values=jnp.inf).reshape(n, -1, block)
    _, best = jax.lax.top_k(-jnp.min(blocks, axis=-1), k)
    candidates = jnp.take_along_axis(blocks, best[:, :, None], axis=1).reshape(n, k * block)
    return -jax.lax.top_k(-candidates, k)[0]


def block_size(m: int, k: int) -> int:
    """The block size ``k_smallest`` uses on rows of ``m``: near ``sqrt(2 m / k)``
    (measured fastest on CPU by ``bench/knn.py``; the cost model alone says
    ``sqrt(m / k)``), and a divisor of ``m`` when one lies within a factor of
    two, since padding copies the whole matrix."""
    target = max(1, round((2 * m / k) ** 0.5))
    divisors = [b for b in range(max(1, target // 2), 2 * target + 1) if m % b == 0]
    return min(divisors, key=lambda b: abs(b - target)) if divisors else target


def brute_force(queries: jax.Array, points: jax.Array, valid: jax.Array, k: int) -> jax.Array:
    """The ``k`` smallest squared distances of each query to the valid ``points``."""
    return k_smallest(jnp.where(valid[None, :], squared_distances(queries, points), jnp.inf), k)


def retried(queries: jax.Array, value: jax.Array, search, *args, chunk: int = RETRY):
    """``value`` with the queries it refused (NaN) answered again by
    ``search(queries, *args)`` (NaN where it refuses too), ``chunk`` at a time, as many
    chunks as there are refused queries."""
    n, d = queries.shape
    refused = jnp.isnan(value)
    rows = jnp.nonzero(refused, size=n + chunk, fill_value=n)[0]  # the refused first
    padded = jnp.concatenate([queries, jnp.zeros((1, d), queries.dtype)])

    def one_chunk(i, values):  # the answers of the refused queries, in their order
        at = jax.lax.dynamic_slice(rows, (i * chunk,), (chunk,))
        return jax.lax.dynamic_update_slice(values, search(padded[at], *args), (i * chunk,))

    trips = (jnp.sum(refused) + chunk - 1) // chunk
    values = jax.lax.fori_loop(0, trips, one_chunk, jnp.zeros(n + chunk, value.dtype))
    return value.at[rows].set(values, mode="drop")


def cell_xy(points: jax.Array, low: jax.Array, width: jax.Array, side) -> jax.Array:
    """The ``(x, y)`` cell of each point in a grid of ``side x side`` cells of ``width``
    from ``low`` (points outside it fall in its edge cells)."""
    xy = jnp.floor((points - low) / width).astype(jnp.int32)
    return jnp.clip(xy, 0, jnp.asarray(side) - 1)
