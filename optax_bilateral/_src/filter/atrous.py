"""The single-device kernel of the a-trous filter, shaped for XLA's CPU backend.

The front door (:mod:`optax_bilateral._src.filter.front`) validates the arguments and
lays the fields out as planes; this kernel then runs every level on those planes.
Its interface is two functions, :func:`plane_shape` and :func:`filter_planes`:
another backend's kernel (a plainer one, with no CPU steering) implements the same
two and the front door stays as it is.

Everything in this module exists to steer XLA's CPU backend (why each choice was
made, and what the alternatives measured, is in BENCHMARKS.md, "Design decisions"):

* Planes padded with zero rows along the *outer* spatial axis only, so that every
  neighbour ``p + o`` is one contiguous flat slice (:func:`_window`); a read that
  runs off an inner axis lands in the next row, where its weight is 0.
* Every kernel computes in a 2-level shape (:func:`_view`), which keeps XLA's loops
  vectorised for any grid size.
* One exp per *pair* of opposite offsets (the data term is symmetric), and weights
  shared between consecutive levels (offset ``2d 2^i`` is offset ``d 2^(i+1)``).
* Exact no-ops (:func:`_after`, :func:`_opaque_one`) and optimisation barriers that
  order and materialise the work, so that only one chunk's weights are alive at a time.
* Full mode: chunks of :data:`_CHUNK` pairs, the pairs two levels share handed over
  between them (:func:`_handover_order`), and a pitch column on power-of-two strides
  (:func:`pitch_columns`).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence

import jax
import jax.numpy as jnp
from jax import lax

from optax_bilateral._src.filter.bilateral import (
    channel_sq_dist,
    level_passes,
    rescale_guide,
    two_channels,
    weight,
)


def plane_shape(spatial_shape: Sequence[int]) -> tuple[int, ...]:
    """The shape this kernel wants each channel's plane in (its 2-level view)."""
    return _view(spatial_shape, spatial_shape[0])


def filter_planes(
    x: jax.Array,
    g: jax.Array,
    valid: jax.Array | None,
    sigma: jax.Array,
    levels: int,
    separable: bool,
    start: int = 0,
) -> jax.Array:
    """Levels ``start .. levels - 1`` on planar arrays.

    Args:
      x: (C, *plane_shape(S)) fields, zero where invalid.
      g: (G, *S) guide.
      valid: (*S) float 0/1, or None for all valid.
      sigma: scalar sigma_d, in the guide's dtype.
      levels, separable: as in :func:`optax_bilateral.atrous_bilateral`.
      start: the first level to run (stride ``2**start``).

    Returns:
      The filtered fields, (C, *S).
    """
    if g.shape[0] > 1:  # one channel: see _pair_weights
        g, sigma = rescale_guide(g, sigma)
    return two_channels(lambda x: _filter_planar(x, g, valid, sigma, levels, separable, start), x)


def _pad_rows(x: jax.Array, lo: int, hi: int, shape: Sequence[int]) -> jax.Array:
    """Zero-pads the planar array ``x`` (C, *shape), or (C, *_view(shape, n0)), by
    ``lo`` / ``hi`` rows along its outer spatial axis; returns it in ``_view``'s shape,
    (C, (lo + n0 + hi) * m, n_last).

    In that shape the pad (along axis 1) stays a plain pad kernel; padding the
    flattened (C, L) array compiles to a slower generic loop."""
    per_row = _view(shape, 1)
    x = x.reshape((x.shape[0], -1) + per_row[1:])
    cfg = [(0, 0, 0)] * x.ndim
    cfg[1] = (lo * per_row[0], hi * per_row[0], 0)
    return lax.pad(x, jnp.zeros((), x.dtype), cfg)


def _view(shape: Sequence[int], rows: int) -> tuple[int, ...]:
    """The shape in which ``rows`` rows of a grid of ``shape`` are computed: every axis
    but the fastest collapsed into one, (rows * n1 * ... * n_{d-2}, n_{d-1}).

    XLA's CPU loops de- and re-linearise every flat read through the operand's shape;
    LLVM folds that for 2 levels but leaves a per-element remainder for 3, which does
    not vectorise unless the plane size is a power of two. The other axes' coordinates
    are then functions of the collapsed row index only (``_coord``)."""
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
    r = r // math.prod(shape[k + 1 : -1]) if k + 1 < len(shape) - 1 else r
    return r if k == 0 else r % shape[k]


def _window(a: jax.Array, start: int, rows: int, shape: Sequence[int]) -> jax.Array:
    """``rows`` rows of a grid of ``shape``, in ``_view``'s shape, read from flat position
    ``start`` of each channel of ``a`` (C, ...), e.g. from ``_pad_rows``: one contiguous
    slice, whatever the offset."""
    c = a.shape[0]
    n = rows * math.prod(shape[1:])
    flat = a.reshape(c, -1)
    return lax.slice(flat, (0, start), (c, start + n)).reshape((c,) + _view(shape, rows))


