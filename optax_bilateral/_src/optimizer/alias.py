"""``bilateral_adam``: the paper's optimizer for the grids of a pytree, Adam for the rest."""

from __future__ import annotations

import inspect
import warnings
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any, cast

import jax
import optax

from optax_bilateral._src.optimizer import coarse, leaves, transforms
from optax_bilateral._src.rules.registry import DEFAULT_SIGMA_D, SPARSE_SIGMA_D
from optax_bilateral._src.validation import check_learning_rate, check_nonnegative

if TYPE_CHECKING:
    from optax_bilateral._src.optimizer.leaf_rule import SpatialAxesSetting
    from optax_bilateral._src.rules.registry import LevelsSetting, SigmaSetting

# The paper's grid runs (both references): b1 = 0.2, b2 = 1 - (1 - b1)^2.
PAPER_B1 = 0.2
# optax.adam's own, for the leaves that are not filtered.
ADAM_B1, ADAM_B2 = 0.9, 0.999

# Keywords bilateral_adam took before 0.1.0 (deprecated since), and where each lives now.
_MOVED = {
    "separable": "postfilter",
    "guide": "postfilter",
    "mask_unobserved": "postfilter",
    "eps_root": "postfilter",
    "mu_dtype": "postfilter",
    "filter_m": "postfilter",
    "filter_v": "postfilter",
    "second_moment": "postfilter",
    "postfilter": "postfilter",
    "weight_decay": "optax.add_decayed_weights",
    "weight_decay_mask": "optax.add_decayed_weights",
}
# What the prefilter shares with the postfilter: its own keywords.
PREFILTER_SETTINGS = tuple(inspect.signature(transforms.prefilter).parameters)


def filtered_chain(
    learning_rate: optax.ScalarOrSchedule,
    b1: jax.typing.ArrayLike = PAPER_B1,
    b2: jax.typing.ArrayLike | None = None,
    eps: jax.typing.ArrayLike = 1e-8,
    *,
    prefilter: bool | Mapping[str, Any] = False,
    tail: Sequence[optax.GradientTransformation] = (),
    **settings: Any,
) -> optax.GradientTransformationExtraArgs:
    """The filtered leaves' optimizer, ``optax.chain(prefilter(...)?, postfilter(b1, b2, eps,
    **settings), *tail, optax.scale_by_learning_rate(learning_rate))``: built here only, for
    :func:`bilateral_adam`, the Mitsuba optimizers and the experiments.

    ``prefilter``: True gives the prefilter the ``settings`` it takes too
    (:data:`PREFILTER_SETTINGS`); a mapping gives it those settings instead.
    """
    if isinstance(prefilter, Mapping):
        pre = [transforms.prefilter(**prefilter)]
    elif prefilter:
        pre = [
            transforms.prefilter(**{k: settings[k] for k in PREFILTER_SETTINGS if k in settings})
        ]
    else:
        pre = []
    post = transforms.postfilter(b1, b2, eps, **settings)
    return optax.chain(*pre, post, *tail, optax.scale_by_learning_rate(learning_rate))


