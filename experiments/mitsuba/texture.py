"""Texture recovery in Mitsuba 3 (main paper Fig. 5 analogue): a GGX roughness texture.

    python -m experiments.mitsuba.texture [--quick] [--out DIR]

The scene, built in code (no downloads): a square plane (``rectangle``) with a
``roughconductor`` BSDF (GGX, perfect conductor) whose ``alpha`` is a ``bitmap``
texture with ``raw=True`` (the texels are roughness values, not sRGB colours),
lit by a synthetic latitude-longitude environment map (a dim sky with stripes and a
sun with a soft halo near the mirror direction of the camera), seen at 60 degrees
elevation by one camera. The target roughness is ``skimage.data.camera()``
(:func:`optax_bilateral.toy.texture.target_roughness`: edges kept, log-uniform map
into ``[0.005, 0.5]``); the reference image is a high-spp render of it.

Every iteration renders the current texture with the ``prb`` integrator at ``spp``
samples per pixel with seed ``i`` (a new seed every iteration, the same for every
method), takes the loss ``mean((I - I_ref)^2 / (I_ref^2 + 1e-2))``, ``dr.backward``,
and one :class:`optax_bilateral.mitsuba.SceneOptimizer` step, which clamps the
roughness to ``[0.005, 0.5]``. Every run starts from a constant ``alpha = 0.1``.

Methods (as experiments/paper/texture.py; best of each sweep reported, every entry listed):

* ``adam``: ``optax.adam`` (b1 0.9, b2 0.999), a small learning-rate sweep.
* ``low-pass``: ``bilateral_adam`` with ``sigma_d = inf``.
* ``bilateral``: ``bilateral_adam``'s chain with ``postfilter(guide="self", log_guide=True)``.
* ``cross-bilateral``: ``bilateral_adam(log_guide=True)`` (guided by the parameters), the paper's.
* ``auto``: as cross-bilateral with ``sigma_d="auto"``; run only once the library
  has it (:func:`experiments.mitsuba.common.auto_unavailable`).

Filtered methods use ``b1 = 0.2, b2 = 1 - (1 - b1)^2`` and ``levels = 5``. The
learning-rate ``decay`` (``constant``, ``cosine``, ``hold-cosine``:
:func:`experiments.mitsuba.common.learning_rate`) is part of the sweeps.

Outputs in ``--out`` (default ``results/mitsuba_texture``): ``summary.json``,
``table.md``, ``images.png`` (renders, error images, recovered textures) and
``{loss,param_error}_vs_{iteration,time}.png``. ``seconds_per_iteration`` and the
time axis come from the methods' steps timed interleaved in one process
(:func:`experiments.mitsuba.runner.time_interleaved`).
"""

from __future__ import annotations

import dataclasses
import math
import pathlib
import time

import jax.numpy as jnp
import numpy as np

from experiments import common
from experiments.mitsuba import common as mc
from experiments.mitsuba import runner
from optax_bilateral.toy import texture as tex

#: The optimized parameter: the roughness bitmap of the plane's BSDF.
KEY = "plane.bsdf.alpha.data"
ALPHA_MIN, ALPHA_MAX = tex.ALPHA_MIN, tex.ALPHA_MAX
LOSS_EPS = tex.LOSS_EPS
CAMERA_ELEVATION = 60.0  # degrees above the plane
CAMERA_DISTANCE = 3.0
CAMERA_FOV = 42.0
REFERENCE_SEED = 1 << 20  # render seeds: iterations use 0, 1, ...; these stay clear of them
EVAL_SEED = 1 << 21


@dataclasses.dataclass(frozen=True)
class Config:
    texture_size: int  # roughness texture side, texels
    image_size: int  # rendered image side, pixels
    iterations: int
    spp: int  # samples per pixel per iteration
    reference_spp: int
    eval_spp: int  # final renders (image loss, figures)
    env_height: int  # environment map rows (columns: twice as many)
    init_alpha: float
    levels: int  # F of the filtered methods
    b1_filtered: float
    record_every: int
    timing_rounds: int  # interleaved rounds behind seconds_per_iteration
    sweeps: dict  # method -> list of swept hyperparameter dicts


