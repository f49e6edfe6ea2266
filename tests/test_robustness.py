"""Robustness: numerical extremes, non-finite gradients, bad input, state, meta-gradients.

docs/robustness.md is the table these tests back. Compile time dominates on CPU, so
most tests share one compiled update whose hyperparameters (learning rate, b1, b2,
eps, sigma_d) are traced through ``optax.inject_hyperparams`` and set per call.
"""

import contextlib
import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

import optax_bilateral as ob
from reference import atrous_reference
from states import filtered_state

KEY = jax.random.PRNGKey(7)
SHAPE = (8, 8, 2)
LR = 0.1
THETA = jax.random.uniform(KEY, SHAPE)  # distinct guide values
NOISE = jax.random.normal(jax.random.fold_in(KEY, 1), SHAPE)


@functools.cache
def _hyper(levels, prefilter):
    """One compiled update per (levels, prefilter); every numeric hyperparameter is traced."""
    opt = optax.inject_hyperparams(ob.bilateral_adam, static_args=("levels",))(
        learning_rate=LR, b1=0.2, b2=0.36, eps=1e-8, sigma_d=0.3, levels=levels, prefilter=prefilter
    )
    return opt, jax.jit(opt.update)


def _init(theta=THETA, levels=2, prefilter=False, **hp):
    """The shared optimizer's state with hyperparameters ``hp`` (strongly typed, as update
    returns them: a weak-typed input would compile the update a second time)."""
    state = _hyper(levels, prefilter)[0].init(theta)
    return state._replace(
        hyperparams={  # via NumPy: never weak
            k: jnp.asarray(np.asarray(hp.get(k, v), v.dtype)) for k, v in state.hyperparams.items()
        }
    )


def _run(grads, theta=THETA, levels=2, prefilter=False, **hp):
    """Updates and final state of len(grads) steps at fixed parameters (hp: traced values)."""
    update = _hyper(levels, prefilter)[1]
    state = _init(theta, levels, prefilter, **hp)
    out = []
    for g in grads:
        u, state = update(jnp.asarray(g, jnp.float32), state, theta)
        out.append(u)
    return out, state


def _finite(tree):
    """Every array finite (of an injected state, the optimizer's own: sigma_d may be inf)."""
    tree = getattr(tree, "inner_state", tree)
    return all(bool(jnp.all(jnp.isfinite(x))) for x in jax.tree.leaves(tree))


def _ref_step(g, theta, sigma_d, levels, eps=1e-8):
    """-lr B g / (sqrt(B g^2) + eps): the step for a time-constant gradient g, any b1, b2
    (bias-corrected moments are then exactly g and g^2), from the float64 reference filter."""
    g = np.asarray(g, np.float64)
    both = np.concatenate([g, g * g], axis=-1)
    b = atrous_reference(both, np.asarray(theta, np.float64), sigma_d, levels, True)
    c = g.shape[-1]
    return -LR * b[..., :c] / (np.sqrt(b[..., c:]) + eps)


# --- sigma_d, levels, grids ------------------------------------------------------------------


def test_sigma_d_extremes():
    u = {s: _run([NOISE], sigma_d=s, eps=0.0)[0][0] for s in (0.0, 1e-30, 1e30, np.inf)}
    assert all(_finite(x) for x in u.values())
    # The guides are distinct (dist >~ 1e-10), so exp(-dist / 1e-30) is exactly 0: as sigma_d = 0.
    np.testing.assert_array_equal(np.asarray(u[1e-30]), np.asarray(u[0.0]))
    # dist / 1e30 <= 1e-30 and exp gives exactly 1: as sigma_d = inf (the low-pass).
    np.testing.assert_array_equal(np.asarray(u[1e30]), np.asarray(u[np.inf]))
    # sigma_d = 0 with distinct guides keeps each texel alone: Adam's first step, -lr sign(g);
    # x * h0 / h0 in float32 is within an ulp of x.
    np.testing.assert_allclose(np.asarray(u[0.0]), -LR * np.sign(np.asarray(NOISE)), rtol=1e-6)
    np.testing.assert_allclose(
        np.asarray(u[np.inf]), _ref_step(NOISE, THETA, np.inf, 2, eps=0.0), rtol=1e-5, atol=1e-7
    )  # float32 sums of <= 25 taps against float64
    assert float(jnp.max(jnp.abs(u[np.inf]))) <= LR * (1 + 1e-6)


