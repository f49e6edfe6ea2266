"""The native kernel of the a-trous filter: one XLA FFI call runs the whole cascade.

The same two functions as the pure-JAX kernels (:func:`plane_shape`, :func:`filter_planes`),
and :func:`filter_fields` for fields in their own layout, computed by the C++ extension
``optax_bilateral._native`` (sources in ``csrc/``, built by ``setup.py``): every level and
pass in one call, each pair's weight computed once and used by both of its points, on
several threads. A separable cascade on a grid of rank >= 2 runs every level in place in the
output's memory, slab by slab; any other cascade of two or more passes alternates between the
output and one working copy of the fields (a last output of the call, so that it is in XLA's
buffer plan).

Derivatives are the pure-JAX kernel's: :func:`filter_planes` is a ``jax.custom_jvp`` whose rule
differentiates
:mod:`optax_bilateral._src.filter.plain`, so ``jax.grad`` / ``jax.jvp`` with respect to
the fields, the guide and sigma_d work as with the other kernels. ``jax.vmap`` runs the call
once per batch element (``vmap_method="sequential"``).

Where the extension is missing or cannot load (no compiler at install time, another OS),
the package still imports and the pure-JAX kernels run; :func:`status` says why, and asking
for ``kernel="native"`` raises with that reason.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Sequence
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from optax_bilateral._src import extension
from optax_bilateral._src.filter import plain
from optax_bilateral._src.filter.bilateral import Deeper, level_passes
from optax_bilateral._src.numerics import Entry

TARGET = "optax_bilateral_atrous"
FIELDS_TARGET = "optax_bilateral_atrous_fields"
SUBGRID_TARGET = "optax_bilateral_local_average"
TEXEL_MEAN_TARGET = "optax_bilateral_texel_distance_mean"
CORRELATION_TARGET = "optax_bilateral_correlation_sums"
NOISE_TEST_TARGET = "optax_bilateral_correlated_noise"
BLEND_TARGET = "optax_bilateral_blend_weights"
STEP_NORM_TARGET = "optax_bilateral_step_norm"
THREADS_ENV = extension.THREADS_ENV
NATIVE_ENV = extension.NATIVE_ENV
threads = extension.threads


class Status(NamedTuple):
    """Whether the native kernel runs, and why (or why not)."""

    available: bool
    reason: str  # "avx512", "avx2" or "baseline" when available, else the error met
    threads: int


_registered = extension.registered


def status() -> Status:
    """Whether the native filter kernel runs in this process (``kernel="auto"`` takes it on
    the CPU where it does), with which instruction set (``"avx512"``, ``"avx2"``,
    ``"baseline"``) or, where it cannot, why; and the threads one call uses
    (``$OPTAX_BILATERAL_THREADS``, else the CPUs this process may run on).

    Example::

        >>> import optax_bilateral as ob
        >>> ob.native_status().available
        True
    """
    ok, reason = _registered()
    return Status(ok, reason, threads())


def _require(what: str) -> None:
    """Raises, naming ``what`` and why, where the extension cannot run."""
    ok, reason = _registered()
    if not ok:
        raise RuntimeError(f"{what} cannot run here: {reason}")


def available() -> bool:
    return _registered()[0]


def plane_shape(spatial_shape: Sequence[int]) -> tuple[int, ...]:
    """The spatial shape itself: the kernel reads the planes as row-major grids."""
    return tuple(spatial_shape)


def _flag(deeper: Deeper | None, dtype) -> tuple[jax.Array, tuple[int, float, int]]:
    """The call's ``deeper`` operand and its static part: ``(0,)`` (never) without one."""
    if deeper is None:
        return jnp.zeros((0,), dtype), (0, 1.0, 0)
    return deeper.flag.vector, deeper.static


def _pure(run, sigma, levels: int, flag: jax.Array, more: tuple[int, float, int]):
    """The call's meaning in JAX (its derivative): ``run(sigma, levels)``, and where ``flag``
    is not empty :class:`Deeper`'s levels where it says so."""
    if not flag.shape[0]:
        return run(sigma, levels)
    return Deeper.of(more, flag).cascade(run, sigma, levels)


