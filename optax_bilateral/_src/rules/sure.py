"""``sigma_d="sure"``: the step scale (``"auto"``'s prefilter scale, 3x the guide's mean change
per step) times one of a few factors, at one of the levels ``F = min_levels .. levels``,
chosen per leaf and step by Stein's unbiased risk estimate.

Derived and measured in docs/auto_sigma.md (section ``sigma_d="sure"``). For a fixed guide the
postfilter ``B`` is linear, so with a sample ``zeta`` of the noise of ``m_hat`` the risk
of a candidate ``B`` is estimated without the true moments:

    risk(B) = sum_i (m_hat - B m_hat)_i^2 - ((I - B) zeta)_i^2 + W (B zeta)_i^2

(the bias's square, unbiased, then the filtered noise's variance, weighted by ``W``:
``W = 1`` is SURE, ``W < 1`` discounts the noise the optimiser averages out over steps).
Each step's risks, over their largest magnitude (every step one vote), enter an exponential
moving average over steps, and its least entry is chosen. The noise sample is the
difference of successive gradients, ``sqrt(rho / 2) (g_t - g_{t-1})``. The candidates of one
factor are one cascade, read after each F. The chosen ``B`` filters both ``m`` and ``v``, then
``"auto"``'s blend follows: one non-negative, row-stochastic operator, so the step stays
bounded (supplement §1.3). Once the blend's gate has been fully open on a leaf, the leaf takes
the mildest candidate for the rest of the run.
"""

from __future__ import annotations

import dataclasses
import functools
from numbers import Real
from typing import NamedTuple, cast

import jax
import jax.numpy as jnp
from jax import lax

from optax_bilateral._src import numerics
from optax_bilateral._src.filter.local import sum_of_squares
from optax_bilateral._src.rules.auto import (
    Auto,
    AutoState,
    blend_weights,
    noise_ratio,
    update_residual,
    upsample,
)
from optax_bilateral._src.rules.sigma import Filtered, Setting, SigmaRule, cast_like
from optax_bilateral._src.validation import check_integer, check_number

# With "sure", F is chosen per step among 2 .. levels; 5 is the suite's best bound.
SURE_LEVELS = 5
"""The default ``levels`` of a leaf with ``sigma_d="sure"``, the most F it may choose (F = 2
.. 5, footprint radius up to 62 texels; the authors' ``stride_levels = 6``)."""


class SureState(NamedTuple):
    """One leaf's state for ``sigma_d="sure"`` (in :class:`PostfilterState`, field
    ``sigma_state``).

    Attributes:
      previous_guide: the guide the last update saw (the step scale; on a large leaf its
        sub-grid, as :attr:`AutoState.previous_guide`).
      residual: ``"auto"``'s residual EMA of ``m_hat - B m_hat`` (the blend).
      previous_gradient: the gradient the last update saw, in the moments' arithmetic
        dtype (the noise sample is its difference from this step's).
      sigma_d: the sigma_d the last update chose, a scalar (0 before the first update, and
        where the guide is constant, which every sigma_d filters alike).
      levels: the F the last update chose (int32 scalar; 0 before the first update).
      risks: the moving average of every candidate's estimated risk, each step's over its
        largest magnitude (0 before the noise is known), factor-major: ``factors[0]`` at
        F = ``min_levels`` .. ``levels``, then ``factors[1]``, ...
      opened: 1 once the blend's gate has been fully open at a step, else 0 (a scalar); from
        then on the leaf takes the mildest candidate.

    Example::

        >>> import jax.numpy as jnp, optax_bilateral as ob
        >>> state = ob.postfilter(sigma_d="sure").init({"tex": jnp.ones((16, 16, 3))})
        >>> sure = state.sigma_state["tex"]
        >>> type(sure).__name__, sure.previous_gradient.shape, float(sure.sigma_d)
        ('SureState', (16, 16, 3), 0.0)
        >>> int(sure.levels), sure.risks.shape   # 3 factors at F = 2 .. 5 (SURE_LEVELS)
        (0, (12,))
        >>> float(sure.opened)
        0.0
    """

    previous_guide: jax.Array
    residual: jax.Array
    previous_gradient: jax.Array
    sigma_d: jax.Array
    levels: jax.Array
    risks: jax.Array
    opened: jax.Array