def default_config(quick: bool = False) -> Config:
    """The issue's setting (256^2 texture, 128^2 image, spp 1, 300 iterations), or a test size."""
    if quick:
        one = dict(learning_rate=0.02, decay="cosine")
        return Config(
            texture_size=32,
            image_size=32,
            iterations=6,
            spp=1,
            reference_spp=16,
            eval_spp=4,
            env_height=32,
            init_alpha=0.1,
            levels=3,
            b1_filtered=0.2,
            record_every=1,
            timing_rounds=1,
            sweeps={
                "adam": [
                    dict(learning_rate=0.01, decay="cosine"),
                    dict(learning_rate=0.03, decay="constant"),
                ],
                "low-pass": [one],
                "bilateral": [dict(one, sigma_d=1.0)],
                "cross-bilateral": [dict(one, sigma_d=0.05)],
                "auto": [one],
            },
        )
    return Config(
        texture_size=256,
        image_size=128,
        iterations=300,
        spp=1,
        reference_spp=512,
        eval_spp=64,
        env_height=256,
        init_alpha=0.1,
        levels=5,
        b1_filtered=0.2,
        record_every=5,
        timing_rounds=12,
        sweeps={
            "adam": [
                dict(learning_rate=0.001, decay="constant"),
                dict(learning_rate=0.003, decay="constant"),
                dict(learning_rate=0.01, decay="constant"),
                dict(learning_rate=0.003, decay="hold-cosine"),
            ],
            "low-pass": [dict(learning_rate=0.02, decay="hold-cosine")],
            "bilateral": [
                dict(learning_rate=0.02, decay="hold-cosine", sigma_d=s) for s in (0.5, 2.0)
            ],
            "cross-bilateral": [
                dict(learning_rate=0.02, decay=d, sigma_d=0.1)
                for d in ("constant", "cosine", "hold-cosine")
            ]
            + [
                dict(learning_rate=0.02, decay=d, sigma_d=0.05) for d in ("constant", "hold-cosine")
            ],
            "auto": [dict(learning_rate=0.02, decay="hold-cosine")],
        },
    )


def hyperparameters(method: str, entry: dict, cfg: Config) -> dict:
    """A sweep entry completed with the method's fixed settings (log guide but for low-pass)."""
    return mc.hyperparameters(
        method, entry, b1=cfg.b1_filtered, levels=cfg.levels, log_guide=method != "low-pass"
    )


# ----------------------------------------------------------------------------- scene


def mirror_direction() -> np.ndarray:
    """The camera's mirror direction at the plane's centre (y up)."""
    e = math.radians(CAMERA_ELEVATION)
    return np.array([0.0, math.sin(e), math.cos(e)])


def environment_map(height: int = 256) -> np.ndarray:
    """A ``(height, 2 height, 3)`` latitude-longitude map in Mitsuba's convention (y up).

    A dim sky brightening upwards, with vertical stripes (so smooth texels reflect
    detail), and a sun with a soft halo centred on :func:`mirror_direction`: a smooth
    texel shows a small, bright highlight, a rough one a dimmer, wider one, so the
    image depends strongly on roughness everywhere on the plane.
    """
    if isinstance(height, bool) or not isinstance(height, int) or height < 4:
        raise ValueError(f"height must be an int >= 4, got {height!r}")
    theta = (np.arange(height) + 0.5) / height * np.pi
    phi = (np.arange(2 * height) + 0.5) / (2 * height) * 2 * np.pi
    theta, phi = np.meshgrid(theta, phi, indexing="ij")
    # Mitsuba's envmap: u = atan2(x, -z) / 2 pi, v = acos(y) / pi.
    d = np.stack([np.sin(theta) * np.sin(phi), np.cos(theta), -np.sin(theta) * np.cos(phi)], -1)
    up = np.clip(d[..., 1], 0.0, 1.0)
    sky = 0.03 + 0.2 * up + 0.05 * (np.sin(12 * phi) > 0) * (d[..., 1] > 0)
    c = d @ mirror_direction()
    sun = 2.0 * np.exp(-(1 - c) / 0.03) + 0.3 * np.exp(-(1 - c) / 0.3)
    return ((sky + sun)[..., None] * np.array([1.0, 0.95, 0.9])).astype(np.float32)


