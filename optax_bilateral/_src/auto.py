"""``sigma_d="auto"``: the data term's scale, and how much to filter, chosen from the data.

Three parts, derived in docs/auto_sigma.md and measured by ``python -m experiments.tuning``:

* **The scale.** In a postfilter, one learning rate in the guide's units:
  ``sigma_d = sqrt(C) mean_p ||guide_t[p] - guide_{t-1}[p]|| / mean_p ||d_{t-1}[p]||``
  (``C`` channels per texel, ``d`` the postfilter's last output ``m~ / (sqrt(v~) + eps)``):
  a guide difference that one step at the learning rate could make or undo is noise the
  optimiser is still moving through; larger ones are edges. It scales with the guide and
  follows the learning rate and its schedule, so it needs no unit. A prefilter, which does
  not see the step it leads to, uses ``STEP_FACTOR`` times the mean guide step instead.
  Before the guide has moved (the first step) the guide's mean neighbour difference
  stands in (``CONTRAST_FACTOR`` times it). On a leaf of more than ``MIN_TEXELS`` texels
  both means run over a strided sub-grid of at least that many (``stride``), and only
  that sub-grid of the guide is kept: such a mean is known to a fraction of a percent,
  and copying and reading the whole guide is memory traffic the update is bound by.
* **The blend** (postfilter with moments only). The filter's bias accumulates over steps,
  its noise reduction does not: texels where the residual ``r = m_hat - B m_hat`` persists
  over time beyond what the moments' noise (supplement eq. 24, ``v - m^2``) explains keep
  more of their unfiltered moments, ``m~ = lam m_hat + (1 - lam) B m_hat`` and likewise
  ``v``. ``lam`` is per entry and the same for ``m`` and ``v``, so ``m~`` and ``v~`` come
  from one non-negative, row-stochastic operator and the step stays bounded
  (supplement §1.3). A leaf blends only where persistent residuals are widespread
  (``GATE``): a few texels with large ``lam`` early on are noise in the estimate itself.
  While a leaf's gate is closed, it is checked only every ``CHECK_PERIOD``-th step, from
  the sub-grid's entries (:func:`gate`), and the blend starts at the step after it opens
  (the residual's average is kept every step): on most leaves of most problems the gate
  stays closed, and the statistics are the blend's dearest part (docs/auto_sigma.md,
  "Cost"; :func:`stage`).
* **Correlated noise** (postfilter with moments, cross-guided). Where the gradient's noise
  is spatially correlated (the transposed blur of a sparse residual: deconvolution or
  tomography from random subsets), neighbouring texels share their noise and the finest
  levels average little of it. Where the lag-1 correlation of ``g - m_hat`` between
  neighbours is at least ``CORRELATED`` and that difference is noise, not the signal's
  drift (``NOISY``; :func:`correlated`), the step filters at ``HEAVY_FACTOR`` times
  sigma_d with :func:`extra_levels` more levels, and without the blend. The check runs at
  the second step and every ``CHECK_PERIOD``-th, and holds until the next
  (``AutoState.correlated``).
"""

from __future__ import annotations

import functools
import math
from typing import Any, NamedTuple, cast

import jax
import jax.numpy as jnp
import numpy as np

from optax_bilateral._src import layout, sharded
from optax_bilateral._src.filter import atrous_bilateral

