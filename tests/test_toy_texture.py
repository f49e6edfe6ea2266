"""Tests of the toy texture renderer against an independent float64 quadrature.

The reference integrates ``f(w_i) cos(theta_i) L(w_i)`` directly over the
hemisphere of incident directions (no importance sampling, no pdf), in NumPy
float64 with its own GGX formulas and ``scipy.ndimage.map_coordinates`` for the
environment lookup: a bug in the renderer's sampling, pdf, BRDF or lookup shows up
as a mismatch.
"""

import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import ndimage

from optax_bilateral.toy import texture as T

SIZE = 4
# One texel per roughness decade-ish: near-mirror to rough.
ALPHAS = np.array([[0.02, 0.1, 0.2, 0.45]] * SIZE, np.float32)
TARGET = np.array([[0.04, 0.06, 0.3, 0.3]] * SIZE, np.float32)
# Texels checked against quadrature (row, col): different view directions and roughness.
PROBES = [(0, 0), (1, 1), (2, 2), (3, 3)]


@pytest.fixture(scope="module")
def scene():
    return T.make_scene(SIZE)


# ----------------------------------------------------------------------------- quadrature


def _env_np(env, x, y, z):
    n = env.shape[0]
    c = np.clip((x / (1 + z) + 1) * n / 2 - 0.5, 0, n - 1)
    r = np.clip((1 - y / (1 + z)) * n / 2 - 0.5, 0, n - 1)
    return ndimage.map_coordinates(env.astype(np.float64), [r, c], order=1, mode="nearest")


def _quad_pixel(wo, alpha, scene, n_beta=1000, n_gamma=800):
    """``int f cos L dw_i`` by the midpoint rule in polar coordinates about the mirror direction.

    ``beta = pi q^2`` puts most nodes near the specular peak (``d beta = 2 pi q dq``).
    """
    wo = np.asarray(wo, np.float64)
    r = np.array([-wo[0], -wo[1], wo[2]])
    t = np.cross(r, [0.0, 0.0, 1.0]) if abs(r[2]) < 0.99 else np.array([1.0, 0.0, 0.0])
    t /= np.linalg.norm(t)
    b = np.cross(r, t)
    q = (np.arange(n_beta) + 0.5) / n_beta
    beta = np.pi * q * q
    jac = 2 * np.pi * q / n_beta * (2 * np.pi / n_gamma) * np.sin(beta)
    gamma = (np.arange(n_gamma) + 0.5) * 2 * np.pi / n_gamma
    sb, cb = np.sin(beta)[:, None], np.cos(beta)[:, None]
    wi = (
        cb[..., None] * r
        + (sb * np.cos(gamma))[..., None] * t
        + (sb * np.sin(gamma))[..., None] * b
    )
    cos_i = wi[..., 2]
    ok = cos_i > 0
    h = wi + wo
    h /= np.linalg.norm(h, axis=-1, keepdims=True)
    cos_h = h[..., 2]
    cos_o = wo[2]
    a2 = float(alpha) ** 2
    d = a2 / (np.pi * (cos_h**2 * (a2 - 1) + 1) ** 2) * (cos_h > 0)

    def g1(c):
        c = np.maximum(c, 1e-12)
        tan2 = (1 - c * c) / (c * c)
        return 2 / (1 + np.sqrt(1 + a2 * tan2))

    f_cos = d * g1(cos_i) * g1(cos_o) / (4 * cos_o)  # f cos_i: the cos_i cancels
    env_v = _env_np(np.asarray(scene.env), wi[..., 0], wi[..., 1], np.clip(cos_i, 0, 1))
    # The sun: E times a Poisson kernel of width bw about s (gnomonic), zero behind it.
    s, bw, e = (
        np.asarray(scene.sun_dir, np.float64),
        float(scene.sun_width),
        float(scene.sun_power),
    )
    c = wi @ s
    env_v = env_v + np.where(c > 0, e * bw / (2 * np.pi * (1 - c * c + bw * bw * c * c) ** 1.5), 0)
    return float(np.sum(np.where(ok, f_cos * env_v, 0.0) * jac[:, None]))


@pytest.fixture(scope="module")
def quadrature(scene):
    """Quadrature values at ALPHAS and TARGET, and d/d alpha by central differences."""
    out = {}
    for p in PROBES:
        wo = np.asarray(scene.wo[p])
        a, at = float(ALPHAS[p]), float(TARGET[p])
        h = 1e-3 * a
        out[p] = dict(
            value=_quad_pixel(wo, a, scene),
            ref=_quad_pixel(wo, at, scene),
            deriv=(_quad_pixel(wo, a + h, scene) - _quad_pixel(wo, a - h, scene)) / (2 * h),
        )
    return out


def test_quadrature_resolves_the_integral(scene):
    # Doubling both resolutions moves the quadrature by < 0.3%: it is a trustworthy reference
    # at the tolerances below (which are a few percent of the value at most).
    wo = np.asarray(scene.wo[0, 0])
    coarse = _quad_pixel(wo, 0.02, scene)
    fine = _quad_pixel(wo, 0.02, scene, n_beta=2000, n_gamma=1600)
    assert abs(coarse - fine) < 3e-3 * abs(fine)


