"""Shared pieces of the Mitsuba 3 experiments (``mitsuba_texture``, ``mitsuba_volume``,
``mitsuba_timing``): variant set-up, the methods, one optimisation run, interleaved timing.

A *problem* (``mitsuba_texture.Problem``, ``mitsuba_volume.Problem``) owns one scene
and its ``mi.SceneParameters`` and provides:

* ``keys``, ``project`` (``key -> (lo, hi)``) and ``init`` (``key -> array``);
* ``reset()``: writes ``init`` into the scene;
* ``render_and_backward(i)``: renders with seed ``i``, ``dr.backward`` of the loss,
  evaluates the gradients (``dr.sync_thread``) and returns the loss as a float;
* ``param_errors(values)``: ``{"param_error": ..., ...}`` of ``{key: array}``;
* ``evaluate(values, run_id)``: untimed, low-noise image loss (keeps the image for figures).
"""

from __future__ import annotations

import math
import os
import subprocess
import sys
import textwrap
import time
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np
import optax

import optax_bilateral as ob
from experiments import common

VARIANT = "llvm_ad_rgb"

#: The methods every Mitsuba experiment runs; ``auto`` only where the library has
#: ``sigma_d="auto"`` (:func:`auto_unavailable` says why not).
METHODS = ("adam", "low-pass", "bilateral", "cross-bilateral", "auto")

_PROBE = textwrap.dedent("""
    import mitsuba as mi, drjit as dr
    from optax_bilateral.mitsuba import check_variant
    mi.set_variant({variant!r})
    check_variant()
    scene = mi.load_dict({{"type": "scene", "integrator": {{"type": "prb"}},
        "sensor": {{"type": "perspective", "to_world": mi.ScalarTransform4f().look_at(
            origin=[0, 0, 4], target=[0, 0, 0], up=[0, 1, 0]),
            "film": {{"type": "hdrfilm", "width": 16, "height": 16}}}},
        "sphere": {{"type": "sphere"}}, "light": {{"type": "constant"}}}})
    image = mi.render(scene, spp=4)
    assert image.shape == (16, 16, 3), image.shape
    mean = float(dr.mean(image, axis=None).numpy())
    assert 0.05 < mean < 10, mean
""")


def probe(variant: str = VARIANT, timeout: float = 300.0) -> str | None:
    """Renders a 16x16 scene with ``variant`` in a fresh process: ``None`` if it worked,
    else a one-line reason. A separate process because an unusable libLLVM aborts the
    process that renders (no Python exception to catch)."""
    try:
        run = subprocess.run(
            [sys.executable, "-c", _PROBE.format(variant=variant)],
            capture_output=True,
            text=True,
            timeout=timeout,
        )
    except subprocess.TimeoutExpired:
        return f"rendering a 16x16 scene with {variant} took over {timeout:.0f} s"
    if run.returncode == 0:
        return None
    lines = [ln.strip() for ln in (run.stderr + run.stdout).splitlines() if ln.strip()]
    # An aborting libLLVM says why on its "LLVM ERROR" line; a Python error on its last line.
    hint = next(
        (ln for ln in lines if ln.startswith("LLVM ERROR")), lines[-1] if lines else "no output"
    )
    return (
        f"Mitsuba {variant} cannot render a 16x16 scene here (exit {run.returncode}): {hint[:300]}"
    )


def setup(variant: str = VARIANT):
    """Imports Mitsuba and Dr.Jit, sets ``variant`` and checks that it can render; returns
    (mi, dr)."""
    import drjit as dr
    import mitsuba as mi

    from optax_bilateral.mitsuba import check_variant

    if mi.variant() != variant:
        mi.set_variant(variant)
    check_variant()
    return mi, dr


def auto_unavailable() -> str | None:
    """``None`` when ``bilateral_adam(sigma_d="auto")`` works in this library, else why not."""
    import jax.numpy as jnp

    try:
        opt = ob.bilateral_adam(0.1, sigma_d="auto", levels=1)
        g = {"x": jnp.ones((4, 4, 1), jnp.float32)}
        opt.update(g, opt.init(g), g)
    except (TypeError, ValueError) as e:
        return f'sigma_d="auto" is not in this version of the library ({type(e).__name__}: {e})'
    return None


