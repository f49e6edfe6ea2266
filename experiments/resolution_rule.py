"""A candidate for ``experiments.tuning``: ``sigma_d="auto"`` with F and the rate rule's
factor set by the grid's resolution (docs/auto_sigma.md, "F from the resolution").

    python -m experiments.tuning --out results/resolution_rule --jobs 2 \\
        --candidates resolution_rule=experiments.resolution_rule:factory
    python -m experiments.tuning --out results/resolution_rule --jobs 2 \\
        --only-scenes signal1d_n256,signal1d_n4096,deblur_n64,deblur_n96 \\
        --candidates resolution_rule=experiments.resolution_rule:factory

The rule: ``levels = ceil(log2(n) / 2)`` for ``n`` the longest spatial side of any leaf
(a footprint of about ``sqrt(n)`` texels), and ``sigma_d = FACTOR^(levels - 3)`` learning
rates (``auto.RATE_FACTOR``, 1 in the library). Both were fitted on the suite's seven
scenes; the held-out scenes check them. Not in the library: see the docs for why.
"""

from __future__ import annotations

import math
from typing import Any

import jax
import optax

import optax_bilateral as ob
from optax_bilateral._src import auto, step

FACTOR = 3.0
CHANNELS_MAX = 4  # a trailing axis this short is channels, not space


def levels_for(params: Any, spatial_axes: Any = None) -> int:
    """``ceil(log2(n) / 2)``, ``n`` the longest spatial side over the leaves (at least 1)."""
    sides = []
    for x in jax.tree.leaves(params):
        axes = spatial_axes if spatial_axes is not None else range(x.ndim)
        sides += [x.shape[a] for a in axes if x.shape[a] > CHANNELS_MAX]
    if not sides:
        raise ValueError(f"no spatial side longer than {CHANNELS_MAX} in params")
    return max(1, math.ceil(math.log2(max(sides)) / 2))


def _rule(learning_rate, spatial_axes, factor: float) -> optax.GradientTransformation:
    def inner(params):
        f = levels_for(params, spatial_axes)
        return f, ob.bilateral_adam(learning_rate, levels=f, spatial_axes=spatial_axes)

    def init(params):
        return inner(params)[1].init(params)

    def update(updates, state, params=None):
        f, opt = inner(updates)
        # auto reads its factor while the update traces, so the cached traces (keyed by
        # shape and settings, not the factor) are dropped before and after.
        auto.RATE_FACTOR = factor ** (f - 3)
        step.leaf_step.clear_cache()
        try:
            return opt.update(updates, state, params)
        finally:
            auto.RATE_FACTOR = 1.0
            step.leaf_step.clear_cache()

    return optax.GradientTransformation(init, update)


def factory(learning_rate, spatial_axes=None) -> optax.GradientTransformation:
    """``bilateral_adam(learning_rate, levels=levels_for(params))`` whose ``"auto"`` scale is
    ``FACTOR^(levels - 3)`` learning rates."""
    return _rule(learning_rate, spatial_axes, FACTOR)


def levels_only(learning_rate, spatial_axes=None) -> optax.GradientTransformation:
    """The same ``levels`` rule with the library's scale (one learning rate at every F)."""
    return _rule(learning_rate, spatial_axes, 1.0)
