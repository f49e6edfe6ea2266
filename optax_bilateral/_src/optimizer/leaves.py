"""Per-leaf settings: which axes of each parameter leaf are spatial, its sigma_d, levels, guide.

A setting is given once for all leaves, or as a pytree *prefix* of the parameters
(one value per subtree), or (for ``spatial_axes``) as a callable ``leaf -> axes``.
"""

from __future__ import annotations

import numbers
import os
import sys
import warnings
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax

from optax_bilateral._src.filter.bilateral import log_transform
from optax_bilateral._src.rules import registry
from optax_bilateral._src.rules.sigma import SigmaRule
from optax_bilateral._src.validation import check_levels, check_sigma_d, normalize_axes

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


# "params" | "self" | a callable params -> guide pytree (a prefix of the parameters).
GuideSetting = str | Callable[[Any], Any]
# None (the default rule) | a tuple of ints | a pytree prefix of tuples | a callable leaf -> axes.
SpatialAxesSetting = Any


# A channels-last leaf has at most this many channels, and every other axis is longer.
MAX_CHANNELS = 4


class LeafRuleWarning(UserWarning):
    """The default leaf rule had to guess a leaf's layout (see :func:`default_spatial_axes`).

    Raised (as a warning) by the transforms' ``init``, once per process for each leaf
    name and shape, naming the leaf, the axes guessed and the ``spatial_axes`` to pass.
    Passing ``spatial_axes`` explicitly silences it; ``warnings.simplefilter("error",
    LeafRuleWarning)`` turns every guess into an error.

    Args:
      *args: the message, as for any ``UserWarning``.

    Example::

        >>> import warnings, jax.numpy as jnp, optax_bilateral as ob
        >>> with warnings.catch_warnings(record=True) as caught:
        ...     warnings.simplefilter("always")
        ...     _ = ob.postfilter(sigma_d=0.1).init({"w": jnp.zeros((13, 17))})  # grid or matrix?
        >>> caught[0].category is ob.LeafRuleWarning
        True
        >>> _ = ob.postfilter(sigma_d=0.1, spatial_axes=()).init({"w": jnp.zeros((13, 17))})
    """


def default_spatial_axes(leaf: Any) -> tuple[int, ...]:
    """The default leaf rule: the spatial axes of a leaf when ``spatial_axes=None``.

    Conservative: a leaf is filtered only where its shape reads one way,

    * ``(H, W, C)`` with ``C <= 4`` and ``H, W > 4``: ``(0, 1)`` (a texture);
    * ``(D, H, W, C)`` with ``C <= 4`` and ``D, H, W > 4``: ``(0, 1, 2)`` (a volume);

    and every other leaf gets Adam's update, unfiltered. Where that may be wrong (the leaf
    could be a grid), the transforms' ``init`` warns once per leaf
    (:class:`LeafRuleWarning`), naming it and the ``spatial_axes`` that filters it:

    * ``()``, and leaves with fewer than 16 entries along every axis and a side of at most
      4 (``(3,)``, ``(4, 8)``, ``(3, 3, 3)``): silent;
    * ``(N,)`` with ``N >= 16`` (a 1-D signal, or weights?): warns, ``(0,)`` filters it;
    * ``(H, W)`` with both sides > 4 (a one-channel image, or a weight matrix?), or a side
      of 16 or more (a signal with channels, or vertex positions?): warns;
    * 3-D and beyond, any other layout (a scalar volume ``(D, H, W)``, channels first
      ``(C, H, W)``, five axes): warns.

    docs/leaves.md has this rule as a table; :func:`optax_bilateral.filtered_axes` lists
    what it gives for every leaf.

    Args:
      leaf: an array or anything with a shape (only ``np.shape(leaf)`` is read).

    Returns:
      The spatial axes, a tuple of ints in increasing order; ``()`` when the leaf is not
      filtered.

    Example::

        >>> import jax.numpy as jnp, optax_bilateral as ob
        >>> ob.default_spatial_axes(jnp.zeros((64, 64, 3)))       # a texture (H, W, C)
        (0, 1)
        >>> ob.default_spatial_axes(jnp.zeros((16, 16, 16, 1)))   # a volume (D, H, W, C)
        (0, 1, 2)
        >>> ob.default_spatial_axes(jnp.zeros((784, 128)))        # a weight matrix: Adam
        ()
    """
    return _default_rule(np.shape(leaf))[0]


