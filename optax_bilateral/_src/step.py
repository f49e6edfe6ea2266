"""One leaf's step, shared by :func:`prefilter` and :func:`postfilter`.

Both transforms run every parameter leaf through :func:`leaf_step`:

    observe      which texels have a finite (and, with mask_unobserved, non-zero) gradient
    moments      postfilter: m, v updated from the (clipped) gradient; unobserved keep theirs
    filter       the a-trous filter of the fields (g, or m and v with one set of weights)
    step         postfilter: the bias-corrected Adam step, 0 where unobserved

When every gradient is finite and within the clip limit (the common case) a
``lax.cond`` takes the plain formula; otherwise the masked one, which leaves
unobserved texels out of the sums. The step is compiled once per :class:`LeafRule`
(its static settings) and shape, also when the update runs eagerly, and inlined
into an enclosing ``jit``.

Where later options plug in: a ``sigma_d`` computed from the data belongs in
:func:`_sigma` (it sees the leaf's fields and guide); a per-texel blend of filtered
and unfiltered moments in :func:`_filtered_moments` (beside the ``filter_m`` /
``filter_v`` switches). docs/design.md has the details.
"""

from __future__ import annotations

import functools
from numbers import Real
from typing import Any, NamedTuple, cast

import jax
import jax.numpy as jnp
from jax import lax

from optax_bilateral._src import auto, layout, numerics, sure
from optax_bilateral._src.filter import atrous_bilateral
from optax_bilateral._src.leaves import log_transform

Moments = tuple[jax.Array, jax.Array] | None


class LeafRule(NamedTuple):
    """The static settings of one leaf's step (hashable: the compiled step's cache key)."""

    stage: str  # "prefilter" or "postfilter"
    axes: tuple[int, ...]  # spatial axes; () = not filtered
    levels: int
    separable: bool
    self_guided: bool  # guide="self": each field guides itself
    log_guide: bool
    mask_unobserved: bool  # all-zero texels are unobserved too
    limit: float  # |g| beyond it (or non-finite) takes the masked path
    guard_sigma: bool  # sigma_d is traced: NaN update if negative or NaN
    compute_dtype: Any = None  # postfilter: the moments' arithmetic dtype
    constants: tuple = ()  # ((name, number), ...): hyperparameters known now
    filter_m: bool = True  # postfilter: filter m (the authors' mtfilter)
    filter_v: bool = True  # postfilter: filter v (the authors' vtfilter)
    second_moment: str = "elementwise"  # or "uniform": the max of v over the leaf
    auto_sigma: bool = False  # sigma_d="auto": chosen from the data (module auto)
    sure_sigma: bool = False  # sigma_d="sure" (with auto_sigma): chosen by SURE (module sure)


def split_numbers(**values: Any) -> tuple[tuple, dict]:
    """Hyperparameters that are Python (or NumPy) numbers stay constants of the compiled
    step, exactly as written; arrays and tracers become its arguments."""
    static = tuple((k, v) for k, v in values.items() if isinstance(v, Real))
    dynamic = {k: v for k, v in values.items() if not isinstance(v, Real)}
    return static, dynamic


