"""Tuning benchmark (issue #17): how much of the filter's gain survives without per-problem tuning.

    python -m experiments.tuning [--quick] [--out DIR] [--only-scenes a,b] [--jobs N]
                                 [--candidates [NAME=]module:factory,...] [--recompute]
                                 [--reference FILE]

For every scene of :mod:`experiments.tuning.scenes` (texture, its noise target, its
low-noise variant, volume, a 1-D signal, deblurring, deblurring at 100x scale)
it reports the final parameter error (median over seeds) of

* ``best_tuned``: ``bilateral_adam`` (postfilter, ``b1 = 0.2``) at the best point of a
  grid over ``sigma_d`` (0, 1e-3 ... 3, inf; times the scene's parameter unit for a
  linear guide), ``levels`` 2..6, ``log_guide`` (scenes with positive parameters
  spanning decades) and the learning rate;
* ``auto``: ``bilateral_adam(learning_rate, sigma_d="auto")``, learning rate swept
  (only when the installed library accepts ``sigma_d="auto"``; otherwise the row
  says "not available");
* ``defaults``: ``bilateral_adam(learning_rate)`` (its default ``sigma_d``, ``levels``),
  learning rate swept;
* ``adam``: ``optax.adam``, learning rate, ``b1`` and ``b2`` (0.999 or ``1 - (1 - b1)^2``) swept;
* ``pyramid``: Weier et al.'s Laplacian-pyramid parameterisation optimised with Adam
  (:func:`optax_bilateral.pyramid_adam`), learning rate and pyramid levels swept;
* any ``--candidates``: learning rate swept.

Every learning-rate sweep starts from the scene's grid (factor 2 apart) and is
extended by one factor of 2 at an edge where the best value lies, up to three
times, so the optimum is inside the grid (``summary.json`` flags points where it
is still at an edge).

Plugging in a candidate (the API the ``sigma_d="auto"`` work uses)
--------------------------------------------------------------------
A *candidate* is a factory ``factory(learning_rate) -> optax.GradientTransformation``
(``learning_rate`` arrives as a traced scalar, so one compiled update program serves
every learning rate and seed). A factory with a ``scene`` parameter also receives the
:class:`experiments.tuning.scenes.Scene` (e.g. to use ``log_guide`` where ``scene.log_guide``).
From the command line (``module`` importable, e.g. a file on ``PYTHONPATH``)::

    python -m experiments.tuning --only-scenes deblur,texture --candidates auto2=mymodule:factory

compares it with the stored grid (``--out``'s ``cache/``; the grid is only run when
its cache is missing or its configuration changed) and adds it to ``table.md``
with its ratios to the best-tuned and to Adam's error. From Python::

    from experiments import tuning
    from experiments.tuning import scenes
    scene = scenes.make("deblur")
    factory = lambda learning_rate, sigma_d: ob.bilateral_adam(learning_rate, sigma_d=sigma_d)
    settings = [{"learning_rate": 0.02, "sigma_d": s} for s in (0.02, 0.1)]
    errors = tuning.evaluate(scene, factory, settings, seeds=(0, 1, 2))  # (2, 3) final errors
    result = tuning.tune(scene, tuning.Family("mine", factory))   # learning rate swept
    result.best.median, result.best.hyper

:func:`run_benchmark` runs the whole table (``candidates={"name": factory}``).

Without the grids: ``--reference``
----------------------------------
The grids take about 17 minutes on two cores; a candidate's own learning-rate sweep
one or two. Every run writes ``reference.json`` (per scene and grid family: a key of the
scene's and the grid's configuration, and each setting's record at its best learning
rate), and ``--reference FILE`` takes the best-tuned, Adam and pyramid grids from such a
file instead of running them (``auto``, the defaults and the candidates still run). The
repository keeps the full run's file, so on a fresh clone::

    python -m experiments.tuning --reference experiments/tuning/reference.json \
        --candidates mine=mymodule:factory --out results/mine

A file of another setting (``--quick`` or not), without a requested scene, or whose
scene, grid or settings no longer match this code's is refused with the reason: rerun
the grids and commit that run's ``reference.json``. The table names the file and the
library version that ran its grids.

Cost: every scene compiles its noisy gradient once (``jax.vmap`` over a batch of
runs: every run of every method advances together) and one update program per
method and static setting (``levels``, ``log_guide``); the runs of a batch differ
in traced hyperparameters and seeds and go through ``jax.lax.map`` in the update
(sequential runs: the filter's ``lax.cond`` stays a branch; under ``vmap`` it
would run both branches). ``summary.json`` records each scene's and family's
seconds.

Outputs in ``--out`` (default ``results/tuning``): ``summary.json`` (per scene:
every method's median error, its hyperparameters and per-seed errors, and the
whole grid), ``table.md``, ``reference.json`` (above), ``<scene>.png`` (final error
against ``sigma_d``, one curve per ``levels`` at that point's best learning rate,
``auto`` / Adam / pyramid as horizontal lines; 0 and inf at the ends of the log axis)
and ``cache/``.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import importlib
import inspect
import json
import math
import os
import pathlib
import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import optax

import optax_bilateral as ob
from experiments import common
from experiments.tuning import scenes as sc

#: ``sigma_d`` grid (times ``scene.scale`` for a linear guide); 0 and inf are the extremes.
SIGMA_GRID = (0.0, 1e-3, 3e-3, 0.01, 0.03, 0.1, 0.3, 1.0, 3.0, math.inf)
LEVELS_GRID = (2, 3, 4, 5, 6)
ADAM_B1 = (0.9, 0.5, 0.2)
PYRAMID_LEVELS = (2, 3, 4, 5, 6)
SEEDS = (0, 1, 2)
#: Rounds of learning-rate grid extension at an edge (each adds one factor of 2).
MAX_EXTEND = 3
LR_RATIO = 2.0
#: Bumped when a change makes cached grids stale.
CACHE_VERSION = 1
#: Worker processes of the command line: one per core (each XLA client runs its small
#: programs on one thread; compilation, a large share of the quick run, is serial).
DEFAULT_JOBS = max(1, min(2, os.cpu_count() or 1))
#: The issue's targets.
TARGET_BEST = 1.10
TARGET_ADAM = 1.05


@dataclasses.dataclass(frozen=True)
class Settings:
    """What the benchmark sweeps; :func:`settings` gives the full and the quick one."""

    sigma_grid: tuple[float, ...]
    levels_grid: tuple[int, ...]
    adam_b1: tuple[float, ...]
    pyramid_levels: tuple[int, ...]
    seeds: tuple[int, ...]
    max_extend: int
    lr_points: int | None = None  # keep only this many of each scene's learning rates (quick)


#: A smaller grid for costly scenes (``--grid reduced``; the Mitsuba scenes spend ~0.1 s a
#: render): one seed, four ``sigma_d``, ``levels`` 3 and 5, Adam's ``b1`` 0.9, the pyramid at
#: 3 and 5 levels, one learning-rate extension.
REDUCED = Settings(
    sigma_grid=(0.01, 0.03, 0.1, 0.3),
    levels_grid=(3, 5),
    adam_b1=(0.9,),
    pyramid_levels=(3, 5),
    seeds=(0,),
    max_extend=1,
)


def settings(quick: bool, grid: str | None = None) -> Settings:
    """The grid of a run: :data:`REDUCED` for ``grid="reduced"``, else the full or quick one."""
    if grid == "reduced":
        return REDUCED
    if grid is not None:
        raise ValueError(f"grid must be None or 'reduced', got {grid!r}")
    if quick:
        return Settings(
            sigma_grid=(0.0, 0.1, math.inf),
            levels_grid=(2,),
            adam_b1=(0.9,),
            pyramid_levels=(3,),
            seeds=(0,),
            max_extend=0,
            lr_points=2,
        )
    return Settings(SIGMA_GRID, LEVELS_GRID, ADAM_B1, PYRAMID_LEVELS, SEEDS, MAX_EXTEND)


# ----------------------------------------------------------------------------- running


_GRAD_PROGRAMS: dict = {}


def _grad_program(scene: sc.Scene):
    """The scene's vmapped noisy gradient, compiled once per scene (shared by every family)."""
    if scene not in _GRAD_PROGRAMS:
        takes_step = "step" in inspect.signature(scene.grad).parameters

        def one(data, params, seed, i):
            key = jax.random.fold_in(jax.random.key(seed), i)
            if takes_step:  # e.g. cameras taken in turn
                return scene.grad(data, params, key, step=i)
            return scene.grad(data, params, key)

        _GRAD_PROGRAMS[scene] = (
            jax.jit(jax.vmap(one, in_axes=(None, 0, 0, None))),
            jax.jit(jax.vmap(scene.error, in_axes=(None, 0))),
        )
    return _GRAD_PROGRAMS[scene]


