"""Texture recovery with Monte Carlo gradients (main paper Fig. 5), on the toy renderer.

Recover a roughness texture ``alpha`` (GGX) of a glossy plane from one rendered
image, ``min mean((I(alpha) - I_ref)^2 / (I_ref^2 + 1e-2))``, where every
iteration renders ``I`` with ``spp`` samples and its gradient with ``spp_grad``
independent samples (``optax_bilateral.toy.texture``), so gradients are genuinely
noisy. Methods (all see the same noise: one PRNG key per iteration, shared):

* ``adam``: ``optax.adam``; a small learning-rate / ``b1`` sweep, best reported.
* ``defaults``: ``bilateral_adam(learning_rate, spatial_axes=(0, 1))``, every filter setting
  at the library's default (``sigma_d="auto"``); only the learning rate is swept, as Adam's.
  ``spatial_axes`` states the layout (one ``(H, W)`` channel), which the default leaf rule
  would guess with a warning.
* ``low-pass``: ``bilateral_adam`` with ``sigma_d = inf`` (a B-spline blur of m, v).
* ``bilateral``: ``postfilter(guide="self", log_guide=True)``, the paper's
  bilateral baseline as the authors' code runs it (``cross_term_off``): each moment
  guides itself, every a-trous level by the log-magnitude of its own input (the
  moment as the previous levels left it). The log makes the guide scale-free: with
  the raw moments as guides ``sigma_d`` would be in gradient units and ``m`` (units
  g) and ``v`` (units g^2) would need different values.
* ``cross-bilateral``: ``bilateral_adam(log_guide=True)`` with a tuned ``sigma_d``, the
  paper's method: guided by ``log alpha``.

The filtered methods but ``defaults`` use ``b1 = 0.2, b2 = 1 - (1 - b1)^2`` and
``levels = 5``. After
every update ``alpha`` is clipped to ``[0.005, 0.5]`` (projected steps, as
Mitsuba clamps roughness). Every run starts from a constant ``alpha = 0.1``.

Comparisons: *equal iterations* (every run gets the same ``iterations``), and
*equal wall time*: each method's step is timed in alternation with the others
(median over rounds: fair ratios on a shared, loaded CPU; compilation and
evaluation excluded); the budget is ``iterations`` cross-bilateral steps, and the
best Adam run is continued for as many iterations as that budget buys (Adam's
steps are cheaper: the filter costs more than this toy's render). The "time" axis
of the plots is iterations x that step time.

Three settings: the demo (``make demo``: 256^2, Adam, the defaults and the tuned
cross-bilateral filter; :func:`demo_config`), ``--full`` (the paper-like 512^2 run with
every baseline and wider sweeps; :func:`default_config`) and ``--quick`` (64^2, for the
tests).

    python -m experiments.paper.texture [--full | --quick] [--out DIR]
                                        [--target camera|noise|phantom]

writes to DIR (default ``results/texture``): ``summary.json``, ``table.md``, ``images.png``
(renders, error images, recovered textures), ``{loss,param_error}_vs_{iteration,time}.png``.
"""

from __future__ import annotations

import dataclasses
import functools
import inspect
import math
import pathlib
import time

import jax
import jax.numpy as jnp
import numpy as np
import optax

import optax_bilateral as ob
from experiments import common
from optax_bilateral.toy import texture as tex

METHODS = ("adam", "defaults", "low-pass", "bilateral", "cross-bilateral")


@dataclasses.dataclass(frozen=True)
class Config:
    size: int  # texture (= image) side, texels
    iterations: int  # equal-iteration budget of every run
    spp: int  # primal samples per pixel per iteration
    spp_grad: int  # gradient samples per pixel per iteration (independent)
    reference_spp: int  # Sobol samples of the target image
    eval_spp: int  # Sobol samples of the final renders (image loss, figures)
    init_alpha: float  # constant initial roughness
    levels: int  # a-trous levels F of the filtered methods
    b1_filtered: float  # b1 of the filtered methods (b2 = 1 - (1 - b1)^2)
    timing_rounds: int  # interleaved timing rounds per method (median; a multiple of 4 so
    # every method leads equally often)
    target: str  # optax_bilateral.toy.texture.target_roughness name
    seed: int
    sweeps: dict  # method -> list of hyperparameter dicts (the methods run, in this order)

    @property
    def methods(self) -> tuple[str, ...]:
        return tuple(m for m in METHODS if m in self.sweeps)


