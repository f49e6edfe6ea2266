"""Benchmarks: what the filter costs, what it buys, and how it scales.

    python -m experiments.benchmarks [--quick] [--out DIR] [--only SECTION,...]

Five sections, each written to ``DIR`` (default ``results/bench``) as ``<section>.json``
and ``<section>.md`` (plus PNG plots), and summarised in ``summary.md``:

* ``overhead`` (supplement Table 1): the update alone, ``bilateral_adam`` against
  ``optax.adam`` on the same arrays (512x512x3 texture, 64^3x1 volume; F = 3 and 5,
  separable and full), and the whole iteration (render + gradient + update) of the
  texture experiment (:mod:`experiments.paper.texture`, 512^2) and the volume experiment
  (:mod:`experiments.paper.volume`, 64^3), Adam against ours with F = 3 and F = 5.
* ``accuracy``: the speed-for-accuracy trade. For F = 1..6, separable or full,
  float32 or bfloat16 fields: the filter's time, its error against the *full*
  filter evaluated in float64 (on a noisy texture gradient guided by a texture with
  edges), and the texture experiment's final error after N iterations.
* ``scaling``: time and XLA's planned peak memory of one separable F = 5 update
  against the grid size (128^2..2048^2 x3, 32^3..128^3 x1) and against F; the
  log-log slope against the number of elements (1 = linear, no hidden quadratic cost).
* ``scale``: memory and growth from 64^2 to 8192^2 (x3) and 16^3 to 384^3 (x1):
  XLA's planned temporaries of one jitted update and the state's size, as multiples
  of the parameter's size, and the time per update against ``optax.adam`` side by
  side, for ``bilateral_adam``'s defaults and a fixed ``sigma_d`` at F = 5; the
  log-log slope of time against the number of elements. Grids too large to time in
  ``SCALE_BUDGET_BYTES`` are planned only.
* ``compile``: compile time of one ``bilateral_adam`` step, and a check that new
  step counts and a ``sigma_d`` schedule (``optax.inject_hyperparams(bilateral_adam,
  static_args=("levels",))``) reuse the compiled program.

Timing method (the machine is shared and noisy): every number is a ratio of
functions timed side by side in one process, in rounds that run every function
once in a rotating order; the reported time is the median over rounds. Compilation
happens before timing. ``--quick`` shrinks everything so that the test suite can
check that the script runs; its numbers mean nothing.
"""

from __future__ import annotations

import functools
import json
import os
import pathlib
import platform
import re
import subprocess
import sys
import time
from collections.abc import Callable, Mapping, Sequence

import jax
import jax.numpy as jnp
import numpy as np
import optax
from tqdm import tqdm

import optax_bilateral as ob
from experiments import common
from experiments.benchmarks.compiles import CompileCounter

SECTIONS = ("overhead", "accuracy", "scaling", "compile", "scale")
# Run order: compile first, so that its cold compile times cannot profit from anything
# the other sections compiled in this process.
_ORDER = ("compile", "overhead", "accuracy", "scaling", "scale")


# --------------------------------------------------------------------------- timing


def interleaved(
    fns: Mapping[str, tuple[Callable, tuple]], rounds: int, inner: int = 1, desc: str = "timing"
) -> dict[str, dict]:
    """Median (and min) seconds per call of each ``fn(*args)``, timed in rotating rounds.

    Every function is called once first (compilation, excluded). Round ``r`` calls each
    function ``inner`` times in a row, the order rotated by ``r``, so that load from other
    processes hits all of them alike. Returns ``{name: {"median", "min", "samples"}}``.
    """
    names = list(fns)
    for k in names:
        f, args = fns[k]
        jax.block_until_ready(f(*args))
    samples: dict[str, list[float]] = {k: [] for k in names}
    for r in tqdm(range(rounds), desc=desc, leave=False):
        for k in names[r % len(names) :] + names[: r % len(names)]:
            f, args = fns[k]
            t0 = time.perf_counter()
            for _ in range(inner):
                out = f(*args)
            jax.block_until_ready(out)
            samples[k].append((time.perf_counter() - t0) / inner)
    return {
        k: {"median": float(np.median(v)), "min": float(np.min(v)), "samples": v}
        for k, v in samples.items()
    }


def machine() -> dict:
    """Where the numbers were measured."""
    cpu = platform.processor() or ""
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    return {
        "cpu": cpu,
        "cores": os.cpu_count(),
        "platform": platform.platform(),
        "python": platform.python_version(),
        "jax": jax.__version__,
        "optax": optax.__version__,
        "device": str(jax.devices()[0]),
        "xla_flags": os.environ.get("XLA_FLAGS", ""),
        "load_average": list(os.getloadavg()) if hasattr(os, "getloadavg") else None,
    }


# --------------------------------------------------------------------------- update programs

B1 = 0.2  # the paper's grid runs (bilateral_adam's default)
B2 = 1 - (1 - B1) ** 2
# The filter's cost is timed at a fixed sigma_d (the targets); "auto" rows add its own cost.
FIXED_SIGMA_D = 0.1
BETWEEN = ", between checks"  # the label suffix of auto's steps that skip the blend


