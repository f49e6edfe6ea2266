"""The guide of each filtered leaf: ``"params"``, ``"self"`` or a callable, checked at ``init``
and resolved at every update (with the log guide where asked)."""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import jax
import numpy as np

from optax_bilateral._src.filter.bilateral import log_transform
from optax_bilateral._src.optimizer.prefix import broadcast_prefix, leaf_names

if TYPE_CHECKING:
    from optax_bilateral._src.optimizer.leaves import LeafSpec

# "params" | "self" | a callable params -> guide pytree (a prefix of the parameters).
GuideSetting = str | Callable[[Any], Any]


def check_guide(guide) -> None:
    if not (guide in ("params", "self") or callable(guide)):
        raise ValueError(
            f"guide must be 'params', 'self' or a callable params -> guide pytree, got {guide!r}"
        )


def guide_spatial_shape(guide_shape, leaf_shape, axes, name):
    """The guide's spatial shape under :func:`atrous_bilateral`'s rule, or a clear error."""
    if len(guide_shape) == len(axes):
        return tuple(guide_shape)
    if len(guide_shape) < len(axes) or any(a >= len(guide_shape) for a in axes):
        raise ValueError(
            f"guide for {name} has shape {tuple(guide_shape)}, which "
            f"lacks the spatial axes {axes} of the leaf (shape {tuple(leaf_shape)})"
        )
    return tuple(guide_shape[a] for a in axes)


def guide_leaves(
    guide, params, tree, specs: list[LeafSpec], log_guide: bool, transform: str
) -> list:
    """The guide array for every leaf (None where the leaf is not filtered or guide='self')."""
    if guide == "self" or not any(s.axes for s in specs):
        return [None] * len(specs)
    if params is None:
        raise ValueError(
            f"{transform} uses guide={guide!r}, which needs the current parameters: "
            f"call update(updates, state, params=params)"
        )
    if guide == "params":
        g = jax.tree.leaves(params)
        if len(g) != len(specs):
            raise ValueError(
                f"params has {len(g)} leaves but the updates have {len(specs)}; "
                "they must have the same structure"
            )
    else:
        g = broadcast_prefix(
            guide(params),
            tree,
            lambda x: x is None or hasattr(x, "shape"),
            "the guide callable's result",
        )
        for x, s, name in zip(g, specs, leaf_names(tree)):
            if x is None and s.axes:
                raise ValueError(
                    f"guide returned None for {name}, which is filtered; return "
                    "an array for it or give it spatial_axes=()"
                )
    return [log_transform(x) if (log_guide and x is not None) else x for x in g]


def check_shapes(guide: GuideSetting, params, specs: list[LeafSpec]) -> None:
    """Init-time check of a callable guide: an array for every filtered leaf, covering the
    leaf's grid (``"params"`` and ``"self"`` cover it by construction)."""
    if not callable(guide) or not any(s.axes for s in specs):
        return
    names, leaves = leaf_names(params), jax.tree.leaves(params)
    shapes = jax.eval_shape(guide, params)
    g_list = broadcast_prefix(
        shapes,
        params,
        lambda x: x is None or hasattr(x, "shape"),
        "the guide callable's result",
    )
    for leaf, name, spec, leaf_guide in zip(leaves, names, specs, g_list):
        if not spec.axes:
            continue
        if leaf_guide is None:
            raise ValueError(
                f"guide returned None for {name}, which is filtered "
                f"(spatial axes {spec.axes}); return an array for it or give it "
                "spatial_axes=()"
            )
        want = tuple(np.shape(leaf)[a] for a in spec.axes)
        got = guide_spatial_shape(leaf_guide.shape, np.shape(leaf), spec.axes, name)
        if got != want:
            raise ValueError(
                f"guide for {name} has spatial shape {got} but the leaf "
                f"has {want} along spatial_axes {spec.axes}: the guide must cover "
                "the same grid"
            )
