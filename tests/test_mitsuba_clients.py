"""Mitsuba users' own loops with this library: Mitsuba's tutorials as clients
(experiments/mitsuba/tutorials.py) and meshes against mi.ad.LargeSteps
(experiments/mitsuba/mesh.py). The one-line swap of docs/mitsuba.md runs verbatim in
tests/test_mitsuba.py, beside the docs' other blocks.

The experiments run in their quick form (tiny films and grids, a few iterations), so the
tests check what a quick run can show: every output is written, the swap changes nothing
where there is nothing to filter, the volume tutorial's upsampling restarts the key's
state, the mesh's Hausdorff metric measures what it says. Without a usable Mitsuba this
module is skipped with one line saying why, and fails under CI (tests/mitsuba_env.py).
"""

import json
import math
import pathlib

import numpy as np
import pytest

import docs_blocks
from mitsuba_env import fail_under_ci, require_mitsuba

MI = require_mitsuba()  # skips this module without a usable Mitsuba; None under CI
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


@pytest.fixture(scope="module", autouse=True)
def mi():
    return fail_under_ci(MI)


def _pngs(summary):
    for p in summary["pngs"]:
        assert pathlib.Path(p).read_bytes()[:8] == PNG_MAGIC


# ----------------------------------------------------------------------------- the tutorials


@pytest.fixture(scope="module")
def tutorials(mi, tmp_path_factory):
    from experiments.mitsuba import tutorials as E

    out = tmp_path_factory.mktemp("mitsuba_tutorials")
    E.main(["--quick", "--out", str(out)])
    return out


def test_every_tutorial_runs_with_both_optimizers_and_writes_its_outputs(tutorials):
    from experiments.mitsuba import tutorials as E

    for tutorial in E.TUTORIALS:
        data = json.loads((tutorials / tutorial / "summary.json").read_text())
        cfg = E.default_config(tutorial, quick=True)
        assert set(data["methods"]) == {"mi.ad.Adam", "BilateralAdam"}
        for name, m in data["methods"].items():
            for key in ("final_param_error", "final_loss", "seconds_per_iteration"):
                assert math.isfinite(m[key]) and m[key] > 0, (tutorial, name, key)
            stages = 2 if tutorial == "volume" else 1
            assert m["iterations"] == stages * cfg.iterations
        timing = {r["method"]: r for r in data["timing"]}
        assert timing["mi.ad.Adam"]["total vs mi.ad.Adam %"] == 0.0
        assert all(0 < r["update ms"] < r["total ms"] for r in timing.values())
        _pngs(data)
        table = (tutorials / tutorial / "table.md").read_text()
        assert "| BilateralAdam |" in table and "Time per iteration" in table
    assert "## volume" in (tutorials / "summary.md").read_text()


def test_the_swap_changes_nothing_on_the_red_walls_colour(tutorials):
    # gradient_based_opt optimizes a Color3f: BilateralAdam gives it Adam's rule, so both
    # optimizers end where the other does, up to Dr.Jit's and optax's rounding of Adam.
    data = json.loads((tutorials / "cbox" / "summary.json").read_text())
    errors = [m["final_param_error"] for m in data["methods"].values()]
    assert errors[0] == pytest.approx(errors[1], rel=1e-4)
    assert max(errors) < 0.9 * data["setting"]["initial_param_error"]


def test_the_volume_tutorials_upsampling_restarts_the_keys_state(mi):
    from experiments.mitsuba import tutorials as E

    cfg = E.default_config("volume", quick=True)
    problem = E.Volume(cfg)
    run = E.TutorialRun(problem, "BilateralAdam", 0.02)
    for i in range(cfg.iterations + 1):
        run.step(i)
    count = run.opt.state[problem.key][3].count
    # Five steps a stage-one iteration; the resample restarts the count, then five more.
    assert count == E.Volume.sensor_count
    assert run.values()[problem.key].shape == (cfg.grids[1],) * 3 + (1,)
    assert np.asarray(run.values()[problem.key]).min() >= 1e-6  # the tutorial's clip


# ----------------------------------------------------------------------------- meshes