def default_config(quick: bool = False) -> Config:
    """The paper-like setting (512^2, 1 spp / 1 spp_grad), or a small one for tests."""
    if quick:
        return Config(
            size=64,
            iterations=30,
            spp=1,
            spp_grad=1,
            reference_spp=64,
            eval_spp=64,
            init_alpha=0.1,
            levels=3,
            b1_filtered=0.2,
            timing_rounds=4,
            target="camera",
            seed=0,
            sweeps={
                "adam": [dict(learning_rate=0.01, b1=0.9), dict(learning_rate=0.03, b1=0.9)],
                "defaults": [dict(learning_rate=0.02)],
                "low-pass": [dict(learning_rate=0.02)],
                "bilateral": [dict(learning_rate=0.02, sigma_d=1.0)],
                "cross-bilateral": [dict(learning_rate=0.02, sigma_d=0.1)],
            },
        )
    return Config(
        size=512,
        iterations=150,
        spp=1,
        spp_grad=1,
        reference_spp=256,
        eval_spp=32,
        init_alpha=0.1,
        levels=5,
        b1_filtered=0.2,
        timing_rounds=24,
        target="camera",
        seed=0,
        sweeps={
            "adam": [
                dict(learning_rate=0.003, b1=0.9),
                dict(learning_rate=0.01, b1=0.9),
                dict(learning_rate=0.03, b1=0.9),
                dict(learning_rate=0.01, b1=0.5),
            ],
            "defaults": [dict(learning_rate=lr) for lr in (0.005, 0.01, 0.02)],
            "low-pass": [dict(learning_rate=0.01), dict(learning_rate=0.02)],
            # Wide enough that the best sigma_d lies inside the sweep, not at its edge.
            "bilateral": [dict(learning_rate=0.02, sigma_d=s) for s in (0.5, 1.0, 2.0, 4.0, 8.0)],
            "cross-bilateral": [
                dict(learning_rate=0.02, sigma_d=0.05),
                dict(learning_rate=0.02, sigma_d=0.1),
            ],
        },
    )


def demo_config() -> Config:
    """``make demo``: Adam at its best learning rate, the defaults and the tuned filter on a
    256^2 texture, in under two minutes on a 2-core CPU (README.md states the time)."""
    return dataclasses.replace(
        default_config(),
        size=256,
        reference_spp=64,
        timing_rounds=8,
        sweeps={
            "adam": [dict(learning_rate=lr, b1=0.9) for lr in (0.003, 0.01, 0.03)],
            "defaults": [dict(learning_rate=lr) for lr in (0.005, 0.01)],
            "cross-bilateral": [dict(learning_rate=0.02, sigma_d=0.05)],
        },
    )


# The texture is one (H, W) channel: said explicitly (the default leaf rule would warn).
SPATIAL_AXES = (0, 1)


def _self_guided(learning_rate, sigma_d, *, b1, levels, log_guide, spatial_axes):
    """The bilateral baseline: ``bilateral_adam``'s update with each moment guiding itself."""
    return optax.chain(
        ob.postfilter(
            b1,
            sigma_d=sigma_d,
            levels=levels,
            guide="self",
            log_guide=log_guide,
            spatial_axes=spatial_axes,
        ),
        optax.scale_by_learning_rate(learning_rate),
    )


def make_optimizer(method: str, cfg: Config) -> optax.GradientTransformation:
    """The method's optimizer with its swept hyperparameters injectable (one compile per method)."""
    if method == "adam":
        return optax.inject_hyperparams(optax.adam)(learning_rate=0.01, b1=0.9)
    if method == "defaults":
        return optax.inject_hyperparams(ob.bilateral_adam, static_args=("spatial_axes",))(
            learning_rate=0.01, spatial_axes=SPATIAL_AXES
        )
    fixed = dict(b1=cfg.b1_filtered, levels=cfg.levels, spatial_axes=SPATIAL_AXES)
    static = ("levels", "b1", "log_guide", "spatial_axes")
    if method == "low-pass":
        return optax.inject_hyperparams(ob.bilateral_adam, static_args=static + ("sigma_d",))(
            learning_rate=0.01, sigma_d=math.inf, **fixed
        )
    if method == "bilateral":
        return optax.inject_hyperparams(_self_guided, static_args=static)(
            learning_rate=0.01, sigma_d=1.0, log_guide=True, **fixed
        )
    if method == "cross-bilateral":
        return optax.inject_hyperparams(ob.bilateral_adam, static_args=static)(
            learning_rate=0.01, sigma_d=0.1, log_guide=True, **fixed
        )
    raise ValueError(f"method must be one of {METHODS}, got {method!r}")