def update_arrays(shape, seed=0, dtype=jnp.float32):
    """Parameters with edges (a guide worth following), a noisy gradient, Adam state."""
    k1, k2 = jax.random.split(jax.random.PRNGKey(seed))
    idx = np.indices(shape[:-1]).sum(0)
    blocks = ((np.indices(shape[:-1]) // max(1, shape[0] // 8)).sum(0) % 2).astype(np.float32)
    params = jnp.asarray(
        0.2 + 0.6 * blocks[..., None] + 0.02 * np.sin(idx)[..., None] * np.ones(shape[-1]),
        jnp.float32,
    )
    params = params + 0.01 * jax.random.normal(k1, shape)
    grad = (0.1 * jax.random.normal(k2, shape)).astype(dtype)
    return params, grad


def update_program(opt: optax.GradientTransformation) -> Callable:
    """jit((grads, state, params) -> (updates, state))."""
    return jax.jit(lambda g, s, p: opt.update(g, s, p))


# The benchmark's arrays are (..., C) grids: every axis but the last is spatial.
def _grid_axes(p):
    return tuple(range(p.ndim - 1))


def _opt(kind: str, levels: int = 5, separable: bool = True, mu_dtype=None):
    """``"adam"``; ``"ours"``: the filter at a fixed ``sigma_d`` (what the targets measure);
    ``"auto"``: ``bilateral_adam``'s default ``sigma_d="auto"``."""
    if kind == "adam":
        return optax.adam(1e-2, b1=B1, b2=B2)
    sigma_d = "auto" if kind == "auto" else FIXED_SIGMA_D
    return common.filtered_adam(
        1e-2,
        sigma_d=sigma_d,
        levels=levels,
        separable=separable,
        mu_dtype=mu_dtype,
        spatial_axes=_grid_axes,
    )


_UPDATES: dict = {}


def _program_of(opt):
    for o, prog in _UPDATES.values():
        if o is opt:
            return prog
    return update_program(opt)


def _program(kind: str, levels: int = 5, separable: bool = True):
    """(optimizer, jitted update), one per setting for the whole process (jit then keeps
    one executable per shape, so sections that time the same update share it)."""
    key = (kind, levels, separable)
    if key not in _UPDATES:
        opt = _opt(kind, levels, separable)
        _UPDATES[key] = (opt, update_program(opt))
    return _UPDATES[key]


def warm_state(opt, params, grad, steps=2):
    """A state after a couple of updates (non-zero moments, count > 0)."""
    state = opt.init(params)
    up = _program_of(opt)
    for _ in range(steps):
        _, state = up(grad, state, params)
    return state


# --------------------------------------------------------------------------- (a) overhead


def update_only(
    shapes: Mapping[str, tuple], variants: Sequence[tuple], rounds: int, inner: int
) -> list[dict]:
    """Update-only time of each variant against ``optax.adam`` on the same arrays."""
    rows = []
    for name, shape in shapes.items():
        params, grad = update_arrays(shape)
        # The guide moved since the state's last step, as in an optimisation (a guide at
        # rest sends sigma_d="auto" to its first-step rule, an extra filter pass).
        moved = params - 1e-2 * grad
        fns = {}
        for label, kind, levels, separable in variants:
            opt, prog = _program(kind, levels, separable)
            # auto: the timed call checks the blend's gate (its dearer step), or is one of
            # the CHECK_PERIOD - 1 steps between checks, which skip the blend.
            warm = 2
            if kind == "auto":
                warm = ob.Auto().check_period - (2 if label.endswith(BETWEEN) else 1)
            fns[label] = (prog, (grad, warm_state(opt, params, grad, warm), moved))
        res = interleaved(fns, rounds, inner, desc=f"update {name}")
        samples = {k: v["samples"] for k, v in res.items()}
        adam = res["adam"]["median"]
        for label, kind, *_ in variants:
            r = res[label]
            row = {
                "grid": name,
                "method": label,
                "ms (median)": 1e3 * r["median"],
                "ms (min)": 1e3 * r["min"],
                "x adam (median)": r["median"] / adam,
                "x adam (min)": r["min"] / res["adam"]["min"],
                "x adam (paired)": common.paired_ratio(samples, label, "adam"),
            }
            sep = label.replace(" full", " separable")
            if label.endswith(" full") and sep in samples:
                row["x separable (paired)"] = common.paired_ratio(samples, label, sep)
            fixed = label.removesuffix(BETWEEN).removesuffix(" auto")
            if kind == "auto" and fixed in samples:
                row["x fixed sigma_d (paired)"] = common.paired_ratio(samples, label, fixed)
                if label + BETWEEN in samples:
                    row["x fixed sigma_d (amortised, paired)"] = amortised_ratio(
                        samples[label], samples[label + BETWEEN], samples[fixed]
                    )
            rows.append(row)
    return rows


def amortised_ratio(check, between, fixed) -> float:
    """``sigma_d="auto"``'s update over a run against a fixed sigma_d's: per round, one step
    that checks the blend's gate and ``CHECK_PERIOD - 1`` that skip it (a closed gate, the
    case of noisy gradients), over ``CHECK_PERIOD`` fixed steps; the median over rounds."""
    c, b, f = (np.asarray(x, float) for x in (check, between, fixed))
    period = ob.Auto().check_period
    return float(np.median((c + (period - 1) * b) / (period * f)))


_PROBLEMS: dict = {}


def channel_rows(quick: bool, rounds: int, place: Callable = lambda a: a) -> list[dict]:
    """The filter alone (F = 3, fixed sigma_d) on a field of one channel against the same
    grid with two: XLA's CPU backend once fused the weights into one channel's passes and
    made them 2-14x slower than two channels' (BENCHMARKS.md, "Design decisions").
    ``place`` puts each array on the devices (``experiments.benchmarks.sharding``: split)."""
    grids = {"16x16": (16, 16)} if quick else {"512x512": (512, 512), "64^3": (64, 64, 64)}
    modes = {"separable": True} if quick else {"separable": True, "full": False}
    rows = []
    for name, shape in grids.items():
        key = jax.random.PRNGKey(0)
        guide = place(jax.random.uniform(key, shape))
        fns = {}
        for mode, separable in modes.items():
            filt = jax.jit(
                functools.partial(
                    ob.atrous_bilateral,
                    sigma_d=FIXED_SIGMA_D,
                    levels=3,
                    spatial_axes=tuple(range(len(shape))),
                    separable=separable,
                )
            )
            for c in (1, 2):
                field = place(jax.random.normal(jax.random.fold_in(key, c), shape + (c,)))
                fns[(mode, c)] = (filt, (field, guide))
        res = interleaved(fns, rounds, 3, desc=f"channels {name}")
        samples = {k: v["samples"] for k, v in res.items()}
        for mode in modes:
            rows.append(
                {
                    "grid": name,
                    "mode": mode,
                    "ms, 1 channel": 1e3 * res[(mode, 1)]["median"],
                    "ms, 2 channels": 1e3 * res[(mode, 2)]["median"],
                    "1 / 2 channels (paired)": common.paired_ratio(samples, (mode, 1), (mode, 2)),
                }
            )
    return rows


def _texture_problem(cfg):
    """The texture experiment's problem (scene, target, reference render), built once."""
    from experiments.paper import texture as texp

    key = (cfg.size, cfg.target, cfg.reference_spp, cfg.seed, cfg.spp, cfg.spp_grad)
    if key not in _PROBLEMS:
        _PROBLEMS[key] = texp.Problem(cfg)
    return _PROBLEMS[key]


# How the texture experiment runs a step (first: its default, which the target uses).
TEXTURE_STEP_KINDS = ("split", "fused")


def texture_iterations(
    quick: bool, rounds: int, levels: Sequence[int], kinds: Sequence[str] = TEXTURE_STEP_KINDS
) -> list[dict]:
    """Per-iteration time of the texture experiment at its default settings.

    Each method is timed twice: as the experiment runs it (``split``: the render and
    gradient, one program shared by every method, then the method's update program)
    and as one program (``fused``: XLA may fuse the update into the gradient's
    computation, but it also compiles the render anew for every optimizer; with glibc's
    default allocator these programs' times differed by up to 25% for reasons unrelated
    to the update). The target uses ``split``: there the methods differ by their update
    only.
    """
    from experiments.paper import texture as texp

    cfg = texp.default_config(quick)
    prob = _texture_problem(cfg)
    steps = {}
    hp = {
        "adam": cfg.sweeps["adam"][1] if len(cfg.sweeps["adam"]) > 1 else cfg.sweeps["adam"][0],
        "cross-bilateral": cfg.sweeps["cross-bilateral"][-1],
    }
    methods = {"Adam": ("adam", cfg)}
    for f in levels:
        methods[f"Ours (F = {f})"] = ("cross-bilateral", texp.dataclasses.replace(cfg, levels=f))
    for name, (m, c) in methods.items():
        opt = texp.make_optimizer(m, c)
        state = texp.set_hyperparams(opt.init(prob.init), hp[m])
        for kind in kinds:
            steps[(name, kind)] = (prob.step_fn(opt, fused=kind == "fused"), (prob.init, state))
    for k, (fn, carry) in steps.items():  # compile, and move off the start
        for i in range(2):
            carry, _ = fn(carry, i)
        jax.block_until_ready(carry)
        steps[k] = (fn, carry)
    samples = common.time_steps_samples(
        steps, rounds=rounds, first_iteration=1000, inner=1 if quick else 5
    )
    rows = []
    scene = f"texture {cfg.size}^2 (spp={cfg.spp}, spp_grad={cfg.spp_grad})"
    for name in methods:
        for kind in kinds:
            t, t_adam = np.median(samples[(name, kind)]), np.median(samples[("Adam", kind)])
            rows.append(
                {
                    "scene": scene,
                    "method": name,
                    "step": kind,
                    "ms per iteration": 1e3 * t,
                    "% vs Adam": 100.0 * (t / t_adam - 1.0),
                    "% vs Adam (paired)": 100.0
                    * (common.paired_ratio(samples, (name, kind), ("Adam", kind)) - 1.0),
                }
            )
    return rows


def volume_iterations(quick: bool, repeats: int, steps: int, levels: Sequence[int]) -> list[dict]:
    """Per-iteration time of the volume experiment (its own interleaved timing table)."""
    from experiments.paper import volume as vexp

    cfg = vexp.config(quick)
    prob = vexp.Problem(cfg)
    table = vexp.timing_table(prob, tuple(levels), repeats, steps)
    rows = []
    for r in table["rows"]:
        rows.append(
            {
                "scene": f"volume {cfg['size']}^3 (density + RGB albedo, "
                f"{cfg['views_per_step']} views of {cfg['resolution']}^2 px)",
                "method": r["Method"],
                "ms per iteration": r["ms per iteration"],
                "% vs Adam": r["% change"],
                "update ms": r["update ms"],
            }
        )
    return rows


def _overhead_setting(quick: bool):
    """(shapes, variants, rounds, inner, levels) of the update-only comparison."""
    variants = [("adam", "adam", 0, True)]
    if quick:
        # The test suite's size: as few compiled programs as possible (compiling dominates).
        variants += [("ours F=1 separable", "ours", 1, True)]
        return {"texture 16x16x3": (16, 16, 3)}, variants, 2, 1, (1,)
    lv = (3, 5)
    variants += [(f"ours F={f} separable", "ours", f, True) for f in lv]
    variants += [(f"ours F={f} full", "ours", f, False) for f in lv]
    auto_label = "ours F=3 separable auto"  # bilateral_adam's defaults
    variants += [(auto_label, "auto", 3, True), (auto_label + BETWEEN, "auto", 3, True)]
    return (
        {"texture 512x512x3": (512, 512, 3), "volume 64^3x1": (64, 64, 64, 1)},
        variants,
        21,
        3,
        lv,
    )


def target_measurements(quick: bool, kinds: Sequence[str] = TEXTURE_STEP_KINDS) -> dict:
    """What :func:`targets` needs: the update-only ratios and the texture experiment's
    per-iteration times, all measured side by side in this process."""
    shapes, variants, rounds, inner, lv = _overhead_setting(quick)
    return {
        "update_only": update_only(shapes, variants, rounds, inner),
        "texture": texture_iterations(quick, rounds=2 if quick else 30, levels=lv, kinds=kinds),
    }


def overhead(out: pathlib.Path, quick: bool) -> dict:
    lv = _overhead_setting(quick)[-1]
    # --quick: the targets' step only (the fused programs compile the render once more each).
    measured = target_measurements(quick, TEXTURE_STEP_KINDS[:1] if quick else TEXTURE_STEP_KINDS)
    upd, tex_rows = measured["update_only"], measured["texture"]
    # The volume experiment's own timing table (tested with that experiment; skipped by --quick).
    vol_rows = [] if quick else volume_iterations(quick, repeats=7, steps=5, levels=lv)
    chan_rows = channel_rows(quick, rounds=2 if quick else 15)
    data = {"update_only": upd, "texture": tex_rows, "volume": vol_rows, "channels": chan_rows}
    md = [
        "### Update only (`bilateral_adam(...).update` vs `optax.adam(...).update`, same arrays)",
        "",
        common.markdown_table(
            [{k: common.fmt(v) for k, v in r.items()} for r in upd],
            list(dict.fromkeys(k for r in upd for k in r)),  # the auto rows' ratios too
        ),
        "",
        "### Per iteration (render + gradient + update), texture experiment defaults",
        "",
        common.markdown_table([{k: common.fmt(v) for k, v in r.items()} for r in tex_rows]),
        "",
        "### Per iteration (render + gradient + update), volume experiment",
        "",
        common.markdown_table([{k: common.fmt(v) for k, v in r.items()} for r in vol_rows]),
        "",
        "### The filter alone (F = 3), a field of one channel against two",
        "",
        common.markdown_table([{k: common.fmt(v) for k, v in r.items()} for r in chan_rows]),
    ]
    md = "\n".join(md)
    common.write_results(out, "overhead", data, md)
    return {"data": data, "md": md}


# --------------------------------------------------------------------------- (b) accuracy


def _texture_fields(size: int, seed: int = 0, reference_spp: int = 64):
    """A noisy Monte Carlo gradient of the texture problem, at the target (as late in a
    run), and the log-roughness guide the texture experiment uses."""
    from optax_bilateral.toy import texture as tex

    scene = tex.make_scene(size)
    target = jnp.asarray(tex.target_roughness("camera", size))
    reference = tex.render_reference(target, scene, reference_spp, seed=seed)

    def loss(a):
        return tex.loss_fn(tex.render(a, scene, jax.random.PRNGKey(seed + 1), 1, 1), reference)

    g = jax.grad(loss)(target)
    return np.asarray(g, np.float64), np.log(np.asarray(target, np.float64) + 1e-8)


def filter_accuracy(size: int, levels: Sequence[int], sigma_d: float, rounds: int) -> list[dict]:
    """Filter time and error vs the full float64 filter, per F, mode and field dtype."""
    g, guide = _texture_fields(size, reference_spp=8 if size < 64 else 64)
    m, v = g, g * g
    with jax.enable_x64(True):
        ref = {}
        for f in levels:
            mf, vf = ob.atrous_bilateral(
                (jnp.asarray(m), jnp.asarray(v)),
                jnp.asarray(guide),
                sigma_d=sigma_d,
                levels=f,
                spatial_axes=(0, 1),
                separable=False,
            )
            ref[f] = (np.asarray(mf), np.asarray(vf))
    rows, fns = [], {}
    for f in levels:
        for separable in (True, False):
            for dtype in ("float32", "bfloat16"):
                if size < 64 and not separable and dtype == "bfloat16":
                    continue  # --quick: fewer programs to compile
                dt = jnp.dtype(dtype)
                fields = (jnp.asarray(m, dt), jnp.asarray(v, dt))
                gd = jnp.asarray(guide, jnp.float32)
                fn = jax.jit(
                    lambda a, b, gd, f=f, separable=separable: ob.atrous_bilateral(
                        (a, b),
                        gd,
                        sigma_d=sigma_d,
                        levels=f,
                        spatial_axes=(0, 1),
                        separable=separable,
                    )
                )
                mf, vf = (np.asarray(x, np.float64) for x in fn(*fields, gd))
                mr, vr = ref[f]
                step, step_ref = mf / np.sqrt(vf + 1e-30), mr / np.sqrt(vr + 1e-30)
                label = f"F={f} {'separable' if separable else 'full'} {dtype}"
                fns[label] = (fn, (*fields, gd))
                rows.append(
                    {
                        "F": f,
                        "mode": "separable" if separable else "full",
                        "dtype": dtype,
                        "m rel. L2 error": float(np.linalg.norm(mf - mr) / np.linalg.norm(mr)),
                        "v rel. L2 error": float(np.linalg.norm(vf - vr) / np.linalg.norm(vr)),
                        "step rel. L2 error": float(
                            np.linalg.norm(step - step_ref) / np.linalg.norm(step_ref)
                        ),
                        "label": label,
                    }
                )
    times = interleaved(fns, rounds, desc="filter accuracy")
    base = times[f"F={levels[0]} separable float32"]["median"]
    for r in rows:
        t = times[r.pop("label")]
        r["filter ms"] = 1e3 * t["median"]
        r[f"x F={levels[0]} separable f32"] = t["median"] / base
    return rows


def texture_runs(quick: bool, levels: Sequence[int], iterations: int | None) -> list[dict]:
    """Final texture error of the texture experiment's cross-bilateral method per setting."""
    from experiments.paper import texture as texp

    cfg = texp.default_config(quick)
    if iterations is not None:
        cfg = texp.dataclasses.replace(cfg, iterations=iterations)
    prob = _texture_problem(cfg)
    hp = cfg.sweeps["cross-bilateral"][-1]
    if quick:
        settings = [(levels[-1], True, jnp.bfloat16)]
    else:
        settings = [
            (f, sep, mu) for mu in (None, jnp.bfloat16) for sep in (True, False) for f in levels
        ]
    rows = []
    adam_opt = texp.make_optimizer("adam", cfg)
    adam_hp = cfg.sweeps["adam"][1] if len(cfg.sweeps["adam"]) > 1 else cfg.sweeps["adam"][0]
    runs = [] if quick else [("adam", None, None, None, adam_opt, adam_hp)]
    for f, separable, mu in settings:
        opt = optax.inject_hyperparams(
            common.filtered_adam,
            static_args=("levels", "b1", "guide", "log_guide", "separable", "mu_dtype"),
        )(
            learning_rate=0.01,
            sigma_d=0.1,
            b1=cfg.b1_filtered,
            levels=f,
            guide="params",
            log_guide=True,
            separable=separable,
            mu_dtype=mu,
        )
        runs.append(("cross-bilateral", f, separable, mu, opt, hp))
    for method, f, separable, mu, opt, h in runs:
        state = texp.set_hyperparams(opt.init(prob.init), h)
        name = (
            method
            if f is None
            else (
                f"F={f} {'separable' if separable else 'full'}{' bf16 m' if mu is not None else ''}"
            )
        )
        tr = common.run_method(
            name, prob.step_fn(opt), (prob.init, state), cfg.iterations, progress=True
        )
        err = float(np.mean(np.abs(np.asarray(tr.final[0]) - np.asarray(prob.target))))
        rows.append(
            {
                "run": name,
                "F": f if f is not None else 0,
                "mode": "-" if separable is None else ("separable" if separable else "full"),
                "moment dtype": "float32" if mu is None else "bfloat16 (m)",
                "iterations": cfg.iterations,
                "final mean |alpha - target|": err,
                "s per iteration (run clock)": float(np.median(tr.step_seconds)),
            }
        )
    return rows


def accuracy(out: pathlib.Path, quick: bool) -> dict:
    levels = (1,) if quick else (1, 2, 3, 4, 5, 6)
    size = 16 if quick else 512
    flt = filter_accuracy(size, levels, sigma_d=0.1, rounds=2 if quick else 11)
    runs = texture_runs(quick, levels, iterations=3 if quick else None)
    data = {
        "filter": flt,
        "texture_runs": runs,
        "filter_grid": f"{size}x{size}, m = g, v = g^2 "
        "(one 1-spp gradient of the texture problem at the target), guide log(alpha_target), "
        "sigma_d = 0.1",
    }
    _plot_accuracy(flt, out / "accuracy.png")
    md = "\n".join(
        [
            f"### Filter time and error vs the full float64 filter ({data['filter_grid']})",
            "",
            common.markdown_table([{k: common.fmt(v) for k, v in r.items()} for r in flt]),
            "",
            "### Texture experiment, cross-bilateral (its default hyperparameters), final error",
            "",
            common.markdown_table([{k: common.fmt(v) for k, v in r.items()} for r in runs]),
        ]
    )
    common.write_results(out, "accuracy", data, md)
    return {"data": data, "md": md}


def _plot_accuracy(rows, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5.5, 4), dpi=110)
    for mode in ("separable", "full"):
        for dtype, mk in (("float32", "o"), ("bfloat16", "x")):
            sel = [r for r in rows if r["mode"] == mode and r["dtype"] == dtype]
            ax.plot(
                [r["filter ms"] for r in sel],
                [max(r["step rel. L2 error"], 1e-9) for r in sel],
                marker=mk,
                label=f"{mode} {dtype}",
            )
            for r in sel:
                ax.annotate(
                    f"F={r['F']}", (r["filter ms"], max(r["step rel. L2 error"], 1e-9)), fontsize=6
                )
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("filter time (ms, median)")
    ax.set_ylabel("rel. L2 error of m/sqrt(v) vs full float64")
    ax.legend(fontsize=7)
    ax.set_title("speed vs accuracy (same F compared)", fontsize=9)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


# --------------------------------------------------------------------------- (c) scaling


def _peak_bytes(compiled) -> int:
    ma = compiled.memory_analysis()
    return int(
        ma.temp_size_in_bytes
        + ma.argument_size_in_bytes
        + ma.output_size_in_bytes
        - ma.alias_size_in_bytes
    )


def scaling(out: pathlib.Path, quick: bool) -> dict:
    if quick:
        grids = {"2d": [(16, 16, 3), (32, 32, 3)]}
        fs, f_grid, rounds = (1,), (16, 16, 3), 2
    else:
        grids = {
            "2d": [(n, n, 3) for n in (128, 256, 512, 1024, 2048)],
            "3d": [(n, n, n, 1) for n in (32, 48, 64, 96, 128)],
        }
        fs, f_grid, rounds = (1, 2, 3, 4, 5, 6), (512, 512, 3), 7
    f_main = 1 if quick else 5
    ours = f"ours F={f_main} separable"
    rows = []
    for dim, shapes in grids.items():
        for shape in shapes:
            params, grad = update_arrays(shape)
            fns, peaks = {}, {}
            for label, kind in (("adam", "adam"), (ours, "ours")):
                opt, prog = _program(kind, f_main)
                state = warm_state(opt, params, grad, steps=1)
                peaks[label] = _peak_bytes(prog.lower(grad, state, params).compile())
                fns[label] = (prog, (grad, state, params))
            res = interleaved(fns, rounds, desc=f"scaling {shape}")
            n = int(np.prod(shape))
            for label in fns:
                rows.append(
                    {
                        "sweep": f"grid {dim}",
                        "shape": "x".join(map(str, shape)),
                        "elements": n,
                        "method": label,
                        "F": 0 if label == "adam" else f_main,
                        "ms": 1e3 * res[label]["median"],
                        "ns per element": 1e9 * res[label]["median"] / n,
                        "peak MB (XLA plan)": peaks[label] / 1e6,
                        "x adam": res[label]["median"] / res["adam"]["median"],
                    }
                )
            del fns
    params, grad = update_arrays(f_grid)
    fns, peaks = {}, {}
    for f in fs:
        opt, prog = _program("ours", f)
        state = warm_state(opt, params, grad, steps=1)
        peaks[f] = _peak_bytes(prog.lower(grad, state, params).compile())
        fns[f] = (prog, (grad, state, params))
    res = interleaved(fns, rounds, desc="scaling F")
    for f in fs:
        rows.append(
            {
                "sweep": "F",
                "shape": "x".join(map(str, f_grid)),
                "elements": int(np.prod(f_grid)),
                "method": f"ours F={f} separable",
                "F": f,
                "ms": 1e3 * res[f]["median"],
                "ns per element": 1e9 * res[f]["median"] / np.prod(f_grid),
                "peak MB (XLA plan)": peaks[f] / 1e6,
                "x adam": float("nan"),
            }
        )
    slopes = {}
    for dim in grids:
        for label in ("adam", ours):
            sel = [r for r in rows if r["sweep"] == f"grid {dim}" and r["method"] == label]
            x = np.log([r["elements"] for r in sel])
            slopes[f"{dim} {label} time"] = float(
                np.polyfit(x, np.log([r["ms"] for r in sel]), 1)[0]
            )
            slopes[f"{dim} {label} peak memory"] = float(
                np.polyfit(x, np.log([r["peak MB (XLA plan)"] for r in sel]), 1)[0]
            )
    sel = [r for r in rows if r["sweep"] == "F"]
    if len(sel) > 1:
        slopes["time vs F (ms per extra level)"] = float(
            np.polyfit([r["F"] for r in sel], [r["ms"] for r in sel], 1)[0]
        )
    _plot_scaling(rows, out / "scaling.png", ours)
    data = {"rows": rows, "loglog_slopes": slopes}
    md = "\n".join(
        [
            f"### Separable F = {f_main} update vs optax.adam, time and XLA's planned peak memory",
            "",
            common.markdown_table([{k: common.fmt(v) for k, v in r.items()} for r in rows]),
            "",
            "Log-log slopes against the number of elements (1 = linear):",
            "",
            common.markdown_table([{"fit": k, "slope": common.fmt(v)} for k, v in slopes.items()]),
        ]
    )
    common.write_results(out, "scaling", data, md)
    return {"data": data, "md": md}


def _plot_scaling(rows, path, ours):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(9, 3.6), dpi=110)
    for dim, mk in (("2d", "o"), ("3d", "s")):
        for label, ls in (("adam", "--"), (ours, "-")):
            sel = [r for r in rows if r["sweep"] == f"grid {dim}" and r["method"] == label]
            x = [r["elements"] for r in sel]
            axes[0].plot(x, [r["ms"] for r in sel], ls, marker=mk, label=f"{dim} {label}")
            axes[1].plot(
                x, [r["peak MB (XLA plan)"] for r in sel], ls, marker=mk, label=f"{dim} {label}"
            )
    for ax, yl in zip(axes, ("ms per update (median)", "peak MB (XLA plan)")):
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("elements")
        ax.set_ylabel(yl)
        ax.legend(fontsize=6)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


