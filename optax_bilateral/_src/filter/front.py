"""The filter's front door: :func:`atrous_bilateral`.

Checks the arguments and sets up the planar layout once, then hands the planes
to a kernel: the native C++ kernel on the CPU (:mod:`optax_bilateral._src.filter.native`, one XLA
FFI call per cascade), the pure-JAX XLA-CPU kernel (:mod:`optax_bilateral._src.filter.atrous`),
the plain kernel for other backends (:mod:`optax_bilateral._src.filter.plain`), or, when
the fields' spatial axes are split over explicit mesh axes, the same per-block code
run on every device with halo exchange (:mod:`optax_bilateral._src.filter.sharded`).

A kernel is anything with the two methods of :class:`Kernel`; :data:`KERNELS` names
the single-device ones.
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import os
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any, Literal, NamedTuple, Protocol

import jax
import jax.numpy as jnp

from optax_bilateral._src.filter import atrous, layout, native, plain, sharded
from optax_bilateral._src.filter.bilateral import Deeper, log_transform
from optax_bilateral._src.validation import check_levels, check_sigma_d, normalize_axes

if TYPE_CHECKING:
    from jaxtyping import Array, ArrayLike, Bool, Float

    Fields = Float[Array, "..."] | Sequence[Float[Array, "..."]]
    Mask = Bool[ArrayLike, "*spatial"]
else:
    Fields = Any
    Mask = Any


class Kernel(Protocol):
    """What the front door needs from a kernel. A kernel may also offer
    ``filter_fields(fields, g, valid, sigma, levels, start)`` (the native kernel does): a
    separable cascade on fields in their own layout, spatial axes first, which the front door
    then calls instead of laying the fields out as planes."""

    def plane_shape(self, spatial_shape: Sequence[int]) -> tuple[int, ...]:
        """The shape each channel's plane is laid out in."""
        ...

    def filter_planes(
        self,
        x: jax.Array,
        g: jax.Array,
        valid: jax.Array | None,
        sigma: jax.Array,
        levels: int,
        separable: bool,
        start: int = 0,
    ) -> jax.Array:
        """Levels ``start .. levels - 1``: x (C, *plane), g (G, *spatial), valid (*spatial) or
        None -> (C, *spatial)."""
        ...


@dataclasses.dataclass(frozen=True)
class DeeperNative:
    """The native kernel with :class:`Deeper`'s levels, decided inside its one call."""

    deeper: Deeper

    def plane_shape(self, spatial_shape: Sequence[int]) -> tuple[int, ...]:
        return native.plane_shape(spatial_shape)

    def filter_planes(self, x, g, valid, sigma, levels, separable, start=0):
        return native.filter_planes(x, g, valid, sigma, levels, separable, start, self.deeper)

    def filter_fields(self, fields, g, valid, sigma, levels, start=0):
        return native.filter_fields(fields, g, valid, sigma, levels, start, self.deeper)


@dataclasses.dataclass(frozen=True)
class DeeperCond:
    """Any other kernel with :class:`Deeper`'s levels: two cascades in a ``lax.cond``."""

    kernel: Kernel
    deeper: Deeper

    def plane_shape(self, spatial_shape: Sequence[int]) -> tuple[int, ...]:
        return self.kernel.plane_shape(spatial_shape)

    def filter_planes(self, x, g, valid, sigma, levels, separable, start=0):
        run = lambda s, top: self.kernel.filter_planes(x, g, valid, s, top, separable, start)
        return self.deeper.cascade(run, sigma, levels)


# The single-device kernels, by the name `atrous_bilateral(kernel=...)` takes.
KERNELS: dict[str, Kernel] = {"native": native, "xla_cpu": atrous, "plain": plain}  # type: ignore[dict-item]
# Overrides kernel="auto" (for benchmarks and debugging); read when a program is traced.
KERNEL_ENV = "OPTAX_BILATERAL_KERNEL"


def resolve_kernel(kernel: str) -> str:
    """The single-device kernel ``kernel`` names: ``"auto"`` is ``$OPTAX_BILATERAL_KERNEL``
    if set, else on JAX's CPU backend ``"native"`` where the extension runs (``"xla_cpu"``
    where it does not, said once), and ``"plain"`` on any other backend. ``"native"`` raises,
    saying why, where the extension cannot run."""
    if kernel == "auto":
        env = os.environ.get(KERNEL_ENV, "")
        if env and env not in KERNELS:
            raise ValueError(f"${KERNEL_ENV} must be one of {sorted(KERNELS)}, got {env!r}")
        kernel = env or _default_kernel(jax.default_backend())
    if kernel not in KERNELS:
        raise ValueError(f"kernel must be 'auto' or one of {sorted(KERNELS)}, got {kernel!r}")
    if kernel == "native" and not native.available():
        raise ValueError(f"kernel='native' cannot run here: {native.status().reason}")
    return kernel


