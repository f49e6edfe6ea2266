"""How a leaf chooses its ``sigma_d``: the :class:`SigmaRule` interface.

A rule is a small frozen object. The per-leaf step (:mod:`optax_bilateral._src.optimizer.step`)
asks it,
in this order, for

* ``init``: the leaf's state (a ``NamedTuple`` of arrays the rule owns, or None);
* ``prepare`` (a postfilter): what the step decides from the state and the count alone,
  before it reads the leaf, in the step's context;
* ``sigma``: this step's ``sigma_d`` (and the state with what it learned from the guide);
* ``prefilter`` (a prefilter) or ``combine`` (a postfilter): the filtered gradient, or the
  ways this step may filter the moments (:class:`Filtered`: ``B m``, ``B v``, the weight
  ``lam`` of a per-entry blend with the unfiltered ones, :func:`blend`) and which one it
  takes; the step compiles each way with its own bounded step (so the filter's last pass
  fuses into it) and runs the one chosen;
* ``read_step`` and ``after_step``: what the rule reads of the step (by default the step at
  the entries ``step_sample`` selects, computed there) and the state with what it taught (a
  postfilter).

Two declarations are read once, when a transform is built: ``default_levels`` (the leaf's
F when the transform's ``levels`` is None) and ``check`` (whether the rule can run in a
transform with these settings, a :class:`Setting`).

Three rules exist, each in its own module with its state and its constants: :class:`Fixed`
(a number, :mod:`~optax_bilateral._src.rules.fixed`), :class:`~optax_bilateral._src.auto.Auto`
(``sigma_d="auto"``, the default) and :class:`~optax_bilateral._src.sure.Sure`
(``sigma_d="sure"``). A rule's tunables are its fields, hashable, so that another setting is
another object (and another compiled step), never a module global. A new rule subclasses
:class:`SigmaRule` and is passed as ``sigma_d``; docs/design.md says where it plugs in.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any, Literal, NamedTuple

import jax
import jax.numpy as jnp

from optax_bilateral._src.filter import operators

# Which transform a leaf's state belongs to: what it can learn from.
Kind = Literal["prefilter", "postfilter", "memoryless"]


class Setting(NamedTuple):
    """What a transform tells each leaf's rule when it is built (:meth:`SigmaRule.check`)."""

    kind: Kind  # the transform: "prefilter", "postfilter", or "memoryless" (b1 = b2 = 0)
    self_guided: bool  # guide="self": m and v are filtered with their own weights
    filters_both: bool  # one operator filters both m and v (filter_m and filter_v)


class StepContext(NamedTuple):
    """What a leaf's step knows before it reads the leaf: the step count (1 at the first
    update) and, in a postfilter, the first moment's decay ``b1``, the bias corrections
    ``1 - b^t`` and their reciprocals, and what the rule decided from its state and the
    count alone (:meth:`SigmaRule.prepare`; None: nothing)."""

    count: jax.Array
    b1: Any = None
    c1: Any = None
    c2: Any = None
    inv_c1: Any = None
    inv_c2: Any = None
    decided: Any = None


class Moments(NamedTuple):
    """A postfilter leaf's fields at this step, in the arithmetic dtype: the updated moments
    (kept at unobserved entries), the observed gradient (0 where unobserved, clipped to
    ``+-limit``), and the observed entries (broadcastable against the leaf). ``given`` is the
    gradient as the leaf received it (None: read ``g``), for a native statistic that reads a
    few entries: it applies the mask and the clip where it reads, so XLA need not write ``g``
    out in full for it; ``drop_zero`` (``mask_unobserved``) says how ``observed`` follows from
    it, for a statistic that makes the mask where it reads."""

    m: jax.Array
    v: jax.Array
    g: jax.Array
    observed: jax.Array
    given: jax.Array | None = None
    limit: float = math.inf
    drop_zero: bool = False


class Filtered(NamedTuple):
    """One way a postfilter step filters the moments: ``B m``, ``B v``, the blend's weight of
    the unfiltered moments (an array like ``m``, or None for no blend; :func:`blend`), the
    rule's state after it, and where the blend is taken (a traced bool: where False, ``B m``
    and ``B v`` unblended; None: wherever ``lam`` is given). One way whose blend is taken or
    not costs the step one kernel where two ways in a switch cost two, and each way's output
    a buffer of its own."""

    m: jax.Array
    v: jax.Array
    lam: jax.Array | None
    state: Any
    blends: jax.Array | None = None
    # lam before it was spread over the leaf, at the rule's sub-grid, where a native statistic
    # of the rule reads it (SigmaRule.read_step); None: not given.
    subgrid_lam: jax.Array | None = None


class Step(NamedTuple):
    """A postfilter leaf's step before its learning rate, for :meth:`SigmaRule.read_step`:
    ``d`` (the whole step, computed where a rule reads it; ``whole`` computes it), ``at`` (the
    step at the entries a select function picks, computed there: the whole one then has the
    learning rate for its one reader, after the read), and the parts the
    step divides, for a rule that computes what it reads from them in one native call: the
    updated moments, the way taken (:class:`Filtered`), the observed entries (broadcastable
    against the leaf) and their sources (the gradient as the leaf received it; whether an
    all-zero texel is unobserved, ``mask_unobserved``), Adam's ``eps`` and ``eps_root``, the
    step's context, and whether the second moment is one for the leaf
    (``second_moment="uniform"``)."""

    whole: Callable[[], jax.Array]
    at: Callable[[Callable[[jax.Array], jax.Array]], jax.Array]
    m: jax.Array
    v: jax.Array
    filtered: Filtered
    observed: jax.Array
    given: jax.Array
    drop_zero: bool
    eps: Any
    eps_root: Any
    ctx: StepContext
    uniform: bool

    @property
    def d(self) -> jax.Array:
        """The whole step."""
        return self.whole()


