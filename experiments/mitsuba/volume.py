"""Volume recovery in Mitsuba 3 (main paper Figs. 8-9 analogue): density and RGB albedo grids.

    python -m experiments.mitsuba.volume [--quick] [--out DIR]

The scene, built in code (no downloads): a ``cube`` with a ``null`` BSDF whose
interior is a ``heterogeneous`` medium: extinction ``scale * density`` from a
``gridvolume`` of shape (D, H, W, 1) and an RGB ``albedo`` ``gridvolume`` (D, H, W, 3),
both over the cube. It is lit by a synthetic environment map (a sky gradient and a
small bright sun) and seen by ``n_views`` cameras on a Fibonacci sphere, rendered
together as one ``batch`` sensor (one image of ``n_views`` tiles) with ``prbvolpath``.
The target is the toy volume's analytic field
(:func:`optax_bilateral.toy.volume.reference_volume`: a wispy smoke density and a
three-colour checker albedo with sharp edges), its axes put in Mitsuba's (z, y, x)
order; every run starts from the toy's constant ``density = 0.05, albedo = 0.5``.

Every iteration renders all views at ``spp`` samples per pixel with seed ``i`` (the
same for every method), takes the loss ``mean((I - I_ref)^2)``, ``dr.backward``, and
one :class:`optax_bilateral.mitsuba.SceneOptimizer` step on both grids, which clamps
density and albedo to ``[0, 1]``.

Methods (as experiments/paper/volume.py; both grids, ``sigma_d`` given per key):

* ``adam``: ``optax.adam`` (b1 0.9, b2 0.999), a small learning-rate sweep.
* ``low-pass``: ``bilateral_adam`` with ``sigma_d = inf``.
* ``bilateral``: ``guide="self"`` with a log guide (m guided by m, v by v, every
  level by its own partially filtered input: the authors' ``cross_term_off``).
* ``cross-bilateral``: ``guide="params"`` (linear guide), the paper's method.
* ``auto``: cross-bilateral with ``sigma_d="auto"`` (the library's default).

Filtered methods: ``b1 = 0.2, b2 = 1 - (1 - b1)^2``, ``levels = 3``. The learning-rate
``decay`` (:func:`experiments.mitsuba.common.learning_rate`) is part of the sweeps.

``final_param_error`` is :func:`optax_bilateral.toy.volume.param_errors`'s: the mean
of the density's mean absolute error and the density-weighted mean absolute albedo
error. ``final_loss`` is the image loss of an ``eval_spp`` render of every view.

Outputs in ``--out`` (default ``results/mitsuba_volume``): ``summary.json``,
``table.md``, ``views.png`` (renders and error images), ``slices.png`` (recovered
grids) and ``{loss,param_error,density_error,albedo_error}_vs_{iteration,time}.png``.
"""

from __future__ import annotations

import dataclasses
import pathlib
import time

import numpy as np

from experiments import common
from experiments.mitsuba import common as mc
from experiments.mitsuba import runner
from optax_bilateral.toy import volume as toy

DENSITY = "cube.interior_medium.sigma_t.data"
ALBEDO = "cube.interior_medium.albedo.data"
KEYS = (DENSITY, ALBEDO)
CAMERA_DISTANCE = 3.0
CAMERA_FOV = 40.0
REFERENCE_SEED = 1 << 20
EVAL_SEED = 1 << 21


@dataclasses.dataclass(frozen=True)
class Config:
    size: int  # grid side, voxels
    image_size: int  # side of each view, pixels
    n_views: int  # cameras, all rendered every iteration
    iterations: int
    spp: int
    reference_spp: int
    eval_spp: int
    density_scale: float  # extinction = density_scale * density (cube side 2)
    max_depth: int  # prbvolpath path length
    env_height: int
    levels: int
    b1_filtered: float
    record_every: int
    timing_rounds: int
    sweeps: dict