# A leaf with this many entries along an axis may be a grid along it (the rule warns).
MIN_GRID = 16


def _default_rule(shape: tuple[int, ...]) -> tuple[tuple[int, ...], str | None]:
    """(spatial axes, why the leaf may be something else) for a leaf of ``shape``; None when
    it reads one way only. :func:`default_spatial_axes` and docs/leaves.md are its table."""
    nd = len(shape)
    long = [n > MAX_CHANNELS for n in shape]
    if nd in (3, 4) and shape[-1] <= MAX_CHANNELS and all(long[:-1]):
        return tuple(range(nd - 1)), None  # a texture (H, W, C), a volume (D, H, W, C)
    if nd == 0 or (max(shape) < MIN_GRID and (nd == 1 or not all(long))):
        return (), None
    if nd == 1:
        return (), (
            f"not filtered: a vector of {shape[0]} entries (weights, a curve?); if it is a "
            "1-D signal on a grid, pass spatial_axes=(0,)"
        )
    if nd == 2 and all(long):
        return (), (
            "not filtered: a weight matrix, or a one-channel image? to filter it as an "
            "image, pass spatial_axes=(0, 1)"
        )
    if nd == 2:
        axis = 0 if long[0] else 1
        return (), (
            f"not filtered: {shape[axis]} points of {shape[1 - axis]} values (vertex "
            f"positions?), or a 1-D signal with {shape[1 - axis]} channel(s)? to filter it "
            f"as a signal, pass spatial_axes=({axis},)"
        )
    if shape[0] <= MAX_CHANNELS and all(long[1:]):
        return (), (
            f"not filtered: it looks channels-first (C, ...); pass "
            f"spatial_axes={tuple(range(1, nd))} to filter it"
        )
    if all(long):
        return (), (
            f"not filtered: a one-channel grid, or a grid of {shape[-1]} channels? pass "
            f"spatial_axes={tuple(range(nd))} for a one-channel grid, "
            f"{tuple(range(nd - 1))} for a channels-last one"
        )
    return (), (
        "not filtered: no layout of at most 4 channels last and longer sides; pass "
        "spatial_axes to filter it"
    )


_WARNED: set = set()
# Frames in these packages are not the user's: a warning points past them.
_LIBRARIES = tuple(
    os.path.dirname(m.__file__) + os.sep
    for m in (sys.modules[__name__.split(".")[0]], jax, optax)
    if m.__file__
)


def _user_stacklevel() -> int:
    """The ``stacklevel`` of the first caller outside this library, optax and JAX (so that a
    warning names the user's line, however deep the optax wrappers around the call)."""
    frame, level = sys._getframe(1), 1
    while frame is not None and frame.f_code.co_filename.startswith(_LIBRARIES):
        frame, level = frame.f_back, level + 1
    return level


def _warn_guess(name: str, shape: tuple[int, ...], note: str) -> None:
    """Warns once per process for each (leaf, shape), at the user's line."""
    if (name, shape) in _WARNED:
        return
    _WARNED.add((name, shape))
    warnings.warn(
        f"optax_bilateral's default leaf rule decided for params leaf {name} of shape "
        f"{shape}: {note}. Passing spatial_axes explicitly (a tuple, a pytree prefix of "
        "tuples or a callable) silences this; optax_bilateral.filtered_axes(params) lists "
        "every leaf's axes.",
        LeafRuleWarning,
        stacklevel=_user_stacklevel(),
    )


class _Box:
    """Keeps a per-leaf value atomic while it is broadcast over a subtree."""

    __slots__ = ("value",)

    def __init__(self, value):
        self.value = value


