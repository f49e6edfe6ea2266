"""The volume scene's Monte Carlo estimator, checked against an independent quadrature.

The reference below is written separately in NumPy/SciPy: pinhole rays from the
scene's camera frames, ``scipy.ndimage.map_coordinates`` for the trilinear
lookups and midpoint-rule quadrature (``exp(-sum sigma dt)``) for every
transmittance and for the in-scattering integral. It shares no code with the
JAX estimator (ratio tracking, stratified in-scattering samples).
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import ndimage, stats

from optax_bilateral.toy import volume

SIZE = 24  # small grid: the quadrature reference is the slow part
RES = 6  # 6 x 6 pixels, one view
VIEW = 40  # a side view
Z = 5.0  # two-sided z bound: P(|N(0,1)| > 5) = 5.7e-7 per comparison
BATCH = 64  # samples per batch mean; batch means are ~normal, their spread gives the SE
N_BATCHES = 64


@pytest.fixture(scope="module")
def scene():
    return volume.make_scene(resolution=RES, n_views=64)


@pytest.fixture(scope="module")
def target():
    """A medium filling the whole cube (every pixel that sees the cube sees medium), with
    the reference volume's sharp albedo checker and density variations in (0.1, 0.7)."""
    ref = volume.reference_volume(SIZE)
    dens = 0.1 + 0.6 * ref["density"] / ref["density"].max()
    return {"density": jnp.asarray(dens), "albedo": jnp.asarray(ref["albedo"])}


def _batch_means(fn, seed):
    """N_BATCHES independent calls of fn(key) (each already a BATCH-sample mean), as float64."""
    keys = jax.random.split(jax.random.key(seed), N_BATCHES)
    return np.stack([np.asarray(fn(k), np.float64) for k in keys])


# ----------------------------------------------------------- independent reference


def _lookup(grid, pts):
    """Trilinear, clamp-to-edge, voxel centres at (i + 1/2)/n: grid (n, n, n), pts (N, 3)."""
    n = np.asarray(grid.shape, np.float64)
    coords = (pts * n - 0.5).T
    return ndimage.map_coordinates(np.asarray(grid, np.float64), coords, order=1, mode="nearest")


def _quadrature_image(params, scene, view, n_steps=160, n_shadow=80, density_scale=None):
    """Pixel-centre radiance by midpoint quadrature: (RES, RES, 3) float64."""
    scale = scene.density_scale if density_scale is None else density_scale
    dens = np.asarray(params["density"], np.float64)[..., 0] * scale
    alb = np.asarray(params["albedo"], np.float64)
    o = scene.origins[view].astype(np.float64)
    n = scene.resolution
    c = (np.arange(n) + 0.5) / n * 2 - 1
    sx, sy = np.meshgrid(c, -c, indexing="xy")  # row i: top to bottom
    d = scene.forward[view][None, None] + scene.tan_half_fov * (
        sx[..., None] * scene.right[view] + sy[..., None] * scene.up[view]
    )
    d = (d / np.linalg.norm(d, axis=-1, keepdims=True)).reshape(-1, 3).astype(np.float64)
    sun = scene.sun_direction.astype(np.float64)
    out = np.zeros((d.shape[0], 3))
    for r, dr in enumerate(d):
        with np.errstate(divide="ignore"):
            ta, tb = -o / dr, (1 - o) / dr
        t_near, t_far = np.max(np.minimum(ta, tb)), np.min(np.maximum(ta, tb))
        t0 = max(t_near, 0.0)
        length = max(t_far - t0, 0.0)
        z = dr[2]
        bg = (
            scene.sky_horizon + (scene.sky_zenith - scene.sky_horizon) * math.sqrt(min(z, 1.0))
            if z >= 0
            else scene.ground
        ).astype(np.float64)
        if length == 0:
            out[r] = bg
            continue
        dt = length / n_steps
        t = t0 + (np.arange(n_steps) + 0.5) * dt
        x = o + t[:, None] * dr
        sig = _lookup(dens, x)
        tau_before = np.concatenate([[0.0], np.cumsum(sig)[:-1]]) * dt + 0.5 * sig * dt
        t_cam = np.exp(-tau_before)
        a = np.stack([_lookup(alb[..., ch], x) for ch in range(3)], -1)
        exit_len = np.min(np.maximum(-x / sun, (1 - x) / sun), axis=-1)
        ds = exit_len / n_shadow
        s = (np.arange(n_shadow) + 0.5)[None, :] * ds[:, None]
        xs = x[:, None, :] + s[..., None] * sun
        sig_sh = _lookup(dens, xs.reshape(-1, 3)).reshape(n_steps, n_shadow)
        t_sun = np.exp(-np.sum(sig_sh, axis=-1) * ds)
        inscatter = np.sum((t_cam * t_sun * sig)[:, None] * a, axis=0) * dt
        out[r] = np.exp(-np.sum(sig) * dt) * bg + inscatter * scene.sun_radiance
    return out.reshape(n, n, 3)


