"""Per-leaf settings: which axes of each parameter leaf are spatial, its sigma_d, levels, guide.

A setting is given once for all leaves, or as a pytree *prefix* of the parameters
(one value per subtree), or (for ``spatial_axes``) as a callable ``leaf -> axes``.
"""

from __future__ import annotations

import numbers
from typing import Any, Callable, NamedTuple, Union

import jax
import jax.numpy as jnp
import numpy as np

from optax_bilateral._src.validation import check_levels, check_sigma_d, normalize_axes

LOG_GUIDE_EPS = 1e-8  # log(|theta| + 1e-8), as the authors' texture runs


def default_spatial_axes(leaf) -> tuple[int, ...]:
    """The default leaf rule.

    * 0-D and 1-D leaves (scalars, vectors): ``()``, not filtered (plain Adam);
    * 2-D leaves ``(H, W)``: both axes spatial;
    * N-D leaves, N >= 3: all but the last axis spatial (channels-last:
      ``(H, W, C)`` textures, ``(D, H, W, C)`` volumes).
    """
    nd = np.ndim(leaf)
    if nd <= 1:
        return ()
    if nd == 2:
        return (0, 1)
    return tuple(range(nd - 1))


class _Box:
    """Keeps a per-leaf value atomic while it is broadcast over a subtree."""

    __slots__ = ("value",)

    def __init__(self, value):
        self.value = value


def _is_axes_atom(x) -> bool:
    return (x is None or callable(x) or isinstance(x, numbers.Integral)
            or (isinstance(x, (tuple, list))
                and all(isinstance(a, numbers.Integral) and not isinstance(a, bool) for a in x)))


def _is_scalar_atom(x) -> bool:
    return x is None or isinstance(x, (numbers.Number, np.ndarray, jax.Array, np.generic)) \
        or hasattr(x, "dtype")


def broadcast_prefix(prefix, tree, is_atom: Callable[[Any], bool], name: str) -> list:
    """One value of ``prefix`` per leaf of ``tree`` (in ``jax.tree.leaves`` order)."""
    n = len(jax.tree.leaves(tree))
    if is_atom(prefix):
        return [prefix] * n
    try:
        boxed = jax.tree.map(
            lambda p, sub: jax.tree.map(lambda _: _Box(p), sub), prefix, tree, is_leaf=is_atom)
    except (ValueError, TypeError) as e:
        raise ValueError(
            f"{name} must be a single value or a pytree prefix of the parameters "
            f"(one value per subtree); its structure does not match: {e}") from None
    values = [b.value for b in jax.tree.leaves(boxed, is_leaf=lambda x: isinstance(x, _Box))]
    if len(values) != n:
        raise ValueError(f"{name}: expected one value per parameter leaf ({n}), got {len(values)}")
    return values


class LeafSpec(NamedTuple):
    """Static per-leaf filter settings plus the (possibly traced) sigma_d."""

    axes: tuple[int, ...]   # () means "not filtered"
    levels: int
    sigma_d: Any


def leaf_names(tree) -> list[str]:
    """A readable path per leaf (``['tex']``, ``[0].albedo``) for error messages."""
    paths = jax.tree_util.tree_flatten_with_path(tree)[0]
    return [jax.tree_util.keystr(p) or "(the root)" for p, _ in paths]


def check_spatial_axes_setting(spatial_axes) -> None:
    """Construction-time check of ``spatial_axes`` (ranges need the leaves: see :func:`leaf_specs`)."""
    atoms = jax.tree.leaves(spatial_axes, is_leaf=_is_axes_atom)
    for ax in atoms:
        if ax is None or callable(ax):
            continue
        if not _is_axes_atom(ax):
            raise TypeError(f"spatial_axes must be None, a tuple of ints, a pytree prefix of such "
                            f"tuples or a callable leaf -> axes; found {ax!r}")
        ax = (ax,) if isinstance(ax, numbers.Integral) else tuple(ax)
        if len(set(ax)) != len(ax):
            raise ValueError(f"spatial_axes={ax} repeats an axis")


def leaf_specs(tree, *, spatial_axes, sigma_d, levels) -> list[LeafSpec]:
    """Resolves spatial axes, levels and sigma_d for every leaf of ``tree``."""
    leaves = jax.tree.leaves(tree)
    names = leaf_names(tree)
    axes_list = broadcast_prefix(spatial_axes, tree, _is_axes_atom, "spatial_axes")
    sigma_list = broadcast_prefix(sigma_d, tree, _is_scalar_atom, "sigma_d")
    levels_list = broadcast_prefix(levels, tree, _is_scalar_atom, "levels")
    specs = []
    for i, (leaf, ax, sig, lev) in enumerate(zip(leaves, axes_list, sigma_list, levels_list)):
        name = names[i]
        if ax is None:
            ax = default_spatial_axes(leaf)
        elif callable(ax):
            ax = ax(leaf)
            ax = default_spatial_axes(leaf) if ax is None else ax
        ax = tuple(ax) if isinstance(ax, (tuple, list)) else (ax,)
        nd = np.ndim(leaf)
        if len(ax) > nd:
            raise ValueError(f"spatial_axes={ax} asks for {len(ax)} spatial axes but parameter "
                             f"leaf {name} has shape {np.shape(leaf)} ({nd} dimension(s))")
        ax = normalize_axes(ax, nd, name=f"spatial_axes (for leaf {name}, shape {np.shape(leaf)})")
        lev = check_levels(lev, name=f"levels (for leaf {name})")
        if sig is None:
            raise ValueError(f"sigma_d is None for leaf {name}; pass a number (inf for a low-pass)")
        check_sigma_d(sig, name=f"sigma_d (for leaf {name})")
        if ax and lev > 0:
            dt = jnp.result_type(leaf)
            if not jnp.issubdtype(dt, jnp.floating):
                raise TypeError(f"params leaf {name} has dtype {dt}; filtered leaves must be "
                                "floating point (integer parameters have no gradient)")
        specs.append(LeafSpec(ax if lev > 0 else (), lev, sig))
    return specs


