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

Every leaf goes through one straight step (``_src/optimizer/step.py``: ``postfilter_leaf``,
``prefilter_leaf``); what the transform decides once per leaf (axes, F, dtypes, the sigma_d
rule) is its ``LeafPlan``.

Non-finite gradients: a texel whose gradient has a NaN or Inf in any channel is
treated as *unobserved* for that step, as ``mask_unobserved`` treats all-zero
texels: it is left out of every filter sum, its moments are kept, and its
update is 0. So one bad Monte Carlo sample cannot spread over a filter
footprint or into the optimizer state. ``scale_by_adam`` stays identical to
``optax.scale_by_adam`` and does not do this (``bilateral_adam`` therefore uses
``postfilter`` with ``levels=0`` for its unfiltered Adam path).

Numerical extremes (``postfilter``; :mod:`optax_bilateral._src.numerics` implements
them, docs/robustness.md has the full table):

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

import contextlib
import contextvars
from collections.abc import Iterator
from typing import TYPE_CHECKING, Any, Literal, NamedTuple, cast

import jax
import jax.numpy as jnp
import optax

from optax_bilateral._src import numerics
from optax_bilateral._src.filter import layout
from optax_bilateral._src.filter.operators import FilterPlan
from optax_bilateral._src.optimizer import guides, leaf_rule, leaves, prefix
from optax_bilateral._src.optimizer.step import (
    AdamHyper,
    Clock,
    LeafPlan,
    postfilter_leaf,
    prefilter_leaf,
)
from optax_bilateral._src.rules import registry as rules
from optax_bilateral._src.rules.registry import DEFAULT_SIGMA_D
from optax_bilateral._src.rules.sigma import Kind, Setting, SigmaRule
from optax_bilateral._src.validation import (
    check_bool,
    check_decay,
    check_levels,
    check_mu_dtype,
    check_nonnegative,
    check_second_moment,
    check_sigma_d,
    is_concrete,
    is_zero,
)

if TYPE_CHECKING:
    from optax_bilateral._src.optimizer.guides import GuideSetting
    from optax_bilateral._src.optimizer.leaf_rule import SpatialAxesSetting
    from optax_bilateral._src.rules.registry import LevelsSetting, SigmaSetting

SecondMoment = Literal["elementwise", "uniform"]

# The function the user called, for the messages init and update raise long after it
# returned: bilateral_adam builds its transforms under its own name (called_as).
_CALLER: contextvars.ContextVar[str | None] = contextvars.ContextVar("caller", default=None)


@contextlib.contextmanager
def called_as(name: str) -> Iterator[None]:
    """Transforms built inside this block name ``name`` in their messages."""
    token = _CALLER.set(name)
    try:
        yield
    finally:
        _CALLER.reset(token)


def _caller(transform: str) -> str:
    """How a transform's messages name it: ``"postfilter"``, or ``"bilateral_adam (its
    postfilter)"`` when built by :func:`bilateral_adam`."""
    outer = _CALLER.get()
    return transform if outer is None else f"{outer} (its {transform})"


try:  # what optax.tree.map_params passes to init in place of the parameters
    from optax.tree_utils._state_utils import _ParamsPlaceholder
except ImportError:  # another optax layout: map_params then sees no parameter-shaped field
    _ParamsPlaceholder = None


class _NotParams:
    """Stands, in the state that ``optax.tree.map_params`` reads the layout from, for a field
    that is not parameter-shaped (per-leaf rule states and counts): a leaf, so that the
    field's real value is left alone (or given to ``transform_non_params``) whole."""


def _is_placeholder(params) -> bool:
    return _ParamsPlaceholder is not None and isinstance(params, _ParamsPlaceholder)


def _placeholder_postfilter_state(params, memoryless: bool):
    """A postfilter's state for ``optax.tree.map_params``: the moments are parameter-shaped."""
    moments = (None, None) if memoryless else (params, params)
    return PostfilterState(jnp.zeros([], jnp.int32), *moments, _NotParams(), _NotParams())


# ----------------------------------------------------------------------------------------
# scale_by_adam


