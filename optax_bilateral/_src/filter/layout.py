"""Array layouts shared by the filter and the transforms.

* *Planar* layout: every field as ``(channels, *plane)`` in the compute dtype, all
  fields stacked along the channels, so that one set of weights serves them all;
  ``plane`` is the spatial shape in the form a kernel asks for.
* *Texel* masks: one boolean per grid point, in ``spatial_axes`` order, the layout
  :func:`optax_bilateral.atrous_bilateral`'s ``mask`` takes.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np


class Restore(NamedTuple):
    """How one field leaves the planar layout."""

    dtype: Any
    perm: tuple[int, ...]  # the transpose that made it planar
    channel_shape: tuple[int, ...]


def to_planes(
    fields: Sequence[jax.Array],
    field_axes: Sequence[tuple[int, ...]],
    compute: Any,
    plane_shape: tuple[int, ...],
) -> tuple[jax.Array, list[Restore]]:
    """Stacks ``fields`` (spatial axes ``field_axes``) into one ``(C, *plane_shape)`` array."""
    planes, restore = [], []
    for f, axes in zip(fields, field_axes):
        chan = tuple(a for a in range(f.ndim) if a not in axes)
        p = jnp.transpose(f, chan + axes).astype(compute)
        planes.append(p.reshape((-1,) + tuple(plane_shape)))
        restore.append(Restore(f.dtype, chan + axes, tuple(f.shape[a] for a in chan)))
    x = jnp.concatenate(planes, axis=0) if len(planes) > 1 else planes[0]
    return x, restore


def guide_planes(
    guide: jax.Array, guide_axes: tuple[int, ...], compute: Any, spatial_shape: tuple[int, ...]
) -> jax.Array:
    """The guide as ``(G, *spatial_shape)``: its channels first, in the compute dtype."""
    chan = tuple(a for a in range(guide.ndim) if a not in guide_axes)
    g = jnp.transpose(guide, chan + guide_axes).astype(compute)
    return g.reshape((-1,) + tuple(spatial_shape))


def from_planes(
    x: jax.Array, restore: Sequence[Restore], spatial_shape: tuple[int, ...]
) -> tuple[jax.Array, ...]:
    """Inverse of :func:`to_planes`; ``x`` is ``(C, *spatial_shape)``."""
    outs, start = [], 0
    for r in restore:
        c = math.prod(r.channel_shape)
        piece = x[start : start + c].reshape(r.channel_shape + tuple(spatial_shape))
        start += c
        outs.append(jnp.transpose(piece, [int(a) for a in np.argsort(r.perm)]).astype(r.dtype))
    return tuple(outs)


def texel_mask(ok: jax.Array, axes: tuple[int, ...]) -> jax.Array:
    """Reduces an elementwise boolean to the spatial grid (a texel is ok iff all its
    channels are), in ``axes`` order."""
    chan = tuple(a for a in range(ok.ndim) if a not in axes)
    m = jnp.all(ok, axis=chan) if chan else ok
    srt = sorted(axes)
    return jnp.transpose(m, [srt.index(a) for a in axes]) if len(axes) > 1 else m


def expand_mask(mask: jax.Array, ndim: int, axes: tuple[int, ...]) -> jax.Array:
    """Inverse of :func:`texel_mask`'s layout: broadcastable against an array of rank
    ``ndim`` whose spatial axes are ``axes``."""
    srt = sorted(axes)
    m = jnp.transpose(mask, [axes.index(a) for a in srt]) if len(axes) > 1 else mask
    shape = [1] * ndim
    for k, a in enumerate(srt):
        shape[a] = m.shape[k]
    return m.reshape(shape)


# Complex leaves: their real view, the real and imaginary parts as a last axis of 2 (two
# channels of one texel, which one set of weights filters alike).


def real_view(x: Any) -> Any:
    """``x``'s real view ``(..., 2)`` if complex, else ``x`` (None stays None)."""
    if x is None or not jnp.iscomplexobj(x):
        return x
    return jnp.stack([jnp.real(x), jnp.imag(x)], axis=-1)


def from_real_view(x: jax.Array, dtype: Any) -> jax.Array:
    """The complex array of ``dtype`` whose real view is ``x``."""
    return jax.lax.complex(x[..., 0], x[..., 1]).astype(dtype)


def norm_view(v: jax.Array) -> jax.Array:
    """A complex leaf's second moment (real values, stored in the leaf's dtype as optax.adam
    does) as its real view: the same ``|g|^2`` average for both parts."""
    real = jnp.real(v)
    return jnp.broadcast_to(real[..., None], real.shape + (2,))
