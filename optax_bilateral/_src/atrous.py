"""A-trous cross-bilateral filter (edge-avoiding B3-spline wavelet, as in SVGF).

One level of stride ``s`` computes, for every grid point ``p``,

    out[p] = sum_q w(p, q) x[q] / sum_q w(p, q),    q = p + s d,  d in {-2..2}^n
    w(p, q) = prod_k h[d_k] * exp(-||guide[p] - guide[q]|| / sigma_d)

with ``h = [1/16, 1/4, 3/8, 1/4, 1/16]``. Level ``i`` uses stride ``2**i`` and
filters the previous level's output; the guide stays fixed. Neighbours outside
the grid are skipped and the remaining weights renormalised.

Implementation notes (why it looks the way it does):

* Every pass works on a *planar* copy of the fields, ``(channels, *spatial)``:
  shifting along the fastest spatial axis then moves contiguous memory and the
  weights (spatial shape only) broadcast over the leading channel axis for free.
* The data term is symmetric, ``w(p, p + o) = w(p + o, p)``, so each pass
  computes one weight array per *pair* of opposite offsets, on the cropped
  region where both ends are inside the grid, and reuses it for ``+o`` and ``-o``
  by zero-padding it on either side. Zero padding is also what skips the
  out-of-grid neighbours.
* All fields (e.g. Adam's ``m`` and ``v``) are filtered by one call, so they get
  exactly the same weights: the bounded-step argument of supplement §1.3 needs
  ``m`` and ``v`` filtered by the *same* row-stochastic operator.
"""

from __future__ import annotations

import functools
import itertools
import math
import numbers
from typing import Sequence

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

# B3-spline taps h[d] for d = -2..2, indexed by |d|.
_H = (3.0 / 8.0, 1.0 / 4.0, 1.0 / 16.0)


def _is_concrete(x) -> bool:
    """True if ``x`` holds a known value now (not a tracer under jit/grad/vmap)."""
    if isinstance(x, jax.core.Tracer):
        return False
    try:
        np.asarray(x)
    except (jax.errors.TracerArrayConversionError, jax.errors.ConcretizationTypeError):
        return False
    return True


def check_sigma_d(sigma_d, name: str = "sigma_d") -> None:
    """Raises if a concrete ``sigma_d`` is negative, NaN or not a real scalar."""
    if isinstance(sigma_d, bool) or not (
        isinstance(sigma_d, numbers.Real) or hasattr(sigma_d, "dtype")
    ):
        raise TypeError(f"{name} must be a real scalar (float, inf allowed), got {sigma_d!r}")
    if hasattr(sigma_d, "shape") and np.shape(sigma_d) != ():
        raise ValueError(f"{name} must be a scalar, got an array of shape {np.shape(sigma_d)}")
    if hasattr(sigma_d, "dtype") and not jnp.issubdtype(sigma_d.dtype, jnp.number):
        raise TypeError(f"{name} must be a real number, got dtype {sigma_d.dtype}")
    if _is_concrete(sigma_d):
        value = float(np.asarray(sigma_d))
        if math.isnan(value) or value < 0:
            raise ValueError(f"{name} must be >= 0 (0 keeps only equal-guide neighbours, "
                             f"inf is a plain low-pass), got {value}")


def check_levels(levels, name: str = "levels") -> int:
    """Returns ``levels`` as a Python int, or raises a clear error."""
    if hasattr(levels, "shape") and not _is_concrete(levels):
        raise TypeError(
            f"{name} is static (it sets how many passes are compiled) but got a traced value. "
            "With optax.inject_hyperparams, pass static_args=('levels',).")
    if isinstance(levels, bool) or not isinstance(levels, (numbers.Integral, np.ndarray, jax.Array)):
        raise TypeError(f"{name} must be a non-negative int (the number of a-trous levels F), "
                        f"got {levels!r}")
    if hasattr(levels, "dtype") and (np.shape(levels) != () or not jnp.issubdtype(levels.dtype, jnp.integer)):
        raise TypeError(f"{name} must be a non-negative int scalar, got {levels!r}")
    levels = int(levels)
    if levels < 0:
        raise ValueError(f"{name} must be >= 0 (0 is the identity), got {levels}")
    return levels


