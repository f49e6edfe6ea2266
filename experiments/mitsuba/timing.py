"""Per-iteration time with the real renderer (supplement Table 1 analogue), Mitsuba 3 on the CPU.

    python -m experiments.mitsuba.timing [--quick] [--out DIR] [--rounds N]

For the texture scene of :mod:`experiments.mitsuba.texture` and the volume scene of
:mod:`experiments.mitsuba.volume` (their default sizes), one process times Adam
(``optax.adam``) and ours (``bilateral_adam``, the experiments' cross-bilateral
settings) at F = 3 and F = 5 levels. Each method runs its own optimization on the
scene (its values written in before its iteration, untimed); a round runs one
iteration of every method in an order rotated every round (so load from other
processes hits all alike) and the tables give medians over rounds of

* render + backward: ``mi.render`` at spp 1, the loss, ``dr.backward``, gradients
  evaluated (``dr.sync_thread()`` before the clock is read);
* update: the whole ``SceneOptimizer.step`` (gradients and values read through DLPack,
  the compiled update and projection, values written back, ``params.update()``), and
  of it the compiled update alone;
* the total, and its change against Adam as the median over rounds of the
  per-round ratio (:func:`experiments.common.paired_ratio`).

``--scenes step`` (in the default) times the optimizer's step alone on a 48^2 x 3 texture:
``mi.ad.Adam`` against ``BilateralAdam`` (the defaults), 10x the rounds.

Writes ``timing.json`` (samples, medians, load averages, versions) and ``timing.md``.
"""

from __future__ import annotations

import dataclasses
import json
import os
import platform
import time

import optax

import optax_bilateral as ob
from experiments import common
from experiments.mitsuba import common as mc
from experiments.mitsuba import runner
from experiments.mitsuba import texture as mitsuba_texture
from experiments.mitsuba import volume as mitsuba_volume

LEVELS = (3, 5)
TIMED_PARTS = (
    ("render", "render + backward ms"),
    ("update", "update ms"),
    ("jit", "of which jitted ms"),
)
SCENES = ("texture", "volume")
# The optimizer's step alone, on a texture of the tutorials' size (issue #52's "BilateralAdam.step
# overhead, 48^2 texture").
STEP = "step"
STEP_SIZE = 48


def transforms(scene: str, cfg) -> dict[str, optax.GradientTransformation]:
    """Adam and ours at each F in :data:`LEVELS`, with the experiment's settings."""
    out = {"Adam": optax.adam(0.01)}
    for f in LEVELS:
        if scene == "texture":
            out[f"Ours (F = {f})"] = ob.bilateral_adam(
                0.02, cfg.b1_filtered, levels=f, sigma_d=0.05, log_guide=True
            )
        else:
            out[f"Ours (F = {f})"] = ob.bilateral_adam(
                0.05,
                cfg.b1_filtered,
                levels=f,
                sigma_d={mitsuba_volume.DENSITY: 0.05, mitsuba_volume.ALBEDO: 0.1},
            )
    return out


def time_scene(scene: str, quick: bool, rounds: int) -> dict:
    module = mitsuba_texture if scene == "texture" else mitsuba_volume
    cfg = module.default_config(quick)
    problem = module.Problem(cfg)
    load_before = runner.load_average()
    t0 = time.perf_counter()
    runs = {name: mc.SceneOptimizerRun(problem, tx) for name, tx in transforms(scene, cfg).items()}
    samples = runner.time_interleaved(runs, rounds=rounds)
    seconds = time.perf_counter() - t0
    rows = runner.timing_rows(samples, "Adam", TIMED_PARTS)
    size = (
        f"{cfg.texture_size}^2 texture, {cfg.image_size}^2 image"
        if scene == "texture"
        else f"{cfg.size}^3 grids, {cfg.n_views} views of {cfg.image_size}^2"
    )
    for r in rows:
        r["scene"] = f"{scene} ({size})"
    return {
        "rows": rows,
        "samples_s": samples,
        "seconds": seconds,
        "load_average_before": load_before,
        "load_average_after": runner.load_average(),
        "config": {k: v for k, v in dataclasses.asdict(cfg).items() if k != "sweeps"},
    }


