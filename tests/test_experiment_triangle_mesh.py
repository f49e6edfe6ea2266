"""End-to-end: ``python -m experiments.paper.triangle_mesh --quick`` and its ``--overhead`` mode."""

import json
import math

from experiments.paper import triangle_mesh as exp


def test_mesh_experiment_quick(tmp_path):
    summary = exp.main(["--quick", "--out", str(tmp_path)])
    on_disk = json.loads((tmp_path / "summary.json").read_text())
    assert on_disk == summary
    methods = summary["methods"]
    assert set(methods) == {"large-steps", "cross-bilateral"}
    start = summary["setting"]["initial_hausdorff"]
    for name, entry in methods.items():
        h = entry["hausdorff"]
        # Both optimizers must have moved the sphere towards the cube within the
        # quick budget (40 noisy iterations); 0.9 leaves room for the noise.
        assert math.isfinite(h) and h < 0.9 * start, (name, h, start)
        assert entry["hausdorff_curve"]["values"][-1] == h
    assert methods["cross-bilateral"]["hyperparameters"]["sigma_d"] == 0.5
    assert {e["method"] for e in summary["sweep"]} == {"large-steps", "cross-bilateral"}
    assert set(summary["extreme"]) == {"large-steps", "cross-bilateral"}
    assert summary["extreme"]["large-steps"]["hyperparameters"]["lambda"] == 999.0
    for png in ("grid.png", "extreme.png", "hausdorff_vs_iteration.png", "loss_vs_time.png"):
        assert (tmp_path / png).stat().st_size > 1000
    assert "| method | lambda | sigma_d | hausdorff |" in (tmp_path / "results.md").read_text()


def test_mesh_overhead_quick(tmp_path):
    result = exp.main(["--overhead", "--quick", "--out", str(tmp_path)])
    assert json.loads((tmp_path / "overhead.json").read_text())["setting"]["quick"] is True
    assert len(result["iteration"]) == 1  # --quick measures one small mesh
    for row in result["iteration"]:
        assert row["large_steps_ms"] > 0 and row["ours_ms"] > 0
        assert math.isclose(row["overhead_pct"], 100 * (row["ours_ms"] / row["large_steps_ms"] - 1))
        for k in ("large-steps", "large-steps-cholesky", "ours", "ours-warm", "ours-cholesky"):
            assert row[f"{k}_iteration_ms"] > row[f"{k}_update_ms"] > 0, k
    assert {r["rhs"] for r in result["solver"]} == {3, 128}
    assert all(r["cholmod_ms"] > 0 and r["cholmod_factor_ms"] > 0 for r in result["solver"])
    assert "Table 2" in (tmp_path / "overhead.md").read_text()