def normalize_axes(spatial_axes, ndim: int, name: str = "spatial_axes") -> tuple[int, ...]:
    """Validates ``spatial_axes`` against an array of rank ``ndim``; returns non-negative axes."""
    if isinstance(spatial_axes, numbers.Integral) and not isinstance(spatial_axes, bool):
        spatial_axes = (spatial_axes,)
    if not isinstance(spatial_axes, (tuple, list)) or not all(
        isinstance(a, numbers.Integral) and not isinstance(a, bool) for a in spatial_axes
    ):
        raise TypeError(f"{name} must be a tuple of ints, got {spatial_axes!r}")
    out = []
    for a in spatial_axes:
        if not -ndim <= a < ndim:
            raise ValueError(f"{name}={tuple(spatial_axes)} is out of range for an array "
                             f"with {ndim} dimension(s)")
        out.append(int(a) % ndim)
    if len(set(out)) != len(out):
        raise ValueError(f"{name}={tuple(spatial_axes)} repeats an axis")
    return tuple(out)


def _weight(d2: jax.Array, sigma_d: jax.Array) -> jax.Array:
    """exp(-sqrt(d2) / sigma_d), with equal guides weighing 1 for every sigma_d.

    Written so that sigma_d = 0 (only equal guides), sigma_d = inf (all 1), an
    overflowing d2 and reverse-mode derivatives at d2 = 0 are all well defined.
    """
    pos = d2 > 0
    dist = jnp.sqrt(jnp.where(pos, d2, 1.0))
    s_pos = sigma_d > 0
    s_safe = jnp.where(s_pos, sigma_d, 1.0)
    w = jnp.exp(-dist / s_safe)
    w = jnp.where(s_pos, w, 0.0)                      # sigma_d = 0: unequal guides get 0
    w = jnp.where(jnp.isposinf(sigma_d), 1.0, w)      # inf/inf would be NaN
    w = jnp.where(pos, w, 1.0)                        # equal guides: 1 for any sigma_d
    return jnp.where(jnp.isnan(d2), 0.0, w)           # a non-finite guide is nobody's neighbour


def _crop(x: jax.Array, lo: Sequence[int], hi: Sequence[int], first_axis: int) -> jax.Array:
    """x[..., lo_k : n_k - hi_k, ...] over the trailing spatial axes."""
    starts = [0] * x.ndim
    limits = list(x.shape)
    for k, (a, b) in enumerate(zip(lo, hi)):
        starts[first_axis + k] = a
        limits[first_axis + k] = x.shape[first_axis + k] - b
    return lax.slice(x, starts, limits)


def _pad(x: jax.Array, lo: Sequence[int], hi: Sequence[int], first_axis: int) -> jax.Array:
    cfg = [(0, 0, 0)] * x.ndim
    for k, (a, b) in enumerate(zip(lo, hi)):
        cfg[first_axis + k] = (a, b, 0)
    return lax.pad(x, jnp.zeros((), x.dtype), cfg)


def _channel_sq_dist(a: jax.Array, b: jax.Array) -> jax.Array:
    """sum_c (a[c] - b[c])**2 over the leading axis."""
    if a.shape[0] <= 16:
        # Unrolled: XLA's CPU reduce over a short leading axis is ~40x slower than adds.
        return sum(jnp.square(a[c] - b[c]) for c in range(a.shape[0]))
    return jnp.sum(jnp.square(a - b), axis=0)


def _flat_offset(off: Sequence[int], shape: Sequence[int]) -> int:
    """Offset of ``off`` in the row-major flattening of ``shape``."""
    return sum(o * math.prod(shape[k + 1:]) for k, o in enumerate(off))


def _inner_in_grid(off, shape, first_row: int, rows: int):
    """For rows ``first_row .. first_row + rows`` of the grid (outer axis may run off
    it), whether ``p + off`` stays inside along every *inner* axis, or None if it
    always does. (Along the outer axis the zero halo takes care of it.)"""
    full = (rows,) + tuple(shape[1:])
    ok = None
    for k in range(1, len(shape)):
        if off[k] == 0:
            continue
        i = lax.broadcasted_iota(jnp.int32, full, k) + off[k]
        t = (i >= 0) & (i < shape[k])
        ok = t if ok is None else ok & t
    return ok


def _rows_in_grid(shape, first_row: int, rows: int, off0: int = 0):
    full = (rows,) + tuple(shape[1:])
    i = lax.broadcasted_iota(jnp.int32, full, 0) + (first_row + off0)
    return (i >= 0) & (i < shape[0])


def _flat_window(a: jax.Array, start: int, rows: int) -> jax.Array:
    """Rows ``rows`` of the planar array ``a`` (C, R, *inner) read from flat position
    ``start`` of each channel plane: a contiguous slice, whatever the offset."""
    c, inner = a.shape[0], a.shape[2:]
    n = rows * math.prod(inner)
    flat = a.reshape(c, -1)
    return lax.slice(flat, (0, start), (c, start + n)).reshape((c, rows) + tuple(inner))


