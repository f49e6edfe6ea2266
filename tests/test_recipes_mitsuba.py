"""docs/recipes.md's Mitsuba blocks run verbatim on the experiments' quick scenes (tiny films
and grids): the texture and volume tutorials' scenes (experiments/mitsuba/tutorials.py) and
the mesh experiment's sphere (experiments/mitsuba/mesh.py), each block then driven by a few
of its loop's iterations. Without a usable Mitsuba this module is skipped with one line
saying why, and fails under CI (tests/mitsuba_env.py).
"""

import numpy as np
import pytest

import docs_blocks
from mitsuba_env import fail_under_ci, require_mitsuba

MI = require_mitsuba()  # skips this module without a usable Mitsuba; None under CI


@pytest.fixture(scope="module", autouse=True)
def mi():
    return fail_under_ci(MI)


def _run(name, ns):
    block = docs_blocks.by("docs/recipes.md", name)
    exec(compile(block.code, block.where, "exec"), ns)
    return ns


def _filtered(opt, key):
    """Whether the key's postfilter keeps a sigma_d rule's state: "auto" keeps one for the
    leaves it filters only."""
    import jax

    import optax_bilateral as ob

    states = jax.tree.leaves(opt.state[key], is_leaf=lambda s: isinstance(s, ob.PostfilterState))
    return any(isinstance(s, ob.PostfilterState) and s.sigma_state is not None for s in states)


@pytest.mark.parametrize(
    "name, tutorial", [("mitsuba-texture", "cbox-texture"), ("mitsuba-volume", "volume")]
)
def test_grid_recipe_filters_its_key_in_the_tutorials_loop(mi, name, tutorial):
    from experiments.mitsuba import tutorials as E

    cfg = E.default_config(tutorial, quick=True)
    problem = (E.TexturedCornellBox if tutorial == "cbox-texture" else E.Volume)(cfg)
    ns = _run(name, {"params": problem.params})
    opt, key = ns["opt"], ns["key"]
    assert key == problem.key
    before = np.array(opt[key])
    for it in range(2):
        problem.iteration(opt, it)
    after = np.array(opt[key])
    assert _filtered(opt, key)
    assert np.isfinite(after).all() and np.abs(after - before).max() > 0
    np.testing.assert_array_equal(np.array(problem.params[key]), after)  # the scene holds them


def test_mesh_recipe_steps_the_scene_mesh(mi):
    import drjit as dr

    from experiments.mitsuba import mesh as E

    problem = E.Problem(E.default_config(quick=True), frequency=3)
    params = problem.params
    ns = _run("mitsuba-mesh", {"params": params})
    opt, key = ns["opt"], ns["key"]
    np.testing.assert_array_equal(np.asarray(ns["mesh"].faces), problem.faces)
    before = np.array(opt[key]).reshape(-1, 3)
    image = mi.render(problem.scene, params, sensor=problem.sensors[0], spp=1, seed=0)
    dr.backward(dr.mean(dr.abs(image - problem.references[0]), axis=None))
    opt.step()
    params.update(opt)
    after = np.array(opt[key]).reshape(-1, 3)
    assert np.isfinite(after).all() and 0 < np.abs(after - before).max() < 0.5