def _segments(iterations: int, target: int = 10) -> int:
    """Number of error records per run: the largest divisor of ``iterations`` up to ``target``."""
    return max(d for d in range(1, min(target, iterations) + 1) if iterations % d == 0)


class Runner:
    """Runs one optimizer factory on one scene for any hyperparameter values and seeds.

    ``factory(**{name: value})`` builds the optimizer from traced scalars (one per
    name in ``names``), so the update compiles once per batch size. Runs go in batches
    of ``scene.batch``, a remainder in batches of a quarter of that (two compiled sizes;
    the last batch padded); ``mode="map"`` applies the update run by run with
    ``lax.map``, ``"vmap"`` vectorises it.
    """

    def __init__(
        self,
        scene: sc.Scene,
        factory: Callable[..., optax.GradientTransformation],
        names: Sequence[str],
        *,
        batch: int | None = None,
        mode: str = "map",
    ):
        if mode not in ("map", "vmap"):
            raise ValueError(f"mode must be 'map' or 'vmap', got {mode!r}")
        self.scene, self.names = scene, tuple(names)
        self.batch = int(batch or scene.batch)
        self.small_batch = max(1, self.batch // 4)
        self._grad, self._error = _grad_program(scene)

        def build(h):
            return factory(**{n: h[j] for j, n in enumerate(self.names)})

        def update_one(data, g, s, p, h):
            u, s = build(h).update(g, s, p)
            return scene.project(data, optax.apply_updates(p, u)), s

        if mode == "map":

            def update(data, g, s, p, h):
                return jax.lax.map(lambda x: update_one(data, *x), (g, s, p, h))
        else:
            update = jax.vmap(update_one, in_axes=(None, 0, 0, 0, 0))
        self._update = jax.jit(update)
        self._init = jax.jit(jax.vmap(lambda h, p: build(h).init(p), in_axes=(0, None)))

    def __call__(
        self, hypers: np.ndarray, seeds: np.ndarray, progress=None
    ) -> tuple[np.ndarray, np.ndarray]:
        """Final errors ``(R,)`` and error records ``(R, segments)`` of runs with
        ``hypers[r]`` (values for ``names``) and ``seeds[r]``."""
        hypers = np.asarray(hypers, np.float32).reshape(len(seeds), len(self.names))
        seeds = np.asarray(seeds, np.int32)
        scene = self.scene
        n_seg = _segments(scene.iterations)
        every = scene.iterations // n_seg
        curves = []
        for start, b in _chunks(len(seeds), self.batch, self.small_batch):
            h, s = hypers[start : start + b], seeds[start : start + b]
            real = len(s)
            if real < b:  # pad with copies of the last run: a compiled shape
                h = np.concatenate([h, np.repeat(h[-1:], b - real, 0)])
                s = np.concatenate([s, np.repeat(s[-1:], b - real, 0)])
            h, s = jnp.asarray(h), jnp.asarray(s)
            params = _batched(scene.init, b)
            state = self._init(h, scene.init)
            recs = []
            for i in range(scene.iterations):
                g = self._grad(scene.data, params, s, i)
                params, state = self._update(scene.data, g, state, params, h)
                if (i + 1) % every == 0:
                    recs.append(self._error(scene.data, params))
            curves.append(np.stack(jax.device_get(recs), axis=1)[:real])
            if progress is not None:
                progress.update(real)
        curves = np.concatenate(curves, axis=0).astype(np.float64)
        return curves[:, -1], curves


def _chunks(n: int, big: int, small: int) -> list[tuple[int, int]]:
    """``(start, size)`` batches covering ``n`` runs: ``big`` ones, then the remainder in
    ``small`` ones unless one more ``big`` batch wastes less."""
    out, start = [], 0
    while n - start >= big:
        out.append((start, big))
        start += big
    rest = n - start
    if rest and -(-rest // small) * small >= big:
        out.append((start, big))
    else:
        out += [(start + k, small) for k in range(0, rest, small)]
    return out


def evaluate(
    scene: sc.Scene,
    make_optimizer: Callable[..., optax.GradientTransformation],
    hyper_grid: Sequence[Mapping[str, float]] | Mapping[str, Sequence[float]],
    seeds: Sequence[int] = SEEDS,
    *,
    mode: str = "map",
    progress: bool = False,
) -> np.ndarray:
    """Final errors ``(len(grid), len(seeds))`` of ``make_optimizer(**point)`` on ``scene``.

    ``hyper_grid`` is a list of points (dicts with the same keys, numbers) or a dict
    of lists (their product). Every value is traced: one compiled program for the grid.
    """
    grid = _as_points(hyper_grid)
    names = tuple(grid[0])
    runner = Runner(scene, make_optimizer, names, mode=mode)
    hypers = np.array([[p[n] for n in names] for p in grid for _ in seeds], np.float32)
    seed_col = np.array([s for _ in grid for s in seeds], np.int32)
    bar = _bar(len(seed_col), f"{scene.name}") if progress else None
    final, _ = runner(hypers, seed_col, bar)
    if bar is not None:
        bar.close()
    return final.reshape(len(grid), len(seeds))


def _as_points(hyper_grid) -> list[dict]:
    if isinstance(hyper_grid, Mapping):
        keys = list(hyper_grid)
        vals = [list(hyper_grid[k]) for k in keys]
        points = [dict(zip(keys, combo)) for combo in _product(vals)]
    else:
        points = [dict(p) for p in hyper_grid]
    if not points:
        raise ValueError("hyper_grid must hold at least one point")
    keys = set(points[0])
    for p in points:
        if set(p) != keys:
            raise ValueError(
                f"every hyper_grid point needs the same keys; got {sorted(p)} and {sorted(keys)}"
            )
        for k, v in p.items():
            if isinstance(v, bool) or not isinstance(v, (int, float, np.floating, np.integer)):
                raise TypeError(
                    f"hyper_grid values must be numbers (they are traced); "
                    f"{k}={v!r}. Close over static settings in the factory instead."
                )
    return points


def _product(vals):
    if not vals:
        return [()]
    return [(v,) + rest for v in vals[0] for rest in _product(vals[1:])]


#: The tqdm line of this process (worker processes draw below the parent's scene bar).
_BAR_POSITION = 0


def _bar(total: int, desc: str):
    from tqdm.auto import tqdm

    return tqdm(
        total=total, desc=desc, unit="run", leave=False, dynamic_ncols=True, position=_BAR_POSITION
    )


def _init_worker(counter) -> None:
    global _BAR_POSITION
    with counter.get_lock():
        counter.value += 1
        _BAR_POSITION = counter.value


# ----------------------------------------------------------------------------- tuning


@dataclasses.dataclass(frozen=True)
class Family:
    """A method and its grid: one compiled update program per entry of ``statics``.

    ``factory(learning_rate, **point, **static)`` returns the optimizer; ``points``
    are the traced hyperparameters besides the learning rate (swept at every point),
    or a function ``static -> points`` when they depend on the static setting.
    ``lr_scale(static)`` multiplies the first learning-rate grid (e.g. ``1/levels`` for the
    pyramid, whose levels add up to ``levels`` times Adam's step).
    """

    name: str
    factory: Callable[..., optax.GradientTransformation]
    statics: tuple[Mapping[str, Any], ...] = ({},)
    points: tuple[Mapping[str, float], ...] | Callable = ({},)
    description: str = ""
    lr_scale: Callable[[Mapping[str, Any]], float] | None = None

    def points_for(self, static: Mapping[str, Any]) -> list[dict]:
        pts = self.points(static) if callable(self.points) else self.points
        return [dict(p) for p in pts]


@dataclasses.dataclass
class Record:
    """All seeds of one setting: static settings, traced hyperparameters, errors."""

    static: dict
    hyper: dict
    errors: list[float]
    curve: list[float]

    @property
    def median(self) -> float:
        return _nan_median(self.errors)

    def to_json(self) -> dict:
        return {
            "static": self.static,
            "hyper": self.hyper,
            "errors": self.errors,
            "median": self.median,
            "curve": self.curve,
        }

    @classmethod
    def from_json(cls, d: dict) -> Record:
        return cls(
            static=d["static"],
            hyper={k: float(v) for k, v in d["hyper"].items()},
            errors=[float(e) for e in d["errors"]],
            curve=[float(e) for e in d["curve"]],
        )


def _batched(tree, b: int):
    """Every leaf of ``tree`` repeated along a new leading axis of size ``b``."""
    return jax.tree.map(lambda x: jnp.broadcast_to(x, (b,) + x.shape), tree)


def _nan_median(values) -> float:
    v = np.asarray(values, np.float64)
    # A diverged run (NaN) counts as infinitely bad, so a median over seeds stays honest.
    return float(np.median(np.where(np.isfinite(v), v, np.inf)))


@dataclasses.dataclass
class Result:
    """Every record of one family on one scene; ``best`` has the smallest median error."""

    family: str
    records: list[Record]
    seconds: float
    at_edge: list[dict]

    @property
    def best(self) -> Record:
        return min(self.records, key=lambda r: r.median)

    def best_where(self, pred: Callable[[Record], bool]) -> Record:
        return min((r for r in self.records if pred(r)), key=lambda r: r.median)


def tune(
    scene: sc.Scene,
    family: Family,
    seeds: Sequence[int] = SEEDS,
    *,
    max_extend: int = MAX_EXTEND,
    learning_rates: Sequence[float] | None = None,
    progress: bool = True,
    mode: str = "map",
) -> Result:
    """Runs ``family`` on ``scene``: every static setting and point, the learning rate swept.

    The sweep starts at ``learning_rates`` (default: the scene's) and adds the next
    value (a factor of 2 beyond) at an edge holding the best median error, up to
    ``max_extend`` times.
    """
    t0 = time.perf_counter()
    lrs0 = tuple(scene.learning_rates if learning_rates is None else learning_rates)
    records: list[Record] = []
    at_edge: list[dict] = []
    for static in family.statics:
        points = family.points_for(static)
        names = ("learning_rate",) + tuple(points[0])
        factory = _bind(family.factory, static, scene)
        runner = Runner(scene, factory, names, mode=mode)
        tried: dict[int, dict[float, Record]] = {k: {} for k in range(len(points))}
        scale = 1.0 if family.lr_scale is None else family.lr_scale(static)
        pending = [(k, _round(lr * scale)) for k in range(len(points)) for lr in lrs0]
        for round_ in range(max_extend + 1):
            if not pending:
                break
            hypers = [[lr] + [points[k][n] for n in names[1:]] for k, lr in pending for _ in seeds]
            seed_col = [s for _ in pending for s in seeds]
            desc = f"{scene.name}: {family.name} {_fmt_static(static)}".strip()
            bar = _bar(len(seed_col), desc) if progress else None
            final, curves = runner(np.array(hypers), np.array(seed_col), bar)
            if bar is not None:
                bar.close()
            n = len(seeds)
            for j, (k, lr) in enumerate(pending):
                rec = Record(
                    static=dict(static),
                    hyper={"learning_rate": lr, **points[k]},
                    errors=[float(e) for e in final[j * n : (j + 1) * n]],
                    curve=[_nan_median(c) for c in curves[j * n : (j + 1) * n].T],
                )
                tried[k][lr] = rec
            pending = []
            for k, by_lr in tried.items():
                lrs = sorted(by_lr)
                best = min(lrs, key=lambda lr: by_lr[lr].median)
                if round_ == max_extend or not math.isfinite(by_lr[best].median):
                    continue
                if best == lrs[0]:
                    pending.append((k, _round(lrs[0] / LR_RATIO)))
                elif best == lrs[-1]:
                    pending.append((k, _round(lrs[-1] * LR_RATIO)))
        for by_lr in tried.values():
            records.extend(by_lr.values())
            lrs = sorted(by_lr)
            best = min(lrs, key=lambda lr: by_lr[lr].median)
            if len(lrs) > 1 and best in (lrs[0], lrs[-1]):
                at_edge.append({"static": dict(static), "hyper": by_lr[best].hyper})
    return Result(
        family=family.name, records=records, seconds=time.perf_counter() - t0, at_edge=at_edge
    )


def _round(x: float) -> float:
    return float(f"{x:.4g}")


def _bind(factory, static: Mapping[str, Any], scene: sc.Scene):
    """``factory`` with the static settings and (if it takes them) the scene and the scene's
    ``spatial_axes`` bound."""
    kwargs = dict(static)
    try:
        accepts = inspect.signature(factory).parameters
    except (TypeError, ValueError):
        accepts = {}
    if "scene" in accepts:
        kwargs["scene"] = scene
    if "spatial_axes" in accepts and scene.spatial_axes is not None:
        kwargs["spatial_axes"] = scene.spatial_axes
    if not kwargs:
        return factory

    def bound(**traced):
        return factory(**traced, **kwargs)

    return bound


def _fmt_static(static: Mapping[str, Any]) -> str:
    return " ".join(f"{k}={v}" for k, v in static.items())


# ----------------------------------------------------------------------------- the families


def _levels_that_matter(scene: sc.Scene, levels_grid: Sequence[int]) -> tuple[list[int], dict]:
    """Levels whose last a-trous pass reaches a neighbour on some leaf; ``{skipped: same_as}``.

    A level of stride ``2^(L-1)`` at least every spatial size has no neighbour inside the
    grid: it is the identity, so ``levels = L`` gives the results of ``L - 1``.
    """
    axes = ob.filtered_axes(scene.init, spatial_axes=scene.spatial_axes)
    sizes = [
        max(np.shape(x)[a] for a in ax)
        for x, ax in zip(jax.tree.leaves(scene.init), axes.values())
        if ax
    ]
    largest = max(sizes) if sizes else 1
    keep, same = [], {}
    for lev in sorted(levels_grid):
        if keep and 2 ** (lev - 1) >= largest:
            same[lev] = keep[-1]
        else:
            keep.append(lev)
    return keep, same


def bilateral_factory(learning_rate, sigma_d, *, levels, log_guide, spatial_axes=None):
    """``bilateral_adam`` (postfilter, its default ``b1``) with a traced ``sigma_d``."""
    return ob.bilateral_adam(
        learning_rate,
        sigma_d=sigma_d,
        levels=levels,
        log_guide=log_guide,
        spatial_axes=spatial_axes,
    )


def adam_factory(learning_rate, b1, b2=0.999):
    return optax.adam(learning_rate, b1=b1, b2=b2)


def pyramid_factory(learning_rate, *, levels, spatial_axes=None):
    return ob.pyramid_adam(learning_rate, levels=levels, spatial_axes=spatial_axes)


def defaults_factory(learning_rate, spatial_axes=None):
    """``bilateral_adam`` with every default (whatever the installed library's defaults are)."""
    return ob.bilateral_adam(learning_rate, spatial_axes=spatial_axes)


def auto_factory(learning_rate, spatial_axes=None):
    return ob.bilateral_adam(learning_rate, sigma_d="auto", spatial_axes=spatial_axes)


def sure_factory(learning_rate, spatial_axes=None):
    """``sigma_d="sure"`` with ``levels=5`` (F chosen among 2-5, its default; written out so
    the measured setting stays fixed; docs/auto_sigma.md), as a
    candidate: ``--candidates sure=experiments.tuning:sure_factory``."""
    return ob.bilateral_adam(learning_rate, sigma_d="sure", levels=5, spatial_axes=spatial_axes)


def auto_available() -> bool:
    """Whether the installed library accepts ``sigma_d="auto"`` (tried on a small grid)."""
    try:
        opt = ob.bilateral_adam(0.1, sigma_d="auto")
        p = jnp.linspace(0.1, 1.0, 64, dtype=jnp.float32).reshape(8, 8)
        u, _ = opt.update(jnp.cos(p * 7), opt.init(p), p)
        return bool(jnp.all(jnp.isfinite(u)))
    except (TypeError, ValueError):
        return False


def bilateral_defaults() -> dict:
    """``bilateral_adam``'s default ``sigma_d``, ``levels`` and ``b1`` (read from its signature)."""
    sig = inspect.signature(ob.bilateral_adam).parameters
    return {k: sig[k].default for k in ("sigma_d", "levels", "b1")}


def families(scene: sc.Scene, s: Settings) -> dict[str, Family]:
    """The grid families of the benchmark on ``scene`` (cached), in running order."""
    levels, _ = _levels_that_matter(scene, s.levels_grid)
    guides = (False, True) if scene.log_guide else (False,)
    statics = tuple({"levels": lev, "log_guide": lg} for lg in guides for lev in levels)

    def sigmas(static):
        # A log guide is unit-free; a linear one is in the parameters' unit.
        unit = 1.0 if static["log_guide"] else scene.scale
        return tuple({"sigma_d": _sigma(x, unit)} for x in s.sigma_grid)

    return {
        "bilateral": Family(
            "bilateral", bilateral_factory, statics, sigmas, "bilateral_adam, postfilter, b1=0.2"
        ),
        "adam": Family(
            "adam",
            adam_factory,
            ({},),
            adam_points(s.adam_b1),
            "optax.adam, b2 = 0.999 or 1-(1-b1)^2",
        ),
        "pyramid": Family(
            "pyramid",
            pyramid_factory,
            tuple({"levels": k} for k in s.pyramid_levels),
            ({},),
            "Laplacian pyramid + Adam (Weier et al. 2025)",
            lr_scale=_per_level,
        ),
        "defaults": Family(
            "defaults",
            defaults_factory,
            description=("bilateral_adam defaults " + json.dumps(_jsonable(bilateral_defaults()))),
        ),
    }


def adam_points(b1s: Sequence[float]) -> tuple[dict, ...]:
    """Adam's ``(b1, b2)`` grid: every ``b1`` with optax's ``b2 = 0.999`` and with the paper's
    pairing ``b2 = 1 - (1 - b1)^2`` (``bilateral_adam``'s default; on the texture scenes
    ``sigma_d = 0``, close to that Adam, halved optax.adam's error)."""
    return tuple({"b1": b, "b2": b2} for b in b1s for b2 in (0.999, _round(1 - (1 - b) ** 2)))


def _per_level(static: Mapping[str, Any]) -> float:
    return 1.0 / static["levels"]


def _sigma(x: float, scale: float) -> float:
    return x if x in (0.0, math.inf) else _round(x * scale)


# ----------------------------------------------------------------------------- caching


def _cache_key(scene: sc.Scene, family: Family, s: Settings, *, library: bool = True) -> str:
    """A hash of everything a family's grid depends on; ``library=False`` leaves out the
    library's version (a reference is meant to outlive it)."""
    spec = {
        "version": CACHE_VERSION,
        "library": ob.__version__ if library else None,
        "scene": scene.config,
        "learning_rates": scene.learning_rates,
        "family": family.name,
        "description": family.description,
        "grid": [[dict(x), family.points_for(x)] for x in family.statics],
        "lr_scale": [
            1.0 if family.lr_scale is None else family.lr_scale(x) for x in family.statics
        ],
        "seeds": list(s.seeds),
        "max_extend": s.max_extend,
        "lr_points": s.lr_points,
    }
    return hashlib.sha256(json.dumps(_jsonable(spec), sort_keys=True).encode()).hexdigest()[:16]


def cached_tune(
    scene: sc.Scene,
    family: Family,
    s: Settings,
    cache_dir: pathlib.Path | None,
    *,
    recompute: bool = False,
    progress: bool = True,
    mode: str = "map",
) -> tuple[Result, bool]:
    """:func:`tune`, or its stored result when the scene, family and settings are unchanged.

    Returns ``(result, from_cache)``.
    """
    path = None if cache_dir is None else cache_dir / scene.name / f"{family.name}.json"
    key = _cache_key(scene, family, s)
    if path is not None and path.exists() and not recompute:
        stored = json.loads(path.read_text())
        if stored.get("key") == key:
            return Result(
                family=family.name,
                records=[Record.from_json(r) for r in stored["records"]],
                seconds=stored["seconds"],
                at_edge=stored["at_edge"],
            ), True
    res = tune(
        scene,
        family,
        s.seeds,
        max_extend=s.max_extend,
        learning_rates=_lrs(scene, s),
        progress=progress,
        mode=mode,
    )
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(
            json.dumps(
                _jsonable(
                    {
                        "key": key,
                        "scene": scene.config,
                        "family": family.name,
                        "seconds": res.seconds,
                        "at_edge": res.at_edge,
                        "records": [r.to_json() for r in res.records],
                    }
                )
            )
            + "\n"
        )
    return res, False


def _lrs(scene: sc.Scene, s: Settings) -> tuple[float, ...]:
    lrs = tuple(scene.learning_rates)
    if s.lr_points is not None and s.lr_points < len(lrs):
        mid = (len(lrs) - s.lr_points) // 2
        lrs = lrs[mid : mid + s.lr_points]
    return lrs


# ----------------------------------------------------------------------------- one scene


def run_scene(
    scene: sc.Scene,
    s: Settings,
    cache_dir: pathlib.Path | None,
    *,
    candidates: Mapping[str, Callable] | None = None,
    recompute: bool = False,
    with_auto: bool | None = None,
    progress: bool = True,
    reference: Mapping[str, Any] | None = None,
) -> dict:
    """Every method on one scene; returns its ``summary.json`` entry.

    ``reference``: the scene's part of a ``reference.json`` (:func:`load_reference`); its
    grids (:data:`REFERENCE_FAMILIES`) are then taken from it instead of being run.
    """
    t0 = time.perf_counter()
    results: dict[str, Result] = {}
    from_cache: dict[str, bool] = {}
    grids = families(scene, s)
    for name, fam in grids.items():
        if reference is not None and name in REFERENCE_FAMILIES:
            results[name], from_cache[name] = _from_reference(reference, scene, fam, s), True
            continue
        if name == "defaults" and (grid_part := _defaults_in_grid(scene, s, results["bilateral"])):
            results[name], from_cache[name] = grid_part, from_cache["bilateral"]
            continue
        results[name], from_cache[name] = cached_tune(
            scene, fam, s, cache_dir, recompute=recompute, progress=progress
        )
    with_auto = auto_available() if with_auto is None else with_auto
    extra = {}
    if with_auto:
        extra["auto"] = Family("auto", auto_factory, description='bilateral_adam(sigma_d="auto")')
    for name, factory in (candidates or {}).items():
        extra[name] = Family(name, factory, description=f"candidate {name}")
    for name, fam in extra.items():
        if name == "auto" and getattr(ob, "DEFAULT_SIGMA_D", None) == "auto":
            # The defaults are bilateral_adam(lr) with sigma_d="auto": the same runs.
            results[name], from_cache[name] = results["defaults"], from_cache["defaults"]
            continue
        results[name] = tune(
            scene,
            fam,
            s.seeds,
            max_extend=s.max_extend,
            learning_rates=_lrs(scene, s),
            progress=progress,
        )
        from_cache[name] = False
    entry = summarize_scene(
        scene,
        s,
        results,
        from_cache,
        with_auto,
        list((candidates or {}).keys()),
        time.perf_counter() - t0,
    )
    entry["from_reference"] = list(REFERENCE_FAMILIES) if reference is not None else []
    library = ob.__version__ if reference is None else reference["library"]
    entry["reference_library"] = library
    entry[_REFERENCE_PART] = reference_part(scene, s, grids, results, library)
    return entry


def _defaults_in_grid(scene: sc.Scene, s: Settings, grid: Result) -> Result | None:
    """The defaults' runs, when the bilateral grid already holds them (the same optimizer,
    the same learning-rate search), else None."""
    d = bilateral_defaults()
    sigma, levels = d["sigma_d"], d["levels"]
    keep, same = _levels_that_matter(scene, s.levels_grid)
    levels = same.get(levels, levels)  # an identity last level: the grid's lower levels
    if isinstance(sigma, str) or levels not in keep:
        return None
    static = {"levels": levels, "log_guide": False}
    recs = [r for r in grid.records if r.static == static and r.hyper["sigma_d"] == sigma]
    if not recs:
        return None
    edge = [e for e in grid.at_edge if e["static"] == static and e["hyper"]["sigma_d"] == sigma]
    return Result(family="defaults", records=recs, seconds=0.0, at_edge=edge)


def _entry(rec: Record, result: Result) -> dict:
    return {
        "error": rec.median,
        "hyperparameters": {**rec.static, **rec.hyper},
        "errors": rec.errors,
        "curve": rec.curve,
        "lr_at_grid_edge": any(
            e["static"] == rec.static and e["hyper"] == rec.hyper for e in result.at_edge
        ),
    }


def summarize_scene(scene, s, results, from_cache, with_auto, candidate_names, seconds) -> dict:
    methods = {"best_tuned": _entry(results["bilateral"].best, results["bilateral"])}
    methods["auto"] = (
        _entry(results["auto"].best, results["auto"])
        if with_auto
        else {
            "error": None,
            "note": 'not available: the installed library does not accept sigma_d="auto"',
        }
    )
    for name in ("defaults", "adam", "pyramid", *candidate_names):
        methods[name] = _entry(results[name].best, results[name])
    methods["defaults"]["hyperparameters"].update(
        {k: v for k, v in bilateral_defaults().items() if k != "b1"}
    )
    best, adam = methods["best_tuned"]["error"], methods["adam"]["error"]
    adam_wins = adam < best
    comparisons = {}
    for name in (["auto"] if with_auto else []) + list(candidate_names):
        err = methods[name]["error"]
        comparisons[name] = {
            "ratio_to_best_tuned": err / best,
            "ratio_to_adam": err / adam,
            f"<= {TARGET_BEST} x best-tuned": bool(err <= TARGET_BEST * best),
            f"<= {TARGET_ADAM} x adam (where Adam wins)": (
                bool(err <= TARGET_ADAM * adam) if adam_wins else None
            ),
        }
    return {
        "scene": scene.name,
        "description": scene.description,
        "error_name": scene.error_name,
        "initial_error": scene.initial_error(),
        "iterations": scene.iterations,
        "seeds": list(s.seeds),
        "scale": scene.scale,
        "log_guide_grid": scene.log_guide,
        "adam_wins": bool(adam_wins),
        "methods": methods,
        "comparisons": comparisons,
        "seconds": {"total": seconds, **{k: r.seconds for k, r in results.items()}},
        "from_cache": from_cache,
        "levels_same_as": {
            str(k): v for k, v in _levels_that_matter(scene, s.levels_grid)[1].items()
        },
        "grid": {
            k: [r.to_json() for r in results[k].records]
            for k in ("bilateral", "adam", "pyramid", "defaults")
        },
        "lr_at_grid_edge": {k: r.at_edge for k, r in results.items() if r.at_edge},
    }


# ----------------------------------------------------------------------------- references

#: The families a reference holds: what a candidate is compared with, and what takes long.
REFERENCE_FAMILIES = ("bilateral", "adam", "pyramid")
REFERENCE_FORMAT = 1
#: The key under which a scene's entry carries its reference part until it is written.
_REFERENCE_PART = "reference_part"


def reference_part(
    scene: sc.Scene, s: Settings, grids: Mapping[str, Family], results, library: str
) -> dict:
    """One scene's part of ``reference.json``: per reference family the key of its grid's
    configuration and, for every setting, the record at its best learning rate (the other
    learning rates were the sweep's, not the comparison's); curves only for the family's best."""
    part: dict[str, Any] = {"library": library, "families": {}}
    for name in REFERENCE_FAMILIES:
        result = results[name]
        best: dict[str, Record] = {}
        for r in result.records:
            setting = _setting(r)
            if setting not in best or r.median < best[setting].median:
                best[setting] = r
        overall = result.best
        best[_setting(overall)] = overall  # a tie keeps the family's best as it was
        records = [{**r.to_json(), "curve": r.curve if r is overall else []} for r in best.values()]
        part["families"][name] = {
            "key": _cache_key(scene, grids[name], s, library=False),
            "seconds": result.seconds,
            "at_edge": result.at_edge,
            "records": records,
        }
    return part


def _setting(r: Record) -> str:
    """A record's setting: everything but the learning rate."""
    hyper = {k: v for k, v in r.hyper.items() if k != "learning_rate"}
    return json.dumps(_jsonable([r.static, hyper]), sort_keys=True)


def load_reference(
    path: str | pathlib.Path, scene_names: Sequence[str], quick: bool
) -> dict[str, Any]:
    """``{"file": path, "scenes": {name: part}}``: the parts of the reference file ``path``
    (a run's ``reference.json``) for ``scene_names``; a clear error when it holds another
    setting or lacks a scene."""
    path = pathlib.Path(path)
    try:
        data = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise ValueError(f"--reference {path}: not a readable JSON file ({e})") from e
    found = data.get("format") if isinstance(data, dict) else None
    if found != REFERENCE_FORMAT:
        raise ValueError(
            f"--reference {path}: expected a tuning run's reference.json "
            f"(format {REFERENCE_FORMAT}), got format {found!r}"
        )
    if bool(data["quick"]) != quick:
        held, this = ("a --quick", "a full") if data["quick"] else ("a full", "a --quick")
        raise ValueError(f"--reference {path} holds {held} run and this is {this} run")
    missing = [n for n in scene_names if n not in data["scenes"]]
    if missing:
        raise ValueError(
            f"--reference {path} has no scene {', '.join(missing)} (it has "
            f"{', '.join(sorted(data['scenes']))}); run their grids without --reference"
        )
    return {"file": str(path), "scenes": {n: data["scenes"][n] for n in scene_names}}


def _from_reference(part: Mapping[str, Any], scene: sc.Scene, family: Family, s: Settings):
    stored = part["families"].get(family.name)
    if stored is None or stored["key"] != _cache_key(scene, family, s, library=False):
        raise ValueError(
            f"the reference's {family.name} grid on {scene.name} was run with another scene, "
            f"grid or settings than this run's; rerun the grids (python -m experiments.tuning "
            f"--only-scenes {scene.name}) and pass that run's reference.json"
        )
    return Result(
        family=family.name,
        records=[Record.from_json(r) for r in stored["records"]],
        seconds=stored["seconds"],
        at_edge=stored["at_edge"],
    )


def write_reference(path: pathlib.Path, entries: Mapping[str, dict], quick: bool, s: Settings):
    """``reference.json``: the scenes' reference parts (taken out of their entries)."""
    scenes = {n: e.pop(_REFERENCE_PART) for n, e in entries.items()}
    data = {
        "format": REFERENCE_FORMAT,
        "quick": quick,
        "settings": dataclasses.asdict(s),
        "scenes": scenes,
    }
    path.write_text(json.dumps(_jsonable(data), sort_keys=True) + "\n")


# ----------------------------------------------------------------------------- outputs


def sensitivity(entry: dict, log_guide: bool) -> dict[int, list[tuple[float, float]]]:
    """``{levels: [(sigma_d, best-over-lr median error), ...]}`` of the bilateral grid."""
    best: dict[tuple[int, float], float] = {}
    for r in entry["grid"]["bilateral"]:
        if bool(r["static"]["log_guide"]) != log_guide:
            continue
        key = (int(r["static"]["levels"]), float(r["hyper"]["sigma_d"]))
        best[key] = min(best.get(key, math.inf), float(r["median"]))
    out: dict[int, list] = {}
    for (lev, sig), err in sorted(best.items()):
        out.setdefault(lev, []).append((sig, err))
    for lev, same in entry.get("levels_same_as", {}).items():
        if same in out:
            out[int(lev)] = list(out[same])
    return dict(sorted(out.items()))


def _xpos(sig: float, lo: float, hi: float) -> float:
    """Where a sigma_d is drawn on a log axis: 0 at ``lo``, inf at ``hi``."""
    return lo if sig == 0 else hi if sig == math.inf else sig


def plot_scene(entry: dict, path: pathlib.Path) -> pathlib.Path:
    """Final error against ``sigma_d`` (one curve per ``levels``), reference methods as lines."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = [False, True] if entry["log_guide_grid"] else [False]
    fig, axes = plt.subplots(1, len(panels), figsize=(7 * len(panels), 4.4), dpi=110, squeeze=False)
    lines = {
        "adam": ("Adam (best lr, b1, b2)", "k", "-"),
        "auto": ("auto", "tab:red", "-"),
        "defaults": ("defaults", "tab:gray", ":"),
        "pyramid": ("pyramid + Adam", "tab:green", "--"),
    }
    for name in entry["methods"]:
        if name not in lines and name != "best_tuned":
            lines[name] = (name, "tab:purple", "-.")
    for ax, lg in zip(axes[0], panels):
        curves = sensitivity(entry, lg)
        finite = sorted({s for c in curves.values() for s, _ in c if 0 < s < math.inf})
        if not finite:
            continue
        lo, hi = finite[0] / 10, finite[-1] * 10  # where 0 and inf are drawn

        for lev, pts in curves.items():
            ax.plot(
                [_xpos(s, lo, hi) for s, _ in pts],
                [e for _, e in pts],
                marker="o",
                ms=3,
                lw=1.3,
                label=f"levels={lev}",
            )
        for name, (label, color, style) in lines.items():
            err = entry["methods"].get(name, {}).get("error")
            if err is not None and math.isfinite(err):
                ax.axhline(err, color=color, ls=style, lw=1.2, label=f"{label}: {err:.4g}")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ticks = [lo] + [t for t in ax.get_xticks() if lo < t < hi] + [hi]
        ax.set_xticks(ticks)
        ax.set_xticklabels(["0"] + [f"{t:g}" for t in ticks[1:-1]] + ["inf"])
        ax.set_xlim(lo / 1.5, hi * 1.5)
        ax.set_xlabel("sigma_d" + (" (log guide)" if lg else " (linear guide)"))
        ax.set_ylabel(f"final error: {entry['error_name']}")
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=7)
    if entry["methods"]["auto"].get("error") is None:
        axes[0, 0].text(
            0.02,
            0.02,
            'auto: not available (sigma_d="auto" not accepted)',
            transform=axes[0, 0].transAxes,
            fontsize=7,
            color="tab:red",
        )
    import textwrap

    title = textwrap.fill(f"{entry['scene']}: {entry['description']}", 100 * len(panels))
    fig.suptitle(
        f"{title}\nmedian of {len(entry['seeds'])} seeds, best learning rate per point", fontsize=9
    )
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)
    return path


def _hp(h: Mapping[str, Any], keys=None) -> str:
    short = {"learning_rate": "lr", "sigma_d": "σ_d", "log_guide": "log"}
    out = []
    for k, v in h.items():
        if keys is not None and k not in keys:
            continue
        if isinstance(v, bool):
            if v:
                out.append(short.get(k, k))
            continue
        out.append(
            f"{short.get(k, k)}={v:g}" if isinstance(v, (int, float)) else f"{short.get(k, k)}={v}"
        )
    return ", ".join(out)


def _cell(methods: dict, k: str, keys=None) -> str:
    """Method ``k``'s error for the table, with the hyperparameters ``keys``."""
    x = methods[k]
    if x.get("error") is None:
        return "not available"
    return f"{x['error']:.4g} ({_hp(x['hyperparameters'], keys)})" if keys else f"{x['error']:.4g}"


def _reference_note(summary: dict) -> str:
    if not summary.get("reference"):
        return ""
    libraries = sorted({e["reference_library"] for e in summary["scenes"].values()})
    return (
        f"Best-tuned, Adam and pyramid: from `{summary['reference']}` (library "
        f"{', '.join(libraries)}; each setting at its best learning rate), not rerun.\n\n"
    )


def markdown(summary: dict) -> str:
    """``table.md``: scenes x methods, ratios and the issue's targets."""
    scenes = summary["scenes"]
    cand = summary["candidates"]
    has_auto = summary["auto_available"]
    head = [
        "scene",
        "initial",
        "best-tuned (σ_d, levels, lr)",
        "auto",
        "defaults",
        "Adam (lr, b1, b2)",
        "pyramid (levels, lr)",
    ] + cand
    rows = []
    for name, e in scenes.items():
        cell = functools.partial(_cell, e["methods"])
        rows.append(
            [
                name,
                f"{e['initial_error']:.4g}",
                cell("best_tuned", ("sigma_d", "levels", "log_guide", "learning_rate")),
                cell("auto"),
                cell("defaults", ("learning_rate",)),
                cell("adam", ("learning_rate", "b1", "b2")),
                cell("pyramid", ("levels", "learning_rate")),
            ]
            + [cell(c) for c in cand]
        )
    lines = ["| " + " | ".join(head) + " |", "|" + "|".join("---" for _ in head) + "|"]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    auto_text = (
        '= bilateral_adam(sigma_d="auto")' if has_auto else "not available in the installed library"
    )
    text = (
        f"# Tuning benchmark ({'quick' if summary['quick'] else 'full'})\n\n"
        f"Final parameter error, median over seeds {summary['settings']['seeds']}; every method "
        f"at its best learning rate. `auto` {auto_text}; "
        f"defaults = bilateral_adam {json.dumps(_jsonable(summary['defaults']))}.\n\n"
        + _reference_note(summary)
        + "\n".join(lines)
        + "\n"
    )
    compared = (["auto"] if has_auto else []) + cand
    targets = [f"auto/best-tuned <= {TARGET_BEST}", f"auto/Adam <= {TARGET_ADAM} where Adam wins"]
    if compared:
        head2 = ["scene", "Adam wins"] + [
            c
            for name in compared
            for c in (
                f"{name}/best-tuned",
                f"{name}/Adam",
                f"{name}: ≤{TARGET_BEST}× best",
                f"{name}: ≤{TARGET_ADAM}× Adam",
            )
        ]
        lines2 = ["| " + " | ".join(head2) + " |", "|" + "|".join("---" for _ in head2) + "|"]
        for name, e in scenes.items():
            row = [name, "yes" if e["adam_wins"] else "no"]
            for c in compared:
                cmp_ = e["comparisons"][c]
                t1 = cmp_[f"<= {TARGET_BEST} x best-tuned"]
                t2 = cmp_[f"<= {TARGET_ADAM} x adam (where Adam wins)"]
                row += [
                    f"{cmp_['ratio_to_best_tuned']:.3g}",
                    f"{cmp_['ratio_to_adam']:.3g}",
                    "met" if t1 else "not met",
                    "—" if t2 is None else ("met" if t2 else "not met"),
                ]
            lines2.append("| " + " | ".join(row) + " |")
        text += "\n## Targets (issue #17)\n\n" + "\n".join(lines2) + "\n"
    else:
        text += (
            f"\n## Targets (issue #17)\n\n{'; '.join(targets)}: not measurable until "
            f'the library accepts sigma_d="auto" (or a --candidates method is given).\n'
        )
    refs = [
        "| scene | Adam wins | defaults / best-tuned | Adam / best-tuned | pyramid / best-tuned "
        "| defaults / Adam | s this run | s computing |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for name, e in scenes.items():
        m = e["methods"]
        b = m["best_tuned"]["error"]
        sec = e["seconds"]
        computing = sum(v for k, v in sec.items() if k != "total")
        refs.append(
            f"| {name} | {'yes' if e['adam_wins'] else 'no'} | {m['defaults']['error'] / b:.3g} "
            f"| {m['adam']['error'] / b:.3g} | {m['pyramid']['error'] / b:.3g} "
            f"| {m['defaults']['error'] / m['adam']['error']:.3g} "
            f"| {sec['total']:.0f} | {computing:.0f} |"
        )
    text += (
        "\n## Without tuning\n\n" + "\n".join(refs) + '\n\n"s computing": the seconds '
        "each family took when it was computed (cached grids keep theirs), with the "
        "scene's setup; run in parallel with other scenes.\n"
    )
    edges = [
        f"- {name}/{fam}: {_hp({**x['static'], **x['hyper']})}"
        for name, e in scenes.items()
        for fam, lst in e["lr_at_grid_edge"].items()
        for x in lst
        if fam != "bilateral"
    ]
    n_bil = sum(len(e["lr_at_grid_edge"].get("bilateral", [])) for e in scenes.values())
    text += (
        f"\nLearning rate still at a grid edge after {summary['settings']['max_extend']} "
        f"extensions: {n_bil} bilateral grid points"
        + (", and:\n" + "\n".join(edges) if edges else "")
        + "\n"
    )
    return text


def load_candidates(specs: Sequence[str]) -> dict[str, Callable]:
    """``[NAME=]module:attr`` entries -> ``{name: factory}`` (name defaults to ``attr``)."""
    out = {}
    for spec in specs:
        name, _, target = spec.rpartition("=")
        module, sep, attr = target.partition(":")
        if not sep or not module or not attr:
            raise ValueError(f"--candidates entries must be [NAME=]module:factory, got {spec!r}")
        factory = getattr(importlib.import_module(module), attr)
        if not callable(factory):
            raise TypeError(f"candidate {spec!r}: {module}.{attr} is not callable")
        name = name or attr
        if name in ("best_tuned", "auto", "defaults", "adam", "pyramid") or name in out:
            raise ValueError(f"candidate name {name!r} is taken; give it another with NAME=")
        out[name] = factory
    return out


#: Rough relative cost of the full scenes (longest first when run in parallel).
_COST_RANK = {
    "texture_low_noise": 6,
    "volume": 5,
    "deblur": 4,
    "deblur_x100": 4,
    "texture": 3,
    "texture_noise": 3,
    "signal1d": 1,
}


def _scene_job(args) -> dict:
    """One scene, end to end (a worker process's unit of work)."""
    name, quick, s, cache, candidates, recompute, with_auto, progress, xla_cache, reference = args
    _use_xla_cache(xla_cache)
    t0 = time.perf_counter()
    scene = sc.make(name, quick)
    jax.block_until_ready(scene.data)
    build = time.perf_counter() - t0
    entry = run_scene(
        scene,
        s,
        pathlib.Path(cache),
        candidates=candidates,
        recompute=recompute,
        with_auto=with_auto,
        progress=progress,
        reference=reference,
    )
    entry["seconds"]["scene_setup"] = build
    entry["seconds"]["total"] += build
    return entry


def _use_xla_cache(path: str | None) -> None:
    """JAX's persistent compilation cache in ``path`` (None: leave JAX's setting alone).

    Identical programs then compile once: across scenes of one shape (the three texture
    scenes share every update program), worker processes and later runs (candidates).
    """
    if path is None:
        return
    jax.config.update("jax_compilation_cache_dir", path)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.2)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)


def _as_done(futures, progress: bool):
    import concurrent.futures

    from tqdm.auto import tqdm

    bar = tqdm(total=len(futures), desc="scenes", unit="scene", disable=not progress)
    for f in concurrent.futures.as_completed(futures):
        bar.update(1)
        yield f.result()
    bar.close()


def run_benchmark(
    scene_names: Sequence[str] | None = None,
    *,
    quick: bool = False,
    out: str | pathlib.Path = "results/tuning",
    candidates: Mapping[str, Callable] | None = None,
    recompute: bool = False,
    progress: bool = True,
    jobs: int = 1,
    xla_cache: str | None = "default",
    reference: str | pathlib.Path | None = None,
    grid: str | None = None,
) -> dict:
    """Runs (or loads from ``out/cache``) every scene; writes ``summary.json``, ``table.md``,
    ``reference.json`` and one PNG per scene to ``out``; returns the summary.

    ``reference``: a run's ``reference.json``; its best-tuned, Adam and pyramid grids are
    used instead of running them (they must be of the same scenes and settings).
    ``grid``: ``"reduced"`` for :data:`REDUCED` instead of the full (or quick) grid.

    ``jobs > 1`` runs scenes in that many worker processes (candidates must then be
    importable module-level functions, as ``--candidates`` gives). ``xla_cache``: JAX's
    persistent compilation cache directory ("default": ``out/cache/xla``; None: off).
    """
    t0 = time.perf_counter()
    names = list(sc.SCENES) if not scene_names else list(scene_names)
    for n in names:
        if n not in sc.ALL:
            raise ValueError(f"unknown scene {n!r}; choose from {sorted(sc.ALL)}")
    out = pathlib.Path(out)
    out.mkdir(parents=True, exist_ok=True)
    s = settings(quick, grid)
    ref = None if reference is None else load_reference(reference, names, quick)
    with_auto = auto_available()
    cache = out / "cache"
    xla_cache = str(cache / "xla") if xla_cache == "default" else xla_cache
    if isinstance(jobs, bool) or not isinstance(jobs, int) or jobs < 1:
        raise ValueError(f"jobs must be a positive int, got {jobs!r}")
    _use_xla_cache(xla_cache)
    args = [
        (
            n,
            quick,
            s,
            str(cache),
            candidates,
            recompute,
            with_auto,
            progress,
            xla_cache,
            None if ref is None else ref["scenes"][n],
        )
        for n in names
    ]
    if jobs == 1:
        done = map(_scene_job, args)
    else:
        import concurrent.futures
        import multiprocessing

        # Scenes run in worker processes (one XLA client each); costly scenes first.
        order = sorted(args, key=lambda a: -_COST_RANK.get(a[0], 0))
        ctx = multiprocessing.get_context("spawn")
        pool = concurrent.futures.ProcessPoolExecutor(
            max_workers=min(jobs, len(names)),
            mp_context=ctx,
            initializer=_init_worker,
            initargs=(ctx.Value("i", 0),),
        )
        futures = [pool.submit(_scene_job, a) for a in order]
        done = _as_done(futures, progress)
    entries = {}
    for entry in done:
        entries[entry["scene"]] = entry
        if progress:
            b = entry["methods"]["best_tuned"]
            print(
                f"{entry['scene']}: best-tuned {b['error']:.4g} ({_hp(b['hyperparameters'])}), "
                f"Adam {entry['methods']['adam']['error']:.4g}, "
                f"{entry['seconds']['total']:.0f} s",
                flush=True,
            )
    if jobs > 1:
        pool.shutdown()
    entries = {n: entries[n] for n in names}
    write_reference(out / "reference.json", entries, quick, s)
    pngs = [str(plot_scene(e, out / f"{n}.png")) for n, e in entries.items()]
    summary = {
        "quick": quick,
        "auto_available": with_auto,
        "candidates": list(candidates or {}),
        "defaults": bilateral_defaults(),
        "settings": dataclasses.asdict(s),
        "reference": None if ref is None else ref["file"],
        "targets": {"best_tuned": TARGET_BEST, "adam": TARGET_ADAM},
        "scenes": entries,
        "pngs": pngs,
        "total_seconds": time.perf_counter() - t0,
    }
    (out / "summary.json").write_text(json.dumps(_jsonable(summary), indent=1) + "\n")
    table = markdown(summary)
    (out / "table.md").write_text(table)
    summary["table"] = table
    return summary


def main(argv=None) -> dict:
    def extra(parser):
        parser.add_argument(
            "--only-scenes",
            default="",
            help=f"comma-separated subset of {','.join(sc.SCENES)} (default: all), "
            f"of the held-out {','.join(sc.HELD_OUT)} or of the rendered "
            f"{','.join(sc.RENDERED)}",
        )
        parser.add_argument(
            "--candidates",
            default="",
            help="comma-separated [NAME=]module:factory candidate methods; "
            "factory(learning_rate) -> optax transform",
        )
        parser.add_argument(
            "--reference",
            default=None,
            help="a run's reference.json (e.g. experiments/tuning/reference.json): take the "
            "best-tuned, Adam and pyramid grids from it instead of running them",
        )
        parser.add_argument(
            "--grid",
            choices=("reduced",),
            default=None,
            help="'reduced': a smaller grid for costly scenes (tuning.REDUCED); "
            "default: the full grid (--quick: the quick one)",
        )
        parser.add_argument(
            "--recompute",
            action="store_true",
            help="rerun the grids even when out/cache holds them",
        )
        parser.add_argument(
            "--jobs",
            type=int,
            default=DEFAULT_JOBS,
            help=f"scenes run in this many worker processes (default "
            f"{DEFAULT_JOBS}: the CPU count, at most 2)",
        )
        parser.add_argument(
            "--xla-cache",
            default="default",
            help="JAX persistent compilation cache dir (default OUT/cache/xla; 'none' to disable)",
        )

    args = common.parse_args(
        "Tuning benchmark of issue #17: best-tuned grid, auto, defaults, "
        "Adam and the Laplacian pyramid on every scene.",
        default_out="results/tuning",
        argv=argv,
        extra=extra,
    )
    scene_names = [x for x in args.only_scenes.split(",") if x]
    candidates = load_candidates([x for x in args.candidates.split(",") if x])
    summary = run_benchmark(
        scene_names,
        quick=args.quick,
        out=args.out,
        candidates=candidates,
        recompute=args.recompute,
        jobs=args.jobs,
        xla_cache=None if args.xla_cache == "none" else args.xla_cache,
        reference=args.reference,
        grid=args.grid,
    )
    print(summary["table"])
    print(
        f"Total {summary['total_seconds']:.1f} s. Wrote {args.out}/summary.json, table.md, "
        "reference.json, "
        f"{len(summary['pngs'])} PNGs."
    )
    return summary


def _jsonable(obj):
    """Plain JSON values: numpy scalars and arrays converted, inf and NaN as strings."""
    if isinstance(obj, Mapping):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _jsonable(obj.tolist())
    if isinstance(obj, (bool, np.bool_)):
        return bool(obj)
    if isinstance(obj, (np.integer, int)):
        return int(obj)
    if isinstance(obj, (np.floating, float)):
        v = float(obj)
        return v if math.isfinite(v) else str(v)
    return obj