@functools.partial(jax.jit, static_argnames=("rule",), inline=True)
def leaf_step(
    g: jax.Array,
    guide: jax.Array | None,
    moments: Moments,
    hyper: dict,
    auto_state: auto.AutoState | None = None,
    *,
    rule: LeafRule,
) -> tuple[jax.Array, Moments, auto.AutoState | None]:
    """One leaf's output, (postfilter) new moments and (``sigma_d="auto"``) new auto state.

    Args:
      g: the leaf's gradient.
      guide: its guide (None for ``guide="self"`` or an unfiltered leaf).
      moments: the stored ``(m, v)``, or None (prefilter; memoryless postfilter).
      hyper: the traced hyperparameters (those not in ``rule.constants``), the step
        ``count`` and, for the postfilter, the bias corrections ``c1``, ``c2``.
      auto_state: with ``rule.auto_sigma``, the leaf's :class:`auto.AutoState`.
      rule: the static settings.

    Returns:
      (the prefiltered gradient or the step, the new ``(m, v)`` in their stored dtypes
      or None, the new auto state or None).
    """
    new_auto = None
    if rule.auto_sigma:
        hyper, new_auto = _auto_sigma(rule, g, guide, hyper, auto_state)
    if rule.stage == "prefilter":
        operands = (g, guide, hyper)
        if rule.mask_unobserved:
            out = _prefilter_masked(rule, operands)
        else:
            out = _when_clean(rule, g, _prefilter_plain, _prefilter_masked, operands)
        return _guarded(rule, out, hyper), None, new_auto
    operands = (g, guide, moments, hyper)
    if rule.mask_unobserved:
        d, m, v, learned = _postfilter_masked(rule, operands)
    else:
        d, m, v, learned = _when_clean(
            rule, g, _postfilter_plain, _postfilter_masked, operands, _plain_variants(rule, hyper)
        )
    d = _guarded(rule, d, hyper)
    if isinstance(new_auto, auto.AutoState) and new_auto.direction is not None:
        learned = {**learned, "direction": auto.direction_norm(d, rule.axes)}
    if new_auto is not None:
        learned = {k: x.astype(getattr(new_auto, k).dtype) for k, x in learned.items()}
        new_auto = new_auto._replace(**learned)
    if moments is None:
        return d, None, new_auto
    return d, (m.astype(moments[0].dtype), v.astype(moments[1].dtype)), new_auto


def _auto_sigma(rule, g, guide, hyper, state):
    """``hyper`` with the leaf's data-driven sigma_d (and the stored residual); the new state
    with this step's guide."""
    hyper = dict(hyper)
    if state is not None and state.residual is not None:
        hyper["residual"] = state.residual
        if isinstance(state, auto.AutoState):
            hyper["gate"] = state.gate
            if not rule.self_guided and rule.filter_m and rule.filter_v:
                hyper["correlated"] = state.correlated
    if rule.sure_sigma:
        sure_state = cast(sure.SureState, state)
        hyper["previous_gradient"] = sure_state.previous_gradient
        hyper["risks"] = sure_state.risks
        hyper["opened"] = sure_state.opened
    if rule.self_guided or guide is None:
        return hyper, state  # each field's own sigma_d, in filter_fields
    previous = None if state is None else state.previous_guide
    direction = state.direction if isinstance(state, auto.AutoState) else None
    hyper["sigma_d"] = auto.sigma(guide, previous, hyper["count"], rule.axes, direction)
    keep = auto.kept_guide(guide, rule.axes)
    keep = keep if previous is None else keep.astype(previous.dtype)
    if state is None:
        return hyper, auto.AutoState(keep, None, None, None)
    return hyper, state._replace(previous_guide=keep)


def _plain_variants(rule, hyper):
    """``sigma_d="auto"``'s forms of the plain step, and which one runs: one per
    :func:`auto.stage` of the blend, and (correlated noise) the heavier one; None where the
    step has one form."""
    if "gate" not in hyper or not rule.axes or not (rule.filter_m and rule.filter_v):
        return None
    index = auto.stage(hyper["gate"], hyper["count"])
    variants = [{"stage": auto.SKIP}, {"stage": auto.CHECK}, {"stage": auto.BLEND}]
    if "correlated" in hyper:
        index = jnp.where(hyper["correlated"] > 0, len(variants), index)
        variants.append({"heavy": True})
    return index, variants


def _when_clean(rule, g, plain, masked, operands, variants=None):
    """``plain`` when every entry of ``g`` is finite and within the limit, else ``masked``
    (only one of them runs); with ``variants`` (a traced index and the keyword arguments of
    each form of ``plain``), that form of ``plain``: a branch each, as a cond inside
    ``plain`` would keep the filter's last level out of the step's fusion."""
    clean = jnp.all(jnp.abs(g) <= rule.limit)
    if variants is None:
        return lax.cond(
            clean, functools.partial(plain, rule), functools.partial(masked, rule), operands
        )
    index, forms = variants
    branches = [functools.partial(masked, rule)]
    branches += [functools.partial(plain, rule, **form) for form in forms]
    return lax.switch(jnp.where(clean, 1 + index, 0), branches, operands)


