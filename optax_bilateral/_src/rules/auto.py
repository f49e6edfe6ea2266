"""``sigma_d="auto"``: the data term's scale, and how much to filter, chosen from the data.

Three parts, derived in docs/auto_sigma.md and measured by ``python -m experiments.tuning``;
their constants are the fields of :class:`Auto` (``"auto"`` is ``Auto()``):

* **The scale.** In a postfilter, one learning rate in the guide's units:
  ``sigma_d = sqrt(C) mean_p ||guide_t[p] - guide_{t-1}[p]|| / mean_p ||d_{t-1}[p]||``
  (``C`` channels per texel, ``d`` the postfilter's last output ``m~ / (sqrt(v~) + eps)``).
  A prefilter, which does not see the step it leads to, uses ``step_factor`` times the mean
  guide step instead. Before the guide has moved (the first step) ``contrast_factor`` times
  the guide's mean deviation from its local average stands in. On a leaf of more than
  ``min_texels`` texels both means run over a strided sub-grid of at least that many (every
  ``s``-th texel along each spatial axis, ``s`` the largest power of two that leaves that
  many), and only that sub-grid of the guide is kept.
* **The blend** (postfilter with moments). Texels where the residual ``r = m_hat - B m_hat``
  persists over time beyond what the moments' noise (supplement eq. 24, ``v - m^2``)
  explains keep more of their unfiltered moments, ``m~ = lam m_hat + (1 - lam) B m_hat`` and
  likewise ``v``, with one ``lam`` for both, so the step stays bounded (supplement §1.3). A
  leaf blends only where persistent residuals are widespread (``gate``); while its gate is
  closed it is checked only every ``check_period``-th step, from the sub-grid.
* **Correlated noise** (postfilter with moments, cross-guided). Where the lag-1 correlation
  of ``g - m_hat`` between neighbours is at least ``correlated`` and that difference is
  noise, not the signal's drift (``noisy``), the step filters at ``heavy_factor`` times
  sigma_d with :attr:`Auto.heavy_levels` more levels, and without the blend. The check runs at the
  second step and every ``check_period``-th, and holds until the next.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from numbers import Real
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax import lax

from optax_bilateral._src import numerics
from optax_bilateral._src.filter.bilateral import Deeper, log_transform
from optax_bilateral._src.filter.local import (
    FromGradient,
    NoiseTest,
    StepCall,
    StepFlags,
    correlated_noise,
    correlation_sums,
    every,
    local_average_subgrid,
    runs_native,
    step_norm,
    subgrid_blend,
    texel_distance_mean,
)
from optax_bilateral._src.filter.operators import CrossGuided
from optax_bilateral._src.rules.sigma import (
    Filtered,
    Moments,
    SigmaRule,
    StepContext,
    blend,
    cast_like,
)
from optax_bilateral._src.validation import check_integer, check_number

SKIP, CHECK, BLEND = 0, 1, 2  # what a postfilter step computes of the blend (blend_phase)
# The first step with a noise estimate: v_hat - m_hat^2 needs two gradients.
FIRST_NOISE_STEP = 2
# m_hat's variance within this share of the gradient's: b1 ~ 0, no memory to tell noise by.
MEMORY_EPS = 1e-6


class AutoState(NamedTuple):
    """One leaf's state for ``sigma_d="auto"`` (in :class:`PrefilterState` and
    :class:`PostfilterState`, field ``sigma_state``).

    Attributes:
      previous_guide: the guide the last update saw, with the guide's shape, or on a leaf of
        more than ``min_texels`` (4096) texels its sub-grid (every ``s``-th texel along each
        spatial axis, ``s`` the largest power of two that leaves at least ``min_texels``);
        None for ``guide="self"``.
      residual: the exponential moving average (decay 0.97) of ``m_hat - B m_hat`` on the
        leaf's sub-grid (``previous_guide``'s texels, with the leaf's channels; the whole
        leaf on a leaf of at most ``min_texels`` texels); None in a :func:`prefilter` or a
        memoryless postfilter (no moments).
      direction: the mean norm per texel of a postfilter's last output
        ``m~ / (sqrt(v~) + eps)`` (a scalar; texels whose norm is NaN left out; 0 before the
        first step); None in a :func:`prefilter`.
      gate: how far the blend was open at the last step (a scalar in [0, 1]; 0 at a step
        that skipped the blend's statistics); None where ``residual`` is. While it is 0,
        it is checked only every ``check_period`` (8) steps, from a sub-grid of the leaf,
        and a gate that opens there blends from the next step.
      correlated: 1 where the gradient's noise was spatially correlated at the last check
        (the second step and every ``check_period``-th), else 0
        (a scalar): until the next check the postfilter filters at ``heavy_factor`` times
        sigma_d with :attr:`Auto.heavy_levels` more levels and without the blend. None where
        ``residual`` is.

    Example::

        >>> import jax.numpy as jnp, optax_bilateral as ob
        >>> state = ob.postfilter().init({"tex": jnp.ones((16, 16, 3))})   # sigma_d="auto"
        >>> auto = state.sigma_state["tex"]
        >>> type(auto).__name__, auto.previous_guide.shape, auto.residual.shape
        ('AutoState', (16, 16, 3), (16, 16, 3))
        >>> float(auto.direction), float(auto.gate), float(auto.correlated)
        (0.0, 0.0, 0.0)
    """

    previous_guide: jax.Array | None
    residual: jax.Array | None
    direction: jax.Array | None
    gate: jax.Array | None
    correlated: jax.Array | None = None


class Decisions(NamedTuple):
    """What a postfilter step of ``"auto"`` decides from its state and the step count alone
    (:meth:`Auto.prepare`): whether it filters heavier (the noise was correlated at the last
    check), checks the correlation, computes the blend's statistics (at least its gate's
    check) and blends; the blend's scalars (:meth:`Auto._blend_scalars`); and ``c1``. What a
    native call reads is an :class:`~optax_bilateral._src.numerics.Entry` of one vector."""

    heavy: jax.Array
    due: numerics.Entry
    computed: numerics.Entry
    blends: jax.Array
    scalars: jax.Array
    c1: numerics.Entry
    lag: numerics.Entry  # 1 - (1 - b1) / c1: the correlated-noise test's (_correlated_noise)
    flags: StepFlags  # what the native step norm reads (Auto.read_step)


@jax.tree_util.register_static
@dataclasses.dataclass(frozen=True)
class Auto(SigmaRule):
    """``sigma_d="auto"`` with its constants as fields (``"auto"`` is ``Auto()``, which
    :func:`optax_bilateral.auto_sigma` builds with other values; docs/auto_sigma.md derives
    each and measures it).

    Attributes:
      rate_factor: postfilter: sigma_d per learning rate (in guide units) per sqrt(channel).
      step_factor: prefilter (and ``"sure"``'s scale): sigma_d per mean guide step.
      contrast_factor: sigma_d per mean deviation of the guide from its local average (the
        first step, or a guide at rest).
      residual_decay: the residual's moving average (~33 steps: a bias below one step's
        noise shows).
      gain: ``lam = 0`` until the persistent residual exceeds ``1 / gain`` times its noise.
      power: ``lam``'s exponent.
      gate_bounds: a leaf's mean ``lam`` below ``gate_bounds[0]``: no blend (the gate,
        :attr:`AutoState.gate`, is 0); above ``gate_bounds[1]``: full blend (1).
      check_period: a closed gate (and the correlation) is checked every this many steps.
      min_texels: a larger leaf's statistics run over a strided sub-grid of at least this
        many texels.
      correlated: the lag-1 correlation of the noise between neighbours at and above which it
        counts as spatially correlated (exp(-1/4): Gaussian noise one texel wide).
      noisy: ``g - m_hat_{t-1}`` must carry at least this share of ``m_hat``'s energy for
        the correlation to be the noise's, not the signal's.
      heavy_factor: sigma_d per learning rate where the gradient's noise is correlated.
      heavy_levels: the levels added where the noise is correlated, on 1-D, 2-D and 3-D
        grids: 2, 1 and none (on 3-D the compiled extra level slows every update;
        docs/auto_sigma.md).

    Example::

        >>> import jax.numpy as jnp, optax_bilateral as ob
        >>> rule = ob.auto_sigma(check_period=4)         # the gate's check every 4th step
        >>> opt = ob.bilateral_adam(0.02, sigma_d=rule)
        >>> state = ob.postfilter(sigma_d=rule).init(jnp.ones((512, 512, 3)))
        >>> state.sigma_state.previous_guide.shape   # a 512x512 leaf's statistics: every 8th texel
        (64, 64, 3)
    """

    rate_factor: float = 1.0
    step_factor: float = 3.0
    contrast_factor: float = 1.5
    residual_decay: float = 0.97
    gain: float = 0.25
    power: float = 2.0
    gate_bounds: tuple[float, float] = (0.5, 0.65)
    check_period: int = 8
    min_texels: int = 4096
    correlated: float = math.exp(-0.25)
    noisy: float = 0.25
    heavy_factor: float = 3.0
    heavy_levels: tuple[int, int, int] = (2, 1, 0)

    def __post_init__(self):
        for name in ("rate_factor", "step_factor", "contrast_factor", "gain", "power"):
            check_number(self, name, low=0, low_open=True)
        check_number(self, "heavy_factor", low=0, low_open=True)
        check_number(self, "residual_decay", low=0, high=1, high_open=True)
        check_number(self, "correlated", low=0, high=1, low_open=True)
        check_number(self, "noisy", low=0)
        check_integer(self, "check_period", low=1)
        check_integer(self, "min_texels", low=1)
        levels = self.heavy_levels
        if not (
            isinstance(levels, tuple)
            and len(levels) == 3
            and all(isinstance(x, int) and not isinstance(x, bool) and x >= 0 for x in levels)
        ):
            raise ValueError(
                f"heavy_levels must be a tuple of 3 ints >= 0 (1-D, 2-D, 3-D grids), got {levels!r}"
            )
        gate = self.gate_bounds
        if not (
            isinstance(gate, tuple)
            and len(gate) == 2
            and all(isinstance(x, Real) for x in gate)
            and 0 <= gate[0] < gate[1] <= 1
        ):
            raise ValueError(
                "gate_bounds must be a tuple (low, high) of numbers with 0 <= low < high <= 1, "
                f"got {gate!r}"
            )

    # ------------------------------------------------------------------ the rule's steps

    def init(self, leaf, guide, plan, kind):
        dtype = jnp.promote_types(jnp.result_type(leaf), jnp.float32)
        previous_guide = None
        if guide is not None:
            previous_guide = self._zero_guide(guide, plan.axes)
        # Every field its own buffer: a state that holds one twice cannot be donated.
        scalar = functools.partial(jnp.zeros, [], dtype)
        direction = None if kind == "prefilter" else scalar()
        if kind != "postfilter":
            return AutoState(previous_guide, None, direction, None, None)
        # The blend's statistics sample the sub-grid only: its residual is all they read.
        residual = numerics.zeros(self._subgrid(jnp.asarray(leaf), plan.axes), dtype)
        return AutoState(previous_guide, residual, direction, scalar(), scalar())

    def prepare(self, state, plan, ctx):
        if state is None or state.residual is None or not (plan.filter_m and plan.filter_v):
            return ctx
        dtype, count = state.residual.dtype, ctx.count
        phase = self._blend_phase(state.gate, count)
        heavy = (state.correlated > 0) & plan.one_operator
        due = ((count == FIRST_NOISE_STEP) | self._check_step(count)) & plan.one_operator
        ratio = _ema_variance_ratio(jnp.asarray(ctx.b1, dtype), jnp.asarray(ctx.c1, dtype))
        lag = 1 - (1 - jnp.asarray(ctx.b1, dtype)) / jnp.asarray(ctx.c1, dtype)
        # What the step's kernels and native calls read, in one XLA kernel.
        c1, c2, inv_c1, inv_c2, ratio, due, computed, lag = numerics.one_kernel(
            (ctx.c1, ctx.c2, ctx.inv_c1, ctx.inv_c2, ratio, due, (phase != SKIP) & ~heavy, lag)
        )
        ctx = ctx._replace(c1=c1.value, c2=c2.value, inv_c1=inv_c1.value, inv_c2=inv_c2.value)
        scalars = self._blend_scalars(ctx, dtype, ratio.value)
        blends = (phase == BLEND) & ~heavy
        # The blend is taken where computed and the gate open: phase BLEND, not heavy.
        flags = StepFlags.of(inv_c1, inv_c2, computed, state.gate)
        decided = Decisions(heavy, due, computed, blends, scalars, c1, lag, flags)
        return ctx._replace(decided=decided)

    def sigma(self, guide, plan, state, ctx):
        if guide is None:  # self-guided: each field's own contrast
            return functools.partial(self._own_contrast, plan=plan), state
        previous = state.previous_guide
        sigma, kept = self._scale(guide, previous, ctx.count, plan.axes, state.direction)
        return sigma, state._replace(previous_guide=kept.astype(previous.dtype))

    def combine(self, moments, op, sigma, state, ctx):
        if state.residual is None or not (op.plan.filter_m and op.plan.filter_v):
            return super().combine(moments, op, sigma, state, ctx)
        axes = op.plan.axes
        if ctx.decided is None:  # not prepared (a rule that delegates to this one)
            ctx = self.prepare(state, op.plan, ctx)
        decided = ctx.decided
        learned = state
        if op.plan.one_operator:  # self-guided: each field's own sigma_d, never heavier
            correlated = self._check_correlation(moments, axes, state, ctx)
            learned = learned._replace(correlated=correlated)
        m_f, v_f = self._cascade(op, moments, sigma, state.correlated, decided.heavy)
        residual = update_residual(self, moments, m_f, state.residual, ctx.inv_c1, axes)
        learned = learned._replace(residual=residual)
        # The blend's statistics (at a CHECK step, the gate's check alone).
        computed = decided.computed
        weights = functools.partial(blend_weights, self, moments, residual, decided.scalars, axes)
        native_lam = None
        if runs_native(moments.m):  # zeros without any work where not computed
            lam, gate = weights(run=computed)
            native_lam = lam
            # Zeros already where not computed: the select is for XLA, whose step kernel reads
            # the upsampled weights slowly without it (docs/auto_sigma.md's decisions).
            lam = jnp.where(computed.value, lam, 0)
        else:
            lam, gate = lax.cond(
                computed.value, weights, functools.partial(_no_weights, self, moments.m, axes)
            )
        f = Filtered(
            m_f,
            v_f,
            upsample(self, lam, moments.m.shape, axes),
            cast_like(learned._replace(gate=gate), state),
            blends=decided.blends,
            subgrid_lam=native_lam,
        )
        return None, (lambda: f,)

    def _cascade(self, op, moments, sigma, correlated, heavy):
        """``(B m, B v)`` at ``sigma``; where the noise is correlated (``heavy``, a traced
        bool: the stored ``correlated`` > 0), at ``sigma`` times :attr:`heavy_factor` and with
        :attr:`heavy_levels` more levels after the plan's F."""
        fields = (moments.m, moments.v)
        if not op.plan.one_operator:
            return op.apply(fields, sigma)
        extra = self.heavy_levels[len(op.plan.axes) - 1]
        if runs_native(moments.m) and isinstance(op, CrossGuided):
            # One native call that reads the stored flag: no conditional, no select of sigma_d.
            deeper = Deeper(extra, self.heavy_factor, numerics.Entry.of(correlated))
            return op.apply_deeper(fields, sigma, deeper)
        sigma = jnp.where(heavy, sigma * self.heavy_factor, sigma)
        if not extra:
            return op.apply(fields, sigma)
        levels = op.plan.levels
        out = op.apply(fields, sigma)
        more = lambda: op.apply(out, sigma, levels=levels + extra, first_level=levels)
        return lax.cond(heavy, more, lambda: out)

    def step_sample(self, plan):
        return functools.partial(self._subgrid, axes=plan.axes)

    def read_step(self, step, plan):
        """The step's direction (:attr:`AutoState.direction`): its mean texel norm at the
        sub-grid. Where the statistics run natively, one FFI call computes the step there from
        its parts (:func:`~optax_bilateral._src.filter.local.step_norm`), with no XLA kernel for
        the step at the sub-grid; else the step computed there and its mean norm."""
        f, decided = step.filtered, step.ctx.decided
        if decided is None:  # not prepared (a rule that delegates to this one)
            return self._direction(step, plan)
        native = (
            f.subgrid_lam is not None  # the blend ran natively (combine): the statistics do
            and not step.uniform
            and step.given.dtype == step.m.dtype == f.m.dtype  # the step's dtype: given's
            and step.given.shape == step.m.shape
            and all(isinstance(x, Real) for x in (step.eps, step.eps_root))
        )
        if not native:
            return self._direction(step, plan)
        where = _SubgridStep(
            plan.axes, self._stride(step.m.shape, plan.axes), float(step.eps), float(step.eps_root)
        )
        reference = functools.partial(_step_norm_reference, where=where)
        how = StepCall(*where, step.drop_zero, reference)
        parts = (step.m, step.v, f.m, f.v, f.subgrid_lam, step.observed)
        return step_norm(parts, step.given, decided.flags, how)

    def _direction(self, step, plan):
        """:meth:`read_step` from the step computed at the sub-grid (on the native kernel the
        mean in one FFI call: an XLA reduction and its scale would be two kernels)."""
        return texel_distance_mean(step.at(self.step_sample(plan)), None, plan.axes, 1)

    def after_step(self, direction, state, plan):
        if state is None or state.direction is None:
            return state
        return state._replace(direction=direction.astype(state.direction.dtype))

    # ------------------------------------------------------------------ the parts

    def _own_contrast(self, field, plan):
        guide = log_transform(field) if plan.log_guide else field
        return self._contrast(guide, plan.axes)

    def _contrast(self, guide, axes, run: jax.Array | bool | numerics.Entry = True, otherwise=None):
        """:attr:`contrast_factor` times the guide's mean distance from its local average (one
        low-pass level of the filter): the scale of its texel-to-texel variation; over the
        sub-grid of a large leaf (:meth:`_stride`; the local averages computed there only, so
        a large leaf's first step holds no full-size temporaries). With ``otherwise`` (an
        :class:`~optax_bilateral._src.numerics.Entry`, native only): its value where ``run``
        is False."""
        guide = guide.astype(jnp.promote_types(guide.dtype, jnp.float32))
        axes = _guide_axes(guide, axes)
        stride = self._stride(guide.shape, axes)
        (local,) = local_average_subgrid((guide,), axes, stride, nan_to_num=True, run=run)
        return texel_distance_mean(
            guide, local, axes, stride, run, otherwise=otherwise, scale=self.contrast_factor
        )

    def _check_correlation(self, moments, axes, state, ctx):
        """The new :attr:`AutoState.correlated`: :meth:`_correlated_noise` where it is due
        (:class:`Decisions`: the second step, the first with a noise estimate, and every
        ``check_period``-th), else the stored one."""
        m, due = moments.m, ctx.decided.due
        stored = state.correlated.astype(m.dtype)
        if runs_native(m) and any(m.shape[a] > 1 for a in axes):
            # One native call tests where due and passes the stored answer on elsewhere.
            g, m, limit, stride = self._noise_inputs(moments, axes)
            test = NoiseTest(
                self.correlated, self.noisy, ctx.decided.lag, numerics.Entry.of(stored)
            )
            # The gradient as given: the call makes the mask where it reads (no mask kernel).
            observed = (
                moments.observed if moments.given is None else FromGradient(moments.drop_zero)
            )
            return correlated_noise(g, m, observed, ctx.decided.c1, axes, stride, due, limit, test)

        def check():
            return self._correlated_noise(moments, axes, ctx, run=due).astype(m.dtype)

        return lax.cond(due.value, check, lambda: stored)

    # ------------------------------------------------------------------ statistics

    def _stride(self, shape: tuple[int, ...], axes: tuple[int, ...]) -> int:
        """The sub-grid's stride along every spatial axis: the largest power of two that
        leaves at least ``min_texels`` texels (1 for a leaf with fewer)."""
        s = 1
        while math.prod(-(-shape[a] // (2 * s)) for a in axes) >= self.min_texels:
            s *= 2
        return s

    def _subgrid(self, x: jax.Array, axes: tuple[int, ...]) -> jax.Array:
        """Every ``stride``-th texel of ``x`` along each of its spatial ``axes``."""
        return every(x, axes, self._stride(x.shape, axes))

    def _kept_guide(self, guide: jax.Array, axes: tuple[int, ...]) -> jax.Array:
        """What :attr:`AutoState.previous_guide` keeps of a guide: its sub-grid."""
        return self._subgrid(guide, _guide_axes(guide, axes))

    def _zero_guide(self, guide: jax.Array, axes: tuple[int, ...]) -> jax.Array:
        """Zeros shaped (and sharded) like :meth:`_kept_guide`: the first ``previous_guide``."""
        return numerics.zeros(self._kept_guide(jnp.asarray(guide), axes))

    def _scale(self, guide, previous, count, axes, direction=None):
        """``(sigma_d, kept)``: the leaf's sigma_d at step ``count`` (1 = first) from its guide
        and the ``previous`` one's sub-grid (:attr:`AutoState.previous_guide`), and this
        guide's sub-grid (:meth:`_kept_guide`, read by the same native call as the step);
        ``direction`` (a postfilter's :attr:`AutoState.direction`) or None for the
        prefilter's and ``"sure"``'s step scale."""
        guide = guide.astype(jnp.promote_types(guide.dtype, jnp.float32))
        guide_axes = _guide_axes(guide, axes)
        stride = self._stride(guide.shape, guide_axes)
        previous = previous.astype(guide.dtype)
        step, kept = texel_distance_mean(guide, previous, guide_axes, stride, keep=True)
        # Only the first step (or a guide at rest) needs the contrast. (Written as at rest,
        # not as moved: the native contrast's `run` reads the same value as the select.)
        at_rest = (count <= 1) | ~(step > 0)
        if direction is None:
            scale = self.step_factor * step
        else:
            channels = math.prod(n for a, n in enumerate(guide.shape) if a not in guide_axes)
            rate = step / jnp.where(direction > 0, direction, 1).astype(step.dtype)
            scale = self.rate_factor * math.sqrt(channels) * rate
            at_rest = at_rest | ~(direction > 0)
        if runs_native(guide):  # the contrast's native call chooses: no select kernel after it
            at_rest, scale = numerics.one_kernel((at_rest, scale))
            return self._contrast(guide, axes, run=at_rest, otherwise=scale), kept
        contrast = lambda: self._contrast(guide, axes).astype(step.dtype)
        return lax.cond(at_rest, contrast, lambda: scale), kept

    def _correlated_noise(self, moments, axes, ctx, run: numerics.Entry) -> jax.Array:
        """Whether the leaf's gradient noise is spatially correlated: the lag-1 correlation
        between neighbours of ``z = g - m_hat`` (``m_hat = m / c1``, the updated first moment
        bias-corrected), averaged over the spatial ``axes``, is at least ``correlated``, and
        ``z`` is noise: ``z = (1 - (1 - b1) / c1) (g - m_hat_{t-1})``, whose energy is at
        least ``noisy`` times ``m_hat``'s. Sums run over the sub-grid and the observed
        entries; False at the first step or with ``b1 = 0``. ``run`` (a traced bool): the
        native sums do no work where it is False (their caller discards the answer)."""
        g, m, limit, stride = self._noise_inputs(moments, axes)
        c1 = ctx.decided.c1
        lags, (noise, signal) = correlation_sums(
            g, m, moments.observed, c1, axes, stride, run, limit
        )
        if not lags.shape[0]:
            return jnp.zeros([], bool)
        s00, s11, s01 = lags[:, 0], lags[:, 1], lags[:, 2]
        den = jnp.sqrt(s00 * s11)
        corr = jnp.where(den > 0, s01 / jnp.where(den > 0, den, 1), 0)
        lag = ctx.decided.lag.value.astype(m.dtype)
        return (jnp.mean(corr) >= self.correlated) & (noise > self.noisy * lag * lag * signal)

    def _noise_inputs(self, moments, axes):
        """``(g, m, limit, stride)`` for the correlated-noise test: the gradient as given
        where the sums run natively (they mask and clip it where they read it: the observed
        gradient would be a full-size temporary for them alone), in at least float32."""
        g, m, limit = moments.g, moments.m, math.inf
        if moments.given is not None and runs_native(m):
            g, limit = moments.given, moments.limit
        dtype = jnp.promote_types(m.dtype, jnp.float32)
        return g.astype(dtype), m.astype(dtype), limit, self._stride(g.shape, axes)

    def _blend_scalars(self, ctx: StepContext, dtype, ratio=None) -> jax.Array:
        """The blend's scalars at this step, in ``dtype``: ``c1``, ``c2``; ``k``, the noise of
        ``m_hat`` per unit of ``v_hat - m_hat^2`` (eq. 24); the residual EMA's variance
        ratio; the factor ``(1 + b1 decay) / (1 - b1 decay)`` (``m_hat`` correlates) as its
        two parts; the residual's bias correction ``1 - decay^t``; 1 where the noise can be
        told from the signal, else 0. ``ratio``: :func:`noise_ratio`'s, if computed already."""
        b1 = jnp.asarray(ctx.b1, dtype)
        c1, c2 = jnp.asarray(ctx.c1, dtype), jnp.asarray(ctx.c2, dtype)
        decay = jnp.asarray(self.residual_decay, dtype)
        bias = 1 - decay ** ctx.count.astype(dtype)
        ratio, usable = noise_ratio(b1, c1, ctx.count, ratio)
        k = jnp.where(usable, ratio / jnp.maximum(1 - ratio, MEMORY_EPS), 0)
        ema = _ema_variance_ratio(decay, bias)
        parts = [c1, c2, k, ema, 1 + b1 * decay, 1 - b1 * decay, bias, usable]
        return jnp.stack([jnp.asarray(x).astype(dtype) for x in parts])

    def _blend_weight(self, m, v, residual, scalars, axes):
        """The blend's weight of the unfiltered moments per entry of the sub-grid, before the
        gate, from ``m``, ``v`` and the residual there and :meth:`_blend_scalars`."""
        c1, c2, k, ema, corr_num, corr_den, bias, usable = scalars
        residual_hat = residual / bias
        # Noise of m_hat from v_hat - m_hat^2 (eq. 24), then of the residual's EMA.
        noise = jnp.maximum(v / c2 - (m / c1) ** 2, 0) * k
        residual_noise = noise * ema
        residual_noise = residual_noise * corr_num / corr_den  # m_hat correlates
        floor, signal = local_average_subgrid((residual_noise, residual_hat**2), axes, 1)
        lam = 1 - floor / (self.gain * jnp.where(signal > 0, signal, 1))
        return jnp.where((usable > 0) & (signal > 0), jnp.clip(lam, 0, 1), 0) ** self.power

    def _gate(self, lam: jax.Array) -> jax.Array:
        low, high = self.gate_bounds
        return jnp.clip((jnp.mean(lam) - low) / (high - low), 0, 1)

    def _check_step(self, count: jax.Array) -> jax.Array:
        """Whether ``count`` is a multiple of :attr:`check_period`: ``lax.rem``, the truncated
        remainder, is 0 exactly where Python's floored ``%`` is, in one operation, not the
        dozen of ``jnp.remainder``'s sign corrections."""
        return lax.rem(count, jnp.asarray(self.check_period, count.dtype)) == 0

    def _blend_phase(self, gate: jax.Array, count: jax.Array) -> jax.Array:
        """What this step computes of the blend: ``BLEND`` (its statistics and the blend) if
        the gate was open at the last step; else ``CHECK`` (the gate alone,
        :func:`blend_weights`) at a multiple of ``check_period``; else ``SKIP`` (nothing)."""
        check = jnp.where(self._check_step(count), CHECK, SKIP)
        return jnp.where(gate > 0, BLEND, check).astype(jnp.int32)


# ---------------------------------------------------------------------- the blend (auto, sure)


def update_residual(
    rule: Auto, moments: Moments, bm: jax.Array, residual, inv_c1, axes
) -> jax.Array:
    """The residual's EMA with this step's ``m_hat - B m_hat`` (``bm``: ``B m``; ``inv_c1``:
    ``1 / c1``, the step's) on the sub-grid (:attr:`AutoState.residual`), kept where the
    entry is not observed."""
    m = moments.m
    sub = lambda x: rule._subgrid(x, axes)
    decay = jnp.asarray(rule.residual_decay, m.dtype)
    residual = residual.astype(m.dtype)
    # The reciprocal as given: left to XLA, m / c1 is a product whose factor depends on the
    # program around it (and may be a kernel of its own).
    scale = jnp.asarray(inv_c1, m.dtype) * (1 - decay)
    new = decay * residual + sub(m - bm) * scale
    return jnp.where(sub(moments.observed), new, residual)


def blend_weights(
    rule: Auto, moments: Moments, residual, scalars, axes, run: jax.Array | bool = True
):
    """``(lam, gate)``: the blend's weight of the unfiltered moments (the gate applied) at
    every entry of the sub-grid (every entry on a leaf of at most ``min_texels`` texels;
    :func:`upsample` spreads it over the leaf), and how far the leaf's blend is open (a
    scalar in [0, 1], ``gate``).

    ``moments.m, moments.v`` are the moments before bias correction (``ctx.c1``, ``ctx.c2``);
    ``residual`` is the residual's EMA with this step's (:func:`update_residual`), on the
    sub-grid; ``scalars`` the step's (:meth:`Auto._blend_scalars`). The weight is a smooth
    field, which a large leaf's sub-grid samples finely enough: every statistic is read there,
    and its local averages are the B-spline's taps between the sub-grid's neighbours. Where
    the filter runs on the native kernel, one FFI call computes all of it
    (:func:`_blend_reference` is its JAX form and derivative), and nothing where ``run`` (a
    traced bool) is False: zeros, which the caller discards.
    """
    m = moments.m
    stride = rule._stride(m.shape, axes)
    low, high = rule.gate_bounds
    constants = (rule.gain, rule.power, low, high - low)
    reference = functools.partial(_blend_reference, rule, axes=tuple(axes), stride=stride)
    return subgrid_blend(m, moments.v, residual, scalars, axes, stride, constants, reference, run)


def _blend_reference(rule: Auto, m, v, residual, scalars, *, axes, stride):
    """:func:`blend_weights` in JAX, from the leaf's ``m``, ``v``."""
    m, v = every(m, axes, stride), every(v, axes, stride)
    lam = rule._blend_weight(m, v, residual, scalars, axes)
    gate = rule._gate(lam)
    return lam * gate, gate


class _SubgridStep(NamedTuple):
    """Where :func:`_step_norm_reference` computes the step, and Adam's ``eps``, ``eps_root``."""

    axes: tuple[int, ...]
    stride: int
    eps: float
    eps_root: float


def _step_norm_reference(m, v, bm, bv, lam, observed, flags, where: _SubgridStep):
    """:meth:`Auto.read_step`'s native norm in JAX (its derivative): the step at the
    sub-grid, as the postfilter computes it there (:func:`blend`,
    :func:`~optax_bilateral._src.numerics.masked_step`), and its mean texel norm."""
    at = functools.partial(every, axes=where.axes, s=where.stride)
    blends = flags.blends
    lam = None if lam is None else jnp.where(flags.computed.value, lam, 0)
    m_t, v_t = blend(lam, at(m), at(bm), blends), blend(lam, at(v), at(bv), blends)
    inv_c1, inv_c2 = flags.inv_c1.value, flags.inv_c2.value
    d = numerics.masked_step(m_t, v_t, inv_c1, inv_c2, where.eps, where.eps_root, at(observed))
    return texel_distance_mean(d, None, where.axes, 1)


def _no_weights(rule: Auto, m: jax.Array, axes) -> tuple[jax.Array, jax.Array]:
    """:func:`blend_weights`' zeros, at a step that computes neither the gate nor the blend."""
    s = rule._stride(m.shape, axes)
    shape = tuple((n - 1) // s + 1 if a in axes else n for a, n in enumerate(m.shape))
    return jnp.zeros(shape, m.dtype), jnp.zeros([], m.dtype)


def upsample(rule: Auto, lam: jax.Array, shape: tuple[int, ...], axes) -> jax.Array:
    """The sub-grid's ``lam`` (:func:`blend_weights`) over the whole leaf of ``shape``: each
    entry repeated over the ``stride`` x ... block it samples (fused into the step)."""
    s = rule._stride(shape, axes)
    for a in axes if s > 1 else ():
        lam = lax.slice_in_dim(jnp.repeat(lam, s, axis=a), 0, shape[a], axis=a)
    return lam


# ---------------------------------------------------------------------- shared statistics


def _guide_axes(guide: jax.Array, axes: tuple[int, ...]) -> tuple[int, ...]:
    """The spatial axes of ``guide``: ``axes`` for a leaf-shaped guide, all for a grid-only one."""
    return tuple(range(guide.ndim)) if guide.ndim == len(axes) else axes


def _ema_variance_ratio(b: jax.Array, c: jax.Array) -> jax.Array:
    """Var of a bias-corrected EMA (decay ``b``, ``c = 1 - b^t``) per unit sample variance:
    ``(1-b)(1-b^2t) / ((1+b)(1-b^t)^2)``, with ``1 - b^2t = c (2 - c)``."""
    return (1 - b) * (2 - c) / ((1 + b) * c)


def noise_ratio(
    b1: jax.Array, c1: jax.Array, count: jax.Array, ratio=None
) -> tuple[jax.Array, jax.Array]:
    """``(rho, usable)``: Var of ``m_hat`` per unit gradient variance (``ratio``, if computed
    already), and whether the noise can be told from the signal (the step has memory:
    ``t > 1``, ``b1 > 0``)."""
    ratio = _ema_variance_ratio(b1, c1) if ratio is None else ratio
    return ratio, (count > 1) & (ratio < 1 - MEMORY_EPS)


def _either(pred, on_true, on_false, *, both: bool):
    """``on_true()`` where ``pred``, else ``on_false()``. ``both``: both computed and one
    selected, no ``lax.cond`` (the native statistics read a sub-grid in microseconds; a
    conditional costs XLA kernels to compile and copies of the full-size fields it passes
    into its branches); else a ``lax.cond`` (the JAX forms' slices cost full-size passes)."""
    if not both:
        return lax.cond(pred, on_true, on_false)
    return jax.tree.map(lambda a, b: jnp.where(pred, a, b), on_true(), on_false())
