"""The sigma_d rules' statistics: local averages (one level of the filter's 5-tap B-spline
with every weight 1, sigma_d = inf), on the whole grid or at a sub-grid, on one device or
sharded like the leaf; the mean distance between texels at a sub-grid; the sums behind the
lag-1 correlation between neighbours; ``"auto"``'s blend at the sub-grid; and sums of
squares that stay fast on one device and valid on a mesh. Where the filter runs on the
native kernel each is one XLA FFI call (csrc/local.h, csrc/stats.h), with the slices here
as its fallback and its derivative (:func:`runs_native`)."""

from __future__ import annotations

import functools
import math
from typing import Any, NamedTuple, cast

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from optax_bilateral._src.filter import native, sharded
from optax_bilateral._src.filter.bilateral import TAPS
from optax_bilateral._src.filter.front import atrous_bilateral, resolve_kernel
from optax_bilateral._src.filter.native import FromGradient, NoiseTest, StepCall, StepFlags
from optax_bilateral._src.numerics import Entry, value


def local_average(fields: tuple[jax.Array, ...], axes: tuple[int, ...]) -> tuple[jax.Array, ...]:
    """Local averages of the statistics: one level of the filter's 5-tap B-spline with
    every weight 1 (sigma_d = inf), on one device or sharded like the leaf. (The filter's
    kernel, not five shifted slices: inside the blend's branch, those hold several full-size
    temporaries.)"""
    # The guide is unused at sigma_d = inf: a grid of zeros, sharded like the leaf.
    channels = tuple(a for a in range(fields[0].ndim) if a not in axes)
    guide = jnp.zeros_like(jnp.sum(fields[0], axis=channels))
    guide = jnp.transpose(guide, [sorted(axes).index(a) for a in axes])
    out = atrous_bilateral(fields, guide, sigma_d=jnp.inf, levels=1, spatial_axes=axes)
    return cast(tuple[jax.Array, ...], out)


def local_average_subgrid(
    fields, axes, stride: int, nan_to_num: bool = False, run: jax.Array | bool | Entry = True
) -> tuple[jax.Array, ...]:
    """:func:`local_average`'s local averages at every ``stride``-th entry along the spatial axes
    only: per axis, the 5 taps read at the sub-grid, normalised over those inside the grid
    (the filter's weight off the grid is 0). Without a sub-grid, or on a grid split over
    devices in its type (whose axes take no slice of uneven length), the full local
    averages' sub-grid. Where the filter runs on the native kernel, one FFI call per field
    (csrc/local.h; its derivative the slices'). ``nan_to_num``: of ``jnp.nan_to_num`` of
    each field, which the native call reads so without a copy. ``run`` (a traced bool): the
    native calls give zeros without any work where it is False (the caller discards them)."""
    if sharded.is_split(fields[0]):
        fields = tuple(jnp.nan_to_num(f) for f in fields) if nan_to_num else fields
        return tuple(every(f, axes, stride) for f in local_average(fields, axes))
    axes = tuple(axes)
    return tuple(
        _native_taps(x, Entry.flag(run), axes, stride, nan_to_num)
        if runs_native(x)
        else _taps(jnp.nan_to_num(x) if nan_to_num else x, axes, stride)
        for x in fields
    )


def runs_native(x: jax.Array) -> bool:
    """Whether the rules' statistics of ``x`` run on the native kernel: the filter does
    (``kernel="auto"`` resolves to it), ``x`` is float32 or float64, not empty and not split
    over an explicit mesh."""
    return (
        not sharded.is_split(x) and native.takes_subgrid(x) and resolve_kernel("auto") == "native"
    )


def _taps(x: jax.Array, axes: tuple[int, ...], stride: int) -> jax.Array:
    for a in axes:
        x = _taps_at_stride(x, a, stride)
    return x


@functools.partial(jax.custom_jvp, nondiff_argnums=(2, 3, 4))
def _native_taps(
    x: jax.Array, run: jax.Array, axes: tuple[int, ...], stride: int, finite: bool
) -> jax.Array:
    return native.subgrid_average(x, axes, stride, finite, run)


@_native_taps.defjvp
def _native_taps_jvp(axes, stride, finite, primals, tangents):
    # Linear in x (in its finite entries, with finite): the tangent is the same average as
    # slices, which jax.grad can transpose; nan_to_num's derivative is 0 where x is not finite.
    (x, run), (t, _) = primals, tangents
    t = jnp.where(jnp.isfinite(x), t, 0) if finite else t
    return _native_taps(x, run, axes, stride, finite), _taps(t, axes, stride)


