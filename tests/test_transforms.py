"""The Optax transforms: Adam equivalence, the paper's equations, composition and interop."""

import functools
import inspect
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import optax
import optimistix as optx
import pytest
from hypothesis import given
from hypothesis import strategies as st

import jaxprs
import optax_bilateral as ob
from optax_bilateral import atrous_bilateral

KEY = jax.random.PRNGKey(0)


def _grads(i, like, scale=1.0):
    return jax.tree.map(
        lambda p: scale * jax.random.normal(jax.random.fold_in(KEY, i), p.shape, p.dtype), like
    )


def _run(opt, params, steps, noise=1.0, jit=True):
    state = opt.init(params)
    upd = jax.jit(opt.update) if jit else opt.update
    out = []
    for i in range(steps):
        g = _grads(i, params, noise)
        u, state = upd(g, state, params)
        params = optax.apply_updates(params, u)
        out.append((g, u))
    return params, state, out


# --- Adam equivalence -------------------------------------------------------------------


@pytest.mark.parametrize("b1,b2,eps_root", [(0.9, 0.999, 0.0), (0.2, 0.36, 1e-8), (0.0, 0.5, 0.0)])
def test_scale_by_adam_equals_optax(b1, b2, eps_root):
    params = {"a": jnp.zeros((6, 5, 2)), "b": jnp.zeros(())}
    ours, theirs = (
        ob.scale_by_adam(b1, b2, 1e-8, eps_root),
        optax.scale_by_adam(b1, b2, 1e-8, eps_root),
    )
    s1, s2 = ours.init(params), theirs.init(params)
    u1f, u2f = jax.jit(ours.update), jax.jit(theirs.update)
    for i in range(35):
        g = _grads(i, params)
        u1, s1 = u1f(g, s1, params)
        u2, s2 = u2f(g, s2, params)
        # Same arithmetic in the same order, compiled the same way: bit-identical.
        jax.tree.map(
            lambda a, b: np.testing.assert_array_equal(np.asarray(a), np.asarray(b)), u1, u2
        )
        jax.tree.map(
            lambda a, b: np.testing.assert_array_equal(np.asarray(a), np.asarray(b)),
            (s1.mu, s1.nu),
            (s2.mu, s2.nu),
        )


@pytest.mark.parametrize("prefilter", [False, True])
def test_bilateral_adam_levels_zero_equals_optax_adam(prefilter):
    params = {"tex": jnp.full((8, 8, 3), 0.5), "light": jnp.ones(())}
    ours = ob.bilateral_adam(0.05, 0.3, 0.7, 1e-6, levels=0, prefilter=prefilter)
    theirs = optax.adam(0.05, 0.3, 0.7, 1e-6)
    _, _, t1 = _run(ours, params, 30)
    _, _, t2 = _run(theirs, params, 30)
    # Same formula; XLA fuses the two programs differently, so agreement is to a few ulps.
    for (_, a), (_, b) in zip(t1, t2):
        jax.tree.map(
            lambda x, y: np.testing.assert_allclose(
                np.asarray(x), np.asarray(y), rtol=5e-7, atol=1e-9
            ),
            a,
            b,
        )


def test_default_b2_is_one_minus_squared():
    params = jnp.zeros((6, 6))
    a = optax.chain(ob.postfilter(0.2, levels=0), optax.scale_by_learning_rate(0.1))
    b = optax.adam(0.1, 0.2, 1 - 0.8**2)
    _, _, t1 = _run(a, params, 5)
    _, _, t2 = _run(b, params, 5)
    np.testing.assert_allclose(np.asarray(t1[-1][1]), np.asarray(t2[-1][1]), rtol=5e-7)


# --- The paper's equations ----------------------------------------------------------------


def _B(x, guide, sigma_d, levels, separable=True, first=0):
    """The filter; ``first=1``: only its level 1 (stride 2), guided by ``x`` itself, as the
    stride-1 filter of each of the 4 interleaved sub-grids."""
    if first:
        assert first == 1 and levels == 2
        out = jnp.zeros_like(x)
        for i in range(2):
            for j in range(2):
                sub = x[i::2, j::2]
                out = out.at[i::2, j::2].set(_B(sub, sub, sigma_d, 1, separable))
        return out
    return atrous_bilateral(
        x, guide, sigma_d=sigma_d, levels=levels, spatial_axes=(0, 1), separable=separable
    )


def test_new_options_refuse_bad_values():
    with pytest.raises(ValueError, match="second_moment"):
        ob.postfilter(second_moment="max")
    with pytest.raises(ValueError, match="second_moment"):
        ob.bilateral_adam(0.1, second_moment="per-texel")
    with pytest.raises(TypeError, match="filter_m"):
        ob.postfilter(filter_m="yes")  # pyright: ignore[reportArgumentType]
    with pytest.raises(TypeError, match="filter_v"):
        ob.bilateral_adam(0.1, filter_v=None)  # pyright: ignore[reportArgumentType]
    with pytest.raises(ValueError, match="weight_decay"):
        ob.bilateral_adam(0.1, weight_decay=-1e-3)
    x = jnp.ones((8, 8, 2))
    with pytest.raises(ValueError, match="guide must be an array or 'self'"):
        atrous_bilateral(x, "params", sigma_d=0.1, levels=1, spatial_axes=(0, 1))  # pyright: ignore[reportArgumentType]
    with pytest.raises(ValueError, match="guide_axes"):
        atrous_bilateral(x, "self", sigma_d=0.1, levels=1, spatial_axes=(0, 1), guide_axes=(0, 1))


