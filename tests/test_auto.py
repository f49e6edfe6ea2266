"""sigma_d="auto": scale invariance, the bounded step, state, transforms and bad input; with
sigma_d="sure" beside it where the same check applies (test_sure.py has the rest)."""

from __future__ import annotations

import functools
import math

import hypothesis.extra.numpy as hnp
import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
from hypothesis import given
from hypothesis import strategies as st

import optax_bilateral as ob
from optax_bilateral._src.filter import local
from states import at_step, filtered_state, with_filtered_state

AUTO, SURE = ob.Auto(), ob.Sure()
EVERY_TEXEL = ob.auto_sigma(min_texels=2**40)  # statistics over every texel (no sub-grid)

SHAPE = (16, 16, 3)


def _target(block=4):
    """A piecewise-constant RGB image of 4 x 4 blocks: edges for the filter to keep."""
    rng = np.random.default_rng(0)
    return jnp.asarray(np.kron(rng.random((4, 4, 3)), np.ones((block, block, 1))), jnp.float32)


def _noisy_grad(params, key, target):
    """Gradient of 0.5 |x - target|^2 plus unit Gaussian noise per entry."""
    return params - target + jax.random.normal(key, params.shape, params.dtype)


def _run(opt, params, target, steps=12, scale=1.0):
    """``steps`` updates of ``opt`` on a problem whose parameters are ``scale`` times the
    unit problem's (the gradient is then the unit gradient / scale: the same loss)."""
    state = opt.init(params)

    @jax.jit
    def step(p, s, key):
        g = _noisy_grad(p / scale, key, target) / scale
        u, s = opt.update(g, s, p)
        return optax.apply_updates(p, u), s

    for i in range(steps):
        params, state = step(params, state, jax.random.PRNGKey(i))
    return params, state


@functools.cache
def _units_runner(sigma_d, log_guide):
    """12 steps of ``bilateral_adam`` on the unit problem stored ``scale`` times larger,
    with the learning rate ``0.05 * scale``: one compiled step serves every scale."""
    opt = optax.inject_hyperparams(
        ob.bilateral_adam, static_args=("sigma_d", "log_guide", "levels")
    )(learning_rate=0.05, sigma_d=sigma_d, log_guide=log_guide)

    @jax.jit
    def step(p, s, key, scale, target):
        g = _noisy_grad(p / scale, key, target) / scale
        u, s = opt.update(g, s, p)
        return optax.apply_updates(p, u), s

    def run(scale):
        target, params = _target(), jnp.full(SHAPE, 0.5 * scale, jnp.float32)
        state = opt.init(params)
        state.hyperparams["learning_rate"] = jnp.asarray(0.05 * scale, jnp.float32)
        for i in range(12):
            params, state = step(params, state, jax.random.PRNGKey(i), scale, target)
        return np.asarray(params) / scale  # in the unit problem's units

    return run


@pytest.mark.parametrize("sigma_d", ["auto", "sure"])
@pytest.mark.parametrize("log_guide", [False, True])
@pytest.mark.parametrize("scale", [1e-3, 1e3])
def test_trajectory_is_invariant_to_the_parameters_units(scale, log_guide, sigma_d):
    # Parameters in other units (x scale, the learning rate with them) give the same
    # trajectory in those units: auto's (and sure's) sigma_d follows the guide's scale. A
    # fixed sigma_d does not (checked below), so the test can fail.
    run = _units_runner(sigma_d, log_guide)
    np.testing.assert_allclose(run(scale), run(1.0), rtol=2e-3, atol=2e-4)
    if not log_guide and sigma_d == "auto":
        fixed = _units_runner(0.1, False)
        assert np.max(np.abs(fixed(scale) - fixed(1.0))) > 1e-3


def test_auto_beats_adam_on_a_noisy_denoising_problem():
    target = _target(block=8)
    x0 = jnp.full(target.shape, 0.5, jnp.float32)

    def error(opt):
        x, _ = _run(opt, x0, target, steps=60)
        return float(jnp.mean(jnp.abs(x - target)))

    adam = min(error(optax.adam(lr)) for lr in (0.01, 0.03))
    auto_err = error(ob.bilateral_adam(0.03, sigma_d="auto"))
    assert auto_err < 0.9 * adam, (auto_err, adam)


# sigma_d="sure" with one factor of 1 records "auto"'s step scale itself (SureState.sigma_d):
# the prefilter's sigma_d, and the scale of "sure"'s candidates.
STEP_SCALE = ob.sure_sigma(factors=(1.0,), first_factor=1.0)


def _step_scales(guides, rule=STEP_SCALE):
    """The step scale (``SureState.sigma_d``) of each update of a postfilter whose guide, its
    parameters, is the next of ``guides``."""
    opt = ob.postfilter(sigma_d=rule, levels=2)
    update, state, out = jax.jit(opt.update), opt.init(guides[0]), []
    for i, guide in enumerate(guides):
        g = jax.random.normal(jax.random.PRNGKey(i), guide.shape)
        _, state = update(g, state, guide)
        out.append(float(state.sigma_state.sigma_d))
    return out


