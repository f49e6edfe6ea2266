"""End to end: ``python -m experiments.tuning --quick`` writes a valid summary, table and figures,
reuses its grid cache, and compares a plugged-in candidate."""

import functools
import json
import math
import pathlib
import shutil

import numpy as np
import pytest

import docs_blocks
import optax_bilateral as ob
from experiments import tuning as T
from experiments.tuning import scenes as sc
from experiments.tuning import store

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
METHODS = ("best_tuned", "auto", "defaults", "adam", "pyramid")


@pytest.fixture(scope="module")
def quick_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("tuning")
    summary = T.main(["--quick", "--out", str(out)])
    # Later tests rerun single scenes into ``out``, which rewrites its reference.json.
    shutil.copy(out / "reference.json", out / "reference_all.json")
    return out, summary


def test_summary_has_every_scene_and_method_with_sane_numbers(quick_run):
    out, _ = quick_run
    data = json.loads((out / "summary.json").read_text())
    assert set(data["scenes"]) == set(sc.SCENES)
    for name, e in data["scenes"].items():
        assert set(METHODS) <= set(e["methods"]), name
        init = e["initial_error"]
        assert math.isfinite(init) and init > 0
        for m in METHODS:
            err = e["methods"][m]["error"]
            if m == "auto" and not data["auto_available"]:
                assert err is None and "not available" in e["methods"][m]["note"]
                continue
            assert isinstance(err, float) and math.isfinite(err) and err >= 0, (name, m)
            assert "learning_rate" in e["methods"][m]["hyperparameters"], (name, m)
        # Optimisation helps: tuned Adam ends below the starting error on every scene.
        assert e["methods"]["adam"]["error"] < init, name
        # The best-tuned entry is the grid's best median.
        medians = [r["median"] for r in e["grid"]["bilateral"]]
        assert e["methods"]["best_tuned"]["error"] == min(medians), name


def test_scaled_scene_is_the_same_problem(quick_run):
    """deblur_x100 is deblur with every parameter (and the grids of lr, linear sigma_d) x100:
    Adam and the best-tuned filter give the same errors (in deblur's units), up to float32
    rounding and Adam's eps (1e-8 against sqrt(v) ~ 1e-3 here: relative 1e-5)."""
    out, _ = quick_run
    s = json.loads((out / "summary.json").read_text())["scenes"]
    for m in ("adam", "best_tuned", "pyramid"):
        a, b = s["deblur"]["methods"][m]["error"], s["deblur_x100"]["methods"][m]["error"]
        assert b == pytest.approx(a, rel=2e-3), m


def test_table_and_figures(quick_run):
    out, summary = quick_run
    table = (out / "table.md").read_text()
    for name in sc.SCENES:
        assert f"| {name} |" in table
    if not summary["auto_available"]:
        assert "not available" in table
    for name in sc.SCENES:
        assert (out / f"{name}.png").read_bytes()[:8] == PNG_MAGIC


def test_candidate_is_compared_and_grid_comes_from_the_cache(quick_run):
    """A candidate equal to the defaults gets the defaults' error; the grids are not rerun."""
    out, _ = quick_run
    summary = T.main(
        [
            "--quick",
            "--out",
            str(out),
            "--only-scenes",
            "signal1d",
            "--candidates",
            "same=experiments.tuning:defaults_factory",
        ]
    )
    e = summary["scenes"]["signal1d"]
    assert all(e["from_cache"][k] for k in ("bilateral", "adam", "pyramid"))
    assert e["methods"]["same"]["error"] == pytest.approx(
        e["methods"]["defaults"]["error"], rel=1e-5
    )
    cmp_ = e["comparisons"]["same"]
    assert cmp_["ratio_to_best_tuned"] == pytest.approx(
        e["methods"]["same"]["error"] / e["methods"]["best_tuned"]["error"]
    )
    assert "same/best-tuned" in (out / "table.md").read_text()


def test_reference_replaces_the_grids(quick_run, tmp_path):
    """With --reference the grids are read, not run: the reference methods' errors are the
    reference run's, no grid is cached, the table names the file, and the new run's
    reference.json carries the same grids on."""
    out, first = quick_run
    ref = out / "reference_all.json"
    summary = T.main(
        [
            "--quick",
            "--out",
            str(tmp_path),
            "--only-scenes",
            "signal1d",
            "--reference",
            str(ref),
            "--candidates",
            "same=experiments.tuning:defaults_factory",
        ]
    )
    e, e0 = summary["scenes"]["signal1d"], first["scenes"]["signal1d"]
    assert e["from_reference"] == list(T.REFERENCE_FAMILIES)
    for m in ("best_tuned", "adam", "pyramid"):
        assert e["methods"][m]["error"] == e0["methods"][m]["error"], m
        assert e["methods"][m]["hyperparameters"] == e0["methods"][m]["hyperparameters"], m
    assert not (tmp_path / "cache" / "signal1d" / "bilateral.json").exists()
    assert e["methods"]["same"]["error"] == pytest.approx(
        e["methods"]["defaults"]["error"], rel=1e-5
    )
    assert f"from `{ref}`" in (tmp_path / "table.md").read_text()
    again = json.loads((tmp_path / "reference.json").read_text())["scenes"]["signal1d"]
    assert again == json.loads(ref.read_text())["scenes"]["signal1d"]
    # Every setting of the grid keeps its best learning rate: the sensitivity curves survive.
    assert T.sensitivity(e, False) == T.sensitivity(e0, False)


