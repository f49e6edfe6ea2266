"""Volume recovery: Adam vs low-pass, bilateral and cross-bilateral gradient filtering.

    python -m experiments.paper.volume [--quick] [--out DIR]

The paper's second grid application (main paper Figs. 8-9, supplement Table 1
volume row) on the toy participating medium of :mod:`optax_bilateral.toy.volume`:
a grid of density (extinction) and RGB albedo in the unit cube, recovered from
noisy single-scattering renders. Every iteration renders a random subset of the
cameras with one sample per pixel for the loss and one independent sample for
the gradient (ratio tracking: unbiased, genuinely noisy), then takes one
optimizer step on both grids and projects them to the valid domain
(``0 <= density <= 1``, ``0 <= albedo <= 1``).

Methods (both grids, with separate ``sigma_d`` for density and albedo given as a
pytree prefix of the parameters, ``{"density": s_d, "albedo": s_a}``):

* ``adam``: ``optax.adam``; the best of a small learning-rate / ``b1`` sweep
  (every sweep entry is reported).
* ``low-pass``: ``bilateral_adam`` with ``sigma_d = inf`` (a plain B-spline low-pass).
* ``bilateral``: ``guide="self"``, the paper's bilateral baseline as the authors'
  code runs it (``cross_term_off``): ``m`` guided by ``m`` and ``v`` by ``v``, every
  a-trous level by its own partially filtered input, in the log domain (moments
  have no fixed scale, so a log guide is the unit-free choice); the best of a
  small ``sigma_d`` sweep (every entry is reported).
* ``cross-bilateral``: ``guide="params"`` (the paper's method).

The filtered methods use the paper's ``b1 = 0.2``, ``b2 = 1 - (1 - b1)^2``, postfilter
only, ``levels = 3`` and one learning rate (0.1), set by hand in short trial runs (not
swept, unlike Adam's learning rate and ``b1``).

Outputs in ``--out`` (default ``results/volume``): ``summary.json``, ``results.md``,
``views.png`` (renders), ``slices.png`` (grid slices), ``{loss,param_error,
density_error,albedo_error}_vs_{iteration,time}.png``, and ``timing.json`` /
``timing.md``: the per-iteration time (rendering + update) of Adam and the
cross-bilateral filter with F = 3 and F = 5, measured interleaved in one process
(the analogue of supplement Table 1).

``final_param_error`` is the mean of the mean absolute density error and the
density-weighted mean absolute albedo error (:func:`optax_bilateral.toy.volume.param_errors`);
``final_loss`` is the image loss ``mean((I - I_ref)^2)`` on a fixed set of
evaluation views at ``eval_spp`` samples per pixel.
"""

from __future__ import annotations

import json
import math
import pathlib
import time
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax

from experiments import common
from optax_bilateral.toy import volume as toy

METHODS = ("adam", "low-pass", "bilateral", "cross-bilateral")


def config(quick: bool) -> dict:
    """Problem sizes and hyperparameters; ``quick`` is the test-suite size."""
    if quick:
        # Few compilations (they dominate at this size): one Adam program, one F = 2
        # program shared by low-pass, cross-bilateral and the timing table, one self-guided.
        return dict(
            size=24,
            resolution=16,
            n_views=16,
            views_per_step=2,
            iterations=30,
            record_every=5,
            evaluate_every=10,
            target_spp=32,
            eval_views=4,
            eval_spp=8,
            image_spp=32,
            lr=0.1,
            b1=0.2,
            sigma_d={"density": 0.05, "albedo": 0.1},
            self_sigma_d=[1.0],
            levels=2,
            adam_sweep=[(0.01, 0.9)],
            timing_levels=(2,),
            timing_repeats=2,
            timing_steps=2,
        )
    return dict(
        size=64,
        resolution=32,
        n_views=64,
        views_per_step=4,
        iterations=300,
        record_every=5,
        evaluate_every=25,
        target_spp=64,
        eval_views=8,
        eval_spp=16,
        image_spp=64,
        lr=0.1,
        b1=0.2,
        sigma_d={"density": 0.05, "albedo": 0.1},
        self_sigma_d=[1.0, 3.0, 10.0, 30.0, 100.0],  # best inside the sweep
        levels=3,
        adam_sweep=[(0.001, 0.9), (0.003, 0.9), (0.01, 0.9), (0.003, 0.2)],
        timing_levels=(3, 5),
        timing_repeats=5,
        timing_steps=5,
    )


