"""Properties at the extremes, explored by hypothesis (profile "ci": >= 100 examples).

The data reach what real gradients do: NaN, +-Inf, huge (1e30, the dtype's maximum),
denormal and signed-zero values; sigma_d in {0, 1e-30, 1e30, inf} or anywhere between;
bfloat16, float16, float32 and float64; 1xN grids and 1 to 4 channels. Shapes, dtypes
and static settings come from small lists, so that the examples share a handful of
compiled programs: XLA compiles a new program for each, in seconds on a CPU.
"""

from __future__ import annotations

import contextlib
import functools
import math

import hypothesis.extra.numpy as hnp
import jax
import jax.numpy as jnp
import numpy as np
import optax
from hypothesis import given
from hypothesis import strategies as st

import jax_compat
import optax_bilateral as ob

SIGMAS = st.one_of(st.sampled_from([0.0, 1e-30, 1e30, math.inf]), st.floats(1e-3, 1e3))
EXTREMES = [0.0, -0.0, 1e-40, -1e-40, 1e-310, 1e30, -1e30, 3e38, -3e38, 1e300, -1e300]
GRADIENTS = st.one_of(st.floats(-3, 3), st.sampled_from([*EXTREMES, math.nan, math.inf, -math.inf]))


def _x64(dtype: str):
    """float64 needs JAX's 64-bit mode, for the compile and every call."""
    return jax_compat.enable_x64(True) if dtype == "float64" else contextlib.nullcontext()


def _cast(x: np.ndarray, dtype: str) -> np.ndarray:
    with np.errstate(over="ignore", invalid="ignore"):
        return x.astype(jnp.dtype(dtype))


def _eps(dtype: str) -> float:
    return float(jnp.finfo(jnp.dtype(dtype)).eps)


# ----------------------------------------------------------------------------------------
# The filter: a convex combination of the fields, whatever the guide and sigma_d

# spatial shape, field channels, guide channels, dtype, levels, separable
FILTER_CONFIGS = [
    ((1, 9), 2, 1, "float32", 2, True),
    ((6, 5), 3, 3, "bfloat16", 2, False),
    ((5, 7), 1, 2, "float16", 2, True),
    ((4, 3, 5), 4, 1, "float64", 2, True),
    ((9,), 2, 1, "float32", 3, False),
]


@st.composite
def filter_problems(draw):
    shape, channels, gch, dtype, levels, separable = draw(st.sampled_from(FILTER_CONFIGS))
    big = float(jnp.finfo(jnp.dtype(dtype)).max) / 4  # sums of such values stay finite
    fields = draw(
        hnp.arrays(
            np.float64,
            (*shape, channels),
            elements=st.one_of(
                st.floats(-3, 3), st.sampled_from([0.0, -0.0, 1e-40, -1e-40, 1e-30, big, -big])
            ),
        )
    )
    guide = draw(
        hnp.arrays(
            np.float64,
            (*shape, gch),
            elements=st.one_of(
                st.floats(-3, 3), st.sampled_from([0.0, 1e-40, 1e30, -1e30, 3e38, math.nan])
            ),
        )
    )
    return (
        shape,
        dtype,
        levels,
        separable,
        _cast(fields, dtype),
        guide.astype(np.float32),
        draw(SIGMAS),
    )


@given(problem=filter_problems())
def test_filter_output_is_a_convex_combination_at_the_extremes(problem):
    shape, dtype, levels, separable, x, guide, sigma_d = problem
    axes = tuple(range(len(shape)))
    with _x64(dtype):
        out = np.asarray(
            ob.atrous_bilateral(
                jnp.asarray(x),
                jnp.asarray(guide),
                sigma_d=sigma_d,
                levels=levels,
                spatial_axes=axes,
                separable=separable,
            )
        )
    assert out.dtype == x.dtype and np.all(np.isfinite(out))
    x64, out64 = x.astype(np.float64), out.astype(np.float64)
    # Rounding: sums in float32 (float64 for float64 fields), then the fields' own dtype;
    # XLA's CPU backend may flush denormals to zero.
    tiny = float(jnp.finfo(jnp.dtype(dtype)).tiny)
    for c in range(x.shape[-1]):
        lo, hi, scale = x64[..., c].min(), x64[..., c].max(), np.abs(x64[..., c]).max()
        tol = 8 * max(_eps(dtype), _eps("float32") if dtype != "float64" else 0.0) * scale + tiny
        assert np.all(out64[..., c] >= lo - tol) and np.all(out64[..., c] <= hi + tol)
    # A point whose guide is NaN is nobody's neighbour: it keeps its own value.
    alone = np.any(np.isnan(guide), axis=-1)
    np.testing.assert_allclose(out64[alone], x64[alone], rtol=4 * _eps(dtype), atol=tiny * 4)