@jax.tree_util.register_static
@dataclasses.dataclass(frozen=True)
class Sure(SigmaRule):
    """``sigma_d="sure"`` with its constants as fields (``"sure"`` is ``Sure()``, which
    :func:`optax_bilateral.sure_sigma` builds with other values).

    Attributes:
      factors: the candidates' sigma_d, times the step scale.
      min_levels: the candidates' F run from this to the leaf's ``levels``.
      variance_weight: ``W``, the weight of the filtered noise's variance in the risk.
      risk_decay: the risks' moving average over steps (~10 steps).
      first_factor: the factor taken (at the middle F) before the noise is known.
      auto: ``"auto"``'s constants, for the step scale, the sub-grid and the blend.

    Example::

        >>> import jax.numpy as jnp, optax_bilateral as ob
        >>> rule = ob.sure_sigma(factors=(1.0, 3.0), first_factor=3.0)
        >>> opt = ob.postfilter(sigma_d=rule)
        >>> state = opt.init(jnp.ones((16, 16, 3)))
        >>> state.sigma_state.risks.shape     # candidates at F = 2 .. 5, two factors each
        (8,)
    """

    factors: tuple[float, ...] = (1.0, 3.0, 10.0)
    min_levels: int = 2
    variance_weight: float = 0.1
    risk_decay: float = 0.9
    first_factor: float = 3.0
    auto: Auto = dataclasses.field(default_factory=Auto)

    def default_levels(self) -> int:
        return SURE_LEVELS

    def check(self, setting: Setting) -> None:
        why = _unusable(setting)
        if why is not None:
            raise ValueError(
                "sigma_d='sure' chooses among filters of Adam's moments m and v by their "
                f"estimated risk: {why}"
            )

    def __post_init__(self):
        factors = self.factors
        if not (
            isinstance(factors, tuple)
            and factors
            and all(isinstance(f, Real) and f > 0 for f in factors)
        ):
            raise ValueError(f"factors must be a non-empty tuple of numbers > 0, got {factors!r}")
        if self.first_factor not in factors:
            raise ValueError(
                f"first_factor must be one of factors {factors}, got {self.first_factor!r}"
            )
        check_integer(self, "min_levels", low=1)
        check_number(self, "variance_weight", low=0)
        check_number(self, "risk_decay", low=0, high=1, high_open=True)
        if not isinstance(self.auto, Auto):
            raise TypeError(f"auto must be an auto_sigma() rule, got {self.auto!r}")

    def init(self, leaf, guide, plan, kind):
        dtype = jnp.promote_types(jnp.result_type(leaf), jnp.float32)
        zeros = lambda shape, dt=dtype: jnp.zeros(shape, dt)  # every field its own buffer
        # "auto"'s guide and residual (this is a cross-guided postfilter's leaf: check()).
        auto = self.auto.init(leaf, guide, plan, kind)
        return SureState(
            cast(jax.Array, auto.previous_guide),
            cast(jax.Array, auto.residual),
            numerics.zeros(leaf, dtype),  # the leaf's sharding too
            zeros([]),
            zeros([], jnp.int32),
            zeros([self._n_candidates(plan.levels)]),
            zeros([]),
        )

    def sigma(self, guide, plan, state, ctx):
        # "auto"'s step scale: its sigma_d where no direction is kept (a prefilter's).
        auto = AutoState(state.previous_guide, None, None, None)
        scale, auto = self.auto.sigma(guide, plan, auto, ctx)
        return scale, state._replace(previous_guide=auto.previous_guide)

    def combine(self, moments, op, sigma, state, ctx):
        return None, (functools.partial(self._filtered, moments, op, sigma, state, ctx),)

    def _filtered(self, moments, op, sigma, state, ctx):
        """The chosen candidate's ``B m``, ``B v``, then ``"auto"``'s blend (:class:`Filtered`)."""
        axes = op.plan.axes
        m_f, v_f, chosen = self._select(moments, op, sigma, state, ctx)
        residual = update_residual(self.auto, moments, m_f, state.residual, ctx.inv_c1, axes)
        scalars = self.auto._blend_scalars(ctx, moments.m.dtype)
        lam, gate = blend_weights(self.auto, moments, residual, scalars, axes)
        lam = upsample(self.auto, lam, moments.m.shape, axes)
        # Sticky: the bias it saw persists, the gate's view of it does not.
        opened = jnp.maximum(state.opened, (gate >= 1).astype(moments.m.dtype))
        new = chosen._replace(residual=residual, opened=opened)
        return Filtered(m_f, v_f, lam, cast_like(new, state))

    def _select(self, moments, op, scale, state, ctx):
        """Per candidate sigma_d one cascade of (m, noise sample), read after each candidate
        F; the candidate of least moving-average risk; then v filtered with the chosen
        operator. Returns ``(B m, B v, the state with the choice)``, its fields not yet cast
        to the state's dtypes."""
        m, v, levels = moments.m, moments.v, op.plan.levels
        b1 = jnp.asarray(ctx.b1, m.dtype)
        ratio, usable = noise_ratio(b1, ctx.c1, ctx.count)
        previous = state.previous_gradient.astype(m.dtype)
        # An unobserved texel's last gradient waits for its next one.
        g = jnp.where(moments.observed, moments.g.astype(m.dtype), previous)
        zeta = _noise_sample(g, previous, ratio, usable)
        cascades = self._candidates((m, zeta), levels, scale, op.apply)
        c1 = jnp.asarray(ctx.c1, m.dtype)
        first = self._first(levels)
        m_f, pick, risks = self._choose(
            m, zeta, cascades, c1, usable, moments.observed, first, state
        )
        sigmas, chosen_levels = self._labels(levels, scale)
        sigma_d, chosen = sigmas[pick], chosen_levels[pick]
        choices = self._level_choices(levels)
        # Only the chosen F's branch runs.
        v_f = lax.switch(
            chosen - choices[0], [lambda n=n: op.apply(v, sigma_d, levels=n) for n in choices]
        )
        new = state._replace(previous_gradient=g, sigma_d=sigma_d, levels=chosen, risks=risks)
        return m_f, v_f, new

    # ------------------------------------------------------------------ candidates

    def _level_choices(self, levels: int) -> tuple[int, ...]:
        """The candidates' F for a leaf filtered with ``levels`` levels at most."""
        return tuple(range(min(self.min_levels, levels), levels + 1))

    def _n_candidates(self, levels: int) -> int:
        """How many candidates a leaf filtered with ``levels`` levels at most has."""
        return len(self.factors) * len(self._level_choices(levels))

    def _labels(self, levels: int, scale) -> tuple[jax.Array, jax.Array]:
        """``(sigma_d, F)`` of every candidate, in :meth:`_choose`'s order (factor-major)."""
        choices = self._level_choices(levels)
        sigma_d = jnp.stack([f * scale for f in self.factors for _ in choices])
        return sigma_d, jnp.asarray([n for _ in self.factors for n in choices], jnp.int32)

    def _first(self, levels: int) -> int:
        """The candidate taken before the noise can be estimated: ``first_factor`` at the
        middle F."""
        choices = self._level_choices(levels)
        return self.factors.index(self.first_factor) * len(choices) + len(choices) // 2

    def _candidates(self, fields, levels: int, scale, apply) -> list:
        """Every candidate's filter of ``fields``, in :meth:`_choose`'s order: per factor one
        cascade, read after each F. ``apply(fields, sigma_d, levels, first_level)`` runs levels
        ``first_level .. levels - 1`` of the leaf's filter."""
        out = []
        for factor in self.factors:
            x, done = fields, 0
            for n in self._level_choices(levels):
                x = apply(x, factor * scale, n, done)
                out.append(x)
                done = n
        return out

    def _choose(self, m, zeta, candidates, c1, usable, observed, first_pick, state):
        """``(B m, pick, risks)``: the candidate ``(B m, B zeta)`` of least moving-average risk
        (``first_pick`` until ``usable``) and the new average.

        ``m`` is the raw first moment (``m / c1`` is ``m_hat``); ``observed`` (full shape)
        leaves unobserved entries out of the sums; ``state.risks`` is the average so far, and
        ``state.opened`` > 0 takes the mildest candidate once usable. The caller filters ``v``
        with the chosen operator.
        """
        observed_only = lambda x: jnp.where(observed, x, 0)
        step = []
        for bm, bz in candidates:
            bias = sum_of_squares(observed_only(m - bm)) / c1**2 - sum_of_squares(
                observed_only(zeta - bz)
            )
            step.append(bias + self.variance_weight * sum_of_squares(observed_only(bz)))
        step = _votes(jnp.stack(step))
        previous = state.risks.astype(step.dtype)
        new = jnp.where(usable, self.risk_decay * previous + (1 - self.risk_decay) * step, previous)
        # Opened: the mildest candidate, the first (factors[0] at the least F).
        best = jnp.where(state.opened > 0, 0, jnp.argmin(new))
        pick = jnp.where(usable, best, first_pick).astype(jnp.int32)
        return lax.select_n(pick, *(c[0] for c in candidates)), pick, new