class Problem:
    """Scene, target images, and the jitted gradient / evaluation functions (compiled once)."""

    def __init__(self, cfg: dict, seed: int = 0):
        self.cfg = cfg
        self.scene = toy.make_scene(resolution=cfg["resolution"], n_views=cfg["n_views"])
        self.target = {k: jnp.asarray(v) for k, v in toy.reference_volume(cfg["size"]).items()}
        self.init = {k: jnp.asarray(v) for k, v in toy.initial_volume(cfg["size"]).items()}
        self.seed = seed
        scene = self.scene
        all_views = jnp.arange(scene.n_views)
        # Reference images: high-sample estimates (unbiased; their residual noise
        # is ~1/sqrt(target_spp) of one sample's).
        self.targets = jnp.concatenate(
            [
                toy.render_mean(
                    self.target,
                    scene,
                    jax.random.fold_in(jax.random.key(seed), 1_000_000 + i),
                    all_views[i : i + 4],
                    spp=cfg["target_spp"],
                )
                for i in range(0, scene.n_views, 4)
            ]
        )  # 4 views per call, as plot_views: one compile
        # Evaluation views: spread over the sphere, fixed.
        self.eval_views = jnp.asarray(
            np.linspace(0, scene.n_views - 1, cfg["eval_views"]).round(), jnp.int32
        )
        base = jax.random.key(seed)
        b = cfg["views_per_step"]

        def grad_fn(params, i):
            key = jax.random.fold_in(base, i)
            k_views, k_render = jax.random.split(key)
            views = jax.random.choice(k_views, scene.n_views, (b,), replace=False)
            loss, grads, _ = toy.loss_and_grad(params, scene, k_render, views, self.targets[views])
            return loss, grads

        def eval_fn(params):
            img = toy.render_mean(
                params,
                scene,
                jax.random.key(seed + 7),
                self.eval_views,
                spp=cfg["eval_spp"],
                batch=cfg["eval_spp"],
            )
            out = toy.param_errors(params, self.target)
            out["loss"] = jnp.mean(jnp.square(img - self.targets[self.eval_views]))
            return out

        self.grad_fn = jax.jit(grad_fn)
        self.eval_fn = jax.jit(eval_fn)

        self._updates = {}

    def update_fn(self, kind: str, static: tuple):
        """A jitted ``(grads, state, params, hp) -> (params, state)`` step with the projection.

        ``hp`` (learning rate, ``b1``/``b2`` for Adam, per-leaf ``sigma_d``) is traced,
        so runs that differ only in these share one compilation (``low-pass`` is the
        cross-bilateral program with ``sigma_d = inf``); ``static`` holds what changes
        the program (``levels``, ``guide``, ``log_guide``, ``b1`` of the filtered methods).
        """
        if (kind, static) not in self._updates:
            scene = self.scene

            def update(grads, state, params, hp):
                opt = _optimizer(kind, dict(static), hp)
                updates, state = opt.update(grads, state, params)
                return toy.project(optax.apply_updates(params, updates), scene), state

            self._updates[(kind, static)] = jax.jit(update)
        return self._updates[(kind, static)]


def _optimizer(kind: str, static: dict, hp: dict) -> optax.GradientTransformation:
    if kind == "adam":
        return optax.adam(hp["learning_rate"], b1=hp["b1"], b2=hp["b2"])
    levels = static["levels"]
    levels = dict(levels) if isinstance(levels, tuple) else levels  # per-leaf, kept hashable
    return common.filtered_adam(
        hp["learning_rate"],
        static["b1"],
        sigma_d=hp["sigma_d"],
        levels=levels,
        guide=static["guide"],
        log_guide=static["log_guide"],
        spatial_axes=(0, 1, 2),  # (D, H, W, C) grids: said explicitly
    )


class Method(NamedTuple):
    """One optimizer configuration: program (``kind``, ``static``) and traced hyperparameters."""

    name: str
    kind: str
    static: tuple
    hp: dict

    @property
    def description(self) -> dict:
        static = {k: dict(v) if isinstance(v, tuple) else v for k, v in self.static}
        return {**static, **self.hp}

    def traced_hp(self):
        return jax.tree.map(lambda x: jnp.asarray(x, jnp.float32), self.hp)

    def init(self, params):
        return _optimizer(self.kind, dict(self.static), self.traced_hp()).init(params)


