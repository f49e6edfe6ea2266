"""``bilateral_adam``: the paper's optimizer as one ``optax.chain``."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import jax
import optax

from optax_bilateral._src import transforms

if TYPE_CHECKING:
    from optax_bilateral._src.leaves import GuideSetting, SpatialAxesSetting


def bilateral_adam(
    learning_rate: optax.ScalarOrSchedule,
    b1: jax.typing.ArrayLike = 0.2,
    b2: jax.typing.ArrayLike | None = None,
    eps: jax.typing.ArrayLike = 1e-8,
    *,
    sigma_d: Any = transforms.DEFAULT_SIGMA_D,
    levels: Any = transforms.DEFAULT_LEVELS,
    prefilter: bool = False,
    postfilter: bool = True,
    separable: bool = True,
    guide: GuideSetting = "params",
    log_guide: bool = False,
    spatial_axes: SpatialAxesSetting = None,
    mask_unobserved: bool = False,
    eps_root: jax.typing.ArrayLike = 0.0,
    mu_dtype: Any = None,
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
    gradients of moderate size (README.md, "Robustness", lists the extremes).

    Defaults follow the paper's grid runs: ``b1 = 0.2``, ``b2 = 1 - (1 - b1)^2``
    (= 0.36), postfilter only, ``levels = 5``. ``sigma_d = 0.1`` suits
    parameters in a unit range and log-domain guides (a guide step of 0.1 weighs
    ``e^-1``); the texture experiment's sweep in the README measures it.

    ``learning_rate`` and ``sigma_d`` can be schedules through
    ``optax.inject_hyperparams(bilateral_adam, static_args=("levels",))``.

    Args:
      learning_rate: a number or an optax schedule.
      b1, b2, eps, eps_root, mu_dtype: as in Adam; ``b2=None`` is ``1-(1-b1)^2``.
      sigma_d, levels, separable, guide, log_guide, spatial_axes, mask_unobserved:
        see :func:`postfilter`.
      prefilter, postfilter: which spatial filters to apply.

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
            )
        )
    parts.append(optax.scale_by_learning_rate(learning_rate))
    return optax.chain(*parts)
