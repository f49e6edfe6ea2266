"""Mitsuba 3 scenes driven by optax transforms (optional extra ``mitsuba``).

Runs any optax ``GradientTransformation`` (e.g. ``bilateral_adam``) on bitmap
textures and grid volumes of a ``mi.SceneParameters``; docs/mitsuba.md has the
loop, the measured results and the pitfalls::

    from optax_bilateral.mitsuba import SceneOptimizer
    opt = SceneOptimizer(ob.bilateral_adam(lr, log_guide=True), params, key,
                         project={key: (0.005, 0.5)})
    state = opt.init()
    # per iteration: render, loss, dr.backward(loss), then
    state = opt.step(state)

Mitsuba and Dr.Jit are imported on first use, not by this module.
"""

from optax_bilateral._src.mitsuba import (
    GRID_NDIMS,
    MIN_LLVM_MAJOR,
    SceneOptimizer,
    check_variant,
    llvm_version,
    observed_texels,
    to_jax,
)

__all__ = (
    "GRID_NDIMS",
    "MIN_LLVM_MAJOR",
    "SceneOptimizer",
    "check_variant",
    "llvm_version",
    "observed_texels",
    "to_jax",
)