def bilateral_adam(
    learning_rate: optax.ScalarOrSchedule,
    b1: jax.typing.ArrayLike | None = None,
    b2: jax.typing.ArrayLike | None = None,
    eps: jax.typing.ArrayLike = 1e-8,
    *,
    sigma_d: SigmaSetting = DEFAULT_SIGMA_D,
    levels: LevelsSetting = None,
    prefilter: bool = False,
    spatial_axes: SpatialAxesSetting = None,
    log_guide: bool = False,
    others: optax.GradientTransformation | None = None,
    **deprecated: Any,
) -> optax.GradientTransformationExtraArgs:
    r"""Adam with spatiotemporal cross-bilateral gradient filtering (Chang et al. 2024) on the
    grid-shaped leaves of a pytree, and Adam's own rule on the others.

    .. math::
        \tilde g_t = A_t g_t, \quad
        m_t = \beta_1 m_{t-1} + (1-\beta_1)\tilde g_t, \quad
        v_t = \beta_2 v_{t-1} + (1-\beta_2)\tilde g_t^2

        \theta_t = \theta_{t-1} - \eta\,
        \frac{B_t m_t/(1-\beta_1^t)}{\sqrt{B_t v_t/(1-\beta_2^t)} + \epsilon}

    on every leaf the leaf rule filters (:func:`filtered_axes` lists them; docs/leaves.md),
    with ``A = I`` unless ``prefilter`` (supplement eq. 11; eq. 14 without the prefilter).
    ``B`` (and ``A``) are a-trous cross-bilateral filters with ``levels`` = F levels guided by
    the current parameters. The other leaves (weights, scalars, colours) get
    ``optax.adam(learning_rate, b1=0.9, b2=0.999, eps=eps)``'s rule, or ``others``.

    It is ``optax.chain(prefilter(...)?, postfilter(b1, b2, eps, ..., unfiltered_betas=(0.9,
    0.999)), optax.scale_by_learning_rate(learning_rate))``: one postfilter, whose leaves
    without spatial axes get Adam's own decay rates. With ``others``, an
    ``optax.multi_transform`` of that chain (the filtered leaves) and ``others`` (the rest).
    The ablation and policy knobs (``separable``, ``guide``, ``mask_unobserved``,
    ``eps_root``, ``mu_dtype``, ``filter_m``, ``filter_v``, ``second_moment``) are
    :func:`postfilter`'s and :func:`prefilter`'s; build that chain to use them.

    Defaults: on filtered leaves the paper's ``b1 = 0.2``, ``b2 = 1 - (1 - b1)^2`` (= 0.36),
    postfilter only, ``sigma_d = "auto"`` (chosen from the data every step,
    docs/auto_sigma.md) with ``levels = 3``; a leaf with ``sigma_d="sure"`` chooses F up to
    ``levels = 5``. On the tuning benchmark's seven scenes the defaults were 0.97-1.10x the
    error of a per-scene tuned sigma_d, beat Adam on six and tied it on the seventh;
    docs/hyperparameters.md says when to tune a number instead.

    ``learning_rate`` and ``sigma_d`` can be schedules through
    ``optax.inject_hyperparams(bilateral_adam, static_args=("levels",))``.

    Args:
      learning_rate: a number >= 0 or an optax schedule.
      b1: decay rate of the first moment, in [0, 1). None (the default): the paper's 0.2 on
        filtered leaves, Adam's 0.9 on the others; a value given applies to every leaf
        (``others`` aside).
      b2: decay rate of the second moment, in [0, 1). None: ``1 - (1 - b1)^2`` on filtered
        leaves (0.36), Adam's 0.999 on the others; a value given applies to every leaf.
      eps: added to the denominator, as in Adam (every leaf).
      sigma_d: data-term scale of the filter's weights ``exp(-|guide[p] - guide[q]| /
        sigma_d)``, in the guide's units (>= 0; ``0`` keeps only equal-guide neighbours,
        ``inf`` is a plain B-spline low-pass), or ``"auto"`` (the default: one learning
        rate in the guide's units, measured per leaf and step from the guide's change, with
        a per-texel blend toward the unfiltered moments; docs/auto_sigma.md), or ``"sure"``
        (an opt-in that also chooses F by Stein's unbiased risk estimate, at 6-10x a fixed
        sigma_d's update time; :func:`postfilter`), or a rule object (:func:`auto_sigma`,
        :func:`sure_sigma`); a pytree prefix of the parameters gives one value per leaf
        (``{"density": "auto", "albedo": 0.1}``). A number is traceable.
      levels: F, the number of a-trous levels (static; footprint radius
        ``2 (2^F - 1)``; ``0`` leaves the leaf to Adam's rule); a number or a pytree prefix.
        The authors' ``stride_levels`` is ``levels + 1``. None (the default): 3
        (:data:`DEFAULT_LEVELS`), and 5 (:data:`SURE_LEVELS`) for the leaves with
        ``sigma_d="sure"``.
      prefilter: also filter the gradient before the moments (``A_t``, eq. 1).
      spatial_axes: ``None`` (the default leaf rule, :func:`default_spatial_axes`;
        ``"default"``: the same rule without its warning), a tuple of axes for every leaf,
        a pytree prefix of tuples (``()`` = not filtered), or a callable ``leaf -> axes``.
      log_guide: guide with ``log(|guide| + 1e-8)`` (the paper's texture runs).
      others: the optimizer of the leaves that are not filtered, learning rate included
        (e.g. ``optax.adam(1e-3)``). None (the default): Adam at ``learning_rate`` with
        ``b1``, ``b2`` (0.9, 0.999 when not given) and ``eps``, with :func:`postfilter`'s
        policy for non-finite gradients (``postfilter(..., levels=0)``).
      **deprecated: the keywords this function took before 0.1.0 (``separable``, ``guide``,
        ``mask_unobserved``, ``eps_root``, ``mu_dtype``, ``filter_m``, ``filter_v``,
        ``second_moment``, ``postfilter``, ``weight_decay``, ``weight_decay_mask``): still
        applied, with a ``DeprecationWarning`` that names where each lives now; they will be
        removed in a future release.

    Returns:
      An ``optax.GradientTransformationExtraArgs``; its ``update`` needs ``params`` (the
      guide) when a leaf is filtered. Its state is the chain's (``state[0]`` the prefilter's
      or the postfilter's), or with ``others`` an ``optax.multi_transform``'s.

    Example::

        >>> import jax, jax.numpy as jnp, optax, optax_bilateral as ob
        >>> params = {"tex": jnp.full((32, 32, 3), 0.5), "exposure": jnp.zeros(())}
        >>> opt = ob.bilateral_adam(learning_rate=0.05)
        >>> state = opt.init(params)
        >>> loss = lambda p: jnp.mean((p["tex"] * jnp.exp(p["exposure"]) - 0.2) ** 2)
        >>> grads = jax.grad(loss)(params)
        >>> updates, state = opt.update(grads, state, params)   # params: the guide
        >>> params = optax.apply_updates(params, updates)
    """
    check_learning_rate(learning_rate)
    check_nonnegative(eps, "eps")
    old = _deprecated(deprecated, others)
    filtered_betas = (PAPER_B1 if b1 is None else b1, b2)
    unfiltered_betas = (ADAM_B1 if b1 is None else b1, ADAM_B2 if b2 is None else b2)
    post = {k: old.pop(k) for k in list(old) if _MOVED[k] == "postfilter"}
    tail = _weight_decay(old.get("weight_decay"), old.get("weight_decay_mask"))
    grid = dict(sigma_d=sigma_d, levels=levels, log_guide=log_guide, spatial_axes=spatial_axes)
    pre: bool | dict = prefilter
    if not post.pop("postfilter", True):  # deprecated: Adam (b1, b2) after the prefilter
        pre = prefilter and {**grid, **{k: post[k] for k in PREFILTER_SETTINGS if k in post}}
        grid = dict(levels=0)
    elif others is None:  # one postfilter: Adam's own decay rates where it does not filter
        post["unfiltered_betas"] = unfiltered_betas
    with transforms.called_as("bilateral_adam"):
        filtered = filtered_chain(
            learning_rate, *filtered_betas, eps, prefilter=pre, tail=tail, **grid, **post
        )
    if others is None:
        return filtered
    return optax.multi_transform(
        {"filtered": filtered, "others": others}, _labels(spatial_axes, levels)
    )