def test_mesh_experiment_writes_the_table_2_analogue(mi, tmp_path):
    from experiments.mitsuba import mesh as E

    argv = ["--quick", "--out", str(tmp_path), "--directions", "8", "--kernel-tol", "0"]
    argv += ["--sigma-d", "2"]
    result = E.main(argv)
    cfg = E.default_config(quick=True)
    rows = json.loads((tmp_path / "summary.json").read_text())["rows"]
    assert [(r["target"], r["vertices"]) for r in rows] == [
        (t, 10 * f * f + 2) for t in cfg.targets for f in cfg.frequencies
    ]
    assert set(cfg.targets) == {"rounded_cube", "bumpy_box"}
    for r in rows:
        assert 0 < r["ours update share"] < 1 and 0 < r["Large Steps update share"] < 1
        assert (
            r["Large Steps ms/iter"] > 0 and r["ours ms/iter"] > 0 and r["ours / Large Steps"] > 0
        )
        for k in ("Large Steps Hausdorff", "ours Hausdorff", "bilateral, sigma_d 2 Hausdorff"):
            assert 0 < r[k] < 1.5 * r["initial Hausdorff"]
        others = ("8 directions", "kernel_tol 0", "sigma_d 2")
        best = min(r["ours Hausdorff"], *(r[f"bilateral, {v} Hausdorff"] for v in others))
        assert r["ours / best filter Hausdorff"] == pytest.approx(r["ours Hausdorff"] / best)
    for r in result["results"].values():
        _pngs(r)
        assert set(r["methods"]) == {
            *E.METHODS,
            "bilateral, 8 directions",
            "bilateral, kernel_tol 0",
            "bilateral, sigma_d 2",
        }
    assert "ours / Large Steps" in (tmp_path / "table.md").read_text()


def test_mesh_experiment_runs_each_seed_and_their_medians(mi, tmp_path):
    from experiments.mitsuba import mesh as E

    argv = ["--quick", "--out", str(tmp_path), "--targets", "rounded_cube", "--seeds", "0", "3"]
    result = E.main(argv)
    rows = json.loads((tmp_path / "summary.json").read_text())["rows"]
    assert [r["seed"] for r in rows] == [0, 3]
    for seed in (0, 3):
        assert (tmp_path / "rounded_cube" / "v92" / f"seed{seed}" / "summary.json").exists()
    # Other render noise, the same start: the seeds' runs end apart.
    assert rows[0]["ours Hausdorff"] != rows[1]["ours Hausdorff"]
    (median,) = result["medians"]
    assert median["seeds"] == 2
    for k in ("ours Hausdorff", "ours / Large Steps", "ours / Large Steps Hausdorff"):
        assert median[k] == pytest.approx(np.median([r[k] for r in rows]))
    assert "Medians over the seeds" in (tmp_path / "table.md").read_text()
    cfg = E.default_config(quick=True)
    with pytest.raises(ValueError, match="seeds must be distinct ints"):
        E.Problem(cfg, 3, seed=E.MAX_SEED + 1)
    for seeds in (["0", "0"], [str(E.MAX_SEED + 1)], ["-1"]):  # refused before any run
        with pytest.raises(ValueError, match="seeds must be distinct ints"):
            E.main(["--quick", "--out", str(tmp_path / "bad"), "--seeds", *seeds])
    assert not (tmp_path / "bad").exists() or not any((tmp_path / "bad").iterdir())


def test_hausdorff_distance_to_the_rounded_cube(mi):
    # The target mesh is on the surface (to its triangles' sag); a sphere of radius R around
    # the cube's centre is at least R - (its corner distance) away, measured exactly.
    from experiments.mitsuba import mesh as E
    from optax_bilateral.toy import triangle_mesh as toy

    cfg = E.default_config(quick=True)
    target = E.rounded_cube(16, cfg.half, cfg.radius)
    assert np.abs(E.rounded_cube_sdf(target[0], cfg.half, cfg.radius)).max() < 1e-6
    assert E.hausdorff(*target, target, cfg) < 0.05
    # Target -> mesh is the distance to the mesh's triangles, not to its samples: a finer mesh
    # on the same surface is within its triangles' sag (sampled, ~0.023 at 10242 vertices).
    fine, finer = E.rounded_cube(32, cfg.half, cfg.radius), E.rounded_cube(48, cfg.half, cfg.radius)
    assert E.hausdorff(*fine, finer, cfg) < 0.006
    # A square shifted off the target square by 0.01 along its normal is 0.01 away, both ways.
    square = (
        np.array([[-1.0, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]]),
        np.array([[0, 1, 2], [0, 2, 3]]),
    )
    lifted = square[0] + [0, 0, 0.01], square[1]
    assert E.hausdorff(*lifted, square, cfg, sdf=lambda p: p[:, 2]) == pytest.approx(
        0.01, abs=1e-12
    )
    sphere, faces = toy.icosphere(8, radius=2.0)
    corner = np.sqrt(3) * (cfg.half - cfg.radius) + cfg.radius
    assert E.hausdorff(sphere, faces, target, cfg) == pytest.approx(2.0 - cfg.half, abs=0.01)
    assert 2.0 - corner < E.hausdorff(sphere, faces, target, cfg)


