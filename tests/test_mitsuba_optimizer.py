"""optax_bilateral.mitsuba.BilateralAdam and OptaxOptimizer: drop-in drjit.opt optimizers.

Most tests use losses written in Dr.Jit without rendering (``sum((x - target)^2)`` and
the like), so the gradients are exact and deterministic; one drives a tiny scene through
``params.update(opt)`` and a render. Mitsuba's own ``mi.ad.Adam`` is the reference for
the keys that get Adam's rule. Without a usable Mitsuba this module is skipped with one
line saying why, and fails under CI (tests/mitsuba_env.py).
"""

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

import optax_bilateral as ob
from mitsuba_env import fail_under_ci, require_mitsuba

MI = require_mitsuba()  # skips this module without a usable Mitsuba; None under CI


@pytest.fixture(scope="module", autouse=True)
def mi():
    return fail_under_ci(MI)


def _dr():
    import drjit as dr

    return dr


def _texture(seed=0, shape=(12, 10, 3)):
    return np.random.default_rng(seed).uniform(0.2, 0.8, shape).astype(np.float32)


def _backward_square(opt, targets, weights=None):
    """dr.backward of sum_k sum(w_k (x_k - t_k)^2): gradient 2 w (x - t), exact."""
    dr = _dr()
    loss = 0
    for k, t in targets.items():
        term = dr.square(opt[k] - t)
        if weights is not None and k in weights:
            term = term * weights[k]
        loss = loss + dr.sum(term, axis=None)
    dr.backward(loss)


def _np(x):
    return np.array(x, copy=True)


# ----------------------------------------------------------------------------- the rule per key


def test_keys_that_are_not_grids_follow_mitsubas_adam(mi):
    # A colour, a flat Float (a mesh's vertex_positions) and a (V, 3) tensor get Adam's rule:
    # the same trajectory as mi.ad.Adam, up to its folding of the bias corrections into the
    # rate and rsqrt(v + eps^2) (relative differences ~1e-6 per step).
    from optax_bilateral.mitsuba import BilateralAdam

    rng = np.random.default_rng(0)
    init = {
        "colour": mi.Color3f(0.3, 0.6, 0.9),
        "positions": mi.Float(rng.normal(size=30).astype(np.float32)),
        "vertices": mi.TensorXf(rng.normal(size=(7, 3)).astype(np.float32)),
    }
    targets = {
        "colour": mi.Color3f(0.1, 0.2, 0.3),
        "positions": mi.Float(np.zeros(30, np.float32)),
        "vertices": mi.TensorXf(np.ones((7, 3), np.float32)),
    }
    ours, theirs = BilateralAdam(lr=0.05, sigma_d=0.1), mi.ad.Adam(lr=0.05)
    for opt in (ours, theirs):
        opt.update(init)
    for _ in range(25):
        for opt in (ours, theirs):
            _backward_square(opt, targets)
            opt.step()
    for k in init:
        a, b = _np(ours[k]), _np(theirs[k])
        assert a.shape == b.shape
        np.testing.assert_allclose(a, b, rtol=0, atol=2e-5)
        assert np.abs(a - _np(init[k])).max() > 0.3  # and both moved a lot


def test_grid_keys_step_as_bilateral_adam(mi):
    # A texture (H, W, C) and a volume (D, H, W, C): the update is ob.bilateral_adam's (the
    # key's value is the guide), from the same gradients. Two compilations of one float32
    # program: equal up to XLA's fusion choices.
    from optax_bilateral.mitsuba import BilateralAdam

    values = {"tex": _texture(0), "vol": _texture(1, (4, 5, 6, 2))}
    targets = {k: np.full_like(v, 0.3) for k, v in values.items()}
    opt = BilateralAdam(lr=0.05, b1=0.2, sigma_d=0.1, levels=2, log_guide=True)
    for k, v in values.items():
        opt[k] = mi.TensorXf(v)
    tx = {  # Mitsuba's grids are channels last: every other axis is filtered
        k: ob.bilateral_adam(
            0.05, 0.2, sigma_d=0.1, levels=2, log_guide=True, spatial_axes=tuple(range(v.ndim - 1))
        )
        for k, v in values.items()
    }
    ref = {k: jnp.asarray(v) for k, v in values.items()}
    ref_state = {k: tx[k].init(v) for k, v in ref.items()}
    update = {k: jax.jit(t.update) for k, t in tx.items()}
    rng = np.random.default_rng(2)
    for _ in range(4):
        weights = {k: rng.uniform(0, 2, v.shape).astype(np.float32) for k, v in values.items()}
        _backward_square(
            opt,
            {k: mi.TensorXf(t) for k, t in targets.items()},
            {k: mi.TensorXf(w) for k, w in weights.items()},
        )
        opt.step()
        for k in ref:
            g = 2 * weights[k] * (ref[k] - targets[k])
            u, ref_state[k] = update[k](g, ref_state[k], ref[k])
            ref[k] = optax.apply_updates(ref[k], u)
    for k in ref:
        np.testing.assert_allclose(_np(opt[k]), np.asarray(ref[k]), rtol=0, atol=1e-6)