@pytest.fixture(scope="module")
def quadrature(scene, target):
    fine = _quadrature_image(target, scene, VIEW)
    coarse = _quadrature_image(target, scene, VIEW, n_steps=80, n_shadow=40)
    return fine, coarse


# ------------------------------------------------------------------ tests


def test_quadrature_reference_is_converged(quadrature):
    fine, coarse = quadrature
    # Midpoint rule is second order: halving the step changes the image by ~3x the
    # remaining error, so a 2e-3 change bounds the fine image's error by ~1e-3.
    assert np.max(np.abs(fine - coarse)) < 2e-3
    # The view must actually see medium (some pixels differ from the plain background).
    assert np.ptp(fine) > 0.2


def test_radiance_estimate_is_unbiased(scene, target, quadrature):
    """Mean of independent estimates matches the quadrature within Z standard errors."""
    fine, _ = quadrature
    views = jnp.array([VIEW])
    means = _batch_means(
        lambda k: volume.render(target, scene, k, views, spp=BATCH, jitter=False)[0], 0
    )
    mean = means.mean(0)
    se = means.std(0, ddof=1) / math.sqrt(N_BATCHES)
    # 108 comparisons at Z = 5 (familywise false-alarm rate < 1e-4); 2e-3 covers the
    # quadrature's own error (see test_quadrature_reference_is_converged).
    excess = np.abs(mean - fine) - (Z * se + 2e-3)
    assert np.all(excess <= 0), (
        f"worst excess {excess.max():.3g} at {np.unravel_index(excess.argmax(), excess.shape)}"
    )
    # Power: the same bound rejects a medium whose extinction is 10% off (it changes
    # some pixels by ~0.04, about 8 standard errors at these sample counts).
    wrong = _quadrature_image(
        target, scene, VIEW, n_steps=80, n_shadow=40, density_scale=1.1 * scene.density_scale
    )
    assert np.any(np.abs(mean - wrong) > Z * se + 2e-3)
    # A single sample is genuinely noisy (this is what the filters are for): the
    # per-sample standard deviation is sqrt(BATCH) times the batch means' spread.
    assert np.max(means.std(0) * math.sqrt(BATCH)) > 0.1


def _grad_call(start, scene, views, targets, key):
    return volume.loss_and_grad(
        start, scene, key, views, targets, spp=BATCH // 4, spp_grad=BATCH // 4, jitter=False
    )


def test_loss_gradient_is_unbiased(scene, target):
    """E[<grad, delta>] from loss_and_grad equals the quadrature loss' central difference."""
    start = {k: jnp.asarray(v) for k, v in volume.initial_volume(SIZE, density=0.3).items()}
    views = jnp.array([VIEW])
    targets = jnp.asarray(
        _quadrature_image(target, scene, VIEW, n_steps=80, n_shadow=40), jnp.float32
    )[None]
    rng = np.random.default_rng(1)
    # A smooth random direction in both grids, plus a uniform density increase so that
    # the loss changes by many standard errors of the gradient estimate.
    delta = {
        k: ndimage.gaussian_filter(rng.standard_normal(np.shape(v)), (2, 2, 2, 0))
        for k, v in start.items()
    }
    delta = {k: v / np.abs(v).max() for k, v in delta.items()}
    delta["density"] = delta["density"] + 1.0

    def qloss(p):
        img = _quadrature_image(p, scene, VIEW, n_steps=80, n_shadow=40)
        return np.mean((img - np.asarray(targets[0], np.float64)) ** 2)

    h = 0.02
    base = {k: np.asarray(v, np.float64) for k, v in start.items()}
    fd = (
        qloss({k: base[k] + h * delta[k] for k in base})
        - qloss({k: base[k] - h * delta[k] for k in base})
    ) / (2 * h)
    # The same difference with half the step: their gap bounds the FD truncation error.
    fd_half = (
        qloss({k: base[k] + h / 2 * delta[k] for k in base})
        - qloss({k: base[k] - h / 2 * delta[k] for k in base})
    ) / h

    d_j = {k: jnp.asarray(v, jnp.float32) for k, v in delta.items()}

    def directional(key):
        _, g, _ = _grad_call(start, scene, views, targets, key)
        return sum(jnp.vdot(g[name], d_j[name]) for name in g)

    dd = _batch_means(directional, 3)
    se = dd.std(ddof=1) / math.sqrt(N_BATCHES)
    # Z standard errors of the mean, plus the FD error estimate and the quadrature's
    # own discretisation (1e-3 radiance error is ~1e-2 of the loss change).
    tol = Z * se + abs(fd - fd_half) + 1e-2 * abs(fd)
    assert abs(dd.mean() - fd) <= tol, (dd.mean(), fd, fd_half, se)
    # The gradient carries signal at this sample count: the mean is many SEs from 0.
    assert abs(fd) > 10 * se