def _guarded(rule, out, hyper):
    if rule.axes and rule.guard_sigma and not rule.auto_sigma:
        return out * numerics.sigma_guard(_sigma(rule, hyper)).astype(out.dtype)
    return out


def _number(rule, hyper, name):
    """A hyperparameter: the constant if it is one (a Python number stays a literal of the
    program, so it must not pass through the cond's operands), else the traced value."""
    for key, value in rule.constants:
        if key == name:
            return value
    return hyper[name]


def _sigma(rule, hyper):
    """The leaf's sigma_d."""
    return _number(rule, hyper, "sigma_d")


# ----------------------------------------------------------------------------------------
# The two stages


def _prefilter_plain(rule, operands):
    g, guide, hyper = operands
    return filter_fields(rule, g, guide, hyper, None)


def _prefilter_masked(rule, operands):
    g, guide, hyper = operands
    # Built inside the branch: a cond's closed-over values would be computed every step.
    observed = _observed(g, rule)
    obs = layout.expand_mask(observed, g.ndim, rule.axes)
    g0 = jnp.clip(jnp.where(obs, g, 0), -rule.limit, rule.limit)
    out = filter_fields(rule, g0, guide, hyper, observed)
    # Unobserved texels pass through as they came, so a later stage still sees them.
    return jnp.where(obs, out, g)


def _postfilter_plain(rule, operands, heavy=False, stage=None):
    g, guide, moments, hyper = operands
    m, v = _moments(rule, g, moments, hyper)

    def finish(m_f, v_f):
        return _step(rule, m_f, v_f, hyper).astype(g.dtype)

    d, learned = _filtered_moments(rule, m, v, guide, hyper, None, g, finish, heavy, stage)
    return d, m, v, learned


def _postfilter_masked(rule, operands):
    g, guide, moments, hyper = operands
    # Built inside the branch: a cond's closed-over values would be computed every step.
    if rule.axes:
        observed = _observed(g, rule)
        obs_full = layout.expand_mask(observed, g.ndim, rule.axes)
    else:
        observed = obs_full = jnp.isfinite(g)
        if rule.mask_unobserved:
            observed = obs_full = obs_full & (g != 0)
    g_obs = jnp.where(obs_full, g, 0).astype(rule.compute_dtype)
    g_obs = jnp.clip(g_obs, -rule.limit, rule.limit)
    m, v = _moments(rule, g_obs, moments, hyper)
    if moments is not None:
        m = jnp.where(obs_full, m, moments[0].astype(rule.compute_dtype))
        v = jnp.where(obs_full, v, moments[1].astype(rule.compute_dtype))

    def finish(m_f, v_f):
        if rule.second_moment == "uniform":
            # The max over the leaf counts unobserved texels by the moments they keep.
            v_f = jnp.where(obs_full, v_f, v)
        return jnp.where(obs_full, _step(rule, m_f, v_f, hyper), 0).astype(g.dtype)

    observed = observed if rule.axes else None
    d, learned = _filtered_moments(rule, m, v, guide, hyper, observed, g_obs, finish)
    return d, m, v, learned


# ----------------------------------------------------------------------------------------
# The parts


def _observed(g, rule):
    """Texel-level mask of observed entries (finite, and not all-zero if mask_unobserved)."""
    m = layout.texel_mask(jnp.isfinite(g), rule.axes)
    if rule.mask_unobserved:
        m = m & ~layout.texel_mask(g == 0, rule.axes)
    return m


def _moments(rule, g, moments, hyper):
    """(m, v) in the compute dtype; without stored moments (memoryless) ``(g, g^2)``."""
    g = g.astype(rule.compute_dtype)
    if moments is None:
        return g, g * g
    m_old, v_old = moments
    num = functools.partial(_number, rule, hyper)
    m = num("one_minus_b1") * g + num("b1") * m_old.astype(rule.compute_dtype)
    v = num("one_minus_b2") * (g**2) + num("b2") * v_old.astype(rule.compute_dtype)
    return m, v


