"""Settings given per leaf: one value for every leaf, or a pytree *prefix* of the parameters
(one value per subtree), broadcast to one value per leaf; and each leaf's readable path."""

from __future__ import annotations

import numbers
from collections.abc import Callable
from typing import Any

import jax
import numpy as np

from optax_bilateral._src.rules.sigma import SigmaRule


class _Box:
    """Keeps a per-leaf value atomic while it is broadcast over a subtree."""

    __slots__ = ("value",)

    def __init__(self, value):
        self.value = value


def is_scalar_atom(x) -> bool:
    return (
        x is None
        or isinstance(x, (numbers.Number, np.ndarray, jax.Array, np.generic))
        or hasattr(x, "dtype")
    )


def is_sigma_atom(x) -> bool:
    """One leaf's ``sigma_d`` inside a pytree prefix: a number, an array, None, a name or a
    rule object."""
    return is_scalar_atom(x) or isinstance(x, (str, SigmaRule))


def broadcast_prefix(prefix, tree, is_atom: Callable[[Any], bool], name: str) -> list:
    """One value of ``prefix`` per leaf of ``tree`` (in ``jax.tree.leaves`` order)."""
    n = len(jax.tree.leaves(tree))
    if is_atom(prefix):
        return [prefix] * n
    try:
        boxed = jax.tree.map(
            lambda p, sub: jax.tree.map(lambda _: _Box(p), sub), prefix, tree, is_leaf=is_atom
        )
    except (ValueError, TypeError) as e:
        raise ValueError(
            f"{name} must be a single value or a pytree prefix of the parameters "
            f"(one value per subtree); its structure does not match: {e}"
        ) from None
    values = [b.value for b in jax.tree.leaves(boxed, is_leaf=lambda x: isinstance(x, _Box))]
    if len(values) != n:
        raise ValueError(f"{name}: expected one value per parameter leaf ({n}), got {len(values)}")
    return values


def leaf_names(tree, root: str = "params") -> list[str]:
    """A readable path per leaf from ``root``, for messages: ``params['tex']``,
    ``params[0].albedo``, ``params`` for a bare array. With ``root=""``, the bare key path
    (``['tex']``; ``(the root)`` for a bare array), as :func:`filtered_axes` and saved
    checkpoints name leaves."""
    paths = jax.tree_util.tree_flatten_with_path(tree)[0]
    if root:
        return [root + jax.tree_util.keystr(p) for p, _ in paths]
    return [jax.tree_util.keystr(p) or "(the root)" for p, _ in paths]