def library_defaults() -> dict:
    """``bilateral_adam``'s default filter settings, as its signature states them."""
    params = inspect.signature(ob.bilateral_adam).parameters
    keys = ("b1", "b2", "sigma_d", "levels", "log_guide")
    return {k: params[k].default for k in keys if k in params}


def fixed_hyperparameters(method: str, cfg: Config) -> dict:
    """The hyperparameters a method does not sweep (reported with every run)."""
    if method == "adam":
        return dict(b2=0.999, eps=1e-8)
    if method == "defaults":
        return {**library_defaults(), "spatial_axes": list(SPATIAL_AXES)}
    b2 = 1 - (1 - cfg.b1_filtered) ** 2
    out = dict(b1=cfg.b1_filtered, b2=b2, levels=cfg.levels)
    if method == "low-pass":
        out["sigma_d"] = math.inf
    elif method == "bilateral":
        out.update(guide="self", log_guide=True)
    else:
        out.update(guide="params", log_guide=True)  # the default guide, as log alpha
    return out


@functools.partial(jax.jit, static_argnames=("spp", "spp_grad"))
def _loss_and_grad(alpha, i, scene, reference, base_key, *, spp, spp_grad):
    """Render (``spp``), loss and gradient (``spp_grad``); one program shared by all methods."""
    key = jax.random.fold_in(base_key, i)  # one key per iteration, shared by all methods

    def loss(a):
        return tex.loss_fn(tex.render(a, scene, key, spp, spp_grad), reference)

    return jax.value_and_grad(loss)(alpha)


@functools.partial(jax.jit, static_argnames=("opt",))
def _apply(grad, carry, target, *, opt):
    """The optimizer's update and the clip to the renderer's roughness range."""
    alpha, state = carry
    updates, state = opt.update(grad, state, alpha)
    alpha = jnp.clip(optax.apply_updates(alpha, updates), tex.ALPHA_MIN, tex.ALPHA_MAX)
    return (alpha, state), jnp.mean(jnp.abs(alpha - target))


def _step(carry, i, scene, reference, target, base_key, *, opt, spp, spp_grad):
    """One iteration: two compiled programs, or one when called under ``jax.jit``."""
    value, grad = _loss_and_grad(
        carry[0], i, scene, reference, base_key, spp=spp, spp_grad=spp_grad
    )
    carry, err = _apply(grad, carry, target, opt=opt)
    return carry, {"loss": value, "param_error": err}


_fused_step = jax.jit(_step, static_argnames=("opt", "spp", "spp_grad"))


class Problem:
    """The scene, target and reference image of one configuration."""

    def __init__(self, cfg: Config):
        self.cfg = cfg
        self.scene = tex.make_scene(cfg.size)
        self.target = jnp.asarray(tex.target_roughness(cfg.target, cfg.size))
        t0 = time.perf_counter()
        self.reference = jax.block_until_ready(
            tex.render_reference(self.target, self.scene, cfg.reference_spp, seed=cfg.seed)
        )
        self.reference_seconds = time.perf_counter() - t0
        self.base_key = jax.random.PRNGKey(cfg.seed + 1)
        self.init = jnp.full((cfg.size, cfg.size), cfg.init_alpha, jnp.float32)
        self.final_images: dict[str, jax.Array] = {}

    def step_fn(self, opt, fused: bool = False):
        """``step(carry, i)``: render and gradient, then update and clip.

        Two compiled programs: the render and gradient (compiled once, shared by every
        method) and the method's update. ``fused=True`` compiles both into one program
        instead (and the render with it, for every optimizer); with glibc's default
        allocator the fused programs' times differed by up to 25% between optimizers for
        reasons unrelated to the update (page faults, BENCHMARKS.md "Two speeds"), so the
        experiment and its timings use the two programs.
        """
        cfg = self.cfg
        run = _fused_step if fused else _step

        def step(carry, i):
            return run(
                carry,
                i,
                self.scene,
                self.reference,
                self.target,
                self.base_key,
                opt=opt,
                spp=cfg.spp,
                spp_grad=cfg.spp_grad,
            )

        return step

    def evaluate(self, run_id: str):
        """Untimed: the image loss of a low-noise render of the current texture."""

        def evaluate(carry):
            img = tex.render_reference(
                carry[0], self.scene, self.cfg.eval_spp, seed=self.cfg.seed + 2
            )
            self.final_images[run_id] = img
            return {"image_loss": tex.loss_fn(img, self.reference)}

        return evaluate