# --------------------------------------------------------------------------- (e) scale

SCALE_METHODS = ("adam", "defaults", "sigma_d=0.1, F=5")
# What one grid's timing may hold at once (parameters, gradient, the three states, the
# largest update's temporaries and outputs): the CI machine's 24 GiB less the system's and
# a neighbour's share. Larger grids get their memory from XLA's plan only.
SCALE_BUDGET_BYTES = 14 * 2**30
SCALE_QUICK_BUDGET_BYTES = 256 * 2**10  # --quick: exercises the skip too


def scale_optimizers(learning_rate: float = 0.02) -> dict[str, optax.GradientTransformation]:
    """optax.adam, bilateral_adam's defaults and a fixed sigma_d at F = 5."""
    return {
        "adam": optax.adam(learning_rate),
        "defaults": ob.bilateral_adam(learning_rate),
        "sigma_d=0.1, F=5": ob.bilateral_adam(learning_rate, sigma_d=0.1, levels=5),
    }


def scale_grids(quick: bool) -> dict[str, list[tuple[int, ...]]]:
    if quick:  # 16^3 exceeds the quick budget: planned, not timed
        return {"2d": [(16, 16, 3)], "3d": [(16, 16, 16, 1)]}
    return {
        "2d": [(n, n, 3) for n in (64, 128, 256, 512, 1024, 2048, 4096, 8192)],
        "3d": [(n, n, n, 1) for n in (16, 32, 64, 128, 256, 384)],
    }