def _noise_sample(g, previous, ratio, usable):
    """A sample of the noise of ``m_hat``: ``sqrt(ratio / 2) (g_t - g_{t-1})`` (0 until the
    noise can be estimated)."""
    return jnp.where(usable, jnp.sqrt(ratio / 2) * (g - previous), 0).astype(g.dtype)


def _votes(risks):
    """One step's risks over their largest finite magnitude, so each step weighs the same in
    the average; an overflowing risk is no evidence for its candidate: 2, worse than any
    finite one."""
    finite = jnp.isfinite(risks)
    largest = jnp.max(jnp.where(finite, jnp.abs(risks), 0))
    scaled = risks / jnp.maximum(largest, jnp.finfo(risks.dtype).tiny)
    return jnp.where(finite, scaled, 2)


def _unusable(setting: Setting) -> str | None:
    """Why ``"sure"`` cannot run in a transform with ``setting`` (None: it can): it compares
    filters of the moments m and v, so it needs both, filtered by one operator."""
    if setting.kind == "prefilter":
        return "a prefilter has no moments; use a number or 'auto'"
    if setting.kind == "memoryless":
        return "b1 = b2 = 0 keeps no moments; use a number or 'auto'"
    if setting.self_guided:
        return "guide='self' gives m and v their own weights; use a number or 'auto'"
    if not setting.filters_both:
        return "it needs filter_m=True and filter_v=True (one operator for both)"
    return None