def test_levels_zero_one_and_longer_than_the_grid_on_tiny_grids():
    # One params tree holds every (grid, levels) case, so one program is compiled. Strides
    # longer than the grid: F = 12 reaches 2^11 on grids of 1, 2 and 7.
    cases = [("1x1", (1, 1), 12), ("1x7", (1, 7), 0), ("1x7", (1, 7), 12), ("2x2x2", (2, 2, 2), 12)]
    rng = np.random.default_rng(0)
    params, grads, levels, axes = {}, {}, {}, {}
    for name, shape, lev in cases:
        k = f"{name}_F{lev}"
        params[k] = jnp.asarray(rng.random(shape), jnp.float32)
        grads[k] = jnp.asarray(rng.normal(size=shape), jnp.float32)
        levels[k] = lev
        axes[k] = tuple(range(len(shape)))  # every axis spatial (2x2x2 = a volume)
    opt = ob.bilateral_adam(LR, eps=0.0, sigma_d=0.5, levels=levels, spatial_axes=axes)
    u, state = jax.jit(opt.update)(grads, opt.init(params), params)
    assert _finite(u) and _finite(state)
    for k in params:
        lev = levels[k]
        # The reference wants channels last: add a channel axis of 1.
        expect = _ref_step(
            np.asarray(grads[k])[..., None], np.asarray(params[k])[..., None], 0.5, lev, eps=0.0
        )
        np.testing.assert_allclose(
            np.asarray(u[k]), expect[..., 0], rtol=1e-5, atol=1e-7, err_msg=k
        )
        if k.startswith("1x1") or lev == 0:
            # Nothing to average with: Adam's first step, +-1 up to rounding (a leaf with
            # levels=0 gets Adam's own b2 = 0.999, whose 1 - b2^t carries float32's ~1e-6).
            np.testing.assert_allclose(
                np.asarray(u[k]), -LR * np.sign(np.asarray(grads[k])), rtol=1e-5
            )


# --- gradient magnitudes ----------------------------------------------------------------------


@pytest.mark.parametrize("prefilter", [False, True])
def test_zero_gradients_with_eps_zero_give_zero_updates(prefilter):
    zeros = jnp.zeros(SHAPE)
    u, state = _run([zeros, zeros], prefilter=prefilter, eps=0.0)
    # 0 / (sqrt(0) + 0) is defined as a zero step, not NaN.
    assert all(np.all(np.asarray(x) == 0) for x in u)
    assert _finite(state)
    # Two flat regions that sigma_d = 0 keeps apart; the right one gets no gradient, so
    # B v = 0 there: it stays put (0/0 -> 0) and the left one moves.
    theta = jnp.where(jnp.arange(8)[None, :, None] < 4, 0.2, 0.8) * jnp.ones(SHAPE)
    g = NOISE.at[:, 4:].set(0.0)
    u, state = _run([g, g], theta=theta, prefilter=prefilter, eps=0.0, sigma_d=0.0)
    assert _finite(u) and _finite(state)
    assert all(np.all(np.asarray(x[:, 4:]) == 0) for x in u)
    assert all(np.all(np.asarray(x[:, :4]) != 0) for x in u)


@pytest.mark.parametrize("prefilter", [False, True])
@pytest.mark.parametrize("scale", [1e30, -1e30, 3e38])
def test_huge_gradients_give_finite_adam_sized_steps(prefilter, scale):
    s = jnp.sign(NOISE)
    u_big, state = _run([scale * s] * 3, prefilter=prefilter, sigma_d=np.inf)
    assert _finite(u_big) and _finite(state)
    for a in u_big:
        # A gradient constant in time steps by at most lr, however large it is.
        assert float(jnp.max(jnp.abs(a))) <= LR * (1 + 1e-5)
        assert float(jnp.max(jnp.abs(a))) > 0.1 * LR
    if not prefilter:
        # Equal magnitudes are all clipped to 1.3e19 alike, so the step is that of +-1
        # gradients (to float32 rounding: the clip value is not a power of two).
        u_one, _ = _run([jnp.sign(scale) * s] * 3, sigma_d=np.inf)
        for a, b in zip(u_big, u_one):
            np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-5, atol=1e-7)


def test_one_huge_texel_stays_bounded_and_finite():
    g = NOISE.at[3, 4, 0].set(1e30)
    u, state = _run([g, NOISE, NOISE], sigma_d=np.inf)
    assert _finite(u) and _finite(state)
    # The bounded step (supplement §1.3) holds for the clipped gradient sequence.
    for t, x in enumerate(u, start=1):
        assert float(jnp.max(jnp.abs(x))) <= LR * _adam_bound(0.2, 0.36, t) * (1 + 1e-5)


@pytest.mark.parametrize("tiny", [1e-30, 1e-40])  # 1e-40 is a float32 denormal
def test_tiny_and_denormal_gradients(tiny):
    g = tiny * jnp.sign(NOISE)
    u, state = _run([g, g], eps=1e-8)
    assert _finite(u) and _finite(state)
    # g^2 underflows to 0, so the step is m / eps, as exact arithmetic gives to ~1e-22 relative.
    for x in u:
        assert float(jnp.max(jnp.abs(x))) <= LR * tiny / 1e-8 * (1 + 1e-5)
    # With eps = 0 the denominator is 0: a zero step (documented), never inf or NaN.
    u, state = _run([g, g], eps=0.0)
    assert _finite(state)
    assert all(np.all(np.asarray(x) == 0) for x in u)