DECAYS = ("constant", "cosine", "hold-cosine")


def learning_rate(lr: float, decay: str, iterations: int):
    """The learning-rate schedule of a run.

    ``constant``: ``lr`` throughout; ``cosine``: cosine-decayed from ``lr`` to 0 over the
    run; ``hold-cosine``: ``lr`` for the first two thirds, then cosine-decayed to 0 over
    the last third (the decay starts once a constant-rate run has mostly converged).
    """
    if decay == "constant":
        return lr
    if decay == "cosine":
        return optax.cosine_decay_schedule(lr, iterations)
    if decay == "hold-cosine":
        hold = (2 * iterations) // 3
        return optax.join_schedules(
            [
                optax.constant_schedule(lr),
                optax.cosine_decay_schedule(lr, max(iterations - hold, 1)),
            ],
            [hold],
        )
    raise ValueError(f"decay must be one of {DECAYS}, got {decay!r}")


def make_transform(
    method: str, hp: Mapping[str, Any], iterations: int
) -> optax.GradientTransformation:
    """The method's optimizer from its hyperparameters (see each experiment's table).

    ``hp`` holds ``learning_rate`` and ``decay`` and, for Adam, ``b1``; for the
    filtered methods ``b1``, ``levels``, ``log_guide`` and ``sigma_d`` (a number or a
    per-key dict; ``auto`` ignores it).
    """
    lr = learning_rate(hp["learning_rate"], hp["decay"], iterations)
    if method == "adam":
        return optax.adam(lr, b1=hp["b1"], b2=hp.get("b2", 0.999))
    common_hp = dict(b1=hp["b1"], levels=hp["levels"], log_guide=hp["log_guide"])
    if method == "low-pass":
        return ob.bilateral_adam(lr, sigma_d=math.inf, **common_hp)
    if method == "bilateral":
        return ob.bilateral_adam(lr, sigma_d=hp["sigma_d"], guide="self", **common_hp)
    if method == "cross-bilateral":
        return ob.bilateral_adam(lr, sigma_d=hp["sigma_d"], guide="params", **common_hp)
    if method == "auto":
        return ob.bilateral_adam(lr, sigma_d="auto", guide="params", **common_hp)
    raise ValueError(f"method must be one of {METHODS}, got {method!r}")


def run_id(method: str, hp: Mapping[str, Any], swept: tuple[str, ...]) -> str:
    """``method[lr=0.01, decay=cosine]``: the name of one sweep entry."""
    return method + "[" + ", ".join(f"{k}={_fmt(hp[k])}" for k in swept if k in hp) + "]"


def _fmt(v) -> str:
    if isinstance(v, float):
        return f"{v:g}"
    if isinstance(v, Mapping):
        return (
            "{"
            + ", ".join(
                f"{str(k).split('.')[-2] if '.' in str(k) else k}: {_fmt(x)}" for k, x in v.items()
            )
            + "}"
        )
    return str(v)


def run_method(
    problem,
    name: str,
    transform,
    iterations: int,
    *,
    hyperparameters: dict,
    record_every: int = 1,
    progress: bool = True,
) -> common.Trace:
    """One optimisation from ``problem.init`` with :class:`SceneOptimizer`; returns the trace.

    The step is render + backward + update (timed); the final values are copied into
    ``trace.final`` (``{key: np.ndarray}``) and evaluated with ``problem.evaluate``.
    """
    import drjit as dr

    from optax_bilateral.mitsuba import SceneOptimizer

    problem.reset()
    opt = SceneOptimizer(transform, problem.params, problem.keys, project=problem.project)

    def step(state, i):
        loss = problem.render_and_backward(i)
        state = opt.step(state)
        dr.sync_thread()
        return state, {"loss": loss, **problem.param_errors(opt.values())}

    trace = common.run_method(
        name,
        step,
        opt.init(),
        iterations,
        record_every=record_every,
        evaluate=lambda _: problem.evaluate(opt.values(), name),
        evaluate_every=iterations,
        hyperparameters=hyperparameters,
        progress=progress,
    )
    trace.final = {k: np.array(v) for k, v in opt.values().items()}
    return trace