def _inner_ok(off: Sequence[int], grid: _Grid, rows: int) -> jax.Array | None:
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

    Added to sigma_d, it makes a pass's weights wait for the previous pass; otherwise
    XLA computes every level's weights first and keeps them all alive.
    """
    # A reduction, so that XLA computes the probe once instead of per weight element.
    corner = lax.slice(x, (0,) * x.ndim, (1,) * (x.ndim - 1) + (min(2, x.shape[-1]),))
    probe = lax.stop_gradient(jnp.max(corner))
    return jnp.where(probe > jnp.inf, 1.0, 0.0).astype(x.dtype)


class _Grid:
    """Static geometry of the planar arrays, (C, n0, *inner), and their flat offsets."""

    def __init__(self, shape: Sequence[int], last: int | None = None):
        self.shape = tuple(shape)
        # The grid's own sizes: the layout's, but without the pitch columns.
        self.bounds = self.shape if last is None else self.shape[:-1] + (last,)
        self.padded = self.bounds != self.shape
        self.n0 = shape[0]
        self.row = math.prod(shape[1:])

    def flat(self, off: Sequence[int]) -> int:
        # > 0 for every offset used (first non-zero component positive, |o_k| < n_k).
        return sum(o * math.prod(self.shape[k + 1 :]) for k, o in enumerate(off))

    def halo(self, off: Sequence[int]) -> int:
        return -(-self.flat(off) // self.row)  # rows spanned: ceil(flat / row)


def _pair_weights(grid: _Grid, gpad, vpad, lead: int, sigma_d, off, h: int) -> jax.Array:
    """E[p] = w(p, p + off) for p over rows -h .. n0 (h >= grid.halo(off)), zero where
    p or p + off is off the grid or invalid.

    w(p, p + off) = E[p] and w(p, p - off) = w(p - off, p) = E[p - off] are then both
    plain flat slices of E: one exp per pair of opposite taps. ``gpad``/``vpad`` are the
    guide and validity with ``lead`` zero rows on both sides. E covers its whole range
    (off-grid rows get exp(-inf) = 0): a padded result would index the reads non-linearly.
    """
    f = grid.flat(off)
    rows = grid.n0 + h
    start = (lead - h) * grid.row
    a, b = _window(gpad, start, rows, grid.shape), _window(gpad, start + f, rows, grid.shape)
    one = a.shape[0] == 1
    if one:
        # One guide channel: the distance |a - b| itself. Halved (and sigma_d with it:
        # exact for normal floats), it cannot overflow, so it needs no rescale_guide.
        d2 = jnp.abs(a[0] * 0.5 - b[0] * 0.5)
        sigma_d = sigma_d * 0.5
    else:
        d2 = channel_sq_dist(a, b)
    i = _coord(grid.shape, rows, 0) - h
    pairs = (i >= 0) & (i < grid.n0 - off[0])  # p and p + off both on the grid
    inner = _inner_ok(off, grid, rows)
    if inner is not None:
        pairs = pairs & inner
    if grid.padded:  # p itself in a pitch column
        pairs = pairs & (_coord(grid.shape, rows, len(grid.shape) - 1) < grid.bounds[-1])
    if vpad is not None:
        pairs = (
            pairs
            & (_window(vpad, start, rows, grid.shape)[0] > 0)
            & (_window(vpad, start + f, rows, grid.shape)[0] > 0)
        )
    return weight(d2, sigma_d, pairs, is_dist=one).reshape(1, -1)  # (1, L): read by _window only


def _opaque_one(a: jax.Array) -> jax.Array:
    """Exactly 1.0 for every element (NaN included), in a form XLA does not fold."""
    return 1.0 + (a != a).astype(a.dtype) * 0.0


def _pass(grid: _Grid, x, pairs, h0, valid, weights, parts=None) -> jax.Array:
    """One normalised bilateral pass over planar arrays.

    x: (C, *view) fields, view = _view(S, n0) (zero where invalid); pairs: [(offset,
    tap)] for one of each pair +o / -o; valid: (*view) float 0/1 or None; weights(off, dep): E from
    ``_pair_weights``, where ``dep`` (an exact 0.0) ties its computation to a point in
    the pass (see ``_after``), so only a chunk's weights are alive at a time; parts:
    lengths of consecutive runs of ``pairs`` that no chunk may cross (default: one run).

    The fields are padded along the outer spatial axis only (whole rows: a pad along
    the fastest axis would put a bounds test on every element) and every neighbour is
    a contiguous flat slice.
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
    for length in parts or [len(pairs)]:
        starts += range(a, a + length, _CHUNK)
        a += length
    stops = dict(zip(starts, starts[1:] + [len(pairs)]))
    ends = {b - 1 for b in stops.values()}
    for k, (off, tap) in enumerate(pairs):
        if k in stops:
            chunk = weights([o for o, _ in pairs[k : stops[k]]], dep)
        e, h = chunk[off]
        f = grid.flat(off)
        w_plus = tap * read(e, h * row)[0]
        w_minus = tap * read(e, h * row - f)[0]
        for inner, term in (
            (tuple(off[1:]), w_plus * read(xpad, r * row + f)),
            (tuple(-o for o in off[1:]), w_minus * read(xpad, r * row - f)),
        ):
            groups[inner] = term if inner not in groups else groups[inner] + term
        den = den + w_plus + w_minus
        if k in ends and k + 1 < len(pairs):
            # Materialise the running sums every _CHUNK pairs: one loop over all of a
            # full pass's pairs stops vectorising.
            num = flush(num)
            # The normaliser first, so that XLA's two-thread split of this kernel along
            # the leading axis gets even halves; the barrier materialises y as one buffer.
            y = jnp.concatenate([jnp.broadcast_to(den, num.shape[1:])[None], num])
            y = lax.optimization_barrier(y)
            dep = _after(y)
            num, den = y[1:], y[0] + dep
    num = flush(num)
    # A full-shape divisor keeps a real divide, which XLA counts as expensive and so
    # materialises the pass instead of fusing it into the next pass's padding.
    den = den * _opaque_one(centre)
    if valid is None:
        return num / den
    return jnp.where(den > 0, num / jnp.where(den > 0, den, 1.0), 0.0)