def test_sigma_follows_the_guide_step_and_starts_from_its_contrast():
    guide = jnp.asarray(np.random.default_rng(1).random((8, 8, 2)), jnp.float32)
    axes = (0, 1)
    moved = guide + 0.01
    # The first step, the same guide again (at rest), then moved by 0.01 * (1, 1).
    first, rest, later = _step_scales([guide, guide, moved])
    local = ob.atrous_bilateral(guide, guide, sigma_d=math.inf, levels=1, spatial_axes=axes)
    deviation = np.linalg.norm(np.asarray(guide - local), axis=-1).mean()
    np.testing.assert_allclose(first, AUTO.contrast_factor * deviation, rtol=1e-5)
    # On white noise that is about the mean neighbour difference.
    diffs = [np.linalg.norm(np.diff(np.asarray(guide), axis=a), axis=-1).mean() for a in axes]
    assert 0.7 < float(first) / np.mean(diffs) < 1.3
    np.testing.assert_allclose(later, AUTO.step_factor * 0.01 * math.sqrt(2), rtol=1e-4)
    # A guide that did not move falls back to the contrast.
    np.testing.assert_allclose(rest, first)
    # The prefilter filters the gradient at that sigma_d, step after step.
    pre = ob.prefilter()
    state = pre.init(guide)
    for i, (params, sigma) in enumerate(zip([guide, guide, moved], [first, rest, later])):
        g = jax.random.normal(jax.random.PRNGKey(i), guide.shape)
        u, state = pre.update(g, state, params)
        fixed = ob.prefilter(sigma_d=sigma)
        np.testing.assert_allclose(u, fixed.update(g, fixed.init(params), params)[0], rtol=1e-5)


# Moments and a gradient for one postfilter step on an 8 x 8 x 2 leaf.
_RNG = np.random.default_rng(5)
_G, _MU = (jnp.asarray(_RNG.normal(size=(8, 8, 2)), jnp.float32) for _ in range(2))
_NU = _MU**2 + jnp.asarray(_RNG.random((8, 8, 2)), jnp.float32)


def _second_update(sigma_d, params, **rule_state):
    """The postfilter's second update (``_MU``, ``_NU`` its moments before it) with
    ``sigma_d`` and the fields of its rule's state given."""
    opt = ob.postfilter(sigma_d=sigma_d)
    return opt.update(_G, at_step(opt.init(params), 1, mu=_MU, nu=_NU, **rule_state), params)[0]


def test_postfilter_sigma_is_one_learning_rate_in_the_guides_units():
    """The postfilter's sigma_d is sqrt(C) times the guide's mean step per unit of its last
    direction (AutoState.direction): its step is the step at that number."""
    guide = jnp.asarray(np.random.default_rng(1).random((8, 8, 2)), jnp.float32)
    # Each texel moved by 0.01 * (1, 1): 0.01 sqrt(2) per step, along a direction of norm 0.5.
    moved = guide + 0.01
    u = _second_update("auto", moved, previous_guide=guide, direction=0.5)
    rate = math.sqrt(2) * 0.01 * math.sqrt(2) / 0.5
    # Here the step moves 10x as much as sigma_d (relative): rtol 1e-4 holds sigma_d to
    # 1e-5, and a sigma_d 3e-5 off fails.
    np.testing.assert_allclose(u, _second_update(rate, moved), rtol=1e-4)
    assert not np.allclose(u, _second_update(rate * (1 + 3e-5), moved), rtol=1e-4, atol=0)
    # No direction yet (0), or a guide at rest: the contrast (the first step's scale).
    (contrast_moved,) = _step_scales([moved])
    (contrast,) = _step_scales([guide])
    u = _second_update("auto", moved, previous_guide=guide, direction=0.0)
    np.testing.assert_allclose(u, _second_update(jnp.float32(contrast_moved), moved), rtol=1e-6)
    u = _second_update("auto", guide, previous_guide=guide, direction=1.0)
    np.testing.assert_allclose(u, _second_update(jnp.float32(contrast), guide), rtol=1e-6)


@pytest.mark.parametrize("learning_rate", [1e-3, 0.5])
def test_the_state_keeps_the_direction_so_sigma_follows_the_learning_rate(learning_rate):
    """Unprojected, the guide (the parameters) moves by lr times the stored direction, so
    the next sigma_d is sqrt(C) lr."""
    opt = ob.bilateral_adam(learning_rate)
    params = _target()
    state = opt.init(params)
    assert float(filtered_state(state).sigma_state.direction) == 0.0
    for i in range(3):
        g = _noisy_grad(params, jax.random.PRNGKey(i), _target())
        u, state = opt.update(g, state, params)
        params = optax.apply_updates(params, u)
        step = np.linalg.norm(np.asarray(u, np.float64), axis=-1).mean()
        np.testing.assert_allclose(
            float(filtered_state(state).sigma_state.direction) * learning_rate, step, rtol=1e-5
        )
    prefilter = ob.prefilter().init(params)
    assert prefilter.sigma_state.direction is None


@st.composite
def blend_problems(draw):
    shape = draw(st.sampled_from([(6, 5, 1), (1, 9, 2), (4, 4, 3)]))
    elements = st.floats(-1e6, 1e6, width=32)
    m = draw(hnp.arrays(np.float32, shape, elements=elements))
    extra = draw(hnp.arrays(np.float32, shape, elements=st.floats(0, 1e6, width=32)))
    residual = draw(hnp.arrays(np.float32, shape, elements=elements))
    guide = draw(hnp.arrays(np.float32, shape[:2], elements=st.floats(-3, 3, width=32)))
    count = draw(st.integers(1, 50))
    return m, m.astype(np.float64) ** 2 + extra, residual, guide, count


B1, B2 = 0.2, 0.36  # the postfilter's moments in the blend's tests


def _blend_step(sigma_d, m, v, params, count, levels=None, **rule_state):
    """``(update, state)`` of step ``count`` of a postfilter (``B1``, ``B2``) from the moments
    ``m, v`` with the gradient ``m`` (the first moment stays ``m``) and its rule's state's
    fields given."""
    opt = ob.postfilter(B1, B2, sigma_d=sigma_d, levels=levels, spatial_axes=(0, 1))
    state = at_step(opt.init(params), count - 1, mu=m, nu=v, **rule_state)
    return opt.update(jnp.asarray(m), state, params)