def test_the_filter_acts_on_grids_only(mi):
    # Noisy gradients of a constant target: the filtered texture stays smoother than the
    # same values stepped by Adam's rule, which a (V, 3) tensor of the same entries gets.
    from optax_bilateral.mitsuba import BilateralAdam

    x0 = np.full((16, 16, 3), 0.5, np.float32)
    opt = BilateralAdam(lr=0.02, sigma_d=np.inf, levels=3)
    opt["tex"] = mi.TensorXf(x0)
    opt["flat"] = mi.TensorXf(x0.reshape(-1, 3))
    rng = np.random.default_rng(3)
    for _ in range(5):
        noise = rng.normal(size=x0.shape).astype(np.float32)
        _backward_square(
            opt,
            {"tex": mi.TensorXf(x0 + noise), "flat": mi.TensorXf((x0 + noise).reshape(-1, 3))},
        )
        opt.step()
    rough = {k: np.abs(np.diff(_np(opt[k]).reshape(16, 16, 3), axis=0)).mean() for k in opt}
    assert rough["tex"] < 0.2 * rough["flat"], rough


# ----------------------------------------------------------------------------- dictionary semantics


def test_writing_a_key_keeps_its_state_and_a_new_shape_starts_afresh(mi):
    dr = _dr()
    from optax_bilateral.mitsuba import BilateralAdam

    opt = BilateralAdam(lr=0.05, sigma_d=0.1, levels=1)
    opt["tex"] = mi.TensorXf(_texture(0))
    target = {"tex": mi.TensorXf(np.full((12, 10, 3), 0.3, np.float32))}
    for _ in range(3):
        _backward_square(opt, target)
        opt.step()
    before = opt.state["tex"][3]
    opt["tex"] = dr.clip(opt["tex"], 0.0, 0.5)  # the tutorials' projection
    after = opt.state["tex"][3]
    assert after.count == 3 and after.state is before.state
    assert _np(opt["tex"]).max() <= 0.5 and dr.grad_enabled(opt["tex"])
    opt["tex"] = mi.TensorXf(np.zeros((24, 20, 3), np.float32))  # upsampled
    assert opt.state["tex"][3].count == 0
    assert not np.any(np.asarray(opt.state["tex"][3].state[0].mu))
    assert len(opt) == 1 and "tex" in opt and list(opt) == ["tex"]
    del opt["tex"]
    assert len(opt) == 0