def test_log_guide_with_zero_and_negative_params():
    theta = jnp.asarray(np.tile(np.array([0.0, -0.5, 0.5, 0.0, -2.0, 1e-12, -0.0, 3.0]), (8, 1)))
    theta = jnp.stack([theta, -theta.T], axis=-1)
    # The guide code is shared by both filters; the (stateless) prefilter compiles fastest.
    pre = ob.prefilter(0.3, 1, log_guide=True)
    upd = jax.jit(pre.update)
    u, _ = upd(NOISE, pre.init(theta), theta)
    assert _finite(u)
    # A row-stochastic filter: |A g| <= max |g|.
    assert float(jnp.max(jnp.abs(u))) <= float(jnp.max(jnp.abs(NOISE))) * (1 + 1e-6)
    # log(|theta| + 1e-8) depends on |theta| only: flipping signs changes nothing...
    u_neg, _ = upd(NOISE, pre.init(theta), -theta)
    np.testing.assert_array_equal(np.asarray(u), np.asarray(u_neg))
    # ... and equals the reference filter guided by log(|theta| + 1e-8) (zeros: log 1e-8 = -18.4).
    ref = atrous_reference(
        np.asarray(NOISE), np.log(np.abs(np.asarray(theta, np.float64)) + 1e-8), 0.3, 1, True
    )
    # Guide values up to |log 1e-8| = 18.4: their float32 rounding (2e-6) over sigma_d = 0.3
    # moves the weights by ~1e-5 relative.
    np.testing.assert_allclose(np.asarray(u), ref, rtol=1e-4, atol=1e-6)


# --- b1, b2 -------------------------------------------------------------------------------------


def _adam_bound(b1, b2, t):
    """max |m_hat| / sqrt(v_hat) after t steps (Cauchy-Schwarz on the two EMAs), b1^2 <= b2."""
    if b1 == 0:
        return math.sqrt((1 - b2**t) / (1 - b2)) if b2 < 1 else math.sqrt(t)
    r = b1 * b1 / b2
    s = sum(r**j for j in range(t))
    return (1 - b1) * math.sqrt(s / (1 - b2)) * math.sqrt(1 - b2**t) / (1 - b1**t)


@pytest.mark.parametrize("b1,b2", [(0.0, 0.0), (0.0, 0.999999), (0.999999, 0.999999), (0.2, 0.36)])
def test_b1_b2_extremes_time_constant_gradient_is_exact_and_noise_is_bounded(b1, b2):
    steps = 6
    # A gradient constant in time: bias-corrected moments are g and g^2 for any b1, b2.
    u, state = _run([NOISE] * steps, b1=b1, b2=b2)
    expect = _ref_step(NOISE, THETA, 0.3, 2)
    for x in u:
        # 1 - b^t for b = 0.999999 (traced float32) is exact via expm1 to ~1e-6; the rest is
        # float32 rounding of the EMAs and filter sums.
        np.testing.assert_allclose(np.asarray(x), expect, rtol=2e-5, atol=1e-7)
    assert _finite(state)
    # Noisy gradients: every step within the Adam bound (which the postfilter keeps, §1.3).
    grads = [jax.random.normal(jax.random.fold_in(KEY, 50 + t), SHAPE) for t in range(steps)]
    u, _ = _run(grads, b1=b1, b2=b2)
    for t, x in enumerate(u, start=1):
        assert float(jnp.max(jnp.abs(x))) <= LR * _adam_bound(b1, b2, t) * (1 + 1e-5)


def test_b2_that_rounds_to_one_in_float32():
    """b1 = 0.999999 and b2 = None gives b2 = 1 - 1e-12, which is 1.0 in float32."""
    # The bias correction does not involve the filter: levels=0 compiles in a fraction.
    opt = ob.bilateral_adam(LR, b1=0.999999, levels=0)
    upd = jax.jit(opt.update)
    state = opt.init(THETA)
    expect = -LR * NOISE / (jnp.abs(NOISE) + 1e-8)
    for _ in range(4):
        u, state = upd(NOISE, state, THETA)
        # Without the float64 1 - b and expm1, 1 - b2^t = 0 and the step was 0 (measured).
        np.testing.assert_allclose(np.asarray(u), expect, rtol=2e-5, atol=1e-7)
    assert _finite(state)


def test_b1_above_sqrt_b2_is_finite_but_unbounded_like_adam():
    """b1 = 0.999999, b2 = 0: m/|g_t| can be large (Adam's own property); it stays finite."""
    grads = [NOISE * (1e-3 if t == 3 else 1.0) for t in range(4)]
    u, state = _run(grads, b1=0.999999, b2=0.0)
    assert _finite(u) and _finite(state)
    assert float(jnp.max(jnp.abs(u[3]))) > 5 * LR  # documented: not within a few learning rates


# --- low precision ------------------------------------------------------------------------------