def default_config(quick: bool = False) -> Config:
    """A 32^3 grid seen by 8 cameras of 40^2 pixels at 1 spp for 200 iterations, or a test size."""
    sd = {DENSITY: 0.05, ALBEDO: 0.1}
    if quick:
        one = dict(learning_rate=0.05, decay="cosine")
        return Config(
            size=8,
            image_size=16,
            n_views=2,
            iterations=4,
            spp=1,
            reference_spp=16,
            eval_spp=4,
            density_scale=4.0,
            max_depth=2,
            env_height=16,
            levels=1,
            b1_filtered=0.2,
            record_every=1,
            timing_rounds=1,
            sweeps={
                "adam": [dict(learning_rate=0.01, decay="cosine")],
                "low-pass": [one],
                "bilateral": [dict(one, sigma_d=1.0)],
                "cross-bilateral": [dict(one, sigma_d=sd)],
                "auto": [one],
            },
        )
    return Config(
        size=32,
        image_size=40,
        n_views=8,
        iterations=200,
        spp=1,
        reference_spp=256,
        eval_spp=32,
        density_scale=4.0,
        max_depth=4,
        env_height=64,
        levels=3,
        b1_filtered=0.2,
        record_every=5,
        timing_rounds=12,
        sweeps={
            "adam": [
                dict(learning_rate=0.002, decay="constant"),
                dict(learning_rate=0.005, decay="constant"),
                dict(learning_rate=0.01, decay="constant"),
                dict(learning_rate=0.005, decay="hold-cosine"),
            ],
            "low-pass": [dict(learning_rate=0.2, decay="hold-cosine")],
            "bilateral": [
                dict(learning_rate=0.2, decay="hold-cosine", sigma_d=s) for s in (1.0, 10.0)
            ],
            "cross-bilateral": [
                dict(learning_rate=0.2, decay=d, sigma_d=sd)
                for d in ("constant", "cosine", "hold-cosine")
            ],
            "auto": [dict(learning_rate=0.2, decay="hold-cosine")],
        },
    )


def hyperparameters(method: str, entry: dict, cfg: Config) -> dict:
    """A sweep entry completed with the method's fixed settings (log guide for bilateral)."""
    return mc.hyperparameters(
        method, entry, b1=cfg.b1_filtered, levels=cfg.levels, log_guide=method == "bilateral"
    )


# ----------------------------------------------------------------------------- scene

SUN_DIRECTION = np.array([0.4, 0.8, 0.45]) / np.linalg.norm([0.4, 0.8, 0.45])


def environment_map(height: int = 64) -> np.ndarray:
    """``(height, 2 height, 3)`` latitude-longitude sky (Mitsuba's convention, y up): a blue
    gradient above a dim ground and a small sun of ~300x the sky's radiance."""
    if isinstance(height, bool) or not isinstance(height, int) or height < 4:
        raise ValueError(f"height must be an int >= 4, got {height!r}")
    theta = (np.arange(height) + 0.5) / height * np.pi
    phi = (np.arange(2 * height) + 0.5) / (2 * height) * 2 * np.pi
    theta, phi = np.meshgrid(theta, phi, indexing="ij")
    d = np.stack([np.sin(theta) * np.sin(phi), np.cos(theta), -np.sin(theta) * np.cos(phi)], -1)
    sky = np.where(d[..., 1] > 0, 0.1 + 0.2 * d[..., 1], 0.05)[..., None] * np.array(
        [0.5, 0.7, 1.0]
    )
    sun = 300.0 * np.exp(-(1 - d @ SUN_DIRECTION) / 0.002)[..., None] * np.array([1.0, 0.9, 0.8])
    return (sky + sun).astype(np.float32)


def camera_positions(n_views: int, distance: float = CAMERA_DISTANCE) -> np.ndarray:
    """``(n, 3)`` points of a Fibonacci sphere of radius ``distance`` (y up)."""
    i = np.arange(n_views) + 0.5
    polar = np.arccos(1 - 2 * i / n_views)
    azimuth = np.pi * (1 + 5**0.5) * i
    return distance * np.stack(
        [np.cos(azimuth) * np.sin(polar), np.cos(polar), np.sin(azimuth) * np.sin(polar)], -1
    )


def target_volume(size: int) -> dict[str, np.ndarray]:
    """The toy's analytic target, axes (x, y, z) -> Mitsuba's grid order (z, y, x)."""
    t = toy.reference_volume(size)
    return {
        DENSITY: np.ascontiguousarray(t["density"].transpose(2, 1, 0, 3)),
        ALBEDO: np.ascontiguousarray(t["albedo"].transpose(2, 1, 0, 3)),
    }