def _is_axes_atom(x) -> bool:
    return (
        x is None
        or callable(x)
        or isinstance(x, numbers.Integral)
        or (
            isinstance(x, (tuple, list))
            and all(isinstance(a, numbers.Integral) and not isinstance(a, bool) for a in x)
        )
    )


def _is_scalar_atom(x) -> bool:
    return (
        x is None
        or isinstance(x, (numbers.Number, np.ndarray, jax.Array, np.generic))
        or hasattr(x, "dtype")
    )


def is_sigma_atom(x) -> bool:
    """One leaf's ``sigma_d`` inside a pytree prefix: a number, an array, None, a name or a
    rule object."""
    return _is_scalar_atom(x) or isinstance(x, (str, SigmaRule))


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


class LeafSpec(NamedTuple):
    """Static per-leaf filter settings plus the (possibly traced) sigma_d."""

    axes: tuple[int, ...]  # () means "not filtered"
    levels: int
    sigma_d: Any


def leaf_names(tree) -> list[str]:
    """A readable path per leaf (``['tex']``, ``[0].albedo``) for error messages."""
    paths = jax.tree_util.tree_flatten_with_path(tree)[0]
    return [jax.tree_util.keystr(p) or "(the root)" for p, _ in paths]


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
                f"{transform}: the update for leaf {name} has shape {np.shape(g)}, but its "
                f"{what} have shape {np.shape(p)}; the gradient of each parameter must have "
                "the parameter's shape"
            )


def check_spatial_axes_setting(spatial_axes) -> None:
    """Construction-time check of ``spatial_axes`` (its ranges need the leaves: see
    :func:`leaf_specs`)."""
    atoms = jax.tree.leaves(spatial_axes, is_leaf=_is_axes_atom)
    for ax in atoms:
        if ax is None or callable(ax):
            continue
        if not _is_axes_atom(ax):
            raise TypeError(
                f"spatial_axes must be None, a tuple of ints, a pytree prefix of such "
                f"tuples or a callable leaf -> axes; found {ax!r}"
            )
        ax = (ax,) if isinstance(ax, numbers.Integral) else tuple(ax)
        if len(set(ax)) != len(ax):
            raise ValueError(f"spatial_axes={ax} repeats an axis")


def _resolve_axes(leaf: Any, setting: Any, name: str, warn: bool) -> tuple[int, ...]:
    """The leaf's spatial axes from its ``spatial_axes`` setting (None: the default rule)."""
    if callable(setting):
        setting = setting(leaf)
    if setting is None:
        setting, note = _default_rule(np.shape(leaf))
        if note is not None and warn:
            _warn_guess(name, tuple(np.shape(leaf)), note)
    ax = tuple(setting) if isinstance(setting, (tuple, list)) else (setting,)
    nd = np.ndim(leaf)
    if len(ax) > nd:
        raise ValueError(
            f"spatial_axes={ax} asks for {len(ax)} spatial axes but parameter "
            f"leaf {name} has shape {np.shape(leaf)} ({nd} dimension(s))"
        )
    return normalize_axes(ax, nd, name=f"spatial_axes (for leaf {name}, shape {np.shape(leaf)})")


def leaf_specs(tree, *, spatial_axes, sigma_d, levels, warn: bool = False) -> list[LeafSpec]:
    """Resolves spatial axes, levels and sigma_d for every leaf of ``tree``; ``warn``: warn
    where the default leaf rule guessed."""
    leaves = jax.tree.leaves(tree)
    names = leaf_names(tree)
    axes_list = broadcast_prefix(spatial_axes, tree, _is_axes_atom, "spatial_axes")
    sigma_list = broadcast_prefix(sigma_d, tree, is_sigma_atom, "sigma_d")
    if levels is None:
        levels_list = [None] * len(leaves)
    else:
        levels_list = broadcast_prefix(levels, tree, _is_scalar_atom, "levels")
    specs = []
    for leaf, name, ax, sig, lev in zip(leaves, names, axes_list, sigma_list, levels_list):
        lev = default_levels(sig) if lev is None else lev
        lev = check_levels(lev, name=f"levels (for leaf {name})")
        ax = _resolve_axes(leaf, ax, name, warn and lev > 0)
        if sig is None:
            raise ValueError(f"sigma_d is None for leaf {name}; pass {registry.SETTINGS}")
        if not isinstance(sig, SigmaRule):
            check_sigma_d(sig, name=f"sigma_d (for leaf {name})", names=tuple(registry.NAMED))
        if ax and lev > 0:
            check_floating(
                leaf,
                name,
                "filtered leaves must be floating point, real or complex (integer parameters "
                "have no gradient)",
            )
        specs.append(LeafSpec(ax if lev > 0 else (), lev, sig))
    return specs