def test_set_learning_rate_per_key_globally_and_as_a_schedule(mi):
    from optax_bilateral.mitsuba import BilateralAdam

    # Under a constant gradient every Adam step is lr (up to eps): the rates show directly.
    dr = _dr()
    opt = BilateralAdam(lr=0.1)
    for k in ("a", "b", "c"):
        opt[k] = mi.Float(1.0, 1.0)
    opt.set_learning_rate({"b": 0.01})
    opt.set_learning_rate(c=optax.linear_schedule(0.2, 0.0, 2))  # 0.2, 0.1, 0.0
    steps = []
    for _ in range(3):
        before = {k: _np(opt[k]) for k in opt}
        dr.backward(sum(dr.sum(opt[k]) for k in opt))
        opt.step()
        steps.append({k: float((before[k] - _np(opt[k]))[0]) for k in opt})
    # float32 bias corrections (1e-5 relative) and a step read as the difference of two
    # values near 1 (a few ulps, 1.2e-7 each).
    tol = dict(rtol=2e-5, atol=4e-7)
    np.testing.assert_allclose([s["a"] for s in steps], [0.1] * 3, **tol)
    np.testing.assert_allclose([s["b"] for s in steps], [0.01] * 3, **tol)
    np.testing.assert_allclose([s["c"] for s in steps], [0.2, 0.1, 0.0], **tol)
    assert opt.learning_rate("b") == 0.01 and opt.learning_rate() == 0.1
    opt.set_learning_rate(1)  # an int is a rate too (Dr.Jit's base ignores it)
    assert opt.learning_rate() == 1
    opt.set_learning_rate(b=None)  # back to the global rate
    assert opt.learning_rate("b") is None
    with pytest.raises(KeyError, match="not a parameter"):
        opt.set_learning_rate({"z": 0.1})
    with pytest.raises(ValueError, match=">= 0"):
        opt.set_learning_rate(-1.0)


def test_reset_one_key_keeps_its_rate_and_the_other_keys(mi):
    from optax_bilateral.mitsuba import BilateralAdam

    opt = BilateralAdam(lr=0.1)
    opt["a"], opt["b"] = mi.Float(1.0, 2.0), mi.Float(3.0)
    opt.set_learning_rate(a=0.5)
    for _ in range(2):
        _backward_square(opt, {"a": mi.Float(0.0, 0.0), "b": mi.Float(0.0)})
        opt.step()
    value_a = _np(opt["a"])
    opt.reset("a")
    a, b = opt.state["a"], opt.state["b"]
    assert a[3].count == 0 and not np.any(np.asarray(a[3].state[0].mu))
    assert a[2] == 0.5 and np.array_equal(_np(opt["a"]), value_a)  # rate and value kept
    assert b[3].count == 2 and np.any(np.asarray(b[3].state[0].mu))
    opt.reset()
    assert opt.state["b"][3].count == 0


def test_mask_updates_keeps_unobserved_texels_and_masks_other_keys_as_drjit(mi):
    from optax_bilateral.mitsuba import BilateralAdam

    x0 = _texture(4, (8, 8, 3))
    weight = np.ones_like(x0)
    weight[:3] = 0.0  # rows no ray reaches: zero gradient in every channel
    weight[5, 5, :2] = 0.0  # seen through one channel: observed
    opt = BilateralAdam(lr=0.05, sigma_d=0.1, levels=2, mask_updates=True)
    opt["tex"] = mi.TensorXf(x0)
    opt["c"] = mi.Color3f(0.5, 0.5, 0.5)
    theirs = mi.ad.Adam(lr=0.05, mask_updates=True)
    theirs["c"] = mi.Color3f(0.5, 0.5, 0.5)
    target = {"tex": mi.TensorXf(np.full_like(x0, 0.9)), "c": mi.Color3f(0.0, 0.0, 0.9)}
    for it in range(3):
        w_c = mi.Color3f(1.0, 0.0 if it else 1.0, 1.0)  # y unobserved after the first step
        _backward_square(opt, target, {"tex": mi.TensorXf(weight), "c": w_c})
        opt.step()
        _backward_square(theirs, {"c": target["c"]}, {"c": w_c})
        theirs.step()
    x = _np(opt["tex"])
    np.testing.assert_array_equal(x[:3], x0[:3])
    assert np.all(x[3:] != x0[3:])
    mu = np.asarray(opt.state["tex"][3].state[0].mu)
    assert not mu[:3].any() and mu[3:].any()
    assert np.all(x[5, 5] != x0[5, 5])  # observed: its neighbours' gradient moves every channel
    # Mitsuba's Adam up to its rounding (bias corrections folded into the rate): 1e-5.
    np.testing.assert_allclose(_np(opt["c"]), _np(theirs["c"]), rtol=0, atol=1e-5)
    assert _np(opt["c"])[1, 0] != 0.5  # moved in the first step, then held


