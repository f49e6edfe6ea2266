"""The single-device kernels: the plain and native kernels decide every extreme as the CPU
kernel does, and ``kernel="auto"`` / ``$OPTAX_BILATERAL_KERNEL`` choose between them. (All three
are checked against the float64 reference in test_atrous.py.)"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from optax_bilateral import atrous_bilateral

RTOL = 1e-5


@pytest.mark.parametrize("separable", [True, False])
# 2-D only: a full 3-D pass compiles for minutes on the CPU kernel (its 3-D paths are
# checked against the reference in test_atrous.py).
@pytest.mark.parametrize("shape", [(6, 7)])
def test_plain_kernel_equals_the_cpu_kernel_at_extremes(shape, separable):
    # Non-finite and huge entries, a NaN guide texel, a mask, and the self-guided filter:
    # the two kernels decide every case the same way (up to float rounding).
    rng = np.random.default_rng(3)
    x = rng.normal(size=shape + (2,)).astype(np.float32)
    x.flat[[1, 5, 9]] = [np.inf, -1e30, np.nan]
    g = rng.normal(size=shape + (3,)).astype(np.float32)
    g.flat[7] = np.nan
    g.flat[11] = 3e38
    mask = jnp.asarray(rng.random(shape) > 0.2)
    axes = tuple(range(len(shape)))
    for guide, m, sigma in ((g, None, 0.5), (g, mask, 0.0), (g, mask, np.inf), ("self", mask, 0.5)):
        out = {
            k: atrous_bilateral(
                jnp.asarray(x),
                guide if isinstance(guide, str) else jnp.asarray(guide),
                sigma_d=sigma,
                levels=2,
                spatial_axes=axes,
                separable=separable,
                mask=m,
                guide_axes=None if isinstance(guide, str) else axes,
                kernel=k,
            )
            for k in ("native", "xla_cpu", "plain")
        }
        np.testing.assert_allclose(out["plain"], out["xla_cpu"], rtol=RTOL, atol=1e-6)
        np.testing.assert_allclose(out["native"], out["xla_cpu"], rtol=RTOL, atol=1e-6)


def test_kernel_choice(monkeypatch):
    from optax_bilateral._src.filter.front import KERNEL_ENV, resolve_kernel

    monkeypatch.delenv(KERNEL_ENV, raising=False)
    assert resolve_kernel("auto") == ("native" if jax.default_backend() == "cpu" else "plain")
    assert resolve_kernel("plain") == "plain"
    monkeypatch.setenv(KERNEL_ENV, "plain")
    assert resolve_kernel("auto") == "plain"
    assert resolve_kernel("xla_cpu") == "xla_cpu"  # an explicit choice wins
    assert resolve_kernel("native") == "native"
    monkeypatch.setenv(KERNEL_ENV, "cuda")
    with pytest.raises(ValueError, match=KERNEL_ENV):
        resolve_kernel("auto")
    x = jnp.ones((4, 4))
    with pytest.raises(ValueError, match="kernel must be"):
        atrous_bilateral(x, x, sigma_d=1.0, levels=1, spatial_axes=(0, 1), kernel="gpu")


@pytest.mark.parametrize("kernel", ["native", "xla_cpu", "plain"])
def test_an_empty_grid_is_returned_as_it_is(kernel):
    # No point to filter: every kernel returns the (empty) fields, with their shapes and dtypes
    # (the planar layout divided by the empty spatial size before).
    x = jnp.zeros((0, 5, 2), jnp.bfloat16)
    y = atrous_bilateral(
        x, jnp.zeros((0, 5)), sigma_d=0.5, levels=3, spatial_axes=(0, 1), kernel=kernel
    )
    assert y.shape == x.shape and y.dtype == x.dtype