class ScaleByAdamState(NamedTuple):
    """State of :func:`scale_by_adam`: step count and the first two moments.

    Attributes:
      count: the number of updates so far, an int32 scalar.
      mu: the first moment ``m_t``, like the parameters (dtype ``mu_dtype`` if given).
      nu: the second moment ``v_t``, like the parameters.

    Example::

        >>> import jax.numpy as jnp, optax_bilateral as ob
        >>> state = ob.scale_by_adam().init({"w": jnp.zeros(3)})
        >>> type(state).__name__, int(state.count), state.mu["w"].shape
        ('ScaleByAdamState', 0, (3,))
    """

    count: jax.Array  # shape=(), int32
    mu: optax.Updates
    nu: optax.Updates


def scale_by_adam(
    b1: jax.typing.ArrayLike = 0.9,
    b2: jax.typing.ArrayLike = 0.999,
    eps: jax.typing.ArrayLike = 1e-8,
    eps_root: jax.typing.ArrayLike = 0.0,
    *,
    mu_dtype: Any = None,
) -> optax.GradientTransformationExtraArgs:
    r"""Adam's scaling, numerically identical to :func:`optax.scale_by_adam`.

    .. math::
        m_t = \beta_1 m_{t-1} + (1-\beta_1) g_t,\quad
        v_t = \beta_2 v_{t-1} + (1-\beta_2) g_t^2,\quad
        \Delta_t = \frac{m_t/(1-\beta_1^t)}{\sqrt{v_t/(1-\beta_2^t) + \epsilon_{root}} + \epsilon}

    (supplement eq. 12). Chained after :func:`prefilter` it is eq. 13. With
    ``b1 = b2 = 0`` it is ``sign(g)`` up to ``eps`` (eq. 15). Unlike :func:`postfilter` it
    has no policy for non-finite or extreme gradients (docs/robustness.md).

    Args:
      b1: decay rate of the first moment, in [0, 1) (default 0.9, Adam's).
      b2: decay rate of the second moment, in [0, 1) (default 0.999, Adam's).
      eps: added to the denominator (default 1e-8).
      eps_root: added inside the square root (default 0).
      mu_dtype: dtype of the first moment (default: the parameters').

    Returns:
      An ``optax.GradientTransformationExtraArgs`` whose state is a
      :class:`ScaleByAdamState`; the updates have the gradients' shapes and need a learning
      rate after them (``optax.scale_by_learning_rate``).

    Example::

        >>> import jax.numpy as jnp, optax_bilateral as ob
        >>> opt = ob.scale_by_adam()
        >>> grads = {"w": jnp.array([0.5, -2.0, 0.0])}
        >>> updates, state = opt.update(grads, opt.init(grads))
        >>> print(updates["w"])     # the first step is g / |g|, up to eps
        [ 0.9999934 -0.9999934  0.       ]
    """
    check_decay(b1, "b1")
    check_decay(b2, "b2")
    check_nonnegative(eps, "eps")
    mu_dtype = check_mu_dtype(mu_dtype)

    def init_fn(params):
        for leaf, name in zip(jax.tree.leaves(params), prefix.leaf_names(params)):
            leaves.check_floating(
                leaf,
                name,
                "scale_by_adam keeps Adam moments for every "
                "leaf, which needs floating point parameters (real or complex)",
            )
        mu = jax.tree.map(lambda p: numerics.zeros(p, mu_dtype), params)
        nu = jax.tree.map(numerics.zeros, params)
        return ScaleByAdamState(count=jnp.zeros([], jnp.int32), mu=mu, nu=nu)

    def update_fn(updates, state, params=None, **extra_args):
        del params, extra_args
        leaves.check_update_shapes(updates, state.mu, "scale_by_adam", "moments")
        mu = jax.tree.map(lambda g, m: (1 - b1) * g + b1 * m, updates, state.mu)
        # |g|^2: a complex leaf's second moment is real, as in optax.adam.
        nu = jax.tree.map(lambda g, v: (1 - b2) * _abs_sq(g) + b2 * v, updates, state.nu)
        count_inc = jnp.asarray(optax.safe_increment(state.count))
        c1 = jnp.asarray(1 - b1**count_inc)
        c2 = jnp.asarray(1 - b2**count_inc)
        new = jax.tree.map(
            lambda m, v: (
                (m / c1.astype(m.dtype)) / (jnp.sqrt(v / c2.astype(v.dtype) + eps_root) + eps)
            ),
            mu,
            nu,
        )
        mu = jax.tree.map(lambda m, old: m.astype(old.dtype), mu, state.mu)
        nu = jax.tree.map(lambda v, old: v.astype(old.dtype), nu, state.nu)
        return new, ScaleByAdamState(count=count_inc, mu=mu, nu=nu)

    return optax.GradientTransformationExtraArgs(init_fn, update_fn)


