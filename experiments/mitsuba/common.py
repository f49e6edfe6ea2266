"""Shared pieces of the Mitsuba 3 experiments: variant set-up, the methods of the
``SceneOptimizer`` experiments (``texture``, ``volume``, ``timing`` beside this module)
and their runs; :mod:`experiments.mitsuba.runner` runs and reports every experiment.

A ``SceneOptimizer`` problem (``texture.Problem``, ``volume.Problem``) owns
one scene and its ``mi.SceneParameters`` and provides, besides the runner's
``param_errors`` and ``evaluate``:

* ``keys``, ``project`` (``key -> (lo, hi)``) and ``init`` (``key -> array``);
* ``reset()``: writes ``init`` into the scene;
* ``render_and_backward(i)``: renders with seed ``i``, ``dr.backward`` of the loss,
  evaluates the gradients (``dr.sync_thread``) and returns the loss as a float.
"""

from __future__ import annotations

import functools
import math
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
from experiments.mitsuba import runner
from experiments.mitsuba.runner import Entry

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

#: The hyperparameters a sweep entry's name shows.
SWEPT = ("learning_rate", "decay", "sigma_d")

#: ``summary.json``'s final metrics of the SceneOptimizer experiments -> trace metrics.
METRIC_KEYS = {
    "final_param_error": "param_error",
    "final_loss": "image_loss",
    "final_train_loss": "loss",
}


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
        # The self guide is a postfilter argument: bilateral_adam's chain with it.
        return common.filtered_adam(lr, sigma_d=hp["sigma_d"], guide="self", **common_hp)
    if method == "cross-bilateral":
        return ob.bilateral_adam(lr, sigma_d=hp["sigma_d"], **common_hp)
    if method == "auto":
        return ob.bilateral_adam(lr, sigma_d="auto", **common_hp)
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


def hyperparameters(method: str, entry: dict, *, b1: float, levels: int, log_guide: bool) -> dict:
    """A sweep entry completed with the method's fixed settings: Adam's b1 0.9, b2 0.999;
    the filtered methods' ``b1``, ``b2 = 1 - (1 - b1)^2``, ``levels``, ``log_guide``,
    ``sigma_d`` (inf for low-pass, "auto" for auto) and guide ("self" for bilateral)."""
    if method == "adam":
        return dict(entry, b1=0.9, b2=0.999)
    hp = dict(entry, b1=b1, b2=1 - (1 - b1) ** 2, levels=levels, log_guide=log_guide)
    if method == "low-pass":
        hp["sigma_d"] = math.inf
    if method == "auto":
        hp["sigma_d"] = "auto"
    hp["guide"] = "self" if method == "bilateral" else "params"
    return hp


class SceneOptimizerRun:
    """A :class:`experiments.mitsuba.runner.Run` of one transform with
    :class:`SceneOptimizer` on ``problem``, from ``problem.init``.

    Its step's parts: ``render`` (render, loss, ``dr.backward``, gradients evaluated),
    ``update`` (the whole :meth:`SceneOptimizer.step`), of which ``jit`` (the compiled
    update, its inputs read from the scene) and ``write`` (the values written back,
    ``params.update()``).
    """

    def __init__(self, problem, transform: optax.GradientTransformation):
        import jax.numpy as jnp

        from optax_bilateral.mitsuba import SceneOptimizer

        problem.reset()
        self.problem = problem
        self.opt = SceneOptimizer(transform, problem.params, problem.keys, project=problem.project)
        self.state = self.opt.init()
        self._values = {k: jnp.array(v) for k, v in self.opt.values().items()}

    def activate(self) -> None:
        self.opt.set_values(self._values)

    def step(self, i: int) -> tuple[float, dict[str, float]]:
        import drjit as dr
        import jax

        t0 = time.perf_counter()
        loss = self.problem.render_and_backward(i)
        t1 = time.perf_counter()
        opt = self.opt
        values, self.state = jax.block_until_ready(
            opt.update(opt.grads(), self.state, opt.values())
        )
        t2 = time.perf_counter()
        opt.set_values(values)
        dr.sync_thread()
        t3 = time.perf_counter()
        self._values = values
        return loss, {"render": t1 - t0, "update": t3 - t1, "jit": t2 - t1, "write": t3 - t2}

    def values(self):
        return self._values


def sweep_entries(
    problem,
    sweeps: Mapping[str, list[dict]],
    hyperparameters: Callable[[str, dict], dict],
    swept: tuple[str, ...],
    iterations: int,
) -> tuple[dict[str, list[Entry]], dict[str, str]]:
    """The SceneOptimizer experiments' entries: every method's sweep (``auto`` skipped, with
    the reason, while the library lacks it). Returns ``(entries, skipped)``; the entries of
    one method share transform objects with the timing run (compiled once)."""
    skipped = {}
    why = auto_unavailable()
    if why is not None:
        skipped["auto"] = why
        print(f"skipping auto: {why}")
    entries: dict[str, list[Entry]] = {}
    for method in (m for m in METHODS if m not in skipped):
        entries[method] = []
        for entry in sweeps[method]:
            hp = hyperparameters(method, entry)
            transform = make_transform(method, hp, iterations)
            entries[method].append(
                Entry(
                    run_id(method, hp, swept),
                    hp,
                    functools.partial(SceneOptimizerRun, problem, transform),
                )
            )
    return entries, skipped


def run_sweeps(problem, cfg, hyperparameters, swept: tuple[str, ...], progress: bool = True):
    """:func:`sweep_entries` run by the runner with ``cfg``'s ``sweeps``, ``iterations``,
    ``record_every`` and ``timing_rounds``; returns ``(traces, samples, skipped)``."""
    entries, skipped = sweep_entries(problem, cfg.sweeps, hyperparameters, swept, cfg.iterations)
    traces, samples = runner.run_entries(
        problem,
        entries,
        iterations=cfg.iterations,
        record_every=cfg.record_every,
        timing_rounds=cfg.timing_rounds,
        progress=progress,
    )
    return traces, samples, skipped


def render_reference(scene, spp: int, seed: int):
    """``(image, seconds)``: a render of ``scene`` as it is (the reference), timed."""
    import drjit as dr
    import mitsuba as mi

    t0 = time.perf_counter()
    image = mi.render(scene, spp=spp, seed=seed)
    dr.eval(image)
    dr.sync_thread()
    return image, time.perf_counter() - t0


def render_views(scene, sensors, spp: int, seed: int) -> list[np.ndarray]:
    """Renders of ``scene`` as it is from each sensor (a ``mi.Sensor`` or the index of one of
    the scene's), without gradients, as NumPy arrays."""
    import drjit as dr
    import mitsuba as mi

    with dr.suspend_grad():
        return [np.array(mi.render(scene, sensor=s, spp=spp, seed=seed)) for s in sensors]


def tone_map(img: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """Log tone map of a linear image into [0, 1] between radiances ``lo`` and ``hi``."""
    img = np.maximum(np.asarray(img, np.float64), lo)
    return np.clip((np.log(img) - np.log(lo)) / (np.log(hi) - np.log(lo)), 0.0, 1.0)