class SigmaRule:
    """The interface of a ``sigma_d`` rule; the defaults are those of a rule that keeps no
    state and filters both moments with one operator.

    A rule is a frozen dataclass, registered as a static pytree (or a pytree, if it holds
    an array), and passed as ``sigma_d``; docs/design.md says where its methods are called.

    Example::

        >>> import dataclasses, jax, jax.numpy as jnp, optax_bilateral as ob
        >>> @jax.tree_util.register_static
        ... @dataclasses.dataclass(frozen=True)
        ... class Halved(ob.SigmaRule):
        ...     value: float = 0.2
        ...     def sigma(self, guide, plan, state, ctx):
        ...         return self.value / 2, state
        >>> params = jnp.full((8, 8, 3), 0.5)
        >>> opt = ob.postfilter(sigma_d=Halved(0.2))      # the same as sigma_d=0.1
        >>> step, _ = opt.update(jnp.ones_like(params), opt.init(params), params)
    """

    def default_levels(self) -> int | None:
        """The leaf's F when the transform's ``levels`` is None; None: the transforms'
        ``DEFAULT_LEVELS``."""
        return None

    def check(self, setting: Setting) -> None:
        """Raises ``ValueError``, saying why, if the rule cannot run in a transform with this
        ``setting``; read once, when the transform is built."""
        del setting

    def init(self, leaf: jax.Array, guide: jax.Array | None, plan, kind: Kind) -> Any:
        """The leaf's state (``guide``: its guide at ``init``, None if self-guided)."""
        del leaf, guide, plan, kind
        return None

    def prepare(self, state, plan, ctx: StepContext) -> StepContext:
        """A postfilter step's context (``ctx``) with what the rule decides from its
        ``state`` and the step count alone, before the step reads the leaf: ``ctx`` itself
        by default. A rule that decides several such scalars computes them, with the bias
        corrections, in one XLA kernel (:func:`~optax_bilateral._src.numerics.one_kernel`)."""
        del state, plan
        return ctx

    def sigma(self, guide, plan, state, ctx: StepContext) -> tuple[operators.Sigma, Any]:
        """This step's ``sigma_d`` (``guide``: the leaf's guide, None if self-guided), and the
        state with what the rule learned from the guide."""
        raise NotImplementedError

    def prefilter(self, g, op, sigma, state, ctx: StepContext) -> tuple[jax.Array, Any]:
        """``A g``, and the new state."""
        del ctx
        return op.apply(g, sigma), state

    def combine(self, moments: Moments, op, sigma, state, ctx: StepContext):
        """``(index, ways)``: the ways this step may filter the moments (functions of no
        argument returning a :class:`Filtered`, traced inside a ``lax.switch`` when there are
        several) and the traced index of the one to take (None with one way). The step
        divides ``blend(lam, m, B m)`` by the root of ``blend(lam, v, B v)`` in each."""
        del ctx

        def filtered():
            return Filtered(*operators.moments(op, moments.m, moments.v, sigma), None, state)

        return None, (filtered,)

    def step_sample(self, plan) -> Callable[[jax.Array], jax.Array] | None:
        """The entries of the step that :meth:`read_step` reads by default: a function that
        selects them from any leaf-shaped (or broadcastable) array, or None for the whole step.
        The step is then computed there a second time, so the whole one is read by the
        learning rate alone."""
        del plan
        return None

    def read_step(self, step: Step, plan) -> Any:
        """What :meth:`after_step` reads of the ``step``: the step at :meth:`step_sample`'s
        entries (the whole step where it gives None)."""
        sample = self.step_sample(plan)
        return step.d if sample is None else step.at(sample)

    def after_step(self, d: Any, state, plan) -> Any:
        """The state with what the step taught: ``d``, what :meth:`read_step` read of it (by
        default its direction, before the learning rate, at :meth:`step_sample`'s
        entries)."""
        del d, plan
        return state

    def guard(self, out: jax.Array, sigma) -> jax.Array:
        """The leaf's output, NaN where ``sigma`` is invalid (a traced value cannot raise)."""
        del sigma
        return out


def blend(
    lam: jax.Array | None, x: jax.Array, bx: jax.Array, blends: jax.Array | None = None
) -> jax.Array:
    """``lam x + (1 - lam) B x`` (``B x`` where ``lam`` is None, or where ``blends`` is False):
    with one ``lam`` for ``m`` and ``v``, one non-negative, row-stochastic operator for both
    (supplement §1.3)."""
    if lam is None:
        return bx
    out = lam * x + (1 - lam) * bx
    return out if blends is None else jnp.where(blends, out, bx)


def cast_like(state: Any, like: Any) -> Any:
    """``state``, a rule's state ``NamedTuple`` with fields computed in the moments' arithmetic
    dtype, with every field cast to the dtype of the same field of ``like`` (the state the
    step received), so that a rule's state keeps its dtypes from step to step; None stays."""
    fields = state._asdict().items()
    return state._replace(
        **{k: x.astype(getattr(like, k).dtype) for k, x in fields if x is not None}
    )
