"""Per-leaf settings: each leaf's spatial axes, levels and sigma_d (``leaf_specs``), and the
checks of the parameters, their dtypes and the updates' shapes."""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from optax_bilateral._src.optimizer import guides
from optax_bilateral._src.optimizer.leaf_rule import (
    SpatialAxesSetting,
    is_axes_atom,
    resolve_axes,
    warn_guesses,
)
from optax_bilateral._src.optimizer.prefix import (
    broadcast_prefix,
    is_scalar_atom,
    is_sigma_atom,
    leaf_names,
)
from optax_bilateral._src.rules import registry
from optax_bilateral._src.rules.sigma import SigmaRule
from optax_bilateral._src.validation import check_levels, check_sigma_d

# F: the benchmark suite's best for auto (docs/auto_sigma.md); the authors' stride_levels = 4.
DEFAULT_LEVELS = 3
"""The default ``levels`` F = 3 of every transform: footprint radius ``2 (2^F - 1) = 14``
texels; the authors' ``stride_levels = 4``. A rule may declare its own
(:meth:`SigmaRule.default_levels`: ``"sure"``'s is ``SURE_LEVELS`` = 5)."""


def default_levels(sigma_d: Any) -> int:
    """A leaf's ``levels`` when the transform's ``levels`` is None (the default): its rule's
    own, else :data:`DEFAULT_LEVELS`."""
    rule = registry.NAMED.get(sigma_d) if isinstance(sigma_d, str) else sigma_d
    own = rule.default_levels() if isinstance(rule, SigmaRule) else None
    return DEFAULT_LEVELS if own is None else own


class LeafSpec(NamedTuple):
    """Static per-leaf filter settings plus the (possibly traced) sigma_d."""

    axes: tuple[int, ...]  # () means "not filtered"
    levels: int
    sigma_d: Any


def leaf_specs(tree, *, spatial_axes, sigma_d, levels, warn: bool = False) -> list[LeafSpec]:
    """Resolves spatial axes, levels and sigma_d for every leaf of ``tree``; ``warn``: one
    warning naming the leaves where the default leaf rule guessed."""
    leaves = jax.tree.leaves(tree)
    names = leaf_names(tree)
    axes_list = broadcast_prefix(spatial_axes, tree, is_axes_atom, "spatial_axes")
    sigma_list = broadcast_prefix(sigma_d, tree, is_sigma_atom, "sigma_d")
    if levels is None:
        levels_list = [None] * len(leaves)
    else:
        levels_list = broadcast_prefix(levels, tree, is_scalar_atom, "levels")
    specs, guesses = [], []
    for leaf, name, ax, sig, lev in zip(leaves, names, axes_list, sigma_list, levels_list):
        lev = default_levels(sig) if lev is None else lev
        lev = check_levels(lev, name=f"levels (for {name})")
        ax, guess = resolve_axes(leaf, ax, name)
        if guess is not None and lev > 0:
            guesses.append(guess)
        if sig is None:
            raise ValueError(f"sigma_d is None for {name}; pass {registry.SETTINGS}")
        if not isinstance(sig, SigmaRule):
            check_sigma_d(sig, name=f"sigma_d (for {name})", names=tuple(registry.NAMED))
        if ax and lev > 0:
            check_floating(
                leaf,
                name,
                "filtered leaves must be floating point, real or complex (integer parameters "
                "have no gradient)",
            )
        specs.append(LeafSpec(ax if lev > 0 else (), lev, sig))
    if warn:
        warn_guesses(guesses)
    return specs


def check_update_shapes(updates, reference, transform: str, what: str = "params") -> None:
    """Raises naming the leaf and both shapes where an update's shape is not its parameter's
    (``reference``: the parameters, or moments shaped like them; None checks nothing), so
    that a gradient is never broadcast against its moments."""
    if reference is None:
        return
    got = jax.tree.leaves(updates)
    try:
        want = jax.tree.structure(updates).flatten_up_to(reference)
    except (TypeError, ValueError) as e:
        raise ValueError(
            f"{transform}: the updates' structure {jax.tree.structure(updates)} is not the "
            f"{what}' {jax.tree.structure(reference)}"
        ) from e
    for g, p, name in zip(got, want, leaf_names(updates)):
        if p is not None and np.shape(g) != np.shape(p):
            raise ValueError(
                f"{transform}: the update for {name} has shape {np.shape(g)}, but its "
                f"{what} have shape {np.shape(p)}; the gradient of each parameter must have "
                "the parameter's shape"
            )


def check_floating(leaf: Any, name: str, why: str) -> None:
    """Raises for a leaf that is not floating point, real or complex."""
    dt = jnp.result_type(leaf)
    if not jnp.issubdtype(dt, jnp.inexact):
        raise TypeError(f"{name} has dtype {dt}; {why}")


def filtered_axes(
    params: Any, *, spatial_axes: SpatialAxesSetting = None, levels: Any = 3
) -> dict[str, tuple[int, ...]]:
    """The spatial axes each leaf of ``params`` is filtered along, ``()`` for none.

    Resolves ``spatial_axes`` and ``levels`` (as given to the transforms; ``None`` is the
    default leaf rule, :func:`default_spatial_axes`) without building an optimizer.

    Args:
      params: the parameters (any pytree of arrays, or of ``jax.ShapeDtypeStruct``).
      spatial_axes: as the transforms' argument: ``None`` or ``"default"`` (the default
        leaf rule), a tuple of axes for every leaf, a pytree prefix of tuples (``()`` = not
        filtered), or a callable ``leaf -> axes``.
      levels: as the transforms' argument (default 3, :data:`DEFAULT_LEVELS`); a leaf with
        ``levels=0`` is not filtered, whatever its axes.

    Returns:
      ``{leaf path: axes}``, e.g. ``{"['tex']": (0, 1), "['w']": ()}``.

    Example::

        >>> import jax.numpy as jnp, optax_bilateral as ob
        >>> ob.filtered_axes({"tex": jnp.zeros((64, 64, 3)), "light": jnp.zeros(())})
        {"['light']": (), "['tex']": (0, 1)}
    """
    specs = leaf_specs(params, spatial_axes=spatial_axes, sigma_d=0.0, levels=levels)
    return {name: spec.axes for name, spec in zip(leaf_names(params, root=""), specs)}


def check_params(params, settings, *, transform: str, all_leaves: bool) -> list[LeafSpec]:
    """Init-time checks: leaf dtypes and dimensions, the settings per leaf, the guide's shapes.

    ``settings`` has the transform's ``spatial_axes``, ``sigma_d``, ``levels`` and ``guide``;
    ``all_leaves``: every leaf must be floating point (it has moments), not only the
    filtered ones.
    """
    specs = settings.specs(params, warn=True)
    names = leaf_names(params)
    leaves = jax.tree.leaves(params)
    if all_leaves:
        for leaf, name in zip(leaves, names):
            check_floating(
                leaf,
                name,
                f"{transform} keeps Adam moments for every leaf, which "
                "needs floating point parameters (real or complex) (exclude other leaves with "
                "optax.multi_transform)",
            )
    guides.check_shapes(settings.guide, params, specs)
    return specs