def _zero_halo(xpad, halo, first_axis):
    """``xpad`` with its (already zero) halo zeroed again by an index test.

    A no-op in value. It stops XLA's simplifier from rewriting the centre tap,
    ``xpad[halo:-halo]``, back into the previous pass's output: that would give the
    previous pass two consumers, and XLA's fusion would then recompute it inside
    both (work doubling with every pass).
    """
    inside = None
    for k, h in enumerate(halo):
        if h == 0:
            continue
        i = lax.broadcasted_iota(jnp.int32, xpad.shape, first_axis + k)
        ok = (i >= h) & (i < xpad.shape[first_axis + k] - h)
        inside = ok if inside is None else inside & ok
    return xpad if inside is None else jnp.where(inside, xpad, 0)


def _after(x: jax.Array) -> jax.Array:
    """An exact 0.0 that XLA cannot see is 0 and that depends on ``x``.

    Added to sigma_d, it makes a pass's weights wait for the previous pass. Without
    it XLA schedules every level's weights first (they depend on the guide only) and
    keeps them all alive: tens of MB of temporaries, which glibc then maps and
    page-faults afresh on every call (measured 4-8x slower on 64^3, F >= 4).
    """
    # A reduction, so XLA computes the probe once instead of fusing it into (and
    # re-evaluating it for every element of) the weight computation.
    corner = lax.slice(x, (0,) * x.ndim, (1,) * (x.ndim - 1) + (min(2, x.shape[-1]),))
    probe = lax.stop_gradient(jnp.max(corner))
    return jnp.where(probe > jnp.inf, 1.0, 0.0).astype(x.dtype)


