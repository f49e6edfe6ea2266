"""A candidate for ``experiments.tuning``: ``sigma_d="auto"`` whose filter gets heavier where
the gradient's noise is spatially correlated (docs/auto_sigma.md, "Correlated gradient noise").

    python -m experiments.tuning --out results/correlation_rule --jobs 2 \\
        --reference experiments/tuning_reference.json \\
        --candidates correlation_rule=experiments.correlation_rule:factory
    python -m experiments.tuning --out results/correlation_rule --jobs 2 \\
        --reference experiments/tuning_reference.json \\
        --only-scenes signal1d_n256,signal1d_n4096,deblur_n64,deblur_n96 \\
        --candidates correlation_rule=experiments.correlation_rule:factory

The signal: the lag-1 correlation between neighbouring texels of ``z = g_t - m_hat_{t-1}``
(the gradient minus Adam's bias-corrected first moment before this step: the signal mostly
cancels, the noise does not), averaged over the spatial axes and the leaves. On the suite it
is 0.00-0.03 on the texture scenes, 0.25 on the volume and 0.92-0.94 on deblurring and the
1-D signal, whose gradients are a transposed blur of a sparse residual, at every stage of
the run.

The rule: at every step, if that correlation is at least ``THRESHOLD`` (``exp(-1/4)``, noise
correlated over a Gaussian width of one texel or more), the update is the one of
``bilateral_adam(learning_rate, levels=3 + EXTRA_LEVELS[d])`` (``d`` spatial axes) with
``auto``'s scale ``FACTOR`` learning rates and its blend's gate shut; otherwise it is the
library's ``bilateral_adam(learning_rate)``. Both share one state, so a run may switch
(``lax.cond``: only the taken branch runs). The constants were fitted on the suite's two
correlated scenes; the held-out scenes check them. Not in the library: see the docs.
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import optax

import optax_bilateral as ob
from optax_bilateral._src import auto, step

THRESHOLD = math.exp(-0.25)
FACTOR = 3.0
EXTRA_LEVELS = {1: 2, 2: 1, 3: 1}
B1 = 0.2  # bilateral_adam's default


def _lag1(z: jax.Array, axes: tuple[int, ...]) -> jax.Array:
    """The lag-1 correlation of ``z`` between neighbours, averaged over ``axes``."""
    out = []
    for a in axes:
        n = z.shape[a]
        x0 = jax.lax.slice_in_dim(z, 0, n - 1, axis=a)
        x1 = jax.lax.slice_in_dim(z, 1, n, axis=a)
        den = jnp.sqrt(jnp.sum(x0 * x0) * jnp.sum(x1 * x1))
        out.append(jnp.sum(x0 * x1) / jnp.where(den > 0, den, 1))
    return jnp.mean(jnp.stack(out))


def noise_correlation(updates: Any, mu: Any, count: jax.Array, spatial_axes: Any) -> jax.Array:
    """The mean over leaves of the lag-1 correlation of ``g - m_hat`` (``g`` at the first step)."""
    c1 = 1 - B1 ** count.astype(jnp.float32)
    axes = ob.filtered_axes(updates, spatial_axes=spatial_axes).values()  # in leaf order
    cs = []
    for leaf_axes, g, m in zip(axes, jax.tree.leaves(updates), jax.tree.leaves(mu)):
        if not leaf_axes:
            continue
        m_hat = jnp.where(count > 0, m / jnp.where(c1 > 0, c1, 1), 0)
        cs.append(_lag1(g - m_hat, leaf_axes))
    return jnp.mean(jnp.stack(cs))


class CorrelationState(NamedTuple):
    inner: Any
    correlated: jax.Array  # whether the last step took the heavier filter (for inspection)


def with_constants(fn, **constants):
    """``fn`` traced with ``auto``'s module constants set (they are read while tracing)."""

    def traced(*args):
        saved = {k: getattr(auto, k) for k in constants}
        for k, v in constants.items():
            setattr(auto, k, v)
        step.leaf_step.clear_cache()
        try:
            return fn(*args)
        finally:
            for k, v in saved.items():
                setattr(auto, k, v)
            step.leaf_step.clear_cache()

    return traced


def _rule(learning_rate, spatial_axes, *, gate_shut: bool, extra: dict[int, int]):
    plain = ob.bilateral_adam(learning_rate, spatial_axes=spatial_axes)

    def heavy(params):
        dims = {len(a) for a in ob.filtered_axes(params, spatial_axes=spatial_axes).values() if a}
        return ob.bilateral_adam(
            learning_rate, levels=3 + extra[max(dims)], spatial_axes=spatial_axes
        )

    def init(params):
        return CorrelationState(plain.init(params), jnp.zeros((), bool))

    def update(updates, state, params=None):
        inner = state.inner
        c = noise_correlation(updates, inner[0].mu, inner[0].count, spatial_axes)
        constants = dict(RATE_FACTOR=FACTOR)
        if gate_shut:
            constants["GATE"] = (2.0, 3.0)  # mean lam <= 1: never open
        correlated = c >= THRESHOLD
        u, new = jax.lax.cond(
            correlated,
            with_constants(lambda: heavy(updates).update(updates, inner, params), **constants),
            with_constants(lambda: plain.update(updates, inner, params)),
        )
        return u, CorrelationState(new, correlated)

    return optax.GradientTransformation(init, update)


def factory(learning_rate, spatial_axes=None) -> optax.GradientTransformation:
    """The rule: 2 more levels in 1-D, 1 in 2-D and 3-D, ``FACTOR`` learning rates, gate shut."""
    return _rule(learning_rate, spatial_axes, gate_shut=True, extra=EXTRA_LEVELS)


def one_level(learning_rate, spatial_axes=None) -> optax.GradientTransformation:
    """The same with one more level whatever the dimension."""
    return _rule(learning_rate, spatial_axes, gate_shut=True, extra={1: 1, 2: 1, 3: 1})


def with_gate(learning_rate, spatial_axes=None) -> optax.GradientTransformation:
    """The rule with the blend's gate as in the library."""
    return _rule(learning_rate, spatial_axes, gate_shut=False, extra=EXTRA_LEVELS)
