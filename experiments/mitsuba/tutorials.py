"""Mitsuba's own tutorials as clients: their loops, run with ``mi.ad.Adam`` and with
``BilateralAdam`` (one line changed).

    python -m experiments.mitsuba.tutorials [--quick] [--out DIR] [--tutorials NAME ...]

The loops are those of mitsuba-renderer/mitsuba-tutorials' ``inverse_rendering``
notebooks, written as they write them (``opt = mi.ad.Adam(lr=...)``, ``opt[key] =
params[key]``, ``params.update(opt)``; per iteration ``mi.render``, the loss,
``dr.backward``, ``opt.step()``, ``opt[key] = dr.clip(opt[key], ...)``,
``params.update(opt)``); the only line that differs between the methods is the one that
builds ``opt``. Scenes are built in code, no downloads:

* ``cbox`` (``gradient_based_opt``): ``mi.cornell_box()`` at 128^2 with ``prb``; the red
  wall's colour ``red.reflectance.value`` (a ``Color3f``) from ``(0.01, 0.2, 0.9)``, spp
  4, 50 iterations, MSE against a 512-spp reference; error: the tutorial's
  ``sum((param_ref - param)^2)``. Not a grid, so ``BilateralAdam`` gives it Adam's rule:
  this client checks that the swap changes nothing where there is nothing to filter.
* ``cbox-texture``: the same loop with the back wall's reflectance a 96^2 RGB bitmap
  (``back.bsdf.reflectance.data``, ``raw=True``) from a constant 0.5 towards
  ``skimage.data.astronaut()`` (mapped to [0.05, 0.95]), spp 1, 80 iterations (a 96^2
  texture at 1 spp, in the tutorial's scene and loop); error: the mean absolute texel error
  over the texels the camera sees (the boxes hide some of the wall).
* ``volume`` (``volume_optimization``): five cameras around a ``cube`` holding a
  ``heterogeneous`` medium (``scale`` 40, ``prbvolpath``, constant emitter); the reference
  density is generated in code (the toy volume's analytic plume on a 64^3 grid) instead of
  the bundled ``volume.vol``; the tutorial's two stages: a 16^3 grid from 0.002, a step
  per camera, clipped to [1e-6, 1], then ``dr.resample`` to a finer grid (the optimizer
  keeps the key and starts its state afresh, as Dr.Jit's do at a new shape) and more spp;
  error: the mean absolute density error on the reference's 64^3 grid (the estimate
  resampled linearly). Smaller than the notebook's on this CPU (see ``default_config``).

Every method runs the same iterations with the same render seeds. All runs of one
tutorial advance together, one iteration of each in turn, each timed
(:func:`experiments.mitsuba.runner.run_interleaved`): error against iteration and
against time, side by side. Outputs in ``--out/<tutorial>`` (default
``results/mitsuba_tutorials``): ``summary.json``, ``table.md``, curves, ``images.png``;
``--out/summary.md`` gathers the tables of every tutorial in ``--out``.
"""

from __future__ import annotations

import dataclasses
import pathlib
import time
from collections.abc import Callable

import numpy as np

from experiments import common
from experiments.mitsuba import common as mc
from experiments.mitsuba import runner

TUTORIALS = ("cbox", "cbox-texture", "volume")
REFERENCE_SEED = 1 << 20
EVAL_SEED = 1 << 21


@dataclasses.dataclass(frozen=True)
class Config:
    resolution: int  # film side, pixels
    iterations: int  # per stage for the volume
    spp: int
    reference_spp: int
    eval_spp: int
    learning_rates: dict  # optimizer -> learning rates swept
    texture_size: int = 96  # cbox-texture
    grids: tuple = (16, 32)  # volume: the grid side of each stage
    stage_spp: tuple = (8, 16)  # volume: spp of each stage
    reference_grid: int = 64  # volume: the generated reference's side
    record_every: int = 1