def texel_distance_mean(
    a: jax.Array,
    b: jax.Array | None,
    axes: tuple[int, ...],
    stride: int,
    run: jax.Array | bool | Entry = True,
    keep: bool = False,
    otherwise: Entry | None = None,
    scale: float = 1.0,
) -> Any:
    """``scale`` times the mean over the sub-grid's texels ``p`` (every ``stride``-th along the
    spatial ``axes``) of ``||a[stride p] - b[p]||``, the norm over ``a``'s other axes (``b``
    None: of ``||a[stride p]||``; else ``b`` has the sub-grid's shape), texels whose norm is
    NaN left out, 0 when none is left; with ``otherwise`` (an
    :class:`~optax_bilateral._src.numerics.Entry`), its value where ``run`` is False. ``keep``:
    ``(mean, every(a, axes, stride))``, the sub-grid the mean read. Where the filter runs on
    the native kernel, one FFI call (csrc/stats.h, sums in double; its derivative the
    slices'), not the slices' XLA kernels, which does no work where ``run`` (a traced bool)
    is False: 0 (or ``otherwise``) and zeros."""
    axes = tuple(axes)
    if runs_native(a):
        return _native_distance(a, b, Entry.flag(run), otherwise, axes, stride, keep, scale)
    return _slices(a, b, Entry.flag(run), otherwise, axes, stride, keep, scale)


def _distance(a, b, axes, stride):
    x = every(a, axes, stride)
    return _nan_skipping_mean(texel_norm(x if b is None else x - b, axes))


def _slices(a, b, run, otherwise, axes, stride, keep, scale):
    """:func:`texel_distance_mean` in XLA's slices (its derivative on the native kernel)."""
    mean = _distance(a, b, axes, stride)
    mean = mean if scale == 1 else scale * mean
    mean = mean if otherwise is None else jnp.where(run.value, mean, otherwise.value)
    return (mean, every(a, axes, stride)) if keep else mean


@functools.partial(jax.custom_jvp, nondiff_argnums=(4, 5, 6, 7))
def _native_distance(a, b, run, otherwise, axes, stride, keep, scale):
    return native.texel_distance_mean(a, b, axes, stride, run, keep, otherwise, scale)


@_native_distance.defjvp
def _native_distance_jvp(axes, stride, keep, scale, primals, tangents):
    # The slices' derivative (and their primal, equal up to float rounding; run or not).
    a, b, run, otherwise = primals

    def slices(a, b, otherwise):
        return _slices(a, b, run, otherwise, axes, stride, keep, scale)

    ta, tb, _, t_otherwise = tangents
    return jax.jvp(slices, (a, b, otherwise), (ta, tb, t_otherwise))


def correlation_sums(
    g: jax.Array,
    m: jax.Array,
    observed: jax.Array,
    c1,
    axes: tuple[int, ...],
    stride: int,
    run: jax.Array | bool | Entry = True,
    limit: float = math.inf,
) -> tuple[jax.Array, jax.Array]:
    """``(lags, energies)``, not differentiated, of ``z = clip(g, -limit, limit) - m / c1`` and
    ``y = m / c1`` where ``observed`` (broadcastable against ``g``), else 0 (``g`` may be the
    gradient as given, unobserved entries and all): for each spatial axis longer than 1, in
    order, the sums of ``x0^2``, ``x1^2`` and ``x0 x1`` of ``z`` over its neighbour pairs
    (:func:`neighbours`), a ``(k, 3)`` array; and the sums of ``z^2`` and ``y^2`` over the
    sub-grid (every ``stride``-th entry along ``axes``), a ``(2,)`` array. ``g`` and ``m`` share
    a float dtype. Where the filter runs on the native kernel, one FFI call (csrc/stats.h,
    sums in double) that computes ``z`` and ``y`` where it reads them, and gives zeros
    without reading anything where ``run`` (a traced bool) is False."""
    axes = tuple(axes)
    g, m = lax.stop_gradient(g), lax.stop_gradient(m)
    pairs = tuple(a for a in axes if g.shape[a] > 1)
    if runs_native(g):
        sums = native.correlation_sums(g, m, observed, c1, axes, pairs, stride, run, limit)
        return sums[:-2].reshape(len(pairs), 3), sums[-2:]
    y = m / jnp.asarray(value(c1), m.dtype)
    z, y = jnp.where(observed, jnp.clip(g, -limit, limit) - y, 0), jnp.where(observed, y, 0)
    lags = [
        _sums(x0 * x0, x1 * x1, x0 * x1)
        for x0, x1 in (neighbours(z, axes, a, stride) for a in pairs)
    ]
    energies = _sums(jnp.square(every(z, axes, stride)), jnp.square(every(y, axes, stride)))
    return jnp.stack(lags) if lags else jnp.zeros((0, 3), z.dtype), energies