def _filtered_moments(rule, m, v, guide, hyper, observed, g, finish, heavy=None, stage=None):
    """``finish(B m, B v)`` (the step), with one set of weights for both moments
    (unfiltered where the leaf is not filtered, and each left as it is when ``filter_m`` /
    ``filter_v`` is off), and what the step learned for the leaf's auto state (``{}``, or
    with moments the new ``residual`` of ``sigma_d="auto"`` and its blend's ``gate``, and
    with ``"sure"`` the gradient ``g``, the chosen sigma_d and F, the risks and whether the
    gate has opened). ``heavy``: whether ``"auto"`` filters for correlated noise (a Python
    bool), and ``stage``: what its blend computes (:func:`auto.stage`); None to read them
    from ``hyper``."""
    if not rule.axes or not (rule.filter_m or rule.filter_v):
        return finish(m, v), {}
    if not rule.filter_v:
        return finish(filter_fields(rule, m, guide, hyper, observed), v), {}
    if not rule.filter_m:
        return finish(m, filter_fields(rule, v, guide, hyper, observed)), {}
    if "correlated" in hyper:  # sigma_d="auto" with moments, cross-guided
        learned = {"correlated": _correlation_check(rule, m, hyper, observed, g)}
        heavy_step = lambda: _heavy_moments(rule, m, v, guide, hyper, observed, finish)
        blend_step = lambda: _blend(rule, m, v, guide, hyper, observed, finish, {}, stage=stage)
        if heavy is None:
            out, more = lax.cond(hyper["correlated"] > 0, heavy_step, blend_step)
        else:
            out, more = heavy_step() if heavy else blend_step()
        return out, {**learned, **more}
    learned = {}
    if rule.sure_sigma:
        m_f, v_f, learned = _sure_moments(rule, m, v, guide, hyper, observed, g)
        if "residual" not in hyper:
            return finish(m_f, v_f), learned
        return _blend(rule, m, v, guide, hyper, observed, finish, learned, (m_f, v_f))
    if "residual" in hyper:
        return _blend(rule, m, v, guide, hyper, observed, finish, learned, stage=stage)
    return finish(*filter_fields(rule, (m, v), guide, hyper, observed)), learned


def _correlation_check(rule, m, hyper, observed, g):
    """The new :attr:`auto.AutoState.correlated`: :func:`auto.correlated` at the second step
    (the first with a noise estimate) and every ``auto.CHECK_PERIOD``-th, else the stored
    one."""
    obs_full = auto.full_mask(observed, m.ndim, rule.axes)
    b1 = _number(rule, hyper, "b1")

    def check():
        now = auto.correlated(g, m, b1=b1, c1=hyper["c1"], axes=rule.axes, observed=obs_full)
        return now.astype(m.dtype)

    stored = lambda: hyper["correlated"].astype(m.dtype)
    count = hyper["count"]
    return lax.cond((count == 2) | (count % auto.CHECK_PERIOD == 0), check, stored)


def _heavy_moments(rule, m, v, guide, hyper, observed, finish):
    """``sigma_d="auto"`` where the gradient's noise is correlated (:func:`auto.correlated`):
    ``auto.HEAVY_FACTOR`` times sigma_d, ``auto.extra_levels`` more levels, no blend."""
    heavy = dict(hyper, sigma_d=hyper["sigma_d"] * auto.HEAVY_FACTOR)
    levels = rule.levels + auto.extra_levels(rule.axes)
    m_f, v_f = _filter(rule, (m, v), guide, heavy, observed, levels=levels)
    residual = _residual(rule, m, m_f, hyper, observed)
    return finish(m_f, v_f), {"gate": jnp.zeros([], m.dtype), "residual": residual}


