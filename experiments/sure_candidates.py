"""Issue #17's SURE study: candidate optimizers for ``python -m experiments.tuning --candidates``.

Not part of the library. Stein's unbiased risk estimate picks ``sigma_d`` and F (or F alone,
the ``surF`` rows) among a few candidates at every step, per leaf (or per texel);
docs/auto_sigma.md has the measured table and why it was not adopted. Reproduce a row, e.g.::

    python -m experiments.tuning --out results/sure \
        --candidates sbF_w05=experiments.sure_candidates:sbF_w05

For a fixed guide the filter B (a-trous cascade, sigma_k, F levels) is linear. With a noise
probe zeta of m_hat's noise (default ``noise="diff"``: sqrt(rho / 2) (g_t - g_{t-1}), which keeps
the noise's spatial correlation; ``"rad"``: a Rademacher vector times sqrt(v_hat - m_hat^2)):

    risk_B = sum_i [ bias2_i + w * var_i ]
    bias2_i = (m_hat - B m_hat)_i^2 - ((I - B) zeta)_i^2     (unbiased for ((I-B) mu)_i^2)
    var_i   = ((B zeta)_i)^2                                  (unbiased for Var (B m_hat)_i)

w = 1 is SURE; w < 1 discounts the noise the trajectory averages out. The identity (Adam) is
a candidate with bias2 = 0, var = s2. The chosen B filters both m and v (the same row per
texel: non-negative, row-stochastic, so the bounded step holds).
"""

import functools
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import optax

import optax_bilateral as ob

H = (1 / 16, 4 / 16, 6 / 16, 4 / 16, 1 / 16)


class S(NamedTuple):
    count: jax.Array
    mu: Any
    nu: Any
    prev: Any
    e: Any
    pg: Any
    rk: Any
    pg2: Any


def ema_var(b, t):
    return (1 - b) * (1 - b ** (2 * t)) / ((1 + b) * (1 - b**t) ** 2)


def _shift(x, a, off):
    """y[p] = x[p + off] along axis a (zero outside), and the validity (as x's dtype)."""
    n = x.shape[a]
    if abs(off) >= n:
        return jnp.zeros_like(x), False
    pad = [(0, 0)] * x.ndim
    pad[a] = (max(-off, 0), max(off, 0))
    xp = jnp.pad(x, pad)
    start = max(off, 0)
    return jax.lax.slice_in_dim(xp, start, start + n, axis=a), True


def _valid(shape, a, off, dtype):
    n = shape[a]
    idx = jnp.arange(n) + off
    ok = ((idx >= 0) & (idx < n)).astype(dtype)
    s = [1] * len(shape)
    s[a] = n
    return ok.reshape(s)


def cascade(fields, guide, sigma, levels, axes):
    """Separable a-trous cross-bilateral cascade; returns [level 1 output, ..., level F output],
    each a tuple of fields. guide has the fields' shape; distance = L2 over non-spatial axes."""
    chan = tuple(i for i in range(guide.ndim) if i not in axes)
    outs = []
    x = tuple(fields)
    for lev in range(levels):
        s = 2**lev
        for a in axes:
            num = [jnp.zeros_like(f) for f in x]
            den = 0.0
            for d, h in zip(range(-2, 3), H):
                off = d * s
                if abs(off) >= guide.shape[a]:
                    continue
                gq, _ = _shift(guide, a, off)
                diff = guide - gq
                dist = (
                    jnp.sqrt(jnp.sum(diff * diff, axis=chan, keepdims=True))
                    if chan
                    else jnp.abs(diff)
                )
                w = h * jnp.exp(-dist / sigma) * _valid(guide.shape, a, off, guide.dtype)
                den = den + w
                for j, f in enumerate(x):
                    fq, _ = _shift(f, a, off)
                    num[j] = num[j] + w * fq
            x = tuple(nm / den for nm in num)
        outs.append(x)
    return outs


def blur(x, axes, levels=1):
    for lev in range(levels):
        s = 2**lev
        for a in axes:
            n = x.shape[a]
            num = jnp.zeros_like(x)
            den = 0.0
            for d, h in zip(range(-2, 3), H):
                off = d * s
                if abs(off) >= n:
                    continue
                xq, _ = _shift(x, a, off)
                w = h * _valid(x.shape, a, off, x.dtype)
                num, den = num + w * xq, den + w
            x = num / den
    return x