def test_grad_scaler_drives_the_step(mi):
    dr = _dr()
    from optax_bilateral.mitsuba import OptaxOptimizer

    opt = OptaxOptimizer(optax.sgd(0.25))
    opt["x"] = mi.Float(1.0, -2.0)
    dr.backward(dr.sum(4.0 * opt["x"]))  # the gradient is 4, scaled 4x
    opt.step(grad_scale=0.25)
    np.testing.assert_allclose(_np(opt["x"]), [0.75, -2.25])
    dr.backward(dr.sum(opt["x"]))
    opt.step(active=mi.Bool(False))  # an overflow step: nothing changes
    np.testing.assert_allclose(_np(opt["x"]), [0.75, -2.25])
    assert opt.state["x"][3].count == 1


# ----------------------------------------------------------------------------- the scene, memory


KEY = "plane.bsdf.reflectance.data"


def _plane(mi):
    """A diffuse plane whose reflectance is an 8x8 texture, seen by an 8x8 camera."""
    return mi.load_dict(
        {
            "type": "scene",
            "integrator": {"type": "direct"},
            "light": {"type": "constant"},
            "sensor": {
                "type": "perspective",
                "to_world": mi.ScalarTransform4f().look_at(
                    origin=[0, 0, 3], target=[0, 0, 0], up=[0, 1, 0]
                ),
                "film": {"type": "hdrfilm", "width": 8, "height": 8},
            },
            "plane": {
                "type": "rectangle",
                "bsdf": {
                    "type": "diffuse",
                    "reflectance": {
                        "type": "bitmap",
                        "raw": True,
                        "data": mi.TensorXf(np.full((8, 8, 3), 0.5, np.float32)),
                    },
                },
            },
        }
    )


def _render_steps(mi, scene, params, opt, iterations):
    """The tutorials' loop: render, loss, backward, step, clip, params.update(opt)."""
    dr = _dr()
    for it in iterations:
        params.update(opt)  # the scene may hold another optimizer's values
        image = mi.render(scene, params, spp=2, seed=it)
        dr.backward(dr.mean(dr.square(image - 0.05), axis=None))  # darker than now
        opt.step()
        opt[KEY] = dr.clip(opt[KEY], 0.0, 1.0)
        params.update(opt)


def test_params_update_puts_the_optimizers_values_in_the_scene(mi):
    from optax_bilateral.mitsuba import BilateralAdam

    scene = _plane(mi)
    params = mi.traverse(scene)
    opt = BilateralAdam(lr=0.05, sigma_d=0.1, levels=1)
    opt[KEY] = params[KEY]
    _render_steps(mi, scene, params, opt, range(2))
    assert np.array_equal(_np(params[KEY]), _np(opt[KEY]))
    assert _np(params[KEY]).mean() < 0.5 - 0.05  # two steps of about lr each
    assert opt.state[KEY][3].count == 2


def test_a_resumed_rendered_loop_follows_the_uninterrupted_one(mi, tmp_path):
    # Mitsuba accumulates rendered gradients with atomics in a varying order, so the two
    # runs agree to float rounding (1e-6 of texels ~0.4 after three steps), not bit for bit.
    from optax_bilateral.mitsuba import BilateralAdam

    scene = _plane(mi)
    params = mi.traverse(scene)
    runs = []
    for _ in range(2):
        opt = BilateralAdam(lr=0.05, sigma_d=0.1, levels=1)
        opt[KEY] = params[KEY]
        runs.append(opt)
    straight, resumed = runs
    _render_steps(mi, scene, params, straight, range(2))
    ob.save_state(tmp_path / "opt.npz", straight.state_dict())
    resumed.load_state_dict(ob.load_state(tmp_path / "opt.npz", resumed.state_dict()))
    _render_steps(mi, scene, params, straight, range(2, 5))
    _render_steps(mi, scene, params, resumed, range(2, 5))
    np.testing.assert_allclose(_np(resumed[KEY]), _np(straight[KEY]), rtol=0, atol=1e-6)
    assert np.abs(_np(straight[KEY]) - 0.5).max() > 0.1