def _residual(rule, m, m_f, hyper, observed):
    """The residual's EMA with this step's ``m_hat - B m_hat`` (:func:`auto.update_residual`)."""
    obs_full = auto.full_mask(observed, m.ndim, rule.axes)
    residual = hyper["residual"].astype(m.dtype)
    return auto.update_residual(m, m_f, residual, hyper["c1"], obs_full)


def _blend(rule, m, v, guide, hyper, observed, finish, learned, filtered=None, stage=None):
    """``finish`` of the moments blended with their filtered ``filtered`` (by default the
    rule's filter of them), ``sigma_d="auto"``'s and ``"sure"``'s, and what the step learned:
    the residual and (``"auto"``) the gate. ``stage`` (``"auto"``): what the step computes
    of the blend (:func:`auto.stage`), or None to choose it in a switch."""
    m_f, v_f = filtered or filter_fields(rule, (m, v), guide, hyper, observed)
    residual = _residual(rule, m, m_f, hyper, observed)
    learned = {**learned, "residual": residual}
    statistics = dict(
        b1=_number(rule, hyper, "b1"),
        c1=hyper["c1"],
        c2=hyper["c2"],
        count=hyper["count"],
        axes=rule.axes,
    )
    if rule.sure_sigma:
        lam, gate = auto.weights(m, v, residual, **statistics)
        # Sticky: the bias it saw persists, the gate's view of it does not.
        learned["opened"] = jnp.maximum(hyper["opened"], (gate >= 1).astype(m.dtype))
        return finish(auto.mix(lam, m, m_f), auto.mix(lam, v, v_f)), learned
    closed = lambda: jnp.zeros([], m.dtype)
    check = lambda: auto.gate(m, v, residual, **statistics)
    if stage is None:  # lam alone crosses the switch so that B m and B v stay outside it,
        # fused into the step (docs/design.md)
        branches = [  # in the order SKIP, CHECK, BLEND
            lambda: (jnp.zeros_like(m), closed()),
            lambda: (jnp.zeros_like(m), check()),
            lambda: auto.weights(m, v, residual, **statistics),
        ]
        lam, learned["gate"] = lax.switch(auto.stage(hyper["gate"], hyper["count"]), branches)
    elif stage == auto.BLEND:
        lam, learned["gate"] = auto.weights(m, v, residual, **statistics)
    else:  # a closed gate: no blend (a check computes the gate for the next step)
        learned["gate"] = check() if stage == auto.CHECK else closed()
        return finish(m_f, v_f), learned
    return finish(auto.mix(lam, m, m_f), auto.mix(lam, v, v_f)), learned


def _sure_moments(rule, m, v, guide, hyper, observed, g):
    """``sigma_d="sure"``: per candidate sigma_d one cascade of (m, noise sample), read after
    each candidate F; the candidate of least moving-average risk (module sure);
    then v filtered with the chosen operator."""
    b1 = jnp.asarray(_number(rule, hyper, "b1"), m.dtype)
    ratio, usable = auto.noise_ratio(b1, hyper["c1"], hyper["count"])
    previous = hyper["previous_gradient"].astype(m.dtype)
    g = g.astype(m.dtype)
    obs_full = auto.full_mask(observed, m.ndim, rule.axes)
    if obs_full is not None:  # an unobserved texel's last gradient waits for its next one
        g = jnp.where(obs_full, g, previous)
    zeta = sure.noise_sample(g, previous, ratio, usable)
    scale = hyper["sigma_d"]

    def filter_at(fields, sigma_d, levels, first_level):
        at = dict(hyper, sigma_d=sigma_d)
        return _filter(rule, fields, guide, at, observed, levels=levels, first_level=first_level)

    candidates = sure.candidates((m, zeta), rule.levels, scale, filter_at)
    c1 = jnp.asarray(hyper["c1"], m.dtype)
    first = sure.first(rule.levels)
    m_f, pick, risks = sure.choose(
        m, zeta, candidates, c1, usable, obs_full, first, hyper["risks"], hyper["opened"]
    )
    sigmas, levels = sure.labels(rule.levels, scale)
    sigma_d, chosen = sigmas[pick], levels[pick]

    def filter_v(n):
        return lambda: _filter(rule, v, guide, dict(hyper, sigma_d=sigma_d), observed, levels=n)

    # Only the chosen F's branch runs.
    choices = sure.level_choices(rule.levels)
    v_f = lax.switch(chosen - choices[0], [filter_v(n) for n in choices])
    learned = {"previous_gradient": g, "sigma_d": sigma_d, "levels": chosen, "risks": risks}
    return m_f, v_f, learned


