"""A leaf's filter for one step: the operator ``A_t`` or ``B_t`` of supplement eqs. 1, 6, 8.

A :class:`FilterPlan` holds what is fixed for a leaf (its axes, F, separable or full, what
guides it), decided once when the transform resolves its settings; :func:`operator` builds
this step's operator from it, the guide and the observed texels. Two operators exist:

* :class:`CrossGuided`, the paper's method: one set of weights from the guide (the current
  parameters, or what a callable made of them) for every field it filters, so that ``B m``
  and ``B v`` come from one non-negative, row-stochastic operator (supplement §1.3).
* :class:`SelfGuided`, the paper's *bilateral* baseline (the authors' ``cross_term_off``):
  each field guides itself, every level by its own partially filtered input.

Unobserved texels (a non-finite gradient, or all-zero ones with ``mask_unobserved``) are left
out of every sum. A cross-guided operator does it with a NaN guide there (a non-finite guide
weighs 0), which costs the kernel nothing; its outputs at those texels are then their own
inputs, which every caller discards. Where the guide cannot hold NaN (an integer guide, or
one not laid out on the grid) and for a self-guided operator, the filter's ``mask`` does it.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any, NamedTuple, Protocol

import jax
import jax.numpy as jnp
from jax.experimental.layout import Layout, with_layout_constraint

from optax_bilateral._src.filter import layout, sharded
from optax_bilateral._src.filter.bilateral import Deeper
from optax_bilateral._src.filter.front import atrous_bilateral, atrous_bilateral_deeper

# A field's sigma_d: a scalar, or (a self-guided operator) a function of the field.
Sigma = Any


class FilterPlan(NamedTuple):
    """What is fixed about a leaf's filter (hashable: part of the compiled step's key)."""

    axes: tuple[int, ...]  # the spatial axes, in pass order
    levels: int  # F
    separable: bool
    self_guided: bool  # guide="self": SelfGuided, else CrossGuided
    log_guide: bool  # self-guided: log(|x| + 1e-8) of each level's input (cross: done already)
    filter_m: bool = True  # postfilter: filter m (the authors' mtfilter)
    filter_v: bool = True  # postfilter: filter v (the authors' vtfilter)

    @property
    def one_operator(self) -> bool:
        """``B m`` and ``B v`` come from one operator: what the bounded step (supplement §1.3)
        and the data-driven rules' blend need."""
        return self.filter_m and self.filter_v and not self.self_guided


class Operator(Protocol):
    """A leaf's filter at this step."""

    @property
    def plan(self) -> FilterPlan: ...

    def apply(
        self, fields: Any, sigma: Sigma, levels: int | None = None, first_level: int = 0
    ) -> Any:
        """Levels ``first_level .. levels - 1`` (default: the plan's F) of the filter of
        ``fields`` (an array or a tuple, one set of weights where the operator has one)."""
        ...


@dataclasses.dataclass(frozen=True)
class CrossGuided:
    """The cross-bilateral operator: weights from ``guide`` (NaN at unobserved texels, or
    ``mask`` where it cannot hold NaN), whose spatial axes are ``guide_axes`` (None: the
    plan's)."""

    plan: FilterPlan
    guide: jax.Array
    mask: jax.Array | None = None
    guide_axes: tuple[int, ...] | None = None

    def apply(self, fields, sigma, levels=None, first_level=0):
        return atrous_bilateral(
            fields,
            self.guide,
            sigma_d=sigma,
            levels=self.plan.levels if levels is None else levels,
            spatial_axes=self.plan.axes,
            separable=self.plan.separable,
            mask=self.mask,
            guide_axes=self.guide_axes,
            first_level=first_level,
        )

    def apply_deeper(self, fields, sigma, deeper: Deeper):
        """:meth:`apply` at the plan's F, and where ``deeper``'s flag says so its more levels
        at its larger sigma_d, decided at run time (:func:`atrous_bilateral_deeper`)."""
        return atrous_bilateral_deeper(
            fields,
            self.guide,
            deeper,
            sigma_d=sigma,
            levels=self.plan.levels,
            spatial_axes=self.plan.axes,
            separable=self.plan.separable,
            mask=self.mask,
            guide_axes=self.guide_axes,
        )


@dataclasses.dataclass(frozen=True)
class SelfGuided:
    """The bilateral operator: each field guides itself (its own weights, every level from its
    own input); ``sigma`` may be a function of the field (``sigma_d="auto"``: its contrast)."""

    plan: FilterPlan
    mask: jax.Array

    def apply(self, fields, sigma, levels=None, first_level=0):
        if not callable(sigma):  # the filter runs each field on its own
            return self._filter(fields, sigma, levels, first_level)
        many = isinstance(fields, tuple)
        out = tuple(
            self._filter(f, sigma(f), levels, first_level) for f in (fields if many else (fields,))
        )
        return out if many else out[0]

    def _filter(self, fields, sigma, levels, first_level):
        return atrous_bilateral(
            fields,
            "self",
            sigma_d=sigma,
            levels=self.plan.levels if levels is None else levels,
            spatial_axes=self.plan.axes,
            separable=self.plan.separable,
            mask=self.mask,
            log_guide=self.plan.log_guide,
            first_level=first_level,
        )


def operator(plan: FilterPlan, guide: jax.Array | None, observed: jax.Array) -> Operator:
    """This step's operator for a leaf: ``observed`` holds its texels (in ``plan.axes``
    order) whose gradient is used; ``guide`` is the leaf's guide (None if self-guided)."""
    if plan.self_guided or guide is None:
        return SelfGuided(plan, observed)
    nan_guide = nan_guide_at(guide, observed, plan.axes)
    if nan_guide is None:
        return CrossGuided(plan, jnp.asarray(guide), observed)
    if sharded.is_split(nan_guide):
        return CrossGuided(plan, nan_guide)
    # In the kernels' layout once, (G, *spatial) row-major: not again inside each branch of a
    # rule's conditional cascade, where the copy would live beside the cascade's outputs.
    axes = plan.axes if nan_guide.ndim > len(plan.axes) else tuple(range(nan_guide.ndim))
    planes = layout.guide_planes(nan_guide, axes, nan_guide.dtype, observed.shape)
    if _layout_constraint_batches():
        planes = with_layout_constraint(planes, Layout(tuple(range(planes.ndim))))
    return CrossGuided(plan, planes, guide_axes=tuple(range(1, planes.ndim)))


@functools.cache
def _layout_constraint_batches() -> bool:
    """Whether this JAX can ``vmap`` a layout constraint (0.7.0 cannot, 0.7.1 on can; without
    it the planes keep the layout XLA picks, as before the constraint)."""
    pin = lambda x: with_layout_constraint(x, Layout((0,)))
    try:
        jax.eval_shape(jax.vmap(pin), jax.ShapeDtypeStruct((1, 1), jnp.float32))
    except NotImplementedError:
        return False
    return True


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


def moments(op: Operator, m: jax.Array, v: jax.Array, sigma: Sigma) -> tuple[jax.Array, jax.Array]:
    """``(B m, B v)`` with one set of weights; each left as it is where the plan does not
    filter it (``filter_m`` / ``filter_v``: the authors' ``mtfilter`` / ``vtfilter``)."""
    plan = op.plan
    if plan.filter_m and plan.filter_v:
        return op.apply((m, v), sigma)
    if plan.filter_m:
        return op.apply(m, sigma), v
    if plan.filter_v:
        return m, op.apply(v, sigma)
    return m, v
