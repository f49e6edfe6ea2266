"""Numerical policies of the transforms, in one place (docs/robustness.md).

* Bias correction ``1 - b^t`` keeps its digits for ``b`` within ``2^-14`` of 1.
* Gradients are clipped before the moment update so that ``m`` and ``v = g^2`` fit
  their dtypes (:func:`moment_limit`), and before the prefilter so that its sums cannot
  overflow (:func:`prefilter_limit`).
* A zero denominator gives a zero step, with finite derivatives (:func:`safe_step`).
* A traced ``sigma_d`` that is negative or NaN makes the update NaN (:func:`sigma_guard`).
* Non-finite gradient entries are counted per leaf (:func:`count_nonfinite`).
* A kernel can be made to run after a value it does not read (:func:`after`): the postfilter's
  step after its rule's read, so that it may write its output over what it reads.

The step counter uses :func:`optax.safe_increment`.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from optax_bilateral._src import extension
from optax_bilateral._src.validation import is_concrete

# Below this 1 - b, float32 keeps fewer than 10 bits of 1 - b in b itself.
NEAR_ONE = 2.0**-14


def zeros(x: Any, dtype: Any = None) -> jax.Array:
    """Zeros like ``x`` (its shape and sharding) in ``dtype`` (``x``'s by default), never
    weakly typed: a state made of them keeps its types through the first update (one
    compile, not two)."""
    return jnp.zeros_like(x, dtype=dtype or jnp.result_type(x))


def one_minus(b: Any) -> Any:
    """``1 - b``, in float64 when ``b`` is a concrete number (keeps its digits for b near 1)."""
    if is_concrete(b):
        return float(1.0 - np.float64(np.asarray(b)))
    return 1 - b


def bias_correction(b: Any, count: jax.Array) -> jax.Array:
    """Adam's ``1 - b^t``.

    Written as optax writes it, except for ``b`` within ``2^-14`` of 1: there
    ``-expm1(t log1p(-(1 - b)))``, which keeps its digits (``1 - b^t`` has an
    absolute error of float32's eps, 3% of ``1 - b`` at ``b = 0.999999``). For a
    concrete ``b``, ``1 - b`` is taken in float64, so ``b`` that rounds to 1 in
    float32 still works (``1 - b^t`` would be 0 and the step 0/0); a traced ``b``
    has float32's precision, so pass such ``b`` as a number, not a hyperparameter.
    """
    # Compiled once per b: eagerly, `b ** count` of a concrete count compiles per count.
    if is_concrete(b):
        return _bias_correction_const(count, b=float(np.asarray(b)))
    return _bias_correction_traced(count, b)


def _bias_correction(count, b):
    t = count.astype(jnp.float32)
    a = one_minus(b)
    if is_concrete(b):
        if a < NEAR_ONE:
            return -jnp.expm1(t * jnp.log1p(jnp.float32(-a)))
        return 1 - b**count
    # Traced b: choose at run time; the unused branch gets a safe a (finite derivatives).
    near = a < NEAR_ONE
    exact = -jnp.expm1(t * jnp.log1p(-jnp.where(near, a, 0)))
    return jnp.where(near, exact, 1 - b**count)


_bias_correction_const = jax.jit(_bias_correction, static_argnames=("b",), inline=True)
_bias_correction_traced = jax.jit(_bias_correction, inline=True)


def moment_limit(
    grad_dtype: Any, compute_dtype: Any, mu_dtype: Any = None, nu_dtype: Any = None
) -> float:
    """Largest |g| the moment update accepts: ``g^2 <= max/2`` where ``v`` is stored and
    computed, ``|g| <= max/2`` where ``m`` is, and finite in ``g``'s own dtype (so that the
    check ``|g| <= limit`` also rejects inf). Without moment buffers (memoryless), the
    compute dtype alone."""
    if nu_dtype is None:
        limits = [math.sqrt(float(jnp.finfo(compute_dtype).max) / 2)]
    else:
        limits = [math.sqrt(float(jnp.finfo(nu_dtype).max) / 2)]
        limits += [float(jnp.finfo(d).max) / 2 for d in (mu_dtype, compute_dtype)]
    return min(min(limits), float(jnp.finfo(grad_dtype).max))


def prefilter_limit(grad_dtype: Any) -> float:
    """Largest |g| the prefilter accepts: ``|A g| <= max |g|`` in exact arithmetic, and the
    margin of 4 keeps the float sums finite too."""
    return min(
        float(jnp.finfo(jnp.promote_types(grad_dtype, jnp.float32)).max) / 4,
        float(jnp.finfo(grad_dtype).max),
    )


def safe_step(
    m_f: jax.Array, v_f: jax.Array, inv_c1: jax.Array, inv_c2: jax.Array, eps: Any, eps_root: Any
) -> jax.Array:
    """``(m_f/c1) / (sqrt(v_f/c2 + eps_root) + eps)``, with 0 where the denominator is 0;
    ``inv_c1``, ``inv_c2``: the bias corrections' reciprocals ``1 / c1``, ``1 / c2``.

    Same values as the plain expression wherever that is finite. ``sqrt`` gets
    derivative 0 at 0: ``B v = 0`` means no gradient reached the footprint, which
    stays so under small changes of the hyperparameters (true derivative 0),
    and ``sqrt'(0) = inf`` times a zero cotangent would make meta-gradients NaN.
    The bias corrections divide as a multiplication by their reciprocals, taken by the
    caller: left to XLA, the rounding of ``m / c1 / den`` depends on the program around it.
    """
    v_hat = v_f * inv_c2.astype(v_f.dtype) + eps_root
    pos = v_hat > 0
    den = jnp.where(pos, jnp.sqrt(jnp.where(pos, v_hat, 1)), 0) + eps
    ok = den > 0
    return jnp.where(ok, (m_f * inv_c1.astype(m_f.dtype)) / jnp.where(ok, den, 1), 0)


def masked_step(m_f, v_f, inv_c1, inv_c2, eps, eps_root, observed) -> jax.Array:
    """:func:`safe_step` where ``observed`` (broadcastable), else 0: the step at the entries
    whose gradient it uses (supplement eq. 10)."""
    return jnp.where(observed, safe_step(m_f, v_f, inv_c1, inv_c2, eps, eps_root), 0)


@dataclasses.dataclass(frozen=True)
class Entry:
    """Entry ``at`` of ``vector``: a scalar of ``dtype`` computed with others in one XLA
    kernel (:func:`one_kernel`). JAX code reads :attr:`value`; a native call reads the vector
    itself at ``at`` (csrc/module.cc), which XLA then computes once rather than as an operand
    of its own."""

    vector: jax.Array
    at: int
    dtype: Any

    @property
    def value(self) -> jax.Array:
        x = jax.lax.index_in_dim(self.vector, self.at, keepdims=False)
        return x != 0 if self.dtype == jnp.bool_ else x.astype(self.dtype)

    @classmethod
    def of(cls, x: Any) -> Entry:
        """``x`` (an :class:`Entry`, or a scalar: the one entry of its own vector)."""
        if isinstance(x, Entry):
            return x
        x = jnp.asarray(x)
        return cls(x.reshape(1), 0, x.dtype)

    @classmethod
    def flag(cls, x: Any) -> Entry:
        """A native call's ``run`` flag: ``x`` (an :class:`Entry`, read as nonzero) or
        ``bool(x)`` as the one entry of its own vector."""
        return x if isinstance(x, Entry) else cls.of(jnp.asarray(x, bool))


jax.tree_util.register_dataclass(Entry, data_fields=["vector"], meta_fields=["at", "dtype"])


def value(x: Any) -> Any:
    """``x``'s value: an :class:`Entry`'s, or ``x`` itself."""
    return x.value if isinstance(x, Entry) else x


# XLA's CPU backend fuses a concatenate of at most this many operands.
ONE_KERNEL_MAX = 8


def one_kernel(tree: Any) -> Any:
    """``tree``'s scalars (floats or bools, at most 8) as :class:`Entry` of one vector that
    XLA computes in one kernel.

    XLA writes out every scalar that an FFI call, a conditional or several full-size kernels
    read as a kernel of its own, and compiles each in milliseconds whatever it computes
    (docs/research/compilation.md). Stacked in their widest dtype (bools as 0 and 1, which
    every float holds exactly) behind an optimization barrier, which keeps XLA from taking the
    vector apart again, they are one kernel (of a longer concatenate, XLA's CPU backend
    computes each operand in a kernel of its own).
    """
    xs, treedef = jax.tree.flatten(tree)
    xs = [jnp.asarray(x) for x in xs]
    for x in xs:
        if x.shape or not (jnp.issubdtype(x.dtype, jnp.floating) or x.dtype == jnp.bool_):
            raise TypeError(f"one_kernel takes float and bool scalars, got {x.dtype}{x.shape}")
    if not 0 < len(xs) <= ONE_KERNEL_MAX:
        raise ValueError(f"one_kernel takes 1 to {ONE_KERNEL_MAX} scalars, got {len(xs)}")
    dtype = jnp.result_type(*(x.dtype for x in xs if x.dtype != jnp.bool_), jnp.float32)
    vector = jax.lax.optimization_barrier(jnp.stack([x.astype(dtype) for x in xs]))
    return jax.tree.unflatten(treedef, [Entry(vector, k, x.dtype) for k, x in enumerate(xs)])


def sigma_guard(sigma_d: Any) -> jax.Array:
    """1 for a valid sigma_d, NaN for a negative or NaN one (traced values cannot raise)."""
    s = jnp.asarray(sigma_d, jnp.float32)
    return jnp.where((s >= 0), 1.0, jnp.nan)


COUNT_TARGET = "optax_bilateral_count_nonfinite"
# The dtypes the native count reads (csrc/count.h): IEEE formats, by their exponent bits.
_NATIVE_COUNT_DTYPES = frozenset(
    map(jnp.dtype, ("float16", "bfloat16", "float32", "float64", "complex64", "complex128"))
)


def count_nonfinite(
    xs: Sequence[jax.Array], totals: Sequence[jax.Array] | None = None
) -> list[jax.Array]:
    """Each array's number of non-finite entries (NaN, +-inf; a complex entry once), as int32,
    or with ``totals`` (int32 scalars, one per array) that number added to its total,
    saturating at int32's maximum; not differentiated.

    On the CPU with the native extension loaded, one XLA FFI call counts them all and adds
    them to their totals (csrc/count.h): an XLA reduction per array compiles in about half of
    ``optax.adam``'s whole update and keeps an int32 copy of the array, and each sum would be
    an XLA kernel of its own. Elsewhere, and for other dtypes or arrays split over an explicit
    mesh, ``jnp.sum``.
    """
    added: list[jax.Array | None] = [None] * len(xs) if totals is None else list(totals)
    if len(added) != len(xs):
        raise ValueError(f"count_nonfinite takes one total per array, got {len(added)}")
    native = [_counts_natively(x) for x in xs]
    picked = [(x, t) for x, t, n in zip(xs, added, native) if n]
    counts = iter(_native_counts([x for x, _ in picked], [t for _, t in picked]))
    out = []
    for x, total, n in zip(xs, added, native):
        if n:
            out.append(next(counts))
            continue
        count = jnp.sum(~jnp.isfinite(x), dtype=jnp.int32)
        top = jnp.iinfo(jnp.int32).max
        out.append(count if total is None else jnp.where(total > top - count, top, total + count))
    return out


def _counts_natively(x: jax.Array) -> bool:
    return x.size > 0 and x.dtype in _NATIVE_COUNT_DTYPES and _native_cpu(x)


def _native_cpu(x: jax.Array) -> bool:
    """Whether an FFI call of this extension can take ``x``: on the CPU, not split over a mesh."""
    if jax.default_backend() != "cpu":
        return False
    try:  # a mesh in the type (explicit, or inside shard_map): no rule splits the FFI call
        mesh = getattr(jax.typeof(x).sharding, "mesh", None)
    except (TypeError, AttributeError):
        mesh = None
    return (mesh is None or mesh.empty) and extension.registered()[0]


def _native_counts(xs: list[jax.Array], totals: list) -> tuple[jax.Array, ...]:
    if not xs:
        return ()
    with_totals = totals[0] is not None
    call = jax.ffi.ffi_call(
        COUNT_TARGET,
        tuple(jax.ShapeDtypeStruct((), jnp.int32) for _ in xs),
        vmap_method="broadcast_all",  # a batch's counts: one block of its operand each
    )
    operands = [jax.lax.stop_gradient(x) for x in xs]
    if with_totals:
        operands += [jnp.asarray(t, jnp.int32).reshape(()) for t in totals]
    return tuple(call(*operands, totals=with_totals))


AFTER_TARGET = "optax_bilateral_after"


def after(arrays: tuple[jax.Array, ...], tokens: Any) -> tuple[jax.Array, ...]:
    """``arrays`` as they are, read after ``tokens`` (a pytree; its leaves that are not JAX
    arrays, such as Python numbers, have no producer to wait for) are computed.

    XLA orders kernels by data alone, and its CPU pipeline drops ``lax.optimization_barrier``
    before it schedules. On the CPU with the native extension loaded, one FFI call that does
    nothing passes the arrays through (its outputs aliased to them, so nothing is copied) with
    the tokens as operands: a kernel that reads its outputs runs after the tokens' producers,
    and may write over an array it reads last. Elsewhere, ``arrays``. Its derivative is the
    identity's.
    """
    leaves = tuple(x for x in jax.tree.leaves(tokens) if isinstance(x, jax.Array))
    if not arrays or not leaves or not all(map(_native_cpu, arrays + leaves)):
        return arrays
    return _after(arrays, leaves)


def materialize(arrays: tuple[jax.Array, ...]) -> tuple[jax.Array, ...]:
    """``arrays`` as they are, each computed once into a buffer of its own.

    XLA's CPU fusion copies a cheap producer into every consumer: a pyramid's level, built
    from the finer level by slices and sums, is then recomputed inside each coarser level and
    inside each of Adam's reads of it. On the CPU with the native extension loaded, the
    pass-through call of :func:`after` (no tokens) is a boundary no fusion crosses. Elsewhere,
    ``arrays``. Its derivative is the identity's (``jax.grad``, ``jax.vjp``, ``jax.jacfwd``);
    ``jax.linear_transpose``, which reads no custom derivative, cannot pass the call.
    """
    if not arrays or not all(map(_native_cpu, arrays)):
        return arrays
    return _after(arrays, ())


@jax.custom_jvp
def _after(arrays: tuple[jax.Array, ...], tokens: tuple[jax.Array, ...]) -> tuple:
    call = jax.ffi.ffi_call(
        AFTER_TARGET,
        tuple(jax.ShapeDtypeStruct(x.shape, x.dtype) for x in arrays),
        vmap_method="broadcast_all",
        input_output_aliases={k: k for k in range(len(arrays))},
    )
    return tuple(call(*arrays, *tokens))


@_after.defjvp
def _after_jvp(primals, tangents):
    return _after(*primals), tangents[0]