# ----------------------------------------------------------------------------------------
# The optimizer: finite, bounded steps; non-finite gradients are unobserved

LR, B1, B2 = 0.1, 0.2, 0.36
# parameter shape (spatial + channels), dtype, separable
UPDATE_CONFIGS = [
    ((1, 9, 1), "float32", True),
    ((6, 5, 3), "bfloat16", True),
    ((5, 6, 2), "float16", False),
    ((4, 5, 4), "float64", True),
]


@functools.cache
def _update(shape, dtype, separable):
    """One compiled update per configuration; sigma_d is traced (set per example)."""

    def postfilter(learning_rate, b1, b2, sigma_d):
        post = ob.postfilter(
            b1, b2, sigma_d=sigma_d, levels=2, separable=separable, spatial_axes=(0, 1)
        )
        return optax.chain(post, optax.scale_by_learning_rate(learning_rate))

    opt = optax.inject_hyperparams(postfilter)(learning_rate=LR, b1=B1, b2=B2, sigma_d=0.3)
    return opt, jax.jit(opt.update)


@st.composite
def update_problems(draw):
    shape, dtype, separable = draw(st.sampled_from(UPDATE_CONFIGS))
    grads = [draw(hnp.arrays(np.float64, shape, elements=GRADIENTS)) for _ in range(2)]
    theta = draw(hnp.arrays(np.float64, shape, elements=st.floats(0.01, 1.0)))
    return (
        shape,
        dtype,
        separable,
        [_cast(g, dtype) for g in grads],
        _cast(theta, dtype),
        draw(SIGMAS),
    )


@given(problem=update_problems())
def test_updates_are_finite_bounded_and_skip_non_finite_texels(problem):
    shape, dtype, separable, grads, theta, sigma_d = problem
    with _x64(dtype):
        opt, update = _update(shape, dtype, separable)
        state = opt.init(jnp.asarray(theta))
        with np.errstate(over="ignore"):  # sigma_d = 1e30 in a float16 hyperparameter is inf
            hyper = {
                k: jnp.asarray(np.asarray(sigma_d if k == "sigma_d" else v, v.dtype))
                for k, v in state.hyperparams.items()
            }
        state = state._replace(hyperparams=hyper)
        for t, g in enumerate(grads, start=1):
            old = state.inner_state[0]
            u, state = update(jnp.asarray(g), state, jnp.asarray(theta))
            u = np.asarray(u, np.float64)
            new = state.inner_state[0]
            mu, nu = np.asarray(new.mu, np.float64), np.asarray(new.nu, np.float64)
            assert np.all(np.isfinite(u)) and np.all(np.isfinite(mu)) and np.all(np.isfinite(nu))
            # A texel with a non-finite gradient in any channel is unobserved: no step, and
            # its moments are kept.
            bad = ~np.all(np.isfinite(g.astype(np.float64)), axis=-1)
            assert np.all(u[bad] == 0)
            np.testing.assert_array_equal(mu[bad], np.asarray(old.mu, np.float64)[bad])
            np.testing.assert_array_equal(nu[bad], np.asarray(old.nu, np.float64)[bad])
            # Supplement 1.3: |step| <= max_k |m_hat_k| / sqrt(v_hat_k) (B is row-stochastic
            # and non-negative; m and v share it). Entries with v = 0 step by m / eps.
            with np.errstate(divide="ignore", invalid="ignore"):
                ratio = np.abs(mu / (1 - B1**t)) / np.sqrt(nu / (1 - B2**t))
            ratio = ratio[np.isfinite(ratio)]
            if ratio.size and np.all(nu > 0):
                # The moments are stored in the parameters' dtype: a few of its ulps.
                assert np.abs(u).max() <= LR * ratio.max() * (1 + 16 * _eps(dtype)) + 1e-30