@functools.cache
def _default_kernel(backend: str) -> str:
    if backend != "cpu":
        return "plain"
    if native.available():
        return "native"
    # Once per process: the filter works, but compiles and runs slower than it would.
    logging.getLogger("optax_bilateral").warning(
        "optax_bilateral: filtering on the pure-JAX 'xla_cpu' kernel: the native kernel "
        "cannot run here (%s)",
        native.status().reason,
    )
    return "xla_cpu"


def atrous_bilateral(
    fields: Fields,
    guide: jax.typing.ArrayLike | Literal["self"],
    *,
    sigma_d: jax.typing.ArrayLike,
    levels: int,
    spatial_axes: Sequence[int],
    separable: bool = True,
    mask: Mask | None = None,
    guide_axes: Sequence[int] | None = None,
    log_guide: bool = False,
    kernel: Literal["auto", "native", "xla_cpu", "plain"] = "auto",
    first_level: int = 0,
) -> Fields:
    r"""A-trous cross-bilateral filter of one or more fields with one set of weights.

    ``out = B_{F-1} ... B_1 B_0 x``, where level ``i`` (stride ``2**i``) is

    .. math::
        (B_i x)[p] = \frac{\sum_q w_i(p,q)\, x[q]}{\sum_q w_i(p,q)}, \quad
        w_i(p,q) = \prod_k h[d_k]\; e^{-\lVert \gamma[p]-\gamma[q] \rVert_2/\sigma_d},
        \quad q = p + 2^i d,\ d \in \{-2..2\}^n

    with B3-spline taps ``h = [1/16, 1/4, 3/8, 1/4, 1/16]`` (docs/method.md;
    supplement eqs. 1, 6, 8). Each ``B_i`` is non-negative and row-stochastic.
    Neighbours outside the grid are skipped and the remaining weights renormalised.

    When the fields' spatial axes are split over *explicit* mesh axes (their type
    carries the sharding), the filter runs per device with halo exchange and returns
    fields with the input's shardings; the result equals the single-device filter
    up to float rounding. Otherwise (one device, or an *auto* mesh, which XLA's
    partitioner splits) it runs the single-device kernel.

    Args:
      fields: an array, or a tuple of arrays, with the same sizes along
        ``spatial_axes``. All are filtered with the same weights (computed once per
        pass), so Adam's ``m`` and ``v`` never get different operators.
      guide: the edge-stopping image ``gamma``. Either an array with exactly the
        spatial axes (its shape is the spatial shape), or an array whose axes
        ``guide_axes`` (default: ``spatial_axes``) have the fields' spatial sizes;
        the distance is the L2 norm over its remaining (channel) axes. A point whose
        guide is NaN is nobody's neighbour.
        Or ``"self"``: the *bilateral* filter (the paper's baseline, the authors'
        ``cross_term_off=True``): each field is guided by itself, and every level
        by its own input, the field as the previous levels left it (so each field,
        and each level, gets its own weights).
      sigma_d: the data term's scale (>= 0). ``0`` keeps only neighbours with an
        equal guide; ``inf`` is a plain B-spline low-pass. May be traced.
      levels: F, the number of a-trous levels (static int >= 0); ``0`` is the
        identity. The footprint radius is ``2 (2**F - 1)``. The authors'
        ``stride_levels = L`` (strides 0, 1, 2, 4, ...: the stride-0 level is the
        identity) is ``levels = L - 1``.
      spatial_axes: the fields' spatial axes (any number, in pass order); the
        other axes are channels that share the weights.
      separable: if True, each level is one normalised 1-D pass of 5 taps per
        spatial axis in the order given (cost 5n per level); if False, all 5**n
        taps at once (the authors' kernels). The two differ across diagonal edges.
      mask: optional boolean array of the spatial shape (in ``spatial_axes``
        order); False entries are left out of every sum (neither read nor written:
        their output is 0).
      guide_axes: the guide's spatial axes, when it has channels and they differ
        from ``spatial_axes``.
      log_guide: guide by ``log(|gamma| + 1e-8)`` (with ``"self"``: of each level's
        input; the authors' ``log_primal``).
      kernel: how the single-device filter is computed; every kernel gives the same
        result up to float rounding. ``"native"``: the C++ kernel (CPU), one XLA FFI call
        for the whole cascade, on ``$OPTAX_BILATERAL_THREADS`` threads (default: every
        usable CPU), compiled in a fraction of the pure-JAX kernels' time
        (docs/performance.md, "The native kernel"); derivatives through it are the
        ``"plain"`` kernel's. ``"xla_cpu"`` is the pure-JAX kernel shaped for XLA's CPU
        backend (chunked, ordered by optimisation barriers); ``"plain"`` is one shifted
        slice per neighbour, which XLA's GPU backend fuses by itself. ``"auto"`` (default):
        the environment variable ``OPTAX_BILATERAL_KERNEL`` if set, else ``"native"`` on
        the CPU backend (``"xla_cpu"`` where the extension cannot run, logged once) and
        ``"plain"`` on any other (BENCHMARKS.md, "GPU"). The sharded filter has its own
        kernel, which runs each device's block on the native kernel when that is the
        choice.
      first_level: run levels ``first_level .. levels - 1`` only (static int, default 0):
        continues a cascade whose first ``first_level`` levels made ``fields``, so the
        outputs after each of several levels cost one cascade, e.g.
        ``y2 = atrous_bilateral(x, ..., levels=2)`` then
        ``y3 = atrous_bilateral(y2, ..., levels=3, first_level=2)`` equals ``levels=3``.

    Returns:
      The filtered fields, with the structure and dtypes of ``fields``. Sums are
      accumulated in at least float32.

    Raises:
      ValueError, TypeError: naming the argument, for a negative or NaN ``sigma_d``,
        a ``levels`` that is not a non-negative int (or a ``first_level`` above it),
        axes out of range or repeated,
        fields, guide or mask whose spatial shapes disagree, non-floating fields.

    Example::

        >>> import jax.numpy as jnp, optax_bilateral as ob
        >>> x = jnp.ones((8, 8, 3))
        >>> y = ob.atrous_bilateral(x, x[..., 0], sigma_d=0.1, levels=2, spatial_axes=(0, 1))
        >>> y.shape
        (8, 8, 3)
    """
    levels = check_levels(levels)
    first_level = check_levels(first_level, "first_level")
    if first_level > levels:
        raise ValueError(f"first_level must be <= levels ({levels}), got {first_level}")
    check_sigma_d(sigma_d)
    kernel = resolve_kernel(kernel)  # type: ignore[assignment]
    self_guided = isinstance(guide, str)
    if self_guided and guide != "self":
        raise ValueError(f"guide must be an array or 'self', got {guide!r}")
    if self_guided and guide_axes is not None:
        raise ValueError("guide_axes must be None with guide='self' (the fields guide themselves)")
    if isinstance(spatial_axes, list):
        spatial_axes = tuple(spatial_axes)
    if isinstance(guide_axes, list):
        guide_axes = tuple(guide_axes)
    if levels == first_level and mask is None:
        return fields  # the identity, without a copy
    run = _Run(levels, first_level, bool(separable), self_guided, bool(log_guide), kernel)
    return _filter_jit(
        fields,
        None if self_guided else guide,
        sigma_d,
        mask,
        spatial_axes=spatial_axes,
        guide_axes=guide_axes,
        run=run,
    )


