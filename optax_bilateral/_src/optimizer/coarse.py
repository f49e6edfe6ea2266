"""A coarse path beside a filtered step, where the gradient touches few texels a step.

A far camera's gradient touches a few texels a step (:mod:`optax_bilateral._src.rules.coverage`):
what it says is about blocks of texels, and Adam on a Laplacian pyramid's coarse levels
(Weier et al. 2025) turns it into steps of whole blocks. :func:`coarse_levels` adds those
steps to another transform's, scaled by how sparse the leaf's gradient is, so that a
gradient that touches every texel gets the other transform's step alone.
"""

from __future__ import annotations

import functools
from typing import Any, NamedTuple, cast

import jax
import jax.numpy as jnp
import optax
from jax import lax

from optax_bilateral._src import numerics
from optax_bilateral._src.optimizer import leaf_rule, transforms
from optax_bilateral._src.optimizer.pyramid import (
    _check_levels,
    _leaf_axes,
    level_shapes,
    pyramid_reconstruct,
    pyramid_transpose,
)
from optax_bilateral._src.rules import coverage
from optax_bilateral._src.validation import check_integer, check_number, is_concrete


class CoarseLevelsState(NamedTuple):
    """State of :func:`coarse_levels`.

    Attributes:
      inner_state: the inner transform's state.
      coarse_state: Adam's state on the coarse coefficients: a list with, per parameter leaf
        (in ``jax.tree.leaves`` order), a tuple of levels ``1 .. levels - 1`` (empty for a
        leaf with no spatial axes).
      coverage: per leaf, the moving average of the share of untouched texels per block and
        its bias correction (:class:`~optax_bilateral._src.rules.coverage.CoverageState`;
        None for a leaf with no spatial axes).

    Example::

        >>> import jax.numpy as jnp, optax, optax_bilateral as ob
        >>> opt = ob.coarse_levels(optax.adam(0.01), 0.01, levels=3)
        >>> state = opt.init({"tex": jnp.zeros((16, 16, 3)), "gain": jnp.zeros(())})
        >>> [m.shape for m in state.coarse_state[0].mu[1]]      # "tex": levels 1 and 2
        [(8, 8, 3), (4, 4, 3)]
        >>> state.coverage[0] is None, state.coverage[1].untouched.shape   # "gain", "tex"
        (True, (2, 2))
    """

    inner_state: Any
    coarse_state: Any
    coverage: Any


class _Settings(NamedTuple):
    levels: int
    share: float
    block: int
    decay: float


