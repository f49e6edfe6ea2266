"""The held-out scenes and ``experiments.resolution_rule``'s candidate (docs/auto_sigma.md)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import optax_bilateral as ob
from experiments import resolution_rule as rr
from experiments import scenes as sc
from experiments import tuning as T
from optax_bilateral._src import auto

AXES = (0, 1)


@pytest.mark.parametrize("name", sorted(n for n in sc.HELD_OUT if "_n" in n))
def test_held_out_scene_is_its_suite_scene_at_another_size(name):
    scene = sc.make(name, quick=True)
    assert scene.name == name and name not in sc.SCENES
    base = sc.make(name.split("_n")[0], quick=True)
    assert scene.init.ndim == base.init.ndim and scene.init.shape != base.init.shape
    assert scene.data["target"].shape == scene.init.shape
    g = scene.grad(scene.data, scene.init, jax.random.key(0))
    assert g.shape == scene.init.shape and bool(jnp.all(jnp.isfinite(g)))
    assert scene.error(scene.data, scene.init) > 0


def test_unknown_scene_names_every_choice():
    with pytest.raises(ValueError, match="deblur_n96"):
        sc.make("deblur_n7")
    with pytest.raises(ValueError, match="unknown scene"):
        T.run_benchmark(["nope"], quick=True, progress=False)


@pytest.mark.parametrize(
    "shape, axes, levels",
    [((16, 16, 16, 3), None, 2), ((64, 64), None, 3), ((128, 128), None, 4),
     ((96, 96), None, 4), ((1024, 1), (0,), 5), ((4096, 1), (0,), 6), ((8, 3), None, 2)],
)  # fmt: skip
def test_levels_grow_with_the_square_root_of_the_longest_side(shape, axes, levels):
    assert rr.levels_for({"x": jnp.zeros(shape)}, axes) == levels


def test_levels_for_rejects_params_without_a_spatial_side():
    with pytest.raises(ValueError, match="no spatial side"):
        rr.levels_for({"x": jnp.zeros((3,))})


def test_candidate_scales_sigma_with_levels_and_leaves_the_library_as_it_was():
    """At F = 4 the candidate's step differs from the library's auto at F = 4 (its scale is
    3 learning rates), ``levels_only`` equals it, and auto's factor is 1 afterwards."""
    x = jnp.asarray(np.random.default_rng(0).uniform(0.2, 0.8, (128, 128)), jnp.float32)
    rng = np.random.default_rng(1)
    grads = [jnp.asarray(rng.normal(size=x.shape), jnp.float32) for _ in range(2)]

    def run(opt):
        state, p, update = opt.init(x), x, jax.jit(opt.update)
        for g in grads:
            u, state = update(g, state, p)
            p = p + u
        return p

    library = run(ob.bilateral_adam(0.01, levels=4, spatial_axes=AXES))
    assert np.allclose(run(rr.levels_only(0.01, AXES)), library, atol=1e-7)
    assert not np.allclose(run(rr.factory(0.01, AXES)), library, atol=1e-5)
    assert auto.RATE_FACTOR == 1.0
    again = run(ob.bilateral_adam(0.01, levels=4, spatial_axes=AXES))
    assert np.allclose(again, library, atol=1e-7)