def run_sweeps(
    prob,
    sweeps: Mapping[str, list[dict]],
    hyperparameters: Callable[[str, dict], dict],
    swept: tuple[str, ...],
    *,
    iterations: int,
    record_every: int,
    timing_rounds: int,
    progress: bool = True,
):
    """Every method's sweep on ``prob``, then the best entries' steps timed interleaved.

    ``auto`` is skipped, with the reason, while the library lacks it. Returns
    ``(traces, samples, skipped)``: ``{method: [Trace]}``, :func:`time_interleaved`'s
    samples of the best entries (their medians set ``seconds_per_iteration`` and the
    time axis of every entry of the method), and ``{method: reason}``.
    """
    skipped = {}
    why = auto_unavailable()
    if why is not None:
        skipped["auto"] = why
        print(f"skipping auto: {why}")
    methods = [m for m in METHODS if m not in skipped]
    traces: dict[str, list[common.Trace]] = {}
    transforms = {}
    for method in methods:
        traces[method] = []
        for entry in sweeps[method]:
            hp = hyperparameters(method, entry)
            name = run_id(method, hp, swept)
            transforms[name] = make_transform(method, hp, iterations)
            traces[method].append(
                run_method(
                    prob,
                    name,
                    transforms[name],
                    iterations,
                    hyperparameters=hp,
                    record_every=record_every,
                    progress=progress,
                )
            )
    # The same transform objects as the runs: their compiled updates are reused.
    samples = time_interleaved(
        prob, {m: transforms[best(traces[m]).name] for m in methods}, rounds=timing_rounds, warmup=1
    )
    for m in methods:
        for tr in traces[m]:
            tr.timed_seconds_per_iteration = float(np.median(samples[m]["total"]))
    return traces, samples, skipped


def time_interleaved(
    problem,
    transforms: Mapping[str, optax.GradientTransformation],
    rounds: int,
    warmup: int = 2,
    first_seed: int = 500_000,
) -> dict[str, dict[str, list[float]]]:
    """Seconds per iteration of each method's render + backward, update, and their total.

    Every method runs its own optimisation from ``problem.init`` on ``problem``'s one
    scene: before its iteration its own values are written in (untimed), so every
    render sees that method's parameters. One scene, because renders got slower with
    more scenes alive in the process. A round runs one iteration of each method, in an
    order rotated every round, so load from other processes hits all alike.
    ``dr.sync_thread()`` / ``jax.block_until_ready`` end each timed part; ``warmup``
    untimed rounds first (compilation). Returns ``{name: {part: [seconds per round]}}``
    with parts ``render`` (render, loss, ``dr.backward``, gradients evaluated),
    ``update`` (the whole :meth:`SceneOptimizer.step`), of which ``jit`` (the compiled
    update, its inputs read from the scene) and ``write`` (the values written back,
    ``params.update()``), and ``total``.
    """
    import drjit as dr
    import jax
    import jax.numpy as jnp

    from optax_bilateral.mitsuba import SceneOptimizer

    problem.reset()
    runs = {}
    for name, transform in transforms.items():
        opt = SceneOptimizer(transform, problem.params, problem.keys, project=problem.project)
        runs[name] = [opt, opt.init(), {k: jnp.array(v) for k, v in opt.values().items()}]
    parts = ("render", "update", "jit", "write", "total")
    samples = {name: {p: [] for p in parts} for name in transforms}
    names = list(transforms)
    seed = first_seed
    for r in range(warmup + rounds):
        for name in names[r % len(names) :] + names[: r % len(names)]:
            opt, state, values = runs[name]
            opt.set_values(values)
            dr.sync_thread()
            t0 = time.perf_counter()
            problem.render_and_backward(seed)
            t1 = time.perf_counter()
            values, state = jax.block_until_ready(opt.update(opt.grads(), state, opt.values()))
            t2 = time.perf_counter()
            opt.set_values(values)
            dr.sync_thread()
            t3 = time.perf_counter()
            runs[name][1:] = [state, values]
            if r >= warmup:
                for p, dt in zip(parts, (t1 - t0, t3 - t1, t2 - t1, t3 - t2, t3 - t0)):
                    samples[name][p].append(dt)
        seed += 1
    return samples


