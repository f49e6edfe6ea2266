"""sigma_d="sure": the risk estimate's choice, the bounded step, state, transforms, bad input.

Scale invariance, the extremes, the bounded step and jit / vmap / inject_hyperparams are
checked beside "auto"'s in test_auto.py.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

import optax_bilateral as ob
from states import filtered_state

SURE = ob.Sure()

SHAPE = (16, 16, 3)
AXES = (0, 1)


LEVELS = 5  # the candidates' F: 2, 3, 4, 5


def _choice(mean, noise, guide, probe=None, seed=0):
    """``(sigma_d / scale, F)`` that sure.choose picks for ``m_hat = mean + noise N(0, 1)``
    with a probe of the same noise (default: an independent draw), the candidates built as
    the step builds them: one cascade per factor, read after every F."""
    rng = np.random.default_rng(seed)
    n = jnp.asarray(noise * rng.normal(size=mean.shape), jnp.float32)
    m = jnp.asarray(mean, jnp.float32) + n
    zeta = jnp.asarray(noise * rng.normal(size=mean.shape), jnp.float32) if probe is None else n
    guide, scale = jnp.asarray(guide, jnp.float32), jnp.asarray(0.1, jnp.float32)
    filter_at = functools.partial(ob.atrous_bilateral, guide=guide, spatial_axes=AXES)
    cands = SURE.candidates(
        (m, zeta),
        LEVELS,
        scale,
        lambda x, s, n, k: filter_at(x, sigma_d=s, levels=n, first_level=k),
    )
    m_f, pick, _ = SURE.choose(m, zeta, cands, 1.0, jnp.asarray(True), None, SURE.first(LEVELS))
    np.testing.assert_array_equal(m_f, cands[int(pick)][0])
    sigma_d, levels = SURE.labels(LEVELS, scale)
    return round(float(sigma_d[pick] / scale), 3), int(levels[pick])


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


def test_the_first_step_takes_the_middle_factor_at_the_middle_level():
    m = jnp.ones((8, 8, 1))
    cands = [(m * k, m * 0) for k in range(len(SURE.factors) * 4)]
    first = SURE.first(LEVELS)
    m_f, pick, risks = SURE.choose(m, m * 0, cands, 1.0, False, None, first)
    sigma_d, levels = SURE.labels(LEVELS, jnp.asarray(0.5))
    assert int(pick) == first and float(sigma_d[pick]) == SURE.first_factor * 0.5
    assert int(levels[pick]) == 4
    np.testing.assert_array_equal(m_f, cands[first][0])
    np.testing.assert_array_equal(risks, np.zeros(len(cands)))  # no evidence yet


def _bias_candidates(m):
    """Candidates ``(k m, 0)``: with a zero noise sample the risk of k is ``(1 - k)^2 |m|^2``,
    least for k = 1."""
    return [(m * k, m * 0) for k in range(len(SURE.factors) * 4)]


def test_the_choice_follows_the_moving_average_of_the_risks():
    # An average that favours candidate 3 outvotes one step's evidence for candidate 1; the
    # same evidence step after step moves the choice there.
    m = jnp.ones((8, 8, 1))
    cands = _bias_candidates(m)
    risks = jnp.zeros(len(cands)).at[3].set(-1.0)
    picks = []
    for _ in range(40):
        _, pick, risks = SURE.choose(m, m * 0, cands, 1.0, True, None, 0, risks)
        picks.append(int(pick))
    assert picks[0] == 3 and picks[-1] == 1, picks
    switch = picks.index(1)
    assert all(p == 3 for p in picks[:switch]) and all(p == 1 for p in picks[switch:])
    # Steps without a usable noise sample leave the average as it is.
    _, pick, kept = SURE.choose(m, m * 0, cands, 1.0, False, None, 0, risks)
    np.testing.assert_array_equal(kept, risks)
    assert int(pick) == 0


def test_once_opened_the_mildest_candidate_is_taken():
    """``opened`` > 0 overrides the least risk with the first candidate (the smallest factor at
    the least F) once the noise is usable; before that the first pick stands."""
    m = jnp.asarray(np.random.default_rng(0).normal(size=(32, 32, 1)), jnp.float32)
    guide = jnp.zeros((32, 32), jnp.float32)
    filter_at = functools.partial(ob.atrous_bilateral, guide=guide, spatial_axes=AXES)
    cands = SURE.candidates(
        (m, m), LEVELS, 0.1, lambda x, s, n, k: filter_at(x, sigma_d=s, levels=n, first_level=k)
    )
    first = SURE.first(LEVELS)

    def pick(usable, opened):
        u = jnp.asarray(usable)
        m_f, p, _ = SURE.choose(m, m, cands, 1.0, u, None, first, None, jnp.asarray(opened))
        np.testing.assert_array_equal(m_f, cands[int(p)][0])
        return int(p)

    # All noise, and a constant guide (every factor filters alike): the deepest F.
    assert int(SURE.labels(LEVELS, 0.1)[1][pick(True, 0.0)]) == LEVELS
    assert pick(True, 1.0) == 0
    assert pick(False, 1.0) == first


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
    m = jnp.linspace(0.5, 1.5, 64, dtype=jnp.float32).reshape(8, 8, 1)
    _, _, unit = SURE.choose(m, m * 0, _bias_candidates(m), 1.0, True, None, 0)
    mc = m * jnp.float32(c)
    _, _, scaled = SURE.choose(mc, mc * 0, _bias_candidates(mc), 1.0, True, None, 0)
    np.testing.assert_allclose(scaled, unit, rtol=1e-5)
    assert float(jnp.max(jnp.abs(unit))) == pytest.approx(1 - SURE.risk_decay)


def test_an_overflowing_risk_votes_against_its_candidate():
    m = jnp.ones((8, 8, 1))
    cands = _bias_candidates(m)
    cands[1] = (m * jnp.inf, m * 0)  # the otherwise least risk, now inf
    cands[2] = (m * jnp.nan, m * 0)
    _, pick, risks = SURE.choose(m, m * 0, cands, 1.0, True, None, 0)
    assert int(pick) == 0 and np.all(np.isfinite(risks))
    assert float(risks[1]) == float(risks[2]) == pytest.approx(2 * (1 - SURE.risk_decay))


@pytest.mark.parametrize("levels, choices", [(1, (1,)), (2, (2,)), (5, (2, 3, 4, 5))])
def test_the_candidates_are_every_factor_at_every_level_from_two(levels, choices):
    assert SURE.level_choices(levels) == choices
    sigma_d, f = SURE.labels(levels, jnp.asarray(2.0))
    expected = [(k * 2.0, n) for k in SURE.factors for n in choices]
    assert [(float(s), int(n)) for s, n in zip(sigma_d, f)] == expected
    assert int(f[SURE.first(levels)]) == choices[len(choices) // 2]


def test_each_candidate_is_the_filter_at_its_labels():
    # sure.candidates reads one cascade per factor after each F: candidate i is the whole
    # filter at labels(levels)[i].
    rng = np.random.default_rng(2)
    x = jnp.asarray(rng.normal(size=(24, 20, 2)), jnp.float32)
    guide, scale = jnp.asarray(rng.random((24, 20)), jnp.float32), jnp.asarray(0.2, jnp.float32)
    filt = functools.partial(ob.atrous_bilateral, guide=guide, spatial_axes=AXES)
    cands = SURE.candidates(
        x, 4, scale, lambda y, s, n, k: filt(y, sigma_d=s, levels=n, first_level=k)
    )
    sigma_d, levels = SURE.labels(4, scale)
    assert len(cands) == len(sigma_d)
    for c, s, n in zip(cands, sigma_d, levels):
        np.testing.assert_allclose(c, filt(x, sigma_d=s, levels=int(n)), atol=1e-6)


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
    assert int(tex.levels) in SURE.level_choices(ob.SURE_LEVELS)
    # The chosen F is the label of the least averaged risk.
    assert tex.risks.shape == (SURE.n_candidates(ob.SURE_LEVELS),)
    best = int(jnp.argmin(tex.risks))
    assert int(tex.levels) == int(SURE.labels(ob.SURE_LEVELS, jnp.asarray(1.0))[1][best])
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
    assert filtered_state(state).sigma_state["tex"].risks.shape == (SURE.n_candidates(expected),)
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