def test_uniform_second_moment_counts_unobserved_texels_by_their_kept_moments():
    """A NaN texel takes the masked path: its update is 0, its moments are kept, and the
    leaf's one denominator is the max over the observed texels' B v and its kept v."""
    theta = jax.random.uniform(KEY, (8, 8, 2)) + 0.1
    post = ob.postfilter(0.2, 0.36, 0.0, sigma_d=0.3, levels=2, second_moment="uniform")
    state = post.init(theta)
    g0 = _grads(0, theta).at[3, 3].set(10.0)  # a large v at (3, 3), kept below
    _, state = jax.jit(post.update)(g0, state, theta)
    g1 = _grads(1, theta).at[3, 3, 0].set(jnp.nan)
    u, new = jax.jit(post.update)(g1, state, theta)
    assert state.nu is not None and new.nu is not None and new.mu is not None
    np.testing.assert_array_equal(np.asarray(u[3, 3]), 0.0)
    np.testing.assert_array_equal(np.asarray(new.nu[3, 3]), np.asarray(state.nu[3, 3]))
    obs = jnp.ones((8, 8), bool).at[3, 3].set(False)
    m_f, v_f = atrous_bilateral(
        (new.mu, new.nu),
        jnp.where(obs[..., None], theta, jnp.nan),
        sigma_d=0.3,
        levels=2,
        spatial_axes=(0, 1),
    )
    v_max = jnp.max(jnp.where(obs[..., None], v_f, new.nu))
    want = (m_f / (1 - 0.2**2)) / jnp.sqrt(v_max / (1 - 0.36**2))
    np.testing.assert_allclose(
        np.asarray(u)[np.asarray(obs)], np.asarray(want)[np.asarray(obs)], rtol=2e-5
    )