def scene_dict(alpha: np.ndarray, image_size: int, env: np.ndarray) -> dict:
    """The Mitsuba scene description with roughness texture ``alpha`` (H, W)."""
    import mitsuba as mi

    e = math.radians(CAMERA_ELEVATION)
    origin = [0.0, CAMERA_DISTANCE * math.sin(e), -CAMERA_DISTANCE * math.cos(e)]
    return {
        "type": "scene",
        "integrator": {"type": "prb", "max_depth": 3},
        "sensor": {
            "type": "perspective",
            "fov": CAMERA_FOV,
            "to_world": mi.ScalarTransform4f().look_at(
                origin=origin, target=[0, 0, 0], up=[0, 1, 0]
            ),
            "film": {
                "type": "hdrfilm",
                "width": image_size,
                "height": image_size,
                "rfilter": {"type": "box"},
                "pixel_format": "rgb",
            },
        },
        "plane": {
            "type": "rectangle",
            "to_world": mi.ScalarTransform4f().rotate([1, 0, 0], -90),  # normal +y
            "bsdf": {
                "type": "roughconductor",
                "distribution": "ggx",
                "material": "none",
                "alpha": {
                    "type": "bitmap",
                    "raw": True,
                    "data": mi.TensorXf(np.asarray(alpha, np.float32)[..., None]),
                },
            },
        },
        "emitter": {"type": "envmap", "bitmap": mi.Bitmap(env)},
    }


class Problem:
    """The scene (its own ``mi.SceneParameters``), target, reference image and metrics."""

    def __init__(self, cfg: Config):
        mi, _ = mc.setup()
        self.cfg = cfg
        self.keys = (KEY,)
        self.project = {KEY: (ALPHA_MIN, ALPHA_MAX)}
        self.target_alpha = tex.target_roughness("camera", cfg.texture_size)
        self.target = {KEY: self.target_alpha[..., None]}
        self.init = {KEY: np.full_like(self.target[KEY], cfg.init_alpha)}
        self.scene = mi.load_dict(
            scene_dict(self.target_alpha, cfg.image_size, environment_map(cfg.env_height))
        )
        self.params = mi.traverse(self.scene)
        self.reference, self.reference_seconds = mc.render_reference(
            self.scene, cfg.reference_spp, REFERENCE_SEED
        )
        self.images: dict[str, np.ndarray] = {}
        self.reset()

    def reset(self):
        import drjit as dr
        import mitsuba as mi

        self.params[KEY] = mi.TensorXf(self.init[KEY])
        self.params.update()
        dr.sync_thread()

    def loss(self, image):
        import drjit as dr

        return dr.mean(
            dr.square(image - self.reference) / (dr.square(self.reference) + LOSS_EPS), axis=None
        )

    def render_and_backward(self, i: int) -> float:
        import drjit as dr
        import mitsuba as mi

        image = mi.render(self.scene, self.params, spp=self.cfg.spp, seed=i)
        loss = self.loss(image)
        dr.backward(loss)
        dr.eval(dr.grad(self.params[KEY]))
        dr.sync_thread()
        return float(loss.numpy())

    def observed_fractions(self, iterations: int) -> tuple[float, float]:
        """Fractions of texels with a gradient (``observed_texels``): per iteration (mean over
        ``iterations`` renders with seeds 0, 1, ...) and in at least one of them."""
        import drjit as dr
        import mitsuba as mi

        from optax_bilateral.mitsuba import observed_texels, to_jax

        self.reset()
        seen, per = None, []
        for i in range(iterations):
            value = mi.TensorXf(dr.detach(self.params[KEY]))
            dr.enable_grad(value)
            self.params[KEY] = value
            self.params.update()
            self.render_and_backward(i)
            obs = np.asarray(observed_texels(to_jax(dr.grad(self.params[KEY]))))
            per.append(float(obs.mean()))
            seen = obs if seen is None else seen | obs
        self.reset()
        return float(np.mean(per)), float(seen.mean())

    def param_errors(self, values) -> dict:
        return {"param_error": jnp.mean(jnp.abs(values[KEY] - self.target[KEY]))}

    def render_values(self, values, spp: int, seed: int) -> np.ndarray:
        """A render of ``values`` (untimed; leaves the scene's values as they were)."""
        import drjit as dr
        import mitsuba as mi

        current = dr.detach(self.params[KEY])
        self.params[KEY] = mi.TensorXf(np.asarray(values[KEY]))
        self.params.update()
        with dr.suspend_grad():
            image = mi.render(self.scene, spp=spp, seed=seed)
            dr.eval(image)
        self.params[KEY] = current
        dr.enable_grad(self.params[KEY])
        self.params.update()
        return np.array(image)

    def evaluate(self, values, run_id: str) -> dict:
        img = self.render_values(values, self.cfg.eval_spp, EVAL_SEED)
        self.images[run_id] = img
        ref = np.asarray(self.reference)
        return {"image_loss": float(np.mean((img - ref) ** 2 / (ref**2 + LOSS_EPS)))}


