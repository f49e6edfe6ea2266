"""The kernel of the a-trous filter on grids sharded across devices: ``shard_map`` with halos.

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

is evaluated on the block only, with the same terms in the same order as the
single-device kernel (:mod:`optax_bilateral._src.filter.atrous`): the result equals it up
to float rounding.

Why not leave it to XLA's SPMD partitioner: with an *explicit* mesh (the
default of ``jax.make_mesh``) the single-device code does not even trace
(slicing a sharded axis to a size the mesh does not divide is a
``ShardingTypeError``); with an *auto* mesh it compiles, slowly, and where the
single-device filter flattens the spatial axes to read neighbours as flat
windows XLA gathers whole grids (``docs/sharding.md`` has the measurements).

The front door (:mod:`optax_bilateral._src.filter.front`) takes this route when a field's
type carries an explicit sharding of a spatial axis (``jax.typeof(x).sharding``,
visible at trace time): :func:`filter_sharded` places the arrays and runs the front
door's per-block function (planar layout, :class:`HaloKernel`, back) on every device.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jax.sharding import AbstractMesh, AxisType, Mesh, NamedSharding, PartitionSpec

from optax_bilateral._src.filter import native
from optax_bilateral._src.filter.bilateral import (
    channel_sq_dist,
    level_passes,
    rescale_guide,
    two_channels,
    weight,
)
from optax_bilateral._src.validation import normalize_axes


class Partition(NamedTuple):
    """How the spatial axes of a grid are split over a device mesh.

    ``mesh_axes[k]`` are the device mesh's axes splitting spatial axis ``k`` (in
    ``spatial_axes`` order; ``()`` = not split), major to minor as in a
    ``PartitionSpec`` entry.
    """

    device_mesh: Mesh | AbstractMesh
    mesh_axes: tuple[tuple[str, ...], ...]

    def shards(self, k: int) -> int:
        return math.prod(self.device_mesh.shape[a] for a in self.mesh_axes[k])


def _entry(e) -> tuple:
    if e is None:
        return ()
    return tuple(e) if isinstance(e, (tuple, list)) else (e,)


def _spec_of(x):
    """(device mesh, entries per axis) of ``x``'s explicit sharding, or None."""
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


def is_split(x) -> bool:
    """Whether some axis of ``x`` is split over an explicit mesh axis."""
    found = _spec_of(x)
    return found is not None and any(found[1])


def spatial_partition(field, spatial_axes) -> Partition | None:
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
    device_mesh, entries = found
    axes = normalize_axes(spatial_axes, np.ndim(field))
    return Partition(device_mesh, tuple(entries[a] for a in axes))


# ----------------------------------------------------------------------------------------
# Halo exchange inside shard_map


class _Axis(NamedTuple):
    mesh_axes: tuple  # device mesh axes splitting this spatial axis; () = not split
    n: int  # number of blocks
    local: int  # block size L
    size: int  # global size N


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
        if j >= n:  # no block that far: all off the grid
            shape = list(x.shape)
            shape[axis] = take
            lows.insert(0, jnp.zeros(shape, x.dtype))
            highs.append(jnp.zeros(shape, x.dtype))
            continue
        # Block b sends its last `take` points up to b + j and its first `take` down to b - j.
        lows.insert(
            0,
            lax.ppermute(
                _slice_axis(x, axis, L - take, L), geo.mesh_axes, [(b, b + j) for b in range(n - j)]
            ),
        )
        highs.append(
            lax.ppermute(
                _slice_axis(x, axis, 0, take), geo.mesh_axes, [(b, b - j) for b in range(j, n)]
            )
        )
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
        start = lax.axis_index(g.mesh_axes) * g.local if g.mesh_axes else 0
        ok = (start + e >= 0) & (start + e < g.size)
        shape = [1] * n
        shape[k] = e.shape[0]
        ok = ok.reshape(shape)
        out = ok if out is None else out & ok
    assert out is not None, "a block has at least one spatial axis"
    return jnp.broadcast_to(out, tuple(g.local + 2 * w for w, g in zip(widths, geo)))


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
        weights.append(
            tap * weight(channel_sq_dist(_at(g_ext, p0, span, 1), _at(g_ext, q0, span, 1)), sigma)
        )
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


def _reshard(x, device_mesh, entries):
    """``x`` with the sharding ``entries`` (a no-op when it has it already)."""
    found = _spec_of(x)
    if found is not None and found[1] == tuple(entries):
        return x
    return jax.sharding.reshard(x, NamedSharding(device_mesh, _spec(entries)))


