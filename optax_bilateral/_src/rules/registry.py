"""The ``sigma_d`` settings a transform takes, and the rule each one names.

``sigma_d`` is a number (:class:`~optax_bilateral._src.fixed.Fixed`), ``"auto"``,
``"sure"`` or ``"sparse"`` (the rules with their default constants), a rule object
(:func:`auto_sigma`, :func:`sure_sigma`, :func:`sparse_sigma`, or a :class:`SigmaRule` of
one's own), or a pytree
prefix of the parameters holding one of those per subtree.
"""

from __future__ import annotations

import warnings
from collections.abc import Mapping, Sequence
from typing import Literal, TypeAlias

import jax

from optax_bilateral._src.rules.auto import Auto
from optax_bilateral._src.rules.fixed import Fixed
from optax_bilateral._src.rules.sigma import SigmaRule
from optax_bilateral._src.rules.sparse import Sparse
from optax_bilateral._src.rules.sure import Sure

SigmaD: TypeAlias = float | jax.Array | Literal["auto", "sure", "sparse"] | SigmaRule
"""One leaf's ``sigma_d``: a number (>= 0, in the guide's units; ``inf`` is a low-pass),
``"auto"``, ``"sure"``, ``"sparse"`` or a rule object."""
SigmaSetting: TypeAlias = "SigmaD | Mapping[str, SigmaSetting] | Sequence[SigmaSetting]"
"""A transform's ``sigma_d``: one :data:`SigmaD` for every leaf, or a pytree prefix of the
parameters (``{"density": "auto", "albedo": 0.1}``)."""
LevelsSetting: TypeAlias = "int | Mapping[str, LevelsSetting] | Sequence[LevelsSetting] | None"
"""A transform's ``levels``: F (a non-negative int) for every leaf, None (the default), or a
pytree prefix of the parameters."""

NAMED = {"auto": Auto(), "sure": Sure(), "sparse": Sparse()}
"""The shorthands a ``sigma_d`` may name, and the rules they stand for."""
# Chosen from the data every step (docs/auto_sigma.md): no number suits every problem.
DEFAULT_SIGMA_D = "auto"
"""The default ``sigma_d`` of every transform: ``"auto"``, chosen per leaf and step from the
guide's change (docs/auto_sigma.md); a number (>= 0, in the guide's units) fixes it."""
SPARSE_SIGMA_D = Sparse(sparse_levels=0, full_coverage=0.8)
"""The default ``sigma_d`` of :func:`optax_bilateral.sparse_adam`: ``"sparse"`` without its
extra filter level and with a coverage of 0.8 counted as full (:class:`Sparse`), ``"auto"``
corrected for gradients that touch few texels a step; the coarse path beside it gives the far
reach (docs/research/camera_distance.md)."""
SETTINGS = (
    "a number >= 0 (inf for a low-pass), 'auto', 'sure', 'sparse' or a sigma_d rule "
    "(ob.auto_sigma(), ob.sure_sigma(), ob.sparse_sigma())"
)
"""What a ``sigma_d`` may be, for error messages."""


def resolve(sigma_d: SigmaD) -> SigmaRule:
    """The rule a leaf's ``sigma_d`` names."""
    if isinstance(sigma_d, SigmaRule):
        return sigma_d
    if isinstance(sigma_d, str):
        return NAMED[sigma_d]
    return Fixed(sigma_d)


def auto_sigma(**constants) -> Auto:
    """``sigma_d="auto"`` with other constants: ``auto_sigma()`` is ``"auto"``.

    Each keyword is a field of :class:`Auto` (``rate_factor``, ``step_factor``,
    ``contrast_factor``, ``residual_decay``, ``gain``, ``power``, ``gate_bounds``,
    ``check_period``, ``min_texels``, ``correlated``, ``noisy``, ``heavy_factor``,
    ``heavy_levels``);
    docs/auto_sigma.md derives the defaults. The result is frozen and hashable: a setting is
    a constant of the compiled update, and another setting is another program.

    Args:
      **constants: the fields to change.

    Returns:
      An :class:`Auto` rule, to pass as ``sigma_d`` (or in a pytree prefix of them).

    Raises:
      TypeError: for a keyword that is not a field.
      ValueError: naming the field, for a value out of its range.

    Example::

        >>> import optax_bilateral as ob
        >>> rule = ob.auto_sigma(check_period=4)
        >>> rule == ob.auto_sigma(check_period=4), rule.rate_factor
        (True, 1.0)
        >>> opt = ob.bilateral_adam(0.02, sigma_d=rule)
    """
    if "gate" in constants:  # the field's former name; AutoState.gate is the gate's value
        warnings.warn(
            "auto_sigma(gate=...) is deprecated and will be removed in a future release: the "
            "field is gate_bounds (AutoState.gate is how far the gate is open)",
            DeprecationWarning,
            stacklevel=2,
        )
        constants["gate_bounds"] = constants.pop("gate")
    return Auto(**constants)


def sure_sigma(**constants) -> Sure:
    """``sigma_d="sure"`` with other constants: ``sure_sigma()`` is ``"sure"``.

    Each keyword is a field of :class:`Sure` (``factors``, ``min_levels``,
    ``variance_weight``, ``risk_decay``, ``first_factor``, and ``auto``: the
    :func:`auto_sigma` rule whose scale, sub-grid and blend it uses).

    Args:
      **constants: the fields to change.

    Returns:
      A :class:`Sure` rule, to pass as a postfilter's ``sigma_d``.

    Raises:
      TypeError: for a keyword that is not a field.
      ValueError: naming the field, for a value out of its range.

    Example::

        >>> import optax_bilateral as ob
        >>> ob.sure_sigma(factors=(1.0, 3.0)).factors
        (1.0, 3.0)
    """
    return Sure(**constants)


def sparse_sigma(**constants) -> Sparse:
    """``sigma_d="sparse"`` with other constants: ``sparse_sigma()`` is ``"sparse"``.

    Each keyword is a field of :class:`Sparse` (``block``, ``decay``, ``max_boost``,
    ``sparse_below``, ``sparse_levels``, ``full_coverage``, and ``auto``: the
    :func:`auto_sigma` rule it runs).

    Args:
      **constants: the fields to change.

    Returns:
      A :class:`Sparse` rule, to pass as a postfilter's ``sigma_d``.

    Raises:
      TypeError: for a keyword that is not a field.
      ValueError: naming the field, for a value out of its range.

    Example::

        >>> import optax_bilateral as ob
        >>> ob.sparse_sigma(sparse_levels=2).sparse_levels
        2
    """
    return Sparse(**constants)