def tree_bytes(tree) -> int:
    """Bytes of a pytree of arrays or ``jax.ShapeDtypeStruct``s."""
    return sum(int(np.prod(x.shape)) * np.dtype(x.dtype).itemsize for x in jax.tree.leaves(tree))


def planned_update(opt: optax.GradientTransformation, shape: tuple[int, ...]) -> dict:
    """One jitted update of a float32 grid ``shape`` compiled from shapes alone (nothing is
    allocated), with XLA's plan of its memory."""
    p = jax.ShapeDtypeStruct(shape, jnp.float32)
    state = jax.eval_shape(opt.init, p)
    compiled = jax.jit(opt.update).lower(p, state, p).compile()
    ma = compiled.memory_analysis()
    return {
        "compiled": compiled,
        "temp": int(ma.temp_size_in_bytes),
        "output": int(ma.output_size_in_bytes),
        "state": tree_bytes(state),
        "params": tree_bytes(p),
    }


def scale_rows(quick: bool, budget: int = SCALE_BUDGET_BYTES) -> list[dict]:
    """Memory (XLA's plan) of every method on every grid; time per update against
    optax.adam, side by side, where the grid's timing fits ``budget``."""
    opts = scale_optimizers()
    grids = [(dim, shape) for dim, shapes in scale_grids(quick).items() for shape in shapes]
    rows = []
    for dim, shape in tqdm(grids, desc="scale"):
        plans = {m: planned_update(opt, shape) for m, opt in opts.items()}
        pbytes = plans["adam"]["params"]
        # Held during the timing: params, grad, every state, then one update at a time.
        held = 2 * pbytes + sum(p["state"] for p in plans.values())
        held += max(p["temp"] + p["output"] for p in plans.values())
        timed = held <= budget
        res = {}
        if timed:
            params, grad = update_arrays(shape)
            fns = {}
            for m, opt in opts.items():
                state = opt.init(params)
                for _ in range(2):  # count 2: the next step is one of auto's between-checks
                    _, state = plans[m]["compiled"](grad, state, params)
                fns[m] = (plans[m]["compiled"], (grad, state, params))
            n = int(np.prod(shape))
            rounds = 3 if quick else (7 if n <= 2**22 else 3)
            res = interleaved(fns, rounds, desc=f"scale {shape}")
            del fns, params, grad, state
        for m, plan in plans.items():
            row = {
                "grid": f"{dim} " + "x".join(map(str, shape)),
                "dim": dim,
                "elements": int(np.prod(shape)),
                "method": m,
                "temp / params": plan["temp"] / pbytes,
                "state / params": plan["state"] / pbytes,
                "temp MB": plan["temp"] / 1e6,
                "state MB": plan["state"] / 1e6,
                "timing held GB": held / 1e9,
                "timed": timed,
            }
            if timed:
                samples = {k: v["samples"] for k, v in res.items()}
                row["ms (median)"] = 1e3 * res[m]["median"]
                row["ns per element"] = 1e9 * res[m]["median"] / row["elements"]
                row["x adam (paired)"] = common.paired_ratio(samples, m, "adam")
            else:
                row["skipped"] = f"timing holds {held / 2**30:.3g} GiB > {budget / 2**30:.3g} GiB"
            rows.append(row)
    return rows


