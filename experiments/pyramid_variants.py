"""A study (issue 47): the filter combined with a Laplacian-pyramid parameterisation.

The two-camera and far-camera scenes (:data:`experiments.scenes.RENDERED`) are where the
defaults lose to ``ob.pyramid_adam``. Each variant here runs Adam's moments on the pyramid's
coefficients (``ob.laplacian_pyramid``) and filters some of them:

* ``pyramid+postfilter(all, self)``: every level's coefficients through ``postfilter``
  (``sigma_d="auto"`` or a number), each guided by itself: ``laplacian_pyramid`` hands its
  inner optimiser no parameters, so there is no other guide;
* ``pyramid+postfilter(c0, self)`` / ``(c0 c1, self)``: only the finest one (two) filtered,
  self-guided, Adam on the others;
* ``pyramid+postfilter(c0, params)``: the finest level filtered with the defaults'
  cross-guide, the parameters (the finest level has their shape), Adam on the others.

Every variant at seed 0 and a few learning rates (the tuning benchmark's reduced setting);
writes ``variants.json`` and ``table.md`` to ``--out``::

    python -m experiments.pyramid_variants --out results/pyramid_variants
"""

from __future__ import annotations

import argparse
import json
import pathlib
from collections.abc import Callable, Sequence

import jax
import jax.numpy as jnp
import optax

import optax_bilateral as ob
from experiments import scenes as sc
from experiments import tuning
from optax_bilateral._src.pyramid import (
    _leaf_axes,
    level_shapes,
    pyramid_reconstruct,
    pyramid_transpose,
)

SCENES = ("mitsuba_close", "mitsuba_mid", "mitsuba_far", "mitsuba_two_cameras")
LRS = (0.004, 0.008, 0.016, 0.032)


def filtered_adam(learning_rate, sigma_d="auto", guide="params", b1=0.9, spatial_axes=None):
    return optax.chain(
        ob.postfilter(b1=b1, sigma_d=sigma_d, guide=guide, spatial_axes=spatial_axes),
        optax.scale_by_learning_rate(learning_rate),
    )


def pyramid_all_self(learning_rate, levels=5, sigma_d="auto", b1=0.9):
    """Every level's coefficients filtered, self-guided."""
    return ob.laplacian_pyramid(filtered_adam(learning_rate, sigma_d, guide="self", b1=b1), levels)


def pyramid_finest_self(learning_rate, levels=5, filtered=1):
    """The finest ``filtered`` levels filtered (self-guided), Adam on the coarser ones."""

    def labels(tree):
        return jax.tree_util.tree_map_with_path(
            lambda path, _: "filtered" if path[-1].idx < filtered else "adam", tree
        )

    inner = optax.multi_transform(
        {
            "filtered": filtered_adam(learning_rate, guide="self"),
            "adam": optax.adam(learning_rate),
        },
        labels,
    )
    return ob.laplacian_pyramid(inner, levels)


def pyramid_finest_cross(learning_rate, levels=5, coarse_factor=1.0, b1=0.9, spatial_axes=None):
    """The finest level filtered and guided by the parameters (the defaults' filter; ``b1``,
    and ``b2 = 1 - (1 - b1)^2``), Adam on the coarser levels at ``coarse_factor`` times the
    learning rate."""
    fine = filtered_adam(learning_rate, b1=b1, spatial_axes=spatial_axes)
    coarse = optax.adam(coarse_factor * learning_rate)

    def init(params):
        leaves = jax.tree.leaves(params)
        zeros = [
            tuple(jnp.zeros(s, x.dtype) for s in level_shapes(x.shape, levels, ax)[1:] if ax)
            for x, ax in zip(leaves, _leaf_axes(params, spatial_axes))
        ]
        return fine.init(params), coarse.init(zeros)

    def update(grads, state, params=None):
        leaves, treedef = jax.tree.flatten(grads)
        axes = _leaf_axes(grads, spatial_axes)
        coeffs = [pyramid_transpose(g, levels, ax) if ax else (g,) for g, ax in zip(leaves, axes)]
        finest = jax.tree.unflatten(treedef, [c[0] for c in coeffs])
        d_fine, s_fine = fine.update(finest, state[0], params)
        d_coarse, s_coarse = coarse.update([c[1:] for c in coeffs], state[1])
        out = [
            pyramid_reconstruct((a, *b), ax) if ax else a
            for a, b, ax in zip(jax.tree.leaves(d_fine), d_coarse, axes)
        ]
        return jax.tree.unflatten(treedef, out), (s_fine, s_coarse)

    return optax.GradientTransformation(init, update)


def candidate(learning_rate, spatial_axes=None):
    """The best variant on the rendered scenes, as a tuning-benchmark candidate
    (``--candidates pyramid3_c0=experiments.pyramid_variants:candidate``): the defaults'
    filter (``b1 = 0.2``) on the finest of 3 pyramid levels, Adam on the coarser two at a
    quarter of the learning rate."""
    return pyramid_finest_cross(learning_rate, 3, 0.25, b1=0.2, spatial_axes=spatial_axes)