def test_same_key_same_image_and_gradient(scene, target):
    views = jnp.array([VIEW])  # the shapes of the tests above: no new compilation
    k = jax.random.key(7)
    a = volume.render(target, scene, k, views, spp=BATCH, jitter=False)
    b = volume.render(target, scene, k, views, spp=BATCH, jitter=False)
    c = volume.render(target, scene, jax.random.key(8), views, spp=BATCH, jitter=False)
    np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert not np.array_equal(np.asarray(a), np.asarray(c))
    start = {k_: jnp.asarray(v) for k_, v in volume.initial_volume(SIZE).items()}
    la, ga, _ = _grad_call(start, scene, views, a, k)
    lb, gb, _ = _grad_call(start, scene, views, a, k)
    lc, gc, _ = _grad_call(start, scene, views, a, jax.random.key(8))
    assert float(la) == float(lb) and float(la) != float(lc)
    for name in ga:
        np.testing.assert_array_equal(np.asarray(ga[name]), np.asarray(gb[name]))
        assert not np.array_equal(np.asarray(ga[name]), np.asarray(gc[name]))


def test_trilinear_matches_scipy_and_its_adjoint():
    rng = np.random.default_rng(0)
    grid = rng.standard_normal((5, 6, 7, 2)).astype(np.float32)
    pts = rng.uniform(-0.05, 1.05, (300, 3)).astype(np.float32)  # includes clamp-to-edge
    got = np.asarray(volume.sampling.trilinear(jnp.asarray(grid), jnp.asarray(pts)))
    want = np.stack([_lookup(grid[..., c], pts.astype(np.float64)) for c in range(2)], -1)
    np.testing.assert_allclose(got, want, atol=1e-5)  # float32 rounding of O(1) values
    # The custom reverse rule is the exact transpose: <J g, c> = <g, J^T c>.
    cot = rng.standard_normal(got.shape).astype(np.float32)
    g2 = rng.standard_normal(grid.shape).astype(np.float32)
    _, vjp = jax.vjp(lambda g: volume.sampling.trilinear(g, jnp.asarray(pts)), jnp.asarray(grid))
    (jt_c,) = vjp(jnp.asarray(cot))
    lhs = np.vdot(np.asarray(volume.sampling.trilinear(jnp.asarray(g2), jnp.asarray(pts))), cot)
    rhs = np.vdot(g2, np.asarray(jt_c))
    assert abs(lhs - rhs) <= 1e-4 * max(1.0, abs(lhs))  # float32 sums of ~600 terms


def test_tracking_cap_bounds_truncation(scene):
    mean = scene.majorant * math.sqrt(3.0)
    assert stats.poisson.sf(scene.n_track, mean) <= scene.truncation_probability
    assert stats.poisson.sf(scene.n_track - 1, mean) > scene.truncation_probability  # smallest cap


def test_reference_volume_is_valid_and_deterministic():
    a, b = volume.reference_volume(16), volume.reference_volume(16)
    for k in a:
        np.testing.assert_array_equal(a[k], b[k])
    assert a["density"].shape == (16, 16, 16, 1) and a["albedo"].shape == (16, 16, 16, 3)
    assert a["density"].min() >= 0 and a["density"].max() <= 1
    assert a["albedo"].min() >= 0 and a["albedo"].max() <= 1
    # Smoke with empty space around it, and an albedo with more than one colour.
    assert 0.05 < np.mean(a["density"] > 0) < 0.6
    assert len(np.unique(a["albedo"].reshape(-1, 3), axis=0)) == 3


def test_project_and_param_errors(target):
    p = {"density": target["density"] * 3 - 1, "albedo": target["albedo"] + 2}
    q = volume.project(p)
    assert float(q["density"].min()) >= 0 and float(q["density"].max()) <= 1
    assert float(q["albedo"].max()) <= 1
    errs = volume.param_errors(target, target)
    assert all(float(v) == 0 for v in errs.values())
    errs = volume.param_errors(q, target)
    assert float(errs["param_error"]) > 0


def test_bad_inputs_raise(scene, target):
    with pytest.raises(TypeError, match="density"):
        volume.render({"density": target["density"]}, scene, jax.random.key(0), jnp.array([0]))
    with pytest.raises(ValueError, match="albedo"):
        volume.render(
            {"density": target["density"], "albedo": target["albedo"][..., :1]},
            scene,
            jax.random.key(0),
            jnp.array([0]),
        )
    with pytest.raises(ValueError, match="views"):
        volume.render(target, scene, jax.random.key(0), jnp.array([[0]]))
    with pytest.raises(ValueError, match="resolution"):
        volume.make_scene(resolution=0)
    with pytest.raises(ValueError, match="sun_direction"):
        volume.make_scene(sun_direction=(0.0, 0.0, 1.0))
    with pytest.raises(ValueError, match="size"):
        volume.reference_volume(1)