# ----------------------------------------------------------------------------- forward


@pytest.fixture(scope="module")
def iid_1spp(scene):
    """20k independent 1-spp images (one compiled function; larger spp = means of groups)."""
    keys = jax.random.split(jax.random.PRNGKey(0), 20000)
    f = jax.jit(jax.vmap(lambda k: T.render(jnp.asarray(ALPHAS), scene, k, 1, 1)))
    return np.asarray(f(keys), np.float64)


def test_forward_estimate_is_unbiased(iid_1spp, quadrature):
    # 20k independent 1-spp images: the mean matches the quadrature within 5 standard errors
    # (a false alarm has probability < 1e-5 per texel), plus 0.5% for the quadrature itself.
    mean, se = iid_1spp.mean(0), iid_1spp.std(0) / np.sqrt(iid_1spp.shape[0])
    for p in PROBES:
        q = quadrature[p]["value"]
        assert abs(mean[p] - q) < 5 * se[p] + 5e-3 * abs(q), (p, mean[p], q, se[p])


def test_forward_error_falls_as_spp_grows(iid_1spp, quadrature):
    # RMS error over 64 images at spp = 4 and 64 (means of disjoint groups of 1-spp images,
    # which is what render(spp=n) computes): i.i.d. Monte Carlo predicts a 4x drop; require
    # > 2.5x (64 images estimate each RMS to ~9%, so a correct estimator passes with margin).
    q = np.array([quadrature[p]["value"] for p in PROBES])
    rms = []
    for spp in (4, 64):
        est = iid_1spp[: 64 * spp].reshape((64, spp) + ALPHAS.shape).mean(1)
        vals = np.stack([est[(slice(None),) + p] for p in PROBES], axis=1)
        rms.append(np.sqrt(np.mean((vals - q) ** 2, axis=0)))
    assert np.all(rms[1] < rms[0] / 2.5), rms


def test_qmc_reference_matches_quadrature(scene, quadrature):
    # 4096 Sobol samples: the reference image within 2% of the quadrature at every probe
    # (i.i.d. sampling at this count has ~2-4% relative standard error on the rough texels;
    # the scrambled Sobol set does far better, so 2% has margin).
    ref = np.asarray(T.render_reference(jnp.asarray(ALPHAS), scene, spp=4096))
    for p in PROBES:
        q = quadrature[p]["value"]
        assert abs(ref[p] - q) < 0.02 * abs(q), (p, ref[p], q)


# ----------------------------------------------------------------------------- gradient


def _loss_grads(scene, reference, n_seeds, spp, spp_grad, seed=1):
    alpha = jnp.asarray(ALPHAS)
    grad = jax.grad(lambda a, k: T.loss_fn(T.render(a, scene, k, spp, spp_grad), reference))
    keys = jax.random.split(jax.random.PRNGKey(seed), n_seeds)
    return np.asarray(jax.jit(jax.vmap(grad, in_axes=(None, 0)))(alpha, keys), np.float64)


def _true_grad(quadrature, p, n_texels):
    q = quadrature[p]
    return 2.0 * (q["value"] - q["ref"]) / (q["ref"] ** 2 + T.LOSS_EPS) * q["deriv"] / n_texels


@pytest.fixture(scope="module")
def reference_image(scene, quadrature):
    """The target image, exact at the probes (quadrature) so the only noise is the renderer's."""
    ref = np.array(T.render_reference(jnp.asarray(TARGET), scene, spp=256))
    for p in PROBES:
        ref[p] = quadrature[p]["ref"]
    return jnp.asarray(ref)


def test_gradient_estimator_is_unbiased(scene, quadrature, reference_image):
    # The mean of 100k independent loss gradients (spp = spp_grad = 1) matches
    # 2 (I - I_ref) / (I_ref^2 + eps) dI/d alpha / n from the quadrature within 5 standard
    # errors (false alarm < 1e-5 per texel) plus 1% for the quadrature's finite differences.
    g = _loss_grads(scene, reference_image, 100_000, 1, 1)
    mean, se = g.mean(0), g.std(0) / np.sqrt(g.shape[0])
    for p in PROBES:
        true = _true_grad(quadrature, p, ALPHAS.size)
        assert abs(mean[p] - true) < 5 * se[p] + 0.01 * abs(true), (p, mean[p], true, se[p])
        # The test has power: the standard error is small against the gradient itself.
        assert 5 * se[p] < 0.5 * abs(true), (p, se[p], true)