def atrous_bilateral_deeper(
    fields: Fields,
    guide: jax.typing.ArrayLike,
    deeper: Deeper,
    *,
    sigma_d: jax.typing.ArrayLike,
    levels: int,
    spatial_axes: Sequence[int],
    separable: bool = True,
    mask: Mask | None = None,
    guide_axes: Sequence[int] | None = None,
) -> Fields:
    """:func:`atrous_bilateral` (cross-guided, on one device), and where ``deeper``'s flag says
    so ``deeper.levels`` more levels, the whole cascade at ``sigma_d * deeper.factor``: on
    the native kernel one call that decides at run time, on the others a ``lax.cond``."""
    check_levels(deeper.levels, "deeper.levels")
    check_sigma_d(sigma_d)
    if isinstance(spatial_axes, list):
        spatial_axes = tuple(spatial_axes)
    if isinstance(guide_axes, list):
        guide_axes = tuple(guide_axes)
    kernel = resolve_kernel("auto")
    run = _Run(check_levels(levels), 0, bool(separable), False, False, kernel, deeper.static)
    return _filter_jit(
        fields,
        guide,
        sigma_d,
        mask,
        deeper.flag.vector,
        spatial_axes=spatial_axes,
        guide_axes=guide_axes,
        run=run,
    )