def set_hyperparams(state, hp: dict):
    for k, v in hp.items():
        state.hyperparams[k] = jnp.asarray(v, state.hyperparams[k].dtype)
    return state


def _run_id(method: str, hp: dict) -> str:
    return method + "[" + ", ".join(f"{k}={v:g}" for k, v in hp.items()) + "]"


METRIC_KEYS = {
    "final_param_error": "param_error",
    "final_loss": "image_loss",
    "final_train_loss": "loss",
}


def run(cfg: Config, out: pathlib.Path, progress: bool = True) -> dict:
    """Runs every method and sweep entry, writes all outputs to ``out``; returns the summary."""
    t_start = time.perf_counter()
    out.mkdir(parents=True, exist_ok=True)
    prob = Problem(cfg)
    traces: dict[str, list[common.Trace]] = {}
    opts = {}
    for method in cfg.methods:
        opt = make_optimizer(method, cfg)
        opts[method] = opt
        step = prob.step_fn(opt)
        traces[method] = []
        for hp in cfg.sweeps[method]:
            run_id = _run_id(method, hp)
            state = set_hyperparams(opt.init(prob.init), hp)
            tr = common.run_method(
                run_id,
                step,
                (prob.init, state),
                cfg.iterations,
                evaluate=prob.evaluate(run_id),
                evaluate_every=cfg.iterations,
                hyperparameters={**hp, **fixed_hyperparameters(method, cfg)},
                progress=progress,
            )
            traces[method].append(tr)

    best = {m: common.best_trace(traces[m], "param_error") for m in cfg.methods}

    # Step cost per method, timed in alternation (fair ratios on a shared, loaded CPU); it
    # sets seconds_per_iteration and the time axis, so these do not depend on the load
    # during each run (the runs' own clocks are kept as measured_seconds_per_iteration).
    spi = common.time_steps_interleaved(
        {m: (prob.step_fn(opts[m]), best[m].final) for m in cfg.methods},
        rounds=cfg.timing_rounds,
        first_iteration=10**6,
    )
    for m in cfg.methods:
        for tr in traces[m]:
            tr.timed_seconds_per_iteration = spi[m]

    # Equal wall time: the budget is the cross-bilateral's N steps; the best Adam run is
    # continued for as many iterations as that budget buys at Adam's step cost.
    budget = cfg.iterations * spi["cross-bilateral"]
    adam_best = best["adam"]
    adam_iters = round(budget / spi["adam"])
    adam_long = adam_best
    if adam_iters > cfg.iterations:
        more = common.run_method(
            "adam (equal time)",
            prob.step_fn(opts["adam"]),
            adam_best.final,
            adam_iters - cfg.iterations,
            first_iteration=cfg.iterations,
            evaluate=prob.evaluate("adam (equal time)"),
            evaluate_every=adam_iters,
            progress=progress,
        )
        adam_long = common.concat_traces(adam_best, more, name="adam (equal time)")

    curves = {m: best[m] for m in cfg.methods}
    if adam_long is not adam_best:
        curves["adam (equal time)"] = adam_long
    labels = {
        "loss": f"training loss ({cfg.spp}-spp render; includes MC variance)",
        "param_error": "param error: mean |alpha - target|",
    }
    pngs = [
        common.plot_curves(
            curves,
            m,
            out / f"{m}_vs_{x}.png",
            x=x,
            ylabel=labels[m],
            title=f"texture {cfg.size}^2 ({cfg.target}): {m} vs {x}",
        )
        for m in ("loss", "param_error")
        for x in ("iteration", "time")
    ]
    pngs.append(_plot_images(prob, best, adam_long, out / "images.png"))

    summary = _summary(cfg, prob, traces, best, adam_long, budget)
    summary["pngs"] = [str(p) for p in pngs]
    summary["total_seconds"] = time.perf_counter() - t_start
    common.write_summary(
        out, summary["methods"], **{k: v for k, v in summary.items() if k != "methods"}
    )
    table = markdown(summary)
    (out / "table.md").write_text(table + "\n")
    summary["table"] = table
    return summary