_CHUNK = 6


def _filter_planar(x, g, valid, sigma, levels: int, separable: bool, start: int = 0) -> jax.Array:
    """Levels ``start .. levels - 1`` on planar arrays: x (C, *S) or (C, *_view(S, n0)) zero
    where invalid, g (G, *S). Returns (C, *S)."""
    shape = g.shape[1:]
    pitch = pitch_columns(shape, separable, g.dtype.itemsize)
    if pitch:
        # Extra zero columns (off the grid for every weight), see pitch_columns.
        g = jnp.pad(g, [(0, 0)] * (g.ndim - 1) + [(0, pitch)])
        x = jnp.pad(x.reshape(x.shape[0], -1, shape[-1]), ((0, 0), (0, 0), (0, pitch)))
        if valid is not None:
            valid = jnp.pad(valid.reshape(-1, shape[-1]), ((0, 0), (0, pitch)))
    grid = _Grid(g.shape[1:], last=shape[-1])
    lead = max(
        [
            grid.halo(off)
            for i in range(start, levels)
            for pairs, _ in level_passes(shape, 2**i, separable)
            for off, _ in pairs
        ]
        or [0]
    )
    # Zero rows in front for the weights' halo, and behind for the reads p + off.
    gpad = _pad_rows(g, lead, lead, grid.shape)
    vpad = None if valid is None else _pad_rows(valid[None], lead, lead, grid.shape)
    # Every kernel works in _view's shape (the fastest axis, and all others collapsed).
    view = _view(grid.shape, grid.n0)
    x = x.reshape(x.shape[:1] + view)
    valid = None if valid is None else valid.reshape(view)
    cache = {}

    def weights(offs, dep):
        """{off: (E, h)} for a chunk of offsets, the new ones computed as one stacked
        array (one XLA kernel, not one per pair: that compiled far slower). Offsets
        shared with the previous level come from the cache (see _handover_order)."""
        new = [o for o in offs if o not in cache]
        if new:
            h = max(grid.halo(o) for o in new)
            stack = jnp.concatenate(
                [_pair_weights(grid, gpad, vpad, lead, sigma + dep, o, h) for o in new]
            )
            for j, o in enumerate(new):
                cache[o] = (stack[j : j + 1], h)
        return {o: cache[o] for o in offs}

    for i in range(start, levels):
        for pairs, h0 in level_passes(shape, 2**i, separable):
            parts = None
            if not separable and len(grid.shape) >= 3:
                pairs, parts = _handover_order(pairs, 2**i, i > start, i + 1 < levels)
            elif not separable:
                cache.clear()  # 2-D full mode recomputes them (see _handover_order)
            x = _pass(grid, x, pairs, h0, valid, weights, parts)
    x = x.reshape(x.shape[:1] + grid.shape)
    return x[..., : shape[-1]] if pitch else x


def pitch_columns(shape: Sequence[int], separable: bool, itemsize: int = 4) -> int:
    """Zero columns appended to the fastest axis in full mode: 1 where the grid's outer
    stride (one step along axis 0, ``prod(shape[1:])`` elements) is a power of two of
    at least 2 KiB, else 0.

    With power-of-two strides, the ~25 (2-D) to ~37 (3-D) read streams of a full pass
    map to the same L1 cache sets; one extra column takes the strides off the powers
    of two. Its points are off the grid for every weight (``_Grid.bounds``) and it is
    sliced off at the end.
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
    level boundary, in place of one chunk's weights. 3-D only: in 2-D the extra weights
    cost more temporary memory than they save."""
    taken = [p for p in pairs if has_prev and all(abs(c) <= stride for c in p[0])]
    handed = [p for p in pairs if has_next and all(c % (2 * stride) == 0 for c in p[0])]
    own = [p for p in pairs if p not in taken and p not in handed]
    parts = [len(r) for r in (taken, own, handed) if r]
    return taken + own + handed, parts