def test_bfloat16_and_float16_params_and_moments_keep_their_dtype():
    dtypes = {"bf16": jnp.bfloat16, "f16": jnp.float16}
    params = {k: THETA.astype(d) for k, d in dtypes.items()}
    grads = {k: NOISE.astype(d) for k, d in dtypes.items()}
    opt = ob.bilateral_adam(LR, sigma_d=0.3, levels=2)
    upd = jax.jit(opt.update)
    state = opt.init(params)
    for _ in range(3):
        u, state = upd(grads, state, params)
        for k, d in dtypes.items():
            assert u[k].dtype == d and filtered_state(state).mu[k].dtype == d
            assert filtered_state(state).nu[k].dtype == d
            expect = _ref_step(
                np.asarray(grads[k], np.float64), np.asarray(params[k], np.float64), 0.3, 2
            )
            # Moments stored with 8 (bf16) or 11 (f16) bits each step; the update rounded once
            # more: a few of that dtype's eps.
            eps = float(jnp.finfo(d).eps)
            np.testing.assert_allclose(
                np.asarray(u[k], np.float64), expect, rtol=8 * eps, atol=8 * eps * LR, err_msg=k
            )
    # |g| = 1000 squares past float16's 65504: clipped at 181 instead (v = inf used to give the
    # texel, and through B v its footprint, 0 steps forever). An inf texel is unobserved.
    big = {
        k: (1000 * jnp.sign(NOISE)).astype(d).at[2, 2, 1].set(jnp.inf) for k, d in dtypes.items()
    }
    u, state = upd(big, opt.init(params), params)
    assert _finite(state) and _finite(u)
    for k in dtypes:
        assert np.all(np.asarray(u[k][2, 2]) == 0)  # the whole texel is unobserved
        assert float(jnp.min(jnp.abs(u[k].at[2, 2].set(LR)))) > 0


# --- non-finite gradients ------------------------------------------------------------------------


def test_non_finite_gradients_without_the_postfilter():
    """prefilter + Adam (eq. 13) and an unfiltered scalar: NaN/Inf entries are unobserved too."""
    f32 = functools.partial(jnp.asarray, dtype=jnp.float32)  # strongly typed: one compile
    params = {"tex": THETA, "light": f32(1.0)}
    opt = optax.chain(
        ob.prefilter(np.inf, 3, spatial_axes={"tex": (0, 1), "light": ()}),
        ob.postfilter(0.2, levels=0),
        optax.scale_by_learning_rate(LR),
    )
    upd = jax.jit(opt.update)
    state = opt.init(params)
    _, state = upd({"tex": NOISE, "light": f32(0.5)}, state, params)
    g_bad = {"tex": NOISE.at[4, 4, 0].set(jnp.nan).at[1, 6, 1].set(-jnp.inf), "light": f32(jnp.inf)}
    u, new = upd(g_bad, state, params)
    assert _finite(u) and _finite(new)
    # The Adam stage is unfiltered, so it masks per entry: the bad entries step 0 and keep
    # their moments; the prefilter left both whole texels out of its sums and passed them on.
    assert (
        float(u["tex"][4, 4, 0]) == 0 and float(u["tex"][1, 6, 1]) == 0 and float(u["light"]) == 0
    )
    for idx in [(4, 4, 0), (1, 6, 1)]:
        assert float(new[1].mu["tex"][idx]) == float(state[1].mu["tex"][idx])
        assert float(new[1].nu["tex"][idx]) == float(state[1].nu["tex"][idx])
    assert float(new[1].nu["light"]) == float(state[1].nu["light"])
    # Every other texel: eq. 13 by hand, with the prefilter's sums skipping the two bad texels.
    keep = np.ones(SHAPE[:2], bool)
    keep[4, 4] = keep[1, 6] = False
    ag = atrous_reference(
        np.where(keep[..., None], np.asarray(g_bad["tex"]), 0),
        np.asarray(THETA),
        np.inf,
        3,
        True,
        mask=keep,
    )
    m = 0.8 * ag + 0.2 * np.asarray(state[1].mu["tex"])
    v = 0.64 * ag**2 + 0.36 * np.asarray(state[1].nu["tex"])
    expect = -LR * (m / (1 - 0.2**2)) / (np.sqrt(v / (1 - 0.36**2)) + 1e-8)
    # float32 filter sums and moments against float64
    np.testing.assert_allclose(np.asarray(u["tex"])[keep], expect[keep], rtol=1e-5, atol=1e-7)


def test_all_gradients_non_finite_is_a_no_op_step():
    _, state = _run([NOISE])
    u2, state2 = _hyper(2, False)[1](jnp.full(SHAPE, jnp.nan, jnp.float32), state, THETA)
    assert np.all(np.asarray(u2) == 0)
    inner, inner2 = filtered_state(state.inner_state), filtered_state(state2.inner_state)
    np.testing.assert_array_equal(np.asarray(inner2.mu), np.asarray(inner.mu))
    np.testing.assert_array_equal(np.asarray(inner2.nu), np.asarray(inner.nu))


# --- long runs --------------------------------------------------------------------------------


@functools.partial(jax.jit, static_argnums=(3,))
def _long_run(theta0, target, noise, steps):
    """``steps`` noisy-gradient steps in one lax.scan; per-step max |update| and error."""
    opt = ob.bilateral_adam(LR / 10, sigma_d=0.2, levels=3)

    def body(carry, t):
        theta, state = carry
        g = 2 * (theta - target) + noise * jax.random.normal(
            jax.random.fold_in(KEY, t), theta.shape
        )
        u, state = opt.update(g, state, theta)
        theta = optax.apply_updates(theta, u)
        return (theta, state), (
            jnp.max(jnp.abs(u)),
            jnp.sqrt(jnp.mean((theta - target) ** 2)),
            jnp.all(jnp.isfinite(u)),
        )

    (theta, state), trace = jax.lax.scan(body, (theta0, opt.init(theta0)), jnp.arange(steps))
    return theta, state, trace


