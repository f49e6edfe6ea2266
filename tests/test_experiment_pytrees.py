"""``python -m experiments.paper.pytrees --quick``: every problem and method gives a finite error at
each learning rate it tried, and the files are written."""

import json
import math

from experiments.paper import pytrees as E


def test_quick_run_writes_every_problem_and_method(tmp_path):
    data = E.main(["--quick", "--out", str(tmp_path)])
    problems = {"texture_mlp", "signal_1d", "volume_3d", "holography"}
    seen = {(r["problem"], r["method"]) for r in data["rows"]}
    for name in problems:
        assert {(name, m) for m in E.methods(name)} <= seen
    assert any(p.startswith("rosenbrock") for p, _ in seen)
    for row in data["rows"]:
        assert math.isfinite(row["error"]) and row["error"] >= 0, row
    for curve in data["curves"].values():
        assert all(math.isfinite(e) for e in curve.values())
    assert json.loads((tmp_path / "pytrees.json").read_text())["steps"] == data["steps"]
    assert (tmp_path / "pytrees.png").read_bytes()[:4] == b"\x89PNG"
