"""End to end: ``python -m experiments.paper.texture --quick`` writes a valid summary and figures;
the demo (``make demo``) and ``--full`` settings run the methods they name."""

import inspect
import json
import math

import pytest

import optax_bilateral as ob
from experiments.paper import texture as E

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


@pytest.fixture(scope="module")
def quick_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("texture")
    summary = E.main(["--quick", "--out", str(out)])
    return out, summary, E.default_config(quick=True)


def test_summary_json_has_every_method_with_finite_numbers(quick_run):
    out, _, cfg = quick_run
    data = json.loads((out / "summary.json").read_text())
    assert set(data["methods"]) == set(E.METHODS)
    for name, m in data["methods"].items():
        for key in ("final_param_error", "final_loss", "seconds_per_iteration"):
            assert isinstance(m[key], float) and math.isfinite(m[key]) and m[key] >= 0, (name, key)
        assert m["seconds_per_iteration"] > 0
        assert m["iterations"] == cfg.iterations
        assert isinstance(m["hyperparameters"], dict) and "learning_rate" in m["hyperparameters"]
        # Every sweep entry is reported, and the reported one is the sweep's best.
        assert len(m["sweep"]) == len(cfg.sweeps[name])
        assert m["final_param_error"] == min(s["final_param_error"] for s in m["sweep"])


def test_methods_are_configured_as_the_paper(quick_run):
    out, _, _ = quick_run
    methods = json.loads((out / "summary.json").read_text())["methods"]
    for name in ("low-pass", "bilateral", "cross-bilateral"):
        hp = methods[name]["hyperparameters"]
        assert hp["b1"] == 0.2 and abs(hp["b2"] - 0.36) < 1e-12, name
    assert methods["low-pass"]["hyperparameters"]["sigma_d"] == "inf"
    assert methods["bilateral"]["hyperparameters"]["guide"] == "self"
    assert methods["cross-bilateral"]["hyperparameters"]["guide"] == "params"
    assert methods["cross-bilateral"]["hyperparameters"]["log_guide"] is True
    # The defaults run sets nothing but the learning rate and the layout, and reports the
    # library's own defaults (sigma_d="auto" among them).
    hp = methods["defaults"]["hyperparameters"]
    defaults = inspect.signature(ob.bilateral_adam).parameters
    assert hp["sigma_d"] == defaults["sigma_d"].default == "auto"
    assert hp["spatial_axes"] == [0, 1]
    for sweep in E.default_config(quick=True).sweeps["defaults"]:
        assert set(sweep) == {"learning_rate"}


def test_demo_shows_adam_the_defaults_and_the_tuned_filter():
    demo = E.demo_config()
    assert demo.methods == ("adam", "defaults", "cross-bilateral")
    assert all(set(s) == {"learning_rate"} for s in demo.sweeps["defaults"])
    assert len(demo.sweeps["adam"]) >= 3  # Adam at its best learning rate of a sweep
    full = E.default_config()
    assert full.methods == E.METHODS and full.size == 512 and full.iterations == 150


def test_cross_bilateral_recovers_the_texture_better_than_adam(quick_run):
    # In the quick setting (64^2, 1 spp, 30 iterations) the paper's method reduces the texel
    # error well below the initial one and below Adam's best sweep entry. Measured when this
    # test was written: cross-bilateral 0.020, Adam 0.067, initial 0.081, and the same
    # optimizer with the filter switched off (levels=0: Adam with b1 = 0.2) 0.049. The bounds
    # (half the initial error; 0.6x Adam's) leave room for numeric drift across XLA versions
    # yet fail if the filter stops doing its work (0.049 breaks both). The defaults
    # (sigma_d="auto", learning rate 0.02) measured 0.020.
    out, _, _ = quick_run
    data = json.loads((out / "summary.json").read_text())
    err = {m: data["methods"][m]["final_param_error"] for m in E.METHODS}
    initial = data["setting"]["initial_param_error"]
    assert err["cross-bilateral"] < 0.5 * initial, (err, initial)
    assert err["cross-bilateral"] < 0.6 * err["adam"], err
    assert err["defaults"] < 0.6 * err["adam"], err


def test_equal_wall_time_block_is_consistent(quick_run):
    out, _, _ = quick_run
    eq = json.loads((out / "summary.json").read_text())["equal_wall_time"]
    assert eq["budget_seconds"] > 0
    assert set(eq["methods"]) == set(E.METHODS)
    for name, e in eq["methods"].items():
        assert math.isfinite(e["param_error"]) and e["iterations"] >= 1, name


def test_figures_and_table_are_written(quick_run):
    out, summary, _ = quick_run
    for name in (
        "images.png",
        "loss_vs_iteration.png",
        "loss_vs_time.png",
        "param_error_vs_iteration.png",
        "param_error_vs_time.png",
    ):
        path = out / name
        assert path.read_bytes()[:8] == PNG_MAGIC, name
        assert str(path) in summary["pngs"]
    table = (out / "table.md").read_text()
    for m in E.METHODS:
        assert f"| {m} |" in table
