"""``bilateral_adam``: the paper's optimizer as one ``optax.chain``."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import jax
import optax

from optax_bilateral._src import transforms
from optax_bilateral._src.validation import check_nonnegative

if TYPE_CHECKING:
    from optax_bilateral._src.leaves import GuideSetting, SpatialAxesSetting
    from optax_bilateral._src.transforms import SecondMoment


def bilateral_adam(
    learning_rate: optax.ScalarOrSchedule,
    b1: jax.typing.ArrayLike = 0.2,
    b2: jax.typing.ArrayLike | None = None,
    eps: jax.typing.ArrayLike = 1e-8,
    *,
    sigma_d: Any = transforms.DEFAULT_SIGMA_D,
    levels: Any = None,
    prefilter: bool = False,
    postfilter: bool = True,
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
    weight_decay: optax.ScalarOrSchedule | None = None,
    weight_decay_mask: Any = None,
) -> optax.GradientTransformationExtraArgs:
    r"""Adam with spatiotemporal cross-bilateral gradient filtering (Chang et al. 2024).

    .. math::
        \tilde g_t = A_t g_t, \quad
        m_t = \beta_1 m_{t-1} + (1-\beta_1)\tilde g_t, \quad
        v_t = \beta_2 v_{t-1} + (1-\beta_2)\tilde g_t^2

        \theta_t = \theta_{t-1} - \eta\,
        \frac{B_t m_t/(1-\beta_1^t)}{\sqrt{B_t v_t/(1-\beta_2^t)} + \epsilon}

    with ``A = I`` unless ``prefilter`` and ``B = I`` unless ``postfilter``
    (supplement eq. 11; eq. 13 prefilter only, eq. 14 postfilter only, eq. 12 =
    Adam). ``A`` and ``B`` are a-trous cross-bilateral filters with ``levels`` =
    F levels guided by the current parameters.

    Equivalent to ``optax.chain(prefilter(...)?, postfilter(...),
    optax.scale_by_learning_rate(learning_rate))``; without the postfilter the
    middle stage is ``postfilter(..., levels=0)``, i.e. Adam with this library's
    handling of non-finite and extreme gradients (``scale_by_adam`` has none).
    With ``levels=0`` it is ``optax.adam(learning_rate, b1, b2, eps)`` on finite
    gradients of moderate size (docs/robustness.md lists the extremes).

    Defaults: the paper's ``b1 = 0.2``, ``b2 = 1 - (1 - b1)^2`` (= 0.36), postfilter
    only; ``sigma_d = "auto"`` (chosen from the data every step, docs/auto_sigma.md) with
    ``levels = 3`` (the authors' ``stride_levels = 4``; their texture runs use
    ``stride_levels = 5``, i.e. ``levels = 4``, their volume runs ``levels = 2``); a leaf
    with ``sigma_d="sure"`` chooses F up to ``levels = 5`` (``stride_levels = 6``). On the
    tuning benchmark's seven scenes the defaults were 0.97-1.10x the error of a
    per-scene tuned sigma_d, beat Adam on six and tied it on the seventh;
    docs/hyperparameters.md says when to tune a number instead.

    ``weight_decay`` is decoupled, as in :func:`optax.adamw`: ``lr * wd * params``
    is subtracted after the (filtered) Adam step, unfiltered. (The authors'
    ``weight_decay`` is torch Adam's coupled L2, ``g + wd * params`` before the
    moments: ``optax.chain(prefilter(...)?, optax.add_decayed_weights(wd),
    postfilter(...), optax.scale_by_learning_rate(lr))`` reproduces it.)

    ``learning_rate`` and ``sigma_d`` can be schedules through
    ``optax.inject_hyperparams(bilateral_adam, static_args=("levels",))``.

    Args:
      learning_rate: a number or an optax schedule.
      b1: decay rate of the first moment, in [0, 1).
      b2: decay rate of the second moment, in [0, 1); ``None`` is ``1 - (1 - b1)^2``.
      eps: added to the denominator, as in Adam.
      sigma_d: data-term scale of the filter's weights ``exp(-|guide[p] - guide[q]| /
        sigma_d)``, in the guide's units (>= 0; ``0`` keeps only equal-guide
        neighbours, ``inf`` is a plain B-spline low-pass), or ``"auto"`` (the
        default: one learning rate in the guide's units, measured per leaf and step
        from the guide's change, with a per-texel blend toward the unfiltered moments;
        docs/auto_sigma.md), or ``"sure"`` (an opt-in that picks among 3x the guide's
        mean change per step times 1, 3, 10 at F = 2 .. ``levels`` by Stein's unbiased
        risk estimate, averaged over about ten steps, and the mildest of them once the
        blend has been fully open on the leaf; with its default ``levels``, 5,
        a better worst case on the tuning scenes at 6-10x a fixed sigma_d's update time;
        :func:`postfilter`); a
        pytree prefix of the parameters gives one value per leaf (``{"density":
        "auto", "albedo": 0.1}``). A number is traceable.
      levels: F, the number of a-trous levels (static; footprint radius
        ``2 (2^F - 1)``; ``0`` is Adam); a number or a pytree prefix. The authors'
        ``stride_levels`` is ``levels + 1`` (their first level has stride 0). With
        ``sigma_d="sure"``, the most levels it may choose. None (the default): 3
        (:data:`DEFAULT_LEVELS`), and 5 (:data:`SURE_LEVELS`) for the leaves with
        ``sigma_d="sure"``.
      prefilter: filter the gradient before the moments (``A_t``, eq. 1).
      postfilter: filter the moments before the step (``B_t``, eqs. 6, 8).
      separable: one normalised 1-D pass per spatial axis (True) or all ``5^n`` taps
        per level (False, the authors' kernels).
      guide: ``"params"`` (cross-bilateral: the current parameters, the paper's
        method), ``"self"`` (bilateral, the authors' ``cross_term_off``: each
        filtered field guides itself, every level by its own, partially filtered,
        input; ``m`` and ``v`` then get different weights), or a callable
        ``params -> guide pytree`` (a prefix of the parameters).
      log_guide: guide with ``log(|guide| + 1e-8)`` (the paper's texture runs).
      spatial_axes: ``None`` (the default leaf rule, :func:`default_spatial_axes`), a
        tuple of axes for every leaf, a pytree prefix of tuples (``()`` = not
        filtered), or a callable ``leaf -> axes``.
      mask_unobserved: texels whose gradient is exactly zero in every channel keep
        their moments, get a zero update and are left out of the filter sums.
        Non-finite gradients are always treated this way.
      eps_root: added inside the square root, as in optax's Adam.
      mu_dtype: dtype of the first moment (default: the parameters'); the second
        moment keeps the parameters' dtype.
      filter_m, filter_v: filter only ``m`` or only ``v`` (the authors' ``mtfilter`` /
        ``vtfilter``); with one of them unfiltered the bound of supplement §1.3 no
        longer holds. See :func:`postfilter`.
      second_moment: ``"elementwise"`` (Adam's) or ``"uniform"`` (one second moment
        per leaf, the max of ``B v``: the Dr.Jit port's ``uniform``).
      weight_decay: decoupled weight decay rate (>= 0) or schedule, as in
        :func:`optax.adamw`; None (the default) adds no stage to the chain.
      weight_decay_mask: as :func:`optax.adamw`'s ``mask``: a pytree of bools like
        the parameters (or a callable returning one); True where weight decay applies.

    Returns:
      An ``optax.GradientTransformationExtraArgs``; its ``update`` needs ``params``
      (the guide) unless ``guide="self"`` or every leaf is unfiltered.

    Example::

        >>> import jax, jax.numpy as jnp, optax, optax_bilateral as ob
        >>> params = {"tex": jnp.full((32, 32, 3), 0.5)}
        >>> opt = ob.bilateral_adam(learning_rate=0.05, sigma_d=0.1, levels=3)
        >>> state = opt.init(params)
        >>> loss = lambda p: jnp.mean((p["tex"] - 0.2) ** 2)
        >>> grads = jax.grad(loss)(params)
        >>> updates, state = opt.update(grads, state, params)   # params: the guide
        >>> params = optax.apply_updates(params, updates)
    """
    if b2 is None:
        b2 = 1 - (1 - b1) ** 2
    if weight_decay is not None and not callable(weight_decay):
        check_nonnegative(weight_decay, "weight_decay")
    parts = []
    common: dict[str, Any] = dict(
        sigma_d=sigma_d,
        levels=levels,
        separable=separable,
        guide=guide,
        log_guide=log_guide,
        spatial_axes=spatial_axes,
    )
    if prefilter:
        parts.append(transforms.prefilter(mask_unobserved=mask_unobserved, **common))
    if postfilter:
        parts.append(
            transforms.postfilter(
                b1,
                b2,
                eps,
                mask_unobserved=mask_unobserved,
                eps_root=eps_root,
                mu_dtype=mu_dtype,
                filter_m=filter_m,
                filter_v=filter_v,
                second_moment=second_moment,
                **common,
            )
        )
    else:
        # Unfiltered Adam, with the postfilter's non-finite and overflow policies.
        parts.append(
            transforms.postfilter(
                b1,
                b2,
                eps,
                levels=0,
                mask_unobserved=mask_unobserved,
                eps_root=eps_root,
                mu_dtype=mu_dtype,
                spatial_axes=spatial_axes,
                second_moment=second_moment,
            )
        )
    if weight_decay is not None:
        # Absent when not asked for (decided by None, not by the value, which
        # inject_hyperparams traces): the chain's state is then what it was before.
        parts.append(optax.add_decayed_weights(weight_decay, weight_decay_mask))
    parts.append(optax.scale_by_learning_rate(learning_rate))
    return optax.chain(*parts)