def test_ten_thousand_steps_no_nan_no_drift():
    target = jnp.where(jnp.arange(8)[:, None, None] < 4, 0.2, 0.8) * jnp.ones(SHAPE)
    # Two problems in one compiled, vmapped scan: noisy gradients from a random start, and
    # zero gradients (theta at the target, no noise).
    thetas, states, traces = jax.vmap(_long_run, in_axes=(0, None, 0, None))(
        jnp.stack([THETA, target]), target, jnp.asarray([1.0, 0.0]), 10_000
    )
    theta, state, (umax, err, ok) = jax.tree.map(lambda x: x[0], (thetas, states, traces))
    assert bool(jnp.all(ok)) and _finite(theta) and _finite(state)
    # Every update within the t>=2 Adam bound for b1=0.2, b2=0.36 (1.06), times lr.
    assert float(jnp.max(umax)) <= 1.07 * LR / 10
    err = np.asarray(err)
    # Converged well below the start (0.3) and stationary: the last 1000 steps' mean error is
    # no worse than steps 4000-5000 (+20% for noise), i.e. no drift.
    assert err[-1000:].mean() < 0.2 * err[0]
    assert err[-1000:].mean() <= 1.2 * err[4000:5000].mean()
    # Zero gradient for 10,000 steps: not one bit moves.
    theta0, (umax0, ok0) = thetas[1], (traces[0][1], traces[2][1])
    np.testing.assert_array_equal(np.asarray(theta0), np.asarray(target))
    assert bool(jnp.all(ok0)) and float(jnp.max(umax0)) == 0.0


# --- bad input ------------------------------------------------------------------------------------


def test_bad_settings_raise_at_construction():
    for fn in (
        lambda **k: ob.bilateral_adam(0.1, **k),
        lambda **k: ob.postfilter(**k),
        lambda **k: ob.prefilter(**k),
    ):
        with pytest.raises(ValueError, match="sigma_d"):
            fn(sigma_d=-1.0)
        with pytest.raises(ValueError, match="sigma_d"):
            fn(sigma_d=float("nan"))
        with pytest.raises(ValueError, match="sigma_d"):
            fn(sigma_d={"a": 0.1, "b": -0.2})
        with pytest.raises(ValueError, match="levels"):
            fn(levels=-1)
        with pytest.raises(TypeError, match="levels"):
            fn(levels=1.5)
        with pytest.raises(TypeError, match="levels"):
            fn(levels=True)
        with pytest.raises(ValueError, match="levels"):
            fn(levels={"a": 2, "b": -3})
        with pytest.raises(ValueError, match=r"spatial_axes.*repeats"):
            fn(spatial_axes=(0, 0))
        with pytest.raises(TypeError, match="spatial_axes"):
            fn(spatial_axes="xy")
        with pytest.raises(ValueError, match="guide"):
            fn(guide="theta")
    for kw, err, name in [
        ({"b1": 1.0}, ValueError, "b1"),
        ({"b2": -0.1}, ValueError, "b2"),
        ({"eps": -1e-8}, ValueError, "eps"),
        ({"eps": float("nan")}, ValueError, "eps"),
        ({"mu_dtype": jnp.int32}, TypeError, "mu_dtype"),
        ({"mu_dtype": "float33"}, TypeError, "mu_dtype"),
        ({"b1": "0.9"}, TypeError, "b1 must be a real number"),  # not b2's default first
        ({"b2": [0.9, 0.99]}, TypeError, "b2 must be a real number"),
        ({"eps": "tiny"}, TypeError, "eps must be a real number"),
    ]:
        with pytest.raises(err, match=name):
            ob.bilateral_adam(0.1, **kw)


def test_errors_name_the_function_called_and_a_readable_leaf_path():
    """Raised at init or update, long after the call: the message names the function the
    user called (``bilateral_adam``, not only its inner postfilter) and the leaf as a path
    from ``params`` (a bare array is ``params``)."""
    tex = jnp.zeros((8, 8, 3))
    opt = ob.bilateral_adam(0.1)
    with pytest.raises(
        ValueError, match=r"^bilateral_adam \(its postfilter\): the update for params has"
    ):
        opt.update(jnp.zeros((8, 8, 1)), opt.init(tex), tex)
    with pytest.raises(ValueError, match=r"^postfilter: the update for params\['t'\] has"):
        post = ob.postfilter()
        post.update({"t": jnp.zeros((8, 8, 1))}, post.init({"t": tex}), {"t": tex})
    with pytest.raises(TypeError, match=r"^params has dtype int32"):
        ob.bilateral_adam(0.1, spatial_axes=(0, 1)).init(jnp.zeros((8, 8, 2), jnp.int32))


