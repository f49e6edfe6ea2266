"""The methods the benchmark compares and their grids: the factories, the families and the
settings of a run (full, quick or reduced)."""

from __future__ import annotations

import dataclasses
import inspect
import json
import math
from collections.abc import Mapping, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import optax

import optax_bilateral as ob
from experiments.tuning.problem import Scene
from experiments.tuning.sweep import MAX_EXTEND, SEEDS, Family, jsonable, rounded

#: ``sigma_d`` grid (times ``scene.scale`` for a linear guide); 0 and inf are the extremes.
SIGMA_GRID = (0.0, 1e-3, 3e-3, 0.01, 0.03, 0.1, 0.3, 1.0, 3.0, math.inf)
LEVELS_GRID = (2, 3, 4, 5, 6)
ADAM_B1 = (0.9, 0.5, 0.2)
PYRAMID_LEVELS = (2, 3, 4, 5, 6)


@dataclasses.dataclass(frozen=True)
class Settings:
    """What the benchmark sweeps; :func:`settings` gives the full and the quick one."""

    sigma_grid: tuple[float, ...]
    levels_grid: tuple[int, ...]
    adam_b1: tuple[float, ...]
    pyramid_levels: tuple[int, ...]
    seeds: tuple[int, ...]
    max_extend: int
    lr_points: int | None = None  # keep only this many of each scene's learning rates (quick)


#: A smaller grid for costly scenes (``--grid reduced``; the Mitsuba scenes spend ~0.1 s a
#: render): one seed, four ``sigma_d``, ``levels`` 3 and 5, Adam's ``b1`` 0.9, the pyramid at
#: 3 and 5 levels, one learning-rate extension.
REDUCED = Settings(
    sigma_grid=(0.01, 0.03, 0.1, 0.3),
    levels_grid=(3, 5),
    adam_b1=(0.9,),
    pyramid_levels=(3, 5),
    seeds=(0,),
    max_extend=1,
)


def settings(quick: bool, grid: str | None = None) -> Settings:
    """The grid of a run: :data:`REDUCED` for ``grid="reduced"``, else the full or quick one."""
    if grid == "reduced":
        return REDUCED
    if grid is not None:
        raise ValueError(f"grid must be None or 'reduced', got {grid!r}")
    if quick:
        return Settings(
            sigma_grid=(0.0, 0.1, math.inf),
            levels_grid=(2,),
            adam_b1=(0.9,),
            pyramid_levels=(3,),
            seeds=(0,),
            max_extend=0,
            lr_points=2,
        )
    return Settings(SIGMA_GRID, LEVELS_GRID, ADAM_B1, PYRAMID_LEVELS, SEEDS, MAX_EXTEND)


def levels_that_matter(scene: Scene, levels_grid: Sequence[int]) -> tuple[list[int], dict]:
    """Levels whose last a-trous pass reaches a neighbour on some leaf; ``{skipped: same_as}``.

    A level of stride ``2^(L-1)`` at least every spatial size has no neighbour inside the
    grid: it is the identity, so ``levels = L`` gives the results of ``L - 1``.
    """
    axes = ob.filtered_axes(scene.init, spatial_axes=scene.spatial_axes)
    sizes = [
        max(np.shape(x)[a] for a in ax)
        for x, ax in zip(jax.tree.leaves(scene.init), axes.values())
        if ax
    ]
    largest = max(sizes) if sizes else 1
    keep, same = [], {}
    for lev in sorted(levels_grid):
        if keep and 2 ** (lev - 1) >= largest:
            same[lev] = keep[-1]
        else:
            keep.append(lev)
    return keep, same


def bilateral_factory(learning_rate, sigma_d, *, levels, log_guide, spatial_axes=None):
    """``bilateral_adam`` (postfilter, its default ``b1``) with a traced ``sigma_d``."""
    return ob.bilateral_adam(
        learning_rate,
        sigma_d=sigma_d,
        levels=levels,
        log_guide=log_guide,
        spatial_axes=spatial_axes,
    )


def adam_factory(learning_rate, b1, b2=0.999):
    return optax.adam(learning_rate, b1=b1, b2=b2)