def _assert_bounded(u, state):
    """``|u| <=`` the largest ``|m_hat| / sqrt(v_hat)`` of the moments ``state`` keeps."""
    t = int(state.count)
    m = np.asarray(state.mu, np.float64) / (1 - B1**t)
    v = np.asarray(state.nu, np.float64) / (1 - B2**t)
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.abs(m) / np.sqrt(v)
    bound = np.max(ratio[np.isfinite(ratio)], initial=0.0)
    got = np.abs(np.asarray(u, np.float64))
    assert np.all(np.isfinite(got)) and np.all(got <= bound * (1 + 1e-5) + 1e-6)


@given(problem=blend_problems())
def test_the_blend_keeps_the_bounded_step(problem):
    # Supplement 1.3: m~ and v~ come from one non-negative row-stochastic operator, so
    # |m~| / sqrt(v~) <= the largest |m| / sqrt(v) of the texels they mix. The gate was open
    # at the last step: this step blends.
    m, v, residual, guide, count = problem
    params = jnp.broadcast_to(jnp.asarray(guide)[..., None], m.shape)
    state = dict(residual=residual, gate=0.5, previous_guide=params)
    u, new = _blend_step("auto", m, v.astype(np.float32), params, count, **state)
    assert np.all(np.isfinite(np.asarray(new.sigma_state.residual)))
    _assert_bounded(u, new)


def _persistent_bias(bias, steps=60, seed=0):
    """A postfilter (``B1``, ``B2``, the gate checked every step) on ``bias + N(0, 1)`` under a
    constant guide, where the filter is a plain low-pass and misses a checkerboard ``bias``
    (B m_hat = m_hat - bias, nearly). Each step's gate, and the share of Adam's last step
    (the moments unfiltered) beyond the filter's along ``bias`` that the last step keeps."""
    opt = ob.postfilter(B1, B2, sigma_d=ob.auto_sigma(check_period=1), spatial_axes=(0, 1))
    x = jnp.zeros(bias.shape)
    update, state, gates = jax.jit(opt.update), opt.init(x), []
    key = jax.random.PRNGKey(seed)
    for t in range(1, steps + 1):
        g = bias + jax.random.normal(jax.random.fold_in(key, t), bias.shape)
        before = state
        u, state = update(g, state, x)
        gates.append(float(state.sigma_state.gate))
    filtered, _ = update(g, at_step(before, steps - 1, gate=0.0), x)  # gate closed: no blend
    m, v = state.mu / (1 - B1**steps), state.nu / (1 - B2**steps)
    sign = np.sign(np.asarray(bias))
    along = lambda d: float(np.mean((np.asarray(d) - np.asarray(filtered)) * sign))
    return gates, along(u) / along(m / (jnp.sqrt(v) + 1e-8))


def _checkerboard(n=32):
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    return jnp.asarray(((i + j) % 2 * 2.0 - 1.0)[..., None], jnp.float32)


def test_the_blend_opens_where_a_bias_below_the_noise_persists_across_the_leaf():
    # The filter's bias, 0.7 of one gradient's noise, on every texel (the i.i.d. noise
    # target): the residual's ~33-step average sees it, the gate opens fully and the step
    # keeps most of what Adam's would beyond the filter's (0.67 here).
    gates, kept = _persistent_bias(0.7 * _checkerboard())
    assert gates[-1] == 1 and kept > 0.5, (gates[-1], kept)


def test_the_blend_stays_closed_where_the_bias_persists_on_half_the_leaf():
    # A bias at the noise level on half the texels (a piecewise-smooth target's edges are
    # fewer): the leaf's gate stays shut and the filtered moments pass unchanged (the
    # former gate at 0.2 opened here).
    half = _checkerboard() * (jnp.arange(32)[None, :, None] < 16)
    gates, _ = _persistent_bias(half)
    assert all(gate == 0 for gate in gates)  # checked every step: no step blends


def _run_auto(steps, target, noise, period=None, seed=0):
    """Each step's ``(update, AutoState.gate, AutoState.residual)`` of ``bilateral_adam()``
    (``sigma_d="auto"``) on ``(x - target) + noise N(0, 1)``, with the gate's check period
    ``period`` if given."""
    rule = ob.auto_sigma(check_period=AUTO.check_period if period is None else period)
    rng = np.random.default_rng(seed)
    opt = ob.bilateral_adam(0.02, sigma_d=rule, spatial_axes=(0, 1))
    update = jax.jit(opt.update)
    x = jnp.full((32, 32, 1), 0.5, jnp.float32)
    state, out = opt.init(x), []
    for _ in range(steps):
        g = (x - target) + noise * jnp.asarray(rng.normal(size=x.shape), jnp.float32)
        u, state = update(g, state, x)
        auto_state = filtered_state(state).sigma_state
        out.append((np.asarray(u), float(auto_state.gate), np.asarray(auto_state.residual)))
        x = x + u
    return out