AUTO = "auto"
RATE_FACTOR = 1.0  # postfilter: sigma_d per learning rate (in guide units) per sqrt(channel)
STEP_FACTOR = 3.0  # prefilter and "sure": sigma_d per mean guide step
CONTRAST_FACTOR = 1.5  # sigma_d per mean deviation from the local average (~ neighbour difference)
RESIDUAL_DECAY = 0.97  # the residual's EMA (~33 steps: a bias below one step's noise shows)
GAIN = 0.25  # lam = 0 until the persistent residual exceeds 1/GAIN times its noise floor
POWER = 2.0
GATE = (0.5, 0.65)  # mean lam of a leaf below GATE[0]: no blend; above GATE[1]: full blend
CHECK_PERIOD = 8  # a closed gate is re-checked every 8th step: a quarter of the residual's EMA
MIN_TEXELS = 16384  # a larger leaf's scale is a mean over a strided sub-grid of >= this many texels
CORRELATED = math.exp(-0.25)  # lag-1 correlation of Gaussian-correlated noise one texel wide
NOISY = 0.25  # g - m_hat_{t-1} has >= 1/4 of m_hat's energy (pure noise: 2.5 at b1 = 0.2)
HEAVY_FACTOR = 3.0  # sigma_d per learning rate where the gradient's noise is correlated


class AutoState(NamedTuple):
    """One leaf's state for ``sigma_d="auto"`` (in :class:`PrefilterState` and
    :class:`PostfilterState`).

    ``sigma_d`` is, in a postfilter, one learning rate in the guide's units: the mean change
    of the guide per step over the mean norm of the step's direction, times ``sqrt(C)``
    for ``C`` channels per texel (in a prefilter, 3 times the mean change of the guide per
    step; before the guide moves: 1.5 times its mean deviation from the local average),
    and the postfilter blends
    ``lam m_hat + (1 - lam) B m_hat`` (likewise ``v``, the same ``lam``) where the filter's
    residual persists beyond the moments' noise ``v - m^2`` (docs/auto_sigma.md).

    Attributes:
      previous_guide: the guide the last update saw, with the guide's shape (the
        parameter leaf's, or a callable guide's), or on a leaf of more than
        ``MIN_TEXELS`` (16384) texels its sub-grid (every ``s``-th texel along each
        spatial axis, :func:`stride`); None for ``guide="self"``.
      residual: the exponential moving average (decay 0.97) of ``m_hat - B m_hat``, with
        the leaf's shape; None in a :func:`prefilter` or a memoryless postfilter (no
        moments).
      direction: the mean norm per texel of a postfilter's last output
        ``m~ / (sqrt(v~) + eps)`` (a scalar; 0 before the first step); None in a
        :func:`prefilter`.
      gate: how far the blend was open at the last step (a scalar in [0, 1]; 0 at a step
        that skipped the blend's statistics); None where ``residual`` is. While it is 0,
        it is checked only every ``CHECK_PERIOD`` (8) steps, from a sub-grid of the leaf,
        and a gate that opens there blends from the next step (:func:`stage`).
      correlated: 1 where the gradient's noise was spatially correlated at the last check
        (:func:`correlated`; the second step and every ``CHECK_PERIOD``-th), else 0 (a
        scalar): until the next check the postfilter filters at ``HEAVY_FACTOR`` times sigma_d with
        :func:`extra_levels` more levels and without the blend. None where ``residual``
        is.

    Example::

        >>> import jax.numpy as jnp, optax_bilateral as ob
        >>> state = ob.postfilter().init({"tex": jnp.ones((16, 16, 3))})   # sigma_d="auto"
        >>> auto = state.auto["tex"]
        >>> type(auto).__name__, auto.previous_guide.shape, auto.residual.shape
        ('AutoState', (16, 16, 3), (16, 16, 3))
        >>> float(auto.direction), float(auto.gate), float(auto.correlated)
        (0.0, 0.0, 0.0)
    """

    previous_guide: jax.Array | None
    residual: jax.Array | None
    direction: jax.Array | None
    gate: jax.Array | None
    correlated: jax.Array | None = None


def is_auto(sigma_d: Any) -> bool:
    return isinstance(sigma_d, str) and sigma_d == AUTO


def _guide_axes(guide: jax.Array, axes: tuple[int, ...]) -> tuple[int, ...]:
    """The spatial axes of ``guide``: ``axes`` for a leaf-shaped guide, all for a grid-only one."""
    return tuple(range(guide.ndim)) if guide.ndim == len(axes) else axes


