"""A-trous cross-bilateral filter (edge-avoiding B3-spline wavelet, as in SVGF).

One level of stride ``s`` computes, for every grid point ``p``,

    out[p] = sum_q w(p, q) x[q] / sum_q w(p, q),    q = p + s d,  d in {-2..2}^n
    w(p, q) = prod_k h[d_k] * exp(-||guide[p] - guide[q]|| / sigma_d)

with ``h = [1/16, 1/4, 3/8, 1/4, 1/16]``. Level ``i`` uses stride ``2**i`` and
filters the previous level's output; the guide stays fixed. Neighbours outside
the grid are skipped and the remaining weights renormalised.

Implementation notes (why it looks the way it does; the numbers are in
BENCHMARKS.md). XLA's CPU backend decides what gets fused and vectorised, so most
of the choices below exist to steer it:

* Every pass works on a *planar* copy of the fields, ``(channels, *spatial)``,
  padded with zero rows along the *outer* spatial axis only. Every neighbour
  ``p + o`` is then one contiguous slice of the flattened plane, at the offset's
  flat position; a read that runs off an inner axis wraps into the next row, where
  its weight is 0 (and an index test zeroes the value, so 0 * inf cannot leak in).
  Padding the fastest axis instead puts a bounds test on every element and
  stops vectorisation.
* Every kernel computes in a 2-level shape, (rows * n1 * ... * n_{d-2}, n_{d-1})
  (``_view``): XLA's CPU loops turned a flat read of a 3-level operand into a urem by
  the plane size per element, vectorised only for power-of-two planes (3-D grids
  with other sides were 2-3x slower per element).
* The data term is symmetric, ``w(p, p + o) = w(p + o, p)``: one exp per *pair* of
  opposite offsets gives both taps, and offset ``2d * 2**i`` at level ``i`` equals
  offset ``d * 2**(i+1)`` at level ``i+1``, so those weights are computed once
  (separable mode; full mode recomputes them to keep its temporaries small).
* The weights are decided inside the exponent (``exp`` is the last operation), so
  XLA materialises them once instead of re-deriving them in every consumer.
* Full mode on grids whose outer stride is a power of two (64^3, 512^2) appends one
  zero column to the fastest axis (``_pitch``): the many streams of a full pass then
  stop mapping to the same cache sets (0.88x the time at 64^3, 0.90-0.94x at 512^2x3).
* A few exact no-ops (``_after``, ``_opaque_one``) steer XLA's scheduler and
  fusion: each pass's weights wait for the previous pass (otherwise every level's
  weights are computed up front and tens of MB stay alive), and each pass is
  materialised rather than fused into the next pass's padding.
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


def _weight(d2: jax.Array, sigma_d: jax.Array, keep=None, *, is_dist: bool = False) -> jax.Array:
    """exp(-sqrt(d2) / sigma_d), with equal guides weighing 1 for every sigma_d.

    With ``is_dist``, ``d2`` already is the distance (one guide channel: ``|a - b|``).

    Written so that sigma_d = 0 (only equal guides), sigma_d = inf (all 1), an
    overflowing d2 and reverse-mode derivatives at d2 = 0 are all well defined.
    ``keep`` (bool, optional) zeroes the weight where False. Every case is decided
    in the exponent, so the exp is the last operation: XLA then materialises the
    weights once instead of re-deriving the cheap selects (and the guide distance
    they need) inside every consumer.
    """
    pos = d2 > 0
    dist = jnp.where(pos, d2, 1.0) if is_dist else jnp.sqrt(jnp.where(pos, d2, 1.0))
    s_pos = sigma_d > 0
    s_safe = jnp.where(s_pos, sigma_d, 1.0)
    arg = dist * (-1.0 / s_safe)                          # one scalar divide, not one per element
    arg = jnp.where(s_pos, arg, -jnp.inf)                 # sigma_d = 0: unequal guides get 0
    arg = jnp.where(jnp.isposinf(sigma_d), 0.0, arg)      # inf/inf would be NaN
    arg = jnp.where(pos, arg, 0.0)                        # equal guides: 1 for any sigma_d
    drop = jnp.isnan(d2)                                  # a non-finite guide is nobody's neighbour
    if keep is not None:
        drop = drop | ~keep
    return jnp.exp(jnp.where(drop, -jnp.inf, arg))


def rescale_guide(g: jax.Array, sigma: jax.Array):
    """(g / s, sigma / s) with ``s`` a power of two that keeps squared guide distances finite.

    The weight depends on ``|g_p - g_q| / sigma`` only, so scaling both by ``s`` changes
    nothing but rounding; ``s = 1`` (an exact no-op) unless the largest finite ``|g|``
    exceeds ``2^(maxexp/2 - 8)`` (``2^56`` in float32), where the squared distance
    ``sum_c (g_p - g_q)^2`` of up to 4096 channels would otherwise overflow to inf and
    weigh such neighbours 0 at any ``sigma``. Powers of two scale exactly (tiny guide
    values may underflow, a difference far below the large ones' float resolution).
    """
    if not jnp.issubdtype(g.dtype, jnp.floating) or g.size == 0:
        return g, sigma
    limit = jnp.finfo(g.dtype).maxexp // 2 - 8
    a = jnp.abs(g)
    m = lax.stop_gradient(jnp.max(jnp.where(jnp.isfinite(a), a, 0)))
    _, e = jnp.frexp(m)                                   # m < 2^e
    k = jnp.maximum(e - limit, 0)
    inv = jnp.ldexp(jnp.ones((), g.dtype), -k)
    return g * inv, sigma * inv.astype(sigma.dtype)


def _channel_sq_dist(a: jax.Array, b: jax.Array) -> jax.Array:
    """sum_c (a[c] - b[c])**2 over the leading axis."""
    if a.shape[0] <= 16:
        # Unrolled: XLA's CPU reduce over a short leading axis is ~40x slower than adds.
        return sum(jnp.square(a[c] - b[c]) for c in range(a.shape[0]))
    return jnp.sum(jnp.square(a - b), axis=0)


def _pad_rows(x: jax.Array, lo: int, hi: int, shape: Sequence[int]) -> jax.Array:
    """Zero-pads the planar array ``x`` (C, *shape), or (C, *_view(shape, n0)), by
    ``lo`` / ``hi`` rows along its outer spatial axis; returns it in ``_view``'s shape,
    (C, (lo + n0 + hi) * m, n_last). In that shape the padded array is a 2-level operand
    for ``_window``'s flat reads (see ``_view``), and the pad (along axis 1) stays a
    plain pad kernel: padding the flattened (C, L) array instead compiled to a generic
    loop measured 3x slower than the pad itself (128^3: 9 ms vs 3 ms per pad)."""
    per_row = _view(shape, 1)
    x = x.reshape((x.shape[0], -1) + per_row[1:])
    cfg = [(0, 0, 0)] * x.ndim
    cfg[1] = (lo * per_row[0], hi * per_row[0], 0)
    return lax.pad(x, jnp.zeros((), x.dtype), cfg)


def _view(shape: Sequence[int], rows: int) -> tuple[int, ...]:
    """The shape in which ``rows`` rows of a grid of ``shape`` are computed: every axis
    but the fastest collapsed into one, (rows * n1 * ... * n_{d-2}, n_{d-1}).

    XLA's CPU emitter loops over a kernel's output shape and, for every flat read,
    delinearises the flat index into the operand's shape and linearises it back. LLVM
    folds that round trip for a 2-level shape (row, column); for 3 levels it folded
    only the inner pair and left a urem by the plane size n1 * n2 per element, which
    is a mask (vectorised) for a power-of-two plane and a real urem (not vectorised)
    otherwise. Measured, 3-D, F=5 filter: 48^3 87 ns/element vs 21 at 64^3, 96^3 69
    vs 42 at 128^3 (the "non-power-of-two cliff"); 2-D grids never showed it. The
    other axes' coordinates are then functions of the collapsed row index only (see
    ``_coord``), computed once per row of the loop."""
    shape = tuple(shape)
    if len(shape) < 2:
        return (rows,)
    return (rows * math.prod(shape[1:-1]), shape[-1])


def _coord(shape: Sequence[int], rows: int, k: int) -> jax.Array:
    """The coordinate along axis ``k`` of every point of ``rows`` rows, in ``_view``'s
    shape (for k = 0: the row index within the window)."""
    shape = tuple(shape)
    view = _view(shape, rows)
    if len(shape) >= 2 and k == len(shape) - 1:
        return lax.broadcasted_iota(jnp.int32, view, 1)
    r = lax.broadcasted_iota(jnp.int32, view, 0)
    r = r // math.prod(shape[k + 1:-1]) if k + 1 < len(shape) - 1 else r
    return r if k == 0 else r % shape[k]


def _window(a: jax.Array, start: int, rows: int, shape: Sequence[int]) -> jax.Array:
    """``rows`` rows of a grid of ``shape``, in ``_view``'s shape, read from flat position
    ``start`` of each channel of ``a`` (C, ...), e.g. from ``_pad_rows``: one contiguous
    slice, whatever the offset."""
    c = a.shape[0]
    n = rows * math.prod(shape[1:])
    flat = a.reshape(c, -1)
    return lax.slice(flat, (0, start), (c, start + n)).reshape((c,) + _view(shape, rows))


def _inner_ok(off: Sequence[int], grid: "_Grid", rows: int):
    """Whether ``p + off`` stays on the grid along every inner axis (for ``rows`` rows of
    ``p``, in ``_view``'s shape), or None if no inner component is non-zero. A flat
    read that runs off an inner axis lands in the neighbouring row instead; this is
    what rejects it."""
    ok = None
    for k in range(1, len(grid.shape)):
        if off[k]:
            i = _coord(grid.shape, rows, k) + off[k]
            t = (i >= 0) & (i < grid.bounds[k])
            ok = t if ok is None else ok & t
    return ok


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


class _Grid:
    """Static geometry of the planar arrays, (C, n0, *inner), and their flat offsets."""

    def __init__(self, shape: Sequence[int], last: int | None = None):
        self.shape = tuple(shape)
        # The grid's own sizes: the layout's, but without _pitch's columns.
        self.bounds = self.shape if last is None else self.shape[:-1] + (last,)
        self.padded = self.bounds != self.shape
        self.n0 = shape[0]
        self.row = math.prod(shape[1:])

    def flat(self, off: Sequence[int]) -> int:
        # > 0 for every offset used (first non-zero component positive, |o_k| < n_k).
        return sum(o * math.prod(self.shape[k + 1:]) for k, o in enumerate(off))

    def halo(self, off: Sequence[int]) -> int:
        return -(-self.flat(off) // self.row)          # rows spanned: ceil(flat / row)


def _pair_weights(grid: _Grid, gpad, vpad, lead: int, sigma_d, off, h: int):
    """E[p] = w(p, p + off) for p over rows -h .. n0 (h >= grid.halo(off)), zero where
    p or p + off is off the grid or invalid.

    w(p, p + off) = E[p] and w(p, p - off) = w(p - off, p) = E[p - off] are then both
    plain flat slices of E: one exp per pair of opposite taps. ``gpad``/``vpad`` are the
    guide and validity with ``lead`` zero rows on both sides. E is computed
    over its whole range (the rows that are off the grid get exp(-inf) = 0) rather than
    on the valid rows and then padded: a padded result makes XLA's CPU loop index the
    flat reads non-linearly, which measured ~3x slower.
    """
    f = grid.flat(off)
    rows = grid.n0 + h
    start = (lead - h) * grid.row
    a, b = _window(gpad, start, rows, grid.shape), _window(gpad, start + f, rows, grid.shape)
    one = a.shape[0] == 1
    if one:
        # One guide channel: the distance itself, |a - b|, no square and no sqrt. Halved
        # (and sigma_d with it: exact for normal floats, so the weights are unchanged), it
        # cannot overflow even for guides at +-float max, so such guides need no rescaling
        # (without rescale_guide's reduction: 512^2 update 0.98x, experiments.ab_update).
        d2 = jnp.abs(a[0] * 0.5 - b[0] * 0.5)
        sigma_d = sigma_d * 0.5
    else:
        d2 = _channel_sq_dist(a, b)
    i = _coord(grid.shape, rows, 0) - h
    keep = (i >= 0) & (i < grid.n0 - off[0])             # p and p + off both on the grid
    inner = _inner_ok(off, grid, rows)
    if inner is not None:
        keep = keep & inner
    if grid.padded:                                      # p itself in a pitch column
        keep = keep & (_coord(grid.shape, rows, len(grid.shape) - 1) < grid.bounds[-1])
    if vpad is not None:
        keep = (keep & (_window(vpad, start, rows, grid.shape)[0] > 0)
                & (_window(vpad, start + f, rows, grid.shape)[0] > 0))
    return _weight(d2, sigma_d, keep, is_dist=one).reshape(1, -1)    # (1, L): read by _window only


def _opaque_one(a: jax.Array) -> jax.Array:
    """Exactly 1.0 for every element (NaN included), in a form XLA does not fold."""
    return 1.0 + (a != a).astype(a.dtype) * 0.0


def _pass(grid: _Grid, x, pairs, h0, valid, weights, parts=None):
    """One normalised bilateral pass over planar arrays.

    x: (C, *view) fields, view = _view(S, n0) (zero where invalid); pairs: [(offset,
    tap)] for one of each pair +o / -o; valid: (*view) float 0/1 or None; weights(off, dep): E from
    ``_pair_weights``, where ``dep`` (an exact 0.0) ties its computation to a point in
    the pass (see ``_after``), so only a chunk's weights are alive at a time; parts:
    lengths of consecutive runs of ``pairs`` that no chunk may cross (default: one run).

    The fields are padded along the outer spatial axis only (whole rows, so XLA's CPU
    loops stay vectorised; a pad along the fastest axis puts a bounds test on every
    element and measured 2-4x slower) and every neighbour is a contiguous flat slice.
    """
    n0, row = grid.n0, grid.row
    r = max(grid.halo(off) for off, _ in pairs)
    xpad = _pad_rows(x, r, r, grid.shape)
    read = functools.partial(_window, rows=n0, shape=grid.shape)
    centre = read(xpad, r * row)
    num = h0 * centre
    den = h0 if valid is None else h0 * valid
    # Reads that wrap across an inner axis have weight 0, but 0 * inf is NaN: zero
    # them, as zero padding would. The test depends on the inner offset only, so the
    # products are summed per inner offset and each sum is masked once.
    groups = {}

    def flush(num):
        for inner, part in groups.items():
            ok = _inner_ok((0,) + inner, grid, n0)
            num = num + (part if ok is None else jnp.where(ok, part, 0.0))
        groups.clear()
        return num

    dep = _after(x)
    # Chunks of at most _CHUNK pairs, none across the ends of ``parts``.
    starts, a = [], 0
    for length in (parts or [len(pairs)]):
        starts += range(a, a + length, _CHUNK)
        a += length
    stops = dict(zip(starts, starts[1:] + [len(pairs)]))
    ends = {b - 1 for b in stops.values()}
    for k, (off, tap) in enumerate(pairs):
        if k in stops:
            chunk = weights([o for o, _ in pairs[k:stops[k]]], dep)
        e, h = chunk[off]
        f = grid.flat(off)
        w_plus = tap * read(e, h * row)[0]
        w_minus = tap * read(e, h * row - f)[0]
        for inner, term in ((tuple(off[1:]), w_plus * read(xpad, r * row + f)),
                            (tuple(-o for o in off[1:]), w_minus * read(xpad, r * row - f))):
            groups[inner] = term if inner not in groups else groups[inner] + term
        den = den + w_plus + w_minus
        if k in ends and k + 1 < len(pairs):
            # Full mode has up to 62 pairs per pass; one XLA loop over all of them stops
            # vectorising (measured 0.12 ms per pair in chunks of 6, 0.36 ms in one
            # loop of 62). Materialise the running sums every _CHUNK pairs.
            num = flush(num)
            # The normaliser goes first: XLA's CPU backend splits this kernel over 2
            # threads along the leading axis, and den (cheap: no field reads) last made
            # the halves uneven (3-D, 2 fields: profiled 713 vs 521 us per chunk; den
            # first: equal halves). The barrier materialises y (one buffer, read by the
            # next chunk and the _after probe); the y / _opaque_one(y) root used before
            # compiled to an extra kernel copying all C + 1 planes at every boundary.
            # Together, filter only, full F=5 under load: 2-D -6%, 3-D +-0 (the update
            # ratios on the shared machine moved within their +-5-20% noise).
            # Tried, no gain or worse: _CHUNK 3/4/8/10/12 (4 ~ 6, larger slower); planar
            # layout (n0, C, *inner) (balanced split, weights read once per row for all
            # channels: filter +-0, update 1.3-1.5x slower in 2-D); exps on only the
            # rows where E can be non-zero, written into a zero array (a fused pad still
            # computes every exp; an in-place dynamic-update-slice: 3-D F=5 +15%).
            y = jnp.concatenate([jnp.broadcast_to(den, num.shape[1:])[None], num])
            y = lax.optimization_barrier(y)
            dep = _after(y)
            num, den = y[1:], y[0] + dep
    num = flush(num)
    # Divide by a full-shape divisor: XLA then keeps a real divide (it rewrites
    # x / broadcast(d) into x * broadcast(1 / d)), counts the pass as expensive and,
    # with the next pass's _after probe as a second consumer, materialises it rather
    # than fusing it into the next pass's padding, whose index arithmetic made the
    # flat reads ~3x slower.
    den = den * _opaque_one(centre)
    if valid is None:
        return num / den
    return jnp.where(den > 0, num / jnp.where(den > 0, den, 1.0), 0.0)


_CHUNK = 6


def _filter_planar(x, g, valid, sigma, levels: int, separable: bool):
    """All levels on planar arrays: x (C, *S) or (C, *_view(S, n0)) zero where invalid,
    g (G, *S). Returns (C, *S)."""
    shape = g.shape[1:]
    pitch = _pitch(shape, separable, g.dtype.itemsize)
    if pitch:
        # Extra zero columns (off the grid for every weight), see _pitch.
        g = jnp.pad(g, [(0, 0)] * (g.ndim - 1) + [(0, pitch)])
        x = jnp.pad(x.reshape(x.shape[0], -1, shape[-1]), ((0, 0), (0, 0), (0, pitch)))
        if valid is not None:
            valid = jnp.pad(valid.reshape(-1, shape[-1]), ((0, 0), (0, pitch)))
    grid = _Grid(g.shape[1:], last=shape[-1])
    lead = max([grid.halo(off) for i in range(levels)
                for pairs, _ in _level_passes(shape, 2 ** i, separable)
                for off, _ in pairs] or [0])
    # Zero rows in front for the weights' halo, and behind for the reads p + off.
    gpad = _pad_rows(g, lead, lead, grid.shape)
    vpad = None if valid is None else _pad_rows(valid[None], lead, lead, grid.shape)
    # Every kernel works in _view's shape (the fastest axis, and all others collapsed).
    view = _view(grid.shape, grid.n0)
    x = x.reshape(x.shape[:1] + view)
    valid = None if valid is None else valid.reshape(view)
    cache = {}

    def weights(offs, dep):
        """{off: (E, h)} for a chunk of offsets. Offset 2d * 2**i at level i is offset
        d * 2**(i+1) at level i+1: the same weights up to the tap, computed once
        (full mode: see _handover_order). The
        new ones are computed as one stacked array (one XLA kernel: compiling a kernel
        per pair made a full-mode 3-D filter take minutes to compile)."""
        new = [o for o in offs if o not in cache]
        if new:
            h = max(grid.halo(o) for o in new)
            stack = jnp.concatenate([_pair_weights(grid, gpad, vpad, lead, sigma + dep, o, h)
                                     for o in new])
            for j, o in enumerate(new):
                cache[o] = (stack[j:j + 1], h)
        return {o: cache[o] for o in offs}

    for i in range(levels):
        for pairs, h0 in _level_passes(shape, 2 ** i, separable):
            parts = None
            if not separable and len(grid.shape) >= 3:
                pairs, parts = _handover_order(pairs, 2 ** i, i > 0, i + 1 < levels)
            elif not separable:
                cache.clear()        # 2-D full mode recomputes them (see _handover_order)
            x = _pass(grid, x, pairs, h0, valid, weights, parts)
    x = x.reshape(x.shape[:1] + grid.shape)
    return x[..., :shape[-1]] if pitch else x


def _pitch(shape: Sequence[int], separable: bool, itemsize: int = 4) -> int:
    """Zero columns appended to the fastest axis in full mode: 1 where the grid's outer
    stride (one step along axis 0, ``prod(shape[1:])`` elements) is a power of two of
    at least 2 KiB, else 0.

    A full pass's chunk kernel reads ~25 (2-D) to ~37 (3-D) streams at once, at flat
    offsets ``s d``. With power-of-two strides the streams that differ in their outer
    component are a multiple of 4 KiB apart (at 64^3, also those along axis 1 at stride
    16): they map to the same sets of the L1 cache, most likely what makes those grids
    slower per element than their neighbours in size. One extra column takes the strides
    off the powers of two (64^3: 16640 bytes instead of 16384); its points are off the
    grid for every weight (``_Grid.bounds``), and it is sliced off at the end.
    Measured (``experiments.ab_update --full``, paired new/old; BENCHMARKS.md, attempts):
    64^3 F = 3 and 5 0.88-0.90x, 512^2x3 F = 5 0.90-0.94x, 1024^2 F = 3 0.82-0.83x,
    32^3 F = 3 0.85-1.14x, 128^3 F = 3 1.01-1.03x; strides that are not powers of two
    gained nothing (48^3 1.03x, 96^3 F = 2 0.96-1.06x, 256^2x3 (1 KiB) 0.97-1.01x), nor
    did separable mode (512^2 1.07x, 64^3 0.97x: five reads per pass).
    """
    stride = math.prod(shape[1:]) * itemsize
    if separable or len(shape) < 2 or stride < 2048 or stride & (stride - 1):
        return 0
    return 1


def _handover_order(pairs, stride: int, has_prev: bool, has_next: bool):
    """Full mode: a level's pairs ordered (taken over, own, handed over), and the lengths
    of those runs (chunks do not cross them).

    Offset ``stride * d`` with every ``d_k`` in {0, +-2} is offset ``2 stride * d/2`` of the
    next level: its weights are computed once and used by both levels. Handed over last
    and taken over first, in whole chunks of their own, they are alive only across the
    level boundary, in place of one chunk's weights: 3-D (13 of 62 pairs per level),
    64^3 F=5: temporaries 21.2 -> 28.6 MiB, 0.92-0.95x the time. Kept anywhere in the level
    instead, they stayed alive for all of it (35.6 MiB, above glibc's 32 MiB mmap
    threshold, page-faulted on every call). Not in 2-D (4 of 12 pairs): 512^2x3 went
    to 33.9 MiB."""
    taken = [p for p in pairs if has_prev and all(abs(c) <= stride for c in p[0])]
    handed = [p for p in pairs if has_next and all(c % (2 * stride) == 0 for c in p[0])]
    own = [p for p in pairs if p not in taken and p not in handed]
    parts = [len(r) for r in (taken, own, handed) if r]
    return taken + own + handed, parts


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
    # Grouped by inner offset (see _pass: one mask per group).
    pairs.sort(key=lambda p: (tuple(abs(c) for c in p[0][1:]), p[0][1:], p[0][0]))
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
        # In _view's shape already: a reshape between the concatenation and the first
        # pass's padding stops XLA fusing them (3-D 128^3: one extra copy, +5 ms).
        planes.append(p.reshape((-1,) + _view(spatial_shape, spatial_shape[0])))
        restore.append((f.dtype, chan + axes, cshape))
    x = jnp.concatenate(planes, axis=0) if len(planes) > 1 else planes[0]
    g_chan = tuple(a for a in range(guide.ndim) if a not in g_axes)
    g = jnp.transpose(guide, g_chan + g_axes).astype(compute)
    g = g.reshape((-1,) + spatial_shape)
    sigma = jnp.asarray(sigma_d, dtype=g.dtype)
    if g.shape[0] > 1:                                  # one channel: see _pair_weights
        g, sigma = rescale_guide(g, sigma)

    valid = None
    if mask is not None:
        valid = mask.astype(compute)
        x = jnp.where(mask.reshape(x.shape[1:]), x, 0)  # also drops NaN/Inf at masked entries

    x = _filter_planar(x, g, valid, sigma, levels, separable)
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