def test_a_closed_gate_skips_the_blend_and_changes_no_update(iid_and_smooth_targets):
    """Where the gate stays closed (a smooth, noisy target), skipping the blend's statistics
    between checks gives, from the same state, the update and the residual average of
    computing them every step, to rounding (the two programs fuse their arithmetic
    differently)."""
    _, smooth = iid_and_smooth_targets
    opt = ob.bilateral_adam(0.02, spatial_axes=(0, 1))
    every_step = ob.auto_sigma(check_period=1)
    every = jax.jit(ob.bilateral_adam(0.02, sigma_d=every_step, spatial_axes=(0, 1)).update)
    x = jnp.full((32, 32, 1), 0.5, jnp.float32)
    skipping = jax.jit(opt.update)
    rng = np.random.default_rng(0)
    state = opt.init(x)
    for _ in range(3 * AUTO.check_period):
        g = (x - smooth) + 0.3 * jnp.asarray(rng.normal(size=x.shape), jnp.float32)
        (u, new), (u_skip, new_skip) = every(g, state, x), skipping(g, state, x)
        auto_state, auto_skip = (
            filtered_state(new).sigma_state,
            filtered_state(new_skip).sigma_state,
        )
        assert float(auto_state.gate) == 0 and float(auto_skip.gate) == 0
        np.testing.assert_allclose(u_skip, u, rtol=1e-6, atol=1e-6 * float(jnp.max(jnp.abs(u))))
        residual, residual_skip = np.asarray(auto_state.residual), auto_skip.residual
        scale = float(np.max(np.abs(residual)))
        np.testing.assert_allclose(residual_skip, residual, rtol=1e-5, atol=1e-6 * scale)
        state, x = new, x + u
    assert np.any(residual != 0)


def test_the_gate_opens_at_a_check_step_and_is_then_computed_every_step(iid_and_smooth_targets):
    """A noise-free gradient toward an i.i.d. target opens the gate at the second step when
    it is checked every step; with the default period the opening waits for the first
    multiple of ``check_period``, and from then on the blend runs at every step."""
    iid, _ = iid_and_smooth_targets
    every = _run_auto(3 * AUTO.check_period, iid, 0.0, period=1)
    assert every[0][1] == 0 and all(gate > 0 for _, gate, _ in every[1:])
    gates = [gate for _, gate, _ in _run_auto(3 * AUTO.check_period, iid, 0.0)]
    first = next(t for t, gate in enumerate(gates, start=1) if gate > 0)
    assert first == AUTO.check_period
    assert all(gate > 0 for gate in gates[first:])


def test_a_step_blends_on_an_open_gate_and_checks_a_closed_one_at_multiples_of_the_period(
    iid_and_smooth_targets,
):
    """What a step computes of the blend, against a rule that checks every step: with the
    gate open at the last step, the blend (the same step and gate); closed, at a multiple of
    ``check_period`` the gate alone (the same gate, the step unblended), else nothing (gate
    0, the step unblended)."""
    iid, _ = iid_and_smooth_targets
    every = ob.auto_sigma(check_period=1)
    opt, every_opt = (ob.postfilter(sigma_d=r, spatial_axes=(0, 1)) for r in (AUTO, every))
    update, every_update = jax.jit(opt.update), jax.jit(every_opt.update)
    # Three noise-free steps toward the i.i.d. target, where the gate opens.
    x = jnp.full((32, 32, 1), 0.5, jnp.float32)
    state = opt.init(x)
    for _ in range(3):
        u, state = every_update(x - iid, state, x)
        x = x - 0.02 * u
    g, period = x - iid, AUTO.check_period
    for count in range(1, 3 * period + 1):
        steps = {}
        for gate in (0.0, 0.5):
            start = at_step(state, count, gate=gate)  # this step: count + 1
            (u, new), (u_every, new_every) = update(g, start, x), every_update(g, start, x)
            scale = float(jnp.max(jnp.abs(u_every)))
            np.testing.assert_allclose(u, u_every, rtol=1e-6, atol=1e-6 * scale)
            checked = gate > 0 or (count + 1) % period == 0
            expected = float(new_every.sigma_state.gate) if checked else 0.0
            assert float(new_every.sigma_state.gate) > 0
            assert float(new.sigma_state.gate) == pytest.approx(expected, rel=1e-5)
            steps[gate] = np.asarray(u)
        assert np.max(np.abs(steps[0.5] - steps[0.0])) > 1e-3 * scale  # the open gate blends


def test_the_gate_from_the_subgrid_is_the_gate_from_every_entry_to_rounding():
    """A closed gate's check computes the local averages at the sub-grid's entries only
    (every s-th texel, test_stride_leaves_at_least_min_texels); they are the full local
    averages' sub-grid. The blend's statistics read the sub-grid only (the residual is kept
    there), so on leaves whose blend weight is uniform in distribution the gate the step
    writes estimates the one from every texel from a sixteenth of them (4096 texels: within
    0.07 over seeds 0-3, 0.05 on seed 0; the gate is 1 / 0.15 times mean lam's error)."""
    rng = np.random.default_rng(3)
    for shape, axes, stride in [
        ((512, 512, 3), (0, 1), 4),
        ((300, 7, 2), (0, 1), 1),
        ((64, 64, 64, 1), (0, 1, 2), 2),
    ]:
        a = jnp.asarray(rng.normal(size=shape), jnp.float32)
        full = [local.every(x, axes, stride) for x in local.local_average((a, a * a), axes)]
        for x, y in zip(local.local_average_subgrid((a, a * a), axes, stride), full):
            np.testing.assert_allclose(x, y, rtol=1e-5, atol=1e-6)
    # A check step (8) whose moments are m_hat = m, v_hat = v, under a constant guide.
    shape, b, t = (256, 256, 2), 0.9, 8
    s = AUTO._stride(shape, (0, 1))
    assert s == 4  # a sixteenth of the texels
    c = 1 - b**t
    key = jax.random.PRNGKey(0)
    m = jax.random.normal(key, shape)
    v = m * m + jax.random.uniform(jax.random.fold_in(key, 1), shape)
    moments = dict(mu=c * m, nu=c * (v - (1 - b) * c * m * m) / b)
    x, gates = jnp.zeros(shape), []
    for scale in (0.0, 0.33, 0.37, 0.45):  # the gate closed, opening, and open
        residual = scale * jax.random.normal(jax.random.fold_in(key, 2), shape)
        gate = {}
        for rule in (AUTO, EVERY_TEXEL):
            opt = ob.postfilter(b, b, sigma_d=rule, spatial_axes=(0, 1))
            kept = residual[::s, ::s] if rule is AUTO else residual  # the state's sub-grid
            _, new = opt.update(c * m, at_step(opt.init(x), t - 1, residual=kept, **moments), x)
            gate[rule] = float(new.sigma_state.gate)
        assert abs(gate[AUTO] - gate[EVERY_TEXEL]) < 0.1, (scale, gate)
        gates.append(gate[EVERY_TEXEL])
    assert gates[0] == 0 and 0 < gates[1] < gates[2] < 1 and gates[3] == 1
    kept = {rule: ob.postfilter(sigma_d=rule).init(x).sigma_state for rule in (AUTO, EVERY_TEXEL)}
    for field in ("previous_guide", "residual"):  # sub-grid, every texel
        assert getattr(kept[AUTO], field).shape == (64, 64, 2)
        assert getattr(kept[EVERY_TEXEL], field).shape == shape


