"""Names of ``optax_bilateral.triangle_mesh`` 0.1.0 kept for one release, each warning.

``scale_by_uniform_adam`` was Large Steps' ``AdamUniform``, which the shared
:func:`~optax_bilateral.postfilter` computes with ``levels=0, second_moment="uniform"``
(bit for bit under ``jit``; eagerly to float32's rounding, docs/triangle_mesh.md).
"""

from __future__ import annotations

import warnings
from typing import Any, NamedTuple

import jax
import optax

from optax_bilateral._src.mesh import config
from optax_bilateral._src.mesh.alias import uniform_adam

REPLACEMENT = 'optax_bilateral.postfilter(b1, b2, eps, levels=0, second_moment="uniform")'


class ScaleByUniformAdamState(NamedTuple):
    """The state ``scale_by_uniform_adam`` returned in 0.1.0 (deprecated: the uniform Adam's
    state is now :class:`optax_bilateral.PostfilterState`)."""

    count: jax.Array
    mu: Any
    nu: Any


def scale_by_uniform_adam(
    b1: jax.typing.ArrayLike = 0.9,
    b2: jax.typing.ArrayLike = 0.999,
    eps: jax.typing.ArrayLike = 1e-8,
) -> optax.GradientTransformationExtraArgs:
    """Deprecated: ``optax_bilateral.postfilter(b1, b2, eps, levels=0,
    second_moment="uniform")``, which this returns, with a ``DeprecationWarning``."""
    warnings.warn(
        f"optax_bilateral.triangle_mesh.scale_by_uniform_adam is deprecated after 0.1.0 and "
        f"will be removed in a future release: use {REPLACEMENT} (the same step; its state "
        "is a PostfilterState)",
        DeprecationWarning,
        stacklevel=2,
    )
    return uniform_adam(b1, b2, eps)


NAMES = {"scale_by_uniform_adam": scale_by_uniform_adam}
# Renamed: the grid transforms' DEFAULT_SIGMA_D is "auto", a different idea.
RENAMED = {"DEFAULT_SIGMA_D": "DEFAULT_NORMAL_SIGMA_D"}
STATES = {"ScaleByUniformAdamState": ScaleByUniformAdamState}


def lookup(module: str, name: str):
    """A deprecated name of ``module`` (a module ``__getattr__``): a state warns when it is
    looked up, the transform when it is called."""
    if name in STATES:
        warnings.warn(
            f"{module}.{name} is deprecated after 0.1.0 and will be removed in a future "
            f"release: nothing returns it any more; {REPLACEMENT} returns a PostfilterState",
            DeprecationWarning,
            stacklevel=3,
        )
        return STATES[name]
    if name in NAMES:
        return NAMES[name]
    if name in RENAMED:
        warnings.warn(
            f"{module}.{name} is deprecated and will be removed in a future release: it is "
            f"{module}.{RENAMED[name]} (optax_bilateral.DEFAULT_SIGMA_D is the grid "
            "transforms' default, 'auto')",
            DeprecationWarning,
            stacklevel=3,
        )
        return getattr(config, RENAMED[name])
    raise AttributeError(f"module {module!r} has no attribute {name!r}")
