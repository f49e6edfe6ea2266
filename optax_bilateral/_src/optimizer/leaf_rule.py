"""The leaf rule: which axes of a parameter leaf are spatial when ``spatial_axes`` is None, and
the warning where it had to guess; the checks of a ``spatial_axes`` setting."""

from __future__ import annotations

import numbers
import os
import sys
import warnings
from typing import Any, NamedTuple

import jax
import numpy as np
import optax

from optax_bilateral._src.validation import normalize_axes

# None (the default rule) | a tuple of ints | a pytree prefix of tuples | a callable leaf -> axes.
SpatialAxesSetting = Any

# spatial_axes="default": the default rule, its guesses accepted without a warning.
ACCEPT = "default"


def is_axes_atom(x) -> bool:
    """One leaf's ``spatial_axes`` inside a pytree prefix."""
    return (
        x is None
        or (isinstance(x, str) and x == ACCEPT)
        or callable(x)
        or isinstance(x, numbers.Integral)
        or (
            isinstance(x, (tuple, list))
            and all(isinstance(a, numbers.Integral) and not isinstance(a, bool) for a in x)
        )
    )


# A channels-last leaf has at most this many channels, and every other axis is longer.
MAX_CHANNELS = 4


class LeafRuleWarning(UserWarning):
    """The default leaf rule had to guess a leaf's layout (see :func:`default_spatial_axes`).

    Raised (as a warning) by the transforms' ``init``: one warning naming every leaf
    guessed (each once per process, by path and shape), what was decided and the
    ``spatial_axes`` that filters it. Passing ``spatial_axes`` explicitly silences it, and
    ``spatial_axes="default"`` accepts the rule's guesses silently;
    ``warnings.simplefilter("error", LeafRuleWarning)`` turns every guess into an error.

    Its arguments are the message's, as for any ``UserWarning``.

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
    could be a grid), the transforms' ``init`` warns (one :class:`LeafRuleWarning` naming
    every such leaf and the ``spatial_axes`` that filters it; ``spatial_axes="default"``
    accepts the rule silently):

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


class Guess(NamedTuple):
    """A leaf the default rule had to guess: its path, its shape and what it decided."""

    name: str
    shape: tuple[int, ...]
    note: str


def warn_guesses(guesses: list[Guess]) -> None:
    """One warning at the user's line for every guessed leaf not warned of before in this
    process (by path and shape), naming each and the ``spatial_axes`` that filters it."""
    new = [g for g in guesses if (g.name, g.shape) not in _WARNED]
    if not new:
        return
    _WARNED.update((g.name, g.shape) for g in new)
    lines = "".join(f"\n  {g.name} of shape {g.shape}: {g.note}" for g in new)
    warnings.warn(
        f"optax_bilateral's default leaf rule decided for {len(new)} leaf(s):{lines}\n"
        "Pass spatial_axes explicitly (a tuple, a pytree prefix of tuples or a callable) to "
        f'decide, or spatial_axes="{ACCEPT}" to accept the rule silently; '
        "optax_bilateral.filtered_axes(params) lists every leaf's axes.",
        LeafRuleWarning,
        stacklevel=_user_stacklevel(),
    )


def check_spatial_axes_setting(spatial_axes) -> None:
    """Construction-time check of ``spatial_axes`` (its ranges need the leaves: see
    :func:`leaf_specs`)."""
    atoms = jax.tree.leaves(spatial_axes, is_leaf=is_axes_atom)
    for ax in atoms:
        if ax is None or callable(ax) or (isinstance(ax, str) and ax == ACCEPT):
            continue
        if not is_axes_atom(ax):
            raise TypeError(
                f'spatial_axes must be None, "{ACCEPT}", a tuple of ints, a pytree prefix of '
                f"such tuples or a callable leaf -> axes; found {ax!r}"
            )
        ax = (ax,) if isinstance(ax, numbers.Integral) else tuple(ax)
        if len(set(ax)) != len(ax):
            raise ValueError(f"spatial_axes={ax} repeats an axis")


def resolve_axes(leaf: Any, setting: Any, name: str) -> tuple[tuple[int, ...], Guess | None]:
    """The leaf's spatial axes from its ``spatial_axes`` setting (None: the default rule; its
    guess, if it had to make one, to warn of; ``"default"``: the rule, silently)."""
    if callable(setting):
        setting = setting(leaf)
    guess = None
    if setting is None or (isinstance(setting, str) and setting == ACCEPT):
        shape = tuple(np.shape(leaf))
        accepted = setting is not None
        setting, note = _default_rule(shape)
        guess = None if note is None or accepted else Guess(name, shape, note)
    ax = tuple(setting) if isinstance(setting, (tuple, list)) else (setting,)
    nd = np.ndim(leaf)
    if len(ax) > nd:
        raise ValueError(
            f"spatial_axes={ax} asks for {len(ax)} spatial axes but "
            f"{name} has shape {np.shape(leaf)} ({nd} dimension(s))"
        )
    where = f"spatial_axes (for {name}, shape {np.shape(leaf)})"
    return normalize_axes(ax, nd, name=where), guess