def markdown(result: dict) -> str:
    cols = [
        "scene",
        "method",
        "render + backward ms",
        "update ms",
        "of which jitted ms",
        "total ms",
        "update share %",
        "total vs Adam %",
        "rounds",
    ]
    rows = [r for s in result["scenes"].values() for r in s["rows"]]
    loads = "; ".join(
        f"{k}: {v['load_average_before']} -> {v['load_average_after']}"
        for k, v in result["scenes"].items()
    )
    return (
        f"Per-iteration time, Mitsuba 3 {result['versions']['mitsuba']} "
        f"({result['variant']}, libLLVM {result['versions']['libllvm']}) on "
        f"{result['cpus']} CPU cores; medians over interleaved rounds in one process. "
        f"Load averages (1, 5, 15 min) before -> after: {loads}.\n\n"
        + common.markdown_table(rows, columns=cols, floatfmt=".3g")
        + "\n"
        + (
            f"\nThe optimizer's step alone, one {result[STEP]['size']}^2 x 3 texture key "
            "(`opt.step()`, the gradient evaluated before, the new value after; medians):\n\n"
            + common.markdown_table(result[STEP]["rows"], floatfmt=".3g")
            + "\n"
            if STEP in result
            else ""
        )
    )


def time_step(quick: bool, rounds: int) -> dict:
    """``opt.step()`` alone on one ``(48, 48, 3)`` texture key (16 quick): ``mi.ad.Adam`` and
    ``BilateralAdam`` (the defaults), interleaved; the gradient is evaluated before the clock
    starts and the new value after it stops. Medians over rounds, and the per-round ratio."""
    import numpy as np

    mi, dr = mc.setup()
    from optax_bilateral.mitsuba import BilateralAdam

    size = 16 if quick else STEP_SIZE
    rng = np.random.default_rng(0)
    target = mi.TensorXf(rng.random((size, size, 3)).astype(np.float32))
    opts = {"mi.ad.Adam": mi.ad.Adam(lr=0.01), "BilateralAdam": BilateralAdam(lr=0.02)}
    for opt in opts.values():
        opt["texture"] = mi.TensorXf(np.full((size, size, 3), 0.5, np.float32))

    def step(opt) -> float:
        dr.backward(dr.mean(dr.square(opt["texture"] - target), axis=None))
        dr.eval(dr.grad(opt["texture"]))
        dr.sync_thread()
        t = time.perf_counter()
        opt.step()
        dr.eval(opt["texture"])
        dr.sync_thread()
        return time.perf_counter() - t

    for opt in opts.values():  # compiles
        for _ in range(3):
            step(opt)
    samples: dict[str, list[float]] = {name: [] for name in opts}
    for _ in range(rounds):
        for name, opt in opts.items():
            samples[name].append(step(opt))
    rows = [
        {
            "method": name,
            "step ms": 1e3 * float(np.median(samples[name])),
            "x mi.ad.Adam": common.paired_ratio(samples, name, "mi.ad.Adam"),
            "rounds": rounds,
        }
        for name in opts
    ]
    return {"size": size, "rows": rows, "samples": samples}


def main(argv=None) -> dict:
    def extra(parser):
        parser.add_argument(
            "--rounds",
            type=int,
            default=None,
            help="interleaved rounds per scene (default: 30, quick: 2)",
        )
        parser.add_argument(
            "--scenes",
            nargs="+",
            default=[*SCENES, STEP],
            choices=[*SCENES, STEP],
            help=f"which scenes to time, and {STEP!r}: the optimizer's step alone (default: all)",
        )

    args = common.parse_args(
        "Per-iteration time of Adam vs ours with Mitsuba 3 (supplement Table 1 analogue).",
        default_out="results/mitsuba_timing",
        argv=argv,
        extra=extra,
    )
    rounds = args.rounds or (2 if args.quick else 30)
    mi, dr = mc.setup()
    from optax_bilateral.mitsuba import llvm_version

    result = {
        "variant": mc.VARIANT,
        "cpus": os.cpu_count(),
        "rounds": rounds,
        "versions": {
            "mitsuba": mi.__version__,
            "drjit": dr.__version__,
            "libllvm": ".".join(map(str, llvm_version() or ())),
            "python": platform.python_version(),
        },
        "scenes": {s: time_scene(s, args.quick, rounds) for s in args.scenes if s != STEP},
    }
    if STEP in args.scenes:
        result[STEP] = time_step(args.quick, 10 * rounds)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "timing.json").write_text(json.dumps(result, indent=2) + "\n")
    table = markdown(result)
    (args.out / "timing.md").write_text(table)
    print(table)
    print(f"Wrote {args.out / 'timing.json'} and {args.out / 'timing.md'}")
    result["table"] = table
    return result


if __name__ == "__main__":
    main()
