# ruff: noqa  (a study kept in git history only: docs/research/camera_distance.md)
"""Study: Auto with a sparsity correction of the filtered first moment."""

import dataclasses
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
from jax import lax

import optax_bilateral as ob
from optax_bilateral._src.filter.local import local_average_subgrid
from optax_bilateral._src.rules.auto import Auto
from optax_bilateral._src.rules.sigma import Filtered


class DensityState(NamedTuple):
    auto: Any
    hits: jax.Array


@jax.tree_util.register_static
@dataclasses.dataclass(frozen=True)
class Density(Auto):
    block: int = 4
    density_decay: float = 0.9
    max_boost: float = 8.0
    extra_levels: int = 0
    sparse_below: float = 0.25
    observed_mean: bool = True
    blend_levels: bool = False
    stat: str = "hits"

    def _grid(self, shape, axes):
        return tuple(-(-shape[a] // self.block) for a in axes)

    def init(self, leaf, guide, plan, kind):
        inner = super().init(leaf, guide, plan, kind)
        return DensityState(inner, jnp.zeros(self._grid(jnp.shape(leaf), plan.axes), jnp.float32))

    def sigma(self, guide, plan, state, ctx):
        s, inner = super().sigma(guide, plan, state.auto, ctx)
        return s, state._replace(auto=inner)

    def after_step(self, d, state, plan):
        return state._replace(auto=super().after_step(d, state.auto, plan))

    def _boost(self, g, observed, hits, axes, count):
        other = tuple(a for a in range(g.ndim) if a not in axes)
        hit = jnp.any((g != 0) & observed, axis=other) if other else (g != 0) & observed
        hit = hit.astype(jnp.float32)  # spatial dims in axes order (axes ascending)
        b = self.block
        pad = [(0, (-n) % b) for n in hit.shape]
        ones = jnp.pad(jnp.ones_like(hit), pad)
        hit = jnp.pad(hit, pad)
        grid = hits.shape

        def blocks(x):
            shp = []
            for n in grid:
                shp += [n, b]
            return x.reshape(shp).sum(axis=tuple(range(1, 2 * len(grid), 2)))

        frac = blocks(hit) / blocks(ones)
        d = self.density_decay
        new = d * hits + (1 - d) * frac
        t = count.astype(jnp.float32)
        est = new / (1 - d**t)
        (smooth,) = local_average_subgrid((est,), tuple(range(len(grid))), 1)
        dens = jnp.maximum(smooth, 1.0 / self.max_boost**2)
        c = jnp.where(dens >= 1, 1.0, lax.rsqrt(dens))
        for i, n in enumerate(g.shape[a] for a in axes):
            c = lax.slice_in_dim(jnp.repeat(c, b, axis=i), 0, n, axis=i)
        shape = [1] * g.ndim
        for i, a in enumerate(axes):
            shape[a] = g.shape[a]
        seen = smooth > 0
        mean = (
            jnp.sum(jnp.where(seen, smooth, 0)) / jnp.maximum(jnp.sum(seen), 1)
            if self.observed_mean
            else jnp.mean(est)
        )
        w = jnp.clip(1 - smooth / self.sparse_below, 0, 1) * seen
        for i, n in enumerate(g.shape[a] for a in axes):
            w = lax.slice_in_dim(jnp.repeat(w, b, axis=i), 0, n, axis=i)
        object.__setattr__(self, "_w", w.reshape(shape))
        return c.reshape(shape), new, mean

    def _boost_v(self, v, axes):
        other = tuple(a for a in range(v.ndim) if a not in axes)
        v = v.astype(jnp.float32)
        v = jnp.mean(v, axis=other) if other else v
        r = jnp.sqrt(v)
        b = self.block
        pad = [(0, (-n) % b) for n in v.shape]
        ones = jnp.pad(jnp.ones_like(v), pad)
        grid = tuple(-(-n // b) for n in v.shape)

        def blocks(x):
            shp = []
            for n in grid:
                shp += [n, b]
            return jnp.pad(x, pad).reshape(shp).sum(axis=tuple(range(1, 2 * len(grid), 2)))

        n = blocks(jnp.ones_like(v))
        bv, br = blocks(v) / n, blocks(r) / n
        bv, br = local_average_subgrid((bv, br), tuple(range(len(grid))), 1)
        seen = bv > 0
        dens = jnp.where(seen, br * br / jnp.where(seen, bv, 1), 1.0)
        dens = jnp.clip(dens, 1.0 / self.max_boost**2, 1.0)
        c = lax.rsqrt(dens)
        w = jnp.clip(1 - dens / self.sparse_below, 0, 1) * seen
        shape = [1] * len(other + axes)
        for a in axes:
            shape[a] = v.shape[axes.index(a)]

        def up(x):
            for i, nn in enumerate(v.shape):
                x = lax.slice_in_dim(jnp.repeat(x, b, axis=i), 0, nn, axis=i)
            return x.reshape(shape)

        object.__setattr__(self, "_w", up(w))
        mean = jnp.sum(jnp.where(seen, dens, 0)) / jnp.maximum(jnp.sum(seen), 1)
        return up(c), mean

    def combine(self, moments, op, sigma, state, ctx):
        axes = op.plan.axes
        if self.stat == "hits":
            c, hits, mean = self._boost(moments.g, moments.observed, state.hits, axes, ctx.count)
        else:
            c, mean = self._boost_v(moments.v, axes)
            hits = state.hits
        object.__setattr__(self, "_sparse", mean < self.sparse_below)
        index, ways = super().combine(moments, op, sigma, state.auto, ctx)

        def wrap(way):
            def w():
                f = way()
                return Filtered(
                    (f.m * c.astype(f.m.dtype)), f.v, f.lam, DensityState(f.state, hits)
                )

            return w

        return index, tuple(wrap(w) for w in ways)

    def _cascade(self, op, moments, sigma, heavy):
        out = super()._cascade(op, moments, sigma, heavy)
        if not self.extra_levels:
            return out
        levels = op.plan.levels
        more = lambda: op.apply(out, sigma, levels=levels + self.extra_levels, first_level=levels)
        if self.blend_levels:

            def mixed():
                w = self._w
                return tuple(
                    w.astype(o.dtype) * x + (1 - w.astype(o.dtype)) * o for x, o in zip(more(), out)
                )

            return lax.cond(jnp.any(self._w > 0) & ~heavy, mixed, lambda: out)
        return lax.cond(self._sparse & ~heavy, more, lambda: out)


def factory(learning_rate, spatial_axes=None, **kw):
    return ob.bilateral_adam(learning_rate, sigma_d=Density(**kw), spatial_axes=spatial_axes)