def test_bad_params_and_guides_raise_at_init():
    tex = jnp.zeros((6, 5, 3))
    with pytest.raises(ValueError, match="spatial_axes"):
        ob.bilateral_adam(0.1, spatial_axes=(0, 3)).init(tex)  # out of range
    with pytest.raises(ValueError, match=r"spatial_axes.*\['v'\]"):
        ob.bilateral_adam(0.1, spatial_axes=(0, 1, 2)).init(
            {"v": jnp.zeros((4, 4))}
        )  # too few dims
    with pytest.raises(ValueError, match="repeats"):
        ob.bilateral_adam(0.1, spatial_axes=(0, -3)).init(tex)  # the same axis twice
    # Integer parameters: a filtered leaf (prefilter) or any leaf with moments (Adam, postfilter).
    with pytest.raises(TypeError, match=r"params\['n'\] has dtype int32"):
        ob.prefilter(0.1, 2).init({"n": jnp.zeros((8, 8, 2), jnp.int32)})
    with pytest.raises(TypeError, match=r"params\['n'\] has dtype int32"):
        ob.bilateral_adam(0.1).init({"x": tex, "n": jnp.zeros((), jnp.int32)})
    with pytest.raises(TypeError, match="params"):
        ob.postfilter(levels=0).init(jnp.zeros((4, 4), jnp.int32))
    # A guide callable whose spatial shape differs from its leaf's, or None for a filtered leaf.
    with pytest.raises(ValueError, match=r"guide.*\(6, 4\).*\(6, 5\)"):
        ob.postfilter(guide=lambda p: p[:, :4]).init(tex)
    with pytest.raises(ValueError, match="guide returned None"):
        ob.postfilter(guide=lambda p: {"a": p["a"], "b": None}).init({"a": tex, "b": tex})
    # ... which passes when that leaf is not filtered.
    ob.postfilter(guide=lambda p: {"a": p["a"], "b": None}, spatial_axes={"a": None, "b": ()}).init(
        {"a": tex, "b": tex}
    )
    # Params missing at update time, for the prefilter too (postfilter: test_transforms).
    pre = ob.prefilter(0.1, 2)
    with pytest.raises(ValueError, match="params"):
        pre.update(tex, pre.init(tex))


def test_traced_negative_sigma_d_makes_the_update_nan():
    """A traced sigma_d cannot raise; a negative (or NaN) one poisons the update loudly."""
    for bad in (-1.0, np.nan):
        u, _ = _run([NOISE], sigma_d=bad)
        assert np.all(np.isnan(np.asarray(u[0])))


# --- state ------------------------------------------------------------------------------------


def test_state_is_a_plain_pytree_of_arrays_and_resumes_bit_identically(tmp_path):
    opt, upd = _hyper(2, False)  # an injected state: hyperparameters included
    grads = [jax.random.normal(jax.random.fold_in(KEY, 200 + i), SHAPE) for i in range(6)]

    def steps(p, s, gs):
        for g in gs:
            u, s = upd(g, s, p)
            p = optax.apply_updates(p, u)
        return p, s

    state = _init()
    assert all(isinstance(x, jax.Array) for x in jax.tree.leaves(opt.init(THETA)))
    p_all, s_all = steps(THETA, state, grads)
    p_half, s_half = steps(THETA, state, grads[:3])
    ob.save_state(tmp_path / "state.npz", s_half)
    restored = ob.load_state(tmp_path / "state.npz", jax.eval_shape(opt.init, THETA))
    assert jax.tree.structure(restored) == jax.tree.structure(s_half)
    p_resumed, s_resumed = steps(p_half, restored, grads[3:])
    for a, b in zip(jax.tree.leaves((p_resumed, s_resumed)), jax.tree.leaves((p_all, s_all))):
        assert a.dtype == b.dtype
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    # A state from other parameters or another optimizer is refused with the reason.
    with pytest.raises(ValueError, match="shape"):
        ob.load_state(tmp_path / "state.npz", opt.init(THETA[:6]))  # still filtered
    with pytest.raises(ValueError, match=r"float32.*bfloat16"):
        ob.load_state(tmp_path / "state.npz", opt.init(THETA.astype(jnp.bfloat16)))
    with pytest.raises(ValueError, match="leaves"):
        ob.load_state(tmp_path / "state.npz", ob.bilateral_adam(LR).init(THETA))
    with pytest.raises(ValueError, match="not an optimizer state"):
        np.savez(tmp_path / "other.npz", x=np.zeros(3))
        ob.load_state(tmp_path / "other.npz", state)


def test_save_load_keeps_special_bits(tmp_path):
    """NaN payloads, -0.0, denormals, bfloat16/float16 and int leaves survive exactly."""
    tree = {
        "f32": jnp.asarray([np.nan, -0.0, 1e-45, np.inf, -3.5], jnp.float32),
        "bf16": jnp.asarray([1.0, -0.0, 3e38, 1e-40], jnp.bfloat16),
        "f16": jnp.asarray([6e-8, 65504.0, -0.0], jnp.float16),
        "count": jnp.asarray(7, jnp.int32),
        "none": None,
        "empty": (),
    }
    ob.save_state(tmp_path / "s.npz", tree)
    back = ob.load_state(tmp_path / "s.npz", tree)
    for a, b in zip(jax.tree.leaves(back), jax.tree.leaves(tree)):
        assert a.dtype == b.dtype
        np.testing.assert_array_equal(
            np.asarray(a).reshape(-1).view(np.uint8), np.asarray(b).reshape(-1).view(np.uint8)
        )