def loglog_slopes(rows: Sequence[Mapping], min_elements: int = 0) -> dict[str, float]:
    """Fitted slope of log(time) against log(elements) per dimension and method (1: a flat
    cost per element), over the timed grids with at least ``min_elements`` elements."""
    slopes = {}
    for dim in sorted({r["dim"] for r in rows}):
        for m in dict.fromkeys(r["method"] for r in rows):
            sel = [
                r
                for r in rows
                if r["dim"] == dim
                and r["method"] == m
                and r["timed"]
                and r["elements"] >= min_elements
            ]
            if len(sel) >= 2:
                x = np.log([r["elements"] for r in sel])
                y = np.log([r["ms (median)"] for r in sel])
                slopes[f"{dim} {m}"] = float(np.polyfit(x, y, 1)[0])
    return slopes


SCALE_COLUMNS = (
    "grid",
    "method",
    "temp / params",
    "state / params",
    "ms (median)",
    "ns per element",
    "x adam (paired)",
    "skipped",
)


def scale(out: pathlib.Path, quick: bool, budget: int | None = None) -> dict:
    if budget is None:
        budget = SCALE_QUICK_BUDGET_BYTES if quick else SCALE_BUDGET_BYTES
    rows = scale_rows(quick, budget)
    big = 2**18  # fits from 512^2x3 and 64^3 up: below, fixed per-call costs dominate
    slopes = {"all timed grids": loglog_slopes(rows)}
    if not quick:
        slopes[f">= {big} elements"] = loglog_slopes(rows, big)
    _plot_scale(rows, out / "scale.png")
    data = {"rows": rows, "loglog_slopes": slopes, "budget_bytes": budget}
    table = [{c: common.fmt(r.get(c, "")) for c in SCALE_COLUMNS} for r in rows]
    slope_rows = [
        {"fit": f"{k}: {name}", "slope": common.fmt(v)}
        for k, fits in slopes.items()
        for name, v in fits.items()
    ]
    md = "\n".join(
        [
            "### Memory and time per update against the grid size",
            "",
            "temp: XLA's planned temporaries of one jitted update "
            "(`compiled.memory_analysis().temp_size_in_bytes`); state: the optimizer "
            "state's bytes; both as multiples of the parameter's bytes (float32). ms: median "
            "over interleaved rounds, state after 2 updates (auto's between-check step); "
            "x adam: median of per-round ratios. Grids whose timing would hold more than "
            f"{budget / 2**30:.3g} GiB are planned, not timed.",
            "",
            common.markdown_table(table, list(SCALE_COLUMNS)),
            "",
            "Log-log slope of time against the number of elements (1 = a flat cost per element):",
            "",
            common.markdown_table(slope_rows),
        ]
    )
    common.write_results(out, "scale", data, md)
    return {"data": data, "md": md}


