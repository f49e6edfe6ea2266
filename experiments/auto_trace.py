"""The sigma_d that ``sigma_d="auto"`` uses along a run, against the step scale it replaced.

    python -m experiments.auto_trace [--scene texture] [--learning-rate 0.01] [--seed 0]
                                     [--out DIR]

Runs ``bilateral_adam(learning_rate)`` (the defaults: the guide is the parameters) on one
tuning scene and, at every step, reads from the parameters and the state the two scales of
docs/auto_sigma.md for its first leaf: the postfilter's rate rule,
``sqrt(C) mean ||Δγ|| / mean ||d||`` (what the run uses), and the step rule
``3 mean ||Δγ||`` (what a prefilter and ``"sure"`` use). Prints the medians of each over
the run's quarters and the final error; with ``--out``, writes every value to
``DIR/auto_trace.json``.
"""

from __future__ import annotations

import argparse
import json
import pathlib

import jax
import jax.numpy as jnp
import numpy as np
import optax

import optax_bilateral as ob
from experiments import scenes
from optax_bilateral._src import auto


def trace(name: str, learning_rate: float, seed: int = 0, quick: bool = False) -> dict:
    """``{"rate": [...], "step": [...], "error": float}``: each scale for the update after
    every step."""
    scene = scenes.make(name, quick=quick)
    opt = ob.bilateral_adam(learning_rate, spatial_axes=scene.spatial_axes)
    axes = next(iter(ob.filtered_axes(scene.init, spatial_axes=scene.spatial_axes).values()))

    @jax.jit
    def step(params, state, i):
        g = scene.grad(scene.data, params, jax.random.fold_in(jax.random.PRNGKey(seed), i))
        u, state = opt.update(g, state, params)
        return scene.project(scene.data, optax.apply_updates(params, u)), state

    params, state = scene.init, opt.init(scene.init)
    rates, steps = [], []
    for i in range(scene.iterations):
        new, state = step(params, state, i)
        # The next update's sigma_d (count i + 2) from this update's move of the guide.
        guide, previous = jax.tree.leaves(new)[0], jax.tree.leaves(params)[0]
        first = jax.tree.leaves(state[0].auto, is_leaf=lambda x: isinstance(x, ob.AutoState))[0]
        count = jnp.asarray(i + 2)
        rates.append(float(auto.sigma(guide, previous, count, axes, first.direction)))
        steps.append(float(auto.sigma(guide, previous, count, axes)))
        params = new
    return {"rate": rates, "step": steps, "error": float(scene.error(scene.data, params))}


def quarters(values) -> list[float]:
    q = max(1, len(values) // 4)
    return [float(np.median(values[k : k + q])) for k in range(0, 4 * q, q)]


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    p.add_argument("--scene", default="texture", choices=sorted(scenes.SCENES))
    p.add_argument("--learning-rate", type=float, default=0.01)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--quick", action="store_true")
    p.add_argument("--out", default=None, help="folder for auto_trace.json (none: print only)")
    args = p.parse_args(argv)
    out = trace(args.scene, args.learning_rate, args.seed, args.quick)
    if args.out is not None:
        folder = pathlib.Path(args.out)
        folder.mkdir(parents=True, exist_ok=True)
        (folder / "auto_trace.json").write_text(json.dumps({**vars(args), **out}) + "\n")
    for rule in ("rate", "step"):
        medians = [f"{x:.3g}" for x in quarters(out[rule])]
        print(f"{rule} rule sigma_d, medians per quarter:", medians)
    print(f"final error {out['error']:.4g}")
    return out


if __name__ == "__main__":
    main()
