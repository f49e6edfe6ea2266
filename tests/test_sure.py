"""sigma_d="sure": the risk estimate's choice, the bounded step, state, transforms, bad input.

Scale invariance, the extremes, the bounded step and jit / vmap / inject_hyperparams are
checked beside "auto"'s in test_auto.py.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

import optax_bilateral as ob
from states import at_step, filtered_state

SURE = ob.Sure()
STEP_SCALE = ob.sure_sigma(factors=(1.0,), first_factor=1.0)  # sigma_d: the step scale itself

SHAPE = (16, 16, 3)
AXES = (0, 1)


LEVELS = 5  # the candidates' F: 2, 3, 4, 5
SCALE = 0.1  # the candidates' sigma_d per factor (their step scale)
T = 20  # the step: 1 - 0.2^20 is 1 in float32, so m_hat = m


def _labels(levels=LEVELS, rule=SURE):
    """``(factor, F)`` of every candidate, in the order of ``SureState.risks``: factor-major,
    F from ``min_levels`` (or ``levels``, if fewer) to ``levels``."""
    choices = range(min(rule.min_levels, levels), levels + 1)
    return [(f, n) for f in rule.factors for n in choices]


def _step(params, m, zeta, *, rule=SURE, levels=LEVELS, b1=0.2, count=T, **rule_state):
    """``(update, SureState)`` of step ``count`` of a postfilter with ``sigma_d=rule`` whose
    first moment is then ``m`` (the gradient is ``m``; ``v`` before it ``m^2 + 1``, the noise
    of ``v - m^2`` keeping the blend shut), whose noise sample is ``zeta``, and
    whose candidates' step scale is ``SCALE`` (the guide, ``params``, moved by ``SCALE / 3``
    per texel and channel: ``C = 1``); ``rule_state``: fields of its ``SureState``."""
    opt = ob.postfilter(b1, 0.36, sigma_d=rule, levels=levels, spatial_axes=AXES)
    m, zeta = jnp.asarray(m, jnp.float32), jnp.asarray(zeta, jnp.float32)
    c1 = 1 - b1**count
    rho = (1 - b1) * (2 - c1) / ((1 + b1) * c1)  # Var m_hat per unit gradient variance
    shift = SCALE / (rule.auto.step_factor * np.sqrt(m.shape[-1]))
    fields = dict(previous_guide=params - shift, previous_gradient=m - zeta / np.sqrt(rho / 2))
    state = at_step(opt.init(params), count - 1, mu=m, nu=m * m + 1, **(fields | rule_state))
    u, state = opt.update(m, state, params)
    return u, state.sigma_state


def _label(state):
    """``(factor, F)`` of the candidate ``state`` records (its sigma_d over ``SCALE``)."""
    return round(float(state.sigma_d) / SCALE, 3), int(state.levels)


def _choice(mean, noise, guide, probe=None, seed=0):
    """``(factor, F)`` that sigma_d="sure" picks for ``m_hat = mean + noise N(0, 1)`` with a
    probe of the same noise (default: an independent draw) from no evidence before."""
    rng = np.random.default_rng(seed)
    n = noise * rng.normal(size=mean.shape)
    zeta = noise * rng.normal(size=mean.shape) if probe is None else n
    guide = jnp.asarray(guide, jnp.float32)[..., None]
    return _label(_step(guide, mean + n, zeta)[1])


def test_the_risk_estimate_filters_noise_and_keeps_detail():
    i, j = np.meshgrid(np.arange(32), np.arange(32), indexing="ij")
    # A flat mean with the probe equal to m's noise: every candidate's bias estimate is 0,
    # so the least variance wins, the deepest cascade.
    flat = np.full((32, 32, 1), 0.5)
    assert _choice(flat, noise=1.0, guide=np.zeros((32, 32)), probe="same")[1] == LEVELS
    # A mean that changes sign every texel, nearly noise-free, under a constant guide (no
    # edge stops the filter): the least bias, the shallowest cascade.
    checker = ((i + j) % 2 * 2.0 - 1.0)[..., None]
    assert _choice(checker, noise=1e-3, guide=np.zeros((32, 32)))[1] == 2
    # The same mean as the guide: the smallest sigma_d stops at every edge and keeps it.
    assert _choice(checker, noise=1e-3, guide=checker[..., 0])[0] == SURE.factors[0]


def _fixed_update(params, m, sigma_d, levels, count=T, b1=0.2):
    """The update of a postfilter at ``sigma_d`` and ``levels`` from the moments ``_step``
    sets."""
    opt = ob.postfilter(b1, 0.36, sigma_d=sigma_d, levels=levels, spatial_axes=AXES)
    m = jnp.asarray(m, jnp.float32)
    state = at_step(opt.init(params), count - 1, mu=m, nu=m * m + 1)
    return opt.update(m, state, params)[0]


def test_the_first_step_takes_the_middle_factor_at_the_middle_level():
    """Before the noise can be estimated: ``first_factor`` times the step scale (the
    contrast, read with a single factor of 1) at the middle F, no evidence in the risks,
    and the step is that candidate's filter."""
    rng = np.random.default_rng(1)
    params = jnp.asarray(rng.random((16, 16, 1)), jnp.float32)
    g = jnp.asarray(rng.normal(size=params.shape), jnp.float32)
    opt, one = (ob.postfilter(sigma_d=r) for r in (SURE, STEP_SCALE))
    u, state = opt.update(g, opt.init(params), params)
    _, scale = one.update(g, one.init(params), params)
    sure, scale = state.sigma_state, float(scale.sigma_state.sigma_d)
    assert int(sure.levels) == 4
    assert float(sure.sigma_d) == pytest.approx(SURE.first_factor * scale, rel=1e-6)
    np.testing.assert_array_equal(sure.risks, np.zeros(len(_labels())))  # no evidence yet
    fixed = ob.postfilter(sigma_d=sure.sigma_d, levels=4)
    np.testing.assert_allclose(u, fixed.update(g, fixed.init(params), params)[0], rtol=1e-5)