def test_mesh_experiment_options_reach_the_runs(mi, monkeypatch, tmp_path):
    from experiments.mitsuba import mesh as E

    seen = []

    def fake(cfg, frequency, out, progress, target, seed):
        seen.append(
            (
                cfg.lambda_,
                cfg.iterations,
                frequency,
                target,
                cfg.directions,
                cfg.kernel_tols,
                cfg.sigma_ds,
                cfg.seeds,
                seed,
                out.name,
            )
        )
        raise StopIteration  # enough: the settings reached the first run

    monkeypatch.setattr(E, "run_vertex_count", fake)
    argv = ["--quick", "--out", str(tmp_path), "--frequencies", "5", "--lambda", "76"]
    with pytest.raises(StopIteration):
        E.main(
            [*argv, "--targets", "bumpy_box", "--iterations", "3", "--directions", "16", "8"]
            + ["--kernel-tol", "0", "0.1", "--sigma-d", "1", "inf", "--seeds", "4", "7"]
        )
    assert seen == [
        (76.0, 3, 5, "bumpy_box", (16, 8), (0.0, 0.1), (1.0, float("inf")), (4, 7), 4, "seed4")
    ]
    with pytest.raises(SystemExit):
        E.main(["--targets", "teapot"])


def test_bumpy_box_has_sharp_edges_bumps_and_a_distance(mi):
    # The second target: a bump rises out of each face's centre, an edge's midpoint is on the
    # (nearly) sharp box, and the signed distance is the distance along the normal nearby.
    from experiments.mitsuba import mesh as E

    cfg = E.default_config(quick=True)
    sdf = E.target_sdf("bumpy_box", cfg)
    h = cfg.half

    def radius(direction):
        d = np.asarray(direction, float) / np.linalg.norm(direction)
        r = np.linspace(0.1, 2.0, 200001)
        return r[np.argmax(sdf(r[:, None] * d) > 0)]

    for axis in ([1, 0, 0], [0, 0, -1]):
        assert h + 0.5 * cfg.bump < radius(axis) < h + cfg.bump
    assert np.sqrt(2) * h - 0.01 < radius([1, 1, 0]) <= np.sqrt(2) * h
    top = np.array([radius([1, 0, 0]), 0, 0])
    for d in (-0.02, 0.01, 0.03):
        np.testing.assert_allclose(sdf((top + [d, 0, 0])[None]), d, rtol=0.05)
    # The mesh's vertices are on the surface; its triangles cut the sharp edges, less so as
    # they shrink.
    gaps = []
    for frequency in (16, 48):
        vertices, faces = E.radial_surface(frequency, sdf)
        assert np.abs(sdf(vertices)).max() < 1e-6
        gaps.append(E.hausdorff(vertices, faces, (vertices, faces), cfg, sdf=sdf))
    assert gaps[1] < 0.5 * gaps[0] and gaps[1] < 0.025
    with pytest.raises(ValueError, match="target must be one of"):
        E.target_sdf("teapot", cfg)


def test_docs_mesh_block_runs_verbatim(mi, monkeypatch):
    # Its names mi and dr come from the docs' setup block, which runs in tests/test_mitsuba.py.
    from experiments.mitsuba import mesh as mitsuba_mesh

    block = docs_blocks.by("docs/mitsuba.md", "mesh").code
    quick = mitsuba_mesh.default_config(quick=True)
    monkeypatch.setattr(mitsuba_mesh, "default_config", lambda quick_=False: quick)
    ns = {"mi": mi, "dr": __import__("drjit")}
    exec(compile(block, "docs/mitsuba.md:mesh", "exec"), ns)
    opt, key, problem = ns["opt"], ns["key"], ns["problem"]
    moved = np.array(opt[key]).reshape(-1, 3)
    assert opt.state[key][3].count == quick.iterations
    assert 0 < np.abs(moved - problem.init).max() < 0.5  # a few steps of lr 0.03
    assert np.isfinite(problem.param_errors({key: moved})["hausdorff"])