class _Arguments(NamedTuple):
    """The checked arguments: fields as a tuple, normalised axes, the spatial shape."""

    single: bool  # fields was one array, not a tuple
    fields: tuple[jax.Array, ...]
    field_axes: tuple[tuple[int, ...], ...]
    shape: tuple[int, ...]  # the spatial shape, in spatial_axes order
    guide: jax.Array | None  # None: each field guides itself
    guide_axes: tuple[int, ...]
    mask: jax.Array | None


def _checked(fields, guide, mask, spatial_axes, guide_axes) -> _Arguments:
    """Every check of the arguments' shapes and dtypes (trace time, before any work)."""
    single = not isinstance(fields, (tuple, list))
    fields = (fields,) if single else tuple(fields)
    if not fields:
        raise ValueError("fields must be an array or a non-empty tuple of arrays")
    fields = tuple(jnp.asarray(f) for f in fields)
    for i, f in enumerate(fields):
        if jnp.issubdtype(f.dtype, jnp.complexfloating):
            raise TypeError(
                f"fields[{i}] is complex ({f.dtype}); filter its real and imaginary "
                "parts as two channels of a real field"
            )
        if not jnp.issubdtype(f.dtype, jnp.floating):
            raise TypeError(f"fields[{i}] must have a floating dtype, got {f.dtype}")
    axes0 = normalize_axes(spatial_axes, fields[0].ndim)
    if not axes0:
        raise ValueError("spatial_axes must name at least one axis")
    shape = tuple(fields[0].shape[a] for a in axes0)
    field_axes = []
    for i, f in enumerate(fields):
        axes = normalize_axes(spatial_axes, f.ndim, name=f"spatial_axes (for fields[{i}])")
        shp = tuple(f.shape[a] for a in axes)
        if shp != shape:
            raise ValueError(
                f"fields[{i}] has spatial shape {shp} along {tuple(spatial_axes)}, "
                f"but fields[0] has {shape}"
            )
        field_axes.append(axes)

    mask = _check_mask(mask, shape)
    if guide is None:
        return _Arguments(single, fields, tuple(field_axes), shape, None, (), mask)
    guide = jnp.asarray(guide)
    if jnp.issubdtype(guide.dtype, jnp.complexfloating):
        raise TypeError(
            f"guide is complex ({guide.dtype}); pass its real and imaginary parts as "
            "two channels of a real guide (the distance is then |gamma_p - gamma_q|)"
        )
    if guide.ndim == len(axes0) and guide_axes is None:
        g_axes = tuple(range(guide.ndim))
    else:
        g_axes = normalize_axes(
            spatial_axes if guide_axes is None else guide_axes,
            guide.ndim,
            name="guide_axes" if guide_axes is not None else "spatial_axes (applied to the guide)",
        )
    g_shape = tuple(guide.shape[a] for a in g_axes)
    if g_shape != shape:
        raise ValueError(
            f"guide has spatial shape {g_shape} but the fields have {shape}: "
            "the guide must cover the same grid"
        )
    return _Arguments(single, fields, tuple(field_axes), shape, guide, g_axes, mask)


def _check_mask(mask, shape):
    if mask is not None:
        mask = jnp.asarray(mask)
        if mask.shape != shape:
            raise ValueError(f"mask must have the spatial shape {shape}, got {mask.shape}")
    return mask


class _Run(NamedTuple):
    """The static settings of a cascade: levels ``start .. levels - 1``, which kernel, and
    what guides it."""

    levels: int
    start: int
    separable: bool
    self_guided: bool  # each field guides itself, every level by its own input
    log_guide: bool
    kernel: str
    deeper: tuple[int, float, int] | None = None  # Deeper.static; its flag is traced


@functools.partial(jax.jit, static_argnames=("spatial_axes", "guide_axes", "run"))
def _filter_jit(fields, guide, sigma_d, mask, flag=None, *, spatial_axes, guide_axes, run: _Run):
    """One compiled program per (shapes, dtypes, shardings, static settings); sigma_d (and
    ``flag``, :class:`Deeper`'s vector where ``run.deeper``) stays traced."""
    args = _checked(fields, guide, mask, spatial_axes, guide_axes)
    if 0 in args.shape:  # an empty grid: no point to filter, no neighbour to read
        return args.fields[0] if args.single else args.fields
    if run.levels == run.start and run.deeper is None:  # only a mask to apply (the front door
        # returns early without one)
        mask = args.mask
        assert mask is not None
        out = tuple(
            jnp.where(layout.expand_mask(mask, f.ndim, ax), f, 0).astype(f.dtype)
            for f, ax in zip(args.fields, args.field_axes)
        )
    elif run.self_guided:
        # Each field guides itself: its own weights, its own guide read at every level.
        out = tuple(
            _filter_route((f,), (ax,), f, ax, args, sigma_d, run)[0]
            for f, ax in zip(args.fields, args.field_axes)
        )
    else:
        out = _filter_route(
            args.fields, args.field_axes, args.guide, args.guide_axes, args, sigma_d, run, flag
        )
    return out[0] if args.single else out


