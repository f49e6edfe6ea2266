"""The a-trous filter on grids sharded across devices: ``shard_map`` with explicit halos.

Each device holds one block of the grid. A pass of stride ``s`` needs, at every
grid point ``p`` of the block, the neighbours ``q = p + s d`` with
``d in {-2..2}^n`` (full) or along one axis (separable), so before each pass
every device fetches a *halo* of ``2 s`` points from the blocks next to it
(``lax.ppermute``; several hops when ``2 s`` is larger than a block). The guide
never changes, so its halo is fetched once, at the widest stride. Points off
the global grid are zero with weight zero, which is exactly the single-device
rule "neighbours outside the grid are skipped and the rest renormalised". Then

    out[p] = (h0 x[p] + sum_o w(p, p+o) x[p+o] + w(p, p-o) x[p-o])
             / (h0 + sum_o w(p, p+o) + w(p, p-o))

is evaluated on the block only, with the same terms in the same order as
:func:`optax_bilateral._src.atrous.atrous_bilateral`: the result equals the
single-device filter up to float rounding.

Why not leave it to XLA's SPMD partitioner: with an *explicit* mesh (the
default of ``jax.make_mesh``) the single-device code does not even trace
(slicing a sharded axis to a size the mesh does not divide is a
``ShardingTypeError``); with an *auto* mesh it compiles, slowly, and where the
single-device filter flattens the spatial axes to read neighbours as flat
windows XLA gathers whole grids (``docs/sharding.md`` has the measurements).

Used when a field's type carries an explicit sharding of a spatial axis
(``jax.typeof(x).sharding``, visible at trace time); anything else goes to the
single-device filter unchanged.
"""

from __future__ import annotations

import functools
import math
from typing import NamedTuple, Optional

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jax.sharding import AxisType, NamedSharding, PartitionSpec

from optax_bilateral._src import atrous


class Partition(NamedTuple):
    """How the spatial axes of a grid are split over a mesh.

    ``names[k]`` are the mesh axes splitting spatial axis ``k`` (in ``spatial_axes``
    order; ``()`` = not split), major to minor as in a ``PartitionSpec`` entry.
    """

    mesh: object        # jax.sharding.Mesh or AbstractMesh
    names: tuple        # tuple[tuple[str, ...], ...]

    def shards(self, k: int) -> int:
        return math.prod(self.mesh.shape[a] for a in self.names[k])


def _entry(e) -> tuple:
    if e is None:
        return ()
    return tuple(e) if isinstance(e, (tuple, list)) else (e,)


def _spec_of(x):
    """(mesh, entries per axis) of ``x``'s explicit sharding, or None."""
    try:
        s = jax.typeof(x).sharding
    except (TypeError, AttributeError):
        return None
    if not isinstance(s, NamedSharding) or s.mesh.empty:
        return None
    explicit = {a for a, t in zip(s.mesh.axis_names, s.mesh.axis_types) if t == AxisType.Explicit}
    spec = tuple(s.spec) + (None,) * (np.ndim(x) - len(s.spec))
    entries = tuple(tuple(a for a in _entry(e) if a in explicit) for e in spec)
    return s.mesh, entries


def spatial_partition(field, spatial_axes) -> Optional[Partition]:
    """How ``field``'s spatial axes are split over explicit mesh axes.

    None if ``field`` has no explicitly sharded axis at all (then the single-device
    filter applies; under an auto mesh XLA splits it). A field sharded only along
    its channels gets a partition with no split axis: the per-device path then
    keeps its channels where they are.
    """
    if not hasattr(field, "shape"):
        return None
    found = _spec_of(field)
    if found is None or not any(found[1]):
        return None
    mesh, entries = found
    axes = atrous.normalize_axes(spatial_axes, np.ndim(field))
    return Partition(mesh, tuple(entries[a] for a in axes))