def sparse_adam(
    learning_rate: optax.ScalarOrSchedule,
    b1: jax.typing.ArrayLike | None = None,
    b2: jax.typing.ArrayLike | None = None,
    eps: jax.typing.ArrayLike = 1e-8,
    *,
    levels: LevelsSetting = None,
    sigma_d: SigmaSetting = SPARSE_SIGMA_D,
    coarse_levels: int = 5,
    coarse_share: float = 0.3,
    spatial_axes: SpatialAxesSetting = None,
    log_guide: bool = False,
    others: optax.GradientTransformation | None = None,
) -> optax.GradientTransformationExtraArgs:
    """:func:`bilateral_adam` for gradients that touch few texels a step: a far camera (many
    texels a pixel), or several cameras in turn.

    ``coarse_levels(bilateral_adam(learning_rate, b1, b2, eps, sigma_d=sigma_d, ...),
    learning_rate, levels=coarse_levels, share=coarse_share)``. The default ``sigma_d``,
    ``sparse_sigma(sparse_levels=0, full_coverage=0.8)`` (:class:`Sparse`), undoes the
    filter's dilution of a sparse gradient by its untouched texels (a block touched at 80% of
    its texels or more counts as full: a blurred or subsampled gradient is not a far
    camera's); :func:`coarse_levels` adds Adam's steps on the coarse levels of a Laplacian
    pyramid where the gradient is sparse, which give the far reach (beside them,
    ``sigma_d="sparse"``'s extra filter level gained 2% on a far camera and nothing elsewhere,
    for about 1.3x the update). On a gradient that touches every texel both reduce to
    :func:`bilateral_adam`'s defaults. Measured against ``pyramid_adam`` and
    the defaults at three camera distances in docs/hyperparameters.md ("How far is my
    camera").

    Args:
      learning_rate: a number >= 0 or an optax schedule (the same for the coarse levels,
        times ``coarse_share``).
      b1: as in :func:`bilateral_adam` (the filtered leaves' first-moment decay).
      b2: as in :func:`bilateral_adam`.
      eps: as in :func:`bilateral_adam`.
      levels: as in :func:`bilateral_adam` (F).
      sigma_d: the filtered leaves' rule, as in :func:`bilateral_adam`; the default corrects
        for untouched texels and adds no level (``"sparse"`` adds one on a sparse leaf).
      spatial_axes: as in :func:`bilateral_adam`, and the pyramid's axes.
      log_guide: as in :func:`bilateral_adam`.
      others: as in :func:`bilateral_adam`.
      coarse_levels: the pyramid's levels, the finest included (static, >= 2).
      coarse_share: the coarse steps' share of ``learning_rate`` (> 0).

    Returns:
      An ``optax.GradientTransformationExtraArgs`` (state
      :class:`~optax_bilateral.CoarseLevelsState`, whose ``inner_state`` is
      :func:`bilateral_adam`'s); its ``update`` needs ``params``.

    Example::

        >>> import jax.numpy as jnp, optax, optax_bilateral as ob
        >>> params = jnp.full((64, 64, 3), 0.5)
        >>> opt = ob.sparse_adam(learning_rate=0.015)
        >>> state = opt.init(params)
        >>> grads = jnp.zeros_like(params).at[::12, ::12].set(0.1)   # a far camera's few texels
        >>> updates, state = opt.update(grads, state, params)
        >>> params = optax.apply_updates(params, updates)
    """
    inner = bilateral_adam(
        learning_rate,
        b1,
        b2,
        eps,
        sigma_d=sigma_d,
        levels=levels,
        spatial_axes=spatial_axes,
        log_guide=log_guide,
        others=others,
    )
    return coarse.coarse_levels(
        inner, learning_rate, levels=coarse_levels, share=coarse_share, spatial_axes=spatial_axes
    )


