"""Laplacian-pyramid parameterisation (Weier et al. 2025): the operator, its transpose, the
transform."""

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

import optax_bilateral as ob
from optax_bilateral._src.optimizer import pyramid as pyr

SHAPES = [((16, 1), (0, 1)), ((13, 10, 3), (0, 1)), ((9, 8), (0, 1)), ((6, 5, 7, 2), (0, 1, 2))]


def upsample_matrix(n_fine: int) -> np.ndarray:
    """Independent reference for one axis: linear interpolation on cell centres.

    Fine sample j sits at coarse coordinate (j + 1/2) / 2 - 1/2; its value
    interpolates the two nearest coarse samples, clamped to the coarse grid.
    """
    m = -(-n_fine // 2)
    u = np.zeros((n_fine, m))
    for j in range(n_fine):
        x = (j + 0.5) / 2 - 0.5
        lo = int(np.floor(x))
        t = x - lo
        for k, w in ((lo, 1 - t), (lo + 1, t)):
            u[j, min(max(k, 0), m - 1)] += w
    return u


def reference_reconstruct(coeffs, axes):
    """c_0 + U(c_1 + U(...)) with dense per-axis matrices (float64)."""
    out = np.asarray(coeffs[-1], np.float64)
    for c in reversed(coeffs[:-1]):
        for a in axes:
            out = np.moveaxis(
                np.tensordot(upsample_matrix(c.shape[a]), np.moveaxis(out, a, 0), axes=1), 0, a
            )
        out = np.asarray(c, np.float64) + out
    return out


def random_coeffs(shape, levels, axes, seed=0):
    rng = np.random.default_rng(seed)
    return [
        rng.standard_normal(s).astype(np.float32) for s in pyr.level_shapes(shape, levels, axes)
    ]


@pytest.mark.parametrize("shape,axes", SHAPES)
def test_reconstruct_matches_dense_interpolation(shape, axes):
    coeffs = random_coeffs(shape, 4, axes)
    got = np.asarray(pyr.pyramid_reconstruct([jnp.asarray(c) for c in coeffs], axes))
    # float32 sums of 4 levels of O(1) values: a few ulps of O(1).
    np.testing.assert_allclose(got, reference_reconstruct(coeffs, axes), atol=1e-5)


@pytest.mark.parametrize("shape,axes", SHAPES)
def test_transpose_is_the_adjoint(shape, axes):
    coeffs = random_coeffs(shape, 4, axes, seed=1)
    g = np.random.default_rng(2).standard_normal(shape).astype(np.float32)
    lhs = float(np.vdot(reference_reconstruct(coeffs, axes), g))
    rhs = sum(
        float(np.vdot(c, t)) for c, t in zip(coeffs, pyr.pyramid_transpose(jnp.asarray(g), 4, axes))
    )
    # Sums of ~1e3 float32 products of O(1) numbers: relative 1e-5.
    assert rhs == pytest.approx(lhs, rel=1e-5, abs=1e-4)


def test_level_shapes_halve_with_ceiling():
    assert pyr.level_shapes((13, 10, 3), 4, (0, 1)) == [
        (13, 10, 3),
        (7, 5, 3),
        (4, 3, 3),
        (2, 2, 3),
    ]


def test_one_level_is_adam():
    rng = np.random.default_rng(3)
    params = {"tex": jnp.asarray(rng.random((8, 8, 3), np.float32)), "light": jnp.ones(3)}
    ours, ref = ob.pyramid_adam(0.05, 1), optax.adam(0.05)
    s1, s2 = ours.init(params), ref.init(params)
    up1, up2 = jax.jit(ours.update), jax.jit(ref.update)
    for t in range(5):
        g = jax.tree.map(
            lambda p, t=t: jnp.asarray(
                np.random.default_rng(t).standard_normal(p.shape), jnp.float32
            ),
            params,
        )
        u1, s1 = up1(g, s1, params)
        u2, s2 = up2(g, s2, params)
        jax.tree.map(
            lambda a, b: np.testing.assert_array_equal(np.asarray(a), np.asarray(b)), u1, u2
        )


def test_equals_adam_on_the_coefficients():
    """Optimising c with optax.adam on f(P c) gives the iterates theta_t = P c_t of the
    transform."""
    axes, levels, shape = (0, 1), 3, (12, 9, 2)
    target = jnp.asarray(np.random.default_rng(4).random(shape, np.float32))

    def f(theta):
        return jnp.sum(jnp.square(theta - target) * jnp.linspace(0.5, 2.0, shape[0])[:, None, None])

    coeffs = [jnp.zeros(s) for s in pyr.level_shapes(shape, levels, axes)]
    opt_c = optax.adam(0.03)
    state_c = opt_c.init(coeffs)
    theta = pyr.pyramid_reconstruct(coeffs, axes)
    opt = ob.pyramid_adam(0.03, levels)
    state = opt.init(theta)

    @jax.jit
    def step(coeffs, state_c, theta, state):
        gc = jax.grad(lambda c: f(pyr.pyramid_reconstruct(c, axes)))(coeffs)
        uc, state_c = opt_c.update(gc, state_c)
        u, state = opt.update(jax.grad(f)(theta), state, theta)
        return optax.apply_updates(coeffs, uc), state_c, optax.apply_updates(theta, u), state

    for _ in range(20):
        coeffs, state_c, theta, state = step(coeffs, state_c, theta, state)
    # 20 float32 steps of size ~0.03 on values ~1: rounding differences of order 1e-6.
    np.testing.assert_allclose(
        np.asarray(theta), np.asarray(pyr.pyramid_reconstruct(coeffs, axes)), atol=1e-5
    )


def test_constant_gradient_steps_levels_times_lr():
    """Adam's first step is -lr sign(g) on every coefficient; upsampling keeps constants, so the
    grid moves by levels * lr (the levels add up)."""
    opt = ob.pyramid_adam(0.01, 4, spatial_axes=(0, 1))
    params = jnp.zeros((16, 16))
    u, _ = jax.jit(opt.update)(jnp.ones((16, 16)), opt.init(params), params)
    np.testing.assert_allclose(np.asarray(u), -0.04, rtol=1e-5)


def test_inject_hyperparams_jit_and_vmap_over_learning_rates():
    factory = optax.inject_hyperparams(ob.pyramid_adam, static_args=("levels",))
    params = jnp.zeros((8, 8))
    g = jnp.asarray(np.random.default_rng(5).standard_normal((8, 8)), jnp.float32)

    @jax.jit
    @jax.vmap
    def step(lr):
        opt = factory(learning_rate=0.1, levels=3)
        state = opt.init(params)
        state.hyperparams["learning_rate"] = lr
        return opt.update(g, state, params)[0]

    u = step(jnp.array([0.1, 0.2]))
    np.testing.assert_allclose(np.asarray(u[1]), 2 * np.asarray(u[0]), rtol=1e-6)
    assert np.all(np.isfinite(np.asarray(u)))


def test_unfiltered_leaves_get_plain_adam():
    params = {"v": jnp.zeros(5)}
    g = {"v": jnp.arange(5.0) - 2}
    u, _ = ob.pyramid_adam(0.1, 3).update(g, ob.pyramid_adam(0.1, 3).init(params), params)
    u2, _ = optax.adam(0.1).update(g, optax.adam(0.1).init(params), params)
    np.testing.assert_array_equal(np.asarray(u["v"]), np.asarray(u2["v"]))


@pytest.mark.parametrize("levels", [0, -1, 2.5, True, "3"])
def test_bad_levels_raise(levels):
    with pytest.raises(ValueError, match="levels must be an int >= 1"):
        ob.pyramid_adam(0.1, levels)


def test_bad_spatial_axes_raise():
    with pytest.raises(ValueError, match="repeats an axis"):
        ob.pyramid_adam(0.1, 2, spatial_axes=(0, 0))
    opt = ob.pyramid_adam(0.1, 2, spatial_axes=(0, 3))
    with pytest.raises(ValueError, match="out of range"):
        opt.init(jnp.zeros((4, 4)))