def timing_rows(samples: Mapping[str, Mapping[str, list[float]]], baseline: str) -> list[dict]:
    """Medians (ms) of each part and the total's change against ``baseline``: the median over
    rounds of the per-round ratio (:func:`experiments.common.paired_ratio`)."""
    totals = {k: v["total"] for k, v in samples.items()}
    rows = []
    for name, s in samples.items():
        render, update, jit, total = (
            1e3 * float(np.median(s[p])) for p in ("render", "update", "jit", "total")
        )
        rows.append(
            {
                "method": name,
                "render + backward ms": render,
                "update ms": update,
                "of which jitted ms": jit,
                "total ms": total,
                "update share %": 100.0
                * float(np.median(np.asarray(s["update"]) / np.asarray(s["total"]))),
                "total vs " + baseline + " %": 100.0
                * (common.paired_ratio(totals, name, baseline) - 1.0),
                "rounds": len(s["total"]),
            }
        )
    return rows


def load_average() -> list[float]:
    """The 1, 5 and 15 minute load averages (the machine's conditions during a timing)."""
    return [round(x, 2) for x in os.getloadavg()]


def tone_map(img: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """Log tone map of a linear image into [0, 1] between radiances ``lo`` and ``hi``."""
    img = np.maximum(np.asarray(img, np.float64), lo)
    return np.clip((np.log(img) - np.log(lo)) / (np.log(hi) - np.log(lo)), 0.0, 1.0)


def best(traces: list[common.Trace]) -> common.Trace:
    """The sweep entry with the smallest final parameter error."""
    return common.best_trace(traces, "param_error")


def summary_methods(
    traces: Mapping[str, list[common.Trace]], metric_keys: Mapping[str, str]
) -> dict[str, dict]:
    """``summary.json``'s ``methods``: the best sweep entry per method, with every entry listed."""

    def entry(t):
        e = {"run": t.name, **common.summary_entry(t, metric_keys)}
        errors = t.metrics["param_error"]
        i = int(np.nanargmin(errors))
        e["lowest_param_error"] = float(errors[i])  # a run that drifts up after it
        e["lowest_param_error_iteration"] = int(t.iterations[i])
        return e

    out = {}
    for method, trs in traces.items():
        out[method] = {**entry(best(trs)), "sweep": [entry(t) for t in trs]}
    return out


def time_budget(traces: Mapping[str, list[common.Trace]]) -> float:
    """Equal-time budget: the shortest total (timed) run time of the best entries."""
    return min(float(best(trs).time_axis[-1]) for trs in traces.values())


def write_tables(
    out,
    title: str,
    methods: Mapping[str, dict],
    budget: float,
    traces: Mapping[str, list[common.Trace]],
    extra_columns: Callable[[dict], dict],
    notes: str = "",
) -> str:
    """``table.md``: the best run per method, then every sweep entry; returns the text."""
    rows = []
    for m, e in methods.items():
        rows.append(
            {
                "method": m,
                "best run": e["run"],
                "param error": e["final_param_error"],
                **extra_columns(e),
                "image loss": e["final_loss"],
                f"param error @ {budget:.1f} s": best(traces[m]).metric_at_time(
                    "param_error", budget
                ),
                "s/iter": e["seconds_per_iteration"],
            }
        )
    sweep_rows = [
        {
            "run": s["run"],
            "param error": s["final_param_error"],
            "lowest (iteration)": f"{s['lowest_param_error']:.4g} "
            f"({s['lowest_param_error_iteration']})",
            "image loss": s["final_loss"],
        }
        for e in methods.values()
        for s in e["sweep"]
    ]
    text = (
        f"{title}\n\n{notes}{common.markdown_table(rows)}\n\nEvery sweep entry:\n\n"
        f"{common.markdown_table(sweep_rows)}\n"
    )
    (out / "table.md").write_text(text)
    return text