def default_config(tutorial: str, quick: bool = False) -> Config:
    """Each tutorial's setting (its notebook's, scaled for the CPU where said), or a test
    size."""
    if tutorial not in TUTORIALS:
        raise ValueError(f"tutorial must be one of {TUTORIALS}, got {tutorial!r}")
    both = ("mi.ad.Adam", "BilateralAdam")
    if quick:
        return Config(
            resolution=16,
            iterations=3,
            spp=1,
            reference_spp=8,
            eval_spp=4,
            learning_rates={m: [0.05] for m in both},
            texture_size=16,
            grids=(6, 8),
            stage_spp=(1, 2),
            reference_grid=16,
        )
    if tutorial == "cbox":
        return Config(128, 50, 4, 512, 64, {m: [0.05] for m in both})
    if tutorial == "cbox-texture":
        rates = {"mi.ad.Adam": [0.003, 0.01, 0.03, 0.1], "BilateralAdam": [0.01, 0.03, 0.1, 0.3]}
        return Config(128, 80, 1, 512, 64, rates, record_every=2)
    # The notebook: 64^2 films, 20 + 20 iterations at spp 8 then 64 on a 64^3 grid (34 s an
    # iteration of the second stage here); scaled to 48^2, spp 8 then 16, a 32^3 grid.
    return Config(48, 20, 8, 256, 32, {m: [0.02, 0.05] for m in both}, record_every=2)


def make_optimizer(name: str, lr: float):
    """The one line that differs: ``mi.ad.Adam(lr=lr)`` or ``BilateralAdam(lr=lr)``."""
    import mitsuba as mi

    from optax_bilateral.mitsuba import BilateralAdam

    if name == "mi.ad.Adam":
        return mi.ad.Adam(lr=lr)
    if name == "BilateralAdam":
        return BilateralAdam(lr=lr)
    raise ValueError(f"optimizer must be 'mi.ad.Adam' or 'BilateralAdam', got {name!r}")


class TutorialRun:
    """A :class:`experiments.mitsuba.runner.Run`: the tutorial's loop with one optimizer."""

    def __init__(self, problem, optimizer: str, lr: float):
        problem.reset()
        self.problem = problem
        self.opt = make_optimizer(optimizer, lr)
        self.opt[problem.key] = problem.params[problem.key]
        problem.params.update(self.opt)

    def activate(self) -> None:
        self.problem.params.update(self.opt)

    def step(self, i: int) -> tuple[float, dict[str, float]]:
        return self.problem.iteration(self.opt, i)

    def values(self):
        return {self.problem.key: np.array(self.opt[self.problem.key])}


def _timed(render_and_backward: Callable[[], float], update: Callable[[], None]):
    """The loop body's two halves, each timed: ``(loss, {"render": s, "update": s})``."""
    import drjit as dr

    t0 = time.perf_counter()
    loss = render_and_backward()
    dr.sync_thread()
    t1 = time.perf_counter()
    update()
    dr.sync_thread()
    return loss, {"render": t1 - t0, "update": time.perf_counter() - t1}


# ----------------------------------------------------------------------------- gradient_based_opt


def cornell_box(resolution: int, back_texture: np.ndarray | None = None) -> dict:
    """``mi.cornell_box()`` at ``resolution``^2 with ``prb`` (the tutorial's ``res=128,
    integrator='prb'``), the back wall optionally with a bitmap reflectance of its own."""
    mi, _ = mc.setup()
    scene = mi.cornell_box()
    scene["integrator"] = {"type": "prb"}
    scene["sensor"]["film"]["width"] = scene["sensor"]["film"]["height"] = resolution
    if back_texture is not None:
        scene["back"]["bsdf"] = {
            "type": "diffuse",
            "reflectance": {"type": "bitmap", "raw": True, "data": mi.TensorXf(back_texture)},
        }
    return scene


