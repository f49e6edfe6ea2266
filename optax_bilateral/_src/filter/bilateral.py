"""The a-trous cross-bilateral operator's terms, shared by every kernel.

One level of stride ``s`` computes, for every grid point ``p``,

    out[p] = sum_q w(p, q) x[q] / sum_q w(p, q),    q = p + s d,  d in {-2..2}^n
    w(p, q) = prod_k h[d_k] * exp(-||guide[p] - guide[q]|| / sigma_d)

with ``h = [1/16, 1/4, 3/8, 1/4, 1/16]`` (docs/method.md). This module holds what
does not depend on how a kernel lays out or schedules its work: the taps, the
data weight, the guide's overflow guard and the list of offsets each level visits.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Sequence
from typing import Any, NamedTuple, cast

import jax
import jax.numpy as jnp
from jax import lax

from optax_bilateral._src.numerics import Entry

# B3-spline taps h[d] for d = -2..2, indexed by |d|.
TAPS = (3.0 / 8.0, 1.0 / 4.0, 1.0 / 16.0)

# An offset and its tap product; one entry stands for the pair +offset / -offset.
Pair = tuple[tuple[int, ...], float]

LOG_GUIDE_EPS = 1e-8  # log(|theta| + 1e-8), as the authors' texture runs


class Deeper(NamedTuple):
    """``levels`` more levels after a cascade's own, the whole cascade at sigma_d times
    ``factor``, where ``flag`` (read as > 0) says so at run time (``sigma_d="auto"``'s heavier
    filter for correlated noise). The native kernel decides inside its one call, where a
    ``lax.cond`` would choose between two cascades (:meth:`cascade`), whose conditional costs
    XLA kernels to compile."""

    levels: int
    factor: float
    flag: Entry

    @property
    def static(self) -> tuple[int, float, int]:
        """What a compiled program fixes: the levels, the factor and the flag's entry."""
        return self.levels, self.factor, self.flag.at

    @classmethod
    def of(cls, static: tuple[int, float, int], vector: jax.Array) -> Deeper:
        levels, factor, at = static
        return cls(levels, factor, Entry(vector, at, vector.dtype))

    def cascade(self, run: Callable[[Any, int], Any], sigma: Any, levels: int) -> Any:
        """``run(sigma, levels)``, or where the flag says so
        ``run(sigma * factor, levels + self.levels)``, in a ``lax.cond``."""
        deep = self.flag.vector[self.flag.at] > 0
        heavier = lambda: run(sigma * self.factor, levels + self.levels)
        return lax.cond(deep, heavier, lambda: run(sigma, levels))


def log_transform(x):
    """log(|x| + 1e-8): the log-domain guide of the paper's texture runs."""
    x = jnp.asarray(x)
    x = x.astype(jnp.promote_types(x.dtype, jnp.float32))
    return jnp.log(jnp.abs(x) + LOG_GUIDE_EPS)


def weight(
    d2: jax.Array, sigma_d: jax.Array, mask: jax.Array | None = None, *, is_dist: bool = False
) -> jax.Array:
    """exp(-sqrt(d2) / sigma_d), with equal guides weighing 1 for every sigma_d.

    With ``is_dist``, ``d2`` already is the distance (one guide channel: ``|a - b|``).
    ``mask`` (bool, optional: the pairs to weigh) zeroes the weight where False; a NaN
    ``d2`` (a non-finite guide) weighs 0.

    Written so that sigma_d = 0 (only equal guides), sigma_d = inf (all 1), an
    overflowing d2 and reverse-mode derivatives at d2 = 0 are all well defined.
    Every case is decided in the exponent, so that ``exp`` is the last operation and
    XLA materialises the weights once instead of re-deriving them in every consumer.
    """
    pos = d2 > 0
    dist = jnp.where(pos, d2, 1.0) if is_dist else jnp.sqrt(jnp.where(pos, d2, 1.0))
    s_pos = sigma_d > 0
    s_safe = jnp.where(s_pos, sigma_d, 1.0)
    arg = dist * (-1.0 / s_safe)  # one scalar divide, not one per element
    arg = jnp.where(s_pos, arg, -jnp.inf)  # sigma_d = 0: unequal guides get 0
    arg = jnp.where(jnp.isposinf(sigma_d), 0.0, arg)  # inf/inf would be NaN
    arg = jnp.where(pos, arg, 0.0)  # equal guides: 1 for any sigma_d
    drop = jnp.isnan(d2)  # a non-finite guide is nobody's neighbour
    if mask is not None:
        drop = drop | ~mask
    return jnp.exp(jnp.where(drop, -jnp.inf, arg))


def rescale_guide(g: jax.Array, sigma: jax.Array) -> tuple[jax.Array, jax.Array]:
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
    _, e = jnp.frexp(m)  # m < 2^e
    k = jnp.maximum(e - limit, 0)
    inv = jnp.ldexp(jnp.ones((), g.dtype), -k)
    return g * inv, sigma * inv.astype(sigma.dtype)


def channel_sq_dist(a: jax.Array, b: jax.Array) -> jax.Array:
    """sum_c (a[c] - b[c])**2 over the leading (channel) axis."""
    if a.shape[0] <= 16:
        # Unrolled: XLA's CPU reduce over a short leading axis is far slower than adds.
        return cast(jax.Array, sum(jnp.square(a[c] - b[c]) for c in range(a.shape[0])))
    return jnp.sum(jnp.square(a - b), axis=0)


def level_passes(
    shape: Sequence[int], stride: int, separable: bool
) -> list[tuple[list[Pair], float]]:
    """The passes of one level: each a list of (offset, tap) pairs, one per pair of
    opposite offsets, and the centre tap ``h0``.

    Offsets whose every tap would leave the grid are dropped. Separable: one pass per
    axis, in axis order. Full: one pass over all 5^n taps, grouped by inner offset (a
    kernel can then mask each group once); every kernel sums them in this order.
    """
    n = len(shape)
    if separable:
        passes = []
        for k in range(n):
            pairs = []
            for d in (1, 2):
                if d * stride < shape[k]:
                    off = [0] * n
                    off[k] = d * stride
                    pairs.append((tuple(off), TAPS[d]))
            if pairs:
                passes.append((pairs, TAPS[0]))
        return passes
    pairs = []
    for d in itertools.product(range(-2, 3), repeat=n):
        nz = [c for c in d if c != 0]
        if not nz or nz[0] < 0:  # keep one of each +d / -d
            continue
        if any(abs(c) * stride >= s for c, s in zip(d, shape)):
            continue
        pairs.append((tuple(c * stride for c in d), math.prod(TAPS[abs(c)] for c in d)))
    pairs.sort(key=lambda p: (tuple(abs(c) for c in p[0][1:]), p[0][1:], p[0][0]))
    return [(pairs, TAPS[0] ** n)] if pairs else []


def two_channels(run: Callable[[jax.Array], jax.Array], x: jax.Array) -> jax.Array:
    """``run(x)`` for planar fields ``x`` (C, ...), with a zero channel added when C = 1.

    With one channel, XLA's CPU backend fuses each weight's exp into the pass that reads
    it, once per read and unvectorised: 2-14x slower than two channels (BENCHMARKS.md,
    "Design decisions"). The zero channel keeps the weights computed once per pass."""
    if x.shape[0] != 1:
        return run(x)
    return run(jnp.concatenate([x, jnp.zeros_like(x)]))[:1]