class Span(NamedTuple):
    """A call's static levels: ``start .. levels - 1``, and :class:`Deeper`'s static part."""

    start: int
    levels: int
    more: tuple[int, float, int]


def filter_planes(
    x: jax.Array,
    g: jax.Array,
    valid: jax.Array | None,
    sigma: jax.Array,
    levels: int,
    separable: bool,
    start: int = 0,
    deeper: Deeper | None = None,
) -> jax.Array:
    """Levels ``start .. levels - 1`` (and :class:`Deeper`'s where its flag says so): x (C, *S)
    zero where invalid, g (G, *S), valid (*S) float 0/1 or None, sigma a scalar in x's
    dtype. Returns (C, *S)."""
    _require("the native filter kernel")
    x = x.reshape(x.shape[:1] + g.shape[1:])
    flag, more = _flag(deeper, x.dtype)
    return _cascade(x, g, valid, sigma, flag, bool(separable), Span(start, levels, more))


@functools.partial(jax.custom_jvp, nondiff_argnums=(5, 6))
def _cascade(x, g, valid, sigma, flag, separable, span):
    # The working copy for the deepest cascade the call may run.
    start, levels, more = span
    work = x.shape if _needs_work(g.shape[1:], levels + more[0], start, separable) else (0,)
    call = jax.ffi.ffi_call(
        TARGET,
        (jax.ShapeDtypeStruct(x.shape, x.dtype), jax.ShapeDtypeStruct(work, x.dtype)),
        vmap_method="sequential",
    )
    out, _ = call(
        x,
        g,
        jnp.zeros((0,), x.dtype) if valid is None else valid.astype(x.dtype),
        jnp.asarray(sigma, x.dtype).reshape(()),
        flag,
        levels=np.int64(levels),
        start=np.int64(start),
        separable=bool(separable),
        has_valid=valid is not None,
        threads=np.int64(threads()),
        **_deeper_attributes(more),
    )
    return out


def _deeper_attributes(more: tuple[int, float, int]) -> dict[str, Any]:
    extra, factor, at = more
    return {
        "deeper_at": np.int64(at),
        "deeper_levels": np.int64(extra),
        "deeper_factor": np.float64(factor),
    }


def _needs_work(shape, levels, start, separable) -> bool:
    """Whether the kernel needs a working copy (csrc/passes.cc, needs_working_copy): a
    separable cascade on a grid of rank >= 2 runs in place; any other alternates between its
    output and the copy from two passes on."""
    if separable and len(shape) >= 2:
        return False
    return sum(len(level_passes(shape, 2**i, separable)) for i in range(start, levels)) > 1


def takes_fields(shape: Sequence[int], separable: bool, field_axes) -> bool:
    """Whether :func:`filter_fields` applies: a separable cascade on a grid of rank >= 2 whose
    fields hold their spatial axes first, in order (channels last, as textures and volumes)."""
    lead = tuple(range(len(shape)))
    return separable and len(shape) >= 2 and all(tuple(a) == lead for a in field_axes)


def filter_fields(
    fields: Sequence[jax.Array],
    g: jax.Array,
    valid: jax.Array | None,
    sigma: jax.Array,
    levels: int,
    start: int = 0,
    deeper: Deeper | None = None,
) -> tuple[jax.Array, ...]:
    """The separable cascade on fields in their own layout, ``(*S, ...)`` with the spatial
    axes first (zero where invalid, in the compute dtype), with guide planes ``g`` (G, *S):
    their channels are taken apart and put back inside the call, so no planar copy of the
    fields is made; and :class:`Deeper`'s levels where its flag says so. Returns the
    fields' shapes."""
    _require("the native filter kernel")
    flag, more = _flag(deeper, g.dtype)
    return _fields_cascade(tuple(fields), g, valid, sigma, flag, Span(start, levels, more))