def _pass(x, guide, valid, sigma_d, offsets_and_taps, h0):
    """One normalised bilateral pass over planar arrays.

    x: (C, *S) fields (zero where invalid); guide: (G, *S); valid: (*S) float 0/1 or
    None; offsets_and_taps: [(offset vector, tap)] for one of each pair +o / -o.

    Every array is padded along the *outer* spatial axis only, by ``r`` rows, and
    every neighbour is read as a contiguous slice of the flattened plane at the
    offset's flat position. A read that runs off an inner axis wraps into the next
    row; the weights (and, for the fields, an index test) zero it. Padding the outer
    axis costs whole rows, so XLA's CPU loops stay vectorised; padding the fastest
    axis instead puts a bounds test on every element and measured 2-4x slower.
    """
    shape = x.shape[1:]
    n0 = shape[0]
    row = math.prod(shape[1:])
    flats = [_flat_offset(off, shape) for off, _ in offsets_and_taps]
    r = max(-(-abs(f) // row) for f in flats)       # halo rows: ceil(|flat offset| / row)

    # Weights: E_o[p] = tap * w(p, p + o), for p over rows -r .. n0 + r (zero when
    # p or p + o is off the grid or invalid). Then w(p, p+o) = E_o[p] and
    # w(p, p-o) = w(p-o, p) = E_o[p - o]: one exp per pair, two plain slices.
    gpad = _pad(guide, [2 * r], [2 * r], 1)
    vpad = None if valid is None else _pad(valid[None], [2 * r], [2 * r], 1)
    weights = []
    for (off, tap), f in zip(offsets_and_taps, flats):
        rows = n0 + 2 * r
        g_p = _flat_window(gpad, r * row, rows)
        g_q = _flat_window(gpad, r * row + f, rows)
        w = tap * _weight(_channel_sq_dist(g_p, g_q), sigma_d)
        ok = _rows_in_grid(shape, -r, rows) & _rows_in_grid(shape, -r, rows, off[0])
        inner = _inner_in_grid(off, shape, -r, rows)
        if inner is not None:
            ok = ok & inner
        if vpad is not None:
            w = w * _flat_window(vpad, r * row, rows)[0] * _flat_window(vpad, r * row + f, rows)[0]
        weights.append(jnp.where(ok, w, 0.0))

    xpad = _pad(x, [r], [r], 1)
    xpad = _zero_halo(xpad, [r], 1)
    num = h0 * _flat_window(xpad, r * row, n0)
    den = h0 if valid is None else h0 * valid
    for (off, _), f, e in zip(offsets_and_taps, flats, weights):
        e = e[None]
        w_plus = _flat_window(e, r * row, n0)[0]
        w_minus = _flat_window(e, r * row - f, n0)[0]
        x_plus = _flat_window(xpad, r * row + f, n0)
        x_minus = _flat_window(xpad, r * row - f, n0)
        # A wrapped read has weight 0; the index test keeps a non-finite value
        # from the neighbouring row out of the sum (0 * inf), as zero padding would.
        ok_plus = _inner_in_grid(off, shape, 0, n0)
        if ok_plus is not None:
            ok_minus = _inner_in_grid([-o for o in off], shape, 0, n0)
            x_plus = jnp.where(ok_plus, x_plus, 0.0)
            x_minus = jnp.where(ok_minus, x_minus, 0.0)
        num = num + w_plus * x_plus + w_minus * x_minus
        den = den + w_plus + w_minus
    if valid is None:
        return num / den
    return jnp.where(den > 0, num / jnp.where(den > 0, den, 1.0), 0.0)


def _level_passes(shape: Sequence[int], stride: int, separable: bool):
    """Static list of passes for one level: each a list of (offset, tap) pairs, and h0."""
    n = len(shape)
    if separable:
        passes = []
        for k in range(n):
            pairs = []
            for d in (1, 2):
                if d * stride < shape[k]:                 # farther taps are all out of grid
                    off = [0] * n
                    off[k] = d * stride
                    pairs.append((tuple(off), _H[d]))
            if pairs:
                passes.append((pairs, _H[0]))
        return passes
    pairs = []
    for d in itertools.product(range(-2, 3), repeat=n):
        nz = [c for c in d if c != 0]
        if not nz or nz[0] < 0:                            # keep one of each +d / -d
            continue
        if any(abs(c) * stride >= s for c, s in zip(d, shape)):
            continue
        pairs.append((tuple(c * stride for c in d), math.prod(_H[abs(c)] for c in d)))
    return [(pairs, _H[0] ** n)] if pairs else []


def atrous_bilateral(fields, guide, *, sigma_d, levels, spatial_axes, separable=True,
                     mask=None, guide_axes=None):
    """A-trous cross-bilateral filter of one or more fields with one set of weights.

    ``out = B_{F-1} ... B_1 B_0 x``, where level ``i`` (stride ``2**i``) is

    .. math::
        (B_i x)[p] = \\frac{\\sum_q w_i(p,q)\\, x[q]}{\\sum_q w_i(p,q)}, \\quad
        w_i(p,q) = \\prod_k h[d_k]\\; e^{-\\lVert \\gamma[p]-\\gamma[q] \\rVert_2/\\sigma_d},
        \\quad q = p + 2^i d,\\ d \\in \\{-2..2\\}^n

    with B3-spline taps ``h = [1/16, 1/4, 3/8, 1/4, 1/16]`` (METHOD.md; supplement
    eqs. 1, 6, 8). Each ``B_i`` is non-negative and row-stochastic.

    Args:
      fields: an array, or a tuple of arrays, with the same sizes along
        ``spatial_axes``. All are filtered with the same weights (computed once per
        pass), so Adam's ``m`` and ``v`` never get different operators.
      guide: the edge-stopping image ``gamma``. Either an array with exactly the
        spatial axes (its shape is the spatial shape), or an array whose axes
        ``guide_axes`` (default: ``spatial_axes``) have the fields' spatial sizes;
        the distance is the L2 norm over its remaining (channel) axes.
      sigma_d: the data term's scale (>= 0). ``0`` keeps only neighbours with an
        equal guide; ``inf`` is a plain B-spline low-pass. May be traced.
      levels: F, the number of a-trous levels (static int >= 0); ``0`` is the
        identity. The footprint radius is ``2 (2**F - 1)``.
      spatial_axes: the fields' spatial axes (any number, in pass order); the
        other axes are channels that share the weights.
      separable: if True, each level is one normalised 1-D pass of 5 taps per
        spatial axis in the order given (cost 5n per level); if False, all 5**n
        taps at once (the authors' kernels). The two differ across diagonal edges.
      mask: optional boolean array of the spatial shape; False entries are left
        out of every sum (neither read nor written: their output is 0).
      guide_axes: the guide's spatial axes, when it has channels and they differ
        from ``spatial_axes``.

    Returns:
      The filtered fields, with the structure and dtypes of ``fields``. Sums are
      accumulated in at least float32.
    """
    levels = check_levels(levels)
    check_sigma_d(sigma_d)
    if isinstance(spatial_axes, list):
        spatial_axes = tuple(spatial_axes)
    if isinstance(guide_axes, list):
        guide_axes = tuple(guide_axes)
    if levels == 0 and mask is None:
        return fields                                   # the identity, without a copy
    return _atrous_jit(fields, guide, sigma_d, mask, levels=levels, spatial_axes=spatial_axes,
                       separable=bool(separable), guide_axes=guide_axes)


@functools.partial(jax.jit, static_argnames=("levels", "spatial_axes", "separable", "guide_axes"))
def _atrous_jit(fields, guide, sigma_d, mask, *, levels, spatial_axes, separable, guide_axes):
    """One compiled program per (shapes, dtypes, static settings); sigma_d stays traced."""
    single = not isinstance(fields, (tuple, list))
    fields = (fields,) if single else tuple(fields)
    if not fields:
        raise ValueError("fields must be an array or a non-empty tuple of arrays")
    fields = tuple(jnp.asarray(f) for f in fields)
    levels = check_levels(levels)
    check_sigma_d(sigma_d)
    for i, f in enumerate(fields):
        if not jnp.issubdtype(f.dtype, jnp.inexact):
            raise TypeError(f"fields[{i}] must have a floating dtype, got {f.dtype}")
    axes0 = normalize_axes(spatial_axes, fields[0].ndim)
    if not axes0:
        raise ValueError("spatial_axes must name at least one axis")
    spatial_shape = tuple(fields[0].shape[a] for a in axes0)
    per_field_axes = []
    for i, f in enumerate(fields):
        axes = normalize_axes(spatial_axes, f.ndim, name=f"spatial_axes (for fields[{i}])")
        shp = tuple(f.shape[a] for a in axes)
        if shp != spatial_shape:
            raise ValueError(f"fields[{i}] has spatial shape {shp} along {tuple(spatial_axes)}, "
                             f"but fields[0] has {spatial_shape}")
        per_field_axes.append(axes)

    guide = jnp.asarray(guide)
    if guide.ndim == len(axes0) and guide_axes is None:
        g_axes = tuple(range(guide.ndim))
    else:
        g_axes = normalize_axes(spatial_axes if guide_axes is None else guide_axes, guide.ndim,
                                name="guide_axes" if guide_axes is not None else
                                "spatial_axes (applied to the guide)")
    g_shape = tuple(guide.shape[a] for a in g_axes)
    if g_shape != spatial_shape:
        raise ValueError(f"guide has spatial shape {g_shape} but the fields have {spatial_shape}: "
                         "the guide must cover the same grid")
    if mask is not None:
        mask = jnp.asarray(mask)
        if mask.shape != spatial_shape:
            raise ValueError(f"mask must have the spatial shape {spatial_shape}, got {mask.shape}")

    compute = jnp.promote_types(jnp.result_type(*fields), jnp.float32)
    if levels == 0:
        if mask is None:
            return fields[0] if single else fields
        out = tuple(jnp.where(_expand(mask, f.ndim, ax), f, 0).astype(f.dtype)
                    for f, ax in zip(fields, per_field_axes))
        return out[0] if single else out

    # Planar layout: (channels, *spatial) with all fields stacked along channels.
    planes, restore = [], []
    for f, axes in zip(fields, per_field_axes):
        chan = tuple(a for a in range(f.ndim) if a not in axes)
        p = jnp.transpose(f, chan + axes).astype(compute)
        cshape = tuple(f.shape[a] for a in chan)
        planes.append(p.reshape((-1,) + spatial_shape))
        restore.append((f.dtype, chan + axes, cshape))
    x = jnp.concatenate(planes, axis=0) if len(planes) > 1 else planes[0]
    g_chan = tuple(a for a in range(guide.ndim) if a not in g_axes)
    g = jnp.transpose(guide, g_chan + g_axes).astype(compute)
    g = g.reshape((-1,) + spatial_shape)
    sigma = jnp.asarray(sigma_d, dtype=g.dtype)

    valid = None
    if mask is not None:
        valid = mask.astype(compute)
        x = jnp.where(mask, x, 0)                       # also drops NaN/Inf at masked entries

    for i in range(levels):
        for pairs, h0 in _level_passes(spatial_shape, 2 ** i, separable):
            x = _pass(x, g, valid, sigma + _after(x), pairs, h0)
    if valid is not None:
        x = jnp.where(mask, x, 0)

    outs, start = [], 0
    for (dtype, perm, cshape) in restore:
        c = math.prod(cshape)
        piece = x[start:start + c].reshape(cshape + spatial_shape)
        start += c
        outs.append(jnp.transpose(piece, np.argsort(perm)).astype(dtype))
    return outs[0] if single else tuple(outs)


def _expand(mask, ndim, axes):
    """Broadcasts a spatial-shape mask against an array whose spatial axes are ``axes``."""
    shape = [1] * ndim
    order = np.argsort(axes)
    m = jnp.transpose(mask, order) if len(axes) > 1 else mask
    for k, a in enumerate(sorted(axes)):
        shape[a] = m.shape[k]
    return m.reshape(shape)
