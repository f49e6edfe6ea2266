"""How much of a leaf a step's gradient touches: its coverage, on a grid of blocks.

A renderer's texture gradient reaches only the texels its samples looked up: one sample a
pixel of a camera that sees 12 texels a pixel touches the 4 texels of one bilinear lookup
in 144. A cross-bilateral filter then averages each step's few values with many zeros, and
``B m / sqrt(B v)`` shrinks by about the square root of the share of texels that were
touched (docs/hyperparameters.md, "How far is my camera"). The coverage is that share: per
block of ``block`` texels along each spatial axis, the share of its texels with a non-zero,
observed gradient, as an exponential moving average over steps (bias-corrected) and smoothed
over neighbouring blocks. The state keeps the moving average of the untouched share, on the
block grid (the leaf's size over ``block^d``): a gradient that touches every texel then has a
coverage of exactly 1, which leaves the transforms that read it unchanged.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax import lax

from optax_bilateral._src.filter.local import local_average_subgrid


class CoverageState(NamedTuple):
    """What a leaf keeps of its coverage.

    Attributes:
      untouched: the moving average of the share of untouched texels per block (float32, the
        block grid, its axes in the leaf's spatial order).
      weight: the same moving average of ones (a float32 scalar): the bias correction, in
        the same arithmetic, so that a block touched at every step, or at none, has a
        coverage of exactly 1, or 0.
    """

    untouched: jax.Array
    weight: jax.Array


class Coverage(NamedTuple):
    """One step's coverage of a leaf.

    Attributes:
      field: the smoothed share of touched texels per block (the block grid), in [0, 1].
      mean: its mean over the blocks that were ever touched (1 where none was).
      state: the :class:`CoverageState` to keep.
    """

    field: jax.Array
    mean: jax.Array
    state: CoverageState


def grid_shape(shape: tuple[int, ...], axes: tuple[int, ...], block: int) -> tuple[int, ...]:
    """The block grid of a leaf of ``shape``: ``ceil(n / block)`` blocks along each of ``axes``
    (in ascending order)."""
    return tuple(-(-shape[a] // block) for a in sorted(axes))


def init(shape: tuple[int, ...], axes: tuple[int, ...], block: int) -> CoverageState:
    """The state before the first step: zeros."""
    zeros = jnp.zeros(grid_shape(shape, axes, block), jnp.float32)
    return CoverageState(zeros, jnp.zeros([], jnp.float32))


def update(state: CoverageState, touched: jax.Array, *, block: int, decay: float) -> Coverage:
    """This step's :class:`Coverage` from the texels it ``touched`` (a bool array over the
    spatial axes, ascending) and the ``state`` kept so far."""
    untouched = _block_share(~touched, block)
    state = CoverageState(
        decay * state.untouched + (1 - decay) * untouched, decay * state.weight + (1 - decay)
    )
    (gap,) = local_average_subgrid(
        (state.untouched / state.weight,), tuple(range(state.untouched.ndim)), 1
    )
    field = jnp.clip(1 - gap, 0, 1)
    seen = field > 0
    mean = jnp.where(
        jnp.any(seen),
        jnp.sum(jnp.where(seen, field, 0)) / jnp.maximum(jnp.sum(seen), 1),
        1.0,
    )
    return Coverage(field, mean, state)


def touched(g: jax.Array, observed: jax.Array, axes: tuple[int, ...]) -> jax.Array:
    """The texels (over ``axes``, ascending) where an observed entry of ``g`` is non-zero."""
    hit = (g != 0) & observed
    channels = tuple(a for a in range(g.ndim) if a not in axes)
    return jnp.any(hit, axis=channels) if channels else hit


def expand(x: jax.Array, shape: tuple[int, ...], axes: tuple[int, ...], block: int) -> jax.Array:
    """A block-grid field over a leaf of ``shape``: each block's value repeated over its
    texels, with unit axes where the leaf has channels (broadcastable against it)."""
    for i, a in enumerate(sorted(axes)):
        x = lax.slice_in_dim(jnp.repeat(x, block, axis=i), 0, shape[a], axis=i)
    out = [1] * len(shape)
    for a in axes:
        out[a] = shape[a]
    return x.reshape(out)


def _block_share(x: jax.Array, block: int) -> jax.Array:
    """The share of true entries of the bool ``x`` in ``block``-wide blocks along every axis
    (a last, partial block by its own texels), as float32."""
    if block == 1:
        return x.astype(jnp.float32)
    pad = [(0, (-n) % block) for n in x.shape]
    blocks = [-(-n // block) for n in x.shape]
    split = [d for n in blocks for d in (n, block)]
    inner = tuple(range(1, 2 * x.ndim, 2))

    def counts(y):
        # Integer counts are exact and stay in XLA's own reduction, which fuses the comparison
        # (the CPU backend hands a float sum to a library kernel, after a full-size copy).
        return jnp.pad(y, pad).reshape(split).sum(axis=inner, dtype=jnp.int32)

    return counts(x).astype(jnp.float32) / counts(jnp.ones_like(x)).astype(jnp.float32)
