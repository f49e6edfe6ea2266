"""Grids kept between runs: the cache of ``--out`` (``OUT/cache/<scene>/<family>.json``) and
reference files (``reference.json``, ``--reference``), both keyed by what a grid depends on."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import pathlib
from collections.abc import Mapping, Sequence
from typing import Any

import optax_bilateral as ob
from experiments.tuning.methods import Settings
from experiments.tuning.problem import Scene
from experiments.tuning.sweep import Family, Record, Result, jsonable, tune

#: Bumped when a change makes cached grids stale.
CACHE_VERSION = 1


# ----------------------------------------------------------------------------- caching


def cache_key(scene: Scene, family: Family, s: Settings, *, library: bool = True) -> str:
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
    return hashlib.sha256(json.dumps(jsonable(spec), sort_keys=True).encode()).hexdigest()[:16]


def cached_tune(
    scene: Scene,
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
    key = cache_key(scene, family, s)
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
        learning_rates=scene_learning_rates(scene, s),
        progress=progress,
        mode=mode,
    )
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(
            json.dumps(
                jsonable(
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


def scene_learning_rates(scene: Scene, s: Settings) -> tuple[float, ...]:
    lrs = tuple(scene.learning_rates)
    if s.lr_points is not None and s.lr_points < len(lrs):
        mid = (len(lrs) - s.lr_points) // 2
        lrs = lrs[mid : mid + s.lr_points]
    return lrs


# ----------------------------------------------------------------------------- references

#: The families a reference holds: what a candidate is compared with, and what takes long.
REFERENCE_FAMILIES = ("bilateral", "adam", "pyramid")
REFERENCE_FORMAT = 1
#: The key under which a scene's entry carries its reference part until it is written.
REFERENCE_PART = "reference_part"


def reference_part(
    scene: Scene, s: Settings, grids: Mapping[str, Family], results, library: str
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
            "key": cache_key(scene, grids[name], s, library=False),
            "seconds": result.seconds,
            "at_edge": result.at_edge,
            "records": records,
        }
    return part


def _setting(r: Record) -> str:
    """A record's setting: everything but the learning rate."""
    hyper = {k: v for k, v in r.hyper.items() if k != "learning_rate"}
    return json.dumps(jsonable([r.static, hyper]), sort_keys=True)


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


def from_reference(part: Mapping[str, Any], scene: Scene, family: Family, s: Settings):
    stored = part["families"].get(family.name)
    if stored is None or stored["key"] != cache_key(scene, family, s, library=False):
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
    scenes = {n: e.pop(REFERENCE_PART) for n, e in entries.items()}
    data = {
        "format": REFERENCE_FORMAT,
        "quick": quick,
        "settings": dataclasses.asdict(s),
        "scenes": scenes,
    }
    path.write_text(json.dumps(jsonable(data), sort_keys=True) + "\n")