def test_load_state_assembles_the_parts_of_a_multiprocess_checkpoint(tmp_path, monkeypatch):
    """Parts as 2 processes write them (tests/test_multiprocess.py runs real ones): each holds
    its row blocks of the grid leaves and a copy of the replicated ones; load_state puts
    the blocks together, and refuses incomplete or mixed sets of parts."""
    from jax.experimental import multihost_utils

    from optax_bilateral._src.optimizer import state_io

    tree = {
        "m": jnp.arange(8 * 6 * 2, dtype=jnp.float32).reshape(8, 6, 2),
        "bf16": jnp.linspace(-1, 1, 8 * 3).reshape(8, 3).astype(jnp.bfloat16),
        "count": jnp.asarray(7, jnp.int32),
    }
    rows = {0: [slice(0, 3), slice(3, 5)], 1: [slice(4, 8)]}  # process 0: two blocks; overlap
    process = [0]

    def blocks_of(x):
        if x.ndim == 0:
            return [((), x)]
        return [((r,), x[r]) for r in rows[process[0]]]

    monkeypatch.setattr(jax, "process_count", lambda: 2)
    monkeypatch.setattr(jax, "process_index", lambda: process[0])
    monkeypatch.setattr(state_io, "_blocks_of", blocks_of)
    monkeypatch.setattr(multihost_utils, "sync_global_devices", lambda name: None)
    path = tmp_path / "state.npz"
    for i in (0, 1):
        process[0] = i
        ob.save_state(path, tree)
    monkeypatch.undo()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["state.npz.0-of-2", "state.npz.1-of-2"]

    back = ob.load_state(path, jax.eval_shape(lambda: tree))
    for a, b in zip(jax.tree.leaves(back), jax.tree.leaves(tree)):
        assert a.dtype == b.dtype
        np.testing.assert_array_equal(
            np.asarray(a).reshape(-1).view(np.uint8), np.asarray(b).reshape(-1).view(np.uint8)
        )
    # A block is read from the pieces it overlaps, across parts.
    ckpt = state_io._open_checkpoint(str(path), contextlib.ExitStack())
    m = 2  # leaves in key order: bf16, count, m
    np.testing.assert_array_equal(ckpt.read(m, (slice(2, 7),), "m"), np.asarray(tree["m"][2:7]))

    # A part missing, a stale part of another run, a gap in the blocks, no checkpoint.
    (tmp_path / "state.npz.1-of-2").rename(tmp_path / "moved")
    with pytest.raises(ValueError, match=r"lacks the parts of processes \[1\]"):
        ob.load_state(path, tree)
    (tmp_path / "moved").rename(tmp_path / "state.npz.1-of-2")
    (tmp_path / "state.npz.2-of-3").write_bytes(b"")
    with pytest.raises(ValueError, match=r"from \[2, 3\] processes"):
        ob.load_state(path, tree)
    (tmp_path / "state.npz.2-of-3").unlink()
    rows[1] = [slice(6, 8)]  # row 5 was process 1's alone: now nobody's
    monkeypatch.setattr(jax, "process_count", lambda: 2)
    monkeypatch.setattr(jax, "process_index", lambda: 1)
    monkeypatch.setattr(state_io, "_blocks_of", blocks_of)
    monkeypatch.setattr(multihost_utils, "sync_global_devices", lambda name: None)
    process[0] = 1
    ob.save_state(path, tree)
    monkeypatch.undo()
    with pytest.raises(ValueError, match="lacks part of state leaf"):
        ob.load_state(path, tree)
    with pytest.raises(FileNotFoundError, match="no optimizer state"):
        ob.load_state(tmp_path / "nothing.npz", tree)


def test_mu_dtype_sets_the_first_moment_precision_only():
    opt = optax.chain(
        ob.postfilter(0.2, mu_dtype=jnp.bfloat16, levels=0), optax.scale_by_learning_rate(LR)
    )
    s = opt.init(THETA)
    assert s[0].mu.dtype == jnp.bfloat16 and s[0].nu.dtype == jnp.float32
    _, s = jax.jit(opt.update)(NOISE, s, THETA)
    assert s[0].mu.dtype == jnp.bfloat16 and s[0].nu.dtype == jnp.float32
    # The stored first moment is the float32 one rounded to bfloat16.
    np.testing.assert_array_equal(
        np.asarray(s[0].mu), np.asarray((0.8 * NOISE).astype(jnp.bfloat16))
    )


# --- differentiability ----------------------------------------------------------------------------


def _meta_loss(sigma_d, lr):
    """Loss after K steps of bilateral_adam, as a function of its sigma_d and learning rate."""
    target = jnp.where(jnp.arange(8)[None, :, None] < 4, 0.3, 0.7) * jnp.ones(SHAPE)
    opt = ob.bilateral_adam(lr, sigma_d=sigma_d, levels=1, eps=1e-8)
    # Gradient only on the left half: the right half has v = 0 beyond the filter footprint,
    # where d sqrt(v) / dv would be inf without the library's safe sqrt.
    seen = (jnp.arange(8)[None, :, None] < 4).astype(jnp.float32)

    def body(carry, t):
        theta, state = carry
        noise = 0.3 * jax.random.normal(jax.random.fold_in(KEY, t), SHAPE)
        g = seen * (2 * (theta - target) + noise)
        u, state = opt.update(g, state, theta)
        return (optax.apply_updates(theta, u), state), None

    theta0 = 0.5 + 0.05 * THETA
    (theta, _), _ = jax.lax.scan(body, (theta0, opt.init(theta0)), jnp.arange(8))
    return jnp.mean(seen * (theta - target) ** 2)