def _evidence():
    """A leaf, its moment and noise sample, on which every step's risks favour one
    candidate (a noisy checkerboard under a random guide)."""
    rng = np.random.default_rng(4)
    params = jnp.asarray(rng.random((16, 16, 1)), jnp.float32)
    i, j = np.meshgrid(np.arange(16), np.arange(16), indexing="ij")
    mean = ((i + j) % 2 * 2.0 - 1.0)[..., None]
    return params, mean + 0.5 * rng.normal(size=mean.shape), 0.5 * rng.normal(size=mean.shape)


def test_the_choice_follows_the_moving_average_of_the_risks():
    # An average that favours another candidate outvotes one step's evidence; the same
    # evidence step after step moves the choice to the candidate it favours.
    params, m, zeta = _evidence()
    labels = _labels()
    _, once = _step(params, m, zeta)
    best = labels.index(_label(once))
    other = (best + len(labels) // 2) % len(labels)
    risks, picks = jnp.zeros(len(labels)).at[other].set(-1.0), []
    for _ in range(40):
        _, state = _step(params, m, zeta, risks=risks)
        picks.append(labels.index(_label(state)))
        risks = state.risks
    assert picks[0] == other and picks[-1] == best, picks
    switch = picks.index(best)
    assert all(p == other for p in picks[:switch]) and all(p == best for p in picks[switch:])
    # Steps without a usable noise sample (b1 = 0: no memory) leave the average as it is
    # and take the first candidate.
    _, kept = _step(params, m, zeta, b1=0.0, risks=risks)
    np.testing.assert_array_equal(kept.risks, risks)
    assert _label(kept) == (SURE.first_factor, 4)


def test_once_opened_the_mildest_candidate_is_taken():
    """``opened`` > 0 overrides the least risk with the first candidate (the smallest factor at
    the least F) once the noise is usable; before that the first pick stands."""
    m = np.random.default_rng(0).normal(size=(32, 32, 1))
    guide = jnp.zeros((32, 32, 1), jnp.float32)

    def pick(usable, opened):
        return _label(_step(guide, m, m, b1=0.2 if usable else 0.0, opened=opened)[1])

    # All noise, and a constant guide (every factor filters alike): the deepest F.
    assert pick(True, 0.0)[1] == LEVELS
    assert pick(True, 1.0) == (SURE.factors[0], 2)
    assert pick(False, 1.0) == (SURE.first_factor, 4)


def _run_sure(steps, target, noise, then=None, seed=0):
    """Each step's ``(opened, F, sigma_d, 3 x the mean guide step)`` of ``bilateral_adam(
    sigma_d="sure")`` on ``(x - target) + noise N(0, 1)``; from step 10 on ``then``'s
    ``(target, noise)`` if given."""
    rng = np.random.default_rng(seed)
    opt = ob.bilateral_adam(0.02, sigma_d="sure")
    update = jax.jit(opt.update)
    x = jnp.full((32, 32, 1), 0.5, jnp.float32)
    state, previous, out = opt.init(x), None, []
    for t in range(steps):
        tg, nz = then if then is not None and t >= 10 else (target, noise)
        g = (x - tg) + nz * jnp.asarray(rng.normal(size=x.shape), jnp.float32)
        u, state = update(g, state, x)
        step = 0.0 if previous is None else 3 * float(jnp.mean(jnp.abs(x - previous)))
        s = filtered_state(state).sigma_state
        out.append((float(s.opened), int(s.levels), float(s.sigma_d), step))
        previous, x = x, x + u
    return out


def test_the_gate_opens_on_an_iid_target_and_the_choice_stays_mild(iid_and_smooth_targets):
    """A noise-free gradient toward an i.i.d. target: the filter's residual persists on every
    texel, the blend's gate opens at the second step, and from then on the leaf takes
    ``FACTORS[0]`` times the step scale at F = 2, also after the target turns smooth and
    noisy (where the gate would close). A smooth, noisy target never opens it."""
    iid, smooth = iid_and_smooth_targets
    steps = _run_sure(30, iid, 0.0, then=(smooth, 0.3))
    assert steps[0][0] == 0 and all(o == 1 for o, *_ in steps[1:])
    for _, levels, sigma_d, scale in steps[2:]:
        assert levels == 2
        assert sigma_d == pytest.approx(SURE.factors[0] * scale, rel=1e-4)
    never = _run_sure(30, smooth, 0.3)
    assert all(o == 0 for o, *_ in never)
    # ... and there the choice is free: a larger factor or a deeper F at some step.
    assert any(lev > 2 or sig > 1.5 * SURE.factors[0] * sc for _, lev, sig, sc in never[2:])


@pytest.mark.parametrize("c", [1e-6, 1e-3, 1.0, 1e3, 1e6])
def test_every_step_casts_one_vote_whatever_the_gradients_scale(c):
    # Each step's risks are divided by their largest magnitude: the average does not let
    # the large early gradients outweigh the small late ones.
    m = np.linspace(0.5, 1.5, 64).reshape(8, 8, 1)
    guide = jnp.asarray(np.random.default_rng(0).random((8, 8, 1)), jnp.float32)
    _, unit = _step(guide, m, 0 * m)
    _, scaled = _step(guide, c * m, 0 * m)
    np.testing.assert_allclose(scaled.risks, unit.risks, rtol=1e-5)
    assert float(jnp.max(jnp.abs(unit.risks))) == pytest.approx(1 - SURE.risk_decay)


def test_an_overflowing_risk_votes_against_its_candidate():
    """A noise sample near float32's limit: the risks of the candidates that filter little
    overflow to +inf (the noise's variance), of those that filter much to -inf (the noise
    they remove), which a least risk would choose. Each such vote is 2, worse than any
    finite one (at most 1): the average stays finite and takes neither."""
    rng = np.random.default_rng(0)
    guide = jnp.asarray(5 * rng.random((32, 32, 1)), jnp.float32)  # edges stop sigma_d = 0.1
    zeta = 7e17 * rng.normal(size=(32, 32, 1))
    _, state = _step(guide, np.ones((32, 32, 1)), zeta)
    risks, overflowed = np.asarray(state.risks), 2 * (1 - SURE.risk_decay)
    assert np.all(np.isfinite(risks))
    worst = np.isclose(risks, overflowed)
    assert worst[0] and worst[-1]  # the mildest (+inf) and the heaviest (-inf)
    assert not worst.all() and not worst[_labels().index(_label(state))]


@pytest.mark.parametrize("levels, choices", [(1, (1,)), (2, (2,)), (5, (2, 3, 4, 5))])
def test_the_candidates_are_every_factor_at_every_level_from_two(levels, choices):
    """The risks hold one entry per factor and F in ``choices``; the first step takes the
    middle F, and a usable one the label of the least average risk (factor-major order)."""
    params, m, zeta = _evidence()
    _, first = _step(params, m, zeta, levels=levels, count=1)
    assert first.risks.shape == (len(SURE.factors) * len(choices),)
    assert int(first.levels) == choices[len(choices) // 2]
    _, state = _step(params, m, zeta, levels=levels)
    labels = [(k, n) for k in SURE.factors for n in choices]
    assert _label(state) == labels[int(jnp.argmin(state.risks))]


def test_each_candidate_is_the_filter_at_its_labels():
    # sure's candidates read one cascade per factor after each F: whichever the average
    # favours, the step is the whole filter at that candidate's sigma_d and F (the blend
    # shut: noise alone, no residual).
    rng = np.random.default_rng(2)
    params = jnp.asarray(rng.random((24, 20, 2)), jnp.float32)
    m = rng.normal(size=params.shape)
    labels = _labels(4)
    for i in range(len(labels)):
        risks = jnp.zeros(len(labels)).at[i].set(-10.0)
        u, state = _step(params, m, m, levels=4, risks=risks)
        assert _label(state) == labels[i]
        fixed = _fixed_update(params, m, state.sigma_d, int(state.levels))
        np.testing.assert_allclose(u, fixed, rtol=1e-5, atol=1e-6)


def _target(block=4):
    """A piecewise-constant RGB image of 4 x 4 blocks (test_auto's)."""
    rng = np.random.default_rng(0)
    return jnp.asarray(np.kron(rng.random((4, 4, 3)), np.ones((block, block, 1))), jnp.float32)


def _grad(params, key, target):
    return params - target + jax.random.normal(key, params.shape, params.dtype)


def test_sure_beats_adam_and_records_its_choice_and_checkpoints(tmp_path):
    # Piecewise-constant target under unit noise (test_auto's problem): a filter must win.
    target = _target(block=8)
    params = {"tex": jnp.full(target.shape, 0.5), "light": jnp.zeros(())}
    opt = ob.bilateral_adam(0.03, sigma_d={"tex": "sure", "light": 0.1})
    adam = optax.adam(0.03)

    def run(opt, steps):
        state, p = opt.init(params), params
        update = jax.jit(opt.update)
        for i in range(steps):
            g = {"tex": _grad(p["tex"], jax.random.PRNGKey(i), target), "light": p["light"] - 1}
            u, state = update(g, state, p)
            p = optax.apply_updates(p, u)
        return p, state

    p, state = run(opt, 60)
    p_adam, _ = run(adam, 60)
    err = float(jnp.mean(jnp.abs(p["tex"] - target)))
    assert err < 0.9 * float(jnp.mean(jnp.abs(p_adam["tex"] - target))), err
    post = filtered_state(state)
    assert post.sigma_state["light"] is None  # not filtered: Adam's rule
    tex = post.sigma_state["tex"]
    assert isinstance(tex, ob.SureState) and tex.residual.shape == target.shape
    assert float(tex.sigma_d) > 0  # the noise dominates: it filtered
    labels = _labels(ob.SURE_LEVELS)
    assert int(tex.levels) in {n for _, n in labels}
    # The chosen F is the label of the least averaged risk.
    assert tex.risks.shape == (len(labels),)
    assert int(tex.levels) == labels[int(jnp.argmin(tex.risks))][1]
    path = tmp_path / "state.npz"
    ob.save_state(path, state)
    restored = ob.load_state(path, opt.init(params))
    for a, b in zip(jax.tree.leaves(restored), jax.tree.leaves(state)):
        np.testing.assert_array_equal(a, b)


def test_an_unobserved_texel_keeps_its_last_gradient_for_the_noise_sample():
    # The noise sample differences a texel's gradient against its last observed one.
    x = jnp.full((8, 8, 2), 0.5, jnp.float32)
    opt = ob.bilateral_adam(0.05, sigma_d="sure", levels=1, mask_unobserved=True)
    rng = np.random.default_rng(0)
    g1, g2 = (jnp.asarray(rng.normal(size=x.shape), jnp.float32) for _ in range(2))
    g2 = g2.at[2, 3].set(0.0)  # unobserved this step
    _, state = opt.update(g1, opt.init(x), x)
    _, state = opt.update(g2, state, x + 0.01)
    kept = np.asarray(filtered_state(state).sigma_state.previous_gradient)
    np.testing.assert_array_equal(kept[2, 3], g1[2, 3])
    np.testing.assert_array_equal(
        np.delete(kept.reshape(64, 2), 19, 0), np.delete(np.asarray(g2).reshape(64, 2), 19, 0)
    )


@pytest.mark.parametrize("levels, expected", [(None, ob.SURE_LEVELS), (2, 2), (4, 4)])
def test_a_sure_leaf_defaults_to_sure_levels_and_the_others_keep_default_levels(levels, expected):
    params = {"tex": jnp.full((16, 16, 3), 0.5), "other": jnp.full((16, 16, 3), 0.5)}
    opt = ob.bilateral_adam(0.05, sigma_d={"tex": "sure", "other": 0.1}, levels=levels)
    state = opt.init(params)
    assert filtered_state(state).sigma_state["tex"].risks.shape == (len(_labels(expected)),)
    # The leaf with a number filters exactly as with levels=3 (or the levels given).
    alone = ob.bilateral_adam(0.05, sigma_d=0.1, levels=levels or ob.DEFAULT_LEVELS)
    rng = np.random.default_rng(0)
    g = {k: jnp.asarray(rng.normal(size=(16, 16, 3)), jnp.float32) for k in params}
    u, _ = opt.update(g, state, params)
    u_alone, _ = alone.update(g["other"], alone.init(params["other"]), params["other"])
    np.testing.assert_array_equal(u["other"], u_alone)


@pytest.mark.parametrize(
    "make, reason",
    [
        (lambda: ob.prefilter(sigma_d="sure"), "prefilter has no moments"),
        (lambda: ob.bilateral_adam(0.1, sigma_d="sure", prefilter=True), "prefilter"),
        (lambda: ob.postfilter(b1=0.0, b2=0.0, sigma_d={"a": "sure"}), "keeps no moments"),
        (lambda: ob.bilateral_adam(0.1, sigma_d="sure", guide="self"), "guide='self'"),
        (lambda: ob.postfilter(sigma_d="sure", filter_v=False), "filter_v=True"),
    ],
    ids=["prefilter", "bilateral_adam-prefilter", "memoryless", "self", "filter_v"],
)
def test_where_it_cannot_work_it_is_refused_at_construction(make, reason):
    with pytest.raises(ValueError, match=rf"sigma_d='sure'.*{reason}"):
        make()
