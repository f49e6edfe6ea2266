# ruff: noqa  (a study kept in git history only: docs/research/camera_distance.md)
import sys

import numpy as np

import optax_bilateral as ob
from experiments.camera_study import coarse
from experiments.tuning import scenes, sweep

for sc in sys.argv[1].split(","):
    s = scenes.make(sc)
    for name, f in [
        ("library", lambda lr: ob.sparse_adam(lr, spatial_axes=s.spatial_axes)),
        (
            "study",
            lambda lr: coarse.coarse_path(
                lr, spatial_axes=s.spatial_axes, levels=5, share=0.25, gate="leaf"
            ),
        ),
    ]:
        e = sweep.evaluate(
            s,
            lambda learning_rate: f(learning_rate),
            [{"learning_rate": x} for x in (0.01, 0.02)],
            (0,),
        )
        print(sc, name, np.round(e[:, 0], 4), flush=True)