class CornellBox:
    """The ``gradient_based_opt`` tutorial: the red wall's colour."""

    key = "red.reflectance.value"

    def __init__(self, cfg: Config, scene: dict | None = None):
        import mitsuba as mi

        mc.setup()
        self.cfg = cfg
        self.scene = mi.load_dict(cornell_box(cfg.resolution) if scene is None else scene)
        self.params = mi.traverse(self.scene)
        self.image_ref, self.reference_seconds = mc.render_reference(
            self.scene, cfg.reference_spp, REFERENCE_SEED
        )
        self.param_ref = np.array(self.params[self.key])
        self.init = self.initial()
        self.images: dict[str, np.ndarray] = {}

    def initial(self):
        return np.array([[0.01], [0.2], [0.9]], np.float32)

    def write(self, value) -> None:
        self.params[self.key] = type(self.params[self.key])(np.asarray(value, np.float32))
        self.params.update()

    def reset(self) -> None:
        self.write(self.init)

    def mse(self, image):
        import drjit as dr

        return dr.mean(dr.square(image - self.image_ref))

    def iteration(self, opt, it: int):
        import drjit as dr
        import mitsuba as mi

        scene, params, key = self.scene, self.params, self.key
        loss = None

        def render_and_backward():
            nonlocal loss
            image = mi.render(scene, params, spp=self.cfg.spp, seed=it)
            loss = self.mse(image)
            dr.backward(loss)
            return float(loss.array[0])

        def update():
            opt.step()
            opt[key] = dr.clip(opt[key], 0.0, 1.0)
            params.update(opt)

        return _timed(render_and_backward, update)

    def param_errors(self, values) -> dict:
        diff = np.asarray(values[self.key], np.float64) - self.param_ref
        return {"param_error": float(np.sum(diff**2))}

    def evaluate(self, values, run_name: str) -> dict:
        current = np.array(self.params[self.key])
        self.write(values[self.key])
        (image,) = mc.render_views(self.scene, [0], self.cfg.eval_spp, EVAL_SEED)
        self.write(current)
        self.images[run_name] = image
        return {"image_loss": float(np.mean((image - np.asarray(self.image_ref)) ** 2))}


def astronaut_albedo(size: int) -> np.ndarray:
    """``skimage.data.astronaut()`` as a ``(size, size, 3)`` float32 albedo in [0.05, 0.95]."""
    from skimage import data, transform

    image = transform.resize(data.astronaut() / 255.0, (size, size), anti_aliasing=True)
    return (0.05 + 0.9 * image).astype(np.float32)