@given(problem=blend_problems(), scale=st.floats(0.5**13, 2.0**13, width=32))
def test_sure_choice_and_blend_keep_the_bounded_step(problem, scale):
    # Whichever candidate sigma_d="sure" chooses (its scale the guide's step times 3), m~ and
    # v~ come from one operator.
    m, v, zeta, guide, _ = problem
    params = jnp.broadcast_to(jnp.asarray(guide)[..., None], m.shape)
    shift = scale / (SURE.auto.step_factor * math.sqrt(m.shape[-1]))  # each texel's step
    state = dict(previous_guide=params - shift, previous_gradient=m - zeta)
    u, new = _blend_step("sure", m, v.astype(np.float32), params, 5, levels=3, **state)
    sigma_d = float(new.sigma_state.sigma_d)
    assert np.isfinite(sigma_d) and sigma_d >= 0
    _assert_bounded(u, new)


def test_state_holds_the_previous_guide_and_residual_and_checkpoints(tmp_path):
    params = {"tex": jnp.full(SHAPE, 0.5), "light": jnp.zeros(())}
    opt = ob.bilateral_adam(0.05, sigma_d={"tex": "auto", "light": 0.1})
    _, state = _run_dict(opt, params, steps=3)
    post = filtered_state(state)
    assert post.sigma_state["light"] is None  # not filtered: Adam's rule
    np.testing.assert_array_equal(post.sigma_state["tex"].previous_guide, _prev_params(opt, params))
    assert post.sigma_state["tex"].residual.shape == SHAPE
    path = tmp_path / "state.npz"
    ob.save_state(path, state)
    restored = ob.load_state(path, opt.init(params))
    for a, b in zip(jax.tree.leaves(restored), jax.tree.leaves(state)):
        np.testing.assert_array_equal(a, b)


def _run_dict(opt, params, steps):
    target = _target()
    state = opt.init(params)
    for i in range(steps):
        g = {
            "tex": _noisy_grad(params["tex"], jax.random.PRNGKey(i), target),
            "light": params["light"] - 1.0,
        }
        u, state = opt.update(g, state, params)
        params = optax.apply_updates(params, u)
    return params, state


def _prev_params(opt, params):
    """The tex parameters the last of 3 updates saw (2 updates in)."""
    x, _ = _run_dict(opt, params, steps=2)
    return x["tex"]


@pytest.mark.parametrize("sigma_d", ["auto", "sure"])
def test_jit_eager_vmap_and_inject_hyperparams_agree(sigma_d):
    target = _target()
    x0 = jnp.full(SHAPE, 0.5, jnp.float32)
    opt = ob.bilateral_adam(0.05, sigma_d=sigma_d, levels=2)
    # The second step, with a moved guide ("sure" chooses once it has a noise sample).
    _, state = opt.update(_noisy_grad(x0, jax.random.PRNGKey(0), target), opt.init(x0), x0)
    x1 = x0 + 0.01
    g = _noisy_grad(x1, jax.random.PRNGKey(1), target)
    eager = opt.update(g, state, x1)
    jitted = jax.jit(opt.update)(g, state, x1)
    for a, b in zip(jax.tree.leaves(eager), jax.tree.leaves(jitted)):
        np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-7)
    injected = optax.inject_hyperparams(ob.bilateral_adam, static_args=("levels", "sigma_d"))(
        learning_rate=0.05, sigma_d=sigma_d, levels=2
    )
    u_inj, _ = injected.update(g, injected.init(x0)._replace(inner_state=state), x1)
    np.testing.assert_allclose(u_inj, eager[0], rtol=1e-6, atol=1e-7)
    batch = jnp.stack([x1, x1 + 0.1])
    states = jax.tree.map(lambda s: jnp.stack([s, s]), state)
    ub, _ = jax.vmap(opt.update)(jnp.stack([g, g]), states, batch)
    np.testing.assert_allclose(ub[0], eager[0], rtol=1e-5, atol=1e-7)


