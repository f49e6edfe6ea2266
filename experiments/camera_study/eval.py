# ruff: noqa  (a study kept in git history only: docs/research/camera_distance.md)
import functools
import sys
import time

import numpy as np

import optax_bilateral as ob
from experiments.camera_study import coarse, density
from experiments.tuning import scenes, sweep

LRS = [float(x) for x in sys.argv[2].split(",")]
SEEDS = tuple(int(s) for s in sys.argv[3].split(",")) if len(sys.argv) > 3 else (0,)
METHODS = {
    "sparse_adam": lambda lr, spatial_axes=None: ob.sparse_adam(lr, spatial_axes=spatial_axes),
    "sparse": lambda lr, spatial_axes=None: ob.bilateral_adam(
        lr, sigma_d="sparse", spatial_axes=spatial_axes
    ),
    "defaults": lambda lr, spatial_axes=None: ob.bilateral_adam(lr, spatial_axes=spatial_axes),
    "density": density.factory,
    "density_b8": functools.partial(density.factory, block=8),
    "density_m4": functools.partial(density.factory, max_boost=4.0),
    "density_x1": functools.partial(density.factory, extra_levels=1),
    "v8": functools.partial(density.factory, block=8, stat="v"),
    "v4": functools.partial(density.factory, block=4, stat="v"),
    "v8x1": functools.partial(density.factory, block=8, extra_levels=1, stat="v"),
    "v8x1w": functools.partial(
        density.factory, block=8, extra_levels=1, blend_levels=True, stat="v"
    ),
    "b8x1_mean": functools.partial(density.factory, block=8, extra_levels=1, observed_mean=False),
    "b8x1": functools.partial(density.factory, block=8, extra_levels=1),
    "b8x2": functools.partial(density.factory, block=8, extra_levels=2),
    "b4x1": functools.partial(density.factory, block=4, extra_levels=1),
    "b8x1w": functools.partial(density.factory, block=8, extra_levels=1, blend_levels=True),
    "b8x2w": functools.partial(density.factory, block=8, extra_levels=2, blend_levels=True),
    "density_d5": functools.partial(density.factory, density_decay=0.5),
    "density_d97": functools.partial(density.factory, density_decay=0.97),
    "density_b8x1": functools.partial(density.factory, block=8, extra_levels=1),
    "density_b1": lambda lr, spatial_axes=None: ob.bilateral_adam(
        lr, b1=0.5, b2=0.75, sigma_d=density.Density(), spatial_axes=spatial_axes
    ),
    "density_x2": functools.partial(density.factory, extra_levels=2),
    "density_x3": functools.partial(density.factory, extra_levels=3),
    "cp25": functools.partial(coarse.coarse_path, share=0.25),
    "cp25d": functools.partial(coarse.coarse_path, share=0.25, fine=ob.auto_sigma()),
    "cp50": functools.partial(coarse.coarse_path, share=0.5),
    "cp25leaf": functools.partial(coarse.coarse_path, share=0.25, gate="leaf"),
    "cp50leaf": functools.partial(coarse.coarse_path, share=0.5, gate="leaf"),
    "cp25field": functools.partial(coarse.coarse_path, share=0.25, gate="field"),
    "cp50field": functools.partial(coarse.coarse_path, share=0.5, gate="field"),
    "cp100field": functools.partial(coarse.coarse_path, share=1.0, gate="field"),
    "L4s25": functools.partial(coarse.coarse_path, levels=4, share=0.25, gate="leaf"),
    "L5s25": functools.partial(coarse.coarse_path, levels=5, share=0.25, gate="leaf"),
    "L3s35": functools.partial(coarse.coarse_path, levels=3, share=0.35, gate="leaf"),
    "L4s15": functools.partial(coarse.coarse_path, levels=4, share=0.15, gate="leaf"),
    "L5s15": functools.partial(coarse.coarse_path, levels=5, share=0.15, gate="leaf"),
    "L3s25": functools.partial(coarse.coarse_path, levels=3, share=0.25, gate="leaf"),
    "pyramid3": lambda lr, spatial_axes=None: ob.pyramid_adam(lr, 3, spatial_axes=spatial_axes),
    "pyramid5": lambda lr, spatial_axes=None: ob.pyramid_adam(lr, 5, spatial_axes=spatial_axes),
}
names = sys.argv[4].split(",") if len(sys.argv) > 4 else ["defaults", "density"]
for sc in sys.argv[1].split(","):
    s = scenes.make(sc)
    for name in names:
        f = METHODS[name]
        fac = lambda learning_rate, f=f: f(learning_rate, spatial_axes=s.spatial_axes)
        t = time.time()
        lrs = LRS if not name.startswith("pyramid") else [x / 4 for x in LRS]
        e = sweep.evaluate(s, fac, [{"learning_rate": x} for x in lrs], SEEDS)
        med = np.median(e, axis=1)
        i = int(np.argmin(med))
        print(
            f"{sc:20s} {name:12s} best {med[i]:.4f} @ {lrs[i]:g} | "
            + " ".join(f"{x:.4f}" for x in med)
            + f"  ({time.time() - t:.0f}s)",
            flush=True,
        )
