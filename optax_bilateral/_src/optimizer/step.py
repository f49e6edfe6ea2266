"""One leaf's step, read top to bottom: observe, moments, operator, the sigma_d rule, step.

:func:`postfilter_leaf` (supplement eqs. 2, 4, 6, 8, 10) and :func:`prefilter_leaf` (eq. 1)
are what :func:`~optax_bilateral.postfilter` and :func:`~optax_bilateral.prefilter` run for
every parameter leaf:

    observe      which entries have a finite (with mask_unobserved: non-zero) gradient
    moments      Adam's m, v from the clipped gradient; unobserved entries keep theirs
    operator     this step's filter B_t (operators.operator): its guide, its mask
    rule         sigma_d (rule.sigma), and the ways to filter the moments (rule.combine)
    step         the bias-corrected, bounded step of the (blended) filtered moments, one per
                 way, in a lax.switch when the rule offers several; 0 where unobserved

Everything that is fixed for a leaf (its filter, dtypes, clip limit) is a :class:`LeafPlan`,
resolved once when the transform traces its update; its sigma_d rule and Adam's
hyperparameters are pytrees whose Python numbers stay constants of the program. Both steps
are compiled once per plan and shape (also when the update runs eagerly), and inlined into
an enclosing ``jit``.
"""

from __future__ import annotations

import dataclasses
import functools
from numbers import Real
from typing import Any, NamedTuple, cast

import jax
import jax.numpy as jnp
from jax import lax

from optax_bilateral._src import numerics
from optax_bilateral._src.filter import layout, operators
from optax_bilateral._src.rules.sigma import Moments, SigmaRule, Step, StepContext, blend


class LeafPlan(NamedTuple):
    """What is fixed about a leaf's step (hashable: the compiled step's key)."""

    filter: operators.FilterPlan | None  # None: not filtered (Adam)
    mask_unobserved: bool  # all-zero texels are unobserved too
    limit: float  # |g| is clipped to it (moments and v = g^2 stay finite)
    compute_dtype: Any = None  # postfilter: the moments' arithmetic dtype
    uniform: bool = False  # second_moment="uniform": one second moment, the max over the leaf
    complex_view: bool = False  # a complex leaf's real view (re, im last): v = |g|^2 for both


@jax.tree_util.register_pytree_node_class
@dataclasses.dataclass(frozen=True)
class AdamHyper:
    """Adam's hyperparameters; Python numbers stay constants of the compiled step, exactly as
    written (``1 - b`` in float64), and arrays or tracers are its arguments."""

    b1: Any
    b2: Any
    eps: Any
    eps_root: Any
    one_minus_b1: Any
    one_minus_b2: Any

    @classmethod
    def of(cls, b1, b2, eps, eps_root) -> AdamHyper:
        return cls(b1, b2, eps, eps_root, numerics.one_minus(b1), numerics.one_minus(b2))

    def tree_flatten(self):
        values = dataclasses.astuple(self)
        numbers = tuple(v if isinstance(v, Real) else None for v in values)
        return tuple(v for v in values if not isinstance(v, Real)), numbers

    @classmethod
    def tree_unflatten(cls, numbers, children):
        children = iter(children)
        return cls(*(next(children) if n is None else n for n in numbers))


class Clock(NamedTuple):
    """The step count (1 at the first update) and Adam's bias corrections ``1 - b^t``."""

    count: jax.Array
    c1: jax.Array
    c2: jax.Array


class Observed(NamedTuple):
    """Which entries of a leaf's gradient this step uses."""

    texels: jax.Array | None  # per texel, in the filter's axes order (None: not filtered)
    entries: jax.Array  # broadcastable against the leaf


