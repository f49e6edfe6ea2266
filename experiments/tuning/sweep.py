"""Running a method on a scene: the batched runner (:class:`Runner`, :func:`evaluate`) and
the learning-rate sweep of a method's grid (:class:`Family`, :func:`tune`)."""

from __future__ import annotations

import dataclasses
import inspect
import math
import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import optax

from experiments.tuning.problem import Scene

SEEDS = (0, 1, 2)
#: Rounds of learning-rate grid extension at an edge (each adds one factor of 2).
MAX_EXTEND = 3
LR_RATIO = 2.0


# ----------------------------------------------------------------------------- running


_GRAD_PROGRAMS: dict = {}


def _grad_program(scene: Scene):
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
        scene: Scene,
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
    scene: Scene,
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


def init_worker(counter) -> None:
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
    scene: Scene,
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
        pending = [(k, rounded(lr * scale)) for k in range(len(points)) for lr in lrs0]
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
                    pending.append((k, rounded(lrs[0] / LR_RATIO)))
                elif best == lrs[-1]:
                    pending.append((k, rounded(lrs[-1] * LR_RATIO)))
        for by_lr in tried.values():
            records.extend(by_lr.values())
            lrs = sorted(by_lr)
            best = min(lrs, key=lambda lr: by_lr[lr].median)
            if len(lrs) > 1 and best in (lrs[0], lrs[-1]):
                at_edge.append({"static": dict(static), "hyper": by_lr[best].hyper})
    return Result(
        family=family.name, records=records, seconds=time.perf_counter() - t0, at_edge=at_edge
    )


def rounded(x: float) -> float:
    return float(f"{x:.4g}")


def _bind(factory, static: Mapping[str, Any], scene: Scene):
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


def jsonable(obj):
    """Plain JSON values: numpy scalars and arrays converted, inf and NaN as strings."""
    if isinstance(obj, Mapping):
        return {str(k): jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return jsonable(obj.tolist())
    if isinstance(obj, (bool, np.bool_)):
        return bool(obj)
    if isinstance(obj, (np.integer, int)):
        return int(obj)
    if isinstance(obj, (np.floating, float)):
        v = float(obj)
        return v if math.isfinite(v) else str(v)
    return obj
