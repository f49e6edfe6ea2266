"""sigma_d="sparse", the coverage it reads, coarse_levels and sparse_adam (issue #54)."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

import optax_bilateral as ob
from optax_bilateral._src.optimizer.pyramid import pyramid_reconstruct, pyramid_transpose
from optax_bilateral._src.rules import coverage


def _sparse_grad(shape, every, key=0):
    """Gradients on every ``every``-th texel along the spatial axes (the rest exactly 0)."""
    g = jax.random.normal(jax.random.PRNGKey(key), shape)
    mask = np.zeros(shape, bool)
    mask[tuple(slice(None, None, every) for _ in shape[:-1])] = True
    return jnp.where(mask, g, 0.0)


def _steps(opt, params, grads):
    state = opt.init(params)
    update = jax.jit(opt.update)  # one compile for the steps (eager dispatch is slower)
    out = []
    for g in grads:
        d, state = update(g, state, params)
        out.append(d)
    return out, state


# ----------------------------------------------------------------------------- the coverage


def test_the_coverage_is_the_share_of_touched_texels_per_block():
    touched = np.zeros((16, 12), bool)
    touched[:8, :8] = True  # the first block full, the others empty
    touched[8, 8] = True  # one texel in 8 x 4 (the last row's blocks are partial: 8 x 4)
    out = coverage.update(
        coverage.init((16, 12), (0, 1), 8), jnp.asarray(touched), block=8, decay=0.9
    )
    untouched = np.asarray(out.state.untouched) / float(out.state.weight)
    np.testing.assert_allclose(untouched, [[0.0, 1.0], [1.0, 31 / 32]], rtol=1e-6)
    assert 0 < float(out.mean) <= 1
    assert out.field.shape == (2, 2)


def test_the_coverage_of_a_step_that_touches_nothing_is_one_and_finite():
    out = coverage.update(
        coverage.init((20, 20), (0, 1), 8), jnp.zeros((20, 20), bool), block=8, decay=0.9
    )
    assert float(out.mean) == 1.0  # no block was ever touched: nothing says it is sparse
    assert np.all(np.asarray(out.field) == 0)


@pytest.mark.parametrize("decay", [0.0, 0.5, 0.9, 0.999])
def test_a_block_touched_at_every_step_has_a_coverage_of_exactly_one(decay):
    state = coverage.init((24, 16), (0, 1), 8)
    for _ in range(7):
        out = coverage.update(state, jnp.ones((24, 16), bool), block=8, decay=decay)
        state = out.state
        assert np.all(np.asarray(out.field) == 1.0) and float(out.mean) == 1.0


def test_the_coverage_follows_a_camera_that_looks_away():
    state = coverage.init((8, 8), (0, 1), 8)
    fields = []
    for touched in [True] * 3 + [False] * 3:
        out = coverage.update(state, jnp.full((8, 8), touched), block=8, decay=0.5)
        state = out.state
        fields.append(float(out.field[0, 0]))
    assert fields[:3] == [1.0, 1.0, 1.0]
    assert fields[3] > fields[4] > fields[5] > 0  # the average forgets, bias-corrected


def test_expand_spreads_blocks_over_the_leaf_with_unit_channel_axes():
    x = jnp.arange(6.0).reshape(2, 3)
    out = coverage.expand(x, (10, 20, 3), (0, 1), 8)
    assert out.shape == (10, 20, 1)
    assert float(out[9, 19, 0]) == 5.0 and float(out[7, 7, 0]) == 0.0


# ----------------------------------------------------------------------------- sigma_d="sparse"


@pytest.mark.parametrize(
    "shape, axes", [((24, 20, 3), (0, 1)), ((10, 8, 12, 1), (0, 1, 2)), ((64, 1), (0,))]
)
def test_sparse_is_auto_on_a_gradient_that_touches_every_texel(shape, axes):
    params = jax.random.uniform(jax.random.PRNGKey(9), shape)
    grads = [jax.random.normal(jax.random.PRNGKey(i), shape) + 0.1 for i in range(3)]
    a, _ = _steps(ob.bilateral_adam(0.02, spatial_axes=axes), params, grads)
    b, _ = _steps(ob.bilateral_adam(0.02, sigma_d="sparse", spatial_axes=axes), params, grads)
    for x, y in zip(a, b):
        np.testing.assert_allclose(x, y, rtol=1e-5, atol=1e-9)


def test_sparse_divides_the_filtered_first_moment_by_the_root_of_the_coverage():
    params = jnp.full((32, 32, 3), 0.5)
    g = _sparse_grad(params.shape, 8)  # one texel in 64: the boost is 8
    rule = ob.sparse_sigma(sparse_levels=0)
    (a,), _ = _steps(ob.postfilter(), params, [g])
    (b,), state = _steps(ob.postfilter(sigma_d=rule), params, [g])
    assert isinstance(state.sigma_state, ob.SparseState)
    moved = np.abs(np.asarray(a)) > 1e-6
    assert moved.mean() > 0.5  # the filter spread the few values
    np.testing.assert_allclose(np.asarray(b)[moved] / np.asarray(a)[moved], 8.0, rtol=1e-4)


def test_the_boost_is_capped_at_max_boost():
    params = jnp.full((32, 32, 3), 0.5)
    g = _sparse_grad(params.shape, 16)  # one texel in 256: 16 uncapped
    (a,), _ = _steps(ob.postfilter(), params, [g])
    (b,), _ = _steps(ob.postfilter(sigma_d=ob.sparse_sigma(sparse_levels=0)), params, [g])
    moved = np.abs(np.asarray(a)) > 1e-6
    np.testing.assert_allclose(np.asarray(b)[moved] / np.asarray(a)[moved], 8.0, rtol=1e-4)


def test_a_sparse_leaf_runs_sparse_levels_more_levels():
    params = jax.random.uniform(jax.random.PRNGKey(1), (32, 32, 3))
    g = _sparse_grad(params.shape, 8)
    (wide,), _ = _steps(ob.postfilter(levels=4), params, [g])
    (b,), _ = _steps(ob.postfilter(sigma_d="sparse", levels=3), params, [g])
    moved = np.abs(np.asarray(wide)) > 1e-6
    np.testing.assert_allclose(np.asarray(b)[moved] / np.asarray(wide)[moved], 8.0, rtol=1e-4)


@pytest.mark.parametrize("wide", [False, True])
def test_a_widened_cascade_and_more_levels_continue_the_widened_one(wide):
    # "auto"'s correlated-noise way asks for F + k levels at once on the native kernel
    # (rules/auto.py, Auto._cascade); on a sparse leaf that must stay the widened cascade
    # continued from level F, as the way's continuation elsewhere, to the bit.
    from optax_bilateral._src.filter import operators
    from optax_bilateral._src.rules import sparse

    rng = np.random.default_rng(3)
    m, v = (jnp.asarray(rng.normal(size=(40, 36, 3)), jnp.float32) for _ in range(2))
    guide = jnp.asarray(rng.normal(size=(40, 36, 3)), jnp.float32)
    plan = operators.FilterPlan((0, 1), 3, True, False, False)
    base = operators.CrossGuided(plan, guide)
    op = sparse._Widened(base, 1, jnp.asarray(wide))
    widened = op.apply((m, v), 0.4)
    want = base.apply(widened, 0.4, levels=5, first_level=3)
    got = op.apply((m, v), 0.4, levels=5)
    for a, b in zip(got, want):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    # A part the caller chose runs as asked.
    part = op.apply((m, v), 0.4, levels=2)
    for a, b in zip(part, base.apply((m, v), 0.4, levels=2)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


@pytest.mark.parametrize("wide", [False, True])
@pytest.mark.parametrize("levels", [None, 5])
def test_a_widened_cascade_in_one_call_equals_its_continuation(wide, levels):
    # On the native kernel each branch runs its own cascade from the fields (no continuation
    # of level F's output inside the conditional, which XLA copied); the same numbers, to the
    # bit, as the continuation the other kernels run.
    from optax_bilateral._src.filter import operators
    from optax_bilateral._src.rules import sparse

    rng = np.random.default_rng(4)
    m, v = (jnp.asarray(rng.normal(size=(40, 36, 3)), jnp.float32) for _ in range(2))
    guide = jnp.asarray(rng.normal(size=(40, 36, 3)), jnp.float32)
    plan = operators.FilterPlan((0, 1), 3, True, False, False)
    op = sparse._Widened(operators.CrossGuided(plan, guide), 1, jnp.asarray(wide))
    assert sparse.runs_native(m)
    got = jax.jit(lambda f: op.apply(f, 0.4, levels))((m, v))
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(sparse, "runs_native", lambda x: False)
        want = jax.jit(lambda f: op.apply(f, 0.4, levels))((m, v))
    for a, b in zip(got, want, strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_a_leaf_above_sparse_below_keeps_its_levels():
    params = jax.random.uniform(jax.random.PRNGKey(1), (32, 32, 3))
    g = _sparse_grad(params.shape, 2)  # a quarter of the texels: at sparse_below
    rule = ob.sparse_sigma(sparse_below=0.2)
    (a,), _ = _steps(ob.postfilter(levels=3), params, [g])
    (b,), _ = _steps(ob.postfilter(sigma_d=rule, levels=3), params, [g])
    moved = np.abs(np.asarray(a)) > 1e-6
    np.testing.assert_allclose(np.asarray(b)[moved] / np.asarray(a)[moved], 2.0, rtol=1e-4)


@pytest.mark.parametrize("fill", [0.0, np.nan])
def test_an_untouched_or_unobserved_leaf_steps_by_zero(fill):
    params = jnp.full((9, 7, 3), 0.5)  # smaller than one block
    opt = ob.bilateral_adam(0.02, sigma_d="sparse")
    grads = [jnp.full(params.shape, fill)] * 2
    out, state = _steps(opt, params, grads)
    for d in out:
        assert np.all(np.asarray(d) == 0)
    assert all(np.all(np.isfinite(x)) for x in jax.tree.leaves(state[0].sigma_state.coverage))


def test_sparse_runs_under_jit_and_its_state_checkpoints(tmp_path):
    params = {"tex": jnp.full((24, 24, 3), 0.5), "exposure": jnp.zeros(())}
    opt = ob.bilateral_adam(0.02, sigma_d="sparse")
    state = opt.init(params)
    update = jax.jit(opt.update)
    for i in range(3):
        g = {"tex": _sparse_grad((24, 24, 3), 4, key=i), "exposure": jnp.ones(())}
        _, state = update(g, state, params)
    ob.save_state(tmp_path / "s.npz", state)
    restored = ob.load_state(tmp_path / "s.npz", opt.init(params))
    for a, b in zip(jax.tree.leaves(restored), jax.tree.leaves(state)):
        np.testing.assert_array_equal(a, b)


def test_sparse_runs_memoryless_where_its_boost_applies_to_the_filtered_gradient():
    params = jnp.full((32, 32, 3), 0.5)
    g = _sparse_grad(params.shape, 8)
    rule = ob.sparse_sigma(sparse_levels=0)
    (a,), _ = _steps(ob.postfilter(b1=0.0, b2=0.0), params, [g])
    (b,), _ = _steps(ob.postfilter(b1=0.0, b2=0.0, sigma_d=rule), params, [g])
    moved = np.abs(np.asarray(a)) > 1e-6
    np.testing.assert_allclose(np.asarray(b)[moved] / np.asarray(a)[moved], 8.0, rtol=1e-4)


def test_sparse_refuses_a_prefilter_naming_why():
    with pytest.raises(ValueError, match=r"sigma_d='sparse'.*prefilter.*'auto'"):
        ob.prefilter(sigma_d="sparse")


def test_a_coverage_at_or_above_full_coverage_is_not_boosted():
    params = jnp.full((32, 32, 3), 0.5)
    g = _sparse_grad(params.shape, 2)  # one texel in 4: a boost of 2 at full_coverage 1
    (a,), _ = _steps(ob.postfilter(), params, [g])
    moved = np.abs(np.asarray(a)) > 1e-6
    for full, boost in ((1.0, 2.0), (0.64, 1.6), (0.25, 1.0), (0.1, 1.0)):
        rule = ob.sparse_sigma(sparse_levels=0, full_coverage=full)
        (b,), _ = _steps(ob.postfilter(sigma_d=rule), params, [g])
        np.testing.assert_allclose(
            np.asarray(b)[moved] / np.asarray(a)[moved], boost, rtol=1e-4, err_msg=f"{full}"
        )


@pytest.mark.parametrize(
    "field, value, error",
    [
        ("full_coverage", 0.0, ValueError),
        ("full_coverage", 1.5, ValueError),
        ("block", 0, ValueError),
        ("block", 2.0, TypeError),
        ("decay", 1.0, ValueError),
        ("decay", -0.1, ValueError),
        ("max_boost", 0.5, ValueError),
        ("sparse_below", 1.5, ValueError),
        ("sparse_levels", -1, ValueError),
        ("auto", "auto", TypeError),
    ],
)
def test_sparse_sigma_names_a_bad_field(field, value, error):
    with pytest.raises(error, match=field):
        ob.sparse_sigma(**{field: value})


# ----------------------------------------------------------------------------- coarse_levels


def test_coarse_levels_adds_nothing_where_every_texel_is_touched():
    params = jnp.zeros((16, 16, 3))
    inner = optax.adam(0.01)
    opt = ob.coarse_levels(inner, 0.01, levels=3)
    g = jax.random.normal(jax.random.PRNGKey(0), params.shape) + 2.0  # no zero entry
    a, _ = inner.update(g, inner.init(params))
    b, _ = opt.update(g, opt.init(params))
    np.testing.assert_allclose(a, b, rtol=1e-6)


def test_coarse_levels_adds_adams_coarse_steps_times_share_and_sparsity():
    params = jnp.zeros((16, 16, 3))
    g = _sparse_grad(params.shape, 8)  # every block touched at 1/64
    lr, share = 0.01, 0.5
    inner = optax.sgd(0.0)  # no step of its own: the coarse path alone
    opt = ob.coarse_levels(inner, lr, levels=3, share=share)
    out, _ = opt.update(g, opt.init(params))
    coeffs = pyramid_transpose(g, 3, (0, 1))
    adam_first = [-lr * c / (jnp.abs(c) + 1e-8) for c in coeffs[1:]]  # Adam's first step
    coverage_mean = 1 / 64
    expect = (
        share
        * (1 - coverage_mean)
        * pyramid_reconstruct((jnp.zeros_like(g),) + tuple(adam_first), (0, 1))
    )
    np.testing.assert_allclose(out, expect, rtol=1e-4, atol=1e-9)


def test_coarse_levels_passes_leaves_without_grid_and_ignores_non_finite_entries():
    params = {"tex": jnp.zeros((16, 16, 3)), "gain": jnp.zeros(())}
    inner = optax.adam(0.01)
    opt = ob.coarse_levels(inner, lambda count: 0.01, levels=3)
    tex = _sparse_grad((16, 16, 3), 4).at[3, 3, 0].set(jnp.nan)
    g = {"tex": tex, "gain": jnp.ones(())}
    out, state = jax.jit(opt.update)(g, opt.init(params))
    a, _ = inner.update(g, inner.init(params))
    np.testing.assert_allclose(out["gain"], a["gain"], rtol=1e-6)
    finite = np.isfinite(np.asarray(a["tex"]))
    assert np.all(np.isfinite(np.asarray(out["tex"])[finite]))
    assert state.coverage[0] is None  # the scalar ("gain", the first leaf) has no coverage


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"levels": 1}, "levels must be an int >= 2"),
        ({"levels": 2.5}, "levels"),
        ({"share": 0.0}, "share"),
        ({"block": 0}, "block"),
        ({"decay": 1.0}, "decay"),
    ],
)
def test_coarse_levels_names_a_bad_argument(kwargs, match):
    with pytest.raises((ValueError, TypeError), match=match):
        ob.coarse_levels(optax.adam(0.01), 0.01, **kwargs)


# ----------------------------------------------------------------------------- sparse_adam


def test_sparse_adam_is_bilateral_adam_on_a_gradient_that_touches_every_texel():
    params = jax.random.uniform(jax.random.PRNGKey(3), (24, 24, 3))
    grads = [jax.random.normal(jax.random.PRNGKey(i), params.shape) + 0.1 for i in range(3)]
    a, _ = _steps(ob.bilateral_adam(0.02), params, grads)
    b, state = _steps(ob.sparse_adam(0.02), params, grads)
    assert isinstance(state, ob.CoarseLevelsState)
    for x, y in zip(a, b):
        np.testing.assert_allclose(x, y, rtol=1e-5, atol=1e-9)


def test_sparse_adam_runs_the_sparse_rule_without_its_extra_level():
    # Its coarse path gives the far reach: the default rule adds no filter level on a
    # sparse leaf and counts a coverage of 0.8 as full, and sigma_d="sparse" (which adds the
    # level and boosts up to a coverage of 1) is a different update there.
    params = jax.random.uniform(jax.random.PRNGKey(4), (48, 48, 3))
    grads = [_sparse_grad(params.shape, 6, key=k) for k in range(3)]
    no_level = ob.sparse_sigma(sparse_levels=0, full_coverage=0.8)
    written_out = ob.coarse_levels(ob.bilateral_adam(0.02, sigma_d=no_level), 0.02, share=0.3)
    a, _ = _steps(ob.sparse_adam(0.02), params, grads)
    b, _ = _steps(written_out, params, grads)
    c, _ = _steps(ob.sparse_adam(0.02, sigma_d="sparse"), params, grads)
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x, y)
    assert float(jnp.max(jnp.abs(a[-1] - c[-1]))) > 1e-6 * float(jnp.max(jnp.abs(a[-1])))


def test_sparse_adam_names_a_bad_sigma_d():
    with pytest.raises((ValueError, TypeError), match="sigma_d"):
        ob.sparse_adam(0.02, sigma_d="sharp")


def test_sparse_adam_moves_texels_a_far_camera_never_touched():
    params = jnp.full((64, 64, 3), 0.5)
    grads = [_sparse_grad(params.shape, 32)]  # beyond F = 3's reach
    (a,), _ = _steps(ob.bilateral_adam(0.02), params, grads)
    (b,), _ = _steps(ob.sparse_adam(0.02), params, grads)
    unmoved = np.abs(np.asarray(a)) == 0
    assert 0.1 < unmoved.mean() < 1  # the filter alone leaves these where they were
    assert (np.abs(np.asarray(b))[unmoved] > 0).mean() > 0.5  # the coarse path moves them
    assert math.isfinite(float(jnp.sum(b)))
