"""``python -m experiments.paper.volume --quick`` end to end: outputs exist and say something
true."""

from __future__ import annotations

import json
import math

import pytest

from experiments.paper import volume as experiment


@pytest.fixture(scope="module")
def quick_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("volume")
    methods = experiment.main(["--quick", "--out", str(out)])
    return out, methods


def test_writes_every_output(quick_run):
    out, _ = quick_run
    for name in (
        "summary.json",
        "results.md",
        "timing.json",
        "timing.md",
        "views.png",
        "slices.png",
        "param_error_vs_iteration.png",
        "param_error_vs_time.png",
        "loss_vs_iteration.png",
        "loss_vs_time.png",
        "albedo_error_vs_iteration.png",
        "density_error_vs_time.png",
    ):
        path = out / name
        assert path.is_file() and path.stat().st_size > 0, name
    assert (out / "views.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_summary_has_every_method_with_finite_metrics(quick_run):
    out, _ = quick_run
    summary = json.loads((out / "summary.json").read_text())
    assert list(summary["methods"]) == list(experiment.METHODS)
    for name, entry in summary["methods"].items():
        for key in (
            "final_param_error",
            "final_loss",
            "seconds_per_iteration",
            "final_density_error",
            "final_albedo_error",
        ):
            assert math.isfinite(entry[key]) and entry[key] >= 0, (name, key, entry[key])
        assert entry["iterations"] == experiment.config(True)["iterations"]
    # Per-leaf sigma_d reached the summary as the pytree prefix the transforms were given.
    assert set(summary["methods"]["cross-bilateral"]["hyperparameters"]["sigma_d"]) == {
        "density",
        "albedo",
    }
    assert summary["methods"]["low-pass"]["hyperparameters"]["sigma_d"]["density"] == "inf"
    assert any(k.startswith("adam") for k in summary["sweeps"])
    assert any(k.startswith("bilateral") for k in summary["sweeps"])


def test_optimisation_makes_progress(quick_run):
    """Every method lowers the evaluation image loss below the constant initial volume's."""
    out, _ = quick_run
    summary = json.loads((out / "summary.json").read_text())
    initial = summary["initial"]["loss"]
    for name, entry in summary["methods"].items():
        assert entry["final_loss"] < initial, (name, entry["final_loss"], initial)


def test_timing_table_rows(quick_run):
    out, _ = quick_run
    timing = json.loads((out / "timing.json").read_text())
    names = [r["Method"] for r in timing["rows"]]
    assert names[0] == "Adam" and all(n.startswith("Ours (F = ") for n in names[1:])
    for row in timing["rows"]:
        assert row["ms per iteration"] > 0 and 0 <= row["update share %"] <= 100
    assert "| Method |" in (out / "timing.md").read_text()