@pytest.mark.parametrize("separable", [True, False])
def test_postfilter_matches_eq_11_and_keeps_unfiltered_moments(separable):
    """chain(prefilter, postfilter) after 4 steps against a by-hand evaluation of eq. 11."""
    b1, b2, eps, sig, F = 0.3, 0.6, 1e-8, 0.4, 2
    theta = jax.random.uniform(KEY, (9, 7, 2))
    opt = optax.chain(
        ob.prefilter(sig, F, separable=separable),
        ob.postfilter(b1, b2, eps, sigma_d=sig, levels=F, separable=separable),
    )
    state = opt.init(theta)
    m = v = jnp.zeros_like(theta)
    for t in range(1, 5):
        g = _grads(t, theta)
        u, state = jax.jit(opt.update)(g, state, theta)
        ag = _B(g, theta, sig, F, separable)
        m, v = b1 * m + (1 - b1) * ag, b2 * v + (1 - b2) * ag**2
        bm, bv = _B((m, v), theta, sig, F, separable)
        expect = (bm / (1 - b1**t)) / (jnp.sqrt(bv / (1 - b2**t)) + eps)
        np.testing.assert_allclose(np.asarray(u), np.asarray(expect), rtol=2e-5, atol=1e-6)
        theta = theta - 0.01 * u
    # The state holds the unfiltered EMAs (eqs. 2, 4), not B m / B v.
    post_state = state[1]
    np.testing.assert_allclose(np.asarray(post_state.mu), np.asarray(m), rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(np.asarray(post_state.nu), np.asarray(v), rtol=1e-5, atol=1e-7)


def test_memoryless_limits_eqs_15_to_17():
    theta = jax.random.uniform(KEY, (10, 10, 3))
    g = _grads(3, theta)
    # Adam: sign(g) up to eps (eq. 15).
    u, _ = jax.jit(ob.scale_by_adam(0.0, 0.0, 1e-12).update)(
        g, ob.scale_by_adam(0.0, 0.0).init(theta), theta
    )
    np.testing.assert_allclose(np.asarray(u), np.sign(np.asarray(g)), rtol=1e-6)
    # Prefilter + Adam: sign(A g) (eq. 16).
    ch = optax.chain(ob.prefilter(0.3, 3), ob.scale_by_adam(0.0, 0.0, 1e-12))
    u, _ = jax.jit(ch.update)(g, ch.init(theta), theta)
    np.testing.assert_allclose(np.asarray(u), np.sign(np.asarray(_B(g, theta, 0.3, 3))), rtol=1e-6)
    # Postfilter: B g / sqrt(B g^2) (eq. 17), with no param-sized buffers in the state.
    post = ob.postfilter(0.0, 0.0, 0.0, sigma_d=0.3, levels=3)
    state = post.init(theta)
    assert all(np.size(x) <= 1 for x in jax.tree.leaves(state))
    u, state = jax.jit(post.update)(g, state, theta)
    bg, bg2 = _B((g, g * g), theta, 0.3, 3)
    np.testing.assert_allclose(np.asarray(u), np.asarray(bg / jnp.sqrt(bg2)), rtol=1e-5)
    assert all(np.size(x) <= 1 for x in jax.tree.leaves(state))
    # Unlike sign steps, its magnitude falls as noise grows (eq. 24).
    signal = jnp.ones_like(theta)
    mags = []
    for noise in (0.1, 1.0, 10.0):
        u, _ = jax.jit(post.update)(signal + noise * g, post.init(theta), theta)
        mags.append(float(jnp.mean(jnp.abs(u))))
    assert mags[0] > mags[1] > mags[2]


@functools.cache
def _bounded_update(levels, separable):
    """One compiled postfilter per (levels, separable); b1, b2 and sigma_d are traced."""
    post = optax.inject_hyperparams(ob.postfilter, static_args=("levels", "separable"))(
        b1=0.2,
        b2=0.36,
        eps=0.0,
        sigma_d=0.3,
        levels=levels,
        separable=separable,
        spatial_axes=(0, 1),
    )
    return post, jax.jit(post.update)


@given(
    seed=st.integers(0, 2**31 - 1),
    sigma_d=st.sampled_from([0.0, 0.05, 0.5, np.inf]),
    b1=st.sampled_from([0.0, 0.2, 0.9]),
    levels=st.sampled_from([1, 3]),
    separable=st.booleans(),
    scale=st.sampled_from([1e-3, 1.0, 1e3]),
)
def test_postfilter_step_is_bounded_supplement_1_3(seed, sigma_d, b1, levels, separable, scale):
    """|Delta| <= max_k |m_hat_k| / sqrt(v_hat_k) for the cross-bilateral postfilter."""
    b2 = 1 - (1 - b1) ** 2
    key = jax.random.PRNGKey(seed)
    theta = jax.random.uniform(key, (6, 5, 2))
    post, upd = _bounded_update(levels, separable)
    state = post.init(theta)
    state = state._replace(
        hyperparams={
            **state.hyperparams,
            "b1": jnp.float32(b1),
            "b2": jnp.float32(b2),
            "sigma_d": jnp.float32(sigma_d),
        }
    )
    for t in range(1, 6):
        g = scale * jax.random.normal(jax.random.fold_in(key, t), theta.shape)
        u, state = upd(g, state, theta)
        inner = state.inner_state
        # The traced b1, b2 are float32: the bias corrections use those values.
        c1 = 1 - np.float32(b1) ** t if b1 else 1.0
        c2 = 1 - np.float32(b2) ** t if b2 else 1.0
        m_hat, v_hat = inner.mu / c1, inner.nu / c2
        bound = float(jnp.max(jnp.abs(m_hat) / jnp.sqrt(v_hat)))
        assert float(jnp.max(jnp.abs(u))) <= bound * (1 + 1e-5)  # float32 rounding of the ratio


# --- Leaves, guides, masks -----------------------------------------------------------------


def test_default_leaf_rule():
    rule = lambda *shape: ob.default_spatial_axes(jnp.zeros(shape))
    assert rule() == () and rule(5) == ()
    assert rule(16, 12, 3) == (0, 1) and rule(5, 6, 4) == (0, 1)  # (H, W, C): textures
    assert rule(16, 12) == () and rule(784, 128) == ()  # (H, W), or weights: Adam's
    assert rule(4, 8) == () and rule(8, 4) == ()  # weight matrices
    assert rule(1024) == () and rule(64, 3) == ()  # 1-D signals, or weights: Adam's
    assert rule(3, 16, 16) == ()  # (C, H, W)
    assert rule(16, 16, 16) == ()  # scalar (D, H, W) volume
    assert rule(8, 9, 10, 1) == (0, 1, 2)  # (D, H, W, C) volume
    assert rule(4, 16, 16, 3) == ()  # a batch of 4 textures
    assert rule(3, 3, 16, 32) == ()  # a conv kernel


@pytest.mark.parametrize(
    "shape,axes,advice",
    [
        ((1024,), (), "spatial_axes=(0,)"),
        ((16,), (), "spatial_axes=(0,)"),
        ((24, 20), (), "spatial_axes=(0, 1)"),
        ((784, 128), (), "spatial_axes=(0, 1)"),
        ((8, 8), (), "spatial_axes=(0, 1)"),
        ((64, 3), (), "spatial_axes=(0,)"),
        ((2, 100), (), "spatial_axes=(1,)"),
        ((3, 16, 16), (), "spatial_axes=(1, 2)"),
        ((16, 16, 16), (), "spatial_axes=(0, 1, 2)"),
        ((2, 16, 16, 16, 3), (), "spatial_axes"),
    ],
)
def test_ambiguous_leaves_warn_once_naming_the_leaf_and_the_setting(shape, axes, advice):
    name = "leaf_" + "x".join(map(str, shape))
    params = {name: jnp.zeros(shape), "tex": jnp.zeros((8, 8, 3)), "b": jnp.zeros(4)}
    assert ob.filtered_axes(params) == {f"['{name}']": axes, "['tex']": (0, 1), "['b']": ()}
    opt = ob.bilateral_adam(0.1, levels=1)
    with pytest.warns(ob.LeafRuleWarning) as record:
        opt.init(params)
    assert len(record) == 1  # the texture and the vector are no guess
    text = str(record[0].message)
    assert f"['{name}']" in text and str(shape) in text and advice in text
    with warnings.catch_warnings():
        warnings.simplefilter("error", ob.LeafRuleWarning)
        opt.init(params)  # once per leaf and process
        # An explicit setting is no guess either.
        ob.bilateral_adam(0.1, levels=1, spatial_axes={name: axes, "tex": (0, 1), "b": ()}).init(
            {**params, name: jnp.ones(shape)}
        )


def test_one_init_warns_once_naming_every_guessed_leaf():
    params = {"w": jnp.zeros((40, 41)), "curve": jnp.zeros(37), "tex": jnp.zeros((8, 8, 3))}
    with pytest.warns(ob.LeafRuleWarning) as record:
        ob.bilateral_adam(0.1).init(params)
    assert len(record) == 1
    text = str(record[0].message)
    assert "2 leaf(s)" in text and "['w'] of shape (40, 41)" in text
    assert "['curve'] of shape (37,)" in text and "spatial_axes=(0,)" in text
    assert "['tex']" not in text and 'spatial_axes="default"' in text


def test_spatial_axes_default_is_the_rule_without_its_warning():
    params = {"w2": jnp.zeros((40, 43)), "v2": jnp.zeros(39), "tex": jnp.zeros((8, 8, 3))}
    assert ob.filtered_axes(params, spatial_axes="default") == ob.filtered_axes(params)
    prefix = {"w2": "default", "v2": (0,), "tex": "default"}
    assert ob.filtered_axes(params, spatial_axes=prefix) == {
        "['tex']": (0, 1),
        "['v2']": (0,),
        "['w2']": (),
    }
    with warnings.catch_warnings():
        warnings.simplefilter("error", ob.LeafRuleWarning)
        for setting in ("default", prefix):
            opt = ob.bilateral_adam(0.1, spatial_axes=setting)
            opt.update(jax.tree.map(jnp.ones_like, params), opt.init(params), params)
    with pytest.raises(TypeError, match='spatial_axes must be None, "default"'):
        ob.bilateral_adam(0.1, spatial_axes="auto")


@pytest.mark.parametrize(
    "shape,axes",
    [
        ((), ()),
        ((15,), ()),
        ((4, 8), ()),
        ((8, 4), ()),
        ((3, 3, 3), ()),
        ((8, 8, 3), (0, 1)),
        ((16, 8, 8, 3), (0, 1, 2)),
        ((5, 5, 5, 1), (0, 1, 2)),
    ],
)
def test_leaves_that_read_one_way_are_decided_silently(shape, axes):
    params = {"leaf": jnp.zeros(shape)}
    assert ob.filtered_axes(params) == {"['leaf']": axes}
    with warnings.catch_warnings():
        warnings.simplefilter("error", ob.LeafRuleWarning)
        ob.bilateral_adam(0.1, levels=1).init(params)


def test_the_leaf_rule_warning_points_at_the_users_line_through_optax_wrappers():
    opt = optax.MultiSteps(optax.chain(optax.clip(1.0), ob.bilateral_adam(0.1)), 2)
    with pytest.warns(ob.LeafRuleWarning) as record:
        line = inspect.currentframe().f_lineno + 1
        opt.init({"stacklevel_probe": jnp.zeros((40, 40))})
    assert (record[0].filename, record[0].lineno) == (__file__, line)


def test_filtered_axes_resolves_prefixes_callables_and_levels():
    params = {"a": jnp.zeros((3, 8, 8)), "b": jnp.zeros((8, 8, 3)), "c": jnp.zeros(())}
    assert ob.filtered_axes(params, spatial_axes={"a": (1, 2), "b": None, "c": ()}) == {
        "['a']": (1, 2),
        "['b']": (0, 1),
        "['c']": (),
    }
    assert ob.filtered_axes(
        params, spatial_axes=lambda x: (1, 2) if x.shape[:1] == (3,) else ()
    ) == {"['a']": (1, 2), "['b']": (), "['c']": ()}
    assert ob.filtered_axes(params, levels={"a": 0, "b": 2, "c": 0}) == {
        "['a']": (),
        "['b']": (0, 1),
        "['c']": (),
    }


@pytest.mark.parametrize(
    "make",
    [
        lambda: ob.bilateral_adam(0.1),
        lambda: ob.prefilter(),
        lambda: ob.scale_by_adam(),
        lambda: ob.bilateral_adam(0.1, levels=0),
    ],
)
def test_complex_parameters_are_taken_and_the_raw_filter_refuses_complex_fields(make):
    # The transforms take complex leaves through their real view (tests/test_complex.py);
    # atrous_bilateral, which has no such view, refuses complex fields and guides.
    params = {"tex": jnp.zeros((8, 8, 2), jnp.complex64), "s": jnp.zeros(())}
    state = make().init(params)
    dtypes = {x.dtype for x in jax.tree.leaves(state)}
    assert dtypes <= {jnp.dtype(jnp.complex64), jnp.dtype(jnp.float32), jnp.dtype(jnp.int32)}
    with pytest.raises(TypeError, match="complex"):
        ob.atrous_bilateral(
            jnp.zeros((8, 8), jnp.complex64),
            jnp.zeros((8, 8)),
            sigma_d=0.1,
            levels=1,
            spatial_axes=(0, 1),
        )
    with pytest.raises(TypeError, match="guide is complex"):
        ob.atrous_bilateral(
            jnp.zeros((8, 8)),
            jnp.zeros((8, 8), jnp.complex64),
            sigma_d=0.1,
            levels=1,
            spatial_axes=(0, 1),
        )


def test_mixed_pytree_filters_the_texture_and_adams_the_scalar():
    params = {
        "tex": jax.random.uniform(KEY, (8, 8, 3)),
        "light": jnp.asarray(2.0),
        "curve": jnp.linspace(0, 1, 7),
    }
    g = _grads(1, params)
    opt = ob.bilateral_adam(1.0, b1=0.0, b2=0.0, eps=0.0, sigma_d=0.5, levels=2)
    u, _ = jax.jit(opt.update)(g, opt.init(params), params)
    # Unfiltered leaves: memoryless Adam = sign(g) (times -lr).
    np.testing.assert_allclose(np.asarray(u["light"]), -np.sign(np.asarray(g["light"])), rtol=1e-6)
    np.testing.assert_allclose(np.asarray(u["curve"]), -np.sign(np.asarray(g["curve"])), rtol=1e-6)
    bg, bg2 = _B((g["tex"], g["tex"] ** 2), params["tex"], 0.5, 2)
    np.testing.assert_allclose(np.asarray(u["tex"]), -np.asarray(bg / jnp.sqrt(bg2)), rtol=1e-5)


def test_spatial_axes_prefix_callable_and_per_leaf_sigma():
    params = {"a": jax.random.uniform(KEY, (3, 8, 8)), "b": jax.random.uniform(KEY, (8, 8, 3))}
    g = _grads(2, params)
    opt = ob.prefilter({"a": 0.2, "b": np.inf}, 2, spatial_axes={"a": (1, 2), "b": ()})
    u, _ = jax.jit(opt.update)(g, opt.init(params), params)
    exp_a = atrous_bilateral(g["a"], params["a"], sigma_d=0.2, levels=2, spatial_axes=(1, 2))
    np.testing.assert_allclose(np.asarray(u["a"]), np.asarray(exp_a), rtol=1e-6)
    np.testing.assert_array_equal(np.asarray(u["b"]), np.asarray(g["b"]))
    opt2 = ob.prefilter(0.2, 2, spatial_axes=lambda leaf: (1, 2) if leaf.shape[0] == 3 else ())
    u2, _ = jax.jit(opt2.update)(g, opt2.init(params), params)
    np.testing.assert_allclose(np.asarray(u2["a"]), np.asarray(exp_a), rtol=1e-6)
    np.testing.assert_array_equal(np.asarray(u2["b"]), np.asarray(g["b"]))


def test_guide_options():
    theta = jax.random.uniform(KEY, (8, 8, 2)) + 0.1
    g = _grads(4, theta)
    # log_guide: the guide is log(|theta| + 1e-8).
    u, _ = jax.jit(ob.prefilter(0.3, 2, log_guide=True).update)(g, (), theta)
    np.testing.assert_allclose(
        np.asarray(u), np.asarray(_B(g, jnp.log(theta + 1e-8), 0.3, 2)), rtol=1e-5
    )
    # "self": the gradient guides itself, each level by its own input (not by g throughout).
    u, _ = jax.jit(ob.prefilter(0.3, 2, guide="self").update)(g, (), theta)
    np.testing.assert_allclose(np.asarray(u), np.asarray(_B(g, "self", 0.3, 2)), rtol=1e-5)
    by_level = _B(_B(g, g, 0.3, 1), None, 0.3, 2, first=1)
    np.testing.assert_allclose(np.asarray(u), np.asarray(by_level), rtol=1e-5)
    assert float(jnp.max(jnp.abs(u - _B(g, g, 0.3, 2)))) > 1e-3
    # A callable returning auxiliary features (here a guide without channels).
    feat = lambda p: jnp.sum(p, axis=-1)
    u, _ = jax.jit(ob.prefilter(0.3, 2, guide=feat).update)(g, (), theta)
    np.testing.assert_allclose(np.asarray(u), np.asarray(_B(g, feat(theta), 0.3, 2)), rtol=1e-5)
    # "self" in the postfilter: m and v get different weights (m guided by m, v by v).
    post = ob.postfilter(0.0, 0.0, 0.0, sigma_d=0.3, levels=2, guide="self")
    u, _ = jax.jit(post.update)(g, post.init(theta), theta)
    np.testing.assert_allclose(
        np.asarray(u),
        np.asarray(_B(g, "self", 0.3, 2) / jnp.sqrt(_B(g * g, "self", 0.3, 2))),
        rtol=1e-5,
    )


def test_missing_params_is_a_clear_error():
    opt = ob.bilateral_adam(0.1)
    p = jnp.zeros((8, 8, 2))
    with pytest.raises(ValueError, match="params"):
        opt.update(p, opt.init(p))
    # guide="self" does not need params.
    opt = ob.bilateral_adam(0.1, guide="self")
    opt.update(jnp.ones((8, 8, 2)), opt.init(p))


def test_mask_unobserved_keeps_state_and_zeroes_update():
    theta = jax.random.uniform(KEY, (8, 8, 2))
    post = ob.postfilter(0.2, sigma_d=0.5, levels=2, mask_unobserved=True)
    state = post.init(theta)
    _, state = jax.jit(post.update)(_grads(0, theta), state, theta)
    g = _grads(1, theta).at[2:4, 2:5].set(0.0)
    u, new = jax.jit(post.update)(g, state, theta)
    assert np.all(np.asarray(u[2:4, 2:5]) == 0)
    np.testing.assert_array_equal(np.asarray(new.mu[2:4, 2:5]), np.asarray(state.mu[2:4, 2:5]))
    np.testing.assert_array_equal(np.asarray(new.nu[2:4, 2:5]), np.asarray(state.nu[2:4, 2:5]))
    # Observed texels moved, and the unobserved ones were left out of their filter sums.
    obs = np.ones((8, 8), bool)
    obs[2:4, 2:5] = False
    bm, bv = atrous_bilateral(
        (new.mu, new.nu), theta, sigma_d=0.5, levels=2, spatial_axes=(0, 1), mask=jnp.asarray(obs)
    )
    expect = (bm / (1 - 0.2**2)) / (jnp.sqrt(bv / (1 - 0.36**2)) + 1e-8)
    np.testing.assert_allclose(np.asarray(u), np.asarray(expect), rtol=1e-5, atol=1e-7)


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_nonfinite_texel_does_not_poison_neighbours_or_state(bad):
    theta = jax.random.uniform(KEY, (16, 16, 3))
    opt = ob.bilateral_adam(0.1, sigma_d=np.inf, levels=3, prefilter=True)
    state = opt.init(theta)
    g = _grads(0, theta).at[5, 7, 1].set(bad)
    u, state = jax.jit(opt.update)(g, state, theta)
    assert np.all(np.isfinite(np.asarray(u)))
    assert all(np.all(np.isfinite(np.asarray(x))) for x in jax.tree.leaves(state))
    assert np.all(np.asarray(u[5, 7]) == 0)
    # The neighbours equal a run where that texel was masked out (unobserved) from the start.
    opt_m = ob.bilateral_adam(0.1, sigma_d=np.inf, levels=3, prefilter=True, mask_unobserved=True)
    u_m, _ = jax.jit(opt_m.update)(g.at[5, 7].set(0.0), opt_m.init(theta), theta)
    np.testing.assert_allclose(np.asarray(u), np.asarray(u_m), rtol=1e-6, atol=1e-7)


@pytest.mark.parametrize("sigma_d", [0.1, "auto"])
@pytest.mark.parametrize("prefilter", [False, True])
def test_clean_and_unobserved_texels_share_one_filter_cascade(prefilter, sigma_d):
    """Clean and unobserved texels take one path (a NaN guide leaves the unobserved out), so
    a fixed sigma_d's update holds one cascade of F levels per transform: no second copy in a
    branch, which would double the compile time. ``"auto"``'s postfilter holds one cascade for
    the step, blended or not (``Auto.combine``: the blend is taken after it), whose
    correlated-noise way runs, in 2-D, one more level: inside the same call where the native
    kernel runs (its ``deeper_levels``), else as a cascade continuing the first in a
    conditional; its statistics run no filter level."""
    theta = jax.random.uniform(KEY, (64, 64, 3))  # large enough for every level's offsets
    opt = ob.bilateral_adam(0.1, sigma_d=sigma_d, levels=3, prefilter=prefilter)
    jaxpr = jax.make_jaxpr(opt.update)(_grads(0, theta), opt.init(theta), theta).jaxpr

    def filters(jx):
        """The levels of every atrous_bilateral call traced into the update."""
        out = []
        for eqn in jx.eqns:
            if eqn.params.get("name") == "_filter_jit":
                out.append(eqn.params["jaxpr"].jaxpr)
                continue
            for v in eqn.params.values():
                for sub in v if isinstance(v, (tuple, list)) else (v,):
                    sub = getattr(sub, "jaxpr", sub)
                    if hasattr(sub, "eqns"):
                        out += filters(sub)
        return out

    def levels_run(f):
        """``(levels, more)``: the levels a cascade runs and those it may add: its native
        calls' ``levels - start`` and ``deeper_levels``, or (pure-JAX kernels) its weights'
        exps, F = 3 on two axes holding 8 (2 pairs per pass, shared between levels) and one
        more level 4."""
        calls = [e for e in jaxprs.eqns(f) if e.primitive.name == "ffi_call"]
        if not calls:
            return {8: 3, 4: 1}[str(f).count(" exp ")], 0
        (a,) = [dict(e.params["attributes"]) for e in calls]
        return int(a["levels"]) - int(a["start"]), int(a["deeper_levels"])

    runs = [levels_run(f) for f in filters(jaxpr)]
    if sigma_d == 0.1:
        assert runs == [(3, 0)] * (1 + prefilter), runs
    elif runs[-1][1]:  # native: the correlated-noise way inside the postfilter's one call
        assert runs == [(3, 0)] * prefilter + [(3, 1)], runs
    else:  # the correlated-noise step's one more level, continuing the cascade
        assert runs == [(3, 0)] * (1 + prefilter) + [(1, 0)], runs


# --- Interop ------------------------------------------------------------------------------


@pytest.mark.parametrize("kind", ["bilateral_adam", "prefilter + postfilter", "memoryless"])
def test_eager_update_compiles_nothing_after_the_first_call(kind):
    """Without jax.jit around it, an update must reuse its compiled programs (it recompiled a
    lax.cond every call: 1-3 s per step); and it equals the jitted update."""
    from experiments.benchmarks.compiles import CompileCounter

    opt = {
        "bilateral_adam": ob.bilateral_adam(0.1, levels=2),
        "prefilter + postfilter": ob.bilateral_adam(0.1, levels=2, prefilter=True),
        "memoryless": ob.postfilter(0.0, 0.0, levels=2),
    }[kind]
    theta = jax.random.uniform(KEY, (32, 32, 3))
    state = opt.init(theta)
    u, state = opt.update(_grads(0, theta), state, theta)
    states, eager = [state], []
    with CompileCounter() as compiles:
        for i in range(1, 4):
            u, state = opt.update(_grads(i, theta), state, theta)
            jax.block_until_ready(u)
            assert compiles.count == 0, f"call {i + 1} compiled {compiles.count} program(s)"
            eager.append(u)
            states.append(state)
    jitted = jax.jit(opt.update)
    for i, u in enumerate(eager, start=1):
        u_jit, _ = jitted(_grads(i, theta), states[i - 1], theta)
        # The same formula; eagerly, the ops around the per-leaf step fuse differently.
        np.testing.assert_allclose(np.asarray(u), np.asarray(u_jit), rtol=1e-6, atol=1e-7)


def test_chain_with_other_transforms_and_jit_of_the_whole_step():
    theta = jnp.full((16, 16, 3), 0.5)
    # A piecewise-constant target: what an edge-stopping filter is built to recover.
    target = jnp.where(jnp.arange(16)[:, None, None] < 8, 0.2, 0.9) * jnp.ones(theta.shape)
    opt = optax.chain(
        optax.clip_by_global_norm(10.0),
        ob.prefilter(0.2, 3),
        ob.postfilter(0.2, sigma_d=0.2, levels=3),
        optax.scale_by_learning_rate(0.05),
    )
    loss = lambda p: jnp.mean((p - target) ** 2)

    @jax.jit
    def step(p, s):
        g = jax.grad(loss)(p)
        u, s = opt.update(g, s, p)
        return optax.apply_updates(p, u), s

    s = opt.init(theta)
    l0 = float(loss(theta))
    for _ in range(50):
        theta, s = step(theta, s)
    assert float(loss(theta)) < 0.5 * l0


def test_inject_hyperparams_sigma_schedule_compiles_once():
    traces = []
    opt = optax.inject_hyperparams(ob.bilateral_adam, static_args=("levels",))(
        learning_rate=optax.linear_schedule(0.1, 0.01, 20),
        sigma_d=optax.linear_schedule(1.0, 0.01, 20),
        levels=3,
    )
    theta = jax.random.uniform(KEY, (8, 8, 3))

    @jax.jit
    def step(g, s, p):
        traces.append(1)
        return opt.update(g, s, p)

    s = opt.init(theta)
    sig = []
    for i in range(6):
        u, s = step(_grads(i, theta), s, theta)
        sig.append(float(s.hyperparams["sigma_d"]))
        assert np.all(np.isfinite(np.asarray(u)))
    assert len(traces) == 1
    assert sig[0] > sig[-1]


def test_inject_hyperparams_traced_levels_is_a_clear_error():
    opt = optax.inject_hyperparams(ob.bilateral_adam)(learning_rate=0.1, levels=3)
    theta = jnp.zeros((8, 8))
    s = opt.init(theta)
    with pytest.raises(TypeError, match="static_args"):
        jax.jit(opt.update)(theta, s, theta)


def test_multi_transform_filters_only_the_texture():
    params = {"tex": jax.random.uniform(KEY, (8, 8, 3)), "light": jnp.ones((3,))}
    opt = optax.multi_transform(
        {"tex": ob.bilateral_adam(0.1, sigma_d=0.3, levels=2), "other": optax.adam(0.1)},
        {"tex": "tex", "light": "other"},
    )
    g = _grads(0, params)
    u, _ = jax.jit(opt.update)(g, opt.init(params), params)
    u_tex, _ = jax.jit(ob.bilateral_adam(0.1, sigma_d=0.3, levels=2).update)(
        g["tex"], ob.bilateral_adam(0.1, sigma_d=0.3, levels=2).init(params["tex"]), params["tex"]
    )
    np.testing.assert_allclose(np.asarray(u["tex"]), np.asarray(u_tex), rtol=1e-6)
    u_l, _ = optax.adam(0.1).update(g["light"], optax.adam(0.1).init(params["light"]))
    np.testing.assert_allclose(np.asarray(u["light"]), np.asarray(u_l), rtol=1e-6)


def test_optimistix_optax_minimiser():
    target = jax.random.uniform(KEY, (12, 12, 2))

    def fn(y, args):
        return jnp.sum((y - target) ** 2)

    solver = optx.OptaxMinimiser(
        ob.bilateral_adam(0.05, sigma_d=0.1, levels=2), rtol=1e-6, atol=1e-6
    )
    y0 = jnp.full((12, 12, 2), 0.5)
    sol = optx.minimise(fn, solver, y0, max_steps=300, throw=False)
    assert float(fn(sol.value, None)) < 0.05 * float(fn(y0, None))


def test_vmap_over_independent_problems():
    opt = ob.bilateral_adam(0.1, sigma_d=0.3, levels=2)
    thetas = jax.random.uniform(KEY, (3, 8, 8, 2))
    gs = jax.random.normal(jax.random.fold_in(KEY, 9), thetas.shape)
    states = jax.vmap(opt.init)(thetas)
    u, _ = jax.jit(jax.vmap(opt.update))(gs, states, thetas)
    for i in range(3):
        ui, _ = jax.jit(opt.update)(gs[i], opt.init(thetas[i]), thetas[i])
        np.testing.assert_allclose(np.asarray(u[i]), np.asarray(ui), rtol=1e-5, atol=1e-7)


@pytest.mark.parametrize("separable", [True, False])
@pytest.mark.parametrize("guide_kind", ["spatial", "channels", "integer"])
def test_masked_filter_by_nan_guide_equals_the_filters_mask(separable, guide_kind):
    # The transforms leave unobserved texels out of the sums with a NaN guide there (it costs
    # the kernel nothing); at observed texels that must equal atrous_bilateral's mask. An
    # integer guide has no NaN: it falls back to the mask.
    from optax_bilateral._src.filter import operators

    k1, k2, k3 = jax.random.split(KEY, 3)
    m = jax.random.normal(k1, (9, 7, 3))
    v = m * m
    guide = {
        "spatial": jax.random.uniform(k2, (9, 7)),
        "channels": jax.random.uniform(k2, (9, 7, 2)),
        "integer": jax.random.randint(k2, (9, 7), 0, 3),
    }[guide_kind]
    obs = jax.random.uniform(k3, (9, 7)) > 0.3
    assert (operators.nan_guide_at(guide, obs, (0, 1)) is None) == (guide_kind == "integer")
    plan = operators.FilterPlan((0, 1), 2, separable, self_guided=False, log_guide=False)
    out = operators.operator(plan, guide, obs).apply((m, v), 0.2)
    ref = atrous_bilateral(
        (m, v), guide, sigma_d=0.2, levels=2, spatial_axes=(0, 1), separable=separable, mask=obs
    )
    sel = np.asarray(obs)
    for a, b in zip(out, ref):  # float32 sums of the same terms: a few ulps
        np.testing.assert_allclose(np.asarray(a)[sel], np.asarray(b)[sel], rtol=1e-6, atol=1e-7)


def test_weight_decay_through_inject_hyperparams():
    """weight_decay as a hyperparameter (traced in the update): the chain keeps its shape,
    and 0 is plain bilateral_adam."""
    theta = jax.random.uniform(KEY, (8, 8, 2)) + 0.1
    g = _grads(0, theta)
    adam = optax.inject_hyperparams(ob.bilateral_adam, static_args=("levels",))
    decayed = adam(learning_rate=0.1, sigma_d=0.3, levels=2, weight_decay=0.5)
    u, _ = jax.jit(decayed.update)(g, decayed.init(theta), theta)
    plain = ob.bilateral_adam(0.1, sigma_d=0.3, levels=2)
    u0, _ = plain.update(g, plain.init(theta), theta)
    np.testing.assert_allclose(
        np.asarray(u), np.asarray(u0 - 0.1 * 0.5 * theta), rtol=1e-5, atol=1e-7
    )
    zero = adam(learning_rate=0.1, sigma_d=0.3, levels=2, weight_decay=0.0)
    u, _ = jax.jit(zero.update)(g, zero.init(theta), theta)
    np.testing.assert_allclose(np.asarray(u), np.asarray(u0), rtol=1e-5, atol=1e-7)


@pytest.mark.parametrize("sigma_d", [0.1, "auto", "sure"])
def test_the_state_can_be_donated(sigma_d):
    """``jit(update, donate_argnums=1)``, the usual way to update in place, needs every
    array of the state in a buffer of its own (XLA refuses one buffer donated twice)."""
    params = {"tex": jnp.ones((16, 16, 3)), "bias": jnp.ones((4,))}
    opt = optax.chain(
        ob.prefilter(sigma_d="auto" if sigma_d == "sure" else sigma_d),
        ob.bilateral_adam(0.01, sigma_d=sigma_d),
    )
    state = opt.init(params)
    arrays = [x for x in jax.tree.leaves(state) if isinstance(x, jax.Array)]
    assert len({id(x) for x in arrays}) == len(arrays)
    update = jax.jit(opt.update, donate_argnums=1)
    grads = jax.tree.map(jnp.ones_like, params)
    for _ in range(2):
        updates, state = update(grads, state, params)
    assert all(bool(jnp.all(jnp.isfinite(u))) for u in jax.tree.leaves(updates))
