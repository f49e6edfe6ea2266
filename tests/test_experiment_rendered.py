"""The tuning suite's rendered scenes (issue #47) without Mitsuba: ``absorption_mc`` (a
sharp-edged absorption map from Monte Carlo transmittances, with an unbiased gradient) and the
camera-distance scenes' geometry and error (their renders:
tests/test_experiment_camera_distance.py)."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from experiments import tuning as T
from experiments.tuning import camera_distance as cd
from experiments.tuning import scenes as sc

MC = dict(density=4.0, length=1.5)


def _gradient_z_scores(estimator, samples: int = 4000):
    """Per-texel z-scores of the mean of ``samples`` gradient estimates against the gradient of
    the loss with transmittances by a fine midpoint rule, on 16 fixed rays through an 8^2 map."""
    sigma = jnp.asarray(sc.shapes_image(8, seed=1)) * 0.8 + 0.1
    rays = sc.random_rays(jax.random.key(0), 16, 0.7)
    target = jnp.asarray(sc.shapes_image(8, seed=3))
    measured = jax.jit(lambda t: sc.transmittance_quadrature(t, rays, points=4096, **MC))(target)

    def loss(s):
        return jnp.mean((sc.transmittance_quadrature(s, rays, points=4096, **MC) - measured) ** 2)

    exact = jax.jit(jax.grad(loss))(sigma)
    keys = jax.random.split(jax.random.key(1), samples)
    g = jax.jit(jax.vmap(lambda k: estimator(sigma, measured, rays, k)))(keys)
    se = g.std(0) / np.sqrt(samples)
    seen = se > 0  # texels no ray crosses have a zero gradient in every sample
    return np.asarray(((g.mean(0) - exact) / jnp.where(seen, se, 1.0))[seen])


def test_absorption_gradient_is_unbiased():
    """The mean of many gradient estimates matches the gradient of the exact loss within Monte
    Carlo error (|z| < 5 on every texel, mean z^2 near 1: its expectation is 1), while the same
    check flags a biased estimator (one transmittance estimate in both factors of the chain
    rule), so the check has the power to fail."""
    z = _gradient_z_scores(lambda s, m, r, k: sc.absorption_grad(s, m, r, k, max_points=32, **MC))
    assert z.size > 20
    assert np.abs(z).max() < 5.0 and np.mean(z**2) < 2.0, (np.abs(z).max(), np.mean(z**2))

    def biased(s, measured, rays, k):
        t = lambda x: sc.transmittance_mc(x, rays, k, max_points=32, **MC)
        return jax.grad(lambda x: jnp.mean((t(x) - measured) ** 2))(s)

    zb = _gradient_z_scores(biased)
    assert np.mean(zb**2) > 25.0, np.mean(zb**2)


def test_absorption_target_has_sharp_edges_and_adam_reduces_the_error():
    """The target is piecewise constant (most texels equal a neighbour, some jump by > 0.1), and
    30 Adam steps on the quick scene's gradients cut the error by a third."""
    scene = sc.make("absorption_mc", quick=True)
    target = np.asarray(scene.data["target"])
    jumps = np.abs(np.diff(target, axis=1))
    assert np.mean(jumps == 0) > 0.5 and np.sum(jumps > 0.1) >= 4
    errors = T.evaluate(scene, T.adam_factory, {"learning_rate": [0.05], "b1": [0.9]}, seeds=(0,))
    assert errors[0, 0] < 0.67 * scene.initial_error(), (errors, scene.initial_error())


def test_camera_distance_inverts_texels_per_pixel():
    for tpp in cd.CAMERAS.values():
        d = cd.camera_distance(tpp, 192, 96)
        assert cd.texels_per_pixel(d, 192, 96) == pytest.approx(tpp, rel=1e-12)
    # The mid camera (2 texels per pixel, texture twice the film) sees the whole plane.
    d = cd.camera_distance(2.0, 192, 96)
    assert 2 * d * math.tan(math.radians(cd.FOV) / 2) == pytest.approx(cd.PLANE_SIDE)


def test_resolved_error_counts_only_what_the_camera_resolves():
    """Detail averaging to zero over 12x12 blocks is invisible to the far camera (error 0) but
    not to the mid one; texels outside the close camera's view are not counted."""
    target = jnp.full((48, 48, 3), 0.5)
    checker = (np.indices((48, 48)).sum(0) % 2 * 2 - 1)[..., None] * 0.1  # +-0.1, zero mean
    x = target + checker
    assert float(cd.resolved_error(x, target, 12.0, 4)) == pytest.approx(0.0, abs=1e-6)
    assert float(cd.resolved_error(x, target, 1.0, 48)) == pytest.approx(0.1, rel=1e-5)
    # The close camera at 0.5 texels per pixel and a 24^2 film sees the central 12^2 texels.
    outside = target.at[:18].set(0.9)
    assert float(cd.resolved_error(outside, target, 0.5, 24)) == 0.0
    assert float(cd.resolved_error(outside.at[24, 24].set(0.9), target, 0.5, 24)) > 0


def test_absorption_edges_is_the_phantom_with_sharp_high_contrast_edges_and_adam_reduces_it():
    """``absorption_edges`` (issue #54): the Shepp-Logan phantom's levels, nearest-neighbour
    so no texel lies between two levels, a 1.0 skull around 0.0 to 0.4 inside; more rays a step
    than ``absorption_mc`` (its edges stand out of the noise); Adam cuts its error."""
    scene = sc.make("absorption_edges", quick=True)
    target = np.asarray(scene.data["target"])
    levels = np.unique(target)
    phantom = np.array([0.0, 0.098, 0.2, 0.298, 0.4, 1.0])
    assert np.all(np.abs(levels[:, None] - phantom).min(axis=1) < 2e-3) and len(levels) >= 4
    assert target.max() == 1.0 and np.sum(np.abs(np.diff(target, axis=0)) >= 0.6) >= 4
    full = sc.make("absorption_edges")
    assert full.config["rays"] > sc.make("absorption_mc").config["rays"]
    assert full.config["target"] == "absorption_edges" and full.init.shape == (96, 96)
    errors = T.evaluate(scene, T.adam_factory, {"learning_rate": [0.05], "b1": [0.9]}, seeds=(0,))
    assert errors[0, 0] < 0.67 * scene.initial_error(), (errors, scene.initial_error())


def test_target_albedo_is_a_central_square_of_the_photograph_in_range():
    a, c = cd.target_albedo(32), cd.target_albedo(32, "coffee")
    assert a.shape == c.shape == (32, 32, 3)
    assert 0.02 <= c.min() and c.max() <= 0.98
    assert np.abs(a - c).mean() > 0.05  # another photograph
    with pytest.raises(ValueError, match="photo must be one of"):
        cd.target_albedo(32, "moon")