@functools.partial(jax.custom_jvp, nondiff_argnums=(5,))
def _fields_cascade(fields, g, valid, sigma, flag, span):
    # The fields and outputs in their own shapes (the call reads each as (points, c_k) from its
    # element count): a reshape around the call would let XLA pick a layout for the outputs
    # that the code after it then copies back.
    dtype, (start, levels, more) = g.dtype, span
    call = jax.ffi.ffi_call(
        FIELDS_TARGET,
        tuple(jax.ShapeDtypeStruct(f.shape, dtype) for f in fields),
        vmap_method="sequential",
    )
    outs = call(
        g,
        jnp.zeros((0,), dtype) if valid is None else valid.astype(dtype),
        jnp.asarray(sigma, dtype).reshape(()),
        flag,
        *fields,
        levels=np.int64(levels),
        start=np.int64(start),
        has_valid=valid is not None,
        threads=np.int64(threads()),
        **_deeper_attributes(more),
    )
    return tuple(outs)


@_fields_cascade.defjvp
def _fields_cascade_jvp(span, primals, tangents):
    # The plain kernel's derivative, on the fields' planes (the flag is not differentiated).
    flag, (start, levels, more) = primals[4], span

    def pure(fields, g, valid, sigma):
        n = g.ndim - 1
        planes = [jnp.moveaxis(f.reshape(f.shape[:n] + (-1,)), -1, 0) for f in fields]
        x = jnp.concatenate(planes)
        run = lambda s, top: plain.filter_planes(x, g, valid, s, top, True, start)
        y = _pure(run, sigma, levels, flag, more)
        out, at = [], 0
        for f, p in zip(fields, planes):
            out.append(jnp.moveaxis(y[at : at + p.shape[0]], 0, -1).reshape(f.shape))
            at += p.shape[0]
        return tuple(out)

    return jax.jvp(pure, primals[:4], tangents[:4])


@_cascade.defjvp
def _cascade_jvp(separable, span, primals, tangents):
    # The pure-JAX kernel's derivative (and its primal, equal up to float rounding).
    flag, (start, levels, more) = primals[4], span

    def pure(x, g, valid, sigma):
        run = lambda s, top: plain.filter_planes(x, g, valid, s, top, separable, start)
        return _pure(run, sigma, levels, flag, more)

    return jax.jvp(pure, primals[:4], tangents[:4])


def takes_subgrid(x: jax.Array) -> bool:
    """Whether :func:`subgrid_average` runs on ``x``: the extension is loaded, ``x`` is float32
    or float64 and not empty."""
    return available() and x.dtype in (jnp.float32, jnp.float64) and x.size > 0


def subgrid_average(
    x: jax.Array,
    axes: Sequence[int],
    stride: int,
    finite: bool = False,
    run: jax.Array | bool | Entry = True,
) -> jax.Array:
    """One level of the B-spline (every data weight 1) along each of ``axes`` in turn, read at
    every ``stride``-th entry: one FFI call for all of them (csrc/local.h); ``finite``: of
    ``jnp.nan_to_num(x)``, read so without a copy; zeros without any work where ``run`` (a
    bool, may be traced, or an :class:`~optax_bilateral._src.numerics.Entry`) is False. Not
    differentiable:
    :func:`optax_bilateral._src.filter.local.local_average_subgrid` gives it a rule."""
    _require("the native local average")
    shape, sizes = list(x.shape), []
    for a in axes:
        shape[a] = (shape[a] - 1) // stride + 1
        sizes.append(math.prod(shape))
    # The passes between the first and the last alternate between two buffers (local.cc).
    work = sum(sizes[:2]) if len(sizes) > 2 else sum(sizes[:1]) if len(sizes) > 1 else 0
    call = jax.ffi.ffi_call(
        SUBGRID_TARGET,
        (jax.ShapeDtypeStruct(tuple(shape), x.dtype), jax.ShapeDtypeStruct((work,), x.dtype)),
        vmap_method="sequential",
    )
    run = Entry.flag(run)
    out, _ = call(
        x,
        run.vector,
        axes=np.asarray(axes, np.int64),
        stride=np.int64(stride),
        finite=finite,
        run_at=np.int64(run.at),
    )
    return out


