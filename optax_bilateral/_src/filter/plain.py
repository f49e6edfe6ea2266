"""A plain kernel of the a-trous filter, for backends other than XLA's CPU.

The same two functions as :mod:`optax_bilateral._src.filter.atrous` (:func:`plane_shape`,
:func:`filter_planes`), written the obvious way: each pass zero-pads the fields, the
guide and the validity once and reads every neighbour as a shifted slice, with no
chunking, barriers or pitch columns. XLA's GPU backend fuses each pass into a few
kernels by itself; the steering that the CPU kernel needs only gets in its way
(BENCHMARKS.md, "GPU").
"""

from __future__ import annotations

from collections.abc import Sequence

import jax
import jax.numpy as jnp
from jax import lax

from optax_bilateral._src.filter.bilateral import (
    Pair,
    channel_sq_dist,
    level_passes,
    rescale_guide,
    weight,
)


def plane_shape(spatial_shape: Sequence[int]) -> tuple[int, ...]:
    """The spatial shape itself: this kernel reads the planes as grids."""
    return tuple(spatial_shape)


def filter_planes(
    x: jax.Array,
    g: jax.Array,
    valid: jax.Array | None,
    sigma: jax.Array,
    levels: int,
    separable: bool,
    start: int = 0,
) -> jax.Array:
    """Levels ``start .. levels - 1``: x (C, *S) zero where invalid, g (G, *S), valid
    (*S) float 0/1 or None. Returns (C, *S)."""
    one = g.shape[0] == 1
    if one:
        # One guide channel: the distance |a/2 - b/2| against sigma/2 cannot overflow.
        g, sigma = g * 0.5, sigma * 0.5
    else:
        g, sigma = rescale_guide(g, sigma)
    shape = g.shape[1:]
    x = x.reshape(x.shape[:1] + shape)
    for i in range(start, levels):
        for pairs, h0 in level_passes(shape, 2**i, separable):
            x = _pass(x, g, valid, sigma, pairs, h0, one)
    return x


def _pass(x, g, valid, sigma, pairs: list[Pair], h0: float, one: bool) -> jax.Array:
    """One normalised pass: the centre and both offsets of every pair."""
    shape = x.shape[1:]
    r = [max(abs(off[k]) for off, _ in pairs) for k in range(len(shape))]
    # Off-grid points are zero in `inside`, so their weight is zero whatever they read.
    inside = jnp.ones(shape, x.dtype) if valid is None else valid
    xp, gp, ip = (_pad(a, r) for a in (x, g, inside[None]))
    num = h0 * x
    den = h0 * inside
    for off, tap in pairs:
        for o in (off, tuple(-c for c in off)):
            gq = _shift(gp, o, r, shape)
            d = jnp.abs(g[0] - gq[0]) if one else channel_sq_dist(g, gq)
            w = tap * weight(d, sigma, is_dist=one) * inside * _shift(ip, o, r, shape)[0]
            num = num + w * _shift(xp, o, r, shape)
            den = den + w
    if valid is None:
        return num / den
    return jnp.where(den > 0, num / jnp.where(den > 0, den, 1.0), 0.0)


def _pad(a: jax.Array, r: Sequence[int]) -> jax.Array:
    """Zero-pads the spatial axes of ``a`` (C, *S) by ``r[k]`` on both sides."""
    return jnp.pad(a, [(0, 0)] + [(k, k) for k in r])


def _shift(a: jax.Array, off: Sequence[int], r: Sequence[int], shape: Sequence[int]) -> jax.Array:
    """``a[p + off]`` for every grid point ``p``, from ``a`` padded by ``r``."""
    lo = (0,) + tuple(k + o for k, o in zip(r, off))
    return lax.slice(a, lo, tuple(b + n for b, n in zip(lo, (a.shape[0],) + tuple(shape))))
