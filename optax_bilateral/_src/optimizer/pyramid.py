"""Laplacian-pyramid parameterisation as an optax transform (Weier et al. 2025).

Weier et al., "Practical Inverse Rendering of Textured and Translucent
Appearance" (SIGGRAPH 2025), optimise a texture as a Laplacian
pyramid: coefficients ``c_0`` (full resolution), ``c_1`` (half), ...,
``c_{K-1}`` (coarsest), with the grid their sum after upsampling,

    theta = P c = c_0 + U(c_1 + U(c_2 + ... U(c_{K-1}))),

and run Adam on the coefficients (all levels with one learning rate). ``P`` is
linear and the loss depends on ``c`` only through ``theta``, so
``df/dc = P^T df/dtheta`` and a step ``delta c`` moves the grid by ``P delta c``.
Written on ``theta`` the method is the transform

    g~_t = P^T g_t,   delta_t = inner(g~_t)  (in coefficient space),   update_t = P delta_t,

with the inner optimiser's state (Adam's moments) held per coefficient. The
step does not depend on ``c`` itself, so projecting ``theta`` onto a valid
domain after the update (clipping) gives the same iterates as clipping the
reconstructed grid and writing the difference back into the coefficients.
This is how :func:`optax_bilateral.triangle_mesh.large_steps` writes a
reparameterisation, too.

``U`` doubles every spatial axis with linear interpolation on cell centres
(output ``2i`` is ``0.75 c[i] + 0.25 c[i-1]``, ``2i+1`` is ``0.75 c[i] + 0.25
c[i+1]``, edges clamped: the bilinear "tent" upsampling of the authors' code),
then crops to the finer level's size; level ``k`` has ``ceil(n / 2^k)``
samples along an axis of ``n``, so any grid size works.
"""

from __future__ import annotations

import functools
import numbers
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any, NamedTuple, cast

import jax
import jax.numpy as jnp
import numpy as np
import optax
from jax import lax

from optax_bilateral._src import numerics
from optax_bilateral._src.optimizer import leaf_rule
from optax_bilateral._src.optimizer import leaves as lv

if TYPE_CHECKING:
    from optax_bilateral._src.optimizer.leaf_rule import SpatialAxesSetting


def _check_levels(levels) -> int:
    if isinstance(levels, bool) or not isinstance(levels, numbers.Integral) or levels < 1:
        raise ValueError(
            f"levels must be an int >= 1 (1 = no pyramid: the inner optimiser "
            f"on the grid itself), got {levels!r}"
        )
    return int(levels)