def atrous_bilateral(fields, guide, *, sigma_d, levels, spatial_axes, separable=True,
                     mask=None, guide_axes=None):
    """:func:`optax_bilateral.atrous_bilateral`, also on grids sharded over explicit mesh axes.

    Same arguments, semantics and result as the single-device filter. When the
    first field's spatial axes are split over *explicit* mesh axes, runs per
    device with halo exchange (see the module docstring) and returns fields with
    the input's shardings; otherwise calls the single-device filter (under an
    *auto* mesh XLA's partitioner then splits it).
    """
    first = fields[0] if isinstance(fields, (tuple, list)) and fields else fields
    try:
        part = spatial_partition(first, spatial_axes)
    except (TypeError, ValueError):
        part = None                                     # the single-device filter explains it
    levels = atrous.check_levels(levels)
    if part is None or levels == 0:
        return atrous.atrous_bilateral(fields, guide, sigma_d=sigma_d, levels=levels,
                                       spatial_axes=spatial_axes, separable=separable,
                                       mask=mask, guide_axes=guide_axes)
    atrous.check_sigma_d(sigma_d)
    return _sharded_jit(fields, guide, sigma_d, mask, levels=levels,
                        spatial_axes=tuple(spatial_axes) if isinstance(spatial_axes, (list, tuple))
                        else spatial_axes,
                        separable=bool(separable),
                        guide_axes=None if guide_axes is None else tuple(guide_axes))


# ----------------------------------------------------------------------------------------
# Halo exchange inside shard_map


class _Axis(NamedTuple):
    names: tuple   # mesh axes splitting this spatial axis; () = not split
    n: int         # number of blocks
    local: int     # block size L
    size: int      # global size N


def _slice_axis(x, axis, start, stop):
    return lax.slice_in_dim(x, start, stop, axis=axis)