def coarse_levels(
    inner: optax.GradientTransformation,
    learning_rate: optax.ScalarOrSchedule,
    levels: int = 5,
    share: float = 0.25,
    b1: float = 0.9,
    b2: float = 0.999,
    *,
    block: int = 8,
    decay: float = 0.9,
    spatial_axes: leaf_rule.SpatialAxesSetting = None,
) -> optax.GradientTransformationExtraArgs:
    r"""``inner``'s update plus Adam's on the coarse levels of a Laplacian pyramid, on the grid
    leaves whose gradient touches few texels a step.

    .. math::
        u_t = \mathrm{inner}(g_t) - \eta\, s\, (1 - \bar c_t)\,
              P\,(0, \mathrm{adam}(P^\top g_t)_{1..K-1})

    with ``P`` the pyramid of :func:`optax_bilateral.laplacian_pyramid` (``K = levels``), its
    finest level left to ``inner``; ``s = share``; and ``c̄`` the leaf's mean coverage over the
    blocks it ever touched (:mod:`optax_bilateral._src.rules.coverage`: the share of texels with a
    non-zero gradient, blocks of ``block`` texels a side, a moving average of decay
    ``decay``). A gradient that touches every texel (``c̄ = 1``) gets ``inner``'s update
    alone; a non-finite gradient entry counts as untouched and adds nothing. Leaves with no
    spatial axes get ``inner``'s update.

    Args:
      inner: the transform of the full-resolution step (e.g. :func:`bilateral_adam`), its
        learning rate applied.
      learning_rate: the coarse levels' learning rate (``eta``; a number or a schedule).
      levels: ``K >= 2``, the pyramid's levels, the finest included (static).
      share: ``s > 0``, the coarse steps' share of ``learning_rate``.
      b1: the coarse levels' Adam first-moment decay rate.
      b2: the coarse levels' Adam second-moment decay rate.
      block: the coverage's blocks, in texels a side.
      decay: the coverage's moving average over steps, in [0, 1).
      spatial_axes: which axes of each leaf are the grid, as in
        :func:`optax_bilateral.postfilter`.

    Returns:
      An ``optax.GradientTransformationExtraArgs`` (state :class:`CoarseLevelsState`).

    Raises:
      ValueError: naming the argument, for one out of its range.

    Example::

        >>> import jax.numpy as jnp, optax, optax_bilateral as ob
        >>> opt = ob.coarse_levels(optax.adam(0.01), 0.01, levels=3)
        >>> params = jnp.zeros((16, 16, 3))
        >>> grads = params.at[::8, ::8].set(1.0)                # 1 texel in 64 touched
        >>> updates, state = opt.update(grads, opt.init(params))
        >>> print(f"{float(updates[4, 4, 0]):.4f}")           # untouched, moved by the coarse path
        -0.0025
    """
    settings = _check(levels, share, block, decay)
    leaf_rule.check_spatial_axes_setting(spatial_axes)
    coarse = optax.chain(
        optax.scale_by_adam(b1=b1, b2=b2), optax.scale_by_learning_rate(learning_rate)
    )

    def init_fn(params):
        if transforms._is_placeholder(params):  # optax.tree.map_params: none parameter-shaped
            no = transforms._NotParams
            return CoarseLevelsState(inner.init(params), no(), no())
        leaves, axes = jax.tree.leaves(params), _leaf_axes(params, spatial_axes)
        shapes = [
            level_shapes(jnp.shape(x), levels, ax)[1:] if ax else [] for x, ax in zip(leaves, axes)
        ]
        dtypes = [jnp.result_type(x) for x in leaves]
        zeros = [tuple(jnp.zeros(s, d) for s in ss) for ss, d in zip(shapes, dtypes)]
        covered = [
            coverage.init(jnp.shape(x), ax, block) if ax else None for x, ax in zip(leaves, axes)
        ]
        return CoarseLevelsState(inner.init(params), coarse.init(zeros), covered)

    def update_fn(updates, state, params=None, **extra_args):
        steps, inner_state = optax.with_extra_args_support(inner).update(
            updates, state.inner_state, params, **extra_args
        )
        grads, axes = jax.tree.leaves(updates), _leaf_axes(updates, spatial_axes)
        covs = [
            _coverage(g, ax, cov, settings) if ax else None
            for g, ax, cov in zip(grads, axes, state.coverage)
        ]
        weights = [settings.share * jnp.clip(1 - c.mean, 0, 1) if c else 0.0 for c in covs]
        flat, treedef = jax.tree.flatten(steps)

        def with_coarse():
            finite = [jnp.where(jnp.isfinite(g), g, 0) for g in grads]
            coeffs = [
                pyramid_transpose(g, levels, a)[1:] if a else () for g, a in zip(finite, axes)
            ]
            coarse_steps, coarse_state = coarse.update(coeffs, state.coarse_state)
            # Adam's steps once each, not inside every level of the reconstruction.
            once = [numerics.materialize(tuple(s)) for s in cast(list, coarse_steps)]
            added = [
                u + _field(u, c, a, w) if a else u for u, c, a, w in zip(flat, once, axes, weights)
            ]
            return added, coarse_state

        # Where no leaf is sparse the coarse path is skipped, its Adam state (count too) kept.
        used = functools.reduce(jnp.logical_or, [jnp.asarray(w) > 0 for w in weights], False)
        out, coarse_state = lax.cond(used, with_coarse, lambda: (flat, state.coarse_state))
        covered = [c.state if c else None for c in covs]
        new = CoarseLevelsState(inner_state, coarse_state, covered)
        return jax.tree.unflatten(treedef, out), new

    return optax.GradientTransformationExtraArgs(init_fn, update_fn)


def _coverage(g, axes, state, settings: _Settings) -> coverage.Coverage:
    touched = coverage.touched(g, jnp.isfinite(g), axes)
    return coverage.update(state, touched, block=settings.block, decay=settings.decay)


def _field(u, steps, axes, weight):
    """The coarse ``steps`` (levels ``1 ..``) on the grid of ``u``, times ``weight``."""
    field = pyramid_reconstruct((jnp.zeros_like(steps[0], shape=u.shape),) + tuple(steps), axes)
    return (weight * field).astype(u.dtype)


def _check(levels, share, block, decay) -> _Settings:
    levels = _check_levels(levels)
    if levels < 2:
        raise ValueError(
            f"levels must be an int >= 2 (the finest level and a coarse one), got {levels!r}"
        )
    settings = _Settings(levels, share, block, decay)
    if is_concrete(share):  # a traced one (optax.inject_hyperparams) is taken as it is
        check_number(settings, "share", low=0, low_open=True)
    check_integer(settings, "block", low=1)
    check_number(settings, "decay", low=0, high=1, high_open=True)
    return settings
