"""``sigma_d="sure"``: the step scale (3x the guide's mean change per step, a prefilter's
``"auto"`` scale) times one of a few factors, or no filter, chosen per leaf and step by
Stein's unbiased risk estimate.

Derived and measured in docs/auto_sigma.md (section ``sigma_d="sure"``). For a fixed guide the
postfilter ``B`` is linear, so with a sample ``zeta`` of the noise of ``m_hat`` the risk
of a candidate ``B`` is estimated without the true moments:

    risk(B) = sum_i (m_hat - B m_hat)_i^2 - ((I - B) zeta)_i^2 + W (B zeta)_i^2

(the bias's square, unbiased, then the filtered noise's variance, weighted by ``W``:
``W = 1`` is SURE, ``W < 1`` discounts the noise the optimiser averages out over steps).
No filter is a candidate too, with risk ``W sum zeta^2``. The noise sample is the
difference of successive gradients, ``sqrt(rho / 2) (g_t - g_{t-1})`` (``rho``: the
variance ratio of Adam's bias-corrected EMA), which keeps the noise's correlation between
neighbours (a renderer's splats, a transposed blur). The chosen ``B`` filters both ``m``
and ``v`` (``v`` only once chosen: the risks need ``B m`` and ``B zeta``), then ``"auto"``'s
blend follows: one non-negative, row-stochastic operator, so the step stays bounded
(supplement §1.3).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax import lax

from optax_bilateral._src import sharded

SURE = "sure"
FACTORS = (1.0, 3.0, 10.0)  # the candidates' sigma_d, times the step scale
VARIANCE_WEIGHT = 0.4  # W
FIRST = 1  # the candidate before the noise can be estimated (t = 1, or b1 = 0)


class SureState(NamedTuple):
    """One leaf's state for ``sigma_d="sure"`` (in :class:`PostfilterState`).

    Attributes:
      previous_guide: the guide the last update saw (the step scale).
      residual: ``"auto"``'s residual EMA of ``m_hat - B m_hat`` (the blend).
      previous_gradient: the gradient the last update saw, in the moments' arithmetic
        dtype (the noise sample is its difference from this step's).
      sigma_d: the sigma_d the last update chose, a scalar; 0 where it chose no filter
        (and where the guide is constant, which every sigma_d filters alike).

    Example::

        >>> import jax.numpy as jnp, optax_bilateral as ob
        >>> state = ob.postfilter(sigma_d="sure").init({"tex": jnp.ones((16, 16, 3))})
        >>> sure = state.auto["tex"]
        >>> type(sure).__name__, sure.previous_gradient.shape, float(sure.sigma_d)
        ('SureState', (16, 16, 3), 0.0)
    """

    previous_guide: jax.Array
    residual: jax.Array
    previous_gradient: jax.Array
    sigma_d: jax.Array


def is_sure(sigma_d) -> bool:
    return isinstance(sigma_d, str) and sigma_d == SURE


def noise_sample(g, previous, ratio, usable):
    """A sample of the noise of ``m_hat``: ``sqrt(ratio / 2) (g_t - g_{t-1})`` (0 until the
    noise can be estimated)."""
    return jnp.where(usable, jnp.sqrt(ratio / 2) * (g - previous), 0).astype(g.dtype)


def choose(m, zeta, candidates, scale, c1, usable, observed):
    """``(B m, sigma_d, filtered)`` of the candidate ``(B m, B zeta)`` of least estimated
    risk, or ``(m, 0, False)`` for no filter; the middle factor until ``usable``.

    ``m`` is the raw first moment (``m / c1`` is ``m_hat``); ``candidates`` has one
    ``(B m, B zeta)`` per factor of ``scale``; ``observed`` (full shape) or None leaves
    unobserved entries out of the sums. The caller filters ``v`` at the returned sigma_d
    (if ``filtered``), so both moments get the chosen operator.
    """
    keep = (lambda x: x) if observed is None else (lambda x: jnp.where(observed, x, 0))
    risks = []
    for bm, bz in candidates:
        bias = _norm2(keep(m - bm)) / c1**2 - _norm2(keep(zeta - bz))
        risks.append(bias + VARIANCE_WEIGHT * _norm2(keep(bz)))
    risks.append(VARIANCE_WEIGHT * _norm2(keep(zeta)))
    # An overflowing risk is no evidence for its candidate.
    risks = jnp.nan_to_num(jnp.stack(risks), nan=jnp.inf)
    pick = jnp.where(usable, jnp.argmin(risks), FIRST).astype(jnp.int32)
    m_f = lax.select_n(pick, *(c[0] for c in candidates), m)
    sigma_d = jnp.append(jnp.asarray(FACTORS, scale.dtype) * scale, 0)[pick]
    return m_f, sigma_d, pick < len(FACTORS)


def _norm2(x):
    """``sum(x^2)``: as a contraction over every axis on one device (XLA's CPU backend runs a
    dot several times faster than a fused elementwise reduction); a sum where ``x`` is split
    over an explicit mesh (a contraction of split axes needs its output sharding named)."""
    if sharded.is_split(x):
        return jnp.sum(x * x)
    return jnp.tensordot(x, x, axes=x.ndim)