def test_meta_gradient_wrt_sigma_d_and_learning_rate_is_finite_and_correct():
    # One compiled program; its loss values give the finite differences too.
    vg = jax.jit(jax.value_and_grad(_meta_loss, argnums=(0, 1)))
    sigma, lr = 0.3, 0.05
    _, (d_sigma, d_lr) = vg(sigma, lr)
    assert np.isfinite(float(d_sigma)) and np.isfinite(float(d_lr))
    assert float(d_lr) != 0 and float(d_sigma) != 0
    # Central differences in float32 (h = 3% of the value): agreement to 10% of the larger
    # of the two magnitudes, enough to catch a wrong sign or a dropped term.
    for x, d, f in [
        (sigma, d_sigma, lambda s: vg(s, lr)[0]),
        (lr, d_lr, lambda rate: vg(sigma, rate)[0]),
    ]:
        h = 0.03 * x
        fd = (float(f(x + h)) - float(f(x - h))) / (2 * h)
        assert abs(float(d) - fd) <= 0.1 * max(abs(fd), abs(float(d))), (float(d), fd)


def test_huge_guide_differences_with_huge_sigma_d():
    # The squared guide distance would overflow float32 above ~1.8e19; the filter rescales
    # the guide and sigma_d by a power of two first (bilateral.rescale_guide).
    x = jnp.asarray([0.0, 1.0])
    for gv in (1e18, 1e20):  # guide distance 2e18 (fine) and 2e20 (d^2 = inf)
        out = ob.atrous_bilateral(
            x, jnp.asarray([gv, -gv]), sigma_d=1e30, levels=1, spatial_axes=(0,)
        )
        # exp(-2e20 / 1e30) = 1: both neighbours weigh their B-spline taps 3/8 and 1/4.
        np.testing.assert_allclose(np.asarray(out), [0.4, 0.6], rtol=1e-6)


@pytest.mark.parametrize("scale", [2.0**70, 1e30, 2.0**126])
def test_guide_scale_invariance_up_to_float_max(scale):
    # The weight depends on |g_p - g_q| / sigma_d only: guides and sigma_d scaled alike by up
    # to ~float32 max (differences of 2 * 2^126 would overflow even unsquared) filter alike.
    rng = np.random.default_rng(0)
    x = jnp.asarray(rng.normal(size=(3, 9, 7)), jnp.float32)
    g = rng.uniform(-1.0, 1.0, size=(2, 9, 7))
    kw = dict(levels=2, spatial_axes=(1, 2), guide_axes=(1, 2))
    ref = ob.atrous_bilateral(x, jnp.asarray(g, jnp.float32), sigma_d=0.3, **kw)
    out = ob.atrous_bilateral(x, jnp.asarray(g * scale, jnp.float32), sigma_d=0.3 * scale, **kw)
    assert np.all(np.isfinite(np.asarray(out)))
    np.testing.assert_allclose(np.asarray(out), np.asarray(ref), rtol=2e-5, atol=2e-6)
    # 2^50 is below the rescaling threshold (2^56): the plain computation, same result.
    small = ob.atrous_bilateral(
        x, jnp.asarray(g * 2.0**50, jnp.float32), sigma_d=0.3 * 2.0**50, **kw
    )
    np.testing.assert_allclose(np.asarray(small), np.asarray(ref), rtol=2e-5, atol=2e-6)


def test_one_channel_guide_at_float_max_needs_no_rescale():
    # One guide channel takes the distance |a - b| without a square or a rescaling pass;
    # |a - b| = 6e38 would overflow float32 unless halved (the kernel's one-channel distance).
    x = jnp.asarray([0.0, 1.0])
    out = ob.atrous_bilateral(
        x, jnp.asarray([3e38, -3e38], jnp.float32), sigma_d=1e38, levels=1, spatial_axes=(0,)
    )
    w = np.exp(-6.0)  # exp(-|a - b| / sigma_d), float64
    ref = [(0.25 * w) / (0.375 + 0.25 * w), 0.375 / (0.375 + 0.25 * w)]
    # float32 rounding of the guide and of the weight's exponent: ~1e-6 relative.
    np.testing.assert_allclose(np.asarray(out), ref, rtol=1e-5)
    # The same guide as a 2-channel guide (second channel 0) takes the rescaling path.
    g2 = jnp.asarray([[3e38, -3e38], [0.0, 0.0]], jnp.float32)
    out2 = ob.atrous_bilateral(x, g2, sigma_d=1e38, levels=1, spatial_axes=(0,), guide_axes=(1,))
    np.testing.assert_allclose(np.asarray(out2), np.asarray(out), rtol=1e-5)