def make_method(
    method: str,
    cfg: dict,
    lr: float | None = None,
    b1: float | None = None,
    levels=None,
    name: str | None = None,
    self_sigma_d: float | None = None,
) -> Method:
    """The configuration of ``method`` (one of :data:`METHODS`) for this experiment.

    ``self_sigma_d`` is the log-domain ``sigma_d`` of ``bilateral`` (default: the
    first entry of ``cfg["self_sigma_d"]``).
    """
    lr = cfg["lr"] if lr is None else lr
    levels = cfg["levels"] if levels is None else levels
    name = name or method
    if method == "adam":
        b1 = 0.9 if b1 is None else b1
        b2 = 0.999 if b1 == 0.9 else 1 - (1 - b1) ** 2
        return Method(name, "adam", (), dict(learning_rate=lr, b1=b1, b2=b2))
    b1 = cfg["b1"] if b1 is None else b1
    if isinstance(levels, dict):
        levels = tuple(sorted(levels.items()))
    if method == "low-pass":
        static = dict(b1=b1, levels=levels, guide="params", log_guide=False)
        sigma_d = {"density": math.inf, "albedo": math.inf}
    elif method == "bilateral":
        static = dict(b1=b1, levels=levels, guide="self", log_guide=True)
        s = cfg["self_sigma_d"][0] if self_sigma_d is None else self_sigma_d
        sigma_d = {"density": s, "albedo": s}
    elif method == "cross-bilateral":
        static = dict(b1=b1, levels=levels, guide="params", log_guide=False)
        sigma_d = dict(cfg["sigma_d"])
    else:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    return Method(
        name, "filtered", tuple(sorted(static.items())), dict(learning_rate=lr, sigma_d=sigma_d)
    )


def run(problem: Problem, method: Method, iterations: int, progress: bool = True) -> common.Trace:
    """Optimises from the constant initial volume; returns the trace (final carry = params)."""
    cfg = problem.cfg
    update = problem.update_fn(method.kind, method.static)
    grad_fn = problem.grad_fn
    hp = method.traced_hp()

    def step(carry, i):
        params, state = carry
        loss, grads = grad_fn(params, jnp.asarray(i, jnp.int32))
        params, state = update(grads, state, params, hp)
        return (params, state), {"train_loss": loss}

    params = problem.init
    trace = common.run_method(
        method.name,
        step,
        (params, method.init(params)),
        iterations,
        evaluate=lambda c: problem.eval_fn(c[0]),
        record_every=cfg["record_every"],
        evaluate_every=cfg["evaluate_every"],
        hyperparameters=method.description,
        progress=progress,
    )
    trace.final = trace.final[0]
    return trace


def timing_table(problem: Problem, levels: tuple[int, ...], repeats: int, steps: int) -> dict:
    """Per-iteration time (rendering + update) of Adam and cross-bilateral F in ``levels``.

    The methods are measured interleaved in one process (rotating order, ``repeats``
    rounds of ``steps`` iterations each, after a warm-up), and the medians reported,
    so that a shared, noisy CPU affects all alike. The update alone is timed the
    same way on fixed gradients. Adam uses the filtered methods' ``b1``, ``b2``.
    """
    cfg = problem.cfg
    rows = {"Adam": make_method("adam", cfg, b1=cfg["b1"])}
    for f in levels:
        rows[f"Ours (F = {f})"] = make_method("cross-bilateral", cfg, levels=f)
    updates = {k: problem.update_fn(m.kind, m.static) for k, m in rows.items()}
    hps = {k: m.traced_hp() for k, m in rows.items()}
    states = {k: m.init(problem.init) for k, m in rows.items()}
    params = {k: problem.init for k in rows}
    _, g_fixed = problem.grad_fn(problem.init, jnp.asarray(0, jnp.int32))
    for k in rows:  # warm-up / compile
        jax.block_until_ready(updates[k](g_fixed, states[k], params[k], hps[k]))
    iteration = {k: [] for k in rows}
    update_only = {k: [] for k in rows}
    names = list(rows)
    counter = 0
    for r in range(repeats):
        order = names[r % len(names) :] + names[: r % len(names)]
        for k in order:
            t0 = time.perf_counter()
            for _ in range(steps):
                counter += 1
                _, g = problem.grad_fn(params[k], jnp.asarray(counter, jnp.int32))
                params[k], states[k] = updates[k](g, states[k], params[k], hps[k])
            jax.block_until_ready(params[k])
            iteration[k].append((time.perf_counter() - t0) / steps)
            t0 = time.perf_counter()
            p, s = params[k], states[k]
            for _ in range(steps):
                p, s = updates[k](g_fixed, s, p, hps[k])
            jax.block_until_ready(p)
            update_only[k].append((time.perf_counter() - t0) / steps)
    adam = float(np.median(iteration["Adam"]))
    table = []
    for k in rows:
        t = float(np.median(iteration[k]))
        u = float(np.median(update_only[k]))
        table.append(
            {
                "Method": k,
                "ms per iteration": 1e3 * t,
                "% change": 0.0 if k == "Adam" else 100.0 * (t / adam - 1.0),
                "update ms": 1e3 * u,
                "update share %": 100.0 * u / t,
                "Grid": f"{cfg['size']}^3 (+ {cfg['views_per_step']} views of "
                f"{cfg['resolution']}^2 px per iteration)",
            }
        )
    return {
        "rows": table,
        "repeats": repeats,
        "steps_per_repeat": steps,
        "samples_ms": {k: [1e3 * x for x in v] for k, v in iteration.items()},
    }