class TexturedCornellBox(CornellBox):
    """The same loop on the back wall's 96^2 albedo texture."""

    key = "back.bsdf.reflectance.data"

    def __init__(self, cfg: Config):
        self.target = astronaut_albedo(cfg.texture_size)
        super().__init__(cfg, cornell_box(cfg.resolution, self.target))
        self.seen = self._seen_texels()

    def initial(self):
        return np.full_like(self.target, 0.5)

    def _seen_texels(self) -> np.ndarray:
        """Texels with a gradient in a high-spp render: those the camera sees."""
        import drjit as dr
        import mitsuba as mi

        self.reset()
        dr.enable_grad(self.params[self.key])
        self.params.update()
        image = mi.render(self.scene, self.params, spp=max(self.cfg.reference_spp // 8, 4))
        dr.backward(self.mse(image))
        grad = np.array(dr.grad(self.params[self.key]))
        self.reset()
        return np.any(grad != 0, axis=-1)

    def param_errors(self, values) -> dict:
        error = np.abs(np.asarray(values[self.key]) - self.target).mean(axis=-1)
        return {"param_error": float(error[self.seen].mean())}


# ----------------------------------------------------------------------------- volume_optimization


def reference_density(size: int = 64) -> np.ndarray:
    """The generated reference: the toy volume's analytic plume, ``(size,) * 3 + (1,)`` in
    Mitsuba's (z, y, x) order (the tutorial loads ``volume.vol`` instead)."""
    from optax_bilateral.toy import volume as toy

    density = toy.reference_volume(size)["density"]
    return np.ascontiguousarray(density.transpose(2, 1, 0, 3)).astype(np.float32)


class Volume:
    """The ``volume_optimization`` tutorial: five cameras, a step per camera, two stages."""

    key = "object.interior_medium.sigma_t.data"
    sensor_count = 5

    def __init__(self, cfg: Config):
        import mitsuba as mi
        from mitsuba import ScalarTransform4f as T

        mc.setup()
        self.cfg = cfg
        self.sensors = []
        for i in range(self.sensor_count):
            angle = 180.0 / self.sensor_count * i - 90.0
            self.sensors.append(
                mi.load_dict(
                    {
                        "type": "perspective",
                        "fov": 45,
                        "to_world": T().rotate([0, 1, 0], angle)
                        @ T().look_at(target=[0, 0, 0], origin=[0, 0, 4], up=[0, 1, 0]),
                        "film": {
                            "type": "hdrfilm",
                            "width": cfg.resolution,
                            "height": cfg.resolution,
                            "filter": {"type": "tent"},
                        },
                    }
                )
            )
        self.reference = reference_density(cfg.reference_grid)
        t0 = time.perf_counter()
        scene_ref = mi.load_dict(self.scene_dict(self.reference))
        self.ref_images = [
            np.array(mi.render(scene_ref, sensor=s, spp=cfg.reference_spp, seed=REFERENCE_SEED))
            for s in self.sensors
        ]
        self.reference_seconds = time.perf_counter() - t0
        self.init = np.full((cfg.grids[0],) * 3 + (1,), 0.002, np.float32)
        self.scene = mi.load_dict(self.scene_dict(self.init))
        self.params = mi.traverse(self.scene)
        self.images: dict[str, np.ndarray] = {}

    def scene_dict(self, grid: np.ndarray) -> dict:
        import mitsuba as mi
        from mitsuba import ScalarTransform4f as T

        return {
            "type": "scene",
            "integrator": {"type": "prbvolpath"},
            "object": {
                "type": "cube",
                "bsdf": {"type": "null"},
                "interior": {
                    "type": "heterogeneous",
                    "sigma_t": {
                        "type": "gridvolume",
                        "grid": mi.VolumeGrid(mi.TensorXf(grid)),
                        "to_world": T().translate(-1).scale(2.0),
                    },
                    "scale": 40.0,
                },
            },
            "emitter": {"type": "constant"},
        }

    def write(self, value) -> None:
        import mitsuba as mi

        self.params[self.key] = mi.TensorXf(np.asarray(value, np.float32))
        self.params.update()

    def reset(self) -> None:
        self.write(self.init)

    def iteration(self, opt, it: int):
        import drjit as dr
        import mitsuba as mi

        scene, params, key, cfg = self.scene, self.params, self.key, self.cfg
        stage = int(it >= cfg.iterations)
        if it == cfg.iterations:  # the tutorial's second stage: a finer grid, more spp
            opt[key] = dr.resample(opt[key], shape=(cfg.grids[1],) * 3 + (1,), filter="linear")
            params.update(opt)
        total_loss = 0.0
        seconds = {"render": 0.0, "update": 0.0}
        for sensor_idx in range(self.sensor_count):
            loss = None

            def render_and_backward(sensor_idx=sensor_idx):
                nonlocal loss
                img = mi.render(
                    scene,
                    params,
                    sensor=self.sensors[sensor_idx],
                    spp=cfg.stage_spp[stage],
                    seed=it,
                )
                loss = dr.mean(dr.square(img - mi.TensorXf(self.ref_images[sensor_idx])))
                dr.backward(loss)
                return float(loss.array[0])

            def update():
                opt.step()
                opt[key] = dr.clip(opt[key], 1e-6, 1.0)
                params.update(opt)

            value, parts = _timed(render_and_backward, update)
            total_loss += value
            for part, s in parts.items():
                seconds[part] += s
        return total_loss, seconds

    def param_errors(self, values) -> dict:
        import drjit as dr
        import mitsuba as mi

        grid = mi.TensorXf(np.asarray(values[self.key], np.float32))
        fine = np.array(dr.resample(grid, shape=self.reference.shape, filter="linear"))
        return {"param_error": float(np.abs(fine - self.reference).mean())}

    def evaluate(self, values, run_name: str) -> dict:
        current = np.array(self.params[self.key])
        self.write(values[self.key])
        images = mc.render_views(self.scene, self.sensors, self.cfg.eval_spp, EVAL_SEED)
        self.write(current)
        self.images[run_name] = np.concatenate(images, axis=1)
        loss = np.mean([np.mean((a - b) ** 2) for a, b in zip(images, self.ref_images)])
        return {"image_loss": float(loss)}


PROBLEMS = {"cbox": CornellBox, "cbox-texture": TexturedCornellBox, "volume": Volume}


# ----------------------------------------------------------------------------- run, report


def entries(problem, cfg: Config) -> dict[str, list[runner.Entry]]:
    """Each optimizer's learning rates, each a :class:`TutorialRun` of the loop."""
    import functools

    return {
        name: [
            runner.Entry(
                f"{name}[lr={lr:g}]",
                {"optimizer": name, "learning_rate": lr},
                functools.partial(TutorialRun, problem, name, lr),
            )
            for lr in lrs
        ]
        for name, lrs in cfg.learning_rates.items()
    }


def run_tutorial(tutorial: str, cfg: Config, out: pathlib.Path, progress: bool = True) -> dict:
    """One tutorial's runs and report in ``out``."""
    started = time.perf_counter()
    out.mkdir(parents=True, exist_ok=True)
    problem = PROBLEMS[tutorial](cfg)
    iterations = cfg.iterations * (2 if tutorial == "volume" else 1)
    traces, samples = runner.run_interleaved(
        problem,
        entries(problem, cfg),
        iterations=iterations,
        record_every=cfg.record_every,
        progress=progress,
    )
    initial = problem.param_errors({problem.key: problem.init})["param_error"]
    labels = {
        "cbox": "sum((param_ref - param)^2) (the tutorial's)",
        "cbox-texture": "mean |texel - target| over seen texels",
        "volume": "mean |density - reference| (64^3)",
    }
    report = runner.Report(
        title=(
            f"Mitsuba tutorial '{tutorial}' ({problem.key}): {iterations} iterations, "
            f"{cfg.resolution}^2 films, initial param error {initial:.4g}; mi.ad.Adam vs "
            "BilateralAdam (one line changed), all runs interleaved. Best entry of each "
            "optimizer by final param error."
        ),
        curves={"param_error": labels[tutorial], "loss": "training loss"},
        curve_title=f"tutorial {tutorial}",
        metric_keys=mc.METRIC_KEYS,
        figures=lambda best, out: [plot_images(problem, best, out / "images.png")],
        timing_baseline="mi.ad.Adam",
        setting={
            **dataclasses.asdict(cfg),
            "tutorial": tutorial,
            "key": problem.key,
            "iterations_total": iterations,
            "initial_param_error": initial,
            "reference_seconds": problem.reference_seconds,
            "final_param_error": labels[tutorial],
            "final_loss": f"MSE of a {cfg.eval_spp}-spp render against the reference",
        },
    )
    return runner.write_report(out, traces, samples, report, started)


def plot_images(problem, best: dict, path: pathlib.Path) -> pathlib.Path:
    """The reference and each optimizer's final render (and texture, for cbox-texture)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if isinstance(problem, Volume):
        reference = np.concatenate(problem.ref_images, axis=1)
    else:
        reference = np.asarray(problem.image_ref)
    rows = {"reference": reference, **{m: problem.images[t.name] for m, t in best.items()}}
    textures = isinstance(problem, TexturedCornellBox)
    width = 3 * reference.shape[1] / reference.shape[0] + (3 if textures else 0)
    fig, axes = plt.subplots(
        len(rows), 2 if textures else 1, figsize=(width, 3 * len(rows)), dpi=80, squeeze=False
    )
    for r, (name, image) in enumerate(rows.items()):
        axes[r, 0].imshow(np.clip(image ** (1 / 2.2), 0, 1))
        axes[r, 0].set_title(name, fontsize=9)
        if textures:
            texels = problem.target if name == "reference" else best[name].final[problem.key]
            axes[r, 1].imshow(np.clip(texels, 0, 1))
            axes[r, 1].set_title("target texture" if name == "reference" else "texture", fontsize=9)
    return common.save_figure(fig, path)


def main(argv=None) -> dict:
    def extra(parser):
        parser.add_argument(
            "--tutorials",
            nargs="+",
            default=list(TUTORIALS),
            choices=TUTORIALS,
            help="which tutorials to run (default: all)",
        )

    args = common.parse_args(
        "Mitsuba's tutorials (gradient_based_opt, volume_optimization) with mi.ad.Adam and "
        "with BilateralAdam, one line changed.",
        default_out="results/mitsuba_tutorials",
        argv=argv,
        extra=extra,
    )
    results = {}
    for tutorial in args.tutorials:
        results[tutorial] = run_tutorial(
            tutorial, default_config(tutorial, args.quick), args.out / tutorial
        )
        print(results[tutorial]["table"])
    # Every tutorial run so far into this folder, so that one can be rerun alone.
    tables = [(t, args.out / t / "table.md") for t in TUTORIALS]
    text = "\n".join(f"## {t}\n\n{p.read_text()}" for t, p in tables if p.exists())
    (args.out / "summary.md").write_text(text)
    print(f"Wrote {args.out / 'summary.md'}")
    return results


if __name__ == "__main__":
    main()