def scene_dict(values: dict, cfg: Config) -> dict:
    import mitsuba as mi

    T = mi.ScalarTransform4f
    sensor = {
        "type": "batch",
        "film": {
            "type": "hdrfilm",
            "width": cfg.image_size * cfg.n_views,
            "height": cfg.image_size,
            "rfilter": {"type": "box"},
            "pixel_format": "rgb",
        },
    }
    for j, origin in enumerate(camera_positions(cfg.n_views)):
        up = [0, 0, 1] if abs(origin[1]) > 0.95 * CAMERA_DISTANCE else [0, 1, 0]
        sensor[f"view{j}"] = {
            "type": "perspective",
            "fov": CAMERA_FOV,
            "to_world": T().look_at(origin=origin.tolist(), target=[0, 0, 0], up=up),
        }
    unit_to_cube = T().translate([-1, -1, -1]).scale(2)  # grid [0,1]^3 -> cube [-1,1]^3

    def grid(v):
        return {
            "type": "gridvolume",
            "grid": mi.VolumeGrid(mi.TensorXf(np.asarray(v, np.float32))),
            "to_world": unit_to_cube,
        }

    return {
        "type": "scene",
        "integrator": {"type": "prbvolpath", "max_depth": cfg.max_depth},
        "sensor": sensor,
        "cube": {
            "type": "cube",
            "bsdf": {"type": "null"},
            "interior": {
                "type": "heterogeneous",
                "sigma_t": grid(values[DENSITY]),
                "albedo": grid(values[ALBEDO]),
                "scale": cfg.density_scale,
            },
        },
        "emitter": {"type": "envmap", "bitmap": mi.Bitmap(environment_map(cfg.env_height))},
    }


class Problem:
    """The scene (its own ``mi.SceneParameters``), target, reference images and metrics."""

    def __init__(self, cfg: Config):
        mi, _ = mc.setup()
        self.cfg = cfg
        self.keys = KEYS
        self.project = {DENSITY: (0.0, 1.0), ALBEDO: (0.0, 1.0)}
        self.target = target_volume(cfg.size)
        init = toy.initial_volume(cfg.size)
        self.init = {DENSITY: init["density"], ALBEDO: init["albedo"]}
        self.scene = mi.load_dict(scene_dict(self.target, cfg))
        self.params = mi.traverse(self.scene)
        self.reference, self.reference_seconds = mc.render_reference(
            self.scene, cfg.reference_spp, REFERENCE_SEED
        )
        self.images: dict[str, np.ndarray] = {}
        self.reset()

    def _write(self, values):
        import drjit as dr
        import mitsuba as mi

        for k in KEYS:
            self.params[k] = mi.TensorXf(np.asarray(values[k], np.float32))
        self.params.update()
        dr.sync_thread()

    def reset(self):
        self._write(self.init)

    def render_and_backward(self, i: int) -> float:
        import drjit as dr
        import mitsuba as mi

        image = mi.render(self.scene, self.params, spp=self.cfg.spp, seed=i)
        loss = dr.mean(dr.square(image - self.reference), axis=None)
        dr.backward(loss)
        dr.eval(*(dr.grad(self.params[k]) for k in KEYS))
        dr.sync_thread()
        return float(loss.numpy())

    def param_errors(self, values) -> dict:
        return dict(
            toy.param_errors(
                {"density": values[DENSITY], "albedo": values[ALBEDO]},
                {"density": self.target[DENSITY], "albedo": self.target[ALBEDO]},
            )
        )

    def render_values(self, values, spp: int, seed: int) -> np.ndarray:
        """All views of ``values`` (untimed; leaves the scene's values as they were)."""
        import drjit as dr

        current = {k: np.array(dr.detach(self.params[k])) for k in KEYS}
        self._write(values)
        with dr.suspend_grad():
            import mitsuba as mi

            image = np.array(mi.render(self.scene, spp=spp, seed=seed))
        self._write(current)
        for k in KEYS:
            dr.enable_grad(self.params[k])
        self.params.update()
        return image

    def evaluate(self, values, run_id: str) -> dict:
        img = self.render_values(values, self.cfg.eval_spp, EVAL_SEED)
        self.images[run_id] = img
        return {"image_loss": float(np.mean((img - np.asarray(self.reference)) ** 2))}


METRIC_KEYS = {
    **mc.METRIC_KEYS,
    "final_density_error": "density_error",
    "final_albedo_error": "albedo_error",
}


def run(cfg: Config, out: pathlib.Path, progress: bool = True) -> dict:
    """Runs every method and sweep entry, writes all outputs to ``out``; returns the summary."""
    started = time.perf_counter()
    out.mkdir(parents=True, exist_ok=True)
    prob = Problem(cfg)
    traces, samples, skipped = mc.run_sweeps(
        prob, cfg, lambda m, e: hyperparameters(m, e, cfg), mc.SWEPT, progress
    )
    initial = {k: float(v) for k, v in prob.param_errors(prob.init).items()}
    report = runner.Report(
        title=(
            f"Mitsuba 3 volume recovery: {cfg.size}^3 density + RGB albedo grids, {cfg.n_views} "
            f"views of {cfg.image_size}^2 px, prbvolpath (max_depth {cfg.max_depth}), spp "
            f"{cfg.spp}, {cfg.iterations} iterations (initial param error "
            f"{initial['param_error']:.4f}). Best entry of each sweep by final param error."
        ),
        curves={m: m for m in ("loss", "param_error", "density_error", "albedo_error")},
        curve_title=f"Mitsuba volume {cfg.size}^3",
        metric_keys=METRIC_KEYS,
        figures=lambda best, out: [
            plot_views(prob, best, out / "views.png"),
            plot_slices(prob, best, out / "slices.png"),
        ],
        extra_columns=lambda e: {
            "density MAE": e["final_density_error"],
            "albedo MAE (weighted)": e["final_albedo_error"],
        },
        skipped=skipped,
        setting={
            **dataclasses.asdict(cfg),
            "keys": list(KEYS),
            "initial": initial,
            "reference_seconds": prob.reference_seconds,
            "loss": "mean((I - I_ref)^2)",
            "final_loss": f"that loss of a {cfg.eval_spp}-spp render of every view",
            "final_param_error": "mean of the density MAE and the density-weighted albedo MAE",
        },
    )
    return runner.write_report(out, traces, samples, report, started)