def _to_img(x):
    return np.clip(np.asarray(x), 0.0, 1.0)


def plot_views(problem: Problem, params_by_name: dict, path: pathlib.Path, views, spp: int) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    views = jnp.asarray(views, jnp.int32)
    rows = {"target": problem.target, "initial": problem.init, **params_by_name}
    fig, axes = plt.subplots(
        len(rows), len(views), figsize=(1.8 * len(views), 1.8 * len(rows)), dpi=110, squeeze=False
    )
    key = jax.random.key(problem.seed + 11)
    for r, (name, p) in enumerate(rows.items()):
        imgs = toy.render_mean(p, problem.scene, key, views, spp=spp, batch=min(spp, 16))
        for c in range(len(views)):
            ax = axes[r, c]
            ax.imshow(_to_img(imgs[c]), interpolation="nearest")
            ax.set_xticks([])
            ax.set_yticks([])
            if c == 0:
                ax.set_ylabel(name, fontsize=8)
            if r == 0:
                ax.set_title(f"view {int(views[c])}", fontsize=8)
    fig.suptitle(f"renders ({spp} spp)", fontsize=9)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def plot_slices(problem: Problem, params_by_name: dict, path: pathlib.Path) -> None:
    """Density and albedo at two z-slices; albedo shown where the target has medium."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = problem.cfg["size"]
    zs = (int(0.4 * n), int(0.65 * n))
    rows = {"target": problem.target, "initial": problem.init, **params_by_name}
    medium = np.asarray(problem.target["density"][..., 0]) > 0.02
    fig, axes = plt.subplots(
        len(rows), 2 * len(zs), figsize=(7.5, 1.9 * len(rows)), dpi=110, squeeze=False
    )
    for r, (name, p) in enumerate(rows.items()):
        d = np.asarray(p["density"][..., 0])
        a = np.asarray(p["albedo"])
        for j, z in enumerate(zs):
            ax = axes[r, 2 * j]
            ax.imshow(
                d[:, :, z].T, origin="lower", cmap="magma", vmin=0, vmax=1, interpolation="nearest"
            )
            ax2 = axes[r, 2 * j + 1]
            ax2.imshow(
                np.where(medium[:, :, z, None], _to_img(a[:, :, z]), 0.0).transpose(1, 0, 2),
                origin="lower",
                interpolation="nearest",
            )
            for a_ in (ax, ax2):
                a_.set_xticks([])
                a_.set_yticks([])
            if r == 0:
                ax.set_title(f"density z={z}", fontsize=8)
                ax2.set_title(f"albedo z={z}", fontsize=8)
        axes[r, 0].set_ylabel(name, fontsize=8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def main(argv=None) -> dict:
    args = common.parse_args(
        "Volume recovery (paper Figs. 8-9, supplement Table 1)",
        default_out="results/volume",
        argv=argv,
    )
    cfg = config(args.quick)
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()
    problem = Problem(cfg)
    jax.block_until_ready(problem.targets)

    traces: dict[str, common.Trace] = {}
    sweep: dict[str, dict] = {}
    adam_traces = []
    for lr, b1 in cfg["adam_sweep"]:
        tr = run(
            problem,
            make_method("adam", cfg, lr=lr, b1=b1, name=f"adam lr={lr} b1={b1}"),
            cfg["iterations"],
        )
        adam_traces.append(tr)
        sweep[tr.name] = common.summary_entry(tr)
    traces["adam"] = common.best_trace(adam_traces, "param_error")
    traces["low-pass"] = run(problem, make_method("low-pass", cfg), cfg["iterations"])
    bilateral_traces = []
    for s in cfg["self_sigma_d"]:
        tr = run(
            problem,
            make_method("bilateral", cfg, self_sigma_d=s, name=f"bilateral sigma_d={s}"),
            cfg["iterations"],
        )
        bilateral_traces.append(tr)
        sweep[tr.name] = common.summary_entry(tr)
    traces["bilateral"] = common.best_trace(bilateral_traces, "param_error")
    traces["cross-bilateral"] = run(problem, make_method("cross-bilateral", cfg), cfg["iterations"])

    # Equal wall time: every method's error at the time budget of the fastest run.
    budget = min(float(tr.rebased_wall_time[-1]) for tr in traces.values())
    methods = {}
    for name, tr in traces.items():
        entry = common.summary_entry(tr)
        for key in ("density_error", "albedo_error"):
            entry[f"final_{key}"] = tr.final_metric(key)
        entry["param_error_at_equal_time"] = tr.metric_at_time("param_error", budget)
        entry["compile_seconds"] = tr.compile_seconds
        methods[name] = entry
    initial = {k: float(v) for k, v in problem.eval_fn(problem.init).items()}

    timing = timing_table(problem, cfg["timing_levels"], cfg["timing_repeats"], cfg["timing_steps"])
    (out / "timing.json").write_text(json.dumps(timing, indent=2) + "\n")
    timing_md = common.markdown_table(timing["rows"], floatfmt=".4g")
    (out / "timing.md").write_text(
        "Per-iteration time (rendering + update), medians of interleaved repeats\n\n"
        + timing_md
        + "\n"
    )

    common.plot_all_curves(
        traces, out, metrics=("loss", "param_error", "density_error", "albedo_error")
    )
    finals = {k: tr.final for k, tr in traces.items()}
    view_ids = np.linspace(0, cfg["n_views"] - 1, 4).round().astype(int)
    plot_views(problem, finals, out / "views.png", view_ids, cfg["image_spp"])
    plot_slices(problem, finals, out / "slices.png")

    total = time.perf_counter() - t_start
    rows = [
        {
            "method": k,
            "param error": m["final_param_error"],
            "density MAE": m["final_density_error"],
            "albedo MAE (weighted)": m["final_albedo_error"],
            "image loss": m["final_loss"],
            "error @ equal time": m["param_error_at_equal_time"],
            "s / iteration": m["seconds_per_iteration"],
        }
        for k, m in methods.items()
    ]
    table = common.markdown_table(rows)
    sweep_rows = [
        {"run": k, "param error": v["final_param_error"], "image loss": v["final_loss"]}
        for k, v in sweep.items()
    ]
    md = (
        f"# Volume recovery ({cfg['size']}^3 grid, {cfg['iterations']} iterations, "
        f"{cfg['views_per_step']} of {cfg['n_views']} views of {cfg['resolution']}^2 px per "
        f"iteration, 1 spp primal + 1 spp gradient)\n\n"
        f"Initial: param error {initial['param_error']:.4g}, image loss {initial['loss']:.4g}. "
        f"Equal-time column: error after {budget:.1f} s of steps.\n\n{table}\n\n"
        f"## Sweeps (best by parameter error: `{traces['adam'].name}`, "
        f"`{traces['bilateral'].name}`)\n\n{common.markdown_table(sweep_rows)}\n\n"
        f"## Per-iteration time (supplement Table 1 analogue)\n\n{timing_md}\n\n"
        f"Total run time: {total:.0f} s.\n"
    )
    (out / "results.md").write_text(md)
    common.write_summary(
        out,
        methods,
        sweeps=sweep,
        initial=initial,
        timing=timing["rows"],
        config=cfg,
        total_seconds=total,
        equal_time_budget_seconds=budget,
    )
    print(md)
    print(f"Wrote {out}/summary.json, results.md, timing.md, views.png, slices.png and curves.")
    return methods


if __name__ == "__main__":
    main()
