"""Argument checks shared by the filter and the transforms.

Every check raises as early as the value can be seen: a concrete value at
construction, a shape at ``init`` or at trace time. A traced value cannot raise;
those are handled by the numerics policies (:mod:`optax_bilateral._src.numerics`).
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Sequence
from typing import Any, cast

import jax
import jax.core
import jax.numpy as jnp
import numpy as np


def is_concrete(x: Any) -> bool:
    """True if ``x`` holds a known value now (not a tracer under jit/grad/vmap)."""
    if isinstance(x, jax.core.Tracer):
        return False
    try:
        np.asarray(x)
    except (jax.errors.TracerArrayConversionError, jax.errors.ConcretizationTypeError):
        return False
    return True


def check_sigma_d(sigma_d: Any, name: str = "sigma_d", *, names: Sequence[str] = ()) -> None:
    """Raises if a concrete ``sigma_d`` is negative, NaN or not a real scalar, and is not one
    of the shorthands ``names`` (e.g. "auto")."""
    listed = " or ".join(map(repr, names))
    if names and isinstance(sigma_d, str):
        if sigma_d not in names:
            raise ValueError(f"{name} must be a number >= 0, {listed}, got {sigma_d!r}")
        return
    if isinstance(sigma_d, bool) or not (
        isinstance(sigma_d, numbers.Real) or hasattr(sigma_d, "dtype")
    ):
        also = f", {listed}" if names else ""
        raise TypeError(f"{name} must be a real scalar (float, inf allowed){also}, got {sigma_d!r}")
    sigma_d = cast(Any, sigma_d)  # a number or an array: told apart by attribute below
    if hasattr(sigma_d, "shape") and np.shape(sigma_d) != ():
        raise ValueError(f"{name} must be a scalar, got an array of shape {np.shape(sigma_d)}")
    if hasattr(sigma_d, "dtype") and not jnp.issubdtype(sigma_d.dtype, jnp.number):
        raise TypeError(f"{name} must be a real number, got dtype {sigma_d.dtype}")
    if is_concrete(sigma_d):
        value = float(np.asarray(sigma_d))
        if math.isnan(value) or value < 0:
            raise ValueError(
                f"{name} must be >= 0 (0 keeps only equal-guide neighbours, "
                f"inf is a plain low-pass), got {value}"
            )


def check_levels(levels: Any, name: str = "levels") -> int:
    """Returns ``levels`` as a Python int, or raises a clear error."""
    if hasattr(levels, "shape") and not is_concrete(levels):
        raise TypeError(
            f"{name} is static (it sets how many passes are compiled) but got a traced value. "
            "With optax.inject_hyperparams, pass static_args=('levels',)."
        )
    if isinstance(levels, bool) or not isinstance(
        levels, (numbers.Integral, np.ndarray, jax.Array)
    ):
        raise TypeError(
            f"{name} must be a non-negative int (the number of a-trous levels F), got {levels!r}"
        )
    levels = cast(Any, levels)  # an int or an array: told apart by attribute below
    if hasattr(levels, "dtype") and (
        np.shape(levels) != () or not jnp.issubdtype(levels.dtype, jnp.integer)
    ):
        raise TypeError(f"{name} must be a non-negative int scalar, got {levels!r}")
    levels = int(levels)
    if levels < 0:
        raise ValueError(f"{name} must be >= 0 (0 is the identity), got {levels}")
    return levels


def normalize_axes(spatial_axes: Any, ndim: int, name: str = "spatial_axes") -> tuple[int, ...]:
    """Validates ``spatial_axes`` against an array of rank ``ndim``; returns non-negative axes."""
    if isinstance(spatial_axes, numbers.Integral) and not isinstance(spatial_axes, bool):
        spatial_axes = (spatial_axes,)
    if not isinstance(spatial_axes, (tuple, list)) or not all(
        isinstance(a, numbers.Integral) and not isinstance(a, bool) for a in spatial_axes
    ):
        raise TypeError(f"{name} must be a tuple of ints, got {spatial_axes!r}")
    out = []
    for a in spatial_axes:
        if not -ndim <= a < ndim:
            raise ValueError(
                f"{name}={tuple(spatial_axes)} is out of range for an array "
                f"with {ndim} dimension(s)"
            )
        out.append(int(a) % ndim)
    if len(set(out)) != len(out):
        raise ValueError(f"{name}={tuple(spatial_axes)} repeats an axis")
    return tuple(out)


def _real(x: Any, name: str) -> float:
    """A concrete ``x`` as a float, or a TypeError naming ``name`` (a string, a list, an array
    of more than one value)."""
    if isinstance(x, (str, bytes)):
        raise TypeError(f"{name} must be a real number, got {x!r}")
    try:
        return float(np.asarray(x))
    except (TypeError, ValueError) as e:
        raise TypeError(f"{name} must be a real number, got {x!r}") from e


def check_decay(x: Any, name: str) -> None:
    """Raises for a concrete decay rate outside [0, 1)."""
    if x is None or not is_concrete(x):
        return
    v = _real(x, name)
    if not 0.0 <= v < 1.0:
        raise ValueError(f"{name} must be in [0, 1), got {v}")


def check_nonnegative(x: Any, name: str, *, finite: bool = False) -> None:
    """Raises for a concrete value that is negative or NaN (with ``finite``, or infinite)."""
    if x is None or not is_concrete(x):
        return
    v = _real(x, name)
    if not v >= 0.0 or (finite and math.isinf(v)):
        raise ValueError(f"{name} must be {'finite and ' if finite else ''}>= 0, got {v}")


def check_positive(x: Any, name: str, why: str = "") -> None:
    """Raises for a concrete value that is not > 0 (NaN included); ``why`` ends the message."""
    if x is None or not is_concrete(x):
        return
    v = _real(x, name)
    if not v > 0.0:
        raise ValueError(f"{name} must be > 0{f' ({why})' if why else ''}, got {v}")


def check_choice(value: Any, name: str, choices: tuple) -> None:
    """Raises unless ``value`` is one of ``choices``."""
    if not isinstance(value, str) or value not in choices:
        raise ValueError(f"{name} must be one of {choices}, got {value!r}")


def check_mu_dtype(mu_dtype: Any) -> jnp.dtype | None:
    """``mu_dtype`` as a floating dtype, or None."""
    if mu_dtype is None:
        return None
    try:
        dt = jnp.dtype(mu_dtype)
    except TypeError:
        raise TypeError(
            f"mu_dtype must be a floating dtype (e.g. jnp.float32) or None, got {mu_dtype!r}"
        ) from None
    if not jnp.issubdtype(dt, jnp.floating):
        raise TypeError(f"mu_dtype must be a floating dtype (e.g. jnp.float32) or None, got {dt}")
    return dt


def is_zero(x: Any) -> bool:
    """True for a concrete value equal to 0 (a traced one may be anything)."""
    return x is not None and is_concrete(x) and float(np.asarray(x)) == 0.0


SECOND_MOMENTS = ("elementwise", "uniform")


def check_second_moment(second_moment: Any) -> None:
    if second_moment not in SECOND_MOMENTS:
        raise ValueError(f"second_moment must be one of {SECOND_MOMENTS}, got {second_moment!r}")


def check_bool(x: Any, name: str) -> bool:
    """``x`` if it is a bool (NumPy's included), else a TypeError naming ``name``."""
    if not isinstance(x, (bool, np.bool_)):
        raise TypeError(f"{name} must be True or False, got {x!r}")
    return bool(x)


def check_number(owner: Any, name: str, *, low=None, high=None, low_open=False, high_open=False):
    """Raises unless ``owner.name`` is a real number in the range (``*_open``: excluded)."""
    x = getattr(owner, name)
    if isinstance(x, bool) or not isinstance(x, numbers.Real) or math.isnan(x):
        raise TypeError(f"{name} must be a real number, got {x!r}")
    too_low = low is not None and (x <= low if low_open else x < low)
    too_high = high is not None and (x >= high if high_open else x > high)
    if too_low or too_high:
        lo = "" if low is None else f"{'>' if low_open else '>='} {low}"
        hi = "" if high is None else f"{'<' if high_open else '<='} {high}"
        raise ValueError(f"{name} must be {' and '.join(p for p in (lo, hi) if p)}, got {x}")


def check_integer(owner: Any, name: str, *, low: int):
    """Raises unless ``owner.name`` is an int >= ``low``."""
    x = getattr(owner, name)
    if isinstance(x, bool) or not isinstance(x, numbers.Integral):
        raise TypeError(f"{name} must be an int, got {x!r}")
    if x < low:
        raise ValueError(f"{name} must be >= {low}, got {x}")


def check_learning_rate(learning_rate: Any) -> None:
    """Raises unless ``learning_rate`` is a schedule (a callable of the step count) or a real
    scalar >= 0 (a traced one is taken as it is)."""
    if callable(learning_rate):
        return
    if isinstance(learning_rate, (bool, str, bytes)) or not (
        isinstance(learning_rate, numbers.Real) or hasattr(learning_rate, "dtype")
    ):
        raise TypeError(
            "learning_rate must be a number >= 0 or an optax schedule (a callable of the step "
            f"count), got {learning_rate!r}"
        )
    shape = np.shape(cast(Any, learning_rate))
    if shape != ():
        raise ValueError(f"learning_rate must be a scalar, got an array of shape {shape}")
    if not jnp.issubdtype(jnp.result_type(learning_rate), jnp.number) or jnp.issubdtype(
        jnp.result_type(learning_rate), jnp.complexfloating
    ):
        raise TypeError(f"learning_rate must be a real number, got {learning_rate!r}")
    check_nonnegative(learning_rate, "learning_rate")