def _guide_spatial_shape(guide_shape, leaf_shape, axes, name):
    """The guide's spatial shape under :func:`atrous_bilateral`'s rule, or a clear error."""
    if len(guide_shape) == len(axes):
        return tuple(guide_shape)
    if len(guide_shape) < len(axes) or any(a >= len(guide_shape) for a in axes):
        raise ValueError(f"guide for params leaf {name} has shape {tuple(guide_shape)}, which "
                         f"lacks the spatial axes {axes} of the leaf (shape {tuple(leaf_shape)})")
    return tuple(guide_shape[a] for a in axes)


def check_params(params, *, spatial_axes, sigma_d, levels, guide, transform: str,
                 all_leaves: bool) -> list[LeafSpec]:
    """Init-time checks: leaf dtypes and dimensions, the settings per leaf, the guide's shapes.

    ``all_leaves``: every leaf must be floating point (it has moments), not only the
    filtered ones.
    """
    specs = leaf_specs(params, spatial_axes=spatial_axes, sigma_d=sigma_d, levels=levels)
    names = leaf_names(params)
    leaves = jax.tree.leaves(params)
    if all_leaves:
        for leaf, name in zip(leaves, names):
            dt = jnp.result_type(leaf)
            if not jnp.issubdtype(dt, jnp.floating):
                raise TypeError(f"params leaf {name} has dtype {dt}; {transform} keeps Adam moments "
                                "for every leaf, which needs real floating point parameters "
                                "(exclude other leaves with optax.multi_transform)")
    if callable(guide) and guide not in ("params", "self") and any(s.axes for s in specs):
        shapes = jax.eval_shape(guide, params)
        g_list = broadcast_prefix(shapes, params, lambda x: x is None or hasattr(x, "shape"),
                                  "the guide callable's result")
        for leaf, name, spec, leaf_guide in zip(leaves, names, specs, g_list):
            if not spec.axes:
                continue
            if leaf_guide is None:
                raise ValueError(f"guide returned None for params leaf {name}, which is filtered "
                                 f"(spatial axes {spec.axes}); return an array for it or give it "
                                 "spatial_axes=()")
            want = tuple(np.shape(leaf)[a] for a in spec.axes)
            got = _guide_spatial_shape(leaf_guide.shape, np.shape(leaf), spec.axes, name)
            if got != want:
                raise ValueError(f"guide for params leaf {name} has spatial shape {got} but the leaf "
                                 f"has {want} along spatial_axes {spec.axes}: the guide must cover "
                                 "the same grid")
    return specs


# "params" | "self" | a callable params -> guide pytree (a prefix of the parameters).
GuideSetting = Union[str, Callable[[Any], Any]]
# None (the default rule) | a tuple of ints | a pytree prefix of tuples | a callable leaf -> axes.
SpatialAxesSetting = Any


def check_guide(guide) -> None:
    if not (guide in ("params", "self") or callable(guide)):
        raise ValueError(f"guide must be 'params', 'self' or a callable params -> guide pytree, "
                         f"got {guide!r}")


def guide_leaves(guide, params, tree, specs: list[LeafSpec], log_guide: bool, transform: str) -> list:
    """The guide array for every leaf (None where the leaf is not filtered or guide='self')."""
    if guide == "self" or not any(s.axes for s in specs):
        return [None] * len(specs)
    if params is None:
        raise ValueError(f"{transform} uses guide={guide!r}, which needs the current parameters: "
                         f"call update(updates, state, params=params)")
    if guide == "params":
        g = jax.tree.leaves(params)
        if len(g) != len(specs):
            raise ValueError(f"params has {len(g)} leaves but the updates have {len(specs)}; "
                             "they must have the same structure")
    else:
        g = broadcast_prefix(guide(params), tree, lambda x: x is None or hasattr(x, "shape"),
                             "the guide callable's result")
        for x, s, name in zip(g, specs, leaf_names(tree)):
            if x is None and s.axes:
                raise ValueError(f"guide returned None for leaf {name}, which is filtered; return "
                                 "an array for it or give it spatial_axes=()")
    return [log_transform(x) if (log_guide and x is not None) else x for x in g]


def log_transform(x):
    """log(|x| + 1e-8): the log-domain guide of the paper's texture runs."""
    x = jnp.asarray(x)
    x = x.astype(jnp.promote_types(x.dtype, jnp.float32))
    return jnp.log(jnp.abs(x) + LOG_GUIDE_EPS)