def _texel_norm(x: jax.Array, axes: tuple[int, ...]) -> jax.Array:
    channels = tuple(a for a in range(x.ndim) if a not in axes)
    return jnp.sqrt(jnp.sum(x * x, axis=channels)) if channels else jnp.abs(x)


def _finite_mean(x: jax.Array) -> jax.Array:
    """Mean over the entries that are not NaN (a masked guide holds NaN at unobserved
    texels); 0 if none."""
    ok = ~jnp.isnan(x)
    return jnp.sum(jnp.where(ok, x, 0)) / jnp.maximum(jnp.sum(ok), 1)


def contrast(guide: jax.Array, axes: tuple[int, ...]) -> jax.Array:
    """The guide's mean distance from its local average (one low-pass level of the filter,
    which runs sharded like the leaf): the scale of its texel-to-texel variation."""
    guide = guide.astype(jnp.promote_types(guide.dtype, jnp.float32))
    axes = _guide_axes(guide, axes)
    (local,) = _smooth((jnp.nan_to_num(guide),), axes)
    return _finite_mean(_texel_norm(guide - local, axes))


def stride(shape: tuple[int, ...], axes: tuple[int, ...]) -> int:
    """The sub-grid's stride along every spatial axis: the largest power of two that leaves
    at least ``MIN_TEXELS`` texels (1 for a leaf with fewer)."""
    s = 1
    while math.prod(-(-shape[a] // (2 * s)) for a in axes) >= MIN_TEXELS:
        s *= 2
    return s


def subgrid(x: jax.Array, axes: tuple[int, ...]) -> jax.Array:
    """Every ``stride``-th texel of ``x`` along each of its spatial ``axes`` (all channels)."""
    s = stride(x.shape, axes)
    if s == 1:
        return x
    return x[tuple(slice(None, None, s) if a in axes else slice(None) for a in range(x.ndim))]


def kept_guide(guide: jax.Array, axes: tuple[int, ...]) -> jax.Array:
    """What :attr:`AutoState.previous_guide` keeps of a guide: its sub-grid."""
    return subgrid(guide, _guide_axes(guide, axes))


def direction_norm(d: jax.Array, axes: tuple[int, ...]) -> jax.Array:
    """The mean norm per texel of a step's direction (:attr:`AutoState.direction`), over the
    same sub-grid as the guide's step; ``d`` is finite (unobserved entries step by 0), so a
    plain mean: one reduction, not two."""
    return jnp.mean(_texel_norm(subgrid(d, axes), axes))


def sigma(
    guide: jax.Array,
    previous: jax.Array | None,
    count: jax.Array,
    axes: tuple[int, ...],
    direction: jax.Array | None = None,
) -> jax.Array:
    """The leaf's sigma_d at step ``count`` (1 = first); ``direction`` (a postfilter's
    :attr:`AutoState.direction`) or None for the prefilter's and ``"sure"``'s step scale."""
    if previous is None:
        return CONTRAST_FACTOR * contrast(guide, axes)
    guide = guide.astype(jnp.promote_types(guide.dtype, jnp.float32))
    guide_axes = _guide_axes(guide, axes)
    now = subgrid(guide, guide_axes)
    step = _finite_mean(_texel_norm(now - previous.astype(guide.dtype), guide_axes))
    moved = (count > 1) & (step > 0)
    if direction is None:
        scale = STEP_FACTOR * step
    else:
        channels = math.prod(n for a, n in enumerate(guide.shape) if a not in guide_axes)
        rate = step / jnp.where(direction > 0, direction, 1).astype(step.dtype)
        scale = RATE_FACTOR * math.sqrt(channels) * rate
        moved = moved & (direction > 0)
    # The contrast costs a filter pass; only the first step (or a guide at rest) needs it.
    return jax.lax.cond(
        moved,
        lambda: scale,
        lambda: (CONTRAST_FACTOR * contrast(guide, axes)).astype(step.dtype),
    )


def extra_levels(axes: tuple[int, ...]) -> int:
    """The levels added where the noise is correlated: 2 on a 1-D grid, 1 on a 2-D one, none
    on 3-D (there the compiled extra level slows every update, also where it does not run;
    docs/auto_sigma.md, "Correlated noise")."""
    return {1: 2, 2: 1}.get(len(axes), 0)


def _neighbours(x: jax.Array, axes: tuple[int, ...], axis: int) -> tuple[jax.Array, jax.Array]:
    """``x[p]`` and ``x[p + 1 along axis]`` for every ``p`` on the sub-grid (:func:`stride`;
    every even ``p`` along ``axis`` where the stride is 1). Pairs from a reshape, not
    shifted slices, which a grid sharded along ``axis`` cannot take."""
    s = stride(x.shape, axes)
    x = x[
        tuple(
            slice(None, None, s) if a in axes and a != axis else slice(None) for a in range(x.ndim)
        )
    ]
    q = max(s, 2)
    n = x.shape[axis] // q
    x = jax.lax.slice_in_dim(x, 0, n * q, axis=axis)
    blocks = x.reshape(x.shape[:axis] + (n, q) + x.shape[axis + 1 :])
    return jnp.take(blocks, 0, axis=axis + 1), jnp.take(blocks, 1, axis=axis + 1)


def correlated(
    g: jax.Array,
    m: jax.Array,
    *,
    b1: Any,
    c1: jax.Array,
    axes: tuple[int, ...],
    observed: jax.Array | None = None,
) -> jax.Array:
    """Whether the leaf's gradient noise is spatially correlated: the lag-1 correlation
    between neighbours of ``z = g - m_hat`` (``m`` the updated first moment, ``c1`` its bias
    correction), averaged over the spatial ``axes``, is at least ``CORRELATED``, and ``z``
    is noise: ``z = (1 - (1 - b1) / c1) (g - m_hat_{t-1})``, whose energy is at least
    ``NOISY`` times ``m_hat``'s. Sums run over the sub-grid (:func:`stride`) and the
    ``observed`` entries (a leaf-shaped mask); False at the first step or with ``b1 = 0``."""
    dtype = jnp.promote_types(m.dtype, jnp.float32)
    c1 = jnp.asarray(c1, dtype)
    m_hat = m.astype(dtype) / c1
    z = g.astype(dtype) - m_hat
    if observed is not None:
        z, m_hat = jnp.where(observed, z, 0), jnp.where(observed, m_hat, 0)
    corr = []
    for a in axes:
        if g.shape[a] > 1:
            x0, x1 = _neighbours(z, axes, a)
            den = jnp.sqrt(jnp.sum(x0 * x0) * jnp.sum(x1 * x1))
            corr.append(jnp.where(den > 0, jnp.sum(x0 * x1) / jnp.where(den > 0, den, 1), 0))
    if not corr:
        return jnp.zeros([], bool)
    lag = 1 - (1 - jnp.asarray(b1, dtype)) / c1
    noise = jnp.sum(jnp.square(subgrid(z, axes)))
    signal = jnp.sum(jnp.square(subgrid(m_hat, axes)))
    return (jnp.mean(jnp.stack(corr)) >= CORRELATED) & (noise > NOISY * lag * lag * signal)


def _ema_variance_ratio(b: jax.Array, c: jax.Array) -> jax.Array:
    """Var of a bias-corrected EMA (decay ``b``, ``c = 1 - b^t``) per unit sample variance:
    ``(1-b)(1-b^2t) / ((1+b)(1-b^t)^2)``, with ``1 - b^2t = c (2 - c)``."""
    return (1 - b) * (2 - c) / ((1 + b) * c)


def noise_ratio(b1: jax.Array, c1: jax.Array, count: jax.Array) -> tuple[jax.Array, jax.Array]:
    """``(rho, usable)``: Var of ``m_hat`` per unit gradient variance, and whether the noise
    can be told from the signal (the step has memory: ``t > 1``, ``b1 > 0``)."""
    ratio = _ema_variance_ratio(b1, c1)
    return ratio, (count > 1) & (ratio < 1 - 1e-6)


def _smooth(fields: tuple[jax.Array, ...], axes: tuple[int, ...]) -> tuple[jax.Array, ...]:
    """Local averages of the statistics: one level of the filter's 5-tap B-spline with
    every weight 1 (sigma_d = inf), on one device or sharded like the leaf."""
    # The guide is unused at sigma_d = inf: a grid of zeros, sharded like the leaf.
    channels = tuple(a for a in range(fields[0].ndim) if a not in axes)
    guide = jnp.zeros_like(jnp.sum(fields[0], axis=channels))
    guide = jnp.transpose(guide, [sorted(axes).index(a) for a in axes])
    out = atrous_bilateral(fields, guide, sigma_d=jnp.inf, levels=1, spatial_axes=axes)
    return cast(tuple[jax.Array, ...], out)


_TAPS = np.array([1, 4, 6, 4, 1]) / 16  # the filter's first level: the B-spline at stride 1


def _smooth_subgrid(fields: tuple[jax.Array, ...], axes: tuple[int, ...]) -> tuple[jax.Array, ...]:
    """:func:`_smooth`'s local averages at the sub-grid's entries (:func:`subgrid`) only:
    per spatial axis, the 5 taps read at every ``stride``-th texel, normalised over those
    inside the grid (the filter's weight off the grid is 0). Without a sub-grid, or on a
    grid split over devices in its type (whose axes take no slice of uneven length), the
    full local averages' sub-grid."""
    s = stride(fields[0].shape, axes)
    if s == 1 or sharded.is_split(fields[0]):
        return tuple(subgrid(f, axes) for f in _smooth(fields, axes))
    out = []
    for x in fields:
        for a in axes:
            x = _taps_at_stride(x, a, s)
        out.append(x)
    return tuple(out)


def _taps_at_stride(x: jax.Array, axis: int, s: int) -> jax.Array:
    n = x.shape[axis]
    r = len(_TAPS) // 2
    kept = (n - 1) // s + 1
    total, norm = 0.0, np.zeros(kept)
    for k, w in enumerate(_TAPS):
        # The sub-grid's texels whose tap k falls on the grid: i in [lo, hi).
        lo = max(0, -(-(r - k) // s))
        hi = min(kept, (n - 1 - k + r) // s + 1)
        if hi <= lo:
            continue
        start = s * lo + k - r
        taps = jax.lax.slice_in_dim(x, start, start + s * (hi - lo - 1) + 1, stride=s, axis=axis)
        # Padded after the slice: only the sub-grid's rows are copied.
        pad = [(0, 0)] * x.ndim
        pad[axis] = (lo, kept - hi)
        total = total + float(w) * jnp.pad(taps, pad)
        norm[lo:hi] += w
    shape = [1] * x.ndim
    shape[axis] = kept
    return total / jnp.asarray(norm.reshape(shape), x.dtype)


def _blend_weight(m, v, residual, smooth, *, b1, c1, c2, count):
    """The blend's weight of the unfiltered moments per entry, before the gate; ``smooth``
    takes the local averages (:func:`_smooth`, or :func:`_smooth_subgrid` at the sub-grid's
    entries only)."""
    dtype = m.dtype
    b1 = jnp.asarray(b1, dtype)
    c1, c2 = jnp.asarray(c1, dtype), jnp.asarray(c2, dtype)
    t = count.astype(dtype)
    decay = jnp.asarray(RESIDUAL_DECAY, dtype)
    residual_hat = residual / (1 - decay**t)
    # Noise of m_hat from v_hat - m_hat^2 (eq. 24), then of the residual's EMA.
    ratio, usable = noise_ratio(b1, c1, count)
    k = jnp.where(usable, ratio / jnp.maximum(1 - ratio, 1e-6), 0)
    noise = jnp.maximum(v / c2 - (m / c1) ** 2, 0) * k
    residual_noise = noise * _ema_variance_ratio(decay, 1 - decay**t)
    residual_noise = residual_noise * (1 + b1 * decay) / (1 - b1 * decay)  # m_hat is correlated
    floor, signal = smooth((residual_noise, residual_hat**2))
    lam = 1 - floor / (GAIN * jnp.where(signal > 0, signal, 1))
    return jnp.where(usable & (signal > 0), jnp.clip(lam, 0, 1), 0) ** POWER


def _gate(lam: jax.Array) -> jax.Array:
    return jnp.clip((jnp.mean(lam) - GATE[0]) / (GATE[1] - GATE[0]), 0, 1)


def weights(
    m: jax.Array,
    v: jax.Array,
    residual: jax.Array,
    *,
    b1: Any,
    c1: jax.Array,
    c2: jax.Array,
    count: jax.Array,
    axes: tuple[int, ...],
) -> tuple[jax.Array, jax.Array]:
    """``(lam, gate)``: the blend's weight of the unfiltered moments per entry (the gate
    applied) and how far the leaf's blend is open (a scalar in [0, 1], ``GATE``).

    ``m, v`` are the moments before bias correction (``c1``, ``c2``); ``residual`` is the
    residual's EMA with this step's (:func:`update_residual`).
    """
    smooth = functools.partial(_smooth, axes=axes)
    lam = _blend_weight(m, v, residual, smooth, b1=b1, c1=c1, c2=c2, count=count)
    gate = _gate(lam)
    return lam * gate, gate


def gate(m: jax.Array, v: jax.Array, residual: jax.Array, *, axes, **statistics) -> jax.Array:
    """:func:`weights`' gate (the same arguments: ``b1``, ``c1``, ``c2``, ``count``) from the
    sub-grid's entries (:func:`stride`) alone: a closed gate's check, which blends nothing
    (the blend, if the gate opens, starts at the next step) and so needs no weight per
    entry."""
    smooth = functools.partial(_smooth_subgrid, axes=axes)
    return _gate(_blend_weight(m, v, residual, smooth, **statistics))


def mix(lam: jax.Array, x: jax.Array, bx: jax.Array) -> jax.Array:
    """``lam x + (1 - lam) B x``: with one ``lam`` for ``m`` and ``v``, one non-negative,
    row-stochastic operator for both."""
    return lam * x + (1 - lam) * bx


SKIP, CHECK, BLEND = 0, 1, 2  # what a step computes of the blend (:func:`stage`), in order


def stage(gate: jax.Array, count: jax.Array) -> jax.Array:
    """What this step computes of the blend: ``BLEND`` (its statistics and the blend) if the
    gate was open at the last step; else ``CHECK`` (the gate alone, :func:`gate`) at a
    multiple of ``CHECK_PERIOD``; else ``SKIP`` (nothing)."""
    check = jnp.where(count % CHECK_PERIOD == 0, CHECK, SKIP)
    return jnp.where(gate > 0, BLEND, check).astype(jnp.int32)


def update_residual(m, bm, residual, c1, observed):
    """The residual's EMA with this step's ``m_hat - B m_hat`` (kept where unobserved)."""
    decay = jnp.asarray(RESIDUAL_DECAY, m.dtype)
    new = decay * residual + (1 - decay) * (m - bm) / jnp.asarray(c1, m.dtype)
    return new if observed is None else jnp.where(observed, new, residual)


def full_mask(observed: jax.Array | None, ndim: int, axes: tuple[int, ...]) -> jax.Array | None:
    return None if observed is None else layout.expand_mask(observed, ndim, axes)