def level_shapes(shape: Sequence[int], levels: int, axes: Sequence[int]) -> list[tuple[int, ...]]:
    """Shapes of the ``levels`` coefficient arrays of a grid of ``shape`` (finest first).

    Level ``k`` has ``ceil(n / 2^k)`` samples along every spatial axis in ``axes``;
    other axes (channels) keep their size.
    """
    levels = _check_levels(levels)
    shapes = [tuple(int(n) for n in shape)]
    for _ in range(levels - 1):
        prev = shapes[-1]
        shapes.append(tuple(-(-n // 2) if a in axes else n for a, n in enumerate(prev)))
    return shapes


def _upsample_axis(c, axis: int, size: int):
    """Linear 2x upsampling on cell centres along ``axis`` (edges clamped), cropped to ``size``:
    the even and odd outputs interleaved by a reshape, with no transposes."""
    m = c.shape[axis]
    prev = _shifted(c, c, axis, 1)  # c[i - 1], c[0] at the edge
    nxt = _shifted(c, c, axis, -1)  # c[i + 1], c[m - 1] at the edge
    even, odd = 0.75 * c + 0.25 * prev, 0.75 * c + 0.25 * nxt
    out = jnp.stack([even, odd], axis=axis + 1)
    out = out.reshape(c.shape[:axis] + (2 * m,) + c.shape[axis + 1 :])
    return lax.slice_in_dim(out, 0, size, axis=axis)


def _downsample_axis(g, axis: int, size: int):
    """The transpose of :func:`_upsample_axis` to ``size`` samples: each coarse sample gathers
    the fine samples its interpolation fed, the clamped edges' included."""
    n = g.shape[axis]
    if n < 2 * size:  # the cropped last odd sample: a zero gradient
        g = jnp.pad(g, [(0, 2 * size - n) if a == axis else (0, 0) for a in range(g.ndim)])
    even = lax.slice_in_dim(g, 0, 2 * size, stride=2, axis=axis)
    odd = lax.slice_in_dim(g, 1, 2 * size, stride=2, axis=axis)
    # even[i + 1] fed c[i] (as its left neighbour), odd[i - 1] fed c[i] (its right one).
    return 0.75 * (even + odd) + 0.25 * (
        _shifted(even, odd, axis, -1) + _shifted(odd, even, axis, 1)
    )


def _shifted(x, edge, axis: int, by: int):
    """``x`` moved ``by`` = +1 (``x[i - 1]``) or -1 (``x[i + 1]``) samples along ``axis``, the
    sample that enters taken from ``edge`` at the same end."""
    m = x.shape[axis]
    if by > 0:
        parts = (lax.slice_in_dim(edge, 0, 1, axis=axis), lax.slice_in_dim(x, 0, m - 1, axis=axis))
    else:
        parts = (lax.slice_in_dim(x, 1, m, axis=axis), lax.slice_in_dim(edge, m - 1, m, axis=axis))
    return jnp.concatenate(parts, axis=axis)


def upsample(c, shape: Sequence[int], axes: Sequence[int]):
    """``U``: one pyramid level ``c`` upsampled to the next finer level's ``shape``."""
    for a in axes:
        c = _upsample_axis(c, a, int(shape[a]))
    return c


def pyramid_reconstruct(coefficients: Sequence[Any], axes: Sequence[int]):
    """``P c``: the grid of a Laplacian pyramid (finest level first), ``c_0 + U(c_1 + U(...))``."""
    coefficients = list(coefficients)
    if not coefficients:
        raise ValueError("coefficients must hold at least one level")
    return _reconstruct(tuple(coefficients), tuple(int(a) for a in axes))


@functools.partial(jax.jit, static_argnames=("axes",))
def _reconstruct(coefficients, axes):
    out = coefficients[-1]
    for k, c in enumerate(reversed(coefficients[:-1])):
        out = c + upsample(out, c.shape, axes)
        if k < len(coefficients) - 2:  # read by the next finer level (the finest by its caller)
            (out,) = numerics.materialize((out,))
    return out


def pyramid_transpose(grid, levels: int, axes: Sequence[int]) -> tuple:
    """``P^T g``: a grid-shaped gradient mapped to the pyramid's coefficients (finest first).

    The exact transpose of :func:`pyramid_reconstruct` (``<P c, g> = <c, P^T g>``).
    """
    return _transpose(grid, _check_levels(levels), tuple(int(a) for a in axes))


@functools.partial(jax.jit, static_argnames=("levels", "axes"))
def _transpose(grid, levels, axes):
    shapes = level_shapes(np.shape(grid), levels, axes)
    out = [grid]
    for coarse in shapes[1:]:
        g = out[-1]
        for a in axes:  # each axis written once: XLA would recompute it in every reader
            (g,) = numerics.materialize((_downsample_axis(g, a, coarse[a]),))
        out.append(g)
    return tuple(out)


class LaplacianPyramidState(NamedTuple):
    """State of :func:`laplacian_pyramid`: the inner optimiser's state on the coefficients.

    Attributes:
      inner_state: ``inner.init`` of the coefficients: a list with, per parameter leaf (in
        ``jax.tree.leaves`` order), a tuple of ``levels`` arrays, finest first (level ``k``
        has ``ceil(n / 2^k)`` samples along each spatial axis of size ``n``); a leaf with
        no spatial axes is a 1-tuple of itself.

    Example::

        >>> import jax.numpy as jnp, optax, optax_bilateral as ob
        >>> state = ob.laplacian_pyramid(optax.adam(0.01), levels=3).init(jnp.zeros((8, 8, 1)))
        >>> [m.shape for m in state.inner_state[0].mu[0]]
        [(8, 8, 1), (4, 4, 1), (2, 2, 1)]
    """

    inner_state: Any


def _leaf_axes(tree, spatial_axes) -> list[tuple[int, ...]]:
    """Spatial axes per leaf, by the library's leaf rule (``default_spatial_axes``)."""
    specs = lv.leaf_specs(tree, spatial_axes=spatial_axes, sigma_d=0.0, levels=1)
    return [s.axes for s in specs]


def laplacian_pyramid(
    inner: optax.GradientTransformation,
    levels: int,
    *,
    spatial_axes: SpatialAxesSetting = None,
) -> optax.GradientTransformationExtraArgs:
    r"""Runs ``inner`` on Laplacian-pyramid coefficients of every grid leaf (Weier et al. 2025).

    .. math::
        \tilde g_t = P^\top g_t, \qquad \Delta_t = \mathrm{inner}(\tilde g_t), \qquad
        u_t = P \Delta_t

    with ``P c = c_0 + U(c_1 + U(\dots c_{K-1}))``: level ``k`` has ``ceil(n / 2^k)``
    samples along each spatial axis of size ``n``, and ``U`` doubles every spatial axis by
    linear interpolation on cell centres (output ``2i`` is ``0.75 c[i] + 0.25 c[i-1]``,
    ``2i+1`` is ``0.75 c[i] + 0.25 c[i+1]``, edges clamped), then crops to the finer
    level's size. Equivalent to optimising the coefficients with ``inner`` while the loss
    sees their sum (``df/dc = P^T df/dtheta``); the inner state lives in coefficient
    space (one array per level and leaf). The inner transform is called with
    ``params=None`` (the coefficients are never formed), so it must not need parameter
    values (Adam, SGD, momentum do not).

    Args:
      inner: the optimiser of the coefficients (e.g. ``optax.adam(lr)``).
      levels: ``K >= 1``, the number of pyramid levels (static); 1 is ``inner``
        on the grid itself.
      spatial_axes: which axes of each leaf are the grid, as in
        :func:`optax_bilateral.postfilter` (``None``: the default leaf rule;
        leaves with no spatial axes are passed to ``inner`` as they are).

    Returns:
      An ``optax.GradientTransformationExtraArgs`` (state :class:`LaplacianPyramidState`)
      whose updates have the gradients' shapes and dtypes.

    Raises:
      ValueError: ``levels`` is not an int >= 1, or ``spatial_axes`` is not a valid setting.

    Example::

        >>> import jax.numpy as jnp, optax, optax_bilateral as ob
        >>> opt = ob.laplacian_pyramid(optax.sgd(1.0), levels=3)
        >>> grads = jnp.zeros((8, 8, 1)).at[3, 3].set(1.0)
        >>> updates, _ = opt.update(grads, opt.init(grads))   # -P P^T g: spread over levels
        >>> print(updates[3, 3, 0], updates[0, 0, 0])
        -1.6728516 -0.390625
    """
    levels = _check_levels(levels)
    leaf_rule.check_spatial_axes_setting(spatial_axes)

    def coefficients(tree):
        flat, treedef = jax.tree.flatten(tree)
        axes = _leaf_axes(tree, spatial_axes)
        return (
            [pyramid_transpose(x, levels, ax) if ax else (x,) for x, ax in zip(flat, axes)],
            treedef,
            axes,
        )

    def init_fn(params):
        flat = jax.tree.leaves(params)
        zeros = [
            tuple(
                jnp.zeros(s, jnp.result_type(x))
                for s in (level_shapes(np.shape(x), levels, ax) if ax else [np.shape(x)])
            )
            for x, ax in zip(flat, _leaf_axes(params, spatial_axes))
        ]
        return LaplacianPyramidState(inner_state=inner.init(zeros))

    def update_fn(updates, state, params=None, **extra_args):
        del params
        coeffs, treedef, axes = coefficients(updates)
        steps, inner_state = optax.with_extra_args_support(inner).update(
            coeffs, state.inner_state, None, **extra_args
        )
        out = [
            pyramid_reconstruct(s, ax).astype(u.dtype) if ax else s[0].astype(u.dtype)
            for s, ax, u in zip(cast(list, steps), axes, jax.tree.leaves(updates))
        ]
        return jax.tree.unflatten(treedef, out), LaplacianPyramidState(inner_state=inner_state)

    return optax.GradientTransformationExtraArgs(init_fn, update_fn)


def pyramid_adam(
    learning_rate: optax.ScalarOrSchedule,
    levels: int,
    b1: jax.typing.ArrayLike = 0.9,
    b2: jax.typing.ArrayLike = 0.999,
    eps: jax.typing.ArrayLike = 1e-8,
    *,
    spatial_axes: SpatialAxesSetting = None,
) -> optax.GradientTransformationExtraArgs:
    """Adam on Laplacian-pyramid coefficients: ``laplacian_pyramid(optax.adam(...), levels)``.

    Weier et al.'s texture parameterisation (SIGGRAPH 2025): one learning rate for
    every level, Adam's defaults (Mitsuba's). ``learning_rate`` (a number or a
    schedule) is traceable through
    ``optax.inject_hyperparams(pyramid_adam, static_args=("levels",))``. The step on the
    grid is ``-lr P adam(P^T g)`` (:func:`laplacian_pyramid` defines ``P``), so a first
    step moves a texel by up to ``levels * lr``.

    Args:
      learning_rate: a number or an optax schedule.
      levels: ``K >= 1``, the number of pyramid levels (static).
      b1: Adam's first-moment decay rate (default 0.9).
      b2: Adam's second-moment decay rate (default 0.999).
      eps: Adam's epsilon (default 1e-8).
      spatial_axes: which axes of each leaf are the grid (``None``: the default leaf
        rule, :func:`default_spatial_axes`), as in :func:`laplacian_pyramid`.

    Returns:
      An ``optax.GradientTransformationExtraArgs`` (state :class:`LaplacianPyramidState`).

    Example::

        >>> import jax.numpy as jnp, optax_bilateral as ob
        >>> opt = ob.pyramid_adam(0.01, levels=3)
        >>> grads = jnp.zeros((8, 8, 1)).at[3, 3].set(1.0)
        >>> updates, _ = opt.update(grads, opt.init(grads))
        >>> round(float(updates.min()), 4)          # three levels of -lr sign steps
        -0.03
    """
    return laplacian_pyramid(
        optax.adam(learning_rate, b1=b1, b2=b2, eps=eps), levels, spatial_axes=spatial_axes
    )
