"""Flow Lenia with parameters embedded in the grid (Sections 5.2 and 5.3), in pure JAX,
following the rules of Plantec et al.'s reference code (``erwanplantec/FlowLenia``,
``flowlenia_params.py``), which the thesis says it uses.

One step from activations ``A`` (``(H, W, C)``, ``C = 1``) and the parameter map
``P`` (``(H, W, |K|)``, the kernel weights ``h`` of every cell):

1. Lenia's potentials ``K_k * A`` by FFT (circular, as in the reference, whatever
   the border), with kernels of concentric rings (``kernel_fields``): radius
   ``(R + 15) r``, rings ``b exp(-(D - a)^2 / w)`` of ``D = |x| / radius``, a soft
   edge ``sigmoid(-10 (D - 1))``, normalised to sum to one on the grid.
2. The parameter-embedded affinity of Section 5.3,
   ``U(p) = sum_k P_k(p) G_k(K_k * A)(p)``, with the growth functions of Eq. 5.1.
3. The flow ``F = (1 - alpha) grad U - alpha grad A_Sigma``,
   ``alpha = clip((A_Sigma / theta_A)^n, 0, 1)``, ``n = 2``, ``theta_A = 2``;
   gradients by unnormalised Sobel filters (zero padding at walls, periodic on a
   torus); then ``F`` itself is clipped per axis to ``[-(reach - s), reach - s]``
   (``flow``).
4. Reintegration tracking (Moroz 2020; Plantec et al. 2023): the matter of every
   cell ``q`` moves to a uniform square of half-side ``s`` centred on
   ``q' = q + clip(dt F(q))``; at walls ``q'`` is kept at least ``s`` inside the grid
   so that no matter leaves it.  Each cell receives the part of the square that
   covers it (``reintegrate``).  Mass is conserved exactly, up to float rounding.
5. ``P`` moves with matter: each cell takes the parameter vector of one of the
   cells that send it matter, drawn with probability proportional to the matter
   received from it (a categorical over the log of the parcels, by Gumbel-max),
   and ``P = 0`` where no matter (less than ``mass_epsilon``) arrives.  With the
   default ``mix = "stoch"`` the draw uses one fixed key (``mix_seed``) at every
   step, as the reference does, so an episode is a deterministic function of
   (system, ``A^0``, ``P^0``); ``mix = "stoch_fresh"`` draws with a fresh key every
   step (the key passed to ``step``).

Displacement bound.  Since ``|F| <= D = reach - s`` per axis and ``dt <= 1``, matter
moves at most ``dt D`` per axis and step (``dt = 0.2``, ``reach = 5``, ``s = 0.65``:
0.87 cells).  The matter of ``q`` covers ``[q' - s, q' + s]`` per axis and the unit
cell of ``p`` is ``[p - 1/2, p + 1/2]``: they overlap only when
``|p - q'| < s + 1/2``, so every receiving cell lies within ``reach`` cells of its
sender per axis, the ``(2 reach + 1)^2`` neighbourhood of the reference.

Two implementations of step 4 agree to float rounding (the same pairs, the same
weights, the same random draws): ``reintegrate_reference`` gathers the whole
``(2 reach + 1)^2`` neighbourhood of every cell, as the reference code does;
``reintegrate`` uses that the overlap factorises per axis and that a square of
side ``2s`` covers at most ``floor(2s) + 2`` cells per axis (3 for ``s = 0.65``),
so each cell sends its matter to 9 cells by a scatter-add, instead of every cell
checking 121 possible senders.  On GPU, XLA's float scatter-add may sum in a
varying order (set ``XLA_FLAGS=--xla_gpu_deterministic_ops=true`` for bitwise
repeatable runs there); on CPU runs are bitwise repeatable.

The initial state (Section 5.3.1) is a ``patch_size`` square of uniform matter in
the centre of an empty grid; ``P^0`` is one uniform ``h`` vector for the whole
patch (``p0 = "patch"``, the reference's parameter-embedding example) or an
independent vector per cell (``p0 = "cell"``); 0 elsewhere.

Remaining departures from the reference code, and why:

- the parameter ranges are Table 5.1's as printed: ``sigma`` in ``[0.001, 0.2]`` and
  ``b`` in ``[0, 1]`` (the reference draws ``sigma`` up to 0.18 and ``b`` from 0.001);
- a cell that receives no matter gets ``P = 0`` ("parameter vectors ... move along
  with matter", and ``P`` is null outside matter at ``t = 0``); in the reference such a
  cell takes the vector of the cell 5 rows and columns away (the categorical over
  all-``-inf`` logits picks its first offset), which streaks parameters across
  empty space;
- at walls the target is kept inside each axis's own size (the reference clips both
  axes to the first one's, the same on square grids);
- kernels are computed in log space (the same values; rings far from every cell
  no longer underflow to 0 / 0) on torus distances (the reference's ``fftshift`` of
  a centred grid: the same on even grids);
- below ``paper`` scale the kernel radius is multiplied by ``radius_scale`` (the grid
  side over 128) so that kernels shrink with the grid and the patch.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from qdnb.core.sharding import replicated, shard_batch

RANGE_FIELDS = (
    "R_range",
    "r_range",
    "h_range",
    "a_range",
    "b_range",
    "w_range",
    "mu_range",
    "sigma_range",
)
MIX_RULES = ("stoch", "stoch_fresh")
P0_RULES = ("patch", "cell")
BORDERS = ("wall", "torus")


@dataclass(frozen=True)
class FlowLeniaConfig:
    """A Flow Lenia world and the parameter space of its random systems (Table 5.1).

    ``reach`` is the neighbourhood radius of reintegration tracking; ``F`` and ``dt F``
    are clipped per axis to ``reach - s`` (see the module docstring).  ``mix``: how
    ``P`` follows matter (``"stoch"``, a fixed key ``mix_seed``; ``"stoch_fresh"``, a
    fresh key every step); ``p0``: one ``h`` vector for the initial patch
    (``"patch"``) or one per cell (``"cell"``); ``border``: ``"wall"`` or ``"torus"``.
    Kernel radii are ``radius_scale (R + radius_offset) r``.  ``mass_epsilon``: a cell
    receiving less matter than this gets ``P = 0``.
    """

    height: int = 128
    width: int = 128
    kernels: int = 10
    channels: int = 1
    rings: int = 3
    steps: int = 50
    patch_size: int = 40
    dt: float = 0.2
    s: float = 0.65
    n: float = 2.0
    theta_A: float = 2.0
    reach: int = 5
    mix: str = "stoch"
    mix_seed: int = 42
    p0: str = "patch"
    border: str = "wall"
    radius_offset: float = 15.0
    radius_scale: float = 1.0
    mass_epsilon: float = 1e-12
    R_range: tuple[float, float] = (2.0, 25.0)
    r_range: tuple[float, float] = (0.2, 1.0)
    h_range: tuple[float, float] = (0.0, 1.0)
    a_range: tuple[float, float] = (0.0, 1.0)
    b_range: tuple[float, float] = (0.0, 1.0)
    w_range: tuple[float, float] = (0.01, 0.5)
    mu_range: tuple[float, float] = (0.05, 0.5)
    sigma_range: tuple[float, float] = (0.001, 0.2)

    def __post_init__(self):
        for name in ("height", "width", "kernels", "rings", "patch_size", "reach"):
            value = getattr(self, name)
            if not isinstance(value, (int, np.integer)) or value < 1:
                raise ValueError(f"{name} must be a positive integer, got {value!r}")
        if not isinstance(self.steps, (int, np.integer)) or self.steps < 0:
            raise ValueError(f"steps must be a non-negative integer, got {self.steps!r}")
        if self.channels != 1:
            raise ValueError(
                f"only single-channel Flow Lenia is implemented (channels=1), got {self.channels}"
            )
        if self.patch_size > min(self.height, self.width):
            raise ValueError(
                f"patch_size {self.patch_size} is larger than the {self.height}x{self.width} grid"
            )
        for name, valid in (("mix", MIX_RULES), ("p0", P0_RULES), ("border", BORDERS)):
            if getattr(self, name) not in valid:
                raise ValueError(
                    f"unknown {name} {getattr(self, name)!r}; valid: {', '.join(valid)}"
                )
        for name in ("dt", "s", "n", "theta_A", "radius_scale"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be positive, got {getattr(self, name)!r}")
        if not self.dt <= 1:
            raise ValueError(
                "dt must be at most 1 (matter moves at most dt (reach - s) per step), got "
                f"{self.dt!r}"
            )
        if self.radius_offset < 0 or self.mass_epsilon < 0:
            raise ValueError(
                f"radius_offset and mass_epsilon must be non-negative, got {self.radius_offset!r} "
                f"and {self.mass_epsilon!r}"
            )
        if self.reach < self.s:
            raise ValueError(
                f"reach ({self.reach}) must be at least s ({self.s}): the flow bound "
                f"reach - s would be negative"
            )
        if 2 * self.reach + 1 > min(self.height, self.width):
            raise ValueError(
                f"the reintegration neighbourhood (2 * reach + 1 = {2 * self.reach + 1} cells) "
                f"does not fit in the {self.height}x{self.width} grid"
            )
        for name in RANGE_FIELDS:
            low, high = getattr(self, name)
            if not low <= high:
                raise ValueError(f"{name} = ({low}, {high}): low must not exceed high")
        for name in ("R_range", "r_range", "w_range", "sigma_range"):
            if not getattr(self, name)[0] > 0:
                raise ValueError(f"{name} must be positive, got {getattr(self, name)}")

    @property
    def flow_bound(self) -> float:
        """``D = reach - s``: the bound on ``|F|`` and on ``|dt F|`` per axis."""
        return self.reach - self.s

    @property
    def max_displacement(self) -> float:
        """``dt D``: the most matter moves per axis in one step."""
        return self.dt * self.flow_bound

    @property
    def slots(self) -> int:
        """Cells per axis a square of side ``2s`` can cover: ``floor(2s) + 2``."""
        return math.floor(2 * self.s) + 2

    def describe(self) -> dict[str, str]:
        """The world's rules as used, in words (``summary.json``'s ``world``)."""
        mixing = {
            "stoch": "categorical, probability proportional to the incoming matter, fixed key "
            f"{self.mix_seed}",
            "stoch_fresh": "categorical, probability proportional to the incoming matter, fresh "
            "key every step",
        }
        return {
            "mixing": mixing[self.mix],
            "p0": {
                "patch": "one uniform h vector for the whole patch",
                "cell": "an independent uniform h vector per cell",
            }[self.p0],
            "flow_bound": f"F and dt·F clipped per axis to ±(reach − s) = ±({self.reach} − "
            f"{self.s:g}) = ±{self.flow_bound:g}: "
            f"at most {self.max_displacement:.3g} cells per step",
            "kernels": f"radius {self.radius_scale:g}·(R + {self.radius_offset:g})·r, rings "
            "b·exp(−(D − a)² / w), edge σ(−10·(D − 1))",
            "alpha": f"clip((A / θ_A)ⁿ, 0, 1) with θ_A = {self.theta_A:g}, n = {self.n:g}",
            "border": self.border,
        }


@struct.dataclass
class System:
    """The parameters of one Flow Lenia system (Table 5.1), with its kernels' FFTs.

    ``R`` is shared; ``r``, ``mu``, ``sigma`` are per kernel (``(|K|,)``) and ``a``,
    ``b``, ``w`` per kernel and ring (``(|K|, rings)``).  ``kernels_fft`` is the
    ``rfft2`` of ``kernel_fields``, ``(H, W // 2 + 1, |K|)``.
    """

    R: jax.Array
    r: jax.Array
    a: jax.Array
    b: jax.Array
    w: jax.Array
    mu: jax.Array
    sigma: jax.Array
    kernels_fft: jax.Array


@struct.dataclass
class State:
    """Activations ``A`` ``(H, W, C)`` and parameter map ``P`` ``(H, W, |K|)``."""

    A: jax.Array
    P: jax.Array


# ----- Lenia: kernels, growth, affinity -----


def torus_distances(height: int, width: int) -> jax.Array:
    """Distance of every cell to cell ``(0, 0)`` on the ``height x width`` torus."""
    rows, cols = np.arange(height), np.arange(width)
    dy = np.minimum(rows, height - rows)[:, None]
    dx = np.minimum(cols, width - cols)[None, :]
    return jnp.asarray(np.sqrt(dy**2 + dx**2), dtype=jnp.float32)


def kernel_fields(
    R: jax.Array,
    r: jax.Array,
    a: jax.Array,
    b: jax.Array,
    w: jax.Array,
    height: int,
    width: int,
    offset: float = 15.0,
    scale: float = 1.0,
) -> jax.Array:
    """Kernels of concentric rings (Section 5.2, as Plantec et al.'s code builds them),
    centred on cell ``(0, 0)``.

    With ``D = |x| / (scale (R + offset) r_k)`` (torus distances),
    ``K_k(x) = sigmoid(-10 (D - 1)) sum_i b_ki exp(-(D - a_ki)^2 / w_ki)``, divided by its
    sum over the grid.  Computed in log space, so that kernels whose rings are all
    far from every cell (``a`` near 1, ``w`` small, a radius under a cell) still
    normalise to one instead of underflowing to 0 / 0.  Returns ``(H, W, |K|)``.
    """
    radius = scale * (R + offset) * r  # (K,)
    d = torus_distances(height, width)[..., None] / radius  # (H, W, K)
    log_b = jnp.log(jnp.maximum(b, jnp.finfo(jnp.float32).tiny))
    log_rings = log_b - (d[..., None] - a) ** 2 / w  # (H, W, K, rings)
    log_k = jax.nn.log_sigmoid(-10.0 * (d - 1.0)) + jax.nn.logsumexp(log_rings, axis=-1)
    return jax.nn.softmax(log_k, axis=(0, 1))


def growth(u: jax.Array, mu: jax.Array, sigma: jax.Array) -> jax.Array:
    """Growth function of Eq. 5.1: ``G(u) = 2 exp(-(u - mu)^2 / (2 sigma^2)) - 1``."""
    return 2.0 * jnp.exp(-((u - mu) ** 2) / (2.0 * sigma**2)) - 1.0


def sample_system(key: jax.Array, cfg: FlowLeniaConfig) -> System:
    """A random system, every parameter uniform in its Table 5.1 range.  The kernel
    weights ``h`` are not part of it: they live in the parameter map ``P``
    (``initial_state`` draws them in ``h_range``)."""
    k = cfg.kernels
    kR, kr, ka, kb, kw, kmu, ksig = jax.random.split(key, 7)

    def uniform(key, shape, bounds):
        return jax.random.uniform(key, shape, minval=bounds[0], maxval=bounds[1])

    R = uniform(kR, (), cfg.R_range)
    r = uniform(kr, (k,), cfg.r_range)
    a = uniform(ka, (k, cfg.rings), cfg.a_range)
    b = uniform(kb, (k, cfg.rings), cfg.b_range)
    w = uniform(kw, (k, cfg.rings), cfg.w_range)
    fields = kernel_fields(
        R, r, a, b, w, cfg.height, cfg.width, cfg.radius_offset, cfg.radius_scale
    )
    return System(
        R=R,
        r=r,
        a=a,
        b=b,
        w=w,
        mu=uniform(kmu, (k,), cfg.mu_range),
        sigma=uniform(ksig, (k,), cfg.sigma_range),
        kernels_fft=jnp.fft.rfft2(fields, axes=(0, 1)),
    )


def initial_patches(key: jax.Array, cfg: FlowLeniaConfig) -> tuple[jax.Array, jax.Array]:
    """A random initial patch (Section 5.3.1): matter uniform in ``[0, 1)``,
    ``(p, p, C)``, and parameters uniform in ``h_range`` by the ``p0`` rule: one vector
    for the whole patch, ``(|K|,)`` (``"patch"``), or one per cell, ``(p, p, |K|)``
    (``"cell"``)."""
    ka, kp = jax.random.split(key)
    p = cfg.patch_size
    shape = (cfg.kernels,) if cfg.p0 == "patch" else (p, p, cfg.kernels)
    return (
        jax.random.uniform(ka, (p, p, cfg.channels)),
        jax.random.uniform(kp, shape, minval=cfg.h_range[0], maxval=cfg.h_range[1]),
    )


def initial_state(key: jax.Array, cfg: FlowLeniaConfig) -> State:
    """A ``patch_size``-square patch of uniform matter in the centre of an empty grid,
    with ``P`` uniform in ``h_range`` on the patch by the ``p0`` rule and 0 elsewhere
    (``initial_patches``)."""
    return place_patch(*initial_patches(key, cfg), cfg)


def place_patch(patch_a: jax.Array, patch_p: jax.Array, cfg: FlowLeniaConfig) -> State:
    """The state with matter ``patch_a`` ``(p, p, C)`` and parameters ``patch_p``
    (``(p, p, |K|)``, or ``(|K|,)`` for one vector on the whole patch) in the centre of
    an empty grid (``p = patch_size``)."""
    p = cfg.patch_size
    if patch_a.shape != (p, p, cfg.channels) or patch_p.shape not in (
        (p, p, cfg.kernels),
        (cfg.kernels,),
    ):
        raise ValueError(
            f"patches of shapes {patch_a.shape} and {patch_p.shape} do not match "
            f"({p}, {p}, {cfg.channels}) and ({p}, {p}, {cfg.kernels}) or ({cfg.kernels},)"
        )
    top, left = (cfg.height - p) // 2, (cfg.width - p) // 2
    A = (
        jnp.zeros((cfg.height, cfg.width, cfg.channels))
        .at[top : top + p, left : left + p]
        .set(patch_a)
    )
    P = (
        jnp.zeros((cfg.height, cfg.width, cfg.kernels))
        .at[top : top + p, left : left + p]
        .set(jnp.broadcast_to(patch_p, (p, p, cfg.kernels)))
    )
    return State(A=A, P=P)


def frames(states: State) -> jax.Array:
    """``(A, P)`` stacked along channels, ``(..., H, W, C + |K|)``: the images the FLT
    reads and predicts."""
    return jnp.concatenate([states.A, states.P], axis=-1)


def potentials(system: System, A: jax.Array) -> jax.Array:
    """``K_k * A`` for every kernel, by FFT: circular, at walls too (as in the reference
    code, whose walls stop matter, not kernels): ``(H, W, |K|)``."""
    height, width = A.shape[:2]
    fa = jnp.fft.rfft2(A[..., 0])
    return jnp.fft.irfft2(fa[..., None] * system.kernels_fft, s=(height, width), axes=(0, 1))


def affinity(system: System, state: State) -> jax.Array:
    """The parameter-embedded affinity of Section 5.3,
    ``U(p) = sum_k P_k(p) G_k(K_k * A)(p)``: ``(H, W, C)``."""
    g = growth(potentials(system, state.A), system.mu, system.sigma)
    return jnp.sum(state.P * g, axis=-1, keepdims=True)


def shift(z: jax.Array, by: int, axis: int, wrap: bool) -> jax.Array:
    """``z`` moved by ``by`` cells along ``axis``: periodic (``wrap``, ``jnp.roll``) or
    filled with zeros from outside the grid (walls)."""
    if wrap:
        return jnp.roll(z, by, axis)
    size = z.shape[axis]
    pad = [(0, 0)] * z.ndim
    pad[axis] = (max(by, 0), max(-by, 0))
    return jax.lax.slice_in_dim(jnp.pad(z, pad), max(-by, 0), max(-by, 0) + size, axis=axis)


def sobel(x: jax.Array, wrap: bool = True) -> jax.Array:
    """Sobel gradient of ``x`` ``(H, W, ...)``: ``(H, W, ..., 2)``, the derivative along
    rows (axis 0) then along columns (axis 1); periodic (``wrap``) or with zeros
    outside the grid (walls, the reference's ``convolve2d(..., mode="same")``).

    Unnormalised filters ``[1, 2, 1] x [1, 0, -1]`` as in Flow Lenia's code: on a
    linear field they give 8 times the slope.
    """

    def smooth(z, axis):
        return shift(z, 1, axis, wrap) + 2.0 * z + shift(z, -1, axis, wrap)

    def diff(z, axis):
        return shift(z, -1, axis, wrap) - shift(z, 1, axis, wrap)

    return jnp.stack([smooth(diff(x, 0), 1), smooth(diff(x, 1), 0)], axis=-1)


def flow(U: jax.Array, A: jax.Array, cfg: FlowLeniaConfig) -> jax.Array:
    """``F = (1 - alpha) grad U - alpha grad A_Sigma`` with
    ``alpha = clip((A_Sigma / theta_A)^n, 0, 1)`` (Section 5.2), clipped per axis to
    ``[-D, D]``, ``D = reach - s`` (the reference's flow bound): ``(H, W, C, 2)``."""
    wrap = cfg.border == "torus"
    a_sum = jnp.sum(A, axis=-1, keepdims=True)  # (H, W, 1)
    alpha = jnp.clip((a_sum / cfg.theta_A) ** cfg.n, 0.0, 1.0)[..., None]
    F = (1.0 - alpha) * sobel(U, wrap) - alpha * sobel(a_sum, wrap)
    return jnp.clip(F, -cfg.flow_bound, cfg.flow_bound)


def displacement(F: jax.Array, cfg: FlowLeniaConfig) -> jax.Array:
    """``dt F`` clipped per axis to ``[-D, D]``, ``D = reach - s``, ``F`` ``(H, W, C, 2)``.
    At walls the target ``q + dt F(q)`` is then kept in ``[s - 1/2, size - 1/2 - s]``
    per axis (cell ``i`` spans ``[i - 1/2, i + 1/2]``), so that the whole square of
    matter stays inside the grid."""
    bound = cfg.flow_bound
    disp = jnp.clip(cfg.dt * F, -bound, bound)
    if cfg.border == "torus":
        return disp
    height, width = F.shape[:2]
    pos = jnp.stack(
        jnp.meshgrid(
            jnp.arange(height, dtype=F.dtype), jnp.arange(width, dtype=F.dtype), indexing="ij"
        ),
        axis=-1,
    )[:, :, None, :]  # (H, W, 1, 2)
    top = jnp.array([height, width], F.dtype) - 0.5 - cfg.s
    return jnp.clip(pos + disp, cfg.s - 0.5, top) - pos


# ----- reintegration tracking -----


def overlap(i: jax.Array, x: jax.Array, s: float) -> jax.Array:
    """Length of ``[x - s, x + s]`` inside the unit cell ``[i - 1/2, i + 1/2]``."""
    return jnp.maximum(jnp.minimum(x + s, i + 0.5) - jnp.maximum(x - s, i - 0.5), 0.0)


def first_cell(x: jax.Array, s: float) -> jax.Array:
    """The cell holding ``x - s`` (integer-valued float): the first cell, relative
    to the sender, that its square can cover along one axis.

    Corrected for the rounding of ``x - s + 1/2``, so that ``overlap`` is exactly 0
    for the cell before it: no matter falls outside the sender's window of
    ``slots`` cells (the window's far end has a margin of at least
    ``floor(2s) + 1 - 2s > 0`` cells).
    """
    lo = x - s
    base = jnp.floor(lo + 0.5)
    return jnp.where(base - 0.5 > lo, base - 1.0, base)


def axis_weights(x: jax.Array, s: float, slots: int) -> tuple[jax.Array, jax.Array]:
    """Along one axis, the first cell a sender's square covers (``first_cell``) and
    the fractions of the square inside that cell and the next ``slots - 1``:
    ``overlap / 2s``, ``(slots, ...)``.

    ``2s`` is taken as the sum of the overlaps (equal in exact arithmetic) and the
    largest fraction as one minus the others, so that the fractions sum to one
    up to a single rounding: without this, the rounding of the divisions biases
    the total mass by about -4e-8 per step.
    """
    base = first_cell(x, s)
    over = jnp.stack([overlap(base + j, x, s) for j in range(slots)])
    frac = over / jnp.sum(over, axis=0)
    largest = jnp.arange(slots).reshape((slots,) + (1,) * x.ndim) == jnp.argmax(over, axis=0)
    rest = jnp.sum(jnp.where(largest, 0.0, frac), axis=0)
    return base, jnp.where(largest, 1.0 - rest, frac)


def _noise(key: jax.Array, cfg: FlowLeniaConfig) -> jax.Array:
    """Gumbel noise, one draw per sender and slot: ``(slots, slots, H, W)``."""
    return jax.random.gumbel(key, (cfg.slots, cfg.slots, cfg.height, cfg.width))


def _mixing_score(parcel: jax.Array, sent: jax.Array, gumbel: jax.Array) -> jax.Array:
    """Gumbel-max scores of the parameter draw: ``log(parcel) + gumbel`` where matter
    is sent (the largest score wins with probability proportional to the parcel),
    ``-inf`` elsewhere.  Shared by both reintegrations, so that they draw alike."""
    return jnp.where(sent, jnp.log(jnp.where(sent, parcel, 1.0)) + gumbel, -jnp.inf)


def reintegrate(
    A: jax.Array, P: jax.Array, disp: jax.Array, key: jax.Array, cfg: FlowLeniaConfig
) -> tuple[jax.Array, jax.Array]:
    """Reintegration tracking with sampling of ``P`` (Sections 5.2 and 5.3).

    ``A^{t+dt}(p) = sum_q A(q) I(q, p)`` with ``I(q, p)`` the fraction of the square
    of half-side ``s`` centred on ``q + disp(q)`` inside cell ``p``; the new
    ``P(p)`` is ``P(q)`` for a sender ``q`` drawn with probability proportional to
    the parcel ``A(q) I(q, p)`` (Gumbel-max on its log, noise from ``key``), and 0
    where less than ``mass_epsilon`` arrives.  ``A`` ``(H, W, 1)``, ``P`` ``(H, W, |K|)``, ``disp``
    ``(H, W, 1, 2)``.

    Each sender covers ``slots x slots`` cells starting at ``first_cell`` per axis;
    its parcels are scatter-added to them (9 per cell instead of 121 gathers).
    """
    height, width = A.shape[:2]
    n = height * width
    k = cfg.slots
    a, dy, dx = A[..., 0], disp[..., 0, 0], disp[..., 0, 1]
    base_y, weight_y = axis_weights(dy, cfg.s, k)  # (H, W), (k, H, W)
    base_x, weight_x = axis_weights(dx, cfg.s, k)
    parcels = a * weight_y[:, None] * weight_x[None, :]  # (k, k, H, W): a * share_y * share_x
    rows = jnp.arange(height)[:, None] + base_y.astype(jnp.int32) + jnp.arange(k)[:, None, None]
    cols = jnp.arange(width)[None, :] + base_x.astype(jnp.int32) + jnp.arange(k)[:, None, None]
    target = ((rows % height)[:, None] * width + (cols % width)[None, :]).reshape(-1)
    parcels = parcels.reshape(-1)
    new_a = jnp.zeros(n, A.dtype).at[target].add(parcels)

    sent = parcels > 0
    score = _mixing_score(parcels, sent, _noise(key, cfg).reshape(-1))
    best = jnp.full(n, -jnp.inf, score.dtype).at[target].max(score)
    pair = jnp.arange(score.shape[0], dtype=jnp.int32)
    winner = (
        jnp.full(n, -1, jnp.int32)
        .at[target]
        .max(jnp.where(sent & (score == best[target]), pair, -1))
    )
    keep = (winner >= 0) & (new_a > cfg.mass_epsilon)
    new_p = jnp.where(keep[:, None], P.reshape(n, -1)[winner % n], 0.0)
    return new_a.reshape(A.shape), new_p.reshape(P.shape)


def reintegrate_reference(
    A: jax.Array, P: jax.Array, disp: jax.Array, key: jax.Array, cfg: FlowLeniaConfig
) -> tuple[jax.Array, jax.Array]:
    """``reintegrate`` by gathering the full ``(2 reach + 1)^2`` neighbourhood of every
    cell (Plantec et al.'s scheme): slower, for checks and benchmarks.

    Every receiver visits every offset; a pair exchanges matter when the offset
    falls in the sender's window, with the same per-axis fractions
    (``axis_weights``) and the same random draws (Gumbel noise per sender and
    slot), so both give the same ``P`` and the same ``A`` up to the order of the
    final sums.  ``tests/test_flow_lenia.py`` checks both against a float64
    computation of the overlap areas.
    """
    k, d = cfg.slots, cfg.reach
    a, dy, dx = A[..., 0], disp[..., 0, 0], disp[..., 0, 1]
    base_y, weight_y = axis_weights(dy, cfg.s, k)  # (H, W), (k, H, W) per sender
    base_x, weight_x = axis_weights(dx, cfg.s, k)
    base = jnp.stack([base_y, base_x]).astype(jnp.int32)
    noise = _noise(key, cfg).reshape(k * k, *a.shape)
    offsets = jnp.array(
        [(oy, ox) for oy in range(-d, d + 1) for ox in range(-d, d + 1)], dtype=jnp.int32
    )

    def receive(carry, offset):
        total, best, best_p = carry

        def from_sender(z, axes=(0, 1)):  # z at q = p - offset, for every receiver p
            return jnp.roll(z, (offset[0], offset[1]), axis=axes)

        slot = offset[:, None, None] - from_sender(base, axes=(1, 2))  # (2, H, W)
        in_window = jnp.all((slot >= 0) & (slot < k), axis=0)
        slot = jnp.clip(slot, 0, k - 1)

        def pick(z, i):  # z (k..., H, W) of the sender, at the pair's slot
            return jnp.take_along_axis(from_sender(z, axes=(1, 2)), i[None], axis=0)[0]

        share_y = jnp.where(in_window, pick(weight_y, slot[0]), 0.0)
        parcel = from_sender(a) * share_y * pick(weight_x, slot[1])
        g = pick(noise, slot[0] * k + slot[1])
        sent = (parcel > 0) & in_window
        score = _mixing_score(parcel, sent, g)
        better = score > best
        best_p = jnp.where(better[..., None], from_sender(P), best_p)
        return (total + parcel, jnp.where(better, score, best), best_p), None

    init = (jnp.zeros_like(a), jnp.full(a.shape, -jnp.inf), jnp.zeros_like(P))
    (total, best, best_p), _ = jax.lax.scan(receive, init, offsets)
    keep = (best > -jnp.inf) & (total > cfg.mass_epsilon)
    return total[..., None], jnp.where(keep[..., None], best_p, 0.0)


# ----- simulation -----


def mixing_key(key: jax.Array, cfg: FlowLeniaConfig) -> jax.Array:
    """The key of a step's parameter draw: the world's fixed key (``mix = "stoch"``,
    so ``key`` is unused and episodes are deterministic) or ``key`` itself
    (``"stoch_fresh"``)."""
    return jax.random.PRNGKey(cfg.mix_seed) if cfg.mix == "stoch" else key


def step(system: System, state: State, key: jax.Array, cfg: FlowLeniaConfig) -> State:
    """One Flow Lenia step: affinity, flow, displacement, reintegration (``key``
    matters only with ``mix = "stoch_fresh"``)."""
    F = flow(affinity(system, state), state.A, cfg)
    A, P = reintegrate(state.A, state.P, displacement(F, cfg), mixing_key(key, cfg), cfg)
    return State(A=A, P=P)


@partial(jax.jit, static_argnames=("cfg", "steps"))
def rollout(
    system: System, state: State, key: jax.Array, cfg: FlowLeniaConfig, steps: int | None = None
) -> State:
    """An episode of ``steps`` (default ``cfg.steps``) steps: states stacked
    ``(T + 1, ...)``, the initial state first."""
    steps = cfg.steps if steps is None else steps

    def body(current, k):
        nxt = step(system, current, k, cfg)
        return nxt, nxt

    _, later = jax.lax.scan(body, state, jax.random.split(key, steps))
    return jax.tree_util.tree_map(lambda x0, xs: jnp.concatenate([x0[None], xs]), state, later)


@partial(jax.jit, static_argnames=("cfg", "batch"))
def simulate_batch(key: jax.Array, cfg: FlowLeniaConfig, batch: int) -> tuple[System, State]:
    """``batch`` random systems, each from its own random initial state: the systems
    and their episodes (``A`` ``(batch, T + 1, H, W, C)``, ``P`` ``(batch, T + 1, H, W, |K|)``)."""
    if batch < 1:
        raise ValueError(f"batch must be a positive integer, got {batch}")
    k_sys, k_init, k_run = jax.random.split(key, 3)
    systems = jax.vmap(sample_system, in_axes=(0, None))(jax.random.split(k_sys, batch), cfg)
    states = jax.vmap(initial_state, in_axes=(0, None))(jax.random.split(k_init, batch), cfg)
    systems, states, keys = shard_batch((systems, states, jax.random.split(k_run, batch)))
    episodes = jax.vmap(lambda sy, st, k: rollout(sy, st, k, cfg))(systems, states, keys)
    return replicated((systems, episodes))


def mass_drift(A: jax.Array) -> jax.Array:
    """Largest relative change of total mass along each episode, ``A`` ``(..., T + 1, H, W, C)``."""
    mass = jnp.sum(A, axis=(-3, -2, -1))
    return jnp.max(jnp.abs(mass / mass[..., :1] - 1.0), axis=-1)


@partial(jax.jit, static_argnames=("cfg", "split"))
def rollout_batch(
    system: System, states: State, key: jax.Array, cfg: FlowLeniaConfig, split: bool = False
) -> State:
    """Episodes of one system from a batch of initial states (``A`` ``(B, H, W, C)``),
    one key each split from ``key``: ``A`` ``(B, T + 1, H, W, C)``, ``P`` likewise.
    They are simulated split over every local device and returned whole on each
    (``replicated``: safe for eager code to read), or, with ``split``, left split for a
    jitted caller that keeps them so (the FLT's training step)."""
    keys = jax.random.split(key, states.A.shape[0])
    states, keys = shard_batch((states, keys))  # the episodes over every local device
    episodes = jax.vmap(lambda st, k: rollout(system, st, k, cfg))(states, keys)
    return episodes if split else replicated(episodes)


@partial(jax.jit, static_argnames=("cfg", "batch", "split"))
def simulate_system(
    system: System, key: jax.Array, cfg: FlowLeniaConfig, batch: int, split: bool = False
) -> State:
    """``batch`` episodes of one system, each from its own random initial state
    (``A`` ``(batch, T + 1, H, W, C)``, ``P`` ``(batch, T + 1, H, W, |K|)``); ``split`` as
    in ``rollout_batch``."""
    if batch < 1:
        raise ValueError(f"batch must be a positive integer, got {batch}")
    k_init, k_run = jax.random.split(key)
    states = jax.vmap(initial_state, in_axes=(0, None))(jax.random.split(k_init, batch), cfg)
    return rollout_batch(system, states, k_run, cfg, split)
