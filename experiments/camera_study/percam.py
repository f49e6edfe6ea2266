# ruff: noqa  (a study kept in git history only: docs/research/camera_distance.md)
import dataclasses
import functools

import optax_bilateral as ob
from experiments.camera_study import density
from experiments.tuning import camera_distance as cd
from experiments.tuning import scenes, sweep

s0 = scenes.make("mitsuba_two_cameras")
film = s0.config["film"]

M0 = {
    "defaults": (lambda lr: ob.bilateral_adam(lr), 0.16),
    "b8x1": (functools.partial(density.factory, block=8, extra_levels=1), 0.04),
    "pyramid5": (lambda lr: ob.pyramid_adam(lr, 5), 0.008),
    "pyramid3": (lambda lr: ob.pyramid_adam(lr, 3), 0.0133),
}
M = {}
for lr in (0.01, 0.02, 0.04):
    M[f"b8x1@{lr}"] = (M0["b8x1"][0], lr)
    M[f"dens_b8@{lr}"] = (functools.partial(density.factory, block=8), lr)
for name, (f, lr) in M.items():
    out = []
    for tpp in (0.5, 12.0):
        s = dataclasses.replace(
            s0, error=lambda data, x, tpp=tpp: cd.resolved_error(x, data["target"], tpp, film)
        )
        out.append(
            float(
                sweep.evaluate(
                    s, lambda learning_rate: f(learning_rate), [{"learning_rate": lr}], (0,)
                )[0, 0]
            )
        )
    print(name, lr, "close %.4f far %.4f mean %.4f" % (out[0], out[1], sum(out) / 2), flush=True)