def correlated_noise(
    g: jax.Array,
    m: jax.Array,
    observed: jax.Array | FromGradient,
    c1: Entry,
    axes: tuple[int, ...],
    stride: int,
    run: Entry,
    limit: float,
    test: NoiseTest,
) -> jax.Array:
    """``test``'s answer from :func:`correlation_sums`' sums where ``run`` says it is due, else
    the stored one, as 1 or 0 in ``g``'s dtype: one native FFI call (the native kernel only;
    ``sigma_d="auto"``'s JAX form of the test runs over :func:`correlation_sums`). With
    ``observed`` a :class:`FromGradient`, ``g`` is the gradient as given and the call makes
    the texels' mask from it where it reads."""
    axes = tuple(axes)
    g, m = lax.stop_gradient(g), lax.stop_gradient(m)
    pairs = tuple(a for a in axes if g.shape[a] > 1)
    return native.correlated_noise(g, m, observed, c1, axes, pairs, stride, run, limit, test)


def neighbours(
    x: jax.Array, axes: tuple[int, ...], axis: int, s: int
) -> tuple[jax.Array, jax.Array]:
    """``x[p]`` and ``x[p + 1 along axis]`` for every ``p`` on the sub-grid of stride ``s``
    (every ``max(s, 2)``-th ``p`` along ``axis``). Pairs from a reshape, not shifted slices,
    which a grid sharded along ``axis`` cannot take."""
    x = x[
        tuple(
            slice(None, None, s) if a in axes and a != axis else slice(None) for a in range(x.ndim)
        )
    ]
    q = max(s, 2)
    n = x.shape[axis] // q
    x = lax.slice_in_dim(x, 0, n * q, axis=axis)
    blocks = x.reshape(x.shape[:axis] + (n, q) + x.shape[axis + 1 :])
    return jnp.take(blocks, 0, axis=axis + 1), jnp.take(blocks, 1, axis=axis + 1)


def _sums(*xs: jax.Array) -> jax.Array:
    """Each of the same-shaped ``xs`` summed, as one reduction of their stack (XLA compiles
    every grid-wide sum as kernels of its own)."""
    return jnp.sum(jnp.stack(xs), axis=tuple(range(1, xs[0].ndim + 1)))


def subgrid_blend(m, v, residual, scalars, axes, stride, constants, reference, run: Any = True):
    """``sigma_d="auto"``'s blend at the sub-grid, ``(lam * gate, gate)``: where the rules'
    statistics run on the native kernel one FFI call (csrc/stats.h: the rule's formula
    written out in C++), whose derivative is ``reference``'s, and which gives zeros without
    computing them where ``run`` (a traced bool) is False (the caller discards them); else
    ``reference(m, v, residual, scalars)``, the rule's own (rules/auto.py, which also
    describes the ``scalars`` and the ``constants``)."""
    if runs_native(m):
        how = BlendCall(tuple(axes), stride, constants, reference)
        return _native_blend(m, v, residual, scalars, Entry.flag(run), how)
    return reference(m, v, residual, scalars)


class BlendCall(NamedTuple):
    """What is fixed about a native blend's call: the sub-grid, the rule's constants, and the
    JAX form that is its derivative."""

    axes: tuple[int, ...]
    stride: int
    constants: tuple[float, float, float, float]
    reference: Any


@functools.partial(jax.custom_jvp, nondiff_argnums=(5,))
def _native_blend(m, v, residual, scalars, run, how: BlendCall):
    return native.blend_weights(m, v, residual, scalars, how.axes, how.stride, how.constants, run)