def pyramid_factory(learning_rate, *, levels, spatial_axes=None):
    return ob.pyramid_adam(learning_rate, levels=levels, spatial_axes=spatial_axes)


def defaults_factory(learning_rate, spatial_axes=None):
    """``bilateral_adam`` with every default (whatever the installed library's defaults are)."""
    return ob.bilateral_adam(learning_rate, spatial_axes=spatial_axes)


def auto_factory(learning_rate, spatial_axes=None):
    return ob.bilateral_adam(learning_rate, sigma_d="auto", spatial_axes=spatial_axes)


def sure_factory(learning_rate, spatial_axes=None):
    """``sigma_d="sure"`` with ``levels=5`` (F chosen among 2-5, its default; written out so
    the measured setting stays fixed; docs/auto_sigma.md), as a
    candidate: ``--candidates sure=experiments.tuning:sure_factory``."""
    return ob.bilateral_adam(learning_rate, sigma_d="sure", levels=5, spatial_axes=spatial_axes)


def sparse_factory(learning_rate, spatial_axes=None):
    """:func:`optax_bilateral.sparse_adam` with its defaults (issue #54), as a candidate:
    ``--candidates sparse=experiments.tuning:sparse_factory``."""
    return ob.sparse_adam(learning_rate, spatial_axes=spatial_axes)


def auto_available() -> bool:
    """Whether the installed library accepts ``sigma_d="auto"`` (tried on a small grid)."""
    try:
        opt = ob.bilateral_adam(0.1, sigma_d="auto")
        p = jnp.linspace(0.1, 1.0, 64, dtype=jnp.float32).reshape(8, 8)
        u, _ = opt.update(jnp.cos(p * 7), opt.init(p), p)
        return bool(jnp.all(jnp.isfinite(u)))
    except (TypeError, ValueError):
        return False


def bilateral_defaults() -> dict:
    """``bilateral_adam``'s default ``sigma_d``, ``levels`` and ``b1`` (read from its signature)."""
    sig = inspect.signature(ob.bilateral_adam).parameters
    return {k: sig[k].default for k in ("sigma_d", "levels", "b1")}


def families(scene: Scene, s: Settings) -> dict[str, Family]:
    """The grid families of the benchmark on ``scene`` (cached), in running order."""
    levels, _ = levels_that_matter(scene, s.levels_grid)
    guides = (False, True) if scene.log_guide else (False,)
    statics = tuple({"levels": lev, "log_guide": lg} for lg in guides for lev in levels)

    def sigmas(static):
        # A log guide is unit-free; a linear one is in the parameters' unit.
        unit = 1.0 if static["log_guide"] else scene.scale
        return tuple({"sigma_d": _sigma(x, unit)} for x in s.sigma_grid)

    return {
        "bilateral": Family(
            "bilateral", bilateral_factory, statics, sigmas, "bilateral_adam, postfilter, b1=0.2"
        ),
        "adam": Family(
            "adam",
            adam_factory,
            ({},),
            adam_points(s.adam_b1),
            "optax.adam, b2 = 0.999 or 1-(1-b1)^2",
        ),
        "pyramid": Family(
            "pyramid",
            pyramid_factory,
            tuple({"levels": k} for k in s.pyramid_levels),
            ({},),
            "Laplacian pyramid + Adam (Weier et al. 2025)",
            lr_scale=_per_level,
        ),
        "defaults": Family(
            "defaults",
            defaults_factory,
            description=("bilateral_adam defaults " + json.dumps(jsonable(bilateral_defaults()))),
        ),
    }


def adam_points(b1s: Sequence[float]) -> tuple[dict, ...]:
    """Adam's ``(b1, b2)`` grid: every ``b1`` with optax's ``b2 = 0.999`` and with the paper's
    pairing ``b2 = 1 - (1 - b1)^2`` (``bilateral_adam``'s default; on the texture scenes
    ``sigma_d = 0``, close to that Adam, halved optax.adam's error)."""
    return tuple({"b1": b, "b2": b2} for b in b1s for b2 in (0.999, rounded(1 - (1 - b) ** 2)))


def _per_level(static: Mapping[str, Any]) -> float:
    return 1.0 / static["levels"]


def _sigma(x: float, scale: float) -> float:
    return x if x in (0.0, math.inf) else rounded(x * scale)
