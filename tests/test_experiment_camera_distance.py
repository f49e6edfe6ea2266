"""The tuning suite's Mitsuba scenes (issue #47, :mod:`experiments.tuning.camera_distance`): a
texture seen from three camera distances and from two cameras in turn, rendered at the quick size.
Without a usable Mitsuba this module is skipped with one line saying why, and fails under CI
(tests/mitsuba_env.py)."""

import numpy as np
import pytest

from experiments import tuning as T
from experiments.tuning import camera_distance as cd
from experiments.tuning import scenes as sc
from mitsuba_env import fail_under_ci, require_mitsuba

MI = require_mitsuba()  # skips this module without a usable Mitsuba; None under CI


@pytest.fixture(scope="module", autouse=True)
def mi():
    return fail_under_ci(MI)


@pytest.fixture(scope="module")
def two_cameras():
    return sc.make("mitsuba_two_cameras", quick=True)


def test_each_camera_sees_the_texels_per_pixel_the_scene_says(mi):
    """Rendered texture coordinates (the ``uv`` AOV, 256 spp: a pixel's mean) step by the
    camera's texels per pixel from pixel to pixel along the film's middle row (within 3%:
    the AOV's Monte Carlo error over a row of 24 pixels or, far away, of the 4 the plane covers)."""
    texture, film = 48, 24
    names = list(cd.CAMERAS)
    d = cd.scene_dict(cd.target_albedo(texture), names, film, np.ones((8, 16, 3), np.float32))
    d["integrator"] = {"type": "aov", "aovs": "uv:uv"}
    scene = mi.load_dict(d)
    for j, name in enumerate(names):
        u = np.array(mi.render(scene, sensor=j, spp=256, seed=0))[film // 2, :, 0]
        on_plane = np.flatnonzero(u > 0)
        first, last = on_plane[0], on_plane[-1]
        measured = abs(u[last] - u[first]) * texture / (last - first)
        assert measured == pytest.approx(cd.CAMERAS[name], rel=0.03), name
    assert len(on_plane) == round(texture / cd.CAMERAS["far"])  # the far camera: 4 pixels


def test_two_cameras_alternate(two_cameras):
    """Even steps render from the close camera (a gradient only on the central texels it sees,
    bilinear lookups reaching one texel further), odd steps from the far one (the whole plane)."""
    import jax

    scene = two_cameras
    key = jax.random.key(0)
    g0 = np.asarray(scene.grad(scene.data, scene.init, key, step=0))
    g1 = np.asarray(scene.grad(scene.data, scene.init, key, step=1))
    t = scene.init.shape[0]
    side = cd.visible_texels(cd.CAMERAS["close"], t, scene.config["film"])
    lo, hi = (t - side) // 2 - 1, (t + side) // 2 + 1
    outside = np.ones((t, t), bool)
    outside[lo:hi, lo:hi] = False
    assert np.any(g0 != 0) and not np.any(g0[outside] != 0)
    assert np.any(g1[outside] != 0)


def test_rendered_scene_is_reproducible_and_adam_reduces_its_error(two_cameras):
    """The runner's Adam on rendered gradients: a seed's run repeats (the render seeds come from
    the keys; up to float rounding, as Mitsuba sums a texel's gradients with atomics in a
    varying order: 1e-7 relative seen), two seeds differ (by 3%), and 12 steps cut the error by
    a quarter."""
    scene = two_cameras
    grid = {"learning_rate": [0.05], "b1": [0.9]}
    first = T.evaluate(scene, T.adam_factory, grid, seeds=(0, 1))
    again = T.evaluate(scene, T.adam_factory, grid, seeds=(0, 1))
    np.testing.assert_allclose(first, again, rtol=1e-5)
    assert abs(first[0, 0] - first[0, 1]) > 1e-3 * first[0, 0]
    assert np.all(first < 0.75 * scene.initial_error()), (first, scene.initial_error())


def test_the_coffee_scene_is_the_far_camera_on_another_photograph(mi):
    far, coffee = sc.make("mitsuba_far", quick=True), sc.make("mitsuba_far_coffee", quick=True)
    assert coffee.config["photo"] == "coffee" and "photo" not in far.config
    assert coffee.config["tpp"] == far.config["tpp"] == [cd.CAMERAS["far"]]
    np.testing.assert_allclose(coffee.data["target"], cd.target_albedo(48, "coffee"))
