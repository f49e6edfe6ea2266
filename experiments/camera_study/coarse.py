# ruff: noqa  (a study kept in git history only: docs/research/camera_distance.md)
"""Study: the defaults' filter (or Density) on the grid plus Adam on coarse pyramid levels."""

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import optax
from jax import lax

import optax_bilateral as ob
from experiments.camera_study import density
from optax_bilateral._src.filter.local import local_average_subgrid
from optax_bilateral._src.optimizer.pyramid import (
    _leaf_axes,
    pyramid_reconstruct,
    pyramid_transpose,
)


class S(NamedTuple):
    fine: Any
    coarse: Any
    hits: Any
    count: Any


def _density(g, axes, hits, count, block, decay):
    other = tuple(a for a in range(g.ndim) if a not in axes)
    hit = (jnp.any(g != 0, axis=other) if other else g != 0).astype(jnp.float32)
    b = block
    grid = hits.shape
    pad = [(0, (-n) % b) for n in hit.shape]

    def blocks(x):
        shp = []
        for n in grid:
            shp += [n, b]
        return jnp.pad(x, pad).reshape(shp).sum(axis=tuple(range(1, 2 * len(grid), 2)))

    frac = blocks(hit) / blocks(jnp.ones_like(hit))
    new = decay * hits + (1 - decay) * frac
    est = new / (1 - decay ** count.astype(jnp.float32))
    (sm,) = local_average_subgrid((est,), tuple(range(len(grid))), 1)
    seen = sm > 0
    mean = jnp.sum(jnp.where(seen, sm, 0)) / jnp.maximum(jnp.sum(seen), 1)
    x = sm
    for i, n in enumerate(hit.shape):
        x = lax.slice_in_dim(jnp.repeat(x, b, axis=i), 0, n, axis=i)
    shape = [1] * g.ndim
    for i, a in enumerate(axes):
        shape[a] = g.shape[a]
    return x.reshape(shape), mean, new, seen


def coarse_path(
    learning_rate,
    spatial_axes=None,
    levels=3,
    share=0.25,
    b1c=0.9,
    b2c=0.999,
    gate="none",
    fine=None,
    block=8,
    decay=0.9,
    fine_b1=None,
    power=1.0,
):
    fine_rule = density.Density(block=8, extra_levels=1) if fine is None else fine
    fopt = ob.bilateral_adam(
        learning_rate,
        b1=fine_b1,
        b2=None if fine_b1 is None else 1 - (1 - fine_b1) ** 2,
        sigma_d=fine_rule,
        spatial_axes=spatial_axes,
    )
    copt = optax.scale_by_adam(b1=b1c, b2=b2c)

    def coeffs(tree):
        flat = jax.tree.leaves(tree)
        axes = _leaf_axes(tree, spatial_axes)
        return [
            pyramid_transpose(x, levels, ax)[1:] if ax else () for x, ax in zip(flat, axes)
        ], axes

    def init(params):
        c, axes = coeffs(params)
        flat = jax.tree.leaves(params)
        hits = [
            jnp.zeros(tuple(-(-x.shape[a] // block) for a in ax), jnp.float32)
            if ax
            else jnp.zeros(())
            for x, ax in zip(flat, axes)
        ]
        return S(fopt.init(params), copt.init(c), hits, jnp.zeros([], jnp.int32))

    def update(g, state, params=None):
        count = state.count + 1
        u, fs = fopt.update(g, state.fine, params)
        c, axes = coeffs(g)
        steps, cs = copt.update(c, state.coarse)
        flat_u, tdef = jax.tree.flatten(u)
        out, hits = [], []
        for x, s, ax, gl, h in zip(flat_u, steps, axes, jax.tree.leaves(g), state.hits):
            if not ax:
                out.append(x)
                hits.append(h)
                continue
            coarse = pyramid_reconstruct((jnp.zeros_like(gl),) + tuple(s), ax)
            dens, mean, h, seen = _density(gl, ax, h, count, block, decay)
            if gate == "none":
                w = 1.0
            elif gate == "leaf":
                w = jnp.clip(1 - mean, 0, 1) ** power
            else:
                w = jnp.clip(1 - dens, 0, 1) ** power
            lr = learning_rate
            out.append(x - (lr * share * w * coarse).astype(x.dtype))
            hits.append(h)
        return jax.tree.unflatten(tdef, out), S(fs, cs, hits, count)

    return optax.GradientTransformationExtraArgs(init, update)