def _plot_scale(rows, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(13, 3.8), dpi=110)
    keys = ("temp / params", "state / params", "ns per element")
    for dim, mk in (("2d", "o"), ("3d", "s")):
        for m, ls in zip(SCALE_METHODS, ("--", "-", ":")):
            sel = [r for r in rows if r["dim"] == dim and r["method"] == m]
            for ax, key in zip(axes, keys):
                pts = [(r["elements"], r[key]) for r in sel if key in r]
                if pts:
                    ax.plot(*zip(*pts), ls, marker=mk, label=f"{dim} {m}")
    for ax, key in zip(axes, keys):
        ax.set_xscale("log")
        ax.set_xlabel("elements (grid points x channels)")
        ax.set_ylabel(key)
        ax.legend(fontsize=6)
    axes[2].set_yscale("log")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


# --------------------------------------------------------------------------- (d) compile


def temp_mb(compiled) -> float:
    """XLA's planned temporary memory of a compiled program, in MiB (NaN if not reported).

    On CPU this is one allocation per call; above glibc's largest mmap threshold (32 MiB)
    it is mapped and page-faulted afresh on every call (BENCHMARKS.md, "Two speeds: the
    allocator")."""
    m = compiled.memory_analysis()
    return float("nan") if m is None else m.temp_size_in_bytes / 2**20


# Issue #42's targets: an update's compile time over optax.adam's, in the same process.
COMPILE_LIMITS = {"defaults": 10.0, "fixed sigma_d": 5.0}


def _compile_optimizers() -> dict[str, optax.GradientTransformation]:
    return {
        "adam": optax.adam(0.02),
        "defaults": ob.bilateral_adam(0.02),
        "fixed sigma_d": ob.bilateral_adam(0.02, sigma_d=FIXED_SIGMA_D),
    }


def cold_compile_seconds(opt, shape) -> tuple[float, float]:
    """``(trace + lower, compile)`` seconds of ``jax.jit(opt.update)`` for a leaf of ``shape``,
    from cold caches (what a user pays for a new shape or a fresh process)."""
    params, grad = update_arrays(shape)
    state = opt.init(params)
    jax.clear_caches()
    t0 = time.perf_counter()
    lowered = jax.jit(opt.update).lower(grad, state, params)
    t1 = time.perf_counter()
    lowered.compile()
    return t1 - t0, time.perf_counter() - t1


def kernel_count(compiled) -> int:
    """The XLA kernels (fusions) of a compiled program: XLA compiles each on its own, so the
    compile follows their number (docs/research/compilation.md)."""
    return len(re.findall(r"= \S+ fusion\(", compiled.as_text() or ""))


def xla_kernels(opt, shape) -> int:
    """:func:`kernel_count` of ``jax.jit(opt.update)`` for a leaf of ``shape``."""
    params, grad = update_arrays(shape)
    return kernel_count(jax.jit(opt.update).lower(grad, opt.init(params), params).compile())


def compile_ratios(quick: bool, repeats: int) -> list[dict]:
    """Per grid and method: median seconds to trace, lower and compile one update, and its
    ratio to ``optax.adam``'s in the same repeat (rotating order; a warm-up compile first, so
    that neither pays JAX's one-time start-up)."""
    grids = [(16, 16, 1)] if quick else [(64, 64, 1), (512, 512, 3)]
    opts = _compile_optimizers()
    cold_compile_seconds(optax.sgd(0.1), (4, 4, 1))  # JAX's own start-up, paid once
    rows = []
    for shape in grids:
        samples: dict[str, list[tuple[float, float]]] = {k: [] for k in opts}
        names = list(opts)
        for r in tqdm(range(repeats), desc=f"compile {shape}", leave=False):
            for name in names[r % len(names) :] + names[: r % len(names)]:
                samples[name].append(cold_compile_seconds(opts[name], shape))
        adam = [a + b for a, b in samples["adam"]]
        for name, xs in samples.items():
            total = [a + b for a, b in xs]
            ratio = float(np.median([t / a for t, a in zip(total, adam)]))
            limit = COMPILE_LIMITS.get(name)
            rows.append(
                {
                    "grid": "x".join(map(str, shape)),
                    "method": name,
                    "trace + lower s": float(np.median([a for a, _ in xs])),
                    "compile s": float(np.median([b for _, b in xs])),
                    "total s": float(np.median(total)),
                    "x adam (median of paired)": ratio,
                    "XLA kernels": xla_kernels(opts[name], shape),
                    "limit": limit,
                    "met": None if limit is None else bool(ratio <= limit),
                }
            )
    return rows


QUICKSTART = """
import time, jax, jax.numpy as jnp, optax, optax_bilateral as ob
i, j = jnp.mgrid[:64, :64]
target = jnp.where((i - 32) ** 2 + (j - 32) ** 2 < 400, 0.8, 0.2)[..., None]
loss = lambda x: 0.5 * jnp.sum((x - target) ** 2)
opt = {opt}
@jax.jit
def step(x, state, key):
    g = jax.grad(loss)(x) + jax.random.normal(key, x.shape)
    updates, state = opt.update(g, state, x)
    return optax.apply_updates(x, updates), state
x = jnp.full(target.shape, 0.5, jnp.float32)  # as the README: compiles once
state = opt.init(x)
keys = jax.random.split(jax.random.key(0), 3)
t = time.perf_counter(); x, state = step(x, state, keys[0]); jax.block_until_ready(x)
first = time.perf_counter() - t
t = time.perf_counter(); x, state = step(x, state, keys[1]); jax.block_until_ready(x)
print(first, time.perf_counter() - t)
"""