def _summary(cfg, prob, traces, best, adam_long, budget) -> dict:
    methods = {}
    for m in cfg.methods:
        entry = common.summary_entry(best[m], METRIC_KEYS)
        entry["sweep"] = [common.summary_entry(t, METRIC_KEYS) for t in traces[m]]
        methods[m] = entry
    equal_time = {}
    for m in cfg.methods:
        tr = adam_long if m == "adam" else best[m]
        keep = tr.time_axis <= budget * (1 + 1e-9)
        equal_time[m] = {
            "param_error": tr.metric_at_time("param_error", budget),
            "iterations": int(tr.iterations[keep][-1]) if keep.any() else 0,
            # A filtered run cheaper than the cross-bilateral still stops at N iterations
            # (it is not continued); its own total time is given here.
            "run_seconds": float(tr.time_axis[-1]),
        }
    methods["adam"]["equal_wall_time"] = {
        "iterations": int(adam_long.iterations[-1]),
        "final_param_error": adam_long.final_metric("param_error"),
        "final_loss": adam_long.final_metric("image_loss"),
    }
    return {
        "methods": methods,
        "equal_wall_time": {"budget_seconds": budget, "methods": equal_time},
        "setting": {
            **dataclasses.asdict(cfg),
            "reference_seconds": prob.reference_seconds,
            "initial_param_error": float(jnp.mean(jnp.abs(prob.init - prob.target))),
            "loss": "mean((I - I_ref)^2 / (I_ref^2 + 1e-2))",
            "final_loss": f"loss of a {cfg.eval_spp}-spp Sobol render of the final texture",
            "final_train_loss": f"loss of the last iteration's {cfg.spp}-spp render",
            "final_param_error": "mean |alpha - alpha_target| over texels",
        },
    }


def markdown(summary: dict) -> str:
    """Two tables: the best run per method (equal iterations and equal time), then every run."""
    eq = summary["equal_wall_time"]
    rows = []
    for m, e in summary["methods"].items():
        et = eq["methods"][m]
        rows.append(
            {
                "method": m,
                "hyperparameters": _hp_str(e["hyperparameters"]),
                "s/iter": e["seconds_per_iteration"],
                "param error @ equal iters": e["final_param_error"],
                "image loss @ equal iters": e["final_loss"],
                "param error @ equal time": et["param_error"],
                "iters in that time": et["iterations"],
            }
        )
    n = next(iter(summary["methods"].values()))["iterations"]
    head = (
        f"Texture recovery ({summary['setting']['target']} target), "
        f"{summary['setting']['size']}^2, spp {summary['setting']['spp']}"
        f"/{summary['setting']['spp_grad']}: best of each sweep at {n} iterations; equal "
        f"wall time = {eq['budget_seconds']:.2f} s = {n} cross-bilateral steps at the step costs "
        f"timed in alternation (column s/iter). "
        f"Initial param error {summary['setting']['initial_param_error']:.4f}.\n\n"
    )
    sweep_rows = [
        {
            "method": m,
            "hyperparameters": _hp_str(s["hyperparameters"], swept_only=True),
            "param error": s["final_param_error"],
            "image loss": s["final_loss"],
            "s/iter": s["seconds_per_iteration"],
        }
        for m, e in summary["methods"].items()
        for s in e["sweep"]
    ]
    return (
        head
        + common.markdown_table(rows)
        + "\n\nEvery sweep entry (equal iterations):\n\n"
        + common.markdown_table(sweep_rows)
    )


def _hp_str(hp: dict, swept_only: bool = False) -> str:
    keys = ("learning_rate", "b1", "sigma_d") if swept_only else tuple(hp)
    short = {"learning_rate": "lr"}

    def fmt(v):
        return f"{v:g}" if isinstance(v, (int, float)) and not isinstance(v, bool) else f"{v}"

    return ", ".join(
        f"{short.get(k, k)}={fmt(v)}" for k, v in hp.items() if k in keys and v is not None
    )


