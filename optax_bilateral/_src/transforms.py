"""Optax transforms: ``prefilter``, ``scale_by_adam`` and ``postfilter``.

Notation (supplement §1): gradients ``g_t``, cross-bilateral operators ``A_t``
(prefilter) and ``B_t`` (postfilter), moments ``m_t, v_t``.

    prefilter    g~_t = A_t g_t                                   (eq. 1)
    moments      m_t = b1 m_{t-1} + (1-b1) g~_t,  v_t = b2 v_{t-1} + (1-b2) g~_t^2   (eqs. 2, 4)
    postfilter   m~_t = B_t m_t,  v~_t = B_t v_t                  (eqs. 6, 8)
    step         Delta_t = (m~_t / (1-b1^t)) / (sqrt(v~_t / (1-b2^t)) + eps)      (eq. 10)

Why ``postfilter`` owns the moments instead of filtering the output of
``scale_by_adam``: the postfilter acts on ``m_t`` and ``v_t`` *before* the
division, and the state must keep the *unfiltered* moments (eqs. 6-9: ``B_t`` is
applied afresh each step and never accumulates). A transform placed after
``scale_by_adam`` only sees the ratio ``m/sqrt(v)``, which cannot be filtered
into ``B m / sqrt(B v)``; so the postfilter is Adam with a filter between the
moment update and the step.

Non-finite gradients: a texel whose gradient has a NaN or Inf in any channel is
treated as *unobserved* for that step, as ``mask_unobserved`` treats all-zero
texels: it is left out of every filter sum, its moments are kept, and its
update is 0. So one bad Monte Carlo sample cannot spread over a filter
footprint or into the optimizer state. ``scale_by_adam`` stays identical to
``optax.scale_by_adam`` and does not do this (``bilateral_adam`` therefore uses
``postfilter`` with ``levels=0`` for its unfiltered Adam path).

Numerical extremes (``postfilter``; README.md, "Robustness", has the full table):

* Finite gradients are clipped to ``+-G`` before the moment update, with ``G``
  the largest magnitude whose square still fits the second moment's dtype
  (``G^2 = max/2``: 1.3e19 for float32 and bfloat16 moments, 181 for float16).
  Without it ``v = g^2`` overflows to inf and the texel (and, through ``B v``,
  its footprint) would step 0 from then on. Since the step is scale-invariant, a
  uniformly huge gradient still gives Adam's ``+-1`` step.
* Where the denominator ``sqrt(B v / (1-b2^t) + eps_root) + eps`` is 0 (only
  with ``eps = eps_root = 0``: all-zero gradients, or gradients whose square
  underflows, ``|g| < ~1e-19`` in float32) the step is 0, not 0/0.
  ``sqrt`` is given derivative 0 at 0 so meta-gradients stay finite there.
* For ``b`` within ``2^-14`` of 1 the bias correction ``1 - b^t`` is evaluated as
  ``-expm1(t log1p(-(1-b)))`` with ``1 - b`` in float64, so ``b`` that rounds to
  1 in float32 (``b2 = 1 - (1-b1)^2`` for ``b1 = 0.999999``) still works.
* ``prefilter`` clips its input to a quarter of the float maximum so the
  filter's sums cannot overflow (``|A g| <= max |g|``).
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple, Optional

import jax
import jax.numpy as jnp
import numpy as np
import optax
from jax import lax

from optax_bilateral._src import atrous, leaves as lv, sharded

# Chosen for parameters in a unit range (albedo, roughness, density) and for
# log-domain guides: a guide step of 0.1 weighs e^-1, a step of 0.5 weighs e^-5.
DEFAULT_SIGMA_D = 0.1


def _safe_increment(count):
    max_int = jnp.iinfo(jnp.int32).max
    return jnp.where(count < max_int, count + 1, max_int).astype(jnp.int32)


def _check_unit(x, name):
    """Raises for a concrete decay rate outside [0, 1)."""
    if x is None or not atrous._is_concrete(x):
        return
    v = float(np.asarray(x))
    if not 0.0 <= v < 1.0:
        raise ValueError(f"{name} must be in [0, 1), got {v}")


def _check_nonneg(x, name):
    if x is None or not atrous._is_concrete(x):
        return
    v = float(np.asarray(x))
    if not v >= 0.0:
        raise ValueError(f"{name} must be >= 0, got {v}")


def _one_minus(b):
    """``1 - b``, in float64 when ``b`` is a concrete number (keeps its digits for b near 1)."""
    if atrous._is_concrete(b):
        return float(1.0 - np.float64(np.asarray(b)))
    return 1 - b


# Below this 1 - b, float32 keeps fewer than 10 bits of 1 - b in b itself.
_NEAR_ONE = 2.0 ** -14


def _bias_correction(b, count):
    """Adam's ``1 - b^t``.

    Written as optax writes it, except for ``b`` within ``2^-14`` of 1: there
    ``-expm1(t log1p(-(1 - b)))``, which keeps its digits (``1 - b^t`` has an
    absolute error of float32's eps, 3% of ``1 - b`` at ``b = 0.999999``). For a
    concrete ``b``, ``1 - b`` is taken in float64, so ``b`` that rounds to 1 in
    float32 still works (``1 - b^t`` would be 0 and the step 0/0); a traced ``b``
    has float32's precision, so pass such ``b`` as a number, not a hyperparameter.
    """
    t = count.astype(jnp.float32)
    a = _one_minus(b)
    if atrous._is_concrete(b):
        if a < _NEAR_ONE:
            return -jnp.expm1(t * jnp.log1p(jnp.float32(-a)))
        return 1 - b ** count
    # Traced b: choose at run time; the unused branch gets a safe a (finite derivatives).
    near = a < _NEAR_ONE
    exact = -jnp.expm1(t * jnp.log1p(-jnp.where(near, a, 0)))
    return jnp.where(near, exact, 1 - b ** count)


def _grad_limit(*dtypes) -> float:
    """Largest |g| whose moments fit every dtype: g^2 <= max/2 for v, |g| <= max/2 for m."""
    limits = [math.sqrt(float(jnp.finfo(dtypes[0]).max) / 2)]
    limits += [float(jnp.finfo(d).max) / 2 for d in dtypes[1:]]
    return min(limits)


def _safe_step(m_f, v_f, c1, c2, eps, eps_root):
    """``(m_f/c1) / (sqrt(v_f/c2 + eps_root) + eps)``, with 0 where the denominator is 0.

    Same values as the plain expression wherever that is finite. ``sqrt`` gets
    derivative 0 at 0: ``B v = 0`` means no gradient reached the footprint, which
    stays so under small changes of the hyperparameters (true derivative 0),
    and ``sqrt'(0) = inf`` times a zero cotangent would make meta-gradients NaN.
    """
    v_hat = v_f / c2.astype(v_f.dtype) + eps_root
    pos = v_hat > 0
    den = jnp.where(pos, jnp.sqrt(jnp.where(pos, v_hat, 1)), 0) + eps
    ok = den > 0
    return jnp.where(ok, (m_f / c1.astype(m_f.dtype)) / jnp.where(ok, den, 1), 0)


def _sigma_guard(sigma_d):
    """1 for a valid sigma_d, NaN for a negative or NaN one (traced values cannot raise)."""
    s = jnp.asarray(sigma_d, jnp.float32)
    return jnp.where((s >= 0), 1.0, jnp.nan)


# ----------------------------------------------------------------------------------------
# scale_by_adam


class ScaleByAdamState(NamedTuple):
    """State of :func:`scale_by_adam`: step count and the first two moments."""

    count: jax.Array  # shape=(), int32
    mu: optax.Updates
    nu: optax.Updates


def scale_by_adam(b1=0.9, b2=0.999, eps=1e-8, eps_root=0.0, *, mu_dtype=None
                  ) -> optax.GradientTransformationExtraArgs:
    r"""Adam's scaling, numerically identical to :func:`optax.scale_by_adam`.

    .. math::
        m_t = \beta_1 m_{t-1} + (1-\beta_1) g_t,\quad
        v_t = \beta_2 v_{t-1} + (1-\beta_2) g_t^2,\quad
        \Delta_t = \frac{m_t/(1-\beta_1^t)}{\sqrt{v_t/(1-\beta_2^t) + \epsilon_{root}} + \epsilon}

    (supplement eq. 12). Chained after :func:`prefilter` it is eq. 13. With
    ``b1 = b2 = 0`` it is ``sign(g)`` up to ``eps`` (eq. 15).
    """
    _check_unit(b1, "b1")
    _check_unit(b2, "b2")
    _check_nonneg(eps, "eps")
    mu_dtype = _check_mu_dtype(mu_dtype)

    def init_fn(params):
        mu = jax.tree.map(lambda p: jnp.zeros_like(p, dtype=mu_dtype or jnp.result_type(p)), params)
        nu = jax.tree.map(jnp.zeros_like, params)
        return ScaleByAdamState(count=jnp.zeros([], jnp.int32), mu=mu, nu=nu)

    def update_fn(updates, state, params=None, **extra_args):
        del params, extra_args
        mu = jax.tree.map(lambda g, m: (1 - b1) * g + b1 * m, updates, state.mu)
        nu = jax.tree.map(lambda g, v: (1 - b2) * (g ** 2) + b2 * v, updates, state.nu)
        count_inc = _safe_increment(state.count)
        c1 = 1 - b1 ** count_inc
        c2 = 1 - b2 ** count_inc
        new = jax.tree.map(
            lambda m, v: (m / c1.astype(m.dtype)) / (jnp.sqrt(v / c2.astype(v.dtype) + eps_root) + eps),
            mu, nu)
        mu = jax.tree.map(lambda m, old: m.astype(old.dtype), mu, state.mu)
        nu = jax.tree.map(lambda v, old: v.astype(old.dtype), nu, state.nu)
        return new, ScaleByAdamState(count=count_inc, mu=mu, nu=nu)

    return optax.GradientTransformationExtraArgs(init_fn, update_fn)


# ----------------------------------------------------------------------------------------
# Filtering one leaf


def _observed(g, axes, mask_zero: bool):
    """Texel-level mask of observed entries (finite, and not all-zero if ``mask_zero``)."""
    ok = jnp.isfinite(g)
    m = lv.texel_mask(ok, axes)
    if mask_zero:
        m = m & ~lv.texel_mask(g == 0, axes)
    return m


def _filter(fields, guide, spec: lv.LeafSpec, separable: bool, mask):
    """The leaf's filter; ``mask`` (observed texels, in ``spec.axes`` order) or None.

    Unobserved texels are left out of every sum. The filter is told so by a NaN guide
    there (``atrous._weight`` gives a pair with a non-finite guide weight 0), not by its
    ``mask``: the masked filter carries validity planes through every pass, which made
    the masked branch of ``_with_mask``'s ``lax.cond`` the program's largest, and XLA
    allocates the largest branch's temporaries on every call (full 2-D update,
    512x512x3: 42.9 MiB, the unmasked branch 28.5 MiB; above glibc's 32 MiB mmap
    threshold every call page-faults them, BENCHMARKS.md "Two speeds"). The outputs
    at unobserved texels are then their own inputs, not 0; every caller discards them,
    and their inputs must be finite (0 * inf would leak into the neighbours' sums).
    """
    if mask is not None:
        nan_guide = _nan_guide(guide, mask, spec)
        if nan_guide is not None:
            guide, mask = nan_guide, None
    # sharded.atrous_bilateral is the single-device filter unless the fields' spatial axes
    # are split over explicit mesh axes (then: per-device blocks with halo exchange).
    return sharded.atrous_bilateral(fields, guide, sigma_d=spec.sigma_d, levels=spec.levels,
                                    spatial_axes=spec.axes, separable=separable, mask=mask)


def _nan_guide(guide, mask, spec: lv.LeafSpec):
    """``guide`` with NaN at the texels where ``mask`` is False, or None if its layout is
    neither the spatial grid nor a leaf's (then the filter's own ``mask`` is used)."""
    guide = jnp.asarray(guide)
    if not jnp.issubdtype(guide.dtype, jnp.floating):
        return None
    if guide.shape == mask.shape:
        m = mask
    elif guide.ndim > max(spec.axes) and tuple(guide.shape[a] for a in spec.axes) == mask.shape:
        m = lv.expand_mask(mask, guide.ndim, spec.axes)
    else:
        return None
    return jnp.where(m, guide, jnp.nan)


def _filter_self(fields, spec, separable, mask, log_guide):
    """guide='self': every field guides itself (each gets its own weights)."""
    out = []
    for f in fields:
        gd = lv.log_transform(f) if log_guide else f
        out.append(_filter(f, gd, spec, separable, mask))
    return tuple(out)


def _with_mask(fn_fast, fn_masked, g, lim, operands):
    """Runs ``fn_fast`` when every entry of ``g`` is finite and within ``+-lim``, else
    ``fn_masked`` (which masks and clips); only one branch executes.

    The fast branch is the plain formula, compiled exactly as before the clip existed.
    """
    # (jnp.max(jnp.abs(g)) <= lim, one reduction instead of a compare and two, measured
    # 2-D update -1..-5% but 3-D 64^3 separable +8..17%: not used.)
    return lax.cond(jnp.all(jnp.abs(g) <= lim), lambda ops: fn_fast(ops),
                    lambda ops: fn_masked(ops), operands)


# ----------------------------------------------------------------------------------------
# prefilter


class PrefilterState(NamedTuple):
    """:func:`prefilter` is stateless."""


def prefilter(sigma_d=DEFAULT_SIGMA_D, levels=5, *, separable=True, guide="params",
              log_guide=False, spatial_axes=None, mask_unobserved=False
              ) -> optax.GradientTransformationExtraArgs:
    r"""Spatial prefilter of the gradient, :math:`\tilde g_t = A_t g_t` (supplement eq. 1).

    ``A_t`` is the a-trous cross-bilateral filter (:func:`atrous_bilateral`) guided
    by the current parameters. Followed by :func:`scale_by_adam` it gives eq. 13;
    followed by :func:`postfilter`, eq. 11. Leaves that are not filtered (see
    ``spatial_axes``) pass through unchanged. Texels with a non-finite gradient
    (and, with ``mask_unobserved``, all-zero texels) are left out of the sums and
    passed through unchanged, so that a following :func:`postfilter` still
    treats them as unobserved (keeps their moments, zero update).

    Args:
      sigma_d: data-term scale (>= 0; ``inf`` = low-pass), a number or a pytree
        prefix of the parameters. Traceable.
      levels: F, number of a-trous levels (static), a number or a prefix.
      separable: one 1-D pass per spatial axis (True) or all 5^n taps (False).
      guide: ``"params"`` (cross-bilateral, the paper's method), ``"self"``
        (bilateral: the gradient guides itself), or a callable
        ``params -> guide pytree`` (a prefix of the parameters).
      log_guide: use ``log(|guide| + 1e-8)`` as the guide.
      spatial_axes: ``None`` (default leaf rule, see :func:`default_spatial_axes`),
        a tuple for every leaf, a pytree prefix of tuples (``()`` = do not
        filter), or a callable ``leaf -> axes``.
      mask_unobserved: leave texels whose gradient is 0 in every channel out of
        the sums (see :func:`postfilter`).

    Gradients beyond a quarter of the float maximum are clipped first, so the
    sums cannot overflow (the module docstring lists the numerical policies).
    """
    lv.check_guide(guide)
    _static_checks(sigma_d, levels, spatial_axes)

    def init_fn(params):
        # Shapes, dtypes and the guide are checked now rather than at the first update.
        lv.check_params(params, spatial_axes=spatial_axes, sigma_d=sigma_d, levels=levels,
                        guide=guide, transform="prefilter", all_leaves=False)
        return PrefilterState()

    def update_fn(updates, state, params=None, **extra_args):
        del extra_args
        specs = lv.leaf_specs(updates, spatial_axes=spatial_axes, sigma_d=sigma_d, levels=levels)
        guides = lv.guide_leaves(guide, params, updates, specs, log_guide, "prefilter")
        flat, treedef = jax.tree.flatten(updates)
        out = []
        for g, gd, spec in zip(flat, guides, specs):
            if not spec.axes:
                out.append(g)
                continue
            # |A g| <= max|g| in exact arithmetic; the margin keeps the float sums finite too.
            lim = min(float(jnp.finfo(jnp.promote_types(g.dtype, jnp.float32)).max) / 4,
                      float(jnp.finfo(g.dtype).max))

            def fast(ops, spec=spec):
                g, gd = ops
                if guide == "self":
                    return _filter_self((g,), spec, separable, None, log_guide)[0]
                return _filter(g, gd, spec, separable, None)

            def masked(ops, spec=spec, lim=lim):
                g, gd = ops
                # Inside the branch: built only when the branch runs (a cond's closed-over
                # values are computed before it, on every step).
                observed = _observed(g, spec.axes, mask_unobserved)
                obs = lv.expand_mask(observed, g.ndim, spec.axes)
                g0 = jnp.clip(jnp.where(obs, g, 0), -lim, lim)
                if guide == "self":
                    out = _filter_self((g0,), spec, separable, observed, log_guide)[0]
                else:
                    out = _filter(g0, gd, spec, separable, observed)
                # Unobserved texels pass through as they came, so a later stage still sees them.
                return jnp.where(obs, out, g)

            if mask_unobserved:
                res = masked((g, gd))
            else:
                res = _with_mask(fast, masked, g, lim, (g, gd))
            if not atrous._is_concrete(spec.sigma_d):
                res = res * _sigma_guard(spec.sigma_d).astype(res.dtype)
            out.append(res)
        return jax.tree.unflatten(treedef, out), state

    return optax.GradientTransformationExtraArgs(init_fn, update_fn)


def _static_checks(sigma_d, levels, spatial_axes):
    """Construction-time checks of the settings that need no parameters.

    Plain values and the values inside a pytree prefix are checked here; what
    depends on the leaves (axis ranges, dimensions) is checked by ``init``.
    """
    for sig in jax.tree.leaves(sigma_d, is_leaf=lambda x: x is None):
        if sig is None:
            raise ValueError("sigma_d must be a number >= 0 (inf for a low-pass), got None")
        atrous.check_sigma_d(sig)
    for lev in jax.tree.leaves(levels):
        if not (hasattr(lev, "shape") and not atrous._is_concrete(lev)):  # traced: update says how
            atrous.check_levels(lev)
    lv.check_spatial_axes_setting(spatial_axes)


# ----------------------------------------------------------------------------------------
# postfilter


class PostfilterState(NamedTuple):
    """State of :func:`postfilter`: the *unfiltered* moments (eqs. 2, 4).

    ``mu`` and ``nu`` are ``None`` in the memoryless case ``b1 = b2 = 0``.
    """

    count: jax.Array  # shape=(), int32
    mu: Optional[optax.Updates]
    nu: Optional[optax.Updates]


def _is_zero(x) -> bool:
    return x is not None and atrous._is_concrete(x) and float(np.asarray(x)) == 0.0


def postfilter(b1=0.2, b2=None, eps=1e-8, *, sigma_d=DEFAULT_SIGMA_D, levels=5, separable=True,
               guide="params", log_guide=False, spatial_axes=None, mask_unobserved=False,
               eps_root=0.0, mu_dtype=None) -> optax.GradientTransformationExtraArgs:
    r"""Adam whose moments are filtered in space after the temporal averages.

    .. math::
        m_t = \beta_1 m_{t-1} + (1-\beta_1) g_t, \qquad v_t = \beta_2 v_{t-1} + (1-\beta_2) g_t^2

        \Delta_t = \frac{B_t m_t / (1-\beta_1^t)}{\sqrt{B_t v_t / (1-\beta_2^t) + \epsilon_{root}} + \epsilon}

    (supplement eqs. 6-11 with bias correction; alone it is eq. 14, after
    :func:`prefilter` eq. 11). ``B_t`` is one a-trous cross-bilateral operator
    applied to ``m_t`` and ``v_t`` with the *same* weights; since it is
    row-stochastic and non-negative, ``|B m| <= c sqrt(B v)`` wherever
    ``|m| <= c sqrt(v)`` (supplement §1.3): the step stays bounded like Adam's.
    The state keeps the unfiltered ``m_t, v_t``; ``B_t`` is applied afresh every
    step and never fed back.

    With ``b1 = b2 = 0`` (supplement §1.1) no moment buffers are kept and the step
    is ``B g / (sqrt(B g^2) + eps)``, which still adapts to the local
    signal-to-noise ratio (eq. 24).

    Args:
      b1, b2: decay rates; ``b2=None`` means ``1 - (1 - b1)^2`` (both references).
      eps, eps_root: as in Adam.
      sigma_d, levels, separable, guide, log_guide, spatial_axes: as in
        :func:`prefilter`. ``guide="self"`` filters ``m`` guided by ``m`` and ``v``
        by ``v``: they then get *different* weights and the bound above no
        longer holds.
      mask_unobserved: texels whose gradient is exactly zero in every channel
        this step keep their moments, get a zero update and are left out of the
        filter sums (Mitsuba's ``mask_updates``; PyTorch's SparseAdam).
        Non-finite gradients are always treated this way.
      mu_dtype: dtype of the first moment buffer (default: the parameters').
        The second moment always has the parameters' dtype.

    Finite gradients are clipped to the largest magnitude whose square fits the
    second moment's dtype (1.3e19 for float32, 181 for float16), and a zero
    denominator gives a zero step; the module docstring lists these policies.
    """
    if b2 is None:
        b2 = 1 - (1 - b1) ** 2
    _check_unit(b1, "b1")
    _check_unit(b2, "b2")
    _check_nonneg(eps, "eps")
    _check_nonneg(eps_root, "eps_root")
    lv.check_guide(guide)
    _static_checks(sigma_d, levels, spatial_axes)
    mu_dtype = _check_mu_dtype(mu_dtype)

    def init_fn(params):
        # Shapes, dtypes and the guide are checked now rather than at the first update.
        lv.check_params(params, spatial_axes=spatial_axes, sigma_d=sigma_d, levels=levels,
                        guide=guide, transform="postfilter", all_leaves=True)
        count = jnp.zeros([], jnp.int32)
        if _is_zero(b1) and _is_zero(b2):
            return PostfilterState(count=count, mu=None, nu=None)
        mu = jax.tree.map(lambda p: jnp.zeros_like(p, dtype=mu_dtype or jnp.result_type(p)), params)
        nu = jax.tree.map(jnp.zeros_like, params)
        return PostfilterState(count=count, mu=mu, nu=nu)

    def update_fn(updates, state, params=None, **extra_args):
        del extra_args
        memoryless = state.mu is None
        count_inc = _safe_increment(state.count)
        specs = lv.leaf_specs(updates, spatial_axes=spatial_axes, sigma_d=sigma_d, levels=levels)
        guides = lv.guide_leaves(guide, params, updates, specs, log_guide, "postfilter")
        flat, treedef = jax.tree.flatten(updates)
        if memoryless:
            mus = nus = [None] * len(flat)
        else:
            mus = treedef.flatten_up_to(state.mu)
            nus = treedef.flatten_up_to(state.nu)
        c1 = _bias_correction(b1, count_inc)
        c2 = _bias_correction(b2, count_inc)
        a1, a2 = _one_minus(b1), _one_minus(b2)

        outs, new_mu, new_nu = [], [], []
        for g, gd, spec, m_old, v_old in zip(flat, guides, specs, mus, nus):
            # Moments are updated in at least float32 and stored back in their own dtype.
            ct = jnp.promote_types(
                jnp.result_type(g, *([] if memoryless else [m_old, v_old])), jnp.float32)
            # Clip so that v = g^2 (and m) cannot overflow where they are stored.
            lim = min(_grad_limit(ct) if memoryless else _grad_limit(v_old.dtype, m_old.dtype, ct),
                      float(jnp.finfo(g.dtype).max))  # finite in g's dtype: |g| <= lim rejects inf

            def moments(g, m_old, v_old, ct=ct, lim=None):
                g = g.astype(ct) if lim is None else jnp.clip(g.astype(ct), -lim, lim)
                if memoryless:
                    return g, g * g
                m = a1 * g + b1 * m_old.astype(ct)
                v = a2 * (g ** 2) + b2 * v_old.astype(ct)
                return m, v

            def step(m_f, v_f):
                return _safe_step(m_f, v_f, c1, c2, eps, eps_root)

            def filt(m, v, mask, spec=spec, gd=gd):
                if not spec.axes:
                    return m, v
                if guide == "self":
                    return _filter_self((m, v), spec, separable, mask, log_guide)
                return _filter((m, v), gd, spec, separable, mask)

            def observed_masks(g, spec=spec):
                if spec.axes:
                    observed = _observed(g, spec.axes, mask_unobserved)
                    return observed, lv.expand_mask(observed, g.ndim, spec.axes)
                obs_full = jnp.isfinite(g)
                if mask_unobserved:
                    obs_full = obs_full & (g != 0)
                return obs_full, obs_full

            def fast(ops, filt=filt, moments=moments, step=step):
                g, m_old, v_old = ops
                m, v = moments(g, m_old, v_old)
                mf, vf = filt(m, v, None)
                return step(mf, vf).astype(g.dtype), m, v

            def masked(ops, filt=filt, moments=moments, step=step, observed_masks=observed_masks,
                       spec=spec, ct=ct, lim=lim):
                g, m_old, v_old = ops
                # Inside the branch: built only when the branch runs (a cond's closed-over
                # values are computed before it, on every step).
                observed, obs_full = observed_masks(g)
                g0 = jnp.where(obs_full, g, 0)
                m, v = moments(g0, m_old, v_old, lim=lim)
                if not memoryless:
                    m = jnp.where(obs_full, m, m_old.astype(ct))
                    v = jnp.where(obs_full, v, v_old.astype(ct))
                mf, vf = filt(m, v, observed if spec.axes else None)
                d = jnp.where(obs_full, step(mf, vf), 0)
                return d.astype(g.dtype), m, v

            ops = (g, m_old, v_old)
            if mask_unobserved:
                d, m, v = masked(ops)
            else:
                d, m, v = _with_mask(fast, masked, g, lim, ops)
            if spec.axes and not atrous._is_concrete(spec.sigma_d):
                d = d * _sigma_guard(spec.sigma_d).astype(d.dtype)
            outs.append(d)
            if not memoryless:
                new_mu.append(m.astype(m_old.dtype))
                new_nu.append(v.astype(v_old.dtype))

        new_state = PostfilterState(
            count=count_inc,
            mu=None if memoryless else jax.tree.unflatten(treedef, new_mu),
            nu=None if memoryless else jax.tree.unflatten(treedef, new_nu))
        return jax.tree.unflatten(treedef, outs), new_state

    return optax.GradientTransformationExtraArgs(init_fn, update_fn)


def _check_mu_dtype(mu_dtype):
    if mu_dtype is None:
        return None
    try:
        dt = jnp.dtype(mu_dtype)
    except TypeError:
        raise TypeError(f"mu_dtype must be a floating dtype (e.g. jnp.float32) or None, "
                        f"got {mu_dtype!r}") from None
    if not jnp.issubdtype(dt, jnp.floating):
        raise TypeError(f"mu_dtype must be a floating dtype (e.g. jnp.float32) or None, got {dt}")
    return dt