def test_values_and_gradients_cross_without_copies(mi):
    dr = _dr()
    from optax_bilateral.mitsuba import BilateralAdam, to_jax

    def shared(jax_array, dr_array):
        return jax_array.unsafe_buffer_pointer() == np.from_dlpack(dr_array).ctypes.data

    opt = BilateralAdam(lr=0.05, sigma_d=0.1, levels=1)
    opt["tex"] = mi.TensorXf(_texture(0))
    opt["pos"] = mi.Float(np.arange(9, dtype=np.float32))
    targets = {"tex": mi.TensorXf(np.zeros((12, 10, 3), np.float32)), "pos": mi.Float(0.0)}
    for _ in range(2):
        _backward_square(opt, targets)
        for k in opt:
            grad = dr.grad(opt[k])
            dr.eval(grad)
            assert shared(to_jax(grad), grad)  # Dr.Jit's gradient buffers: 64-byte aligned
        opt.step()
        for k in opt:  # the new value is the JAX result's buffer itself
            assert shared(to_jax(dr.detach(opt[k])), opt[k])


# ----------------------------------------------------------------------------- checkpoints


def _run(opt, steps, first):
    rng = np.random.default_rng(first)
    dr = _dr()
    for _ in range(steps):
        import mitsuba as mi

        w = mi.TensorXf(rng.uniform(0, 2, (12, 10, 3)).astype(np.float32))
        _backward_square(
            opt,
            {"tex": mi.TensorXf(np.full((12, 10, 3), 0.3, np.float32)), "c": mi.Color3f(0, 1, 0)},
            {"tex": w},
        )
        opt.step()
        opt["tex"] = dr.clip(opt["tex"], 0.0, 0.6)


def _fresh(mi, lr_c=0.02):
    from optax_bilateral.mitsuba import BilateralAdam

    opt = BilateralAdam(lr=optax.cosine_decay_schedule(0.05, 10), levels=2, log_guide=True)
    opt["tex"] = mi.TensorXf(_texture(9))
    opt["c"] = mi.Color3f(0.5, 0.5, 0.5)
    opt.set_learning_rate(c=lr_c)
    return opt


def test_a_resumed_run_is_bit_identical_to_an_uninterrupted_one(mi, tmp_path):
    # sigma_d="auto" (the default, with a state of its own), a schedule and a per-key rate.
    straight = _fresh(mi)
    _run(straight, 3, first=0)
    ob.save_state(tmp_path / "opt.npz", straight.state_dict())
    _run(straight, 3, first=1)

    resumed = _fresh(mi, lr_c=0.5)  # a new process would rebuild it; the file has the rate
    resumed.load_state_dict(ob.load_state(tmp_path / "opt.npz", resumed.state_dict()))
    assert resumed.learning_rate("c") == pytest.approx(0.02)
    assert resumed.state["tex"][3].count == 3
    _run(resumed, 3, first=1)
    for k in ("tex", "c"):
        np.testing.assert_array_equal(_np(resumed[k]), _np(straight[k]))
        jax.tree.map(
            np.testing.assert_array_equal, resumed.state[k][3].state, straight.state[k][3].state
        )


def test_load_state_dict_names_what_does_not_match(mi):
    from optax_bilateral.mitsuba import BilateralAdam

    saved = _fresh(mi).state_dict()
    other = BilateralAdam(lr=0.05)
    other["tex"] = mi.TensorXf(_texture(9))
    with pytest.raises(ValueError, match=r"keys \['tex'\].*register them"):
        other.load_state_dict(saved)
    other["c"] = mi.Color3f(0.5, 0.5, 0.5)
    other["tex"] = mi.TensorXf(np.zeros((3, 3, 3), np.float32))
    with pytest.raises(ValueError, match=r"saved value of 'tex' is float32\[12, 10, 3\]"):
        other.load_state_dict(saved)


# ------------------------------------------------------------------------ any transform, bad input


