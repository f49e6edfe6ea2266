"""``sigma_d="sure"``: the step scale (3x the guide's mean change per step, a prefilter's
``"auto"`` scale) times one of a few factors, at one of the levels ``F = 2 .. levels``,
chosen per leaf and step by Stein's unbiased risk estimate.

Derived and measured in docs/auto_sigma.md (section ``sigma_d="sure"``). For a fixed guide the
postfilter ``B`` is linear, so with a sample ``zeta`` of the noise of ``m_hat`` the risk
of a candidate ``B`` is estimated without the true moments:

    risk(B) = sum_i (m_hat - B m_hat)_i^2 - ((I - B) zeta)_i^2 + W (B zeta)_i^2

(the bias's square, unbiased, then the filtered noise's variance, weighted by ``W``:
``W = 1`` is SURE, ``W < 1`` discounts the noise the optimiser averages out over steps).
One step's estimate is noisy, and a choice that flips from step to step blurs more than a
steady one; so each step's risks, over their largest magnitude (every step one vote),
enter an exponential moving average over steps, and its least entry is chosen.
No filter is not a candidate: with ``W < 1`` it wins on a noisy risk estimate late in a
run, and one unfiltered Adam step then moves every entry by a learning rate. The noise
sample is the difference of successive gradients, ``sqrt(rho / 2) (g_t - g_{t-1})`` (``rho``: the
variance ratio of Adam's bias-corrected EMA), which keeps the noise's correlation between
neighbours (a renderer's splats, a transposed blur). The candidates of one factor are one
cascade, read after each F (``atrous_bilateral``'s ``first_level``). The chosen ``B``
filters both ``m`` and ``v`` (``v`` only once chosen: the risks need ``B m`` and
``B zeta``), then ``"auto"``'s blend follows: one non-negative, row-stochastic operator,
so the step stays bounded (supplement §1.3).

Once the blend's gate has been fully open on a leaf (the filter's residual persisted over
most of it: its guide does not predict its gradient, as on an i.i.d. target), the leaf takes
the mildest candidate, ``FACTORS[0]`` at the least F, for the rest of the run: that bias is
small against one step's noise, so the per-step risk cannot see it, and late in a run, once
the gate has closed again, it would choose a deeper filter.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax import lax

from optax_bilateral._src import sharded

SURE = "sure"
FACTORS = (1.0, 3.0, 10.0)  # the candidates' sigma_d, times the step scale
MIN_LEVELS = 2  # the candidates' F: MIN_LEVELS .. the leaf's levels
VARIANCE_WEIGHT = 0.1  # W
RISK_DECAY = 0.9  # the risks' moving average over steps (~10 steps)
FIRST_FACTOR = 3.0  # before the noise is known (t = 1, or b1 = 0): this factor, the middle F


class SureState(NamedTuple):
    """One leaf's state for ``sigma_d="sure"`` (in :class:`PostfilterState`).

    Attributes:
      previous_guide: the guide the last update saw (the step scale; on a large leaf its
        sub-grid, as :attr:`AutoState.previous_guide`).
      residual: ``"auto"``'s residual EMA of ``m_hat - B m_hat`` (the blend).
      previous_gradient: the gradient the last update saw, in the moments' arithmetic
        dtype (the noise sample is its difference from this step's).
      sigma_d: the sigma_d the last update chose, a scalar (0 before the first update, and
        where the guide is constant, which every sigma_d filters alike).
      levels: the F the last update chose (int32 scalar; 0 before the first update).
      risks: the moving average of every candidate's estimated risk, each step's over its
        largest magnitude, in :func:`labels`' order (0 before the noise is known).
      opened: 1 once the blend's gate has been fully open at a step, else 0 (a scalar); from
        then on the leaf takes the mildest candidate.

    Example::

        >>> import jax.numpy as jnp, optax_bilateral as ob
        >>> state = ob.postfilter(sigma_d="sure").init({"tex": jnp.ones((16, 16, 3))})
        >>> sure = state.auto["tex"]
        >>> type(sure).__name__, sure.previous_gradient.shape, float(sure.sigma_d)
        ('SureState', (16, 16, 3), 0.0)
        >>> int(sure.levels), sure.risks.shape   # 3 factors at F = 2 .. 5 (SURE_LEVELS)
        (0, (12,))
        >>> float(sure.opened)
        0.0
    """

    previous_guide: jax.Array
    residual: jax.Array
    previous_gradient: jax.Array
    sigma_d: jax.Array
    levels: jax.Array
    risks: jax.Array
    opened: jax.Array


def is_sure(sigma_d) -> bool:
    return isinstance(sigma_d, str) and sigma_d == SURE


def level_choices(levels: int) -> tuple[int, ...]:
    """The candidates' F for a leaf filtered with ``levels`` levels at most."""
    return tuple(range(min(MIN_LEVELS, levels), levels + 1))


def count(levels: int) -> int:
    """How many candidates a leaf filtered with ``levels`` levels at most has."""
    return len(FACTORS) * len(level_choices(levels))


def labels(levels: int, scale: jax.Array) -> tuple[jax.Array, jax.Array]:
    """``(sigma_d, F)`` of every candidate, in :func:`choose`'s order (factor-major)."""
    choices = level_choices(levels)
    sigma_d = jnp.stack([f * scale for f in FACTORS for _ in choices])
    return sigma_d, jnp.asarray([n for _ in FACTORS for n in choices], jnp.int32)


def first(levels: int) -> int:
    """The candidate taken before the noise can be estimated: ``FIRST_FACTOR`` at the middle F."""
    choices = level_choices(levels)
    return FACTORS.index(FIRST_FACTOR) * len(choices) + len(choices) // 2


def candidates(fields, levels: int, scale, filter_at) -> list:
    """Every candidate's filter of ``fields``, in :func:`choose`'s order: per factor one
    cascade, read after each F. ``filter_at(fields, sigma_d, levels, first_level)`` runs
    levels ``first_level .. levels - 1`` of the leaf's filter."""
    out = []
    for factor in FACTORS:
        x, done = fields, 0
        for n in level_choices(levels):
            x = filter_at(x, factor * scale, n, done)
            out.append(x)
            done = n
    return out


def noise_sample(g, previous, ratio, usable):
    """A sample of the noise of ``m_hat``: ``sqrt(ratio / 2) (g_t - g_{t-1})`` (0 until the
    noise can be estimated)."""
    return jnp.where(usable, jnp.sqrt(ratio / 2) * (g - previous), 0).astype(g.dtype)


def choose(m, zeta, candidates, c1, usable, observed, first_pick, previous_risks=None, opened=None):
    """``(B m, pick, risks)``: the candidate ``(B m, B zeta)`` of least moving-average risk
    (``first_pick`` until ``usable``) and the new average.

    ``m`` is the raw first moment (``m / c1`` is ``m_hat``); ``observed`` (full shape) or
    None leaves unobserved entries out of the sums; ``previous_risks`` is the average so
    far (None: none, so this step's estimate alone decides); ``opened`` (a scalar, see
    :attr:`SureState.opened`) > 0 takes the mildest candidate once usable. The caller
    filters ``v`` with the chosen operator, so both moments get it.
    """
    keep = (lambda x: x) if observed is None else (lambda x: jnp.where(observed, x, 0))
    risks = []
    for bm, bz in candidates:
        bias = _norm2(keep(m - bm)) / c1**2 - _norm2(keep(zeta - bz))
        risks.append(bias + VARIANCE_WEIGHT * _norm2(keep(bz)))
    risks = _votes(jnp.stack(risks))
    previous = jnp.zeros_like(risks) if previous_risks is None else previous_risks
    previous = previous.astype(risks.dtype)
    risks = jnp.where(usable, RISK_DECAY * previous + (1 - RISK_DECAY) * risks, previous)
    best = jnp.argmin(risks)
    if opened is not None:  # the mildest candidate, the first: FACTORS[0] at the least F
        best = jnp.where(opened > 0, 0, best)
    pick = jnp.where(usable, best, first_pick).astype(jnp.int32)
    return lax.select_n(pick, *(c[0] for c in candidates)), pick, risks


def _votes(risks):
    """One step's risks over their largest finite magnitude, so each step weighs the same in
    the average (the risks shrink as the optimiser converges); an overflowing risk is no
    evidence for its candidate: 2, worse than any finite one."""
    finite = jnp.isfinite(risks)
    largest = jnp.max(jnp.where(finite, jnp.abs(risks), 0))
    scaled = risks / jnp.maximum(largest, jnp.finfo(risks.dtype).tiny)
    return jnp.where(finite, scaled, 2)


def _norm2(x):
    """``sum(x^2)``: as a contraction over every axis on one device (XLA's CPU backend runs a
    dot several times faster than a fused elementwise reduction); a sum where ``x`` is split
    over an explicit mesh (a contraction of split axes needs its output sharding named)."""
    if sharded.is_split(x):
        return jnp.sum(x * x)
    return jnp.tensordot(x, x, axes=x.ndim)