class HaloKernel:
    """The per-block kernel, with the interface of :mod:`optax_bilateral._src.filter.atrous`:
    planes are the block's own spatial shape, and each pass first fetches its halo.

    ``native``: each level runs as one call of the native kernel
    (:mod:`optax_bilateral._src.filter.native`) on the block
    extended by the level's reach along every
    axis (corners included, so a separable level's later passes read correct values in the
    halo), and keeps the block's own points."""

    def __init__(self, geo: Sequence[_Axis], shape: tuple[int, ...], native: bool = False):
        self.geo = tuple(geo)
        self.shape = shape  # the global spatial shape
        self.native = native

    def plane_shape(self, spatial_shape: Sequence[int]) -> tuple[int, ...]:
        return tuple(spatial_shape)

    def filter_planes(
        self,
        x: jax.Array,
        g: jax.Array,
        valid: jax.Array | None,
        sigma: jax.Array,
        levels: int,
        separable: bool,
        start: int = 0,
    ) -> jax.Array:
        geo, shape = self.geo, self.shape
        passes = [p for i in range(start, levels) for p in level_passes(shape, 2**i, separable)]
        # The guide's halo along each axis: the widest offset any pass reads.
        g_halo = [
            max([abs(off[k]) for pairs, _ in passes for off, _ in pairs] + [0])
            for k in range(len(shape))
        ]
        if valid is not None:
            g = jnp.where(valid > 0, g, jnp.nan)  # masked points are nobody's neighbour
        if self.native:
            return self._native_levels(x, g, g_halo, sigma, levels, separable, start)
        # The guide with halos, fetched once per halo pattern (per axis when separable).
        cache = {}

        def extended(pattern):
            if pattern not in cache:
                widths = [w if on else 0 for w, on in zip(g_halo, pattern)]
                inside = _inside(widths, geo)
                g_ext = jnp.where(inside, _extend(g, widths, 1, geo), jnp.nan)
                # The single device's overflow guard, per block: a power of two, so a
                # block's own scale gives the same weights as a global one.
                g_ext, s_ext = rescale_guide(g_ext, sigma)
                cache[pattern] = (g_ext, widths, s_ext)
            return cache[pattern]

        def run(x):
            for pairs, h0 in passes:
                pattern = tuple(any(off[k] for off, _ in pairs) for k in range(len(shape)))
                g_ext, gw, s_ext = extended(pattern)
                x = _local_pass(x, g_ext, gw, valid, s_ext, pairs, h0, geo)
                x = lax.optimization_barrier(x)
            return x

        # 2-D full passes on a block keep their weights materialised with one channel too.
        return run(x) if len(shape) == 2 and not separable else two_channels(run, x)

    def _native_levels(self, x, g, g_halo, sigma, levels, separable, start):
        """Each level: the block and its reach (off the grid: zero fields, NaN guide, so
        weight 0), filtered by the native kernel; the block's points kept. The guide's halo
        is fetched once, at the widest reach. Masked points need no mask here: their guide
        is NaN and their fields zero, so their output is their own zero."""
        geo, shape = self.geo, self.shape
        inside = _inside(g_halo, geo)
        g_ext = jnp.where(inside, _extend(g, g_halo, 1, geo), jnp.nan)
        block = x.shape[1:]
        for i in range(start, levels):
            pairs = [off for ps, _ in level_passes(shape, 2**i, separable) for off, _ in ps]
            if not pairs:
                continue
            reach = [max(abs(off[k]) for off in pairs) for k in range(len(shape))]
            x_ext = _extend(x, reach, 1, geo)
            g_lvl = _at(g_ext, [h - r for h, r in zip(g_halo, reach)], x_ext.shape[1:], 1)
            y = native.filter_planes(x_ext, g_lvl, None, sigma, i + 1, separable, start=i)
            x = _at(y, reach, block, 1)
        return x


BlockFn = Callable[..., tuple]


def filter_sharded(
    filter_blocks: BlockFn,
    partition: Partition,
    fields: Sequence[jax.Array],
    field_axes: Sequence[tuple[int, ...]],
    shape: tuple[int, ...],
    guide: jax.Array,
    guide_axes: tuple[int, ...],
    mask: jax.Array | None,
    sigma_d: Any,
    *,
    gather_channels: bool = False,
    native: bool = False,
) -> tuple[jax.Array, ...]:
    """``filter_blocks(fields, guide, mask, sigma_d, kernel)`` run per device on its block,
    with a :class:`HaloKernel` (``native``: its levels on the native kernel); returns the
    fields with the input's shardings.

    Every field gets the first field's spatial split, its channel axes keep their own
    (``gather_channels``: are gathered within each block, for a field that guides
    itself); the guide's channels are gathered within each block (the distance sums
    over them).
    """
    device_mesh, mesh_axes = partition
    used = {a for e in mesh_axes for a in e}
    specs, out_specs = [], []
    for f, axes in zip(fields, field_axes):
        own = _spec_of(f)
        entries: list[tuple[str, ...]] = [()] * f.ndim
        for a in range(f.ndim):
            if a in axes:
                entries[a] = mesh_axes[axes.index(a)]
            elif own is not None and own[0] == device_mesh:
                entries[a] = tuple(n for n in own[1][a] if n not in used)
        out_specs.append(tuple(entries))
        if gather_channels:
            entries = [e if a in axes else () for a, e in enumerate(entries)]
        specs.append(tuple(entries))
    fields = tuple(_reshard(f, device_mesh, e) for f, e in zip(fields, specs))
    g_entries: list[tuple[str, ...]] = [()] * guide.ndim
    for k, a in enumerate(guide_axes):
        g_entries[a] = mesh_axes[k]
    guide = _reshard(guide, device_mesh, g_entries)
    has_mask = mask is not None
    args = [jnp.asarray(sigma_d), *fields, guide]
    in_specs = [PartitionSpec(), *[_spec(e) for e in specs], _spec(g_entries)]
    if has_mask:
        args.append(_reshard(mask, device_mesh, mesh_axes))
        in_specs.append(_spec(mesh_axes))
    geo = tuple(
        _Axis(mesh_axes[k], partition.shards(k), shape[k] // partition.shards(k), shape[k])
        for k in range(len(shape))
    )
    kernel = HaloKernel(geo, shape, native=native)
    n = len(fields)

    def body(sigma, *local):
        m = local[n + 1] if has_mask else None
        return filter_blocks(local[:n], local[n], m, sigma, kernel)

    out = jax.shard_map(
        body, mesh=device_mesh, in_specs=tuple(in_specs), out_specs=tuple(_spec(e) for e in specs)
    )(*args)
    if gather_channels:
        out = tuple(_reshard(o, device_mesh, e) for o, e in zip(out, out_specs))
    return out