def test_reusing_primal_samples_for_the_gradient_is_biased(scene, quadrature, reference_image):
    # Negative control for the test above: differentiating the *same* 1-spp estimate that
    # gives the value correlates (I - I_ref) with dI, and the mean misses the true gradient
    # by far more than 5 standard errors on at least one probe. This is why render() splits
    # its key into independent primal and gradient samples.
    alpha = jnp.asarray(ALPHAS)
    h, w = ALPHAS.shape

    def correlated(a, k):
        u = jax.random.uniform(k, (1, h, w, 2))
        return jax.grad(lambda a: T.loss_fn(T.estimate(a, scene, u), reference_image))(a)

    keys = jax.random.split(jax.random.PRNGKey(2), 100_000)
    g = np.asarray(jax.jit(jax.vmap(correlated, in_axes=(None, 0)))(alpha, keys), np.float64)
    mean, se = g.mean(0), g.std(0) / np.sqrt(g.shape[0])
    z = [abs(mean[p] - _true_grad(quadrature, p, ALPHAS.size)) / se[p] for p in PROBES]
    assert max(z) > 10, z


def test_closed_form_score_matches_autodiff(scene):
    # render()'s VJP uses d log f / d alpha in closed form; with the same samples it must equal
    # reverse-mode through estimate(). Same arithmetic up to float32 rounding: rtol 1e-4.
    alpha = jnp.asarray(ALPHAS)
    u = jax.random.uniform(jax.random.PRNGKey(5), (8,) + ALPHAS.shape + (2,))
    auto = jax.jit(jax.grad(lambda a: jnp.sum(T.estimate(a, scene, u))))(alpha)
    _, dw = jax.jit(lambda a: T.sample_weights(a, scene, u[..., 0], u[..., 1], with_score=True))(
        alpha
    )
    np.testing.assert_allclose(np.asarray(jnp.mean(dw, 0)), np.asarray(auto), rtol=1e-4, atol=1e-6)


def test_pixel_value_falls_monotonically_with_roughness():  # 16 texels: corners to centre
    # The scene is built so that the texture is identifiable: at every texel the
    # noise-free pixel value falls as alpha grows (the sun's halo contains every
    # mirror direction). 256 Sobol samples: the steps checked are > 5% of the value.
    scene = T.make_scene(SIZE)
    alphas = [0.005, 0.02, 0.05, 0.1, 0.2, 0.5]
    imgs = [
        np.asarray(T.render_reference(jnp.full((SIZE, SIZE), a), scene, spp=256)) for a in alphas
    ]
    assert all(np.all(b < 0.95 * a) for a, b in itertools.pairwise(imgs))


# ----------------------------------------------------------------------------- determinism & API


def test_render_is_deterministic_for_a_fixed_key(scene):
    alpha = jnp.asarray(ALPHAS)
    key = jax.random.PRNGKey(7)

    @jax.jit
    def value_and_grad(k):
        return jax.value_and_grad(lambda a: jnp.sum(T.render(a, scene, k, 2, 3)))(alpha)

    v1, g1 = value_and_grad(key)
    v2, g2 = value_and_grad(key)
    assert float(v1) == float(v2)
    np.testing.assert_array_equal(np.asarray(g1), np.asarray(g2))
    v3, g3 = value_and_grad(jax.random.PRNGKey(8))
    assert float(v3) != float(v1)
    assert not np.array_equal(np.asarray(g1), np.asarray(g3))


def test_primal_does_not_depend_on_spp_grad(scene):
    # The value uses only the primal key, so changing the gradient's sample count leaves it.
    alpha = jnp.asarray(ALPHAS)
    key = jax.random.PRNGKey(3)
    render = jax.jit(T.render, static_argnums=(3, 4))
    np.testing.assert_array_equal(
        np.asarray(render(alpha, scene, key, 2, 1)), np.asarray(render(alpha, scene, key, 2, 5))
    )


def test_targets_are_in_range_and_deterministic():
    for name in ("camera", "noise", "phantom"):
        t = T.target_roughness(name, 64)
        assert t.shape == (64, 64) and t.dtype == np.float32
        assert t.min() >= T.ALPHA_MIN * (1 - 1e-6) and t.max() <= T.ALPHA_MAX * (1 + 1e-6)
        np.testing.assert_array_equal(t, T.target_roughness(name, 64))
    # The piecewise-smooth target has far smaller neighbour differences than the noise one.
    tv = {
        n: np.mean(np.abs(np.diff(np.log(T.target_roughness(n, 64)), axis=0)))
        for n in ("camera", "noise")
    }
    assert tv["camera"] < 0.25 * tv["noise"], tv


def test_bad_input_raises(scene):
    key = jax.random.PRNGKey(0)
    with pytest.raises(ValueError, match="alpha"):
        T.render(jnp.ones((3, 3)), scene, key)
    with pytest.raises(ValueError, match="spp_grad"):
        T.render(jnp.asarray(ALPHAS), scene, key, 1, 0)
    with pytest.raises(ValueError, match="spp"):
        T.render_reference(jnp.asarray(ALPHAS), scene, spp=0)
    with pytest.raises(TypeError, match="scene"):
        T.render(jnp.asarray(ALPHAS), "scene", key)
    with pytest.raises(ValueError, match="name"):
        T.target_roughness("lena")
    with pytest.raises(ValueError, match="camera_position"):
        T.camera_directions(4, camera_position=(0.0, 0.0, -1.0))