def _plot_images(prob: Problem, best: dict, adam_long, path: pathlib.Path) -> pathlib.Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import LogNorm

    ref = np.asarray(prob.reference)
    noisy = np.asarray(tex.render(prob.target, prob.scene, prob.base_key, prob.cfg.spp, 1))
    tgt = np.asarray(prob.target)
    lo, hi = (float(v) for v in np.percentile(ref, [0.5, 99.5]))

    def tone(img):  # log tone map: the image spans ~2 decades
        return (np.log(np.maximum(img, 1e-3)) - np.log(lo)) / (np.log(hi) - np.log(lo))

    runs = [(m, best[m]) for m in prob.cfg.methods]
    if adam_long is not best["adam"]:
        runs.insert(1, ("adam (equal time)", adam_long))
    fig, axes = plt.subplots(len(runs) + 1, 4, figsize=(12, 3 * (len(runs) + 1)), dpi=90)
    norm = LogNorm(tex.ALPHA_MIN, tex.ALPHA_MAX)
    axes[0, 0].imshow(tone(ref), cmap="gray", vmin=0, vmax=1)
    axes[0, 0].set_title("reference image")
    axes[0, 1].imshow(tone(noisy), cmap="gray", vmin=0, vmax=1)
    axes[0, 1].set_title(f"target, {prob.cfg.spp}-spp render")
    axes[0, 2].imshow(tgt, cmap="viridis", norm=norm)
    axes[0, 2].set_title("target roughness (log)")
    axes[0, 3].imshow(np.asarray(prob.init), cmap="viridis", norm=norm)
    axes[0, 3].set_title("initial roughness")
    for r, (label, tr) in enumerate(runs, start=1):
        alpha = np.asarray(tr.final[0])
        img = np.asarray(prob.final_images[tr.name])  # run_method's name is the run id
        rel = np.abs(img - ref) / np.sqrt(ref**2 + tex.LOSS_EPS)
        axes[r, 0].imshow(tone(img), cmap="gray", vmin=0, vmax=1)
        axes[r, 0].set_title(f"{label}: render")
        axes[r, 1].imshow(rel, cmap="magma", vmin=0, vmax=0.5)
        axes[r, 1].set_title("relative image error (0..0.5)")
        axes[r, 2].imshow(alpha, cmap="viridis", norm=norm)
        axes[r, 2].set_title(f"roughness, err {tr.final_metric('param_error'):.4f}")
        axes[r, 3].imshow(np.abs(alpha - tgt), cmap="magma", vmin=0, vmax=0.1)
        axes[r, 3].set_title("|alpha - target| (0..0.1)")
    return common.save_figure(fig, path)


def main(argv=None) -> dict:
    def extra(parser):
        parser.add_argument(
            "--full",
            action="store_true",
            help="the paper-like 512^2 run with every baseline (low-pass, bilateral) and "
            "wider sweeps, instead of the demo (256^2: Adam, the defaults, the tuned filter)",
        )
        parser.add_argument(
            "--target",
            default="camera",
            choices=("camera", "noise", "phantom"),
            help="target roughness texture (noise: high-frequency, supplement "
            "Fig. 4, where spatial filtering is biased)",
        )

    args = common.parse_args(
        "Texture recovery (paper Fig. 5) on the toy renderer: Adam, bilateral_adam's "
        "defaults and the tuned cross-bilateral filter (--full: and the low-pass and "
        "bilateral baselines).",
        default_out="results/texture",
        argv=argv,
        extra=extra,
    )
    cfg = default_config(args.quick) if args.quick or args.full else demo_config()
    cfg = dataclasses.replace(cfg, target=args.target)
    summary = run(cfg, args.out)
    print(summary["table"])
    print(
        f"\nTotal {summary['total_seconds']:.1f} s (reference image "
        f"{summary['setting']['reference_seconds']:.1f} s)."
    )
    print(f"Summary: {args.out / 'summary.json'}")
    print("Figures:")
    for p in summary["pngs"]:
        print(f"  {p}")
    return summary


if __name__ == "__main__":
    main()