def test_optax_optimizer_runs_a_mesh_transform_on_flat_vertex_positions(mi):
    # Large Steps wants (V, 3); a Mitsuba mesh holds its positions flat: `shapes` gives the
    # transform its view, and the optimizer keeps (and params.update writes) the flat Float.
    dr = _dr()
    import optax_bilateral.triangle_mesh as obm
    from optax_bilateral.mitsuba import OptaxOptimizer
    from optax_bilateral.toy import triangle_mesh as toy

    v0, faces = toy.icosphere(2)
    tx = obm.large_steps(0.01, obm.mesh_laplacian(faces), 4.0)
    opt = OptaxOptimizer(tx, shapes={"positions": (-1, 3)})
    opt["positions"] = mi.Float(v0.ravel())
    dr.backward(dr.sum(dr.square(opt["positions"])))  # gradient 2 v: shrink the sphere
    opt.step()
    u, _ = tx.update(2 * jnp.asarray(v0), tx.init(jnp.asarray(v0)), jnp.asarray(v0))
    assert isinstance(opt["positions"], mi.Float)
    np.testing.assert_allclose(_np(opt["positions"]), (v0 + np.asarray(u)).ravel(), atol=1e-6)
    with pytest.raises(ValueError, match=r"shapes\['positions'\] = \(-1, 5\) does not fit"):
        OptaxOptimizer(tx, shapes={"positions": (-1, 5)})["positions"] = mi.Float(v0.ravel())


def test_large_steps_through_optax_optimizer_is_mitsubas_large_steps(mi):
    # The library's large_steps on x and mi.ad.LargeSteps + mi.ad.Adam(uniform=True) on
    # u = (I + lambda L) x are one method: the same positions from the same gradients, up to
    # the solvers' and the two Adams' rounding (1e-5 of the unit sphere's size).
    dr = _dr()
    import optax_bilateral.triangle_mesh as obm
    from optax_bilateral.mitsuba import OptaxOptimizer
    from optax_bilateral.toy import triangle_mesh as toy

    v0, faces = toy.icosphere(4)
    ls = mi.ad.LargeSteps(mi.Float(v0.ravel()), mi.UInt(faces.ravel().astype(np.uint32)), 19.0)
    theirs = mi.ad.Adam(lr=0.01, uniform=True)
    theirs["u"] = ls.to_differential(mi.Float(v0.ravel()))
    ours = OptaxOptimizer(
        obm.large_steps(0.01, obm.mesh_laplacian(faces), 19.0, solver="cholesky"),
        shapes={"x": (-1, 3)},
    )
    ours["x"] = mi.Float(v0.ravel())
    rng = np.random.default_rng(5)
    for _ in range(5):
        g = mi.Float(rng.normal(size=v0.size).astype(np.float32))
        dr.backward(dr.sum(ls.from_differential(theirs["u"]) * g))
        theirs.step()
        dr.backward(dr.sum(ours["x"] * g))
        ours.step()
    x_theirs = _np(ls.from_differential(theirs["u"]))
    np.testing.assert_allclose(_np(ours["x"]), x_theirs, rtol=0, atol=1e-5)
    assert np.abs(x_theirs - v0.ravel()).max() > 0.01  # five steps of about lr


def test_bad_arguments_are_reported_early(mi):
    from optax_bilateral.mitsuba import BilateralAdam, OptaxOptimizer

    with pytest.raises(TypeError, match="GradientTransformation"):
        OptaxOptimizer(0.1)
    with pytest.raises(TypeError, match="lr must be a number"):
        BilateralAdam(lr="fast")
    with pytest.raises(ValueError, match="lr must be finite and >= 0"):
        BilateralAdam(lr=-0.1)
    with pytest.raises(TypeError, match="mask_updates must be a bool"):
        BilateralAdam(lr=0.1, mask_updates=1)
    with pytest.raises(TypeError, match="others must be an optax"):
        BilateralAdam(lr=0.1, others="adam")
    with pytest.raises(ValueError, match="b1"):
        BilateralAdam(lr=0.1, b1=1.5)  # the library's own check, at construction
    opt = BilateralAdam(lr=0.1, sigma_d={"tex": 0.1})
    with pytest.raises(KeyError, match=r"sigma_d is a dict without an entry for 'other'"):
        opt["other"] = mi.TensorXf(_texture(0))
    opt["tex"] = mi.TensorXf(_texture(0))  # per-key settings resolve at registration
    opt["colour"] = mi.Color3f(0.1, 0.2, 0.3)  # not a grid: no sigma_d needed
    with pytest.raises(TypeError, match="differentiable"):
        opt["ints"] = mi.UInt(1, 2)  # Dr.Jit's own check