@pytest.mark.parametrize(
    "sigma_d, kwargs",
    [
        ("auto", dict(prefilter=True, postfilter=False)),
        ("auto", dict(prefilter=True)),
        ("auto", dict(guide="self")),
        ("auto", dict(b1=0.0, b2=0.0)),
        ("auto", dict(mask_unobserved=True)),
        ("auto", dict(log_guide=True, separable=False)),
        ("sure", dict(mask_unobserved=True)),
        ("sure", dict(log_guide=True, separable=False)),
        ("sure", dict(b1=0.0, b2=0.5)),  # no memory: the noise is never estimated
    ],
    ids=[
        "prefilter",
        "pre+post",
        "self",
        "memoryless",
        "mask",
        "log-full",
        "sure-mask",
        "sure-log-full",
        "sure-b1=0",
    ],
)
def test_every_composition_runs_and_stays_finite_at_the_extremes(sigma_d, kwargs):
    x0 = jnp.full((8, 6, 2), 0.5, jnp.float32)
    opt = ob.bilateral_adam(0.05, sigma_d=sigma_d, levels=2, **kwargs)
    state = opt.init(x0)
    update = jax.jit(opt.update)
    x = x0
    rng = np.random.default_rng(0)
    for g in (
        rng.normal(size=x0.shape),
        np.zeros(x0.shape),  # nothing observed (mask) / zero gradient
        np.where(rng.random(x0.shape) < 0.1, np.nan, rng.normal(size=x0.shape) * 1e30),
        rng.normal(size=x0.shape) * 1e-30,
        rng.normal(size=x0.shape),
    ):
        g = jnp.asarray(g, jnp.float32)
        u, state = update(g, state, x)
        assert np.all(np.isfinite(np.asarray(u))), kwargs
        bad = ~np.all(np.isfinite(np.asarray(g)), axis=-1)
        if "prefilter" not in kwargs or kwargs.get("postfilter", True):
            assert np.all(np.asarray(u)[bad] == 0)
        if sigma_d == "sure":
            assert np.isfinite(float(filtered_state(state).sigma_state.sigma_d))
        x = optax.apply_updates(x, u)


def test_a_constant_guide_and_a_guide_that_never_moves():
    # sigma_d from a constant guide is 0; every neighbour then has an equal guide and
    # weighs 1 (the filter's rule), so the first step is the plain low-pass of the moments.
    x0 = jnp.zeros((8, 8, 1))
    g = jnp.asarray(np.random.default_rng(0).normal(size=x0.shape), jnp.float32)
    u_auto, _ = ob.bilateral_adam(1.0, sigma_d="auto", levels=2).update(
        g, ob.bilateral_adam(1.0, sigma_d="auto", levels=2).init(x0), x0
    )
    u_inf, _ = ob.bilateral_adam(1.0, sigma_d=math.inf, levels=2).update(
        g, ob.bilateral_adam(1.0, sigma_d=math.inf, levels=2).init(x0), x0
    )
    np.testing.assert_allclose(u_auto, u_inf, rtol=1e-6)


@pytest.mark.parametrize("bad", ["Auto", "adaptive", ""])
def test_other_strings_are_refused_naming_sigma_d(bad):
    with pytest.raises(ValueError, match=r"sigma_d.*'auto'"):
        ob.bilateral_adam(0.1, sigma_d=bad)
    with pytest.raises(ValueError, match=r"sigma_d.*'auto'"):
        ob.postfilter(sigma_d={"a": bad}).init({"a": jnp.zeros((4, 4, 1))})


def test_the_filter_itself_takes_numbers_only():
    with pytest.raises(TypeError, match="sigma_d"):
        ob.atrous_bilateral(
            jnp.zeros((4, 4)), jnp.zeros((4, 4)), sigma_d="auto", levels=1, spatial_axes=(0, 1)
        )