def check_floating(leaf: Any, name: str, why: str) -> None:
    """Raises for a leaf that is not floating point, real or complex."""
    dt = jnp.result_type(leaf)
    if not jnp.issubdtype(dt, jnp.inexact):
        raise TypeError(f"params leaf {name} has dtype {dt}; {why}")


def filtered_axes(
    params: Any, *, spatial_axes: SpatialAxesSetting = None, levels: Any = 3
) -> dict[str, tuple[int, ...]]:
    """The spatial axes each leaf of ``params`` is filtered along, ``()`` for none.

    Resolves ``spatial_axes`` and ``levels`` (as given to the transforms; ``None`` is the
    default leaf rule, :func:`default_spatial_axes`) without building an optimizer.

    Args:
      params: the parameters (any pytree of arrays, or of ``jax.ShapeDtypeStruct``).
      spatial_axes: as the transforms' argument: ``None`` (the default leaf rule), a tuple
        of axes for every leaf, a pytree prefix of tuples (``()`` = not filtered), or a
        callable ``leaf -> axes``.
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
    return {name: spec.axes for name, spec in zip(leaf_names(params), specs)}


def _guide_spatial_shape(guide_shape, leaf_shape, axes, name):
    """The guide's spatial shape under :func:`atrous_bilateral`'s rule, or a clear error."""
    if len(guide_shape) == len(axes):
        return tuple(guide_shape)
    if len(guide_shape) < len(axes) or any(a >= len(guide_shape) for a in axes):
        raise ValueError(
            f"guide for params leaf {name} has shape {tuple(guide_shape)}, which "
            f"lacks the spatial axes {axes} of the leaf (shape {tuple(leaf_shape)})"
        )
    return tuple(guide_shape[a] for a in axes)


def check_params(params, settings, *, transform: str, all_leaves: bool) -> list[LeafSpec]:
    """Init-time checks: leaf dtypes and dimensions, the settings per leaf, the guide's shapes.

    ``settings`` has the transform's ``spatial_axes``, ``sigma_d``, ``levels`` and ``guide``;
    ``all_leaves``: every leaf must be floating point (it has moments), not only the
    filtered ones.
    """
    guide = settings.guide
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
    if callable(guide) and guide not in ("params", "self") and any(s.axes for s in specs):
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
                    f"guide returned None for params leaf {name}, which is filtered "
                    f"(spatial axes {spec.axes}); return an array for it or give it "
                    "spatial_axes=()"
                )
            want = tuple(np.shape(leaf)[a] for a in spec.axes)
            got = _guide_spatial_shape(leaf_guide.shape, np.shape(leaf), spec.axes, name)
            if got != want:
                raise ValueError(
                    f"guide for params leaf {name} has spatial shape {got} but the leaf "
                    f"has {want} along spatial_axes {spec.axes}: the guide must cover "
                    "the same grid"
                )
    return specs


def check_guide(guide) -> None:
    if not (guide in ("params", "self") or callable(guide)):
        raise ValueError(
            f"guide must be 'params', 'self' or a callable params -> guide pytree, got {guide!r}"
        )


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
                    f"guide returned None for leaf {name}, which is filtered; return "
                    "an array for it or give it spatial_axes=()"
                )
    return [log_transform(x) if (log_guide and x is not None) else x for x in g]