def _step(rule, m_f, v_f, hyper):
    if rule.second_moment == "uniform":
        # One second moment for the whole leaf (Large Steps' and the Dr.Jit port's uniform).
        v_f = jnp.broadcast_to(jnp.max(v_f), v_f.shape)
    num = functools.partial(_number, rule, hyper)
    return numerics.safe_step(m_f, v_f, num("c1"), num("c2"), num("eps"), num("eps_root"))


def filter_fields(rule, fields, guide, hyper, observed) -> Any:
    """The leaf's filter of ``fields`` (an array or a tuple); ``observed`` (texels, in
    ``rule.axes`` order) or None.

    With ``guide="self"`` every field guides itself, each level by its own input (the
    authors' ``cross_term_off``), so each field gets its own weights; unobserved texels
    are left out by the filter's ``mask`` (a guide read from the fields cannot carry NaN).
    """
    if rule.self_guided:
        if rule.auto_sigma:  # each field's own sigma_d, from its own contrast
            many = isinstance(fields, tuple)
            out = tuple(
                _self_filter(rule, f, _self_sigma(rule, f, hyper), observed)
                for f in (fields if many else (fields,))
            )
            return out if many else out[0]
        return _self_filter(rule, fields, _sigma(rule, hyper), observed)
    return _filter(rule, fields, guide, hyper, observed)


def _self_filter(rule, fields, sigma_d, observed):
    return atrous_bilateral(
        fields,
        "self",
        sigma_d=sigma_d,
        levels=rule.levels,
        spatial_axes=rule.axes,
        separable=rule.separable,
        mask=observed,
        log_guide=rule.log_guide,
    )


def _self_sigma(rule, field, hyper):
    guide = log_transform(field) if rule.log_guide else field
    return auto.sigma(guide, None, hyper["count"], rule.axes)


def _filter(rule, fields, guide, hyper, observed, levels=None, first_level=0):
    """Unobserved texels are left out of every sum by a NaN guide there (a non-finite
    guide weighs 0), not by the filter's ``mask``: then both branches of the step's cond
    compile to the same filter, and XLA sizes its temporaries by the larger branch. The
    outputs at unobserved texels are then their own inputs, not 0; every caller discards
    them, and their inputs must be finite (0 * inf would leak into the neighbours' sums).
    ``levels`` (default: the rule's) and ``first_level`` run part of the cascade.
    """
    if observed is not None:
        nan_guide = nan_guide_at(guide, observed, rule.axes)
        if nan_guide is not None:
            guide, observed = nan_guide, None
    return atrous_bilateral(
        fields,
        guide,
        sigma_d=_sigma(rule, hyper),
        levels=rule.levels if levels is None else levels,
        spatial_axes=rule.axes,
        separable=rule.separable,
        mask=observed,
        first_level=first_level,
    )


def nan_guide_at(guide, observed, axes):
    """``guide`` with NaN at the texels where ``observed`` is False, or None if its layout is
    neither the spatial grid nor a leaf's, or it cannot hold NaN (then the filter's own
    ``mask`` is used)."""
    guide = jnp.asarray(guide)
    if not jnp.issubdtype(guide.dtype, jnp.floating):
        return None
    if guide.shape == observed.shape:
        m = observed
    elif guide.ndim > max(axes) and tuple(guide.shape[a] for a in axes) == observed.shape:
        m = layout.expand_mask(observed, guide.ndim, axes)
    else:
        return None
    return jnp.where(m, guide, jnp.nan)
