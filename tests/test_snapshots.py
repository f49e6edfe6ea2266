"""The public API equals its snapshot (tests/snapshots.py), and the normalisation of the
opt-in HLO check (``python tests/snapshots.py --check``) drops names and locations only.

An intentional change re-records them (``python tests/snapshots.py``) in the same commit
and says why in its message.
"""

import difflib

import snapshots


def test_normalisation_drops_names_and_locations_only():
    a = (
        "module @jit_f attributes {x = 1} {\n  func.func public @main(%arg0: tensor<f32>) -> "
        '(tensor<f32> {jax.result_info = "result[0]"}) {\n    %0 = call @_where_3(%arg0) : '
        "(tensor<f32>) -> tensor<f32> loc(#loc1)\n    return %0 : tensor<f32>\n  }\n}\n"
        '#loc1 = loc("x")\n'
    )
    b = a.replace("@jit_f", "@jit_g").replace("_where_3", "_where").replace("result[0]", "out")
    assert snapshots.normalise_hlo(a) == snapshots.normalise_hlo(b)
    c = a.replace("tensor<f32>) -> tensor<f32> loc", "tensor<f32>) -> tensor<f64> loc")
    assert snapshots.normalise_hlo(a) != snapshots.normalise_hlo(c)


def test_public_api_is_unchanged():
    want = snapshots.API_PATH.read_text().splitlines()
    got = snapshots.api_lines()
    diff = "\n".join(difflib.unified_diff(want, got, "recorded", "now", lineterm=""))
    assert got == want, (
        f"the public API changed (re-record with python tests/snapshots.py):\n{diff}"
    )