def run(cfg: Config, out: pathlib.Path, progress: bool = True) -> dict:
    """Runs every method and sweep entry, writes all outputs to ``out``; returns the summary."""
    started = time.perf_counter()
    out.mkdir(parents=True, exist_ok=True)
    prob = Problem(cfg)
    observed = prob.observed_fractions(20)
    traces, samples, skipped = mc.run_sweeps(
        prob, cfg, lambda m, e: hyperparameters(m, e, cfg), mc.SWEPT, progress
    )
    initial = float(np.mean(np.abs(prob.init[KEY] - prob.target[KEY])))
    report = runner.Report(
        title=(
            f"Mitsuba 3 texture recovery: {cfg.texture_size}^2 GGX roughness, {cfg.image_size}^2 "
            f"image, prb, spp {cfg.spp}, {cfg.iterations} iterations (initial param error "
            f"{initial:.4f}). Best entry of each sweep by final param error."
        ),
        curves={
            "loss": f"training loss ({cfg.spp}-spp render)",
            "param_error": "param error: mean |alpha - target|",
        },
        curve_title=f"Mitsuba texture {cfg.texture_size}^2",
        metric_keys=mc.METRIC_KEYS,
        figures=lambda best, out: [plot_images(prob, best, out / "images.png")],
        notes=(
            f"Texels with a gradient: {100 * observed[0]:.1f}% per iteration, "
            f"{100 * observed[1]:.2f}% within 20 iterations (spp {cfg.spp}).\n\n"
        ),
        skipped=skipped,
        setting={
            **dataclasses.asdict(cfg),
            "key": KEY,
            "initial_param_error": initial,
            "reference_seconds": prob.reference_seconds,
            "observed_texels_per_iteration": observed[0],
            "observed_texels_within_20_iterations": observed[1],
            "loss": "mean((I - I_ref)^2 / (I_ref^2 + 1e-2))",
            "final_loss": f"that loss of a {cfg.eval_spp}-spp render of the final texture",
            "final_train_loss": f"the loss of the last iteration's {cfg.spp}-spp render",
            "final_param_error": "mean |alpha - alpha_target| over texels",
        },
    )
    return runner.write_report(out, traces, samples, report, started)


def plot_images(prob: Problem, best: dict, path: pathlib.Path) -> pathlib.Path:
    """Reference, target and initial; per method its render, relative error, roughness and error."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import LogNorm

    ref = np.asarray(prob.reference)
    lo, hi = (float(v) for v in np.percentile(ref, [0.5, 99.5]))
    noisy = prob.render_values(prob.target, prob.cfg.spp, 0)
    rows = len(best) + 1
    fig, axes = plt.subplots(rows, 4, figsize=(12, 3 * rows), dpi=80, squeeze=False)
    norm = LogNorm(ALPHA_MIN, ALPHA_MAX)
    axes[0, 0].imshow(mc.tone_map(ref, lo, hi))
    axes[0, 0].set_title("reference image")
    axes[0, 1].imshow(mc.tone_map(noisy, lo, hi))
    axes[0, 1].set_title(f"target, {prob.cfg.spp}-spp render")
    axes[0, 2].imshow(prob.target_alpha, cmap="viridis", norm=norm)
    axes[0, 2].set_title("target roughness (log)")
    axes[0, 3].imshow(prob.init[KEY][..., 0], cmap="viridis", norm=norm)
    axes[0, 3].set_title("initial roughness")
    for r, (method, tr) in enumerate(best.items(), start=1):
        alpha = tr.final[KEY][..., 0]
        img = prob.images[tr.name]
        rel = np.mean(np.abs(img - ref) / np.sqrt(ref**2 + LOSS_EPS), axis=-1)
        axes[r, 0].imshow(mc.tone_map(img, lo, hi))
        axes[r, 0].set_title(f"{method}: render ({prob.cfg.eval_spp} spp)")
        axes[r, 1].imshow(rel, cmap="magma", vmin=0, vmax=0.5)
        axes[r, 1].set_title("relative image error (0..0.5)")
        axes[r, 2].imshow(alpha, cmap="viridis", norm=norm)
        axes[r, 2].set_title(f"roughness, err {tr.final_metric('param_error'):.4f}")
        axes[r, 3].imshow(np.abs(alpha - prob.target_alpha), cmap="magma", vmin=0, vmax=0.1)
        axes[r, 3].set_title("|alpha - target| (0..0.1)")
    return common.save_figure(fig, path)


def main(argv=None) -> dict:
    return runner.main(
        "Texture recovery in Mitsuba 3 (paper Fig. 5 analogue): adam, "
        "low-pass, bilateral, cross-bilateral, auto.",
        "results/mitsuba_texture",
        run,
        default_config,
        argv,
    )


if __name__ == "__main__":
    main()