def _filter_route(fields, field_axes, guide, guide_axes, args, sigma_d, run: _Run, flag=None):
    """The single-device kernel, or the sharded one when the fields' type says so."""
    filter_blocks = functools.partial(
        _filter_blocks, field_axes=field_axes, guide_axes=guide_axes, run=run
    )
    partition = sharded.spatial_partition(fields[0], field_axes[0])
    if partition is None:
        kernel = KERNELS[run.kernel]
        if run.deeper is not None and flag is not None:
            deeper = Deeper.of(run.deeper, flag)
            kernel = DeeperNative(deeper) if kernel is native else DeeperCond(kernel, deeper)
        return filter_blocks(fields, guide, args.mask, sigma_d, kernel)
    if run.deeper is not None:
        raise ValueError("a deeper cascade runs on one device; these fields are split")
    return sharded.filter_sharded(
        filter_blocks,
        partition,
        fields,
        field_axes,
        args.shape,
        guide,
        guide_axes,
        args.mask,
        sigma_d,
        gather_channels=run.self_guided,
        native=run.kernel == "native",
    )


def _filter_blocks(
    fields, guide, mask, sigma_d, kernel: Kernel, *, field_axes, guide_axes, run: _Run
) -> tuple[jax.Array, ...]:
    """Planar layout in, ``kernel``, layout out: on the whole grid, or on one device's block.

    Levels ``run.start .. run.levels - 1``. ``run.self_guided``: ``fields`` is one field, and
    level ``i`` is guided by its input (the field after levels ``0 .. i-1``); ``guide`` is
    then not read."""
    compute = jnp.promote_types(jnp.result_type(*fields), jnp.float32)
    shape = tuple(fields[0].shape[a] for a in field_axes[0])
    if (
        not run.self_guided
        and hasattr(kernel, "filter_fields")
        and native.takes_fields(shape, run.separable, field_axes)
    ):
        return _filter_fields(fields, guide, mask, sigma_d, kernel, guide_axes, compute, run)
    # In the kernel's plane shape already: a reshape between the concatenation and the
    # first pass would stop XLA fusing them.
    planes = kernel.plane_shape(shape)
    x, restore = layout.to_planes(fields, field_axes, compute, planes)
    g = None
    if not run.self_guided:
        g = layout.guide_planes(guide, guide_axes, compute, shape)
        g = log_transform(g) if run.log_guide else g
    sigma = jnp.asarray(sigma_d, dtype=compute)
    valid = None
    if mask is not None:
        valid = mask.astype(compute)
        x = jnp.where(mask.reshape(x.shape[1:]), x, 0)  # also drops NaN/Inf at masked entries
    if run.self_guided:
        for i in range(run.start, run.levels):
            g = x.reshape(x.shape[:1] + shape)
            g = log_transform(g) if run.log_guide else g
            x = kernel.filter_planes(x, g, valid, sigma, i + 1, run.separable, start=i)
            x = x.reshape(x.shape[:1] + planes)
        x = x.reshape(x.shape[:1] + shape)
    else:
        assert g is not None
        x = kernel.filter_planes(x, g, valid, sigma, run.levels, run.separable, start=run.start)
    if mask is not None:
        x = jnp.where(mask, x, 0)
    return layout.from_planes(x, restore, shape)


def _filter_fields(fields, guide, mask, sigma_d, kernel, guide_axes, compute, run: _Run):
    """The native kernel on fields in their own layout (spatial axes first): no planar copy
    of the fields, which the kernel takes apart and puts back itself."""
    shape = tuple(guide.shape[a] for a in guide_axes)
    g = layout.guide_planes(guide, guide_axes, compute, shape)
    g = log_transform(g) if run.log_guide else g
    sigma = jnp.asarray(sigma_d, dtype=compute)
    n = len(shape)
    xs = [f.astype(compute) for f in fields]
    valid = None
    if mask is not None:
        valid = mask.astype(compute)
        xs = [jnp.where(mask.reshape(shape + (1,) * (x.ndim - n)), x, 0) for x in xs]
    ys = kernel.filter_fields(xs, g, valid, sigma, run.levels, start=run.start)
    if mask is not None:
        ys = [jnp.where(mask.reshape(shape + (1,) * (y.ndim - n)), y, 0) for y in ys]
    return tuple(y.astype(f.dtype) for y, f in zip(ys, fields))