@pytest.mark.parametrize(
    "shape, axes, expected",
    [
        ((64, 64, 3), (0, 1), 1),  # the suite's textures: every texel
        ((128, 128, 1), (0, 1), 2),
        ((256, 256, 1), (0, 1), 4),
        ((512, 512, 3), (0, 1), 8),
        ((64, 64, 64, 1), (0, 1, 2), 4),
        ((1 << 20,), (0,), 256),
        ((3, 1000, 1000), (1, 2), 8),  # channels first
    ],
)
def test_stride_leaves_at_least_min_texels(shape, axes, expected):
    """The state keeps every s-th texel of the guide along each spatial axis: the largest
    power of two s that leaves at least ``min_texels`` texels (1 below that)."""
    opt = ob.postfilter(spatial_axes=axes)
    kept = jax.eval_shape(opt.init, jax.ShapeDtypeStruct(shape, jnp.float32))
    kept = kept.sigma_state.previous_guide.shape
    count = lambda s: math.prod(-(-shape[a] // s) for a in axes)
    assert kept == tuple(-(-n // expected) if a in axes else n for a, n in enumerate(shape))
    assert count(expected) >= AUTO.min_texels or expected == 1
    assert count(2 * expected) < AUTO.min_texels


def test_a_large_leaf_keeps_a_sub_grid_of_its_guide_and_sigma_is_its_full_mean():
    """Above ``min_texels`` the state keeps every s-th texel; the guide's mean step over it is
    the full grid's to about a percent (1.3% here, from 4875 texels of a step whose size varies
    per texel), and an unprojected step still gives sqrt(C) lr."""
    rng = np.random.default_rng(0)
    shape = (300, 260, 2)  # 78000 texels: stride 4, not dividing 300 or 260 evenly
    guide = jnp.asarray(rng.random(shape), jnp.float32)
    step = jnp.asarray(rng.standard_normal(shape) * rng.random(shape[:2])[..., None], jnp.float32)
    _, sub = _step_scales([guide, guide + 0.01 * step])
    full = AUTO.step_factor * 0.01 * np.linalg.norm(np.asarray(step), axis=-1).mean()
    np.testing.assert_allclose(sub, full, rtol=2e-2)
    opt = ob.bilateral_adam(0.02)
    params = jnp.asarray(rng.random(shape), jnp.float32)
    state = opt.init(params)
    assert filtered_state(state).sigma_state.previous_guide.shape == (75, 65, 2)
    for _ in range(3):
        g = jnp.asarray(rng.standard_normal(shape), jnp.float32) + params - 0.5
        u, state = opt.update(g, state, params)
        np.testing.assert_array_equal(
            filtered_state(state).sigma_state.previous_guide, params[::4, ::4]
        )
        params = optax.apply_updates(params, u)
        moved = np.linalg.norm(np.asarray(u, np.float64), axis=-1).mean()
        np.testing.assert_allclose(
            float(filtered_state(state).sigma_state.direction) * 0.02, moved, rtol=5e-3
        )


# ----------------------------------------------------------------------------------------
# Correlated gradient noise


def _blurred(noise: np.ndarray, width: float) -> np.ndarray:
    """``noise`` convolved along its first two axes with a Gaussian of ``width`` texels
    (lag-1 correlation ``exp(-1 / (4 width^2))``), wrapping around."""
    k = np.arange(-8, 9)
    kernel = np.exp(-(k**2) / (2 * width**2))
    out = noise
    for axis in (0, 1):
        out = sum(w * np.roll(out, int(d), axis=axis) for d, w in zip(k, kernel))
    return out


def _correlated(g, m_hat, t=5, b1=0.2, observed=None):
    """``AutoState.correlated`` after step ``t`` (a check step: ``check_period=t``) of a
    postfilter whose gradient is ``g`` and whose first moment is then ``m_hat (1 - b1^t)``;
    texels where ``observed`` is False get a NaN gradient (unobserved)."""
    c1 = 1 - b1**t
    g, m = jnp.asarray(g, jnp.float32), jnp.asarray(m_hat * c1, jnp.float32)
    mu = (m - (1 - b1) * g) / b1 if b1 else jnp.zeros_like(m)  # m = b1 mu + (1 - b1) g
    if observed is not None:
        g = jnp.where(observed, g, jnp.nan)
    rule = ob.auto_sigma(check_period=t)
    opt = ob.postfilter(b1, 0.36, sigma_d=rule, spatial_axes=(0, 1))
    params = jnp.zeros(g.shape)
    _, state = opt.update(g, at_step(opt.init(params), t - 1, mu=mu), params)
    return bool(state.sigma_state.correlated)


def _tells_blurred_from_white(shape, scale=1.0):
    """``correlated`` on white noise, noise blurred over 1.5 texels (lag-1 correlation
    exp(-1/9) = 0.89) and over half a texel (exp(-1) = 0.37, below ``correlated``)."""
    rng = np.random.default_rng(0)
    noise = rng.normal(size=shape)
    signal = 0.1 * np.ones(shape)
    blurred = _blurred(noise, 1.5)
    blurred /= blurred.std()
    assert not _correlated(scale * (signal + noise), scale * signal)
    assert _correlated(scale * (signal + blurred), scale * signal)
    assert not _correlated(scale * (signal + _blurred(noise, 0.5)), scale * signal)


@pytest.mark.parametrize("scale", [1e-3, 1.0, 1e3])
def test_correlated_tells_blurred_noise_from_white_noise_at_every_scale(scale):
    _tells_blurred_from_white((64, 64, 3), scale)


def test_correlated_reads_pairs_on_the_subgrid_of_a_large_leaf():
    """On a leaf with a sub-grid (stride 8 at 512x512) the pairs are texels 8i and 8i + 1:
    the same lag-1 correlation, from a 32nd of the texels."""
    init = ob.postfilter(spatial_axes=(0, 1)).init
    kept = jax.eval_shape(init, jax.ShapeDtypeStruct((512, 512, 1), jnp.float32))
    assert kept.sigma_state.previous_guide.shape == (64, 64, 1)
    _tells_blurred_from_white((512, 512, 1))


def test_correlated_needs_the_difference_to_be_noise_not_the_signals_drift():
    """A smooth gradient that moved a little since the first moment (a noise-free run's
    first steps) is perfectly correlated but not noise: ``noisy`` keeps the step as it is."""
    x = np.linspace(0, 1, 64)
    signal = np.sin(3 * x)[:, None, None] * np.cos(2 * x)[None, :, None] * np.ones((1, 1, 3))
    drift = np.cos(5 * x)[:, None, None] * np.ones((1, 64, 3))
    lag = 1 - (1 - 0.2) / (1 - 0.2**5)  # z = lag (g - m_hat_{t-1})
    small = 0.5 * math.sqrt(AUTO.noisy) * lag * np.linalg.norm(signal) / np.linalg.norm(drift)
    assert not _correlated(signal + small * drift, signal)
    assert _correlated(signal + 4 * small * drift, signal)


def test_correlated_is_false_without_memory_a_first_step_or_a_gradient():
    rng = np.random.default_rng(1)
    blurred = _blurred(rng.normal(size=(32, 32, 1)), 1.5)
    g = jnp.asarray(blurred, jnp.float32)
    # First step: m = (1 - b1) g and c1 = 1 - b1, so g - m_hat = 0.
    assert not _correlated(g, g, t=1)
    # b1 = 0: m_hat is g.
    assert not _correlated(g, g, b1=0.0)
    assert not _correlated(np.zeros((32, 32, 1)), np.zeros((32, 32, 1)))
    # Unobserved texels are left out: blurred noise only on a masked-out half counts for nothing.
    observed = jnp.asarray(np.arange(32)[:, None, None] < 16) * jnp.ones((1, 32, 1), bool)
    half = np.where(np.asarray(observed), 0.0, blurred)
    assert _correlated(half + 0.01, 0.01 * np.ones_like(half))
    assert not _correlated(half + 0.01, 0.01 * np.ones_like(half), observed=observed)


def _correlated_problem(steps, **kwargs):
    """``bilateral_adam`` on ``x - target`` plus noise blurred over 1.5 texels; each step's
    ``AutoState.correlated``, and the last state and parameters."""
    rng = np.random.default_rng(2)
    target = _target()
    opt = ob.bilateral_adam(0.02, spatial_axes=(0, 1), **kwargs)
    x = jnp.full(SHAPE, 0.5, jnp.float32)
    state, flags = opt.init(x), []
    update = jax.jit(opt.update)
    for _ in range(steps):
        noise = _blurred(rng.normal(size=SHAPE), 1.5)
        g = (x - target) + jnp.asarray(noise / noise.std(), jnp.float32)
        u, state = update(g, state, x)
        flags.append(float(filtered_state(state).sigma_state.correlated))
        x = x + u
    return flags, state, x


def test_a_run_on_correlated_noise_switches_from_its_second_step_and_a_self_guided_one_never():
    flags, _, _ = _correlated_problem(2 * AUTO.check_period + 2)
    assert flags[0] == 0  # the first step has no noise estimate
    assert all(f == 1 for f in flags[1:])
    flags, _, _ = _correlated_problem(4, guide="self")  # self-guided: never heavier
    assert all(f == 0 for f in flags)


def _with_correlated(state, flag: int):
    """``state`` with ``AutoState.correlated`` set to ``flag``."""
    post = filtered_state(state)
    auto_state = post.sigma_state._replace(correlated=jnp.full([], flag, jnp.float32))
    return with_filtered_state(state, post._replace(sigma_state=auto_state))


def test_a_correlated_step_is_the_filter_at_heavy_factor_with_extra_levels_and_no_blend():
    """With ``AutoState.correlated`` set, the update is the one of ``levels + 1`` levels at
    ``heavy_factor`` times sigma_d without the blend (clean and masked gradients alike)."""
    _, state, x = _correlated_problem(2)
    heavy, light = _with_correlated(state, 1), _with_correlated(state, 0)
    g = jnp.asarray(_blurred(np.random.default_rng(3).normal(size=SHAPE), 1.5), jnp.float32)
    masked = g.at[3, 4].set(jnp.nan)
    opt = ob.bilateral_adam(0.02, spatial_axes=(0, 1))
    # count 3: not a check step, so the reference's blend stays closed as well.
    heavier = ob.auto_sigma(rate_factor=AUTO.rate_factor * AUTO.heavy_factor)
    reference = ob.bilateral_adam(
        0.02, sigma_d=heavier, spatial_axes=(0, 1), levels=ob.DEFAULT_LEVELS + 1
    )
    for grad in (g, masked):
        u, new = opt.update(grad, heavy, x)
        assert (
            float(filtered_state(new).sigma_state.correlated) == 1
            and float(filtered_state(new).sigma_state.gate) == 0
        )
        u_ref, _ = reference.update(grad, light, x)
        np.testing.assert_allclose(u, u_ref, rtol=1e-5, atol=1e-7)
        assert np.all(np.isfinite(np.asarray(u)))
        u_light, _ = opt.update(grad, light, x)
        assert np.max(np.abs(np.asarray(u_light) - np.asarray(u))) > 1e-3 * np.max(np.abs(u))
    assert float(u[3, 4, 0]) == 0  # the masked texel does not move


def test_heavy_levels_sets_the_levels_a_correlated_step_adds():
    """``auto_sigma(heavy_levels=(1-D, 2-D, 3-D))``: a correlated 2-D step runs ``levels + 2``
    levels with ``(0, 2, 0)``, and ``levels`` alone with ``(2, 0, 0)``."""
    _, state, x = _correlated_problem(2)
    heavy, light = _with_correlated(state, 1), _with_correlated(state, 0)
    g = jnp.asarray(_blurred(np.random.default_rng(4).normal(size=SHAPE), 1.5), jnp.float32)
    heavier = ob.auto_sigma(rate_factor=AUTO.rate_factor * AUTO.heavy_factor)
    for added in (2, 0):
        rule = ob.auto_sigma(heavy_levels=(2 - added, added, 0))
        opt = ob.bilateral_adam(0.02, sigma_d=rule, spatial_axes=(0, 1))
        levels = ob.DEFAULT_LEVELS + added
        reference = ob.bilateral_adam(0.02, sigma_d=heavier, spatial_axes=(0, 1), levels=levels)
        u, _ = opt.update(g, heavy, x)
        u_ref, _ = reference.update(g, light, x)
        np.testing.assert_allclose(u, u_ref, rtol=1e-5, atol=1e-7)


@pytest.mark.parametrize("bad", [(1, 2), (1, -1, 0), (1.0, 1, 0), [2, 1, 0], (True, 1, 0)])
def test_heavy_levels_must_be_three_non_negative_ints(bad):
    with pytest.raises(ValueError, match="heavy_levels must be a tuple of 3 ints"):
        ob.auto_sigma(heavy_levels=bad)


@pytest.mark.parametrize("period", [1, 3, 8])
def test_the_check_steps_are_the_multiples_of_the_check_period(period):
    # lax.rem (truncated) in place of jnp.remainder (floored): the same multiples, negative
    # counts and int32's ends included.
    rule = ob.Auto(check_period=period)
    top = np.iinfo(np.int32).max
    counts = np.array([0, 1, 2, 7, 8, 9, 16, 24, 25, -1, -8, -9, top, top - 7, -top - 1], np.int32)
    got = np.asarray(rule._check_step(jnp.asarray(counts)))
    np.testing.assert_array_equal(got, counts.astype(np.int64) % period == 0)
    assert got.any() and (period == 1 or not got.all())