def test_reference_that_does_not_match_is_refused(quick_run, tmp_path):
    out, _ = quick_run
    ref = json.loads((out / "reference_all.json").read_text())

    def write(data) -> pathlib.Path:
        path = tmp_path / "ref.json"
        path.write_text(json.dumps(data))
        return path

    def run(path, names=("signal1d",), quick=True):
        T.run_benchmark(list(names), quick=quick, out=tmp_path / "out", reference=path)

    with pytest.raises(ValueError, match="holds a --quick run and this is a full run"):
        run(write(ref), quick=False)
    with pytest.raises(ValueError, match="has no scene nope_scene"):
        T.load_reference(write(ref), ["signal1d", "nope_scene"], quick=True)
    with pytest.raises(ValueError, match=r"expected a tuning run's reference\.json"):
        run(write({"scenes": {}}))
    with pytest.raises(ValueError, match="not a readable JSON file"):
        run(tmp_path / "missing.json")
    stale = json.loads(json.dumps(ref))
    stale["scenes"]["signal1d"]["families"]["adam"]["key"] = "0" * 16
    with pytest.raises(ValueError, match="adam grid on signal1d was run with another scene"):
        run(write(stale))


def test_committed_reference_matches_the_scenes():
    """experiments/tuning/reference.json was run on today's scenes and settings: a change to
    a scene or a grid makes it stale, and this fails until it is regenerated."""
    path = pathlib.Path(__file__).parents[1] / "experiments" / "tuning" / "reference.json"
    names = [*sc.SCENES, *sc.HELD_OUT]
    ref = T.load_reference(path, names, quick=False)
    s = T.settings(False)
    for name in names:
        scene = sc.make(name)
        grids = T.families(scene, s)
        for fam in T.REFERENCE_FAMILIES:
            stored = ref["scenes"][name]["families"][fam]
            key = store.cache_key(scene, grids[fam], s, library=False)
            assert stored["key"] == key, (name, fam)
            assert stored["records"], (name, fam)


@pytest.mark.parametrize("name, fraction", [("texture_mixed50", 0.5), ("texture_mixed75", 0.75)])
def test_mixed_target_is_camera_left_and_noise_right(name, fraction):
    """The held-out mixed scenes: the camera target's left columns, the noise target's right
    ones; the suite's texture scenes keep their configuration (and so their grids' keys)."""
    mixed, camera, noise = (sc.make(n, quick=True) for n in (name, "texture", "texture_noise"))
    size = mixed.init.shape[1]
    k = size - round(size * fraction)
    t, c, n = (np.asarray(x.data["target"]) for x in (mixed, camera, noise))
    np.testing.assert_array_equal(t[:, :k], c[:, :k])
    np.testing.assert_array_equal(t[:, k:], n[:, k:])
    assert mixed.config["noise_fraction"] == fraction
    assert "noise_fraction" not in camera.config and "noise_fraction" not in noise.config


def test_evaluate_shapes_and_rejects_bad_grids():
    scene = sc.make("signal1d", quick=True)
    errs = T.evaluate(
        scene, T.adam_factory, {"learning_rate": [0.01, 0.02], "b1": [0.9]}, seeds=(0, 1)
    )
    assert errs.shape == (2, 2) and np.all(np.isfinite(errs))
    # Seeds change the noise: two seeds of one setting differ.
    assert errs[0, 0] != errs[0, 1]
    with pytest.raises(TypeError, match="must be numbers"):
        T.evaluate(scene, T.adam_factory, [{"learning_rate": 0.01, "b1": "x"}], seeds=(0,))
    with pytest.raises(ValueError, match="same keys"):
        T.evaluate(
            scene,
            T.adam_factory,
            [{"learning_rate": 0.01, "b1": 0.9}, {"learning_rate": 0.01}],
            seeds=(0,),
        )


def test_bad_cli_arguments():
    with pytest.raises(ValueError, match="unknown scene"):
        T.run_benchmark(["nope"], quick=True, out="/tmp/unused-tuning")
    with pytest.raises(ValueError, match=r"\[NAME=\]module:factory"):
        T.load_candidates(["no_colon"])
    with pytest.raises(ValueError, match="taken"):
        T.load_candidates(["adam=experiments.tuning:adam_factory"])


@pytest.mark.parametrize("name", ["api", "cost"])
def test_docs_blocks_run_on_the_quick_scenes(name, quick_run, monkeypatch, tmp_path, capsys):
    """docs/tuning.md's "From Python" and "Cost" blocks, verbatim, on the quick scenes; the
    benchmark reads the quick run's grids (--reference) and writes into a temporary folder."""
    out, _ = quick_run
    make = sc.make
    monkeypatch.setattr(sc, "make", lambda scene, quick=False: make(scene, True))
    monkeypatch.setattr(
        T,
        "run_benchmark",
        functools.partial(
            T.run_benchmark, quick=True, reference=out / "reference_all.json", out=tmp_path
        ),
    )
    factory = lambda learning_rate: ob.bilateral_adam(learning_rate, levels=3)
    ns = {"ob": ob, "factory": factory}
    exec(compile(docs_blocks.by("docs/tuning.md", name).code, f"docs/tuning.md:{name}", "exec"), ns)
    if name == "api":
        assert ns["errors"].shape == (4, 3) and np.isfinite(ns["errors"]).all()
        assert ns["result"].family == "mine"
        e = ns["summary"]["scenes"]["deblur"]
        assert math.isfinite(e["methods"]["mine"]["error"])
    else:
        lines = capsys.readouterr().out.strip().splitlines()
        assert [line.split()[0] for line in lines] == ["texture", "deblur", "signal1d"]
