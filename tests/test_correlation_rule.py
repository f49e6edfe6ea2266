"""``experiments.correlation_rule``'s candidate (docs/auto_sigma.md, "Correlated gradient
noise"): its statistic, and that it runs the library's ``auto`` or the heavier filter."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import optax_bilateral as ob
from experiments import correlation_rule as cr
from experiments import scenes as sc
from optax_bilateral._src import auto

AXES = (0, 1)


def _blurred(x: np.ndarray, sigma: float) -> np.ndarray:
    """``x`` blurred along its first two axes by a Gaussian of ``sigma`` texels (periodic)."""
    k = np.exp(-0.5 * (np.arange(-8, 9) / sigma) ** 2)
    k /= k.sum()
    for a in AXES:
        x = sum(w * np.roll(x, s, axis=a) for s, w in zip(range(-8, 9), k))
    return x


def _noise(shape, sigma=0.0, seed=0):
    x = np.random.default_rng(seed).normal(size=shape)
    return jnp.asarray(_blurred(x, sigma) if sigma else x, jnp.float32)


@pytest.mark.parametrize("scale", [1e-3, 1.0, 1e3])
def test_white_noise_is_uncorrelated_and_blurred_noise_is_correlated(scale):
    zero = jnp.zeros((64, 64, 3))
    count = jnp.asarray(0)
    white = cr.noise_correlation(scale * _noise((64, 64, 3)), zero, count, AXES)
    blurred = cr.noise_correlation(scale * _noise((64, 64, 3), 1.5), zero, count, AXES)
    assert abs(float(white)) < 0.05
    # Gaussian-correlated noise of width sqrt(2) * 1.5: lag-1 correlation exp(-1 / (4 * 2.25))
    assert float(blurred) == pytest.approx(np.exp(-1 / 9), abs=0.03)
    assert float(blurred) >= cr.THRESHOLD


def test_a_gradient_without_noise_gives_zero_not_nan():
    zero = jnp.zeros((16, 16))
    assert float(cr.noise_correlation(zero, zero, jnp.asarray(3), AXES)) == 0.0


@pytest.mark.parametrize(("name", "correlated"), [("deblur", True), ("texture", False)])
def test_the_suites_deconvolution_noise_is_correlated_and_the_textures_is_not(name, correlated):
    """``g_2 - g_1`` (the statistic at the second step, ``m_hat = g_1``) at the quick scene's
    start: deblurring's gradient is a transposed blur of a sparse residual."""
    scene = sc.make(name, quick=True)
    g1, g2 = (scene.grad(scene.data, scene.init, jax.random.key(k)) for k in range(2))
    m = (1 - cr.B1) * g1
    c = cr.noise_correlation(g2, m, jnp.asarray(1), scene.spatial_axes)
    assert (float(c) >= cr.THRESHOLD) == correlated


def _run(opt, grads, x):
    state, p, update = opt.init(x), x, jax.jit(opt.update)
    for g in grads:
        u, state = update(g, state, p)
        p = p + u
    return p, state


def _library(levels, **constants):
    """``bilateral_adam(0.01, levels=levels)`` traced with ``auto``'s constants set."""
    opt = ob.bilateral_adam(0.01, levels=levels, spatial_axes=AXES)
    return cr.with_constants(lambda: _run(opt, _GRADS[levels], _X), **constants)()


_X = jnp.asarray(np.random.default_rng(2).uniform(0.2, 0.8, (48, 48)), jnp.float32)
_GRADS = {
    3: [_noise(_X.shape, seed=s) for s in range(3)],  # white: the library's auto
    4: [_noise(_X.shape, 1.5, seed=s) for s in range(3)],  # correlated: the heavy filter
}


@pytest.mark.parametrize("levels", [3, 4])
def test_candidate_runs_the_library_or_the_heavier_filter_and_restores_auto(levels):
    heavy = levels == 4
    p, state = _run(cr.factory(0.01, AXES), _GRADS[levels], _X)
    assert bool(state.correlated) == heavy
    constants = dict(RATE_FACTOR=cr.FACTOR, GATE=(2.0, 3.0)) if heavy else {}
    expected, _ = _library(levels, **constants)
    np.testing.assert_allclose(p, expected, atol=1e-6)
    assert auto.RATE_FACTOR == 1.0 and auto.GATE == (0.5, 0.65)
