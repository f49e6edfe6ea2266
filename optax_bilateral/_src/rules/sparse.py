"""``sigma_d="sparse"``: ``"auto"`` for gradients that touch a few texels a step.

A far camera's texture gradient reaches the few texels its samples looked up
(:mod:`optax_bilateral._src.rules.coverage`). Filtered over a neighbourhood of untouched texels,
``B m`` falls with the share ``c`` of touched ones and ``sqrt(B v)`` with ``sqrt(c)``, so the
step shrinks by ``sqrt(c)``: the best learning rate then moves with the camera. This rule runs
``"auto"`` and divides the filtered ``B m`` by ``sqrt(c)`` (at most ``max_boost``), with ``c``
the leaf's coverage where its block is; where the touched blocks' mean coverage is below
``sparse_below``, the filter runs ``sparse_levels`` more levels (a wider reach, to gather more
touched texels). On a gradient that touches every texel (``c = 1``) it is ``"auto"``.

Measured in docs/research/camera_distance.md.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
from jax import lax

from optax_bilateral._src.filter.local import runs_native
from optax_bilateral._src.rules import coverage
from optax_bilateral._src.rules.auto import Auto
from optax_bilateral._src.rules.sigma import Filtered, Setting, SigmaRule
from optax_bilateral._src.validation import check_integer, check_number


class SparseState(NamedTuple):
    """One leaf's state for ``sigma_d="sparse"`` (in :class:`PostfilterState`, field
    ``sigma_state``).

    Attributes:
      auto: ``"auto"``'s state (:class:`AutoState`).
      coverage: the moving average of the share of untouched texels per block of
        ``block`` texels along each spatial axis, and its bias correction
        (:class:`~optax_bilateral._src.rules.coverage.CoverageState`; zeros before the first
        step).

    Example::

        >>> import jax.numpy as jnp, optax_bilateral as ob
        >>> state = ob.postfilter(sigma_d="sparse").init({"tex": jnp.ones((64, 48, 3))})
        >>> sparse = state.sigma_state["tex"]
        >>> type(sparse.auto).__name__, sparse.coverage.untouched.shape  # blocks of 8 x 8
        ('AutoState', (8, 6))
    """

    auto: Any
    coverage: coverage.CoverageState


@jax.tree_util.register_static
@dataclasses.dataclass(frozen=True)
class Sparse(SigmaRule):
    """``sigma_d="sparse"`` with its constants as fields (``"sparse"`` is ``Sparse()``, which
    :func:`optax_bilateral.sparse_sigma` builds with other values).

    Attributes:
      block: the coverage's blocks, in texels along each spatial axis.
      decay: the coverage's moving average over steps (~10 steps: two cameras in turn
        average out).
      max_boost: the most ``B m`` is multiplied by (reached at a coverage of
        ``full_coverage / max_boost^2``: one touched texel in 64 at 8 and 1).
      sparse_below: a leaf whose touched blocks' mean coverage is below this runs
        ``sparse_levels`` more levels.
      sparse_levels: the levels added on a sparse leaf.
      full_coverage: the coverage counted as full: ``B m`` is multiplied by
        ``(full_coverage / coverage)^(1/2)`` where the coverage is below it, by 1 elsewhere.
      auto: ``"auto"``'s constants.

    Example::

        >>> import jax.numpy as jnp, optax_bilateral as ob
        >>> params = jnp.full((32, 32, 3), 0.5)
        >>> grads = jnp.zeros_like(params).at[::8, ::8].set(1.0)    # 1 texel in 64 touched
        >>> opt = ob.postfilter(sigma_d="sparse")
        >>> state = opt.init(params)
        >>> step, state = opt.update(grads, state, params)
        >>> cov = state.sigma_state.coverage
        >>> print(f"{1 - float(cov.untouched.max() / cov.weight):.4f}")  # touched: 1 in 64
        0.0156
    """

    block: int = 8
    decay: float = 0.9
    max_boost: float = 8.0
    sparse_below: float = 0.25
    sparse_levels: int = 1
    full_coverage: float = 1.0
    auto: Auto = dataclasses.field(default_factory=Auto)

    def __post_init__(self):
        check_integer(self, "block", low=1)
        check_number(self, "decay", low=0, high=1, high_open=True)
        check_number(self, "max_boost", low=1)
        check_number(self, "sparse_below", low=0, high=1)
        check_integer(self, "sparse_levels", low=0)
        check_number(self, "full_coverage", low=0, high=1, low_open=True)
        if not isinstance(self.auto, Auto):
            raise TypeError(f"auto must be an auto_sigma() rule, got {self.auto!r}")

    def default_levels(self) -> int | None:
        return self.auto.default_levels()

    def check(self, setting: Setting) -> None:
        if setting.kind == "prefilter":
            raise ValueError(
                "sigma_d='sparse' corrects a postfilter's filtered moments for the texels a "
                "step's gradient did not touch; a prefilter's output is normalised by Adam "
                "afterwards, which cancels that shrinkage: use 'auto' there"
            )
        self.auto.check(setting)

    def init(self, leaf, guide, plan, kind):
        auto = self.auto.init(leaf, guide, plan, kind)
        return SparseState(auto, coverage.init(jnp.shape(leaf), plan.axes, self.block))

    def prepare(self, state, plan, ctx):
        return self.auto.prepare(state.auto, plan, ctx)

    def sigma(self, guide, plan, state, ctx):
        sigma, auto = self.auto.sigma(guide, plan, state.auto, ctx)
        return sigma, state._replace(auto=auto)

    def combine(self, moments, op, sigma, state, ctx):
        axes = op.plan.axes
        touched = coverage.touched(moments.g, moments.observed, axes)
        cov = coverage.update(state.coverage, touched, block=self.block, decay=self.decay)
        floor = 1.0 / (self.max_boost * self.max_boost)
        boost = lax.rsqrt(jnp.clip(cov.field / self.full_coverage, floor, 1.0))
        boost = coverage.expand(boost, moments.m.shape, axes, self.block)
        if self.sparse_levels:  # a wider filter on a sparse leaf: one more cond, no more ways
            op = _Widened(op, self.sparse_levels, cov.mean < self.sparse_below)
        index, ways = self.auto.combine(moments, op, sigma, state.auto, ctx)
        wrap = functools.partial(_boosted, boost=boost, covered=cov.state)
        return index, tuple(functools.partial(wrap, w) for w in ways)

    def step_sample(self, plan):
        return self.auto.step_sample(plan)

    def read_step(self, step, plan):
        # From the step at the sub-grid: B m is boosted there, which a native norm from the
        # parts would read as a full-size array of its own.
        return self.auto._direction(step, plan)

    def after_step(self, d, state, plan):
        return state._replace(auto=self.auto.after_step(d, state.auto, plan))


@dataclasses.dataclass(frozen=True)
class _Widened:
    """``op`` whose full cascade runs ``extra`` more levels where ``wide`` (a traced bool): one
    ``lax.cond`` around the extra levels (as ``"auto"``'s heavy levels), far cheaper than a
    second set of the step's ways in its switch (the commit that made it measured).
    ``"auto"``'s heavy continuation then restarts at level F of a widened cascade: both, on
    a leaf that is sparse and correlated at once."""

    op: Any
    extra: int
    wide: jax.Array

    @property
    def plan(self):
        return self.op.plan

    def apply(self, fields, sigma, levels=None, first_level=0):
        f = self.op.plan.levels
        whole = levels is None or (first_level == 0 and levels > f)
        if not whole:  # a part of the cascade that the caller chose
            return self.op.apply(fields, sigma, levels, first_level)
        if runs_native(jax.tree.leaves(fields)[0]):
            # Each branch its own cascade from the fields (the native kernel's F + extra levels
            # in one call equal F levels continued, to the bit): neither passes its input
            # through, so XLA gives the kernel's outputs to the conditional's without copies.
            def wider():
                out = self.op.apply(fields, sigma, levels=f + self.extra)
                return out if levels is None else self.op.apply(out, sigma, levels, first_level=f)

            return lax.cond(self.wide, wider, lambda: self.op.apply(fields, sigma, levels))
        out = self.op.apply(fields, sigma)
        more = lambda: self.op.apply(out, sigma, levels=f + self.extra, first_level=f)
        out = lax.cond(self.wide, more, lambda: out)
        if levels is None:
            return out
        # The whole cascade and more ("auto"'s heavy way on the native kernel): the widened
        # cascade, continued from level F, as that way's continuation does elsewhere.
        return self.op.apply(out, sigma, levels=levels, first_level=f)


def _boosted(way, *, boost, covered) -> Filtered:
    """``way``'s :class:`Filtered` with ``B m`` multiplied by ``boost`` and the coverage's new
    state in the rule's."""
    f = way()
    return f._replace(m=f.m * boost.astype(f.m.dtype), state=SparseState(f.state, covered))
