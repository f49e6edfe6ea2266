"""Mitsuba 3 scenes driven by optax transforms (optional extra ``mitsuba``).

A Mitsuba script keeps its loop and swaps one line: :class:`BilateralAdam` is a
``drjit.opt.Optimizer`` like ``mi.ad.Adam`` that filters textures and volumes with the
paper's method, and :class:`OptaxOptimizer` runs any optax transform in that loop::

    from optax_bilateral.mitsuba import BilateralAdam
    opt = BilateralAdam(lr=0.1)               # was: opt = mi.ad.Adam(lr=0.01)
    opt[key] = params[key]
    params.update(opt)
    # per iteration: render, loss, dr.backward(loss), opt.step(), params.update(opt)

:class:`SceneOptimizer` is the lower-level, functional path: one optax transform on a
dict of scene tensors with an explicit state. docs/mitsuba.md has the loops, the
measured results and the pitfalls.

Mitsuba and Dr.Jit are imported on first use (the optimizer classes, which subclass
Dr.Jit's, on first access), not by this module.
"""

from typing import TYPE_CHECKING

from optax_bilateral._src.mitsuba.bridge import (
    GRID_NDIMS,
    MIN_LLVM_MAJOR,
    SceneOptimizer,
    check_variant,
    llvm_version,
    observed_texels,
    to_jax,
)

if TYPE_CHECKING:
    from optax_bilateral._src.mitsuba.optimizer import BilateralAdam, OptaxOptimizer

_DRJIT_CLASSES = ("BilateralAdam", "OptaxOptimizer")


def __getattr__(name: str):
    # The optimizers subclass drjit.opt.Optimizer, so defining them imports Dr.Jit.
    if name in _DRJIT_CLASSES:
        try:
            from optax_bilateral._src.mitsuba import optimizer as mitsuba_optimizer
        except ImportError as e:
            from optax_bilateral._src.mitsuba.bridge import INSTALL_HINT

            raise ImportError(f"optax_bilateral.mitsuba.{name} needs Dr.Jit: {INSTALL_HINT}") from e
        return getattr(mitsuba_optimizer, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = (
    "GRID_NDIMS",
    "MIN_LLVM_MAJOR",
    "BilateralAdam",
    "OptaxOptimizer",
    "SceneOptimizer",
    "check_variant",
    "llvm_version",
    "observed_texels",
    "to_jax",
)