def quickstart_first_calls() -> list[dict]:
    """The README quick start's first call of its jitted step (its compilation), in a fresh
    process each, for ``bilateral_adam`` and ``optax.adam``; and the second call."""
    rows = []
    for name, opt in (
        ("ob.bilateral_adam(learning_rate=0.02)", "ob.bilateral_adam(learning_rate=0.02)"),
        ("optax.adam(learning_rate=0.01)", "optax.adam(learning_rate=0.01)"),
    ):
        run = subprocess.run(
            [sys.executable, "-c", QUICKSTART.format(opt=opt)],
            capture_output=True,
            text=True,
            check=True,
        )
        first, second = map(float, run.stdout.split())
        rows.append({"optimizer": name, "first call s": first, "second call s": second})
    return rows


def compile_times(out: pathlib.Path, quick: bool) -> dict:
    rows = compile_ratios(quick, repeats=1 if quick else 5)
    first_calls = [] if quick else quickstart_first_calls()
    # No recompilation: steps (count changes) and a traced sigma_d schedule.
    shape = (8, 8, 3) if quick else (128, 128, 3)
    params, grad = update_arrays(shape)
    sched = optax.exponential_decay(0.2, transition_steps=1, decay_rate=0.8)
    opt = optax.inject_hyperparams(ob.bilateral_adam, static_args=("levels",))(
        learning_rate=optax.linear_schedule(1e-2, 1e-3, 10), sigma_d=sched, levels=1 if quick else 3
    )

    @jax.jit
    def step(g, s, p):
        upd, s = opt.update(g, s, p)
        return optax.apply_updates(p, upd), s

    state = opt.init(params)
    grads = [grad * (1 + 0.1 * i) for i in range(8)]
    states = []
    with CompileCounter() as compiles:  # the first step compiles, no other may
        for g in grads:
            params, state = step(g, state, params)
            states.append(state)
    sigmas = [float(s.hyperparams["sigma_d"]) for s in states]
    check = {
        "steps": 8,
        "compiled programs": compiles.count,
        "sigma_d seen by the steps": sigmas,
        "no recompilation": compiles.count == 1,
    }
    eager = eager_updates(quick)
    data = {"rows": rows, "quickstart": first_calls, "recompile_check": check, "eager": eager}
    md = [
        "### Compile time of one update (`jax.jit(opt.update).lower(...).compile()`, cold caches), "
        "against optax.adam's in the same process",
        "",
        "Medians over repeats in rotating order, after a warm-up compile; the ratio is the median "
        "of each repeat's ratio. Limits: issue #42.",
        "",
        common.markdown_table([{k: common.fmt(v) for k, v in r.items()} for r in rows]),
        "",
    ]
    if first_calls:
        md += [
            "### The README quick start's first call of its jitted step (a fresh process each)",
            "",
            common.markdown_table([{k: common.fmt(v) for k, v in r.items()} for r in first_calls]),
            "",
        ]
    md += [
        "Recompilation check: "
        '`optax.inject_hyperparams(bilateral_adam, static_args=("levels",))` '
        "with a decaying sigma_d schedule and a learning-rate schedule, "
        f"{check['steps']} steps on "
        f"{'x'.join(map(str, shape))}: {check['compiled programs']} compiled "
        f"program(s) (sigma_d went {sigmas[0]:.3g} -> {sigmas[-1]:.3g}).",
        "",
        f"### Eager updates (no jax.jit around `update`), after the first call, {eager[0]['grid']}",
        "",
        common.markdown_table([{k: common.fmt(v) for k, v in r.items()} for r in eager]),
    ]
    md = "\n".join(md)
    common.write_results(out, "compile", data, md)
    return {"data": data, "md": md}


EAGER_LIMIT_MS = 100.0


def eager_updates(quick: bool, calls: int = 7) -> list[dict]:
    """Updates called eagerly (no ``jax.jit``), as notebooks and eager optax wrappers call
    them: milliseconds per call after the first, and XLA compilations during those calls
    (0: every program is cached; one per call would mean a recompilation every step)."""
    shape = (16, 16, 3) if quick else (32, 32, 3)
    params, grad = update_arrays(shape)
    opts = {
        "adam": optax.adam(1e-2, b1=B1, b2=B2),
        "bilateral_adam": ob.bilateral_adam(1e-2),
        "prefilter + postfilter": ob.bilateral_adam(1e-2, prefilter=True),
        "memoryless postfilter": optax.chain(
            ob.postfilter(0.0, 0.0), optax.scale_by_learning_rate(1e-2)
        ),
    }
    rows = []
    for name, opt in opts.items():
        state = opt.init(params)
        upd, state = opt.update(grad, state, params)  # the first call compiles
        jax.block_until_ready(upd)
        times = []
        with CompileCounter() as compiles:
            for _ in range(calls):
                t0 = time.perf_counter()
                upd, state = opt.update(grad, state, params)
                jax.block_until_ready(upd)
                times.append(time.perf_counter() - t0)
        ms = 1e3 * float(np.median(times))
        rows.append(
            {
                "grid": "x".join(map(str, shape)),
                "method": name,
                "calls": calls,
                "eager ms (median)": ms,
                "eager ms (max)": 1e3 * max(times),
                "compilations": compiles.count,
                "limit ms": EAGER_LIMIT_MS,
                "met": bool(ms <= EAGER_LIMIT_MS and compiles.count == 0),
            }
        )
    return rows


# --------------------------------------------------------------------------- targets


def targets(overhead_data: dict) -> list[dict]:
    """The issue's performance targets, checked against this run's overhead section.

    Ratios only (both sides timed side by side in this process): the separable F = 5
    update against ``optax.adam`` (texture 512x512x3: <= 20x; volume 64^3x1: <= 30x),
    full against separable per tap (<= 1.5 * 5^n / (5 n)), and the texture experiment's
    per-iteration overhead at its default F = 5 (<= 10%), all at a fixed ``sigma_d``. Each
    ratio is the *paired* one where the rows have it (the median over rounds of the two
    programs' times in the same round, :func:`common.paired_ratio`), else the ratio of the
    two medians. And ``sigma_d="auto"`` against a fixed ``sigma_d`` (F = 3 separable: <= 1.2x).
    """
    upd = {(r["grid"], r["method"]): r for r in overhead_data["update_only"]}
    rows = []

    def add(name, value, limit, unit=""):
        if value is None:
            return
        rows.append(
            {
                "target": name,
                "measured": value,
                "limit": limit,
                "unit": unit,
                "met": bool(value <= limit),
            }
        )

    for grid, limit in (("texture 512x512x3", 20.0), ("volume 64^3x1", 30.0)):
        r = upd.get((grid, "ours F=5 separable"))
        add(
            f"separable F=5 update / adam update, {grid}",
            r and r.get("x adam (paired)", r["x adam (median)"]),
            limit,
            "x",
        )
    for grid, n in (("texture 512x512x3", 2), ("volume 64^3x1", 3)):
        for f in (3, 5):
            full, sep = (
                upd.get((grid, f"ours F={f} full")),
                upd.get((grid, f"ours F={f} separable")),
            )
            if full and sep:
                add(
                    f"full / separable update, F={f}, {grid}",
                    full.get("x separable (paired)", full["ms (median)"] / sep["ms (median)"]),
                    1.5 * 5**n / (5 * n),
                    "x",
                )
    for grid in ("texture 512x512x3", "volume 64^3x1"):  # issue #17: auto costs <= 1.2x
        r = upd.get((grid, "ours F=3 separable auto"))
        add(
            f"auto / fixed sigma_d update over its check period, F=3 separable, {grid}",
            r and r.get("x fixed sigma_d (amortised, paired)"),
            1.2,
            "x",
        )
    tex = {
        r["method"]: r
        for r in overhead_data["texture"]
        if r.get("step", TEXTURE_STEP_KINDS[0]) == TEXTURE_STEP_KINDS[0]
    }
    if "Ours (F = 5)" in tex:
        r = tex["Ours (F = 5)"]
        add(
            "texture experiment per-iteration overhead, F=5",
            r.get("% vs Adam (paired)", r["% vs Adam"]),
            10.0,
            "%",
        )
    return rows