def _abs_sq(g: jax.Array) -> jax.Array:
    return jnp.real(g) ** 2 + jnp.imag(g) ** 2 if jnp.iscomplexobj(g) else g**2


# ----------------------------------------------------------------------------------------
# What a filtering transform decides per leaf


class _Filtering(NamedTuple):
    """A filtering transform's settings, resolved per leaf into plans, rules and guides."""

    sigma_d: Any
    levels: Any
    separable: bool
    guide: Any
    log_guide: bool
    spatial_axes: Any
    filter_m: bool = True
    filter_v: bool = True

    def check(self) -> None:
        """Construction-time checks of the settings that need no parameters (what depends on
        the leaves, axis ranges and dimensions, is checked by ``init``)."""
        guides.check_guide(self.guide)
        for sig in jax.tree.leaves(self.sigma_d, is_leaf=prefix.is_sigma_atom):
            if isinstance(sig, SigmaRule):
                continue
            if sig is None:
                raise ValueError(f"sigma_d must be {rules.SETTINGS}, got None")
            check_sigma_d(sig, names=tuple(rules.NAMED))
        for lev in jax.tree.leaves(self.levels):
            if not (hasattr(lev, "shape") and not is_concrete(lev)):
                check_levels(lev)  # a traced one: update says how
        leaf_rule.check_spatial_axes_setting(self.spatial_axes)

    def specs(self, tree, warn: bool = False) -> list[leaves.LeafSpec]:
        return leaves.leaf_specs(
            tree,
            spatial_axes=self.spatial_axes,
            sigma_d=self.sigma_d,
            levels=self.levels,
            warn=warn,
        )

    def filter_plan(self, spec: leaves.LeafSpec) -> FilterPlan | None:
        if not spec.axes:
            return None
        return FilterPlan(
            spec.axes,
            spec.levels,
            self.separable,
            self.guide == "self",
            self.log_guide,
            self.filter_m,
            self.filter_v,
        )

    def guides(self, params, tree, specs, transform: str) -> list:
        return guides.guide_leaves(self.guide, params, tree, specs, self.log_guide, transform)

    def init_states(self, params, specs, transform: str, kind: Kind):
        """Per leaf, its sigma_d rule's state (None for an unfiltered leaf or a rule that keeps
        none); None if no leaf has one."""
        plans = [self.filter_plan(spec) for spec in specs]
        if not any(plans):
            return None
        guide_list = self.guides(params, params, specs, transform)
        states = [
            None
            if plan is None
            else rules.resolve(spec.sigma_d).init(
                layout.real_view(leaf), layout.real_view(guide), plan, kind
            )
            for leaf, guide, spec, plan in zip(jax.tree.leaves(params), guide_list, specs, plans)
        ]
        if all(s is None for s in states):
            return None
        return jax.tree.unflatten(jax.tree.structure(params), states)


def _per_leaf(tree, treedef) -> list:
    """The entries of a per-leaf state tree (None everywhere if there is none)."""
    if tree is None:
        return [None] * treedef.num_leaves
    return treedef.flatten_up_to(tree)


# ----------------------------------------------------------------------------------------
# prefilter


class PrefilterState(NamedTuple):
    """State of :func:`prefilter`: none, unless a leaf's sigma_d rule keeps one (``"auto"``).

    Attributes:
      count: the number of updates so far (int32 scalar), or None when no leaf's rule
        keeps a state.
      sigma_state: None when no leaf's rule keeps a state; else a pytree with the
        parameters' structure holding, per leaf, its rule's state (an :class:`AutoState`:
        the guide of the last update), or None for leaves with a numeric ``sigma_d`` or
        not filtered.

    Example::

        >>> import jax.numpy as jnp, optax_bilateral as ob
        >>> ob.prefilter(sigma_d=0.1).init(jnp.ones((16, 16, 3)))
        PrefilterState(count=None, sigma_state=None)
        >>> state = ob.prefilter().init(jnp.ones((16, 16, 3)))       # sigma_d="auto"
        >>> int(state.count), state.sigma_state.previous_guide.shape
        (0, (16, 16, 3))
    """

    count: Any = None  # shape=(), int32, or None
    sigma_state: Any = None