def _labels(spatial_axes, levels):
    """The leaf rule as ``optax.multi_transform``'s labels: ``"filtered"`` where a leaf has spatial
    axes and ``levels > 0``, ``"others"`` elsewhere (warning where the rule guessed)."""

    def labels(tree):
        specs = leaves.leaf_specs(
            tree, spatial_axes=spatial_axes, sigma_d=0.0, levels=levels, warn=True
        )
        flat = ["filtered" if spec.axes else "others" for spec in specs]
        return jax.tree.unflatten(jax.tree.structure(tree), flat)

    return labels


def _deprecated(keywords: dict, others) -> dict:
    """The deprecated keywords, each with a warning that says where it lives now.
    ``optax.inject_hyperparams`` binds them as one keyword, ``deprecated``: unpacked."""
    keywords = {**keywords.pop("deprecated", {}), **keywords}
    for name in keywords:
        if name not in _MOVED:
            raise TypeError(f"bilateral_adam() got an unexpected keyword argument {name!r}")
        warnings.warn(
            f"bilateral_adam({name}=...) is deprecated since 0.1.0 and will be removed in a "
            f"future release: it is an argument of {_MOVED[name]}; build optax.chain("
            "ob.prefilter(...)?, ob.postfilter(...), optax.scale_by_learning_rate(lr)) for the "
            'filtered leaves (README.md, "The three compositions")',
            DeprecationWarning,
            stacklevel=3,
        )
    if others is not None and "weight_decay" in keywords:
        raise ValueError(
            "weight_decay applies to bilateral_adam's own optimizers only; with others=..., "
            "put optax.add_decayed_weights in the chains you build"
        )
    return dict(keywords)


def _weight_decay(weight_decay, mask) -> list:
    """Decoupled weight decay before the learning rate, as :func:`optax.adamw` (deprecated
    here: ``optax.add_decayed_weights``)."""
    if weight_decay is None:
        return []
    if not callable(weight_decay):
        check_nonnegative(weight_decay, "weight_decay")
    return [optax.add_decayed_weights(cast(Any, weight_decay), mask)]