def texel_distance_mean(
    a: jax.Array,
    b: jax.Array | None,
    axes: Sequence[int],
    stride: int,
    run: jax.Array | bool | Entry = True,
    keep: bool = False,
    otherwise: Entry | None = None,
    scale: float = 1.0,
) -> Any:
    """``scale`` times the mean over the sub-grid's texels of ``||a[stride p] - b[p]||``
    (csrc/stats.h): one FFI call, sums in double; without any work where ``run`` (a bool, may
    be traced, or an :class:`~optax_bilateral._src.numerics.Entry`) is False, ``otherwise``'s
    value (default 0). ``keep``: ``(mean, a's sub-grid)``, the values the mean read (zeros
    where it does not run). Not differentiable:
    :func:`optax_bilateral._src.filter.local.texel_distance_mean` gives it a rule."""
    _require("the native texel statistics")
    shape = [(n - 1) // stride + 1 if d in axes else n for d, n in enumerate(a.shape)]
    call = jax.ffi.ffi_call(
        TEXEL_MEAN_TARGET,
        (
            jax.ShapeDtypeStruct((), a.dtype),
            jax.ShapeDtypeStruct(tuple(shape) if keep else (0,), a.dtype),
        ),
        vmap_method="sequential",
    )
    run = Entry.flag(run)
    mean, kept = call(
        a,
        jnp.zeros((0,), a.dtype) if b is None else b,
        run.vector,
        jnp.zeros((0,), a.dtype) if otherwise is None else otherwise.vector,
        axes=np.asarray(axes, np.int64),
        stride=np.int64(stride),
        has_b=b is not None,
        run_at=np.int64(run.at),
        keep=keep,
        otherwise_at=np.int64(0 if otherwise is None else otherwise.at),
        scale=np.float64(scale),
    )
    return (mean, kept) if keep else mean


class FromGradient(NamedTuple):
    """The observed texels, read by a native statistic from the gradient as given where it
    reads it (``g``): every channel finite and, with ``drop_zero`` (``mask_unobserved``), not
    all 0, as optimizer/step.py's ``observe`` makes them: XLA writes no mask out for the call."""

    drop_zero: bool


def _mask_operand(observed: jax.Array | FromGradient, ndim: int) -> tuple[jax.Array, bool]:
    """The ``observed`` operand of a statistic's FFI call (an empty one: the mask is read from
    the gradient) and its ``drop_zero`` attribute."""
    if isinstance(observed, FromGradient):
        return jnp.zeros((0,), bool), bool(observed.drop_zero)
    mask = jnp.asarray(observed, bool)
    return mask.reshape((1,) * (ndim - mask.ndim) + mask.shape), False


def correlation_sums(
    g: jax.Array,
    m: jax.Array,
    observed: jax.Array | FromGradient,
    c1: jax.Array | Entry,
    axes: Sequence[int],
    pair_axes: Sequence[int],
    stride: int,
    run: jax.Array | bool | Entry = True,
    limit: float = math.inf,
) -> jax.Array:
    """The correlated-noise check's sums (csrc/stats.h), ``(3 len(pair_axes) + 2,)``, of
    ``z = clip(g, -limit, limit) - m / c1`` and ``y = m / c1`` where ``observed`` (bool,
    broadcastable against ``g``, or :class:`FromGradient`), else 0, each computed where the
    sums read it: one FFI call, sums in double; zeros without any work where ``run`` (a bool,
    may be traced) is False. ``c1`` and ``run`` may be
    :class:`~optax_bilateral._src.numerics.Entry`. Not differentiable (its callers stop the
    gradient)."""
    _require("the native texel statistics")
    if not limit > 0:
        raise ValueError(f"limit must be > 0 (inf: no clip), got {limit!r}")
    call = jax.ffi.ffi_call(
        CORRELATION_TARGET,
        jax.ShapeDtypeStruct((3 * len(pair_axes) + 2,), g.dtype),
        vmap_method="sequential",
    )
    mask, drop_zero = _mask_operand(observed, g.ndim)
    c1 = c1 if isinstance(c1, Entry) else Entry.of(jnp.asarray(c1, g.dtype))
    run = Entry.flag(run)
    return call(
        g,
        m,
        mask,
        c1.vector,
        run.vector,
        axes=np.asarray(axes, np.int64),
        pair_axes=np.asarray(pair_axes, np.int64),
        stride=np.int64(stride),
        limit=np.float64(limit),
        drop_zero=drop_zero,
        c1_at=np.int64(c1.at),
        run_at=np.int64(run.at),
    )


class NoiseTest(NamedTuple):
    """``sigma_d="auto"``'s correlated-noise test from :func:`correlation_sums`' sums: the
    lag-1 correlations' mean at least ``correlated`` and the noise's energy above ``noisy``
    times ``lag**2`` times the signal's; ``stored`` is the answer where the test does not run.
    ``lag`` and ``stored`` are :class:`~optax_bilateral._src.numerics.Entry`."""

    correlated: float
    noisy: float
    lag: Entry
    stored: Entry


def correlated_noise(
    g: jax.Array,
    m: jax.Array,
    observed: jax.Array | FromGradient,
    c1: Entry,
    axes: Sequence[int],
    pair_axes: Sequence[int],
    stride: int,
    run: Entry,
    limit: float,
    test: NoiseTest,
) -> jax.Array:
    """``test``'s answer (1 or 0, in ``g``'s dtype) from :func:`correlation_sums`' sums where
    ``run`` says it is due, else ``test.stored``'s value, without reading anything: one FFI
    call (csrc/module.cc, the test in the float arithmetic of its JAX form, whose
    ``c1`` and ``lag`` are entries of one vector). Not differentiable."""
    _require("the native texel statistics")
    if not limit > 0:
        raise ValueError(f"limit must be > 0 (inf: no clip), got {limit!r}")
    if not pair_axes:
        raise ValueError("the correlated-noise test needs at least one pair axis")
    if c1.vector is not test.lag.vector:
        raise ValueError("c1 and test.lag must be entries of one vector")
    call = jax.ffi.ffi_call(
        NOISE_TEST_TARGET, jax.ShapeDtypeStruct((), g.dtype), vmap_method="sequential"
    )
    mask, drop_zero = _mask_operand(observed, g.ndim)
    return call(
        g,
        m,
        mask,
        c1.vector,
        run.vector,
        test.stored.vector,
        axes=np.asarray(axes, np.int64),
        pair_axes=np.asarray(pair_axes, np.int64),
        stride=np.int64(stride),
        limit=np.float64(limit),
        drop_zero=drop_zero,
        c1_at=np.int64(c1.at),
        run_at=np.int64(run.at),
        lag_at=np.int64(test.lag.at),
        stored_at=np.int64(test.stored.at),
        correlated=np.float64(test.correlated),
        noisy=np.float64(test.noisy),
    )


def blend_weights(
    m: jax.Array,
    v: jax.Array,
    residual: jax.Array,
    scalars: jax.Array,
    axes: Sequence[int],
    stride: int,
    constants: tuple[float, float, float, float],
    run: jax.Array | bool | Entry = True,
) -> tuple[jax.Array, jax.Array]:
    """``sigma_d="auto"``'s blend at the sub-grid (csrc/stats.h): ``(lam * gate, gate)`` from
    ``m``, ``v`` (the leaf's shape), the residual (the sub-grid's), the step's 8 ``scalars``
    and the rule's ``constants`` ``(gain, power, low, high - low)``; zeros without any work
    where ``run`` (a bool, may be traced, or an
    :class:`~optax_bilateral._src.numerics.Entry`) is False. One FFI call; not differentiable:
    :func:`optax_bilateral._src.filter.local.subgrid_blend` gives it a rule."""
    _require("the native texel statistics")
    call = jax.ffi.ffi_call(
        BLEND_TARGET,
        (jax.ShapeDtypeStruct(residual.shape, m.dtype), jax.ShapeDtypeStruct((), m.dtype)),
        vmap_method="sequential",
    )
    gain, power, low, span = (float(c) for c in constants)
    run = Entry.flag(run)
    lam, gate = call(
        m,
        v,
        residual,
        scalars,
        run.vector,
        axes=np.asarray(axes, np.int64),
        stride=np.int64(stride),
        gain=np.float64(gain),
        power=np.float64(power),
        low=np.float64(low),
        span=np.float64(span),
        run_at=np.int64(run.at),
    )
    return lam, gate


class StepCall(NamedTuple):
    """What is fixed about a step norm's call: the sub-grid (every ``stride``-th texel along
    ``axes``), Adam's ``eps`` and ``eps_root``, whether an all-zero texel is unobserved
    (``mask_unobserved``), and the JAX form that is its derivative (:func:`step_norm`)."""

    axes: tuple[int, ...]
    stride: int
    eps: float
    eps_root: float
    drop_zero: bool
    reference: Any


@dataclasses.dataclass(frozen=True)
class StepFlags:
    """What :func:`step_norm` reads besides the step's parts: the step's vector of scalars (its
    one XLA kernel of them, :func:`~optax_bilateral._src.numerics.one_kernel`), which holds
    ``1 / c1``, ``1 / c2`` and whether the blend's statistics were computed at this step, at
    ``inv_c1_at``, ``inv_c2_at`` and ``computed_at``; and ``gate``, the rule's gate before the
    step (a scalar). The blend is taken where computed and the gate is > 0."""

    scalars: jax.Array
    gate: jax.Array
    inv_c1_at: int
    inv_c2_at: int
    computed_at: int

    @classmethod
    def of(cls, inv_c1: Entry, inv_c2: Entry, computed: Entry, gate: jax.Array) -> StepFlags:
        """From three entries of one vector and the gate."""
        if not inv_c1.vector is inv_c2.vector is computed.vector:
            raise ValueError("inv_c1, inv_c2 and computed must be entries of one vector")
        return cls(inv_c1.vector, jnp.asarray(gate), inv_c1.at, inv_c2.at, computed.at)

    @property
    def inv_c1(self) -> Entry:
        return Entry(self.scalars, self.inv_c1_at, self.scalars.dtype)

    @property
    def inv_c2(self) -> Entry:
        return Entry(self.scalars, self.inv_c2_at, self.scalars.dtype)

    @property
    def computed(self) -> Entry:
        return Entry(self.scalars, self.computed_at, jnp.bool_)

    @property
    def blends(self) -> jax.Array:
        """Whether the step takes the blend (computed and the gate open)."""
        return self.computed.value & (self.gate > 0)


jax.tree_util.register_dataclass(
    StepFlags,
    data_fields=["scalars", "gate"],
    meta_fields=["inv_c1_at", "inv_c2_at", "computed_at"],
)


def step_norm(
    m: jax.Array,
    v: jax.Array,
    bm: jax.Array,
    bv: jax.Array,
    grad: jax.Array,
    lam: jax.Array | None,
    flags: StepFlags,
    how: StepCall,
) -> jax.Array:
    """The mean texel norm at the sub-grid (every ``how.stride``-th texel along ``how.axes``)
    of the postfilter's step before its learning rate (csrc/stats.h), computed from its parts
    where the mean reads them: the moments ``m``, ``v``, the filtered ``bm``, ``bv`` and the
    gradient as the leaf received it (one shape and float dtype: a texel is observed where its
    gradient is finite, and with ``how.drop_zero`` not all 0), the blend's weight ``lam`` at
    the sub-grid (None: no blend), with ``flags``' scalars and Adam's ``how.eps``,
    ``how.eps_root``. One FFI call, norms and mean in double; not differentiable:
    :func:`optax_bilateral._src.filter.local.step_norm` gives it a rule."""
    _require("the native texel statistics")
    call = jax.ffi.ffi_call(
        STEP_NORM_TARGET, jax.ShapeDtypeStruct((), m.dtype), vmap_method="sequential"
    )
    return call(
        m,
        v,
        bm,
        bv,
        grad,
        jnp.zeros((0,), m.dtype) if lam is None else lam,
        flags.scalars,
        flags.gate.reshape(1),
        axes=np.asarray(how.axes, np.int64),
        stride=np.int64(how.stride),
        has_lam=lam is not None,
        drop_zero=bool(how.drop_zero),
        inv_c1_at=np.int64(flags.inv_c1_at),
        inv_c2_at=np.int64(flags.inv_c2_at),
        blend_at=np.int64(flags.computed_at),
        gate_at=np.int64(0),
        eps=np.float64(how.eps),
        eps_root=np.float64(how.eps_root),
    )