def prefilter(
    sigma_d: SigmaSetting = DEFAULT_SIGMA_D,
    levels: LevelsSetting = None,
    *,
    separable: bool = True,
    guide: GuideSetting = "params",
    log_guide: bool = False,
    spatial_axes: SpatialAxesSetting = None,
    mask_unobserved: bool = False,
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
      sigma_d: data-term scale (>= 0; ``inf`` = low-pass) or ``"auto"`` (the
        default: 3x the guide's mean change per step, per leaf, since a prefilter does
        not see the step it leads to; docs/auto_sigma.md), or a rule object
        (:func:`auto_sigma`); a value or a pytree prefix of the parameters. A number is
        traceable. (``"sure"`` needs Adam's moments: :func:`postfilter` only.)
      levels: F, number of a-trous levels (static), a number or a prefix; None (the
        default): :data:`DEFAULT_LEVELS` = 3. The authors' ``stride_levels = L`` is
        ``levels = L - 1`` (their strides are 0, 1, 2, 4, ...; the stride-0 level is
        the identity).
      separable: one 1-D pass per spatial axis (True) or all 5^n taps (False).
      guide: ``"params"`` (cross-bilateral, the paper's method), ``"self"``
        (bilateral, the paper's baseline and the authors' ``cross_term_off``: the
        gradient guides itself, every level by its own, partially filtered,
        input), or a callable ``params -> guide pytree`` (a prefix of the
        parameters).
      log_guide: use ``log(|guide| + 1e-8)`` as the guide (the authors'
        ``log_primal``; with ``"self"``, of each level's input).
      spatial_axes: ``None`` (default leaf rule, see :func:`default_spatial_axes`;
        ``"default"``: the same rule without its warning), a tuple for every leaf, a
        pytree prefix of tuples (``()`` = do not filter), or a callable ``leaf -> axes``.
      mask_unobserved: leave texels whose gradient is 0 in every channel out of
        the sums (see :func:`postfilter`).

    Gradients beyond a quarter of the float maximum are clipped first, so the
    sums cannot overflow (docs/robustness.md lists the numerical policies).

    Returns:
      An ``optax.GradientTransformationExtraArgs`` (state :class:`PrefilterState`) whose
      ``update(grads, state, params)`` returns ``A_t g_t`` with the gradients' shapes and
      dtypes; it needs ``params`` (the guide) unless ``guide="self"``.

    Example::

        >>> import jax.numpy as jnp, optax, optax_bilateral as ob
        >>> params = jnp.ones((16, 16, 3))                       # a flat 16x16 RGB texture
        >>> grads = jnp.zeros((16, 16, 3)).at[8, 8].set(1.0)     # one noisy texel
        >>> opt = ob.prefilter(sigma_d=0.1, levels=2)
        >>> filtered, _ = opt.update(grads, opt.init(params), params)
        >>> print(filtered[8, 8])                                # spread over its neighbours
        [0.02954102 0.02954102 0.02954102]
        >>> eq13 = optax.chain(ob.prefilter(sigma_d=0.1, levels=2),
        ...                    ob.scale_by_adam(b1=0.2, b2=0.36),
        ...                    optax.scale_by_learning_rate(0.01))
        >>> updates, _ = eq13.update(grads, eq13.init(params), params)
        >>> print(updates[8, 10])                # -lr sign(A g): step 1 of Adam is a sign step
        [-0.01 -0.01 -0.01]
    """
    settings = _Filtering(sigma_d, levels, separable, guide, log_guide, spatial_axes)
    settings.check()
    _check_rules(sigma_d, Setting("prefilter", guide == "self", filters_both=True))
    name = _caller("prefilter")

    def init_fn(params):
        if _is_placeholder(params):  # optax.tree.map_params: no parameter-shaped field
            return PrefilterState(count=_NotParams(), sigma_state=_NotParams())
        # Shapes, dtypes and the guide are checked now rather than at the first update.
        specs = leaves.check_params(params, settings, transform=name, all_leaves=False)
        sigma_state = settings.init_states(params, specs, name, "prefilter")
        if sigma_state is None:
            return PrefilterState()
        return PrefilterState(count=jnp.zeros([], jnp.int32), sigma_state=sigma_state)

    def update_fn(updates, state, params=None, **extra_args):
        del extra_args
        leaves.check_update_shapes(updates, params, name)
        specs = settings.specs(updates)
        guide_list = settings.guides(params, updates, specs, name)
        flat, treedef = jax.tree.flatten(updates)
        # A stateless prefilter's state may also be passed as () (it was an empty tuple).
        tree = state.sigma_state if isinstance(state, PrefilterState) else None
        count = None if tree is None else optax.safe_increment(state.count)
        out, new_states = [], []
        for g, leaf_guide, spec, leaf_state in zip(
            flat, guide_list, specs, _per_leaf(tree, treedef)
        ):
            plan = LeafPlan(
                settings.filter_plan(spec),
                mask_unobserved,
                numerics.prefilter_limit(jnp.finfo(g.dtype).dtype),
                complex_view=jnp.iscomplexobj(g),
            )
            if plan.filter is not None:
                rule = rules.resolve(spec.sigma_d)
                a_g, leaf_state = prefilter_leaf(
                    layout.real_view(g),
                    layout.real_view(leaf_guide),
                    leaf_state,
                    rule,
                    count,
                    plan=plan,
                )
                g = layout.from_real_view(a_g, g.dtype) if plan.complex_view else a_g
            out.append(g)
            new_states.append(leaf_state)
        if tree is None:
            return jax.tree.unflatten(treedef, out), state
        new_state = PrefilterState(count, jax.tree.unflatten(treedef, new_states))
        return jax.tree.unflatten(treedef, out), new_state

    return optax.GradientTransformationExtraArgs(init_fn, update_fn)


def _check_rules(sigma_d, setting: Setting) -> None:
    """Each leaf's rule checks, when the transform is built, that it can run in it."""
    for atom in jax.tree.leaves(sigma_d, is_leaf=prefix.is_sigma_atom):
        if isinstance(atom, (str, SigmaRule)):
            rules.resolve(cast(Any, atom)).check(setting)


# ----------------------------------------------------------------------------------------
# postfilter


class PostfilterState(NamedTuple):
    """State of :func:`postfilter`: the *unfiltered* moments (eqs. 2, 4).

    Attributes:
      count: the number of updates so far, an int32 scalar.
      mu: the first moment ``m_t`` (unfiltered), like the parameters; None in the
        memoryless case ``b1 = b2 = 0``.
      nu: the second moment ``v_t`` (unfiltered), like the parameters; None when
        ``b1 = b2 = 0``.
      sigma_state: None unless a leaf's sigma_d rule keeps a state; then a pytree with the
        parameters' structure holding, per leaf, its rule's state (an :class:`AutoState`
        for ``"auto"``, a :class:`SureState` for ``"sure"``; None for leaves with a numeric
        ``sigma_d`` or not filtered).
      nonfinite_count: per leaf (a pytree like the parameters), how many gradient entries
        were not finite (NaN or infinite) since ``init``, an int32 scalar that saturates at
        its maximum. Those entries are dropped from the moments and the filter, and their
        step is 0; a count that grows is a renderer or a loss to look at.

    Example::

        >>> import jax.numpy as jnp, optax_bilateral as ob
        >>> state = ob.postfilter(sigma_d=0.1).init(jnp.ones((16, 16, 3)))
        >>> int(state.count), state.mu.shape, state.sigma_state
        (0, (16, 16, 3), None)
        >>> ob.postfilter(b1=0.0, b2=0.0, sigma_d=0.1).init(jnp.ones((16, 16, 3))).mu is None
        True
    """

    count: jax.Array  # shape=(), int32
    mu: optax.Updates | None
    nu: optax.Updates | None
    sigma_state: Any = None
    nonfinite_count: Any = None


def postfilter(
    b1: jax.typing.ArrayLike = 0.2,
    b2: jax.typing.ArrayLike | None = None,
    eps: jax.typing.ArrayLike = 1e-8,
    *,
    sigma_d: SigmaSetting = DEFAULT_SIGMA_D,
    levels: LevelsSetting = None,
    separable: bool = True,
    guide: GuideSetting = "params",
    log_guide: bool = False,
    spatial_axes: SpatialAxesSetting = None,
    mask_unobserved: bool = False,
    eps_root: jax.typing.ArrayLike = 0.0,
    mu_dtype: Any = None,
    filter_m: bool = True,
    filter_v: bool = True,
    second_moment: SecondMoment = "elementwise",
    unfiltered_betas: tuple[jax.typing.ArrayLike, jax.typing.ArrayLike] | None = None,
) -> optax.GradientTransformationExtraArgs:
    r"""Adam whose moments are filtered in space after the temporal averages.

    .. math::
        m_t = \beta_1 m_{t-1} + (1-\beta_1) g_t, \qquad v_t = \beta_2 v_{t-1} + (1-\beta_2) g_t^2

        \Delta_t = \frac{B_t m_t / (1-\beta_1^t)}
                        {\sqrt{B_t v_t / (1-\beta_2^t) + \epsilon_{root}} + \epsilon}

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
      b1: decay rate of the first moment, in [0, 1).
      b2: decay rate of the second moment, in [0, 1); ``None`` means
        ``1 - (1 - b1)^2`` (both references).
      eps: added to the denominator, as in Adam.
      sigma_d: data-term scale (>= 0; ``inf`` = low-pass), in the guide's units, or
        ``"auto"`` (the default: one learning rate in the guide's units per leaf, the
        guide's mean change per step over the step's mean direction ``m~ / sqrt(v~)``
        times ``sqrt(channels)``, and a per-entry blend ``lam m + (1 - lam) B m``
        (likewise ``v``, the same ``lam``) where the filter's residual persists beyond
        the moments' noise; docs/auto_sigma.md), or ``"sure"`` (an opt-in: 3x the
        guide's mean change per step times 1, 3 or 10, at F = 2 .. ``levels``, chosen
        per leaf and step by Stein's unbiased risk estimate averaged over about ten
        steps, then the same blend, and the mildest candidate once that blend has been
        fully open on the leaf; per
        step three cascades of m and a noise sample and one of v; a guide and moments
        needed; :class:`SureState`), or a rule object (:func:`auto_sigma`,
        :func:`sure_sigma`, or a :class:`SigmaRule` of one's own); a value or a pytree
        prefix of the parameters. A number is traceable.
      levels: F, number of a-trous levels (static), a number or a prefix; the
        authors' ``stride_levels`` - 1. With ``sigma_d="sure"``, the most it may use.
        None (the default): :data:`DEFAULT_LEVELS` = 3, and :data:`SURE_LEVELS` = 5
        for the leaves with ``sigma_d="sure"`` (the tuning suite's best bound).
      separable: one 1-D pass per spatial axis (True) or all 5^n taps (False).
      guide: ``"params"`` (cross-bilateral, the paper's method), ``"self"``, or a
        callable ``params -> guide pytree`` (a prefix of the parameters).
        ``guide="self"`` filters ``m`` guided by ``m`` and ``v`` by ``v``, every level
        by its own input: they then get *different* weights and the bound above no
        longer holds.
      log_guide: use ``log(|guide| + 1e-8)`` as the guide.
      spatial_axes: ``None`` (default leaf rule, see :func:`default_spatial_axes`;
        ``"default"``: the same rule without its warning), a tuple for every leaf, a
        pytree prefix of tuples (``()`` = do not filter), or a callable ``leaf -> axes``.
      mask_unobserved: texels whose gradient is exactly zero in every channel
        this step keep their moments, get a zero update and are left out of the
        filter sums (Mitsuba's ``mask_updates``; PyTorch's SparseAdam).
        Non-finite gradients are always treated this way.
      mu_dtype: dtype of the first moment buffer (default: the parameters').
        The second moment always has the parameters' dtype.
      eps_root: added inside the square root, as in optax's Adam.
      filter_m: filter ``m`` (the authors' ``mtfilter``); False uses it unfiltered. With
        only one of ``m``, ``v`` filtered the bound above no longer holds.
      filter_v: filter ``v`` (the authors' ``vtfilter``); False uses it unfiltered.
      second_moment: ``"elementwise"`` (Adam's: each entry's own ``B v``) or
        ``"uniform"``: one second moment per leaf, the max of ``B v`` over it
        (Large Steps' ``AdamUniform``; the Dr.Jit port's ``uniform``, which puts
        ``eps`` on the uncorrected root, is this one with ``eps / sqrt(1 - b2^t)``).
        Unobserved texels enter the max with the moments they keep.
      unfiltered_betas: ``(b1, b2)`` of the leaves this postfilter does not filter (its
        leaf rule gives them no spatial axes, or ``levels=0``); None (the default): ``b1``
        and ``b2`` for every leaf. :func:`bilateral_adam` passes Adam's own ``(0.9, 0.999)``.

    Finite gradients are clipped to the largest magnitude whose square fits the
    second moment's dtype (1.3e19 for float32, 181 for float16), and a zero
    denominator gives a zero step; docs/robustness.md lists these policies.

    Returns:
      An ``optax.GradientTransformationExtraArgs`` (state :class:`PostfilterState`) whose
      ``update(grads, state, params)`` returns the step ``Delta_t`` with the gradients'
      shapes (no learning rate: chain ``optax.scale_by_learning_rate``, as
      :func:`bilateral_adam` does); it needs ``params`` (the guide) unless
      ``guide="self"``.

    Example::

        >>> import jax, jax.numpy as jnp, optax_bilateral as ob
        >>> params = jnp.ones((16, 16, 3))
        >>> grads = 0.1 * jax.random.normal(jax.random.key(0), (16, 16, 3))
        >>> opt = ob.postfilter(b1=0.2, sigma_d=0.1, levels=2)
        >>> step, state = opt.update(grads, opt.init(params), params)
        >>> bool(jnp.abs(step).max() <= 1.0)     # bounded like Adam's (supplement §1.3)
        True
        >>> bool(jnp.all(state.mu == 0.8 * grads))   # the state keeps the unfiltered m_t
        True
    """
    b2 = _check_adam(b1, b2, eps, eps_root)
    unfiltered_betas = _check_betas(unfiltered_betas, (b1, b2))
    filter_m, filter_v = check_bool(filter_m, "filter_m"), check_bool(filter_v, "filter_v")
    settings = _Filtering(
        sigma_d, levels, separable, guide, log_guide, spatial_axes, filter_m, filter_v
    )
    settings.check()
    mu_dtype = check_mu_dtype(mu_dtype)
    check_second_moment(second_moment)
    memoryless = all(map(is_zero, (b1, b2, *unfiltered_betas)))
    name = _caller("postfilter")
    kind = "memoryless" if memoryless else "postfilter"
    _check_rules(sigma_d, Setting(kind, guide == "self", filter_m and filter_v))

    def init_fn(params):
        if _is_placeholder(params):
            return _placeholder_postfilter_state(params, memoryless)
        # Shapes, dtypes and the guide are checked now rather than at the first update.
        specs = leaves.check_params(params, settings, transform=name, all_leaves=True)
        sigma_state = settings.init_states(params, specs, name, kind)
        count = jnp.zeros([], jnp.int32)
        nonfinite = jax.tree.map(lambda _: jnp.zeros([], jnp.int32), params)
        mu = None if memoryless else jax.tree.map(lambda p: numerics.zeros(p, mu_dtype), params)
        nu = None if memoryless else jax.tree.map(numerics.zeros, params)
        return PostfilterState(count, mu, nu, sigma_state, nonfinite)

    def update_fn(updates, state, params=None, **extra_args):
        del extra_args
        leaves.check_update_shapes(updates, params, name)
        leaves.check_update_shapes(updates, state.mu, name, "moments")
        count = jnp.asarray(optax.safe_increment(state.count))
        adams = _adams((b1, b2), unfiltered_betas, eps, eps_root, count)
        specs = settings.specs(updates)
        guide_list = settings.guides(params, updates, specs, name)
        flat, treedef = jax.tree.flatten(updates)
        moments = _moments(state, treedef)
        outs = []
        for g, leaf_guide, spec, leaf_moments, leaf_state in zip(
            flat, guide_list, specs, moments, _per_leaf(state.sigma_state, treedef)
        ):
            plan = _post_plan(settings, spec, g, leaf_moments, mask_unobserved, second_moment)
            rule = rules.resolve(spec.sigma_d)
            adam, clock = adams[plan.filter is not None]
            outs.append(
                _postfilter_leaf(
                    g, leaf_guide, leaf_moments, leaf_state, rule, adam, clock, plan=plan
                )
            )
        d, new_moments, new_states = zip(*outs) if outs else ((), (), ())
        unflatten = lambda xs: jax.tree.unflatten(treedef, list(xs))
        return unflatten(d), PostfilterState(
            count=count,
            mu=None if state.mu is None else unflatten(m for m, _ in new_moments),
            nu=None if state.nu is None else unflatten(v for _, v in new_moments),
            sigma_state=None if state.sigma_state is None else unflatten(new_states),
            nonfinite_count=_count_nonfinite(state.nonfinite_count, updates),
        )

    # optax's OptState alias admits no None fields (the memoryless state has them).
    return optax.GradientTransformationExtraArgs(init_fn, update_fn)  # pyright: ignore[reportArgumentType]


def _count_nonfinite(counts, updates):
    """The per-leaf counts of non-finite gradient entries, with this step's added (saturating
    at int32's maximum); None stays None (a state from before the field existed)."""
    if counts is None:
        return None
    totals, treedef = jax.tree.flatten(counts)
    return treedef.unflatten(numerics.count_nonfinite(treedef.flatten_up_to(updates), totals))


def _check_betas(betas, default) -> tuple:
    """``unfiltered_betas`` checked (``default`` if None)."""
    if betas is None:
        return tuple(default)
    if not (isinstance(betas, (tuple, list)) and len(betas) == 2):
        raise TypeError(f"unfiltered_betas must be a pair (b1, b2) or None, got {betas!r}")
    check_decay(betas[0], "unfiltered_betas[0] (b1)")
    check_decay(betas[1], "unfiltered_betas[1] (b2)")
    return tuple(betas)


def _adams(filtered, unfiltered, eps, eps_root, count) -> dict:
    """``{is the leaf filtered: (AdamHyper, Clock)}``: each kind of leaf's decay rates and
    bias corrections at step ``count``."""
    out = {}
    for key, (b1, b2) in ((True, filtered), (False, unfiltered)):
        clock = Clock(
            count, numerics.bias_correction(b1, count), numerics.bias_correction(b2, count)
        )
        out[key] = (AdamHyper.of(b1, b2, eps, eps_root), clock)
    return out


def _check_adam(b1, b2, eps, eps_root):
    """Adam's hyperparameters checked; ``b2``, with None as ``1 - (1 - b1)^2``."""
    check_decay(b1, "b1")  # before b2's default reads it
    b2 = 1 - (1 - b1) ** 2 if b2 is None else b2
    check_decay(b2, "b2")
    check_nonnegative(eps, "eps")
    check_nonnegative(eps_root, "eps_root")
    return b2


def _moments(state: PostfilterState, treedef) -> list:
    """The stored ``(m, v)`` per leaf, or None per leaf (memoryless)."""
    if state.mu is None or state.nu is None:
        return [None] * treedef.num_leaves
    return list(zip(treedef.flatten_up_to(state.mu), treedef.flatten_up_to(state.nu)))


def _post_plan(settings, spec, g, moments, mask_unobserved, second_moment) -> LeafPlan:
    """A postfilter leaf's plan: moments updated in at least float32 (stored back in their own
    dtypes), gradients clipped where ``m``, ``v = g^2`` and ``g`` itself stay finite; a
    complex leaf's in its real parts' dtypes (it is updated through its real view)."""
    real = lambda x: jnp.finfo(jnp.result_type(x)).dtype
    stored = [] if moments is None else [real(x) for x in moments]
    compute_dtype = jnp.promote_types(jnp.result_type(real(g), *stored), jnp.float32)
    return LeafPlan(
        settings.filter_plan(spec),
        mask_unobserved,
        numerics.moment_limit(real(g), compute_dtype, *stored),
        compute_dtype,
        second_moment == "uniform",
        jnp.iscomplexobj(g),
    )


def _postfilter_leaf(g, guide, moments, state, rule, adam, clock, *, plan: LeafPlan):
    """:func:`postfilter_leaf`; a complex leaf through its real view (its parts as a last axis
    of 2, one ``|g|^2`` second moment for both: optax.adam's rule), its moments stored
    complex like the leaf, as optax.adam stores them."""
    if not plan.complex_view:
        return postfilter_leaf(g, guide, moments, state, rule, adam, clock, plan=plan)
    view = None if moments is None else (layout.real_view(moments[0]), layout.norm_view(moments[1]))
    guide = layout.real_view(guide)
    d, new, state = postfilter_leaf(
        layout.real_view(g), guide, view, state, rule, adam, clock, plan=plan
    )
    if new is not None and moments is not None:
        m, v = new
        new = (layout.from_real_view(m, moments[0].dtype), v[..., 0].astype(moments[1].dtype))
    return layout.from_real_view(d, g.dtype), new, state