def aggregate_targets(per_process: Sequence[Sequence[Mapping]]) -> list[dict]:
    """One row per target from the rows of :func:`targets` measured in several processes:
    the median over processes (``measured``, which decides ``met``), its range, every
    process's value, and in how many processes the target was met."""
    order, values, info = [], {}, {}
    for rows in per_process:
        for r in rows:
            if r["target"] not in values:
                order.append(r["target"])
                values[r["target"]] = []
                info[r["target"]] = (r["limit"], r["unit"])
            values[r["target"]].append(float(r["measured"]))
    out = []
    for name in order:
        v = values[name]
        limit, unit = info[name]
        med = float(np.median(v))
        out.append(
            {
                "target": name,
                "measured": med,
                "min": float(min(v)),
                "max": float(max(v)),
                "limit": limit,
                "unit": unit,
                "met": bool(med <= limit),
                "met in": f"{sum(x <= limit for x in v)}/{len(v)}",
                "per process": v,
            }
        )
    return out


def repeated_targets(out: pathlib.Path, quick: bool, processes: int) -> list[dict]:
    """:func:`target_measurements` in ``processes`` fresh Python processes, one after another.

    Why: the same compiled program can run at two speeds for a whole process on this
    machine (BENCHMARKS.md, "Targets over fresh processes"), so one process's ratios can
    be 3x off. Each
    worker times everything side by side, as the overhead section does; the targets are
    then checked on the median over processes. The workers share a persistent
    compilation cache in ``out/jax_cache`` (compile time is not measured here).
    """
    env = dict(os.environ)
    env.setdefault("JAX_COMPILATION_CACHE_DIR", str((out / "jax_cache").resolve()))
    env.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0")
    per_process = []
    for i in tqdm(range(processes), desc="target processes"):
        d = out / "processes" / str(i)
        cmd = [sys.executable, "-m", "experiments.benchmarks", "--worker", "--out", str(d)]
        subprocess.run(
            cmd + (["--quick"] if quick else []),
            check=True,
            env=env,
            cwd=pathlib.Path(__file__).resolve().parents[2],
        )
        per_process.append(json.loads((d / "measurements.json").read_text())["targets"])
    return aggregate_targets(per_process)


def _targets_md(rows: Sequence[Mapping]) -> str:
    cols = ["target", "measured", "min", "max", "limit", "unit", "met", "met in"]
    return common.markdown_table([{k: common.fmt(r.get(k, "")) for k in cols} for r in rows], cols)


# --------------------------------------------------------------------------- main


def main(argv: Sequence[str] | None = None) -> dict:
    def extra(p):
        p.add_argument(
            "--only",
            default=",".join(SECTIONS),
            help=f"comma-separated sections to run, of {SECTIONS}",
        )
        p.add_argument(
            "--processes",
            type=int,
            default=1,
            help="check the targets on the median over this many fresh processes "
            "(each timing everything side by side); 1: this process's overhead "
            "section",
        )
        p.add_argument(
            "--scale-budget-gib",
            type=float,
            default=None,
            help="scale: time only the grids whose timing holds at most this much memory "
            f"(default {SCALE_BUDGET_BYTES / 2**30:g}; --quick: "
            f"{SCALE_QUICK_BUDGET_BYTES / 2**10:g} KiB)",
        )
        p.add_argument(
            "--worker",
            action="store_true",
            help="internal: measure the targets' inputs once, write "
            "measurements.json to --out and exit",
        )

    args = common.parse_args("optax_bilateral benchmarks", "results/bench", argv, extra)
    quick = args.quick or common.quick_from_env()
    if args.processes < 1:
        raise ValueError(f"--processes must be >= 1, got {args.processes}")
    if args.worker:
        data = target_measurements(quick, kinds=TEXTURE_STEP_KINDS[:1])  # the targets' step
        data["targets"] = targets(data)
        data["machine"] = machine()
        common.write_results(args.out, "measurements", data, _targets_md(data["targets"]))
        return data
    only = [s.strip() for s in args.only.split(",") if s.strip()]
    bad = [s for s in only if s not in SECTIONS]
    if bad:
        raise ValueError(f"--only: unknown section(s) {bad}; choose from {SECTIONS}")
    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    info = machine()
    t0 = time.perf_counter()
    runners = {
        "overhead": overhead,
        "accuracy": accuracy,
        "scaling": scaling,
        "compile": compile_times,
        "scale": functools.partial(
            scale,
            budget=None if args.scale_budget_gib is None else int(args.scale_budget_gib * 2**30),
        ),
    }
    results = {}
    for s in sorted(only, key=_ORDER.index):
        results[s] = runners[s](out, quick)
    info["load_average_end"] = list(os.getloadavg()) if hasattr(os, "getloadavg") else None
    info["seconds"] = time.perf_counter() - t0
    info["command"] = (
        "python -m experiments.benchmarks"
        + (" --quick" if quick else "")
        + (f" --only {args.only}" if args.only != ",".join(SECTIONS) else "")
        + (f" --processes {args.processes}" if args.processes > 1 else "")
        + (f" --scale-budget-gib {args.scale_budget_gib:g}" if args.scale_budget_gib else "")
    )
    md = [
        f"# Benchmarks ({'quick: not meaningful' if quick else 'full'})",
        "",
        "Machine: " + ", ".join(f"{k}={v}" for k, v in info.items()),
        "",
    ]
    if "overhead" in results:
        if args.processes > 1:
            checked = repeated_targets(out, quick, args.processes)
            note = (
                f"Median over {args.processes} fresh processes, each timing everything "
                "side by side (`--processes`); `met in`: processes where the target held."
            )
        else:
            checked = targets(results["overhead"]["data"])
            note = "From this process's overhead section (one process; see `--processes`)."
        results["targets"] = {"data": checked, "md": note + "\n\n" + _targets_md(checked)}
        common.write_results(out, "targets", checked, results["targets"]["md"])
        md += ["## targets", "", results["targets"]["md"], ""]
    for s in only:
        md += [f"## {s}", "", results[s]["md"], ""]
    (out / "summary.md").write_text("\n".join(md))
    (out / "machine.json").write_text(json.dumps(common.jsonable(info), indent=1) + "\n")
    return {"machine": info, **{s: r["data"] for s, r in results.items()}}