def texel_norm(x, axes):
    chan = tuple(i for i in range(x.ndim) if i not in axes)
    return jnp.sqrt(jnp.sum(x * x, axis=chan)) if chan else jnp.abs(x)


def base_sigma(gd, prev, t, axes):
    """The library's step scale (``"sure"``'s, and a prefilter's ``"auto"``): 3 * mean guide
    step; 1.5 * mean distance from the local average before the guide moves."""
    step = jnp.mean(texel_norm(gd - prev, axes))
    con = jnp.mean(texel_norm(gd - blur(gd, axes), axes))
    return jnp.where((t > 1) & (step > 0), 3.0 * step, 1.5 * con)


def sure_adam(
    learning_rate,
    b1=0.2,
    b2=None,
    eps=1e-8,
    factors=(0.3, 1.0, 3.0, 10.0),
    level_set=(3,),
    w=1.0,
    per_texel=False,
    avg_levels=2,
    bias="step",
    beta=0.9,
    identity=True,
    spatial_axes=None,
    log_guide=False,
    noise="diff",
    blend=False,
    risk_decay=0.0,
    weighting="none",
    blend_constants=(0.9, (0.2, 0.35)),  # the blend's (residual decay, gate); auto's former
):
    if weighting not in ("none", "step"):
        raise ValueError(f"weighting must be 'none' or 'step', got {weighting!r}")
    b2 = 1 - (1 - b1) ** 2 if b2 is None else b2
    maxl = max(level_set)
    ncand = len(factors) * len(level_set)

    def axes_of(x):
        return tuple(spatial_axes) if spatial_axes is not None else ob.default_spatial_axes(x)

    def init(p):
        z = jax.tree.map(jnp.zeros_like, p)
        e = jax.tree.map(lambda x: jnp.zeros((ncand + 1,) + x.shape, x.dtype), p)
        rk = jax.tree.map(lambda x: jnp.zeros((ncand + 1,), x.dtype), p)
        return S(jnp.zeros([], jnp.int32), z, z, z, e, z, rk, z)

    def update(g, st, p):
        t = st.count + 1
        tf = t.astype(jnp.float32)
        c1, c2 = 1 - b1**tf, 1 - b2**tf
        rm = ema_var(b1, tf)
        have = (t > 1) & (rm < 1 - 1e-6)
        k = jnp.where(have, rm / jnp.maximum(1 - rm, 1e-6), 0.0)
        key = jax.random.fold_in(jax.random.PRNGKey(17), t)

        def leaf(i, g, m, v, prev, e, pg, rk, pg2, x):
            axes = axes_of(x)
            g0 = g
            m = b1 * m + (1 - b1) * g
            v = b2 * v + (1 - b2) * g * g
            mh, vh = m / c1, v / c2
            if not axes:
                return mh / (jnp.sqrt(vh) + eps), m, v, prev, e, g0, rk, pg
            gd = jnp.log(jnp.abs(x) + 1e-8) if log_guide else x
            s0 = base_sigma(gd, prev, t, axes)
            s2 = jnp.maximum(vh - mh * mh, 0) * k
            if noise in ("diff", "diff2"):
                # a sample with the noise's spatial covariance: successive gradients are
                # independent draws (slowly moving mean); scaled to the noise of m_hat
                zeta = jnp.where(t > 1, jnp.sqrt(rm / 2) * (g - pg), 0.0)
                if noise == "diff2":
                    # second difference: removes the mean's linear drift
                    zeta = jnp.where(t > 2, jnp.sqrt(rm / 6) * (g - 2 * pg + pg2), zeta)
                s2 = zeta * zeta
            else:
                z = jax.random.rademacher(jax.random.fold_in(key, i), mh.shape, mh.dtype)
                zeta = z * jnp.sqrt(s2)
            bm, bv, bz = [], [], []
            for f in factors:
                outs = cascade((mh, vh, zeta), gd, jnp.maximum(f * s0, 1e-30), maxl, axes)
                for L in level_set:
                    bm.append(outs[L - 1][0])
                    bv.append(outs[L - 1][1])
                    bz.append(outs[L - 1][2])
            bm, bv, bz = jnp.stack(bm), jnp.stack(bv), jnp.stack(bz)
            r = mh[None] - bm
            nres = (zeta[None] - bz) ** 2
            e_blend = e[-1]
            e = e[:-1]
            if bias == "ema":
                e = beta * e + (1 - beta) * r
                eh = e / (1 - beta**tf)
                corr = ema_var(beta, tf) * (1 + b1 * beta) / (1 - b1 * beta)
                bias2 = eh * eh - nres * corr
            else:
                bias2 = r * r - nres
            risk = bias2 + w * bz * bz
            cand_m, cand_v = bm, bv
            if identity:
                risk = jnp.concatenate([risk, (w * s2)[None]])
                cand_m = jnp.concatenate([bm, mh[None]])
                cand_v = jnp.concatenate([bv, vh[None]])
            if weighting == "step":
                # Adam's step error is (m_f - mu) / sqrt(v): weigh each entry's risk by 1 / v
                # (its local average, so that one noisy v does not decide)
                vb = blur(vh, axes)
                risk = risk * jnp.where(vb > 0, 1 / jnp.where(vb > 0, vb, 1), 0)[None]
            # the middle candidate before the noise can be estimated (t = 1: s2 = 0)
            mid = (len(factors) // 2) * len(level_set) + len(level_set) // 2
            if per_texel:
                rs = jnp.stack([blur(rk, axes, avg_levels) for rk in risk])
                chan = tuple(j + 1 for j in range(mh.ndim) if j not in axes)
                if chan:
                    rs = jnp.sum(rs, axis=chan, keepdims=True)
                pick = jnp.argmin(rs, axis=0)
                pick = jnp.where(have, pick, mid)
                pick = jnp.broadcast_to(pick, mh.shape)
                mf = jnp.take_along_axis(cand_m, pick[None], 0)[0]
                vf = jnp.take_along_axis(cand_v, pick[None], 0)[0]
            else:
                tot = jnp.sum(risk.reshape(risk.shape[0], -1), axis=1)
                if risk_decay:
                    # time-smoothed leaf risks (from t = 2 on, when the noise is measured)
                    tot = jnp.pad(tot, (0, rk.shape[0] - tot.shape[0]))
                    n_t = jnp.maximum(tf - 1, 1)
                    rk = jnp.where(have, risk_decay * rk + (1 - risk_decay) * tot, rk)
                    tot = (rk / (1 - risk_decay**n_t))[: risk.shape[0]]
                pick = jnp.where(have, jnp.argmin(tot), mid)
                mf, vf = cand_m[pick], cand_v[pick]
            if blend:
                decay, gate = blend_constants
                mf, vf, e_blend = _blend(
                    mh, vh, mf, vf, e_blend, b1, c1, tf, have, k, axes, decay=decay, gate=gate
                )
            e = jnp.concatenate([e, e_blend[None]])
            return mf / (jnp.sqrt(vf) + eps), m, v, gd, e, g0, rk, pg

        flat, tdef = jax.tree.flatten(g)
        parts = (tdef.flatten_up_to(s) for s in (st.mu, st.nu, st.prev, st.e, st.pg, st.rk, st.pg2))
        outs = [leaf(i, *a) for i, a in enumerate(zip(flat, *parts, tdef.flatten_up_to(p)))]
        un = lambda j: tdef.unflatten([o[j] for o in outs])
        return jax.tree.map(lambda d: -learning_rate * d, un(0)), S(
            t, un(1), un(2), un(3), un(4), un(5), un(6), un(7)
        )

    return optax.GradientTransformation(init, update)


def _blend(mh, vh, bm, bv, e, b1, c1, tf, have, k, axes, decay=0.9, gain=0.25, gate=(0.2, 0.35)):
    """optax_bilateral/_src/auto.py's blend (persistent residual vs its noise floor, gated)."""
    e = decay * e + (1 - decay) * (mh - bm)
    eh = e / (1 - decay**tf)
    noise = jnp.maximum(vh - mh * mh, 0) * k
    noise = noise * ema_var(decay, tf) * (1 + b1 * decay) / (1 - b1 * decay)
    floor, signal = blur(noise, axes), blur(eh * eh, axes)
    lam = 1 - floor / (gain * jnp.where(signal > 0, signal, 1))
    lam = jnp.where(have & (signal > 0), jnp.clip(lam, 0, 1), 0) ** 2
    lam = lam * jnp.clip((jnp.mean(lam) - gate[0]) / (gate[1] - gate[0]), 0, 1)
    return lam * mh + (1 - lam) * bm, lam * vh + (1 - lam) * bv, e


def _factory(learning_rate, spatial_axes=None, **kw):
    return sure_adam(learning_rate, spatial_axes=spatial_axes, **kw)


def _f(**kw):
    return functools.partial(_factory, **kw)


# docs/auto_sigma.md's rows: SURE over sigma_d and F (2-5) with auto's blend; w = 1 without
# the identity; w = 0.5 with it; leaf risks averaged over steps, w = 0.2.
F_SET = (2, 3, 4, 5)
sbF_w1 = _f(w=1.0, identity=False, blend=True, level_set=F_SET)
sbF_w05 = _f(w=0.5, identity=True, blend=True, level_set=F_SET)
sbFr_w02 = _f(w=0.2, identity=True, blend=True, level_set=F_SET, risk_decay=0.8)
# sbF_w1 with the blend's current constants (auto.RESIDUAL_DECAY, auto.GATE).
sbF_w1_b97 = _f(
    w=1.0, identity=False, blend=True, level_set=F_SET, blend_constants=(0.97, (0.5, 0.65))
)
# The per-entry probe (negative risk estimates) and the per-texel choice.
leaf_w1_rad = _f(w=1.0, noise="rad")
texF_w1_b = _f(w=1.0, identity=False, blend=True, per_texel=True, level_set=F_SET)
# SURE over F alone, sigma_d = auto's s0 (factors=(1.0,)), with auto's blend: F 1-5 or 2-4.
surF_w1 = _f(factors=(1.0,), w=1.0, identity=False, blend=True, level_set=(1, 2, 3, 4, 5))
surF_w05 = _f(factors=(1.0,), w=0.5, identity=True, blend=True, level_set=(1, 2, 3, 4, 5))
surF234_w1_r = _f(
    factors=(1.0,), w=1.0, identity=False, blend=True, level_set=(2, 3, 4), risk_decay=0.9
)
surF234_w05 = _f(factors=(1.0,), w=0.5, identity=True, blend=True, level_set=(2, 3, 4))
# SURE over sigma_d alone (s0 x {0.3, 1, 3, 10}, or {1, 3, 10}: sbS3) at F = 3, auto's levels,
# with auto's blend; sbS3F4 at F = 4, sbS3F34 over F in {3, 4} too, sbS2 over s0 x {1, 3}.
sbS_w1 = _f(w=1.0, identity=False, blend=True, level_set=(3,))
sbS_w05 = _f(w=0.5, identity=True, blend=True, level_set=(3,))
S3 = (1.0, 3.0, 10.0)
sbS3_w05 = _f(factors=S3, w=0.5, identity=True, blend=True, level_set=(3,))
sbS3_w04 = _f(factors=S3, w=0.4, identity=True, blend=True, level_set=(3,))
sbS3_w03 = _f(factors=S3, w=0.3, identity=True, blend=True, level_set=(3,))
sbS3F4_w05 = _f(factors=S3, w=0.5, identity=True, blend=True, level_set=(4,))
sbS3F34_w04 = _f(factors=S3, w=0.4, identity=True, blend=True, level_set=(3, 4))
sbS2_w05 = _f(factors=(1.0, 3.0), w=0.5, identity=True, blend=True, level_set=(3,))
sbS3F34_w03 = _f(factors=S3, w=0.3, identity=True, blend=True, level_set=(3, 4))
sbS3F345_w04 = _f(factors=S3, w=0.4, identity=True, blend=True, level_set=(3, 4, 5))
sbS3F345_w03 = _f(factors=S3, w=0.3, identity=True, blend=True, level_set=(3, 4, 5))
# The same with each entry's risk weighed by 1 / (local average of v_hat): Adam's step error.
_vw = functools.partial(_f, factors=S3, identity=True, blend=True, weighting="step")
sbS3_w04_vw = _vw(w=0.4, level_set=(3,))
sbS3_w1_vw = _vw(w=1.0, level_set=(3,))
sbS3F345_w04_vw = _vw(w=0.4, level_set=(3, 4, 5))
sbS3F345_w1_vw = _vw(w=1.0, level_set=(3, 4, 5))
# Variants that did worse (docs/auto_sigma.md): a larger w, no identity, averaged risks.
sbS_w07 = _f(w=0.7, identity=True, blend=True, level_set=(3,))
sbS_w05_noid = _f(w=0.5, identity=False, blend=True, level_set=(3,))
sbSr_w05 = _f(w=0.5, identity=True, blend=True, level_set=(3,), risk_decay=0.8)
sbS3_w05_noid = _f(factors=S3, w=0.5, identity=False, blend=True, level_set=(3,))