def _exchange(x, axis: int, geo: _Axis, width: int):
    """``x`` with ``width`` points of the neighbouring blocks on both sides of ``axis``.

    Positions off the global grid are zero. A halo wider than a block is fetched
    in several hops: hop ``j`` brings the part that lies ``j`` blocks away.
    """
    if width == 0:
        return x
    if geo.n == 1:
        cfg = [(0, 0, 0)] * x.ndim
        cfg[axis] = (width, width, 0)
        return lax.pad(x, jnp.zeros((), x.dtype), cfg)
    L, n = geo.local, geo.n
    lows, highs = [], []
    for j in range(1, -(-width // L) + 1):
        take = min(L, width - (j - 1) * L)
        if j >= n:                                      # no block that far: all off the grid
            shape = list(x.shape)
            shape[axis] = take
            lows.insert(0, jnp.zeros(shape, x.dtype))
            highs.append(jnp.zeros(shape, x.dtype))
            continue
        # Block b sends its last `take` points up to b + j and its first `take` down to b - j.
        lows.insert(0, lax.ppermute(_slice_axis(x, axis, L - take, L), geo.names,
                                    [(b, b + j) for b in range(n - j)]))
        highs.append(lax.ppermute(_slice_axis(x, axis, 0, take), geo.names,
                                  [(b, b - j) for b in range(j, n)]))
    return jnp.concatenate(lows + [x] + highs, axis=axis)


def _extend(x, widths, first_axis: int, geo):
    for k, w in enumerate(widths):
        x = _exchange(x, first_axis + k, geo[k], w)
    return x


def _inside(widths, geo):
    """True where a point of the extended block lies on the global grid."""
    out = None
    n = len(geo)
    for k, (w, g) in enumerate(zip(widths, geo)):
        e = jnp.arange(-w, g.local + w)
        start = lax.axis_index(g.names) * g.local if g.names else 0
        ok = (start + e >= 0) & (start + e < g.size)
        shape = [1] * n
        shape[k] = e.shape[0]
        ok = ok.reshape(shape)
        out = ok if out is None else out & ok
    return jnp.broadcast_to(out, tuple(g.local + 2 * w for w, g in zip(widths, geo)))


def _sq_dist(a, b):
    """sum_c (a[c] - b[c])**2 over the leading (channel) axis."""
    if a.shape[0] <= 16:
        return sum(jnp.square(a[c] - b[c]) for c in range(a.shape[0]))
    return jnp.sum(jnp.square(a - b), axis=0)


def _at(x, starts, size, first_axis):
    start = [0] * x.ndim
    limit = list(x.shape)
    for k, (a, m) in enumerate(zip(starts, size)):
        start[first_axis + k] = a
        limit[first_axis + k] = a + m
    return lax.slice(x, start, limit)


def _local_pass(x, g_ext, gw, valid, sigma, pairs, h0, geo):
    """One normalised pass on this device's block.

    ``x``: (C, *L) block, zero where invalid. ``g_ext``: the guide with ``gw``-wide
    halos, NaN off the grid and outside the mask, so those points weigh 0 (the
    single-device rule for a non-finite guide). ``valid``: the block's mask or None.
    """
    L = x.shape[1:]
    n = len(L)
    hw = [max(abs(off[k]) for off, _ in pairs) for k in range(n)]
    x_ext = _extend(x, hw, 1, geo)
    weights = []
    for off, tap in pairs:
        # One weight array per pair +o/-o over p' in [min(0,-o), max(L, L-o)): w(p', p'+o)
        # serves p's neighbour p+o (at p' = p) and p-o (at p' = p-o, by symmetry).
        lo = [min(0, -o) for o in off]
        span = [m + abs(o) for m, o in zip(L, off)]
        p0 = [g + a for g, a in zip(gw, lo)]
        q0 = [a + o for a, o in zip(p0, off)]
        weights.append(tap * atrous._weight(
            _sq_dist(_at(g_ext, p0, span, 1), _at(g_ext, q0, span, 1)), sigma))
    # Materialise the weights and the extended block: without this XLA fuses the
    # weight arithmetic into the per-channel sums and redoes it for every channel.
    weights, x_ext = lax.optimization_barrier((weights, x_ext))
    num = h0 * _at(x_ext, hw, L, 1)
    den = h0 if valid is None else h0 * valid
    for (off, _), w in zip(pairs, weights):
        lo = [min(0, -o) for o in off]
        w_plus = _at(w, [-a for a in lo], L, 0)
        w_minus = _at(w, [-o - a for o, a in zip(off, lo)], L, 0)
        x_plus = _at(x_ext, [h + o for h, o in zip(hw, off)], L, 1)
        x_minus = _at(x_ext, [h - o for h, o in zip(hw, off)], L, 1)
        num = num + w_plus * x_plus + w_minus * x_minus
        den = den + w_plus + w_minus
    if valid is None:
        return num / den
    return jnp.where(den > 0, num / jnp.where(den > 0, den, 1.0), 0.0)


def _spec(entries):
    return PartitionSpec(*[None if not e else (e[0] if len(e) == 1 else e) for e in entries])


def _reshard(x, mesh, entries):
    """``x`` with the sharding ``entries`` (a no-op when it has it already)."""
    found = _spec_of(x)
    if found is not None and found[1] == tuple(entries):
        return x
    return jax.sharding.reshard(x, NamedSharding(mesh, _spec(entries)))


@functools.partial(jax.jit, static_argnames=("levels", "spatial_axes", "separable", "guide_axes"))
def _sharded_jit(fields, guide, sigma_d, mask, *, levels, spatial_axes, separable, guide_axes):
    single = not isinstance(fields, (tuple, list))
    fields = (fields,) if single else tuple(fields)
    fields = tuple(jnp.asarray(f) for f in fields)
    for i, f in enumerate(fields):
        if not jnp.issubdtype(f.dtype, jnp.inexact):
            raise TypeError(f"fields[{i}] must have a floating dtype, got {f.dtype}")
    part = spatial_partition(fields[0], spatial_axes)
    mesh = part.mesh
    axes0 = atrous.normalize_axes(spatial_axes, fields[0].ndim)
    shape = tuple(fields[0].shape[a] for a in axes0)
    used = {a for e in part.names for a in e}

    # Every field gets the first field's spatial split; its channel axes keep their own.
    per_axes, specs = [], []
    for i, f in enumerate(fields):
        axes = atrous.normalize_axes(spatial_axes, f.ndim, name=f"spatial_axes (for fields[{i}])")
        shp = tuple(f.shape[a] for a in axes)
        if shp != shape:
            raise ValueError(f"fields[{i}] has spatial shape {shp} along {spatial_axes}, "
                             f"but fields[0] has {shape}")
        own = _spec_of(f)
        entries = [()] * f.ndim
        for a in range(f.ndim):
            if a in axes:
                entries[a] = part.names[axes.index(a)]
            elif own is not None and own[0] == mesh:
                entries[a] = tuple(n for n in own[1][a] if n not in used)
        per_axes.append(axes)
        specs.append(tuple(entries))
    fields = tuple(_reshard(f, mesh, e) for f, e in zip(fields, specs))

    guide = jnp.asarray(guide)
    if guide.ndim == len(axes0) and guide_axes is None:
        g_axes = tuple(range(guide.ndim))
    else:
        g_axes = atrous.normalize_axes(spatial_axes if guide_axes is None else guide_axes,
                                       guide.ndim, name="guide_axes" if guide_axes is not None
                                       else "spatial_axes (applied to the guide)")
    g_shape = tuple(guide.shape[a] for a in g_axes)
    if g_shape != shape:
        raise ValueError(f"guide has spatial shape {g_shape} but the fields have {shape}: "
                         "the guide must cover the same grid")
    # The guide's channels are gathered within each block (the distance sums over them).
    g_entries = [()] * guide.ndim
    for k, a in enumerate(g_axes):
        g_entries[a] = part.names[k]
    guide = _reshard(guide, mesh, g_entries)
    has_mask = mask is not None
    args = [jnp.asarray(sigma_d), *fields, guide]
    in_specs = [PartitionSpec(), *[_spec(e) for e in specs], _spec(g_entries)]
    if has_mask:
        mask = jnp.asarray(mask)
        if mask.shape != shape:
            raise ValueError(f"mask must have the spatial shape {shape}, got {mask.shape}")
        args.append(_reshard(mask, mesh, part.names))
        in_specs.append(_spec(part.names))

    compute = jnp.promote_types(jnp.result_type(*fields), jnp.float32)
    geo = tuple(_Axis(part.names[k], part.shards(k), shape[k] // part.shards(k), shape[k])
                for k in range(len(shape)))
    passes = [p for i in range(levels) for p in atrous._level_passes(shape, 2 ** i, separable)]
    # The guide's halo along each axis: the widest offset any pass reads.
    g_halo = [max([abs(off[k]) for pairs, _ in passes for off, _ in pairs] + [0])
              for k in range(len(shape))]

    def body(sigma, *local):
        fl, g = local[:len(fields)], local[len(fields)]
        m = local[len(fields) + 1] if has_mask else None
        planes, restore = [], []
        for f, axes in zip(fl, per_axes):
            chan = tuple(a for a in range(f.ndim) if a not in axes)
            cshape = tuple(f.shape[a] for a in chan)
            planes.append(jnp.transpose(f, chan + axes).astype(compute)
                          .reshape((-1,) + tuple(f.shape[a] for a in axes)))
            restore.append((f.dtype, chan + axes, cshape, tuple(f.shape[a] for a in axes)))
        x = jnp.concatenate(planes, axis=0) if len(planes) > 1 else planes[0]
        g_chan = tuple(a for a in range(g.ndim) if a not in g_axes)
        g = jnp.transpose(g, g_chan + g_axes).astype(compute)
        g = g.reshape((-1,) + x.shape[1:])
        sigma = sigma.astype(compute)
        if has_mask:
            x = jnp.where(m, x, 0)                       # also drops NaN/Inf at masked entries
        valid = None
        if has_mask:
            valid = m.astype(compute)
            g = jnp.where(m, g, jnp.nan)                 # masked points are nobody's neighbour
        # The guide with halos, fetched once per halo pattern (per axis when separable).
        cache = {}

        def extended(pattern):
            if pattern not in cache:
                widths = [w if on else 0 for w, on in zip(g_halo, pattern)]
                inside = _inside(widths, geo)
                g_ext = jnp.where(inside, _extend(g, widths, 1, geo), jnp.nan)
                # The single device's overflow guard, per block: the weights depend on
                # |g_p - g_q| / sigma only and the scale is a power of two, so a block's own
                # scale gives the same weights as a global one, without an all-reduce.
                g_ext, s_ext = atrous.rescale_guide(g_ext, sigma)
                cache[pattern] = (g_ext, widths, s_ext)
            return cache[pattern]

        for pairs, h0 in passes:
            pattern = tuple(any(off[k] for off, _ in pairs) for k in range(len(shape)))
            g_ext, gw, s_ext = extended(pattern)
            x = _local_pass(x, g_ext, gw, valid, s_ext, pairs, h0, geo)
            x = lax.optimization_barrier(x)
        if has_mask:
            x = jnp.where(m, x, 0)
        outs, start = [], 0
        for dtype, perm, cshape, lshape in restore:
            c = math.prod(cshape)
            piece = x[start:start + c].reshape(cshape + lshape)
            start += c
            outs.append(jnp.transpose(piece, np.argsort(perm)).astype(dtype))
        return tuple(outs)

    out = jax.shard_map(body, mesh=mesh, in_specs=tuple(in_specs),
                        out_specs=tuple(_spec(e) for e in specs))(*args)
    return out[0] if single else out