@functools.partial(jax.jit, static_argnames=("plan",), inline=True)
def postfilter_leaf(
    g, guide, moments, state, rule: SigmaRule, adam: AdamHyper, clock: Clock, *, plan
):
    """One leaf of :func:`~optax_bilateral.postfilter`: ``(d, (m, v) or None, state)``.

    ``moments`` is the stored ``(m, v)``, or None (memoryless); ``guide`` the leaf's guide
    (None if self-guided or not filtered); ``state`` its sigma_d rule's state.
    """
    ctx = StepContext(clock.count, adam.b1, clock.c1, clock.c2, 1 / clock.c1, 1 / clock.c2)
    if plan.filter is not None:
        ctx = rule.prepare(state, plan.filter, ctx)
    observed = observe(g, plan)
    g_obs = jnp.where(observed.entries, g, 0).astype(plan.compute_dtype)
    g_obs = jnp.clip(g_obs, -plan.limit, plan.limit)
    m, v = adam_moments(g_obs, moments, observed, adam, plan.compute_dtype, plan.complex_view)
    if plan.filter is None:
        d = bounded_step(m, v, v, observed, adam, ctx, plan.uniform).astype(g.dtype)
    else:
        op = operators.operator(plan.filter, guide, cast(jax.Array, observed.texels))
        sigma, state = rule.sigma(guide, plan.filter, state, ctx)
        fields = Moments(m, v, g_obs, observed.entries, g, plan.limit, plan.mask_unobserved)
        index, ways = rule.combine(fields, op, sigma, state, ctx)

        def finish(way):
            f = way()

            def step_at(at, f=f):  # the step at the entries `at` selects from leaf-shaped arrays
                lam = None if f.lam is None else at(f.lam)
                m_t = blend(lam, at(m), at(f.m), f.blends)
                v_t = blend(lam, at(v), at(f.v), f.blends)
                obs = Observed(None, at(observed.entries))
                d = bounded_step(m_t, v_t, at(v), obs, adam, ctx, plan.uniform)
                return rule.guard(d.astype(g.dtype), sigma)

            whole = _Once(functools.partial(step_at, _whole))
            # The rule reads the step at its own sample, computed there: the whole step then has
            # one reader, the learning rate, which XLA fuses into it (no full-size temporary).
            # With one second moment for the leaf, the sample of the whole step.
            at = (lambda select: select(whole())) if plan.uniform else step_at
            parts = (m, v, f, observed.entries, g, plan.mask_unobserved)
            step = Step(whole, at, *parts, adam.eps, adam.eps_root, ctx, plan.uniform)
            read = rule.read_step(step, plan.filter)
            if whole.value is None:  # not read: computed after the read, it may overwrite B m
                bm, bv = numerics.after((f.m, f.v), read)
                whole.value = step_at(_whole, f._replace(m=bm, v=bv))
            return whole(), rule.after_step(read, f.state, plan.filter)

        if index is None:
            d, state = finish(*ways)
        else:  # a branch each: the filter's last pass stays fused into its step
            d, state = lax.switch(index, [functools.partial(finish, w) for w in ways])
    if moments is None:
        return d, None, state
    return d, (m.astype(moments[0].dtype), v.astype(moments[1].dtype)), state


def _whole(x):
    return x


class _Once:
    """A value computed at its first call (``value``: None until then)."""

    def __init__(self, compute):
        self.compute, self.value = compute, None

    def __call__(self):
        if self.value is None:
            self.value = self.compute()
        return self.value


@functools.partial(jax.jit, static_argnames=("plan",), inline=True)
def prefilter_leaf(g, guide, state, rule: SigmaRule, count, *, plan):
    """One filtered leaf of :func:`~optax_bilateral.prefilter`: ``(A g, state)``. Unobserved
    texels pass through as they came, so that a following postfilter still sees them."""
    ctx = StepContext(count)
    observed = observe(g, plan)
    g_obs = jnp.clip(jnp.where(observed.entries, g, 0), -plan.limit, plan.limit)
    op = operators.operator(plan.filter, guide, cast(jax.Array, observed.texels))
    sigma, state = rule.sigma(guide, plan.filter, state, ctx)
    out, state = rule.prefilter(g_obs, op, sigma, state, ctx)
    return rule.guard(jnp.where(observed.entries, out, g), sigma), state


def observe(g: jax.Array, plan: LeafPlan) -> Observed:
    """The entries with a finite gradient (and, with ``mask_unobserved``, not all-zero); on a
    filtered leaf a texel counts as a whole (all its channels)."""
    if plan.filter is None:
        ok = jnp.isfinite(g)
        ok = ok & (g != 0) if plan.mask_unobserved else ok
        if plan.complex_view:  # a complex entry counts as a whole
            ok = jnp.all(ok, axis=-1, keepdims=True)
        return Observed(None, ok)
    axes = plan.filter.axes
    texels = layout.texel_mask(jnp.isfinite(g), axes)
    if plan.mask_unobserved:
        texels = texels & ~layout.texel_mask(g == 0, axes)
    return Observed(texels, layout.expand_mask(texels, g.ndim, axes))


def adam_moments(g, moments, observed: Observed, adam: AdamHyper, dtype, complex_view=False):
    """Adam's ``(m, v)`` in the arithmetic ``dtype``, kept at unobserved entries (supplement
    eqs. 2, 4); without stored moments (memoryless, supplement §1.1) ``(g, g^2)``. On a
    complex leaf's real view ``g^2`` is ``|g|^2``, the same for both parts (optax.adam's)."""
    g = g.astype(dtype)
    g2 = g * g
    if complex_view:
        g2 = jnp.broadcast_to(jnp.sum(g2, axis=-1, keepdims=True), g2.shape)
    if moments is None:
        return g, g2
    m_old, v_old = (x.astype(dtype) for x in moments)
    m = adam.one_minus_b1 * g + adam.b1 * m_old
    v = adam.one_minus_b2 * g2 + adam.b2 * v_old
    return jnp.where(observed.entries, m, m_old), jnp.where(observed.entries, v, v_old)


def bounded_step(m_f, v_f, v, observed: Observed, adam: AdamHyper, ctx: StepContext, uniform: bool):
    """``(m~ / c1) / (sqrt(v~ / c2 + eps_root) + eps)`` where observed, else 0 (eq. 10);
    ``uniform``: one second moment for the leaf, the max of ``v~`` (unobserved entries by
    the moments they keep), as Large Steps' and the Dr.Jit port's ``uniform``."""
    if uniform:
        v_f = jnp.where(observed.entries, v_f, v)
        v_f = jnp.broadcast_to(jnp.max(v_f), v_f.shape)
    return numerics.masked_step(
        m_f, v_f, ctx.inv_c1, ctx.inv_c2, adam.eps, adam.eps_root, observed.entries
    )