def _tiles(img: np.ndarray, n_views: int) -> list[np.ndarray]:
    return np.split(np.asarray(img), n_views, axis=1)


def plot_views(prob: Problem, best: dict, path: pathlib.Path, max_views: int = 4) -> pathlib.Path:
    """Per row (reference, initial, each method): renders of a few views and |error| images."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cfg = prob.cfg
    views = np.linspace(0, cfg.n_views - 1, min(max_views, cfg.n_views)).round().astype(int)
    ref = _tiles(prob.reference, cfg.n_views)
    rows = {
        "reference": np.asarray(prob.reference),
        "initial": prob.render_values(prob.init, cfg.eval_spp, EVAL_SEED),
    }
    rows.update({m: prob.images[tr.name] for m, tr in best.items()})
    hi = float(np.percentile(np.asarray(prob.reference), 99.5)) or 1.0
    fig, axes = plt.subplots(
        len(rows),
        2 * len(views),
        figsize=(2.0 * 2 * len(views), 2.0 * len(rows)),
        dpi=80,
        squeeze=False,
    )
    for r, (name, img) in enumerate(rows.items()):
        tiles = _tiles(img, cfg.n_views)
        for c, v in enumerate(views):
            axes[r, 2 * c].imshow(np.clip(tiles[v] / hi, 0, 1), interpolation="nearest")
            axes[r, 2 * c + 1].imshow(
                np.abs(tiles[v] - ref[v]).mean(-1),
                cmap="magma",
                vmin=0,
                vmax=0.25 * hi,
                interpolation="nearest",
            )
            if r == 0:
                axes[r, 2 * c].set_title(f"view {v}", fontsize=8)
                axes[r, 2 * c + 1].set_title(f"|error| view {v}", fontsize=8)
        axes[r, 0].set_ylabel(name, fontsize=8)
    fig.suptitle(
        f"renders ({cfg.eval_spp} spp) and |render - reference| (0..{0.25 * hi:.2g})", fontsize=9
    )
    return common.save_figure(fig, path)


def plot_slices(prob: Problem, best: dict, path: pathlib.Path) -> pathlib.Path:
    """Density and albedo (where the target has medium) at two depths, per row."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = prob.cfg.size
    zs = (int(0.4 * n), int(0.65 * n))
    rows = {"target": prob.target, "initial": prob.init, **{m: tr.final for m, tr in best.items()}}
    medium = prob.target[DENSITY][..., 0] > 0.02
    fig, axes = plt.subplots(
        len(rows), 2 * len(zs), figsize=(7.5, 1.9 * len(rows)), dpi=90, squeeze=False
    )
    for r, (name, p) in enumerate(rows.items()):
        d, a = np.asarray(p[DENSITY][..., 0]), np.clip(np.asarray(p[ALBEDO]), 0, 1)
        for j, z in enumerate(zs):
            axes[r, 2 * j].imshow(
                d[z], origin="lower", cmap="magma", vmin=0, vmax=1, interpolation="nearest"
            )
            axes[r, 2 * j + 1].imshow(
                np.where(medium[z, ..., None], a[z], 0.0), origin="lower", interpolation="nearest"
            )
            if r == 0:
                axes[r, 2 * j].set_title(f"density, slice {z}", fontsize=8)
                axes[r, 2 * j + 1].set_title(f"albedo, slice {z}", fontsize=8)
        axes[r, 0].set_ylabel(name, fontsize=8)
    return common.save_figure(fig, path)


def main(argv=None) -> dict:
    return runner.main(
        "Volume recovery in Mitsuba 3 (paper Figs. 8-9 analogue): adam, "
        "low-pass, bilateral, cross-bilateral, auto.",
        "results/mitsuba_volume",
        run,
        default_config,
        argv,
    )


if __name__ == "__main__":
    main()