@_native_blend.defjvp
def _native_blend_jvp(how, primals, tangents):
    # The reference's derivative where it runs, zeros (constant outputs) where it does not.
    run = value(primals[4])
    out, tangent = jax.jvp(how.reference, primals[:4], tangents[:4])
    zero = lambda x: jnp.where(run, x, jnp.zeros_like(x))
    return jax.tree.map(zero, out), jax.tree.map(zero, tangent)


def step_norm(parts: tuple, given: jax.Array, flags: StepFlags, how: StepCall) -> jax.Array:
    """The postfilter step's mean texel norm at the sub-grid from its ``parts``, ``(m, v, B m,
    B v, lam, observed)`` (:func:`native.step_norm`: one FFI call, where XLA would compute the
    step at the sub-grid in a kernel of its own and the mean in a second call), its texels
    observed or not from the gradient as ``given`` (which gives ``observed``, the step's mask:
    XLA need not write the mask out for the call); its derivative is ``how.reference``'s, the
    rule's JAX form (``reference(*parts, flags)``). The native kernel only: the caller checks
    :func:`runs_native`."""
    return _native_step_norm(parts, given, flags, how)


@functools.partial(jax.custom_jvp, nondiff_argnums=(3,))
def _native_step_norm(parts, given, flags, how: StepCall):
    m, v, bm, bv, lam, _ = parts  # the mask read from the gradient
    return native.step_norm(m, v, bm, bv, given, lam, flags, how)


@_native_step_norm.defjvp
def _native_step_norm_jvp(how, primals, tangents):
    # The mask is piecewise constant in the gradient: no derivative through it.
    (parts, _, flags), (t_parts, _, t_flags) = primals, tangents
    return jax.jvp(lambda p, f: how.reference(*p, f), (parts, flags), (t_parts, t_flags))


def texel_norm(x: jax.Array, axes: tuple[int, ...]) -> jax.Array:
    """Each texel's norm over the axes of ``x`` that are not spatial (``axes``)."""
    channels = tuple(a for a in range(x.ndim) if a not in axes)
    return jnp.sqrt(jnp.sum(x * x, axis=channels)) if channels else jnp.abs(x)


def _nan_skipping_mean(x: jax.Array) -> jax.Array:
    """Mean over the entries that are not NaN; 0 if none."""
    ok = ~jnp.isnan(x)
    return jnp.sum(jnp.where(ok, x, 0)) / jnp.maximum(jnp.sum(ok), 1)


def every(x: jax.Array, axes: tuple[int, ...], s: int) -> jax.Array:
    """Every ``s``-th entry of ``x`` along its ``axes``."""
    if s == 1:
        return x
    # A strided lax.slice, not indexing: an eager init of a grid on an explicit mesh keeps it split.
    strides = tuple(s if a in axes else 1 for a in range(x.ndim))
    return lax.slice(x, (0,) * x.ndim, x.shape, strides)


def _taps_at_stride(x: jax.Array, axis: int, s: int) -> jax.Array:
    n = x.shape[axis]
    r = len(TAPS) - 1  # the taps' radius: h[d] for d = -r .. r
    kept = (n - 1) // s + 1
    total, norm = 0.0, np.zeros(kept)
    for k in range(2 * r + 1):
        w = TAPS[abs(k - r)]
        # The sub-grid's texels whose tap k falls on the grid: i in [lo, hi).
        lo = max(0, -(-(r - k) // s))
        hi = min(kept, (n - 1 - k + r) // s + 1)
        if hi <= lo:
            continue
        start = s * lo + k - r
        taps = lax.slice_in_dim(x, start, start + s * (hi - lo - 1) + 1, stride=s, axis=axis)
        # Padded after the slice: only the sub-grid's rows are copied.
        pad = [(0, 0)] * x.ndim
        pad[axis] = (lo, kept - hi)
        total = total + float(w) * jnp.pad(taps, pad)
        norm[lo:hi] += w
    shape = [1] * x.ndim
    shape[axis] = kept
    return total / jnp.asarray(norm.reshape(shape), x.dtype)


def sum_of_squares(x: jax.Array) -> jax.Array:
    """``sum(x^2)``: as a contraction over every axis on one device (XLA's CPU backend runs a
    dot several times faster than a fused elementwise reduction); a sum where ``x`` is split
    over an explicit mesh (a contraction of split axes needs its output sharding named)."""
    if sharded.is_split(x):
        return jnp.sum(x * x)
    return jnp.tensordot(x, x, axes=x.ndim)
