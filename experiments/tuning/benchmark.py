"""Every method on every scene: one scene's runs and summary, the whole benchmark
(:func:`run_benchmark`, scenes in worker processes) and its command line (:func:`main`)."""

from __future__ import annotations

import dataclasses
import importlib
import json
import os
import pathlib
import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import jax

import optax_bilateral as ob
from experiments import common
from experiments.tuning import scenes as sc
from experiments.tuning.methods import (
    Settings,
    auto_available,
    auto_factory,
    bilateral_defaults,
    families,
    levels_that_matter,
    settings,
)
from experiments.tuning.problem import Scene
from experiments.tuning.report import (
    TARGET_ADAM,
    TARGET_BEST,
    format_hyperparameters,
    markdown,
    plot_scene,
)
from experiments.tuning.store import (
    REFERENCE_FAMILIES,
    REFERENCE_PART,
    cached_tune,
    from_reference,
    load_reference,
    reference_part,
    scene_learning_rates,
    write_reference,
)
from experiments.tuning.sweep import Family, Record, Result, init_worker, jsonable, tune

#: Worker processes of the command line: one per core (each XLA client runs its small
#: programs on one thread; compilation, a large share of the quick run, is serial).
DEFAULT_JOBS = max(1, min(2, os.cpu_count() or 1))


# ----------------------------------------------------------------------------- one scene


def run_scene(
    scene: Scene,
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
            results[name], from_cache[name] = from_reference(reference, scene, fam, s), True
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
            learning_rates=scene_learning_rates(scene, s),
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
    entry[REFERENCE_PART] = reference_part(scene, s, grids, results, library)
    return entry


def _defaults_in_grid(scene: Scene, s: Settings, grid: Result) -> Result | None:
    """The defaults' runs, when the bilateral grid already holds them (the same optimizer,
    the same learning-rate search), else None."""
    d = bilateral_defaults()
    sigma, levels = d["sigma_d"], d["levels"]
    keep, same = levels_that_matter(scene, s.levels_grid)
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
            str(k): v for k, v in levels_that_matter(scene, s.levels_grid)[1].items()
        },
        "grid": {
            k: [r.to_json() for r in results[k].records]
            for k in ("bilateral", "adam", "pyramid", "defaults")
        },
        "lr_at_grid_edge": {k: r.at_edge for k, r in results.items() if r.at_edge},
    }


# ----------------------------------------------------------------------------- command line


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
            initializer=init_worker,
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
                f"{entry['scene']}: best-tuned {b['error']:.4g} "
                f"({format_hyperparameters(b['hyperparameters'])}), "
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
    (out / "summary.json").write_text(json.dumps(jsonable(summary), indent=1) + "\n")
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