def variants() -> dict[str, tuple[Callable[..., optax.GradientTransformation], Sequence[float]]]:
    def wide(f):
        return f, LRS + (0.064,)

    return {
        "defaults": (tuning.defaults_factory, (0.01, 0.02, 0.04, 0.08, 0.16, 0.32)),
        "pyramid_adam (5)": (lambda learning_rate: ob.pyramid_adam(learning_rate, 5), LRS),
        "pyramid (5) + postfilter(all, self), auto": wide(pyramid_all_self),
        "pyramid (3) + postfilter(all, self), auto": wide(
            lambda learning_rate: pyramid_all_self(learning_rate, levels=3)
        ),
        "pyramid (5) + postfilter(all, self), auto, b1 0.5": wide(
            lambda learning_rate: pyramid_all_self(learning_rate, b1=0.5)
        ),
        "pyramid (5) + postfilter(all, self), sigma_d 0.3": wide(
            lambda learning_rate: pyramid_all_self(learning_rate, sigma_d=0.3)
        ),
        "pyramid (5) + postfilter(c0, self), auto": (pyramid_finest_self, LRS),
        "pyramid (5) + postfilter(c0 c1, self), auto": (
            lambda learning_rate: pyramid_finest_self(learning_rate, filtered=2),
            LRS,
        ),
        "pyramid (5) + postfilter(c0, params), auto": (pyramid_finest_cross, LRS),
        "pyramid (3) + postfilter(c0, params), auto": (
            lambda learning_rate: pyramid_finest_cross(learning_rate, levels=3),
            LRS,
        ),
        "pyramid (5) + postfilter(c0, params), auto, coarse lr x0.25": (
            lambda learning_rate: pyramid_finest_cross(learning_rate, coarse_factor=0.25),
            (0.01, 0.02, 0.04, 0.08),
        ),
        "pyramid (3) + postfilter(c0, params), auto, coarse lr x0.25": (
            lambda learning_rate: pyramid_finest_cross(learning_rate, 3, coarse_factor=0.25),
            (0.01, 0.02, 0.04, 0.08),
        ),
        "pyramid (3) + postfilter(c0, params), auto, coarse lr x0.1": (
            lambda learning_rate: pyramid_finest_cross(learning_rate, 3, coarse_factor=0.1),
            (0.01, 0.02, 0.04, 0.08),
        ),
        "pyramid (5) + postfilter(c0, params), auto, coarse lr x0.1": (
            lambda learning_rate: pyramid_finest_cross(learning_rate, coarse_factor=0.1),
            (0.01, 0.02, 0.04, 0.08),
        ),
        "pyramid (3) + postfilter(c0, params, b1 0.2), auto, coarse lr x0.1": (
            lambda learning_rate: pyramid_finest_cross(learning_rate, 3, 0.1, b1=0.2),
            (0.01, 0.02, 0.04, 0.08, 0.16),
        ),
        "pyramid (3) + postfilter(c0, params, b1 0.2), auto, coarse lr x0.25": (
            lambda learning_rate: pyramid_finest_cross(learning_rate, 3, 0.25, b1=0.2),
            (0.01, 0.02, 0.04, 0.08, 0.16),
        ),
    }


def main(argv: Sequence[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=pathlib.Path, default=pathlib.Path("results/pyramid_variants"))
    p.add_argument("--scenes", default=",".join(SCENES))
    p.add_argument("--only", default=None, help="variant names separated by semicolons")
    a = p.parse_args(argv)
    table = variants()
    names = a.only.split(";") if a.only else list(table)
    results: dict[str, dict[str, dict[str, float]]] = {}
    for scene_name in a.scenes.split(","):
        scene = sc.RENDERED[scene_name](False)
        for name in names:
            make, lrs = table[name]
            errors = tuning.evaluate(
                scene, make, {"learning_rate": list(lrs)}, seeds=(0,), progress=True
            )
            row = {f"{lr:g}": float(e) for lr, e in zip(lrs, errors[:, 0])}
            results.setdefault(name, {})[scene_name] = row
            print(scene_name, name, row, flush=True)
    a.out.mkdir(parents=True, exist_ok=True)
    (a.out / "variants.json").write_text(json.dumps(results, indent=1))
    scenes = a.scenes.split(",")
    lines = ["| variant | " + " | ".join(scenes) + " |", "|---" * (len(scenes) + 1) + "|"]
    for name, per in results.items():
        cells = []
        for s in scenes:
            best = min(per[s].items(), key=lambda kv: kv[1])
            cells.append(f"{best[1]:.4f} (lr {best[0]})")
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    (a.out / "table.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return results


if __name__ == "__main__":
    main()
